"""Stage 5d — the driver's common case in two compiled calls.

:func:`torchpvs.solve` with default options runs, per call: the rotation predictor, Newton at
the warm start's basis order, the order check (one Newton step of the next order and the tip
change it makes), the Magnus step-count check (the tip with half the steps), and the actuation
forces with their one-sided values at kinks (:mod:`torchpvs.order_control`,
:mod:`torchpvs.forces`). Each stage is compiled per element, but between them the driver
builds tensors, layouts and masks in torch: at a batch of one that glue, not arithmetic, was
nearly all of a solve's time (docs/performance.md).

Here the same stages run in two compiled calls: the tracker's fused call
(:func:`torchpvs.tracker.solve_core`: the layout at the solve's order, the predictor,
Newton, the tip pose, the stability verdict, the forces and their kink sides), then
:func:`_order_check` (the layout at the next order, the order step, the poses of both orders
and the half-step pose). The driver takes the result only where every element converged and
every check passed at the first order tried, which is where its own loop would stop after one
round; anywhere else (a higher order needed, more Magnus steps, an element not converged) it
returns ``None`` and the driver solves as before, from the same start, so the results of a
call never depend on which path ran. What the fused path returns is the driver's
:class:`~torchpvs.order_control.SolveState` and outputs, computed by the same compiled
element functions from the same inputs (``tests/test_fused.py`` compares the two paths).

Where it applies: batches of up to :data:`MAX_BATCH` (above, the rounds' batched stages and the
layouts they keep between calls are faster), CPU float64 tensors without gradient, numba
importable, no tip load or load coordinates, ``kernel="compiled"``, the energy-consistent
forces, a warm start (if any) of the solve's own basis order; with a fixed ``order`` or
``n_magnus`` the corresponding check is skipped exactly as the driver skips it.
"""

from __future__ import annotations

import functools
import math
from dataclasses import replace
from typing import NamedTuple

import numpy as np
import torch

from . import compiled
from .basis import gauss_legendre
from .compiled import pose_one, step_one
from .compiled_layout import layout_and_maps_of, layout_maps_arrays
from .compiled_load import cached_jit
from .equilibrium import Equilibrium
from .forces import KINK_DELTA, KINK_TOL, kink_mask
from .kernel import COMPILED, VANISHING
from .newton import stability_threshold, tolerance
from .options import SolverOptions
from .order_control import SolveState, newton_tol
from .plan import MAGNUS_START, ORDER_START, Plan
from .predictor import PREDICTOR_TRUST, initial_q
from .scene import Scene
from .sections import Discretization, TubeTensors, n_coordinates
from .tracker import kink_mask_arrays, kink_sides, layout_and_track, solve_core

__all__ = ["MAX_BATCH", "FusedSolve", "control_blocks", "fused_solve"]


class FusedSolve(NamedTuple):
    """What :func:`fused_solve` hands back to the driver: the solve (``res``, its ``tip``,
    ``R``, ``error_estimate`` and ``magnus_estimate`` filled in as the driver's checks fill
    them) and the outputs :meth:`Equilibrium.from_solution` would otherwise compute:
    ``forces`` ``(retraction side, torques, insertion side, kink mask)`` ``(B, N)`` or
    ``None`` (``compute_forces=False``), ``rel`` ``(B, N-1)`` [rad], the relative rotations
    at the outer tube's end, ``stable`` ``(B,)`` the stability verdicts and ``dofs`` ``(B,)``
    the active coordinate counts."""

    res: SolveState
    forces: tuple[torch.Tensor, ...] | None
    rel: torch.Tensor
    stable: torch.Tensor
    dofs: torch.Tensor


@cached_jit(nogil=True)
def _order_check(q, EI, GJ, L, Ls, coef, D, A, unloaded, xg, wg, xq, wq, xm, phi_q, n, Qb,
                 phi_m, Q_m, xm_h, phi_mh, Q_mh, small, tiny, order_step, coarse, tip, R, est,
                 est_m):
    """Per element, on the layout at ``(D, A)`` of the basis the arrays describe (``n``
    functions; ``q (B, nq)`` padded to it): with ``order_step``
    (:func:`torchpvs.order_control.order_estimate`) the tip pose of ``q`` into ``tip``, ``R``,
    one undamped Newton step from ``q`` and the tip change it makes into ``est`` (inf where
    the step fails or a tip is not finite); with ``coarse``
    (:func:`torchpvs.order_control.refine_magnus`'s checks) the tip change of ``q`` with the
    Magnus nodes ``xm_h`` (half the steps, or twice as many) against ``tip`` into ``est_m``
    (``tip`` is then read, not written, where ``order_step`` is False)."""
    lay = layout_maps_arrays(EI, GJ, L, Ls, coef, D, A, unloaded, 1e-12, xg, wg, xq, wq, xm,
                             phi_q, n)
    (_ell, _tau, _start, h, _present, _curved, _active, _presc, qmask, psi0, gconst, _W,
     tip_tube, _s_tip, _bl, _sec, psec, cidx, ustar, EIw, EIws, GJw, Hsec, guide, bvec,
     qmask_c, h_c, _pinc_s, p_h, p_inc, p_held, p_local) = lay
    B, nq = q.shape
    N = D.shape[1]
    S = h.shape[1]
    nc = cidx.shape[1]
    dt = q.dtype
    psi_tip = np.empty(N, dtype=dt)
    tip1 = np.empty(3, dtype=dt)
    R1 = np.empty((3, 3), dtype=dt)
    q1 = np.empty(nq, dtype=dt)
    qc = np.empty(nc, dtype=dt)
    if order_step:
        for b in range(B):
            pose_one(q[b], qmask[b], psi0[b], D[b], tip_tube[b], psec[b], p_h[b], p_inc[b],
                     p_held[b], p_local[b], phi_m, Q_m, S, small, tip[b], R[b], psi_tip)
            for i in range(nc):
                qc[i] = q[b, cidx[b, i]] * qmask[b, cidx[b, i]]
            ok = step_one(qc, qmask_c[b], psi0[b], bvec[b], h_c[b], ustar[b], EIw[b],
                          EIws[b], GJw[b], Hsec[b], guide[b], gconst[b], phi_q, Qb, None, tiny)
            if not ok:
                est[b] = np.inf
                continue
            for i in range(nq):
                q1[i] = q[b, i]
            for i in range(nc):
                q1[cidx[b, i]] = qc[i]
            pose_one(q1, qmask[b], psi0[b], D[b], tip_tube[b], psec[b], p_h[b], p_inc[b],
                     p_held[b], p_local[b], phi_m, Q_m, S, small, tip1, R1, psi_tip)
            d = 0.0
            for k in range(3):
                d += (tip1[k] - tip[b, k]) ** 2
            est[b] = math.sqrt(d) if math.isfinite(d) else np.inf
    if coarse:
        lh = layout_maps_arrays(EI, GJ, L, Ls, coef, D, A, unloaded, 1e-12, xg, wg, xq, wq,
                                xm_h, phi_q, n)
        psec_h, ph_h, pinc_h, pheld_h, ploc_h = lh[16], lh[28], lh[29], lh[30], lh[31]
        for b in range(B):
            pose_one(q[b], qmask[b], psi0[b], D[b], tip_tube[b], psec_h[b], ph_h[b],
                     pinc_h[b], pheld_h[b], ploc_h[b], phi_mh, Q_mh, S, small, tip1, R1,
                     psi_tip)
            d = 0.0
            for k in range(3):
                d += (tip1[k] - tip[b, k]) ** 2
            est_m[b] = math.sqrt(d)


class _Tables(NamedTuple):
    layout: tuple            # (xg, wg, xq, wq, xm, phi_q) of the layout call
    phi: np.ndarray          # (Q, n) basis at the quadrature nodes
    Qb: np.ndarray
    phi_m: np.ndarray        # basis at the Magnus nodes
    Q_m: np.ndarray
    xm_h: np.ndarray         # Magnus nodes of half the steps, and the basis there
    phi_mh: np.ndarray
    Q_mh: np.ndarray


@functools.lru_cache(maxsize=64)
def _tables(disc: Discretization, P: int) -> _Tables:
    """The numpy tables of ``disc`` (float64, CPU) for precurvature polynomials of ``P``
    coefficients; the half-step ones are empty for an odd step count."""
    dt, cpu = torch.float64, torch.device("cpu")
    tab = disc.tables(dt, cpu)
    xg, wg = gauss_legendre(max(2, P + 1), dtype=dt)
    m = disc.n_magnus
    if m % 2 == 0:
        th = replace(disc, n_magnus=m // 2).tables(dt, cpu)
        half = (th.xm, th.phi_m, th.Q_m)
    else:
        half = (tab.xm[:0], tab.phi_m[:0], tab.Q_m[:0])

    def c(t):
        return np.ascontiguousarray(t.numpy())

    return _Tables(tuple(c(t) for t in (xg, wg, tab.xq, tab.wq, tab.xm, tab.phi_q)),
                   c(tab.phi_q), c(tab.Q_q), c(tab.phi_m), c(tab.Q_m), *(c(t) for t in half))


@functools.lru_cache(maxsize=64)
def _discretization(opts: SolverOptions, order: int, n_magnus: int) -> Discretization:
    return replace(opts.discretization(order), n_magnus=n_magnus)


#: The largest batch the fused path takes. It rebuilds every layout it needs in compiled code
#: on each call (the order check's, the half-step pose's, each kink side's), where the rounds
#: keep them between calls at the same insertions (torchpvs.plan) and batch each stage over
#: the rows. Measured on the Fig. 3 robot at its kink, warm 1 deg steps, one thread
#: (docs/performance.md): fused / rounds per solve 0.30x at B = 1, 0.41x at 4, 0.63x at 16,
#: 0.94x at 64, 1.17x at 256.
MAX_BATCH = 32


def _applies(D, F, M, opts: SolverOptions) -> bool:
    B = D.shape[0]
    return (B <= MAX_BATCH and compiled.available() and opts.kernel == "compiled"
            and D.device.type == "cpu"
            and D.dtype == torch.float64 and not opts.load_coordinates
            and (not opts.compute_forces or opts.force_model == "energy")
            and opts.max_total_iter > opts.max_iter
            # the fused calls do not look at the clock: only where even max_iter iterations
            # of every element (~0.1 ms each) fit well inside the time limit
            and (opts.time_limit is None or B * opts.max_iter * 1e-4 < 0.5 * opts.time_limit)
            and not (F.numpy().any() or M.numpy().any()))


def _tube_arrays(tubes: TubeTensors, B: int) -> tuple[np.ndarray, ...]:
    """``(EI, GJ, L, Ls, coef)`` as C-contiguous float64 arrays of ``B`` rows, writable copies:
    numba compiles a readonly array (a broadcast view, which ``np.ascontiguousarray`` returns
    as it is at ``B = 1``) as another type, i.e. every kernel a second time."""
    return tuple(np.array(np.broadcast_to(x.detach().numpy(), (B,) + x.shape[1:]), order="C")
                 for x in (tubes.EI, tubes.GJ, tubes.length, tubes.straight, tubes.coef))


def _constants(scene: Scene, tubes: TubeTensors, opts: SolverOptions):
    """``(length, consts)``: the longest tube [m] and the Newton constants of the compiled
    calls ``(tolerance, saddle threshold, eps, tiny)`` (float64)."""
    dt = torch.float64
    eps = float(torch.finfo(dt).eps)
    consts = np.array([tolerance(newton_tol(scene, opts), dt), 0.01 * eps ** 0.5, eps,
                       float(torch.finfo(dt).tiny)])
    return float(tubes.length.max()), consts


def _kinks(tubes: TubeTensors, D: np.ndarray, plan: Plan | None) -> tuple:
    """The kink analysis of :func:`torchpvs.forces.kink_plan` at insertions ``D (B, N)`` in
    numpy: ``(kink (B, N), blocked (B, N), sel, sj, Dn, n_retract)``
    (:func:`torchpvs.tracker.kink_sides`); ``plan``: the plan whose own tubes these are (their
    arrays are kept on it)."""
    if tubes.length.shape[0] != 1:       # tubes per row: the torch mask
        with torch.no_grad():
            kink = kink_mask(tubes, torch.from_numpy(D), KINK_TOL).numpy()
        return (kink, *kink_sides(kink, D))

    def arrays():
        return (np.ascontiguousarray(tubes.length.detach().numpy().reshape(-1)),
                np.ascontiguousarray(tubes.straight.detach().numpy().reshape(-1)),
                np.ascontiguousarray(
                    (tubes.coef.detach().abs().sum((-1, -2)) > 0).numpy().reshape(-1)))

    L, Ls, curved = arrays() if plan is None else plan.static(("fused kink arrays",), arrays)
    kink = kink_mask_arrays(L, Ls, curved, D)
    return (kink, *kink_sides(kink, D))


def _predictor_arrays(initial, D, A, scene: Scene):
    """``(H_prev, cidx_prev, qmask_c_prev, predict, dA)`` of the rotation predictor
    (:func:`torchpvs.predictor.rotation_predictor`'s conditions; ``predict`` all False where
    they do not hold)."""
    B, N = D.shape
    ctx = initial.context if isinstance(initial, Equilibrium) else None
    info = None if ctx is None else ctx.implicit
    if (info is None or info.Hc is None or info.Hc.shape[0] != B or info.with_load
            or (ctx.scene.tubes is not scene.tubes and ctx.scene.tubes != scene.tubes)
            or ctx.insertion.shape != D.shape
            or not torch.equal(ctx.insertion, D)):
        return (np.zeros((B, 1, 1)), np.zeros((B, 1), dtype=np.int64), np.zeros((B, 1)),
                np.zeros(B, dtype=np.bool_), np.zeros((B, N)))
    dA = A.numpy() - ctx.rotation.detach().numpy()
    if not np.abs(dA).max() <= math.pi:       # (whole turns: none within +-pi)
        dA = dA - (2 * math.pi) * np.round(dA / (2 * math.pi))
    c = np.ascontiguousarray
    return (c(info.Hc.detach().numpy()), c(info.cidx.numpy()), c(info.qmask_c.detach().numpy()),
            np.ones(B, dtype=np.bool_), c(dA))


def fused_solve(scene: Scene, tubes: TubeTensors, D, A, F, M, opts: SolverOptions, initial,
                plan: Plan) -> FusedSolve | None:
    """The driver's first round (predictor, Newton, order and Magnus checks) and the
    actuation forces in two compiled calls, on canonical ``(B, ...)`` tensors (``A`` already
    reduced by whole turns, no gradient wanted); ``None`` where the fused path does not apply
    or its result is not final (see the module docstring): the driver then solves itself."""
    if not _applies(D, F, M, opts):
        return None
    B, N = D.shape
    q_init, init_order, init_magnus = initial_q(initial, B, N)
    if opts.order is not None:
        order = opts.order
    else:
        order = min(init_order if init_order is not None else ORDER_START, opts.max_order)
    m = opts.n_magnus or init_magnus or MAGNUS_START
    auto_order, auto_magnus = opts.order is None, opts.n_magnus is None
    if (auto_magnus and m % 2) or (q_init is not None and init_order != order):
        return None
    disc = _discretization(opts, order, m)
    n = disc.n_basis
    nq = n_coordinates(N, n)
    dt = D.dtype
    own = tubes is plan.tubes       # (the plan's own tubes never change; others may)
    loaded = torch.zeros(B, dtype=torch.bool)
    # (outside inference mode: the layout the context keeps is then an ordinary tensor, which
    # Equilibrium.released need not copy)
    # The plan's layout of these insertions where it keeps one; else the compiled call's own
    # (the same function of the same inputs) is converted after it, and kept: a cold start's
    # guess needs it first.
    kept = plan.kept_layout(tubes, D, A, F, M, loaded, disc, COMPILED.layout)
    if kept is None and q_init is None:
        kept = plan.layout(tubes, D, A, F, M, loaded, disc, nq, COMPILED.layout, grad=False)
    tab = disc.tables(dt, D.device)
    if q_init is None:
        with torch.no_grad():
            q_init = COMPILED.guess(*kept, tab, disc, N)
    P = tubes.coef.shape[-1]
    t0 = _tables(disc, P)
    c = np.ascontiguousarray
    if own:
        tube_arrays = plan.static(("fused tube arrays", B), lambda: _tube_arrays(tubes, B))
        length, consts = plan.static(("fused constants", opts.tol, opts.accuracy),
                                     lambda: _constants(scene, tubes, opts))
    else:
        tube_arrays = _tube_arrays(tubes, B)
        length, consts = _constants(scene, tubes, opts)
    Dn, An = c(D.numpy()), c(A.numpy())
    unloaded = np.zeros(B, dtype=np.bool_)
    H_prev, cidx_prev, qmc_prev, predict, dA = _predictor_arrays(initial, D, A, scene)
    tip, R, res = np.empty((B, 3)), np.empty((B, 3, 3)), np.empty(B)
    it, conv = np.zeros(B, dtype=np.int64), np.zeros(B, dtype=np.bool_)
    verdict, U, twist = np.empty(B, dtype=np.int8), np.empty(B), np.empty((B, max(N - 1, 0)))
    forces = opts.compute_forces
    if forces:
        # (kept with a kept layout: the same insertions)
        kink, blocked, sel, sj, Dk, n_r = (
            _kinks(tubes, Dn, plan if own else None) if kept is None else
            plan.cached(disc, kept[0], ("fused kinks", KINK_DELTA, KINK_TOL),
                        lambda: _kinks(tubes, Dn, plan if own else None)))
        tD, tA, vals = np.empty((B, N)), np.empty((B, N)), np.empty(len(sel))
    else:
        sel, sj, Dk = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros((0, N))
        tD, tA, vals = np.empty((1, N)), np.empty((1, N)), np.empty(0)
    lay_k, q, H, _ = solve_core(
        *tube_arrays, Dn, An, unloaded, *t0.layout[:5], n, c(q_init.to(dt).numpy()),
        H_prev, cidx_prev, qmc_prev, predict, dA, length, PREDICTOR_TRUST, t0.phi, t0.Qb,
        t0.phi_m, t0.Q_m, 1e-6, consts, opts.method == "minimize", opts.max_iter,
        stability_threshold(dt), tip, R, res, it, conv, verdict, forces, tD, tA, sel, sj, Dk,
        VANISHING * length, vals, U, twist)
    if not conv.all():
        return None
    if kept is None:
        lay, maps = layout_and_maps_of(lay_k, tubes, D, A, F, M, loaded, disc)
        plan.keep_layout(tubes, D, A, loaded, disc, lay, maps, COMPILED.layout)
    else:
        # the layout the context keeps must be the one solved on (same function, same inputs)
        lay, maps = kept
        cidx, mc = lay_k[17], maps.cidx.numpy()
        if not (cidx.shape == mc.shape and (cidx == mc).all()):
            return None
    err = est_m = None
    if auto_order or auto_magnus:
        # the driver's order estimate (at order + 1, where the solution's own tip is taken
        # too) and the Magnus check on the same layout; at a fixed order, the Magnus check
        # on the solve's own layout and tip
        d1 = _discretization(opts, order + 1, m) if auto_order else disc
        t1 = _tables(d1, P) if auto_order else t0
        q1 = q
        if auto_order:
            n1 = d1.n_basis
            X = np.zeros((B, 2 * N, 2 + N, n1))
            X[..., :n] = q[:, N:].reshape(B, 2 * N, 2 + N, n)
            q1 = np.concatenate([q[:, :N], X.reshape(B, -1)], -1)
        est, est_m = np.full(B, np.nan), np.full(B, np.nan)
        _order_check(q1, *tube_arrays, Dn, An, unloaded, *t1.layout, d1.n_basis, t1.Qb,
                     t1.phi_m, t1.Q_m, t1.xm_h, t1.phi_mh, t1.Q_mh, 1e-6, consts[3], auto_order,
                     auto_magnus, tip, R, est, est_m)
        if not np.isfinite(tip).all():
            return None
        if auto_order:
            budget = opts.accuracy / 2 if auto_magnus else opts.accuracy
            if not bool((est <= budget).all()):
                return None
            err = est
        if auto_magnus:
            if not bool((est_m <= opts.accuracy / 2).all()):
                # refine_magnus's next check: the tip with twice the steps; the count stays
                # where that agrees within accuracy / 2 (else the rounds double it)
                tf = _tables(replace(d1, n_magnus=2 * m), P)
                _order_check(q1, *tube_arrays, Dn, An, unloaded, *t1.layout, d1.n_basis,
                             t1.Qb, t1.phi_m, t1.Q_m, tf.layout[4], tf.phi_m, tf.Q_m, 1e-6,
                             consts[3], False, True, tip, R, est, est_m)
                if not bool((est_m <= opts.accuracy / 2).all()):
                    return None
            if err is not None:
                err = err + est_m
        else:
            est_m = None
    t = torch.from_numpy
    state = SolveState(
        q=t(q), lay=lay, tab=tab, disc=disc, order=order, maps=maps, Hc=t(H), g=None,
        # the energy of Newton's last evaluation at q (the compiled sum: the eager
        # mechanics.elastic_energy_maps there agrees to round-off, 1e-14 relative, and would
        # cost a sixth of a single solve)
        converged=t(conv), verdict=t(verdict), residual=t(res), iterations=t(it), energy=t(U),
        D=D, alpha=A, F=F, M=M, loaded=loaded, with_load=False, has_moment=False, tip=t(tip),
        R=t(R))
    state.error_estimate = None if err is None else t(err)
    state.magnus_estimate = None if est_m is None else t(est_m)
    out = None
    if forces:
        retract, ins = tD.copy(), tD.copy()
        ins[blocked] = np.nan
        retract[sel[:n_r], sj[:n_r]] = vals[:n_r]
        ins[sel[n_r:], sj[n_r:]] = vals[n_r:]
        out = (t(retract), t(tA), t(ins), t(kink))
    dofs = lay.qmask.numpy().sum(-1).astype(np.int64)
    return FusedSolve(state, out, t(twist), t(verdict == 1), t(dofs))


def control_blocks(eq) -> tuple[torch.Tensor, torch.Tensor] | None:
    """``(K (B, 2N, 2N), J_x (B, 6, 2N))`` of an :class:`~torchpvs.Equilibrium`, the control
    step of :mod:`torchpvs.jacobians` (actuator stiffness ``U_xx - U_xq H^-1 U_qx`` and tip
    Jacobian ``P_x - P_q H^-1 U_qx``, one-sided at kinks: the retraction side ``KINK_DELTA``
    away, with the equilibrium's ``q`` and ``H`` where the sections there have the same
    coordinates, else at the side's own equilibrium) in ONE compiled call: the tracker's
    (:func:`torchpvs.tracker.layout_and_track` from the solution, whose Newton test passes at
    once, and its control rows). ``None`` where it does not apply (the conditions of the fused
    solve, any batch size; an element that did not converge): the torch closed forms then."""
    ctx = eq.context
    info, opts = ctx.implicit, ctx.options
    q = eq.q
    B, N = ctx.insertion.shape
    if (info.with_load or info.has_moment or q.requires_grad or q.device.type != "cpu"
            or q.dtype != torch.float64 or opts.kernel != "compiled"
            or not compiled.available() or any(t.requires_grad for t in ctx.tubes.tensors())
            or not bool(eq.converged.all())):
        return None
    tubes = ctx.tubes
    D, A = ctx.insertion.detach(), ctx.rotation.detach()
    if opts.compute_forces and opts.force_model == "energy":
        kink = eq.force_kink.numpy()        # the solve's own analysis (the same mask)
    else:
        with torch.no_grad():
            kink = kink_mask(tubes, D).numpy()
    Dn = np.ascontiguousarray(D.numpy())
    L = np.broadcast_to(tubes.length.detach().numpy(), Dn.shape)
    sign = np.where(np.abs(L - Dn) <= KINK_DELTA / 2, -1.0, 1.0)
    D_side = np.ascontiguousarray(np.maximum.accumulate(Dn + KINK_DELTA * sign * kink, -1))
    side = kink.any(-1).astype(np.int8)
    disc = ctx.discretization
    t0 = _tables(disc, tubes.coef.shape[-1])
    tube_arrays = _tube_arrays(tubes, B)
    eps = float(torch.finfo(q.dtype).eps)
    consts = np.array([tolerance(newton_tol(ctx.scene, opts), q.dtype), 0.01 * eps ** 0.5, eps,
                       float(torch.finfo(q.dtype).tiny)])
    conv = np.zeros(B, dtype=np.bool_)
    J, K = np.empty((B, 6, 2 * N)), np.empty((B, 2 * N, 2 * N))
    none = np.zeros(0, dtype=np.int64)
    length = float(tubes.length.max())
    layout_and_track(
        *tube_arrays, Dn, np.ascontiguousarray(A.numpy()), np.zeros(B, dtype=np.bool_),
        *t0.layout[:5], disc.n_basis, np.ascontiguousarray(q.detach().numpy()),
        np.zeros((B, 1, 1)), np.zeros((B, 1), dtype=np.int64), np.zeros((B, 1)),
        np.zeros(B, dtype=np.bool_), np.zeros((B, N)), length, PREDICTOR_TRUST, t0.phi, t0.Qb,
        t0.phi_m, t0.Q_m, 1e-6, consts, opts.method == "minimize", opts.max_iter,
        stability_threshold(q.dtype), np.empty((B, 3)), np.empty((B, 3, 3)), np.empty(B),
        np.zeros(B, dtype=np.int64), conv, np.empty(B, dtype=np.int8), True, D_side, side, J, K,
        False, np.empty((1, N)), np.empty((1, N)), none, none, np.zeros((0, N)),
        VANISHING * length, np.empty(0), True, np.empty(B), np.empty((B, max(N - 1, 0))), False,
        np.empty(1))
    if not bool(conv.all()):
        return None
    return torch.from_numpy(K), torch.from_numpy(J)
