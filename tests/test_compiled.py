"""The compiled CPU kernel (torchpvs.compiled, numba) against the eager reference kernel.

Reference: the eager kernel (torchpvs.kernel.EAGER, batched torch), which the rest of the suite
checks against closed forms, the paper's tables and the independent standard-model solver. The
compiled kernel re-implements the same iteration element by element, so both must give the same
equilibria: tips within 1e-12 m, actuation forces within 1e-9 N (N m), and the same
convergence flags, iteration counts and stability verdicts, on the suite's scenes (the paper's
Fig. 3 and section III-B robots, a kink at the orifice, three nested tubes, seeded random
robots, unstable equilibria) and in float32.
"""

from __future__ import annotations

import dataclasses
import math
import os
import subprocess
import sys

import numpy as np
import pytest
import torch
from hypothesis import HealthCheck, given, settings

import torchpvs as tp
import torchpvs.solver as solver_mod
from torchpvs import SolverOptions, compiled
from torchpvs.kernel import COMPILED, EAGER, KERNELS
from torchpvs.testing import (
    D1_FIG3,
    SWEEPS,
    assert_same_equilibria,
    fig3,
    nested_scene,
    random_scene,
    scene_strategy,
    spy_results,
)

DT = torch.float64
pytestmark = pytest.mark.skipif(not compiled.available(), reason="numba is not installed")


def both(scene, options: SolverOptions | None = None, **kw):
    """The same solve on the eager and the compiled kernel."""
    opts = options or SolverOptions()
    return tuple(tp.solve(scene, **kw, options=dataclasses.replace(opts, kernel=k))
                 for k in ("newton", "compiled"))


def assert_same(eager, comp, tip_tol=1e-12, force_tol=1e-9):
    """Same equilibria: tips, forces, flags, iterations, verdicts."""
    assert_same_equilibria(eager, comp, tip_tol, force_tol)


@pytest.mark.parametrize("sweep", sorted(SWEEPS))
def test_fig3_sweeps_match_the_eager_kernel(sweep):
    """The paper's Fig. 3 sweeps (section III-C: D1 = 93.5 mm, the outer tube's kink at the
    orifice), one batch per sweep, cold and warm."""
    D2, alphas = SWEEPS[sweep]
    rot = torch.tensor([[0.0, math.radians(a)] for a in alphas], dtype=DT)
    ins = torch.tensor([[D1_FIG3, D2]] * len(alphas), dtype=DT)
    eager, comp = both(fig3(), insertion=ins, rotation=rot)
    assert_same(eager, comp)
    warm_e, warm_c = both(fig3(), insertion=ins, rotation=rot + 0.02, initial=eager)
    assert_same(warm_e, warm_c)


def test_a_batch_of_mixed_sections_matches():
    """Insertions that put a tube in the guide, at the orifice kink and beyond (elements with
    different active sections in one batch), rotations over the circle."""
    rng = np.random.default_rng(3)
    B = 40
    ins = torch.tensor(np.column_stack([rng.uniform(0.0, 0.12, B), rng.uniform(0.12, 0.21, B)]),
                       dtype=DT)
    rot = torch.tensor(rng.uniform(-math.pi, math.pi, (B, 2)), dtype=DT)
    assert_same(*both(fig3(), insertion=ins, rotation=rot))


def test_padding_a_batch_changes_no_bit_of_an_element():
    """A batch pads each element's compact coordinates to its longest element's; the compiled
    Newton works on the sections that matter (``compiled.active_extent``) and the tracker's
    factorizations skip the padding (``compiled.factor_leading``). Reference: each element
    solved alone, with no padding at all: the same coordinates, iterations, residuals, tips,
    forces, stability margins and actuator stiffnesses, bit for bit (the padding is an
    identity block that adds exact zeros)."""
    rng = np.random.default_rng(5)
    k = 24
    D = np.column_stack([rng.uniform(0.0, 0.12, k), rng.uniform(0.12, 0.21, k)])
    A = rng.uniform(-math.pi, math.pi, (k, 2))
    scene = fig3()
    tracker = tp.Tracker(scene, insertion=D[:1], rotation=A[:1])
    near = tp.solve(scene, insertion=torch.tensor(D), rotation=torch.tensor(A),
                    options=tracker.options)
    assert bool(near.converged.all())
    dofs = near.dofs.numpy()
    assert len(set(dofs.tolist())) >= 3            # padded: elements of 1, 2 and 3 sections
    q0 = near.q.numpy()
    kw = {"stiffness": True, "forces": True, "margin": True, "threads": 1}
    batch = tracker.solve_from(q0, D, A + 0.05, **kw)
    assert batch.converged.all() and (batch.iterations > 0).any()
    for b in range(k):
        alone = tracker.solve_from(q0[b:b + 1], D[b:b + 1], A[b:b + 1] + 0.05, **kw)
        for name in ("q", "tip", "R", "residual", "iterations", "energy", "actuation_forces",
                     "actuation_torques", "min_stiffness_eigenvalue", "actuator_stiffness"):
            np.testing.assert_array_equal(getattr(batch, name)[b], getattr(alone, name)[0],
                                          err_msg=f"{name}, element {b} ({dofs[b]} dofs)")


def test_the_leading_factorization_is_the_full_one():
    """``compiled.factor_leading`` / ``solve_leading`` on a matrix with a decoupled, inactive
    trailing block against ``cholesky`` / ``cho_solve`` on the whole matrix: the same solution
    bit for bit; a coupled or active trailing row is kept in the leading block; a matrix that
    is not positive definite (in the block or after it) is reported."""
    rng = np.random.default_rng(2)
    n, ne = 11, 7
    M = rng.normal(size=(ne, ne))
    H = np.diag(rng.uniform(0.5, 2.0, n))
    H[:ne, :ne] = M @ M.T + ne * np.eye(ne)
    qm = np.zeros(n)
    qm[:ne - 1] = 1.0               # the last leading row is inactive but coupled
    b = rng.normal(size=n)
    L, ok = compiled.factor_leading(H, qm, 0)
    assert ok and L.shape == (ne, ne)
    x, ref = np.empty(n), np.empty(n)
    compiled.solve_leading(H, L, b, x)
    Lf = np.empty((n, n))
    assert compiled.cholesky(H, Lf)
    compiled.cho_solve(Lf, b, ref)
    np.testing.assert_array_equal(x, ref)
    np.testing.assert_allclose(H @ x, b, rtol=1e-12, atol=1e-12)
    H2 = H.copy()
    H2[n - 1, n - 1] = -1.0         # a negative pivot after the block
    assert not compiled.factor_leading(H2, qm, 0)[1]
    H3 = H.copy()
    H3[0, 0] = -1.0                 # inside it
    assert not compiled.factor_leading(H3, qm, 0)[1]
    qm[n - 2] = 1.0                 # an active row further on: kept
    assert compiled.factor_leading(H, qm, 0)[0].shape == (n - 1, n - 1)


@pytest.mark.parametrize("alpha2", [170.0, 186.0, 190.0])
@pytest.mark.parametrize("method", ["minimize", "root"])
def test_multistable_robot_same_branch_and_verdict(alpha2, method):
    """Section III-B robot beyond its stability threshold (three equilibria): ``minimize``
    leaves the unstable middle one (saddle test and escape), ``root`` lands on it (unstable
    verdict). Both kernels must agree on the equilibrium and the verdict."""
    sc = tp.load_scene("renda2021_section3b").with_actuation(
        rotation=[0.0, math.radians(alpha2)])
    eager, comp = both(sc, options=SolverOptions(method=method))
    assert_same(eager, comp)
    assert bool(eager.stable[0]) is (method == "minimize")


@pytest.mark.parametrize("seed", range(6))
def test_seeded_random_robots_match(seed):
    assert_same(*both(random_scene(seed)))


@pytest.mark.parametrize("n_tubes", [3, 4])
def test_nested_robots_match(n_tubes):
    assert_same(*both(nested_scene(n_tubes, seed=1)))


@settings(max_examples=12, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(scene_strategy(max_tubes=3))
def test_random_scenes_match(scene):
    """Property: on any valid scene of the suite's strategy the kernels agree (a tip load, if
    the strategy draws one, runs the eager kernel in both)."""
    assert_same(*both(scene))


def test_float32_matches_float64_eager_to_float32_precision():
    """float32: the compiled kernel converges where the eager one does, to the same equilibrium
    within float32's resolution."""
    rot = torch.tensor([[0.0, math.radians(a)] for a in range(0, 281, 40)], dtype=torch.float32)
    ins = torch.tensor([[D1_FIG3, 0.2085]] * rot.shape[0], dtype=torch.float32)
    e32 = tp.solve(fig3(), insertion=ins, rotation=rot, options=SolverOptions(kernel="newton"))
    c32 = tp.solve(fig3(), insertion=ins, rotation=rot, options=SolverOptions(kernel="compiled"))
    assert c32.tip_position.dtype == torch.float32
    assert bool(c32.converged.all()) and torch.equal(e32.converged, c32.converged)
    assert float((e32.tip_position - c32.tip_position).abs().max()) < 1e-6


def _spy_compiled_solve(monkeypatch) -> list[bool]:
    """Patch compiled.solve to record, per call, whether the compiled kernel solved (True) or
    handed the solve to the eager one (None returned: False)."""
    return spy_results(monkeypatch, compiled, "solve")


@pytest.mark.parametrize("force", [[0.1, -0.2, 0.05], [0.5, 0.3, -0.4]])
def test_a_tip_force_is_solved_by_the_compiled_kernel_and_agrees(monkeypatch, force):
    """With a dead tip force the compiled kernel solves (its load terms: compiled_load), and
    gives the eager kernel's iterations, verdicts and equilibria to rounding (8 rotations)."""
    calls = _spy_compiled_solve(monkeypatch)
    sc = fig3().with_load(tip_force=force)
    rot = torch.tensor(np.random.default_rng(0).uniform(-3, 3, (8, 2)), dtype=DT)
    eager, comp = both(sc, rotation=rot)
    assert calls and all(calls), calls
    assert bool(comp.converged.all())
    assert_same(eager, comp)
    assert float((eager.q - comp.q).abs().max()) < 1e-12


def test_a_tip_moment_still_runs_the_eager_solve_and_agrees(monkeypatch):
    """A dead tip moment (non-conservative) is not in the compiled load terms: the compiled
    kernel hands the solve to the eager one, with the same result."""
    calls = _spy_compiled_solve(monkeypatch)
    eager, comp = both(fig3().with_load(tip_force=[0.1, 0.0, 0.0], tip_moment=[0.0, 0.002, 0.0]))
    assert calls and not any(calls)
    assert_same(eager, comp)


def _captured_problems(scene, rotation, options):
    """(q, Problem) of every Newton solve of ``tp.solve(scene, rotation=...)``."""
    from torchpvs.newton import newton
    got = []

    def solve(q, prob, L_char, **kw):
        got.append((q.clone(), prob))
        return newton(q, prob, L_char, **kw)

    KERNELS["capture"] = EAGER._replace(solve=solve)
    try:
        tp.solve(scene, rotation=rotation, options=dataclasses.replace(options, kernel="capture"))
    finally:
        del KERNELS["capture"]
    return got


@pytest.mark.parametrize("case", ["fig3", "random1", "nested3", "held"])
def test_the_compiled_load_terms_are_the_autograd_ones(case):
    """compiled_load.load_work's gradient and Hessian of the tip force's work against the
    eager kernel's autograd through the Magnus chain (newton._load_hessian), at perturbed
    coordinates of every captured problem: relative 1e-12. "held": a force put on an unloaded
    problem, whose distal section is prescribed (the held tubes' Rz(psi) u* terms, which a
    loaded layout never has)."""
    from torchpvs.compiled_load import load_work
    from torchpvs.mechanics import compact_q
    from torchpvs.newton import _load_hessian
    force = torch.tensor([0.2, -0.1, 0.3], dtype=DT)
    sc = {"fig3": fig3(), "random1": random_scene(1), "nested3": nested_scene(3, seed=1),
          "held": fig3()}[case]
    if case != "held":
        sc = sc.with_load(tip_force=force.tolist())
    rot = torch.tensor(np.random.default_rng(0).uniform(-3, 3, (4, len(sc.tubes))), dtype=DT)
    probs = _captured_problems(sc, rot, SolverOptions())
    assert probs
    gen = torch.Generator().manual_seed(0)
    checked = held = 0
    for q, prob in probs[:3]:
        B = q.shape[0]
        if case == "held":
            assert prob.lay is not None and not prob.with_load
            prob = prob._replace(lay=prob.lay._replace(force=force.expand(B, 3).contiguous()),
                                 with_load=True)
        held += int((prob.maps.pose.ustar_held != 0).any())
        qc = compact_q(q, prob.maps.cidx)
        qc = qc + 0.01 * torch.randn(qc.shape, generator=gen, dtype=DT) * prob.maps.qmask
        Hr, gr = _load_hessian(qc, prob)
        LD = compiled._load_arrays(prob, DT, B)
        nc = qc.shape[1]
        for b in range(B):
            gW, HW = np.empty(nc), np.empty((nc, nc))
            W = load_work(qc[b].numpy().copy(), *(a[b] for a in LD[:10]), LD[10], LD[11], 2,
                          gW, HW)
            assert W != 0.0
            # newton._load_hessian differentiates minus the work
            g_ref, H_ref = -gr[b].numpy(), -Hr[b].numpy()
            assert np.abs(gW - g_ref).max() <= 1e-12 * np.abs(g_ref).max()
            assert np.abs(HW - H_ref).max() <= 1e-12 * np.abs(H_ref).max()
            checked += 1
    assert checked >= 4
    assert (held > 0) == (case == "held")


def test_the_machine_code_cache_follows_both_compiled_modules():
    """numba re-compiles a cached function when its own file changes, not when a function it
    calls from another file does: compiled.py's kernels kept the old load terms after
    compiled_load.py changed (measured: the loaded solve ran at the old speed until the cache
    was deleted). The cache directory is therefore named by both sources and numba's version,
    and every compiled kernel of both modules caches there."""
    from torchpvs import compiled_load
    a, b = b"def f(): pass\n", b"def g(): pass\n"
    cache_dir = compiled_load.cache_dir
    d = cache_dir([a, b], "0.1", "/c")
    assert d == cache_dir([a, b], "0.1", "/c") and d.startswith("/c/numba-")
    assert len({d, cache_dir([a + b"#", b], "0.1", "/c"), cache_dir([a, b + b"#"], "0.1", "/c"),
                cache_dir([a, b], "0.2", "/c")}) == 4
    root = compiled_load._CACHE_DIR
    assert root is not None
    for f in (compiled.evaluate, compiled.total, compiled._newton_serial, compiled._pose_parallel,
              compiled_load.load_work, compiled_load.exp_jets):
        assert f._cache._cache_path.startswith(root), f


@pytest.mark.parametrize("case", ["fig3", "nested3"])
def test_the_line_search_work_is_the_newton_work_bit_for_bit(case):
    """The line search evaluates the work alone (order 0: compiled_load.exp_value, no jets) and
    compares it with the energy of the Newton evaluation (order 2: the jets' values): the two
    must be the same number, or Armijo tests could flip on round-off. Both are also the work
    ``F . p_tip`` of the eager kernel's tip pose (mechanics.tip_pose, an independent
    implementation of the Magnus chain) to 1e-14 relative."""
    from torchpvs.compiled_load import load_work
    from torchpvs.mechanics import compact_q, tip_pose
    force = torch.tensor([0.2, -0.1, 0.3], dtype=DT)
    sc = {"fig3": fig3(), "nested3": nested_scene(3, seed=1)}[case].with_load(
        tip_force=force.tolist())
    rot = torch.tensor(np.random.default_rng(1).uniform(-3, 3, (4, len(sc.tubes))), dtype=DT)
    probs = _captured_problems(sc, rot, SolverOptions())
    gen = torch.Generator().manual_seed(1)
    checked = 0
    for q, prob in probs[:3]:
        B = q.shape[0]
        qc = compact_q(q, prob.maps.cidx)
        qc = qc + 0.05 * torch.randn(qc.shape, generator=gen, dtype=DT) * prob.maps.qmask
        qp = torch.zeros_like(q).scatter(1, prob.maps.cidx, qc)
        tip = tip_pose(qp, prob.lay, prob.tab, prob.maps.pose)[0]
        LD = compiled._load_arrays(prob, DT, B)
        nc = qc.shape[1]
        for b in range(B):
            gW, HW = np.empty(nc), np.empty((nc, nc))
            args = (qc[b].numpy().copy(), *(a[b] for a in LD[:10]), LD[10], LD[11])
            W0 = load_work(*args, 0, gW, HW)
            W2 = load_work(*args, 2, gW, HW)
            assert W0 == W2
            W_ref = float(force @ tip[b])
            assert abs(W0 - W_ref) <= 1e-14 * abs(W_ref)
            checked += 1
    assert checked >= 4


def test_a_tip_force_in_float32_matches_the_eager_kernel_to_float32_precision():
    """float32 with a tip force: the compiled load terms run in float32 and converge where the
    eager kernel does, to its equilibrium within float32's resolution."""
    sc = fig3().with_load(tip_force=[0.1, -0.2, 0.05])
    rot = torch.tensor([[0.0, math.radians(a)] for a in range(0, 281, 40)], dtype=torch.float32)
    e32, c32 = (tp.solve(sc, rotation=rot, options=SolverOptions(kernel=k, dtype=torch.float32))
                for k in ("newton", "compiled"))
    assert c32.tip_position.dtype == torch.float32
    assert bool(c32.converged.all()) and torch.equal(e32.converged, c32.converged)
    assert float((e32.tip_position - c32.tip_position).abs().max()) < 1e-6


def test_the_compiled_kernel_is_registered_and_runs_solve_and_step(monkeypatch):
    """KERNELS["compiled"] replaces solve, step (the order estimate's Newton steps), the
    new-section step, pose and the force partials, and keeps the eager functions for the rest;
    the compiled solve and step are reached by a default automatic-order solve."""
    assert KERNELS["compiled"] is COMPILED
    for f in ("guess", "spd_solve"):
        assert getattr(COMPILED, f) is getattr(EAGER, f)
    calls = {"solve": 0, "step": 0}
    real_solve, real_step = compiled.solve, compiled.step

    def solve(*a, **k):
        out = real_solve(*a, **k)
        calls["solve"] += out is not None
        return out

    def step(*a, **k):
        out = real_step(*a, **k)
        calls["step"] += out is not None
        return out

    monkeypatch.setattr(compiled, "solve", solve)
    monkeypatch.setattr(compiled, "step", step)
    # the driver's rounds (the fused path, torchpvs.fused, runs the same element functions
    # in its own two calls: tests/test_fused.py)
    monkeypatch.setattr(solver_mod, "fused_solve", lambda *a, **k: None)
    tp.solve(fig3(), options=SolverOptions(kernel="compiled", order=None))
    assert calls["solve"] > 0 and calls["step"] > 0, calls


@pytest.mark.parametrize("scene", [fig3(), random_scene(1), random_scene(2),
                                   nested_scene(3, seed=1), nested_scene(4, seed=2)],
                         ids=["fig3", "random1", "random2", "nested3", "nested4"])
def test_the_compiled_tip_pose_is_the_magnus_chain(monkeypatch, scene):
    """Every tip pose a solve asks for (the solution's, the order estimate's step and the
    Magnus check's coarse pose, some with a leading dim of two coordinate sets): the compiled
    pose against torchpvs.mechanics.tip_pose on the same arguments, to 1e-14 (position [m],
    rotation entries, tube angles [rad])."""
    from torchpvs.mechanics import tip_pose
    worst = []

    def both_poses(q, lay, tab, const):
        ref = tip_pose(q, lay, tab, const)
        out = compiled.pose(q, lay, tab, const)
        worst.append(max(float((a - b).abs().max()) for a, b in zip(ref, out, strict=True)))
        return ref

    monkeypatch.setitem(KERNELS, "pose-check", EAGER._replace(pose=both_poses))
    rot = torch.tensor(np.random.default_rng(1).uniform(-3, 3, (16, len(scene.tubes))), dtype=DT)
    tp.solve(scene, rotation=rot, options=SolverOptions(kernel="pose-check"))
    assert worst and max(worst) < 1e-14, worst


def _kink_scenes():
    """(scene, insertion) pairs with a section cut exactly at a kink and next to it (the
    one-sided forces' re-solves and the cut order of coinciding cuts)."""
    sc = fig3(alpha2_deg=80.0)
    L1, L2 = sc.tubes[0].length, sc.tubes[1].length
    Ls1, Ls2 = sc.tubes[0].straight_length, sc.tubes[1].straight_length
    D1 = D1_FIG3 - 1e-3
    out = []
    for D in ([Ls1, 0.2085], [D1, Ls2], [D1, L2 - (L1 - D1)], [D1, Ls2 - (L1 - D1)]):
        for off in (0.0, 1e-6, -1e-6):
            j = 0 if D[0] == Ls1 else 1
            Dj = list(D)
            Dj[j] += off
            out.append((sc, Dj))
    return out


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_compiled_force_partials_are_the_closed_form(monkeypatch, dtype):
    """Every closed-form force evaluation a solve makes (the equilibrium's and its kink
    sides'), and the same at coordinates off the equilibrium: the compiled partials against
    torchpvs.forces.closed_form_partials on the same arguments (relative 1e-12 in float64,
    1e-5 in float32), on the suite's scenes and at kinks."""
    from torchpvs.forces import closed_form_partials
    worst = []
    noise = torch.Generator().manual_seed(0)

    def check(q, lay, tubes, tab, disc, const=None):
        ref = closed_form_partials(q, lay, tubes, tab, disc, const)
        q_off = q + 0.3 * torch.randn(q.shape, generator=noise, dtype=q.dtype) * lay.qmask
        for qq, r in ((q, ref), (q_off, closed_form_partials(q_off, lay, tubes, tab, disc))):
            out = compiled.partials(qq, lay, tubes, tab)
            assert out[0].dtype == dtype
            worst.append(max(float((a - b).abs().max() / (a.abs().max() + 1e-3))
                             for a, b in zip(r, out, strict=True)))
        return ref

    monkeypatch.setitem(KERNELS, "partials-check", EAGER._replace(partials=check))
    opts = SolverOptions(kernel="partials-check", dtype=dtype)
    for scene in (fig3(), random_scene(1), random_scene(2), nested_scene(3, seed=1),
                  nested_scene(4, seed=2)):
        rot = np.random.default_rng(1).uniform(-3, 3, (8, len(scene.tubes)))
        tp.solve(scene, rotation=torch.tensor(rot, dtype=dtype), options=opts)
    for scene, D in _kink_scenes():
        tp.solve(scene, insertion=torch.tensor(D, dtype=dtype), options=opts)
    assert len(worst) >= 30, len(worst)
    assert max(worst) < (1e-12 if dtype == torch.float64 else 1e-5), max(worst)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_compiled_actuation_rows_are_the_autograd_ones(dtype):
    """The actuator stiffness's rows ``U_xq, U_xD, U_xalpha`` for the insertions and for all
    actuators (compiled: a complex step of the force partials per actuator) against one
    reverse pass of autograd through
    torchpvs.forces.closed_form_partials (the eager kernel's), at equilibria and at coordinates
    off them, on the suite's scenes (2-4 tubes, random robots) and next to kinks: relative
    1e-11 in float64, 1e-5 in float32; the layout's coordinate masks identical."""
    from torchpvs.forces import actuation_rows
    from torchpvs.kernel import _compiled_actuation_rows
    worst = []
    noise = torch.Generator().manual_seed(0)
    cases = [(scene, None) for scene in (fig3(), random_scene(1), random_scene(2),
                                         nested_scene(3, seed=1), nested_scene(4, seed=2))]
    cases += [(scene, D) for scene, D in _kink_scenes()[1::3]]
    for scene, D in cases:
        rot = np.random.default_rng(1).uniform(-3, 3, (6, len(scene.tubes)))
        kw = {} if D is None else {"insertion": torch.tensor(D, dtype=dtype).expand(6, -1)}
        eq = tp.solve(scene, rotation=torch.tensor(rot, dtype=dtype),
                      options=SolverOptions(dtype=dtype), **kw)
        ctx, info = eq.context, eq.context.implicit
        q = eq.q.detach()
        q_off = q + 0.2 * torch.randn(q.shape, generator=noise, dtype=dtype) * info.qmask
        for qq, rotations in ((q, False), (q_off, False), (q_off, True)):
            args = (qq, ctx.tubes, ctx.insertion, ctx.rotation, info.loaded, info.tab, info.disc,
                    rotations)
            ref, out = actuation_rows(*args), _compiled_actuation_rows(*args)
            assert torch.equal(ref[3], out[3])
            assert all(o.dtype == dtype and o.shape == r.shape
                       for o, r in zip(out[:3], ref[:3], strict=True))
            qm = ref[3][:, None]
            for r, o in zip((ref[0] * qm, *ref[1:3]), (out[0] * qm, *out[1:3]), strict=True):
                worst.append(float((r - o).abs().max() / r.abs().max()))
    assert len(worst) >= 3 * 3 * len(cases)
    assert max(worst) < (1e-11 if dtype == torch.float64 else 1e-5), max(worst)


def test_the_actuator_stiffness_is_the_same_on_both_kernels():
    """``actuator_stiffness`` of the same equilibria solved on the eager and the compiled
    kernel (which take the actuator rows from autograd and from the complex step), the kink
    sides and a base at the orifice included, to 1e-9 relative."""
    from torchpvs.jacobians import actuator_stiffness
    rot = torch.tensor(np.random.default_rng(3).uniform(-3, 3, (4, 2)), dtype=DT)
    # [0.0, 0.15]: a base at the orifice, every row from the kernel (no guide twist row)
    for scene, D in [(fig3(), [0.05, 0.15]), (fig3(), [0.0, 0.15]), *_kink_scenes()[::2]]:
        eqs = both(scene, insertion=torch.tensor(D, dtype=DT).expand(4, 2), rotation=rot)
        Ke, Kc = (actuator_stiffness(e) for e in eqs)
        np.testing.assert_allclose(Kc.numpy(), Ke.numpy(), rtol=1e-9,
                                   atol=1e-9 * float(Ke.abs().max()))


def test_the_compiled_load_rows_are_the_autograd_ones():
    """``compiled.load_rows`` (a fourth-order central difference of the exact tip partials at
    layouts moved along their slopes) against the double backward of ``-F . p`` through a
    fresh layout and ``mechanics.tip_pose``: every row of ``U_xq`` and ``U_xx`` along the
    insertions and the rotations, at loaded Fig. 3 equilibria off and at the kink of its
    default insertion, and on a random robot, to 1e-10 of the largest entry (measured about
    3e-13)."""
    from torchpvs.mechanics import tip_pose
    from torchpvs.sections import build_layout
    cases = [(fig3(), [0.05, 0.15], [0.3, -0.1, 0.05]),
             (fig3(), [D1_FIG3, 0.2085], [0.0, 0.2, -0.3]),
             (nested_scene(3), None, [0.1, 0.2, 0.1])]
    for scene, D0, F0 in cases:
        kw = {} if D0 is None else {"insertion": torch.tensor([D0], dtype=DT)}
        F = torch.tensor([F0], dtype=DT)
        eq = tp.solve(scene, tip_force=F, **kw)
        ctx, info = eq.context, eq.context.implicit
        D, A, q = ctx.insertion.detach(), ctx.rotation.detach() + 0.4, eq.q.detach()
        N = D.shape[1]
        zero = torch.zeros(1, 3, dtype=DT)
        with torch.no_grad():
            lay = build_layout(ctx.tubes, D, A, zero, zero, info.loaded, info.disc)
        Gq, XD, XA = compiled.load_rows(q, lay, ctx.tubes, info.tab, F, rotations=True)
        qr, Dr, Ar = (t.clone().requires_grad_(True) for t in (q, D, A))
        p = tip_pose(qr, build_layout(ctx.tubes, Dr, Ar, zero, zero, info.loaded, info.disc),
                     info.tab)[0]
        gD, gA = torch.autograd.grad(-(F * p).sum(), (Dr, Ar), create_graph=True)
        ref, got = [], []
        for d in range(2 * N):
            out = gD[0, d] if d < N else gA[0, d - N]
            rq, rD, rA = torch.autograd.grad(out, (qr, Dr, Ar), retain_graph=True)
            ref.append(torch.cat([rq[0] * info.qmask[0], rD[0], rA[0]]))
            got.append(torch.cat([Gq[0, d] * info.qmask[0], XD[0, d], XA[0, d]]))
        ref, got = torch.stack(ref), torch.stack(got)
        np.testing.assert_allclose(got.numpy(), ref.numpy(), rtol=0,
                                   atol=1e-10 * float(ref.abs().max()))
        # float32 inputs: computed in float64, returned in float32
        lay32 = type(lay)._make(t.float() if t.is_floating_point() else t for t in lay)
        out32 = compiled.load_rows(q.float(), lay32, ctx.tubes.map(lambda t: t.float()),
                                   info.disc.tables(torch.float32, q.device), F.float(), True)
        assert all(t.dtype == torch.float32 for t in out32)
        np.testing.assert_allclose(out32[0][0].double().numpy(), Gq[0].numpy(), rtol=0,
                                   atol=1e-5 * float(ref.abs().max()))


def test_the_loaded_actuator_stiffness_is_the_same_on_both_kernels(monkeypatch):
    """``actuator_stiffness`` and the control Jacobians of equilibria under a dead tip force
    (the robust environment's plants) on the eager kernel (a double backward through the
    loaded potential) and the compiled one (the elastic rows' complex step plus the load's
    rows), the kink sides and a base at the orifice (every row from the kernel) included,
    to 1e-9 relative."""
    from torchpvs.jacobians import actuator_stiffness
    calls = []
    real = compiled.load_rows
    monkeypatch.setattr(compiled, "load_rows",
                        lambda *a, **k: calls.append(a[4].shape[0]) or real(*a, **k))
    rng = np.random.default_rng(5)
    rot = torch.tensor(rng.uniform(-3, 3, (4, 2)), dtype=DT)
    F = torch.tensor(rng.normal(size=(4, 3)) * 0.3, dtype=DT)
    for scene, D in [(fig3(), [0.05, 0.15]), (fig3(), [0.0, 0.15]), *_kink_scenes()[::3]]:
        eqs = both(scene, insertion=torch.tensor(D, dtype=DT).expand(4, 2), rotation=rot,
                   tip_force=F)
        assert all(bool(e.context.implicit.with_load) for e in eqs)
        calls.clear()
        Ke, Kc = (actuator_stiffness(e) for e in eqs)
        assert calls, "the compiled stiffness took no load rows"
        np.testing.assert_allclose(Kc.numpy(), Ke.numpy(), rtol=1e-9,
                                   atol=1e-9 * float(Ke.abs().max()))
    Je, Jc = (e.jacobians(compliance=False) for e in eqs)
    np.testing.assert_allclose(Jc.tip_jacobian.numpy(), Je.tip_jacobian.numpy(), rtol=1e-9,
                               atol=1e-9 * float(Je.tip_jacobian.abs().max()))


def test_cos_sin_of_a_complex_step_is_numbas_complex_cos_and_sin_bit_for_bit():
    """``compiled.cos_sin`` (the complex steps' angles) against numba's own ``np.cos`` and
    ``np.sin`` of complex arguments, element by element: equal bit for bit with the complex
    steps' imaginary parts (1e-30..1e-9, any real part) and beyond them (1e-9..1, where it
    falls back to the complex functions); real arguments give math.cos and math.sin."""
    from numba import njit

    @njit
    def both(z, ref, new):
        for i in range(z.shape[0]):
            ref[i, 0], ref[i, 1] = np.cos(z[i]), np.sin(z[i])
            new[i, 0], new[i, 1] = compiled.cos_sin(z[i])

    rng = np.random.default_rng(0)
    a = rng.uniform(-50, 50, 20000)
    b = rng.choice([-1.0, 1.0], 20000) * 10.0 ** rng.uniform(-30, 0, 20000)
    z = a + 1j * b
    ref, new = np.empty((len(z), 2), complex), np.empty((len(z), 2), complex)
    both(z, ref, new)
    assert np.array_equal(ref.view(np.float64), new.view(np.float64))
    r_ref, r_new = np.empty((len(a), 2)), np.empty((len(a), 2))
    both(a, r_ref, r_new)
    assert np.array_equal(r_new, np.stack([np.cos(a), np.sin(a)], -1))


@pytest.mark.parametrize("angle", [0.0, 1e-7, 0.05, 0.3162, 0.3163, 1.0, 3.0])
def test_the_se3_right_jacobian_is_the_derivative_of_the_matrix_exponential(angle):
    """``compiled.se3_right_jacobian`` (the tip partials' chain): ``exp(om)^-1 d exp(om + t
    e_a)/dt = [J_r e_a]^`` against forward-mode autograd of ``torch.linalg.matrix_exp`` of the
    4 x 4 twist matrix (an independent exponential), on both sides of its series switch
    (``|omega|^2 = 0.1``) and at zero rotation."""
    rng = np.random.default_rng(int(angle * 1e4))
    w = rng.normal(size=3)
    w *= angle / np.linalg.norm(w)
    om = np.concatenate([w, rng.normal(size=3)])

    def hat(x):
        Z = torch.zeros(4, 4, dtype=torch.float64)
        Z[0, 1], Z[0, 2], Z[1, 2] = -x[2], x[1], -x[0]
        Z[1, 0], Z[2, 0], Z[2, 1] = x[2], -x[1], x[0]
        Z[:3, 3] = x[3:]
        return Z

    x = torch.tensor(om)
    E = torch.linalg.matrix_exp(hat(x))
    dE = torch.func.jacfwd(lambda y: torch.linalg.matrix_exp(hat(y)))(x)     # (4, 4, 6)
    M = torch.linalg.solve(E, dE.permute(2, 0, 1))                             # (6, 4, 4)
    ref_w = torch.stack([M[:, 2, 1], M[:, 0, 2], M[:, 1, 0]], 0).numpy()      # columns a
    ref_v = M[:, :3, 3].T.numpy()
    Jw, Q = np.empty((3, 3)), np.empty((3, 3))
    compiled.se3_right_jacobian(om, 1e-6, Jw, Q)
    got_w = np.concatenate([Jw, np.zeros((3, 3))], 1)
    got_v = np.concatenate([Q, Jw], 1)
    np.testing.assert_allclose(got_w, ref_w, rtol=0, atol=1e-13)
    np.testing.assert_allclose(got_v, ref_v, rtol=0, atol=1e-13 * (1 + np.abs(om).max()))


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_the_compiled_tip_partials_are_the_autograd_ones(dtype):
    """The tip twist's partials ``P_q, P_D, P_alpha`` (compiled: a complex step of the tip pose
    as a function of the layout, per coordinate and actuator) against one reverse pass of
    autograd through a fresh layout and torchpvs.mechanics.tip_pose (the eager kernel's), at
    equilibria and at coordinates off them, unloaded and on a loaded layout (coordinates on the
    distal sections), on the suite's scenes (2-4 tubes, random robots) and next to kinks:
    relative 1e-11 in float64, 1e-5 in float32."""
    from torchpvs.kernel import _compiled_tip_partials
    from torchpvs.mechanics import tip_partials
    worst = []
    noise = torch.Generator().manual_seed(0)
    cases = [(scene, None) for scene in (fig3(), random_scene(1), random_scene(2),
                                         nested_scene(3, seed=1), nested_scene(4, seed=2))]
    cases += [(scene, D) for scene, D in _kink_scenes()[1::3]]
    for (scene, D), force in zip(cases, [0.0, 0.3] * len(cases), strict=False):
        rot = np.random.default_rng(1).uniform(-3, 3, (6, len(scene.tubes)))
        kw = {} if D is None else {"insertion": torch.tensor(D, dtype=dtype).expand(6, -1)}
        eq = tp.solve(scene, rotation=torch.tensor(rot, dtype=dtype),
                      tip_force=torch.tensor([force, 0.0, 0.0], dtype=dtype),
                      options=SolverOptions(dtype=dtype), **kw)
        ctx, info = eq.context, eq.context.implicit
        assert bool(info.loaded.any()) == (force > 0)
        q = eq.q.detach()
        q_off = q + 0.2 * torch.randn(q.shape, generator=noise, dtype=dtype) * info.qmask
        for qq in (q, q_off):
            args = (qq, ctx.tubes, ctx.insertion, ctx.rotation, info.loaded, info.tab, info.disc)
            ref, out = tip_partials(*args), _compiled_tip_partials(*args)
            assert all(o.dtype == dtype and o.shape == r.shape
                       for o, r in zip(out, ref, strict=True))
            for r, o in zip(ref, out, strict=True):
                worst.append(float((r - o).abs().max() / r.abs().max()))
    assert len(worst) >= 3 * 2 * len(cases)
    assert max(worst) < (1e-11 if dtype == torch.float64 else 1e-5), max(worst)



def test_the_force_contracted_tip_partials_are_the_full_ones_contracted():
    """``compiled.tip_force_partials_q_one`` (the load rows' ``F . P_q``, contracted per Magnus
    step) against the full ``P_q`` of ``compiled.tip_partials`` (which the test above holds to
    autograd) contracted with the same force, on the suite's scenes, at equilibria and off
    them: equal to round-off (1e-13 of the largest entry)."""
    from torchpvs.kernel import _on_layout
    rng = np.random.default_rng(3)
    worst = []
    for scene in (fig3(), random_scene(1), nested_scene(3, seed=1), nested_scene(4, seed=2)):
        rot = rng.uniform(-3, 3, (4, len(scene.tubes)))
        eq = tp.solve(scene, rotation=torch.tensor(rot), tip_force=torch.tensor([0.2, 0.1, 0.0]))
        ctx, info = eq.context, eq.context.implicit
        q = eq.q.detach()
        for qq in (q, q + 0.1 * torch.from_numpy(rng.normal(size=q.shape)) * info.qmask):
            (Pq, _, _), lay = _on_layout(compiled.tip_partials, qq, ctx.tubes, ctx.insertion,
                                         ctx.rotation, info.loaded, info.disc, None, info.tab)
            qa, arrays = compiled._pose_arrays(qq, lay, ctx.tubes, info.tab)
            (qmask, D, _L, _Ls, coef, tau, psi0, start, h, present, curved, presc, _tt, xm,
             phi, Qb) = arrays
            for b in range(qa.shape[0]):
                F = rng.normal(size=3)
                g = np.empty(qa.shape[1])
                compiled.tip_force_partials_q_one(
                    qa[b], qmask[b], D[b], coef[b], tau[b], psi0[b], start[b], h[b],
                    present[b], curved[b], presc[b], xm, phi, Qb, F, g)
                ref = F @ Pq[b, :3].numpy()
                worst.append(float(np.abs(g - ref).max() / np.abs(ref).max()))
    assert len(worst) == 4 * 2 * 4
    assert max(worst) < 1e-13, max(worst)

def test_the_control_jacobians_are_the_same_on_both_kernels():
    """``control_jacobians`` (stiffness, tip Jacobian, tip compliance) of the same equilibria
    solved on the eager and the compiled kernel, which take the tip partials from autograd and
    from the complex step, the kink sides included, to 1e-9 relative."""
    from torchpvs.jacobians import control_jacobians
    rot = torch.tensor(np.random.default_rng(4).uniform(-3, 3, (3, 2)), dtype=DT)
    for scene, D in [(fig3(), [0.05, 0.15]), *_kink_scenes()[::4]]:
        eqs = both(scene, insertion=torch.tensor(D, dtype=DT).expand(3, 2), rotation=rot)
        je, jc = (control_jacobians(e) for e in eqs)
        for name in ("actuator_stiffness", "tip_jacobian", "tip_compliance"):
            a, b = getattr(je, name), getattr(jc, name)
            np.testing.assert_allclose(b.numpy(), a.numpy(), rtol=1e-9,
                                       atol=1e-9 * float(a.abs().max()), err_msg=name)


def test_the_compiled_new_section_step_is_the_eager_one(monkeypatch):
    """The new-section step of the one-sided forces (a section of length 1e-7 m appearing at a
    kink, solved for with the rest held): the compiled step against kernel.new_section_step,
    the same rows applied and the same coordinates to 1e-12 (relative)."""
    from torchpvs.kernel import VANISHING, new_section_step
    seen = []

    def check(q, prob, new, length):
        ref = new_section_step(q, prob, new, length)
        out = compiled.section_step(q, prob, new, VANISHING * length)
        assert torch.equal(ref[1], out[1])
        seen.append((int(ref[1].sum()),
                     float((ref[0] - out[0]).abs().max() / (ref[0].abs().max() + 1e-30))))
        return ref

    monkeypatch.setitem(KERNELS, "section-check", EAGER._replace(section_step=check))
    rot = torch.tensor(np.random.default_rng(2).uniform(-3, 3, (8, 2)), dtype=DT)
    for scene, D in _kink_scenes():
        tp.solve(scene, insertion=torch.tensor(D, dtype=DT).expand(8, 2), rotation=rot,
                 options=SolverOptions(kernel="section-check"))
    assert sum(applied for applied, _ in seen) >= 12, seen
    assert max(d for _, d in seen) < 1e-12, seen


def test_a_one_thread_batch_solve_launches_no_numba_thread_pool():
    """With one torch thread a batch of >= 8 runs the serial loop and never starts numba's
    thread pool: its OpenMP worker would spin a second core for the rest of the process (a
    one-thread training used 1.8 cores). In a fresh process, as a training run starts; 64
    rows, so that the driver's rounds solve (the fused path takes up to 32, serially)."""
    code = ("import torch, numba, torchpvs; torch.set_num_threads(1); "
            "sc = torchpvs.load_scene('renda2021_fig3'); "
            "r = torchpvs.solve(sc, rotation=torch.rand(64, 2, dtype=torch.float64), "
            "options=torchpvs.SolverOptions(kernel='compiled')); "
            "assert bool(r.converged.all())\n"
            "try:\n    print('layer', numba.threading_layer())\n"
            "except ValueError:\n    print('no pool')")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True, env=dict(os.environ, OMP_NUM_THREADS="1"))
    assert out.stdout.split()[-2:] == ["no", "pool"], out.stdout


def test_each_kernel_is_compiled_once_for_the_default_solve_and_the_tracker():
    """First use is numba's compile time (docs/performance.md, *First use*): a kernel called
    with an int literal is compiled once per literal value and once more for a variable, and
    a readonly array (a broadcast view) is another type than a writable one, so either
    compiles a kernel, with everything it calls, a second time. The arrays the fused solve and
    the tracker pass are writable and the constant orders and components are numba int64
    (whatever the cache holds); where this process compiled the kernels (an empty cache: a
    function loaded from the cache brings its callees' code, and their dispatchers stay
    empty), no signature of the energy, the precurvature polynomials, the layout or the solve
    core holds a literal or a readonly array after a solve, its control step and a tracker
    step."""
    import numba

    from torchpvs import compiled_layout, fused, tracker

    scene = fig3()
    eq = tp.solve(scene, rotation=torch.tensor([0.0, 1.0], dtype=DT))
    eq.jacobians(compliance=False)
    tr = tp.Tracker(scene, rotation=np.array([0.0, 1.0]), initial=eq)
    tr.step(tr._D.copy(), np.array([0.0, 1.02]), jacobians=True, forces=True, margin=True)
    for a in (*fused._tube_arrays(eq.context.tubes, 1), *tr._tube_args,
              *tr._tube_args_for(3)[0]):
        assert numba.typeof(a).mutable and a.flags.c_contiguous
    for c in (compiled._E0, compiled._E2, compiled._E3, compiled._C0, compiled._C1,
              compiled._C2, compiled_layout._C0, compiled_layout._C1):
        assert numba.typeof(c) == numba.int64
    kernels = (compiled.evaluate, compiled.total, compiled.horner, compiled.horner_derivative,
               compiled_layout._horner_zero, compiled_layout.layout_maps_arrays,
               tracker.solve_core)
    for k in kernels:
        for sig in k.signatures:
            for t in sig:
                name = f"{k.py_func.__name__}{sig}"
                assert "Literal" not in str(t) and "readonly" not in str(t), name
