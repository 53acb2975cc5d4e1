"""Force-controlled equilibria: ``solve_force_controlled(scene, forces=..., torques=...)``.

Some actuator coordinates are commanded by a generalized force — an insertion force ``tau_Dj``
[N] or a rotation torque ``tau_alphaj`` [N·m], docs/conventions.md signs: ``tau = dU*/dx``, the
force
the actuator applies along increasing ``x`` to hold the robot — and the others by a position
(``D_j`` [m], ``alpha_j`` [rad]). The solver finds the free actuator coordinates ``x_f`` with
``tau_f(x) = commanded`` by a Levenberg-Marquardt-damped Newton iteration on ``x_f``:

* the Jacobian is the actuator stiffness ``K_ff = dtau_f/dx_f``, the free block of
  :func:`torchpvs.jacobians.actuator_stiffness` (the Schur complement of the full Hessian);
* every evaluation of ``tau(x)`` is a warm-started :func:`torchpvs.solve` (the previous
  equilibrium's coordinates), so the iteration follows the branch it starts on;
* steps are capped (``max_step``), kept inside the valid stroke (``0 <= D_1 <= D_2 <= ...``)
  and accepted only when they reduce ``|scaled residual|`` (otherwise the damping grows);
* coordinates are scaled to ``(D / ell, alpha)`` and forces to ``(tau_D * ell, tau_alpha)``,
  ``ell`` the longest tube, so that the damping and the step norm are unit-consistent.

Zero-stiffness modes. Without a tip load, rotating every tube together costs no energy
(``sum_j tau_alphaj = 0`` identically, docs/physics.md): when *all* rotations are torque-controlled,
the common rotation is undetermined. It is not fixed by a constraint: the Newton step is the
**least-norm step** (truncated-SVD pseudo-inverse of the scaled ``K_ff``), which has no component
along the zero mode, so the common rotation keeps its initial value (the mean of the free
rotations stays at the mean of ``rotation``). Commanded torques must then sum to zero, or no
equilibrium exists (the whole robot would spin): that element fails at once with a reason.
Other exact zero modes (for example moving both insertions together while only straight
material crosses the orifice) are treated the same way. A tip load breaks the rotation symmetry.

Failure. An element that finds no equilibrium gets ``converged = False`` and a reason: commanded
torques with a non-zero sum on a free common rotation; a stroke limit (``D_j >= D_{j-1} >= 0``)
that blocks the iteration (the commanded forces push the tube past it); a tube retracted fully
into the guide (no elastic force resists beyond); a rotation that travels more than
``max_rotation_travel`` (the tube would spin); or a stall — a minimum of the residual that is
not zero, where ``K_ff`` is singular: the commanded value lies beyond the largest elastic
force/torque the branch can resist (the reason prints the closest value reached). Bad input
(shapes, non-finite values, invalid positions) raises ``ValueError`` naming the field.

Like ``method="root"`` of :func:`torchpvs.solve`, the iteration converges to the force-controlled
equilibrium near its start, stable or not: ``stable`` reports whether it is stable *under force
control* — the shape Hessian positive definite (``Equilibrium.stable``) and the symmetric part
of the free actuator stiffness ``K_ff`` positive definite (the full Hessian over ``(q, x_f)``
is positive definite iff both are; the common-rotation zero mode is excluded as neutral).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, replace

import torch

from .clock import work_clock
from .equilibrium import Equilibrium
from .inputs import scene_inputs
from .jacobians import actuator_stiffness, control_jacobians
from .options import SolverError, SolverOptions, check_time_limit, within_deadline
from .scene import Scene, load_scene
from .solver import solve

__all__ = ["ForceControlled", "commanded_force_jacobian", "solve_force_controlled"]


@dataclass(frozen=True, eq=False)
class ForceControlled:
    """Result of :func:`solve_force_controlled` (``B`` elements, ``N`` tubes).

    Attributes:
        equilibrium: the :class:`~torchpvs.Equilibrium` at the solved actuation.
        insertion: ``(B, N)`` [m] and ``rotation``: ``(B, N)`` [rad] — the solved actuation
            (commanded positions where position-controlled).
        forces: ``(B, N)`` [N] and ``torques``: ``(B, N)`` [N·m] — ``tau = dU*/dx`` at the
            solution (on every coordinate, commanded or not).
        commanded: ``(B, 2N)`` bool, coordinate ``(D_1..D_N, alpha_1..alpha_N)`` is
            force-controlled.
        residual: ``(B, 2N)`` ``tau - commanded`` [N, N·m] on commanded coordinates, 0 elsewhere.
        converged: ``(B,)`` bool; ``reason``: per element, ``"converged"`` or why not.
        tolerance: ``(B, 2N)`` the convergence thresholds used on ``residual`` [N, N·m]:
            ``force_tol``/``torque_tol`` or the dtype's floor where that is larger.
        iterations: ``(B,)`` accepted + rejected Newton trials (one equilibrium solve each).
        actuator_stiffness: ``(B, 2N, 2N)`` ``dtau/dx`` at the solution [N/m, N, N·m/rad].
        stiffness_margin: ``(B,)`` [N·m] smallest eigenvalue of the symmetric part of the scaled
            free block ``S K_ff S`` (``S = diag(ell for D, 1 for alpha)``, ``ell`` the longest
            tube), the common-rotation zero mode excluded; ``+inf`` with nothing commanded.
        stable: ``(B,)`` bool, stable under force control: ``equilibrium.stable`` and
            ``stiffness_margin > 0``.
        zero_modes: ``(B,)`` number of exact zero-stiffness modes of ``K_ff`` (1 for a free
            common rotation; their components were left at the initial values).
    """

    equilibrium: Equilibrium
    insertion: torch.Tensor
    rotation: torch.Tensor
    forces: torch.Tensor
    torques: torch.Tensor
    commanded: torch.Tensor
    residual: torch.Tensor
    converged: torch.Tensor
    reason: tuple[str, ...]
    iterations: torch.Tensor
    actuator_stiffness: torch.Tensor
    stiffness_margin: torch.Tensor
    stable: torch.Tensor
    zero_modes: torch.Tensor
    tolerance: torch.Tensor

    def __len__(self) -> int:
        return self.insertion.shape[0]


def _commands(x, N: int, name: str, dtype, device) -> torch.Tensor:
    """``None`` / ``(N,)`` / ``(B, N)`` with NaN = position-controlled -> ``(B, N)``."""
    if x is None:
        return torch.full((1, N), float("nan"), dtype=dtype, device=device)
    t = torch.as_tensor(x, dtype=dtype, device=device)
    if t.ndim == 1:
        t = t[None]
    if t.ndim != 2 or t.shape[-1] != N:
        raise ValueError(f"{name} must have shape ({N},) or (B, {N}) (NaN = position-"
                         f"controlled), got {tuple(t.shape)}")
    if bool(torch.isinf(t).any()):
        raise ValueError(f"{name} must be finite or NaN (NaN = position-controlled), got inf")
    return t


# Convergence floors (in units of eps x the energy scale, see solve_force_controlled): about 3x
# and 2x the largest float32 rounding of tau measured on the Fig. 3 robot.
TORQUE_FLOOR = 8.0
FORCE_FLOOR = 64.0


def _energy_scale(scene: Scene, F: torch.Tensor, M: torch.Tensor, cmd: torch.Tensor,
                  free: torch.Tensor, ell: float) -> torch.Tensor:
    """``(B,)`` [J] the scale of the energies whose derivatives are the actuator forces: the
    energy to straighten every tube's curved part (``EI |u*_xy|^2 + GJ u*_z^2`` times its
    length, ``|u*|`` bounded by its coefficients), plus the work of the tip load and of the
    commanded forces and torques over the robot's length ``ell`` [m] / one radian."""
    e = 0.0
    for t in scene.tubes:
        lc = t.curved_length
        ux, uy, uz = (sum(abs(c) * lc**k for k, c in enumerate(ax)) for ax in t.precurvature)
        e += (t.bending_stiffness * (ux**2 + uy**2) + t.torsional_stiffness * uz**2) * lc
    N = cmd.shape[-1] // 2
    c = (cmd * free).abs()
    return (e + F.norm(dim=-1) * ell + M.norm(dim=-1) + c[:, :N].sum(-1) * ell
            + c[:, N:].sum(-1))


def _names(N: int) -> list[str]:
    return [f"D_{j + 1}" for j in range(N)] + [f"alpha_{j + 1}" for j in range(N)]


def _trial(x, K, r, S, free, mu, s_ref, active, max_step):
    """One damped Newton trial on the free coordinates: ``(x_try (B, 2N), block (B,), s_ref)``.

    The step solves ``K_ff dx = -r`` in scaled units (``S``: insertions over the robot's
    length, rotations in rad) by a truncated, Levenberg–Marquardt-damped SVD, is capped to
    ``max_step`` (insertion [m], rotation [rad]) and shortened so that ``0 <= D_1 <= D_2 <=
    ...`` holds along it. ``block``: active elements whose step the stroke limits cut to
    nothing (a command that drives a carriage into a limit). ``s_ref (B,)``: the damping's
    reference, the largest singular value of the first trial's scaled stiffness (pass None on
    the first trial, then the value returned)."""
    N = x.shape[-1] // 2
    dtype = x.dtype
    Ks = S[:, None] * K * S[None, :] * (free[:, :, None] & free[:, None, :])
    rs = r * S
    U, sv, Vh = torch.linalg.svd(Ks)
    if s_ref is None:
        s_ref = sv[:, 0].clamp(min=torch.finfo(dtype).tiny)
    keep = sv > 1e-9 * sv[:, :1]
    coef = torch.where(keep, sv / (sv**2 + mu[:, None] * s_ref[:, None]**2),
                       torch.zeros_like(sv))
    step = -(Vh.transpose(-1, -2) @ (coef * (U.transpose(-1, -2) @ rs[..., None])[..., 0])
             [..., None])[..., 0]
    dx = step * S * free
    # trust region: cap the largest insertion / rotation change
    capD = (dx[:, :N].abs().amax(-1) / max_step[0]).clamp(min=1.0)
    capA = (dx[:, N:].abs().amax(-1) / max_step[1]).clamp(min=1.0)
    dx = dx / torch.maximum(capD, capA)[:, None]
    # stroke: keep 0 <= D_1 <= D_2 <= ... along the step
    D, dD = x[:, :N], dx[:, :N]
    g = D - torch.cat([torch.zeros_like(D[:, :1]), D[:, :-1]], -1)
    dg = dD - torch.cat([torch.zeros_like(dD[:, :1]), dD[:, :-1]], -1)
    lim = torch.where(dg < 0, g / (-dg).clamp(min=torch.finfo(dtype).tiny),
                      torch.full_like(g, math.inf))
    t = lim.amin(-1).clamp(max=1.0)
    block = active & (t * dx.abs().amax(-1) <= 1e-15)
    x_try = torch.where(active[:, None], x + t[:, None] * dx, x)
    for j in range(N):   # round-off: re-impose the ordering on free insertions
        lo = x_try[:, j - 1] if j > 0 else torch.zeros_like(x_try[:, 0])
        x_try[:, j] = torch.where(free[:, j], torch.maximum(x_try[:, j], lo), x_try[:, j])
        if j + 1 < N:
            hi = x_try[:, j + 1]
            x_try[:, j] = torch.where(free[:, j] & ~free[:, j + 1],
                                      torch.minimum(x_try[:, j], hi), x_try[:, j])
    return torch.where(block[:, None], x, x_try), block, s_ref


def solve_force_controlled(
    scene: Scene | str, *, forces=None, torques=None, insertion=None, rotation=None,
    tip_force=None, tip_moment=None, options: SolverOptions | None = None,
    initial: Equilibrium | torch.Tensor | None = None, force_tol: float = 1e-8,
    torque_tol: float = 1e-10, max_iter: int = 60, max_step: tuple[float, float] = (5e-3, 0.25),
    max_rotation_travel: float = 2 * math.pi, on_failure: str = "warn",
    time_limit: float | None = 120.0,
) -> ForceControlled:
    """Equilibrium with commanded actuator forces/torques on some coordinates (batched).

    Args:
        scene: a :class:`~torchpvs.Scene` or a built-in scene name / file path.
        forces: ``(N,)`` or ``(B, N)`` commanded insertion forces ``tau_Dj`` [N]; NaN (or
            ``None`` for all) = ``D_j`` position-controlled.
        torques: ``(N,)`` or ``(B, N)`` commanded rotation torques ``tau_alphaj`` [N·m]; NaN (or
            ``None``) = ``alpha_j`` position-controlled.
        insertion, rotation: ``(N,)`` or ``(B, N)`` [m], [rad]: the commanded positions of the
            position-controlled coordinates and the starting point of the free ones (default
            the scene's actuation). Must be a valid actuation (docs/conventions.md).
        tip_force, tip_moment: ``(3,)`` or ``(B, 3)`` [N], [N·m], base frame (default the
            scene's load).
        options: :class:`~torchpvs.SolverOptions` of the inner equilibrium solves. An automatic
            order / Magnus step count is chosen by the first solve and then frozen, so that
            ``tau(x)`` is one smooth function during the iteration.
        initial: warm start (an :class:`~torchpvs.Equilibrium` or coordinates) of the first solve.
        force_tol: convergence threshold on ``|tau_Dj - commanded|`` [N].
        torque_tol: convergence threshold on ``|tau_alphaj - commanded|`` [N·m]. Both are
            raised, per element, to the floor the dtype can resolve (``64 eps E / ell`` [N] and
            ``8 eps E`` [N·m], ``E`` the energy scale of the robot, its load and the commands:
            about 3e-6 N·m for the Fig. 3 robot in float32, 1e-15 N·m in float64);
            :attr:`ForceControlled.tolerance` holds the thresholds used.
        max_iter: Newton trials (each one batched equilibrium solve + ``2N`` adjoint passes).
        max_step: ``(insertion [m], rotation [rad])`` largest change of a coordinate per step.
        max_rotation_travel: [rad] a free rotation moving farther than this from its start fails
            (the commanded torque exceeds what the tube can resist: it would spin).
        on_failure: ``"warn"`` (default), ``"raise"`` (:class:`~torchpvs.SolverError`) or
            ``"ignore"`` for elements without an equilibrium (status is always in the result).
        time_limit: [s] wall-clock bound on the whole call (default 120 s; ``None``: none),
            checked before every Newton trial, every solve bounded by what is left; elements
            still unconverged then say "time limit ... reached".

    Returns:
        :class:`ForceControlled`.
    """
    t_start = work_clock()
    check_time_limit(time_limit)
    deadline = None if time_limit is None else t_start + time_limit
    if not isinstance(scene, Scene):
        scene = load_scene(scene)
    opts = options or SolverOptions()
    for nm, v in (("force_tol", force_tol), ("torque_tol", torque_tol),
                  ("max_rotation_travel", max_rotation_travel)):
        if not (isinstance(v, (int, float)) and v > 0 and math.isfinite(v)):
            raise ValueError(f"{nm} must be a positive number, got {v!r}")
    if not isinstance(max_iter, int) or max_iter < 1:
        raise ValueError(f"max_iter must be an integer >= 1, got {max_iter!r}")
    if len(max_step) != 2 or not all(s > 0 for s in max_step):
        raise ValueError(f"max_step must be (insertion [m] > 0, rotation [rad] > 0), "
                         f"got {max_step!r}")
    if on_failure not in ("warn", "raise", "ignore"):
        raise ValueError(f"on_failure must be 'warn', 'raise' or 'ignore', got {on_failure!r}")
    D0, A0, F, M, dtype, device = scene_inputs(
        scene, insertion, rotation, tip_force, tip_moment, dtype=opts.dtype, device=opts.device,
        forces=forces, torques=torques)
    N = scene.n_tubes
    cmd_f = _commands(forces, N, "forces", dtype, device)
    cmd_t = _commands(torques, N, "torques", dtype, device)
    B = max(D0.shape[0], cmd_f.shape[0], cmd_t.shape[0])
    for nm, t in (("forces", cmd_f), ("torques", cmd_t), ("insertion", D0)):
        if t.shape[0] not in (1, B):
            raise ValueError(f"{nm} has batch size {t.shape[0]}, expected 1 or {B}")
    cmd = torch.cat([cmd_f.expand(B, N), cmd_t.expand(B, N)], -1).clone()
    free = ~torch.isnan(cmd)                                              # (B, 2N)
    cmd = torch.where(free, cmd, torch.zeros_like(cmd))
    x = torch.cat([D0.expand(B, N), A0.expand(B, N)], -1).clone()
    F, M = F.expand(B, 3).contiguous(), M.expand(B, 3).contiguous()
    ell = max(t.length for t in scene.tubes)
    S = torch.tensor([ell] * N + [1.0] * N, dtype=dtype, device=device)
    # Tolerances follow the dtype: tau = dU*/dx rounds at about eps x the scale of the energy
    # (measured on the Fig. 3 robot in float32 against float64: torques within 2.4 eps E,
    # forces within 31 eps E / ell, E = 0.72 J), so a threshold below that floor can never be
    # met (float32 used to stall 3e-8 N·m from a 1e-10 target and report "unreachable").
    # In float64 the floors (~1e-15 N·m, ~3e-14 N) lie far below the
    # defaults.
    eps = torch.finfo(dtype).eps
    E = _energy_scale(scene, F, M, cmd, free, ell)                              # (B,) [J]
    floor = torch.cat([(FORCE_FLOOR * eps / ell) * E[:, None].expand(B, N),
                       (TORQUE_FLOOR * eps) * E[:, None].expand(B, N)], -1)
    tol = torch.maximum(torch.tensor([float(force_tol)] * N + [float(torque_tol)] * N,
                                     dtype=dtype, device=device), floor)         # (B, 2N)
    L = torch.tensor([t.length for t in scene.tubes], dtype=dtype, device=device)
    names = _names(N)

    inner = replace(opts, on_failure="ignore")

    def evaluate(xx, init):
        eq = solve(scene, insertion=xx[:, :N], rotation=xx[:, N:], tip_force=F, tip_moment=M,
                   options=within_deadline(inner, deadline), initial=init)
        tau = torch.cat([eq.actuation_forces, eq.actuation_torques], -1).detach()
        return eq, tau

    eq, tau = evaluate(x, initial)
    if opts.order is None or opts.n_magnus is None:
        inner = replace(inner, order=eq.order, n_magnus=eq.context.discretization.n_magnus)
    failed = ~eq.converged.clone()
    reason: list[str] = [("" if bool(eq.converged[b]) else
                          f"the equilibrium solve at the initial actuation failed: {eq.reason[b]}")
                         for b in range(B)]
    # Free common rotation (all rotations torque-controlled, unloaded tip): a zero mode.
    unloaded = (F.abs().sum(-1) == 0) & (M.abs().sum(-1) == 0)
    common_free = free[:, N:].all(-1) & unloaded
    sum_t = cmd[:, N:].sum(-1)
    bad_sum = common_free & (sum_t.abs() > N * tol[:, N:].amax(-1))
    for b in bad_sum.nonzero().flatten().tolist():
        failed[b] = True
        reason[b] = (f"no equilibrium: every rotation is torque-controlled and the tip is "
                     f"unloaded, so the torques must sum to zero (sum_j tau_alpha_j = 0, the "
                     f"common rotation is a zero-stiffness mode); commanded sum = "
                     f"{float(sum_t[b]):.6g} N·m")

    K = actuator_stiffness(eq)
    q = eq.q.detach()
    eqs = eq
    mu = torch.full((B,), 1e-8, dtype=dtype, device=device)
    s_ref = None
    iters = torch.zeros(B, dtype=torch.long, device=device)
    blocked = torch.zeros(B, dtype=torch.bool, device=device)
    x_start = x.clone()

    def residual(t):
        return (t - cmd) * free

    r = residual(tau)

    def precision_stall(b: int) -> bool:
        # The least-norm Newton step from the stalled point, in scaled units (D / ell, rad):
        # tiny where K_ff is regular and only rounding stops the decrease, large where the
        # command lies beyond the branch's largest resistance (K_ff -> 0 at the stall).
        fb = free[b]
        Kb = (S[:, None] * K[b] * S[None, :])[fb][:, fb]
        step = torch.linalg.pinv(Kb, rtol=1e-9) @ (r[b] * S)[fb]
        return bool(step.abs().amax() <= eps ** 0.5)

    history: list[torch.Tensor] = []
    window = 8
    timed_out = False
    for _ in range(max_iter):
        done = ((r.abs() <= tol) | ~free).all(-1)
        active = ~done & ~failed
        if not bool(active.any()):
            break
        if deadline is not None and work_clock() > deadline:
            timed_out = True
            break
        x_try, block, s_ref = _trial(x, K, r, S, free, mu, s_ref, active, max_step)
        eq_try, tau_try = evaluate(x_try, q)
        r_try = residual(tau_try)
        phi = ((r * S) ** 2).sum(-1)
        phi_try = ((r_try * S) ** 2).sum(-1)
        ok = active & ~block & eq_try.converged & (phi_try < phi) & torch.isfinite(phi_try)
        iters = iters + active.long()
        blocked = torch.where(active, block, blocked)
        if bool(ok.any()):
            K_try = actuator_stiffness(eq_try)
            K = torch.where(ok[:, None, None], K_try, K)
            q = torch.where(ok[:, None], eq_try.q.detach(), q)
            x = torch.where(ok[:, None], x_try, x)
            tau = torch.where(ok[:, None], tau_try, tau)
            r = residual(tau)
        mu = torch.where(ok, (mu * 0.1).clamp(min=1e-12),
                         torch.where(active, mu * 10.0, mu))
        # stagnation: the merit fell by less than 1% over the last `window` trials
        history.append(((r * S) ** 2).sum(-1))
        stalled = mu > 1e10
        if len(history) > window:
            stalled = stalled | (history[-1] > 0.99 * history[-1 - window])
        # failures detected along the way
        for b in active.nonzero().flatten().tolist():
            if failed[b]:
                continue
            travel = (x[b, N:] - x_start[b, N:]).abs() * free[b, N:]
            inside = free[b, :N] & (x[b, :N] >= L - 1e-12)
            if bool((travel > max_rotation_travel).any()):
                j = int(travel.argmax())
                failed[b] = True
                reason[b] = (f"no equilibrium: alpha_{j + 1} turned more than "
                             f"{max_rotation_travel:.3g} rad without balancing the commanded "
                             f"torque {float(cmd[b, N + j]):.6g} N·m (torques[{j}] exceeds the "
                             f"largest elastic resistance: the tube would spin)")
            elif bool(inside.any()):
                j = int(inside.nonzero()[0])
                failed[b] = True
                reason[b] = (f"no equilibrium: insertion D_{j + 1} retracted tube {j + 1} fully "
                             f"into the guide (D >= length {float(L[j]):.6g} m) without "
                             f"balancing forces[{j}] = {float(cmd[b, j]):.6g} N")
            elif bool(stalled[b]):
                failed[b] = True
                k = int(((r[b] * S).abs()).argmax())
                nm = names[k]
                unit = "N·m" if k >= N else "N"
                field = f"torques[{k - N}]" if k >= N else f"forces[{k}]"
                if bool(blocked[b]):
                    j = k if k < N else int(((r[b, :N] * S[:N]).abs()).argmax())
                    rule = f"D_{j + 1} >= D_{j}" if j > 0 else "D_1 >= 0"
                    reason[b] = (f"no equilibrium in the valid stroke: the commanded forces "
                                 f"drive insertion D_{j + 1} against the limit {rule} "
                                 f"(docs/conventions.md) at D = {x[b, :N].tolist()} m; residual "
                                 f"{nm}: {float(r[b, k]):.6g} {unit}")
                elif precision_stall(b):
                    reason[b] = (f"stalled at the rounding level of {dtype}: |tau - commanded| "
                                 f"stopped decreasing at {field} = {float(cmd[b, k]):.6g} {unit} "
                                 f"(reached {float(tau[b, k]):.6g} {unit}, residual "
                                 f"{float(r[b, k]):.3g} > threshold {float(tol[b, k]):.3g} "
                                 f"{unit}) with a non-singular stiffness: the Newton step left "
                                 f"is below what {dtype} resolves; raise force_tol/torque_tol "
                                 f"or solve in float64")
                else:
                    kk = float(K[b, k, k]) * (ell**2 if k < N else 1.0)
                    reason[b] = (f"no equilibrium reachable: |tau - commanded| stopped "
                                 f"decreasing — {field} = {float(cmd[b, k]):.6g} {unit} lies "
                                 f"beyond the largest elastic resistance reachable on this "
                                 f"branch from the start (closest reached: "
                                 f"{float(tau[b, k]):.6g} {unit} at {nm} = "
                                 f"{float(x[b, k]):.6g}, where dtau/d{nm} = "
                                 f"{float(K[b, k, k]):.3g}; scaled {kk:.3g} N·m)")
    conv = ((r.abs() <= tol) | ~free).all(-1) & ~failed
    for b in range(B):
        if bool(conv[b]):
            reason[b] = "converged"
        elif not reason[b] and timed_out:
            k = int(((r[b] * S).abs()).argmax())
            reason[b] = (f"time limit time_limit={time_limit:g} s reached after "
                         f"{int(iters[b])} trials: largest residual {names[k]}: "
                         f"{float(r[b, k]):.3g}")
        elif not reason[b]:
            k = int(((r[b] * S).abs()).argmax())
            reason[b] = (f"not converged after {int(iters[b])} trials (max_iter): largest "
                         f"residual {names[k]}: {float(r[b, k]):.3g}; try more max_iter or a "
                         f"start closer to the solution (continuation in the commanded values)")
    # final equilibrium at the accepted actuation (warm: no Newton iterations)
    eqs = solve(scene, insertion=x[:, :N], rotation=x[:, N:], tip_force=F, tip_moment=M,
                options=within_deadline(inner, None if deadline is None else
                                        max(deadline, work_clock())
                                        + 0.1 * time_limit), initial=q)
    margin, tiny = _stiffness_margin(K, S, free, common_free)
    stable = eqs.stable & (margin > tiny)
    zero_modes = common_free.long()
    result = ForceControlled(
        equilibrium=eqs, insertion=x[:, :N].clone(), rotation=x[:, N:].clone(),
        forces=tau[:, :N].clone(), torques=tau[:, N:].clone(), commanded=free, residual=r,
        converged=conv, reason=tuple(reason), iterations=iters, actuator_stiffness=K,
        stiffness_margin=margin, stable=stable, zero_modes=zero_modes, tolerance=tol)
    bad = (~conv).nonzero().flatten().tolist()
    if bad and on_failure != "ignore":
        msg = (f"solve_force_controlled: {len(bad)} of {B} element(s) found no equilibrium "
               f"(first: element {bad[0]}: {reason[bad[0]]})")
        if on_failure == "raise":
            raise SolverError(msg)
        warnings.warn(msg, RuntimeWarning, stacklevel=2)
    return result


def _stiffness_margin(K, S, free, common_free):
    """``(margin (B,), tiny (B,))``: the least eigenvalue of the scaled, symmetrized stiffness
    on the free coordinates (inf where none is free), the common-rotation zero mode excluded
    where it exists (``common_free``), and the threshold it must exceed to count as stable."""
    N = K.shape[-1] // 2
    Ks = S[:, None] * K * S[None, :]
    Kf = torch.where(free[:, :, None] & free[:, None, :], 0.5 * (Ks + Ks.transpose(1, 2)),
                     torch.zeros_like(Ks))
    big = Kf.abs().amax((-1, -2)) * 10 + 1.0
    Kf = Kf + torch.diag_embed((~free) * big[:, None])
    # exclude the common-rotation zero mode: add a large multiple of its projector
    n = torch.tensor([0.0] * N + [N ** -0.5] * N, dtype=K.dtype, device=K.device)
    Kf = Kf + common_free[:, None, None] * big[:, None, None] * torch.outer(n, n)
    margin = torch.linalg.eigvalsh(Kf)[:, 0]
    margin = torch.where(free.any(-1), margin, torch.full_like(margin, math.inf))
    return margin, 1e-10 * Ks.abs().amax((-1, -2))


def commanded_force_jacobian(result: ForceControlled) -> torch.Tensor:
    """``d(tip)/d(commanded tau)`` ``(B, 6, 2N)`` at a force-controlled equilibrium: rows
    ``(p_x, p_y, p_z)`` [m] and spatial rotation ``(omega_x, omega_y, omega_z)`` [rad] of the
    tip per unit commanded force [N] / torque [N·m], columns ``(D_1..D_N, alpha_1..alpha_N)``,
    zero on position-controlled columns: ``J_x[:, f] K_ff^+`` (least-norm pseudo-inverse of the
    free actuator stiffness block; the position-controlled coordinates are held).
    Differs from :attr:`~torchpvs.jacobians.ControlJacobians.force_jacobian`, which assumes
    every coordinate force-controlled."""
    J = control_jacobians(result.equilibrium)
    f = result.commanded
    K = result.actuator_stiffness
    N = K.shape[-1] // 2
    ell = float(result.equilibrium.context.tubes.length.max())
    S = torch.tensor([ell] * N + [1.0] * N, dtype=K.dtype, device=K.device)
    Kff = S[:, None] * K * S[None, :] * (f[:, :, None] & f[:, None, :])
    Kp = S[:, None] * torch.linalg.pinv(Kff, rtol=1e-9) * S[None, :]
    Jx = J.tip_jacobian * f[:, None, :]
    return Jx @ Kp
