"""PVS solver against independent references: closed forms, physics identities, finite
differences, and (in test_pvs_vs_reference.py) the separately implemented standard model."""

from __future__ import annotations

import math

import pytest
import torch
from conftest import E, G, two_tubes

import torchpvs as tp
from torchpvs.scene import Actuation, Scene, Tube
from torchpvs.sections import n_coordinates


def arc_tip(kappa: float, L: float) -> torch.Tensor:
    """Planar circular arc bending toward +x (u*_y > 0, docs/conventions.md)."""
    return torch.tensor([(1 - math.cos(kappa * L)) / kappa, 0.0, math.sin(kappa * L) / kappa],
                        dtype=torch.float64)


@pytest.mark.parametrize("alpha2", [0.0, math.pi])
def test_torsionless_closed_form_eq31(alpha2):
    """Paper eq. (31): fully overlapping tubes with aligned (or opposed) planar precurvatures
    carry no torsion, and the shared curvature is k = (EI1 k1* + EI2 k2*) / (EI1 + EI2)."""
    L = 0.05  # short enough that the opposed configuration is stable
    sc = two_tubes(L=L, alpha2=alpha2)
    EI1, EI2 = (t.bending_stiffness for t in sc.tubes)
    k2 = 13.8 * math.cos(alpha2)
    kappa = (EI1 * 9.9 + EI2 * k2) / (EI1 + EI2)
    eq = tp.solve(sc, options=tp.SolverOptions(order=2))
    assert bool(eq.converged[0]) and bool(eq.stable[0])
    ref = arc_tip(kappa, L)
    err = (eq.tip_position[0] - ref).norm() / ref.norm()
    assert err < 1e-10, err


def test_configurational_force_single_tube():
    """A precurved tube sliding out of a straight frictionless guide feels 1/2 EI kappa^2
    (Bigoni et al. 2015; docs/physics.md): retracting stores 1/2 EI kappa^2 per metre in the
    guide."""
    kappa = 20.0
    t = Tube(E=E, G=G, inner_diameter=0.0, outer_diameter=1.6e-3,
             straight_length=0.0, curved_length=0.2,
             precurvature=((), (kappa,), ()), name="rod")
    sc = Scene((t,), Actuation((0.05,), (0.3,)))
    eq = tp.solve(sc)
    expected = 0.5 * t.bending_stiffness * kappa**2
    assert abs(float(eq.actuation_forces[0, 0]) - expected) / expected < 1e-6
    assert abs(float(eq.actuation_torques[0, 0])) < 1e-12


def test_rotating_all_tubes_rotates_tip_about_z():
    sc = tp.load_scene("renda2021_fig3")
    phi = 0.7
    base = torch.tensor(sc.actuation.rotation, dtype=torch.float64)
    eq0 = tp.solve(sc)
    eq1 = tp.solve(sc, rotation=base + phi)
    Rz = torch.tensor([[math.cos(phi), -math.sin(phi), 0], [math.sin(phi), math.cos(phi), 0],
                       [0, 0, 1]], dtype=torch.float64)
    assert torch.allclose(eq1.tip_position[0], Rz @ eq0.tip_position[0], atol=1e-10)
    assert torch.allclose(eq1.tip_rotation[0], Rz @ eq0.tip_rotation[0], atol=1e-9)


def test_sum_of_torques_vanishes():
    """Rotating all tubes together costs no energy: sum_j tau_alpha_j = 0 (docs/physics.md)."""
    sc = tp.load_scene("renda2021_fig3")
    rot = torch.tensor([[0.0, 0.5], [0.3, 2.0], [1.0, -1.0]], dtype=torch.float64)
    eq = tp.solve(sc, rotation=rot)
    tau = eq.actuation_torques
    assert (tau.sum(-1).abs() <= 1e-9 * tau.abs().amax(-1)).all()


def test_forces_match_finite_differences_of_equilibrium_energy():
    """tau = dU*/d(D, alpha) (docs/conventions.md): central differences of the equilibrium
    energy."""
    sc = two_tubes(lengths=(0.15, 0.22), straight=(0.05, 0.1), D=(0.03, 0.06), alpha2=1.0)
    opts = tp.SolverOptions(order=5)
    eq = tp.solve(sc, options=opts)
    D0 = torch.tensor(sc.actuation.insertion, dtype=torch.float64)
    A0 = torch.tensor(sc.actuation.rotation, dtype=torch.float64)
    h = 1e-6
    for j in range(2):
        dD = torch.zeros(2, dtype=torch.float64)
        dD[j] = h
        Up = tp.solve(sc, insertion=D0 + dD, options=opts, initial=eq).energy
        Um = tp.solve(sc, insertion=D0 - dD, options=opts, initial=eq).energy
        fd = float((Up - Um) / (2 * h))
        assert abs(fd - float(eq.actuation_forces[0, j])) <= 1e-6 * max(1.0, abs(fd)), (j, fd)
        Up = tp.solve(sc, rotation=A0 + dD, options=opts, initial=eq).energy
        Um = tp.solve(sc, rotation=A0 - dD, options=opts, initial=eq).energy
        fd = float((Up - Um) / (2 * h))
        assert abs(fd - float(eq.actuation_torques[0, j])) <= 1e-6 * max(1e-3, abs(fd)), (j, fd)


@pytest.mark.parametrize("force", [1e-4, 1e-3])
def test_small_tip_force_matches_euler_bernoulli(force):
    """Cantilever deflection F L^3 / (3 EI) for small loads (elastica -> Euler–Bernoulli)."""
    t = Tube(E=E, G=G, inner_diameter=0.0, outer_diameter=1.6e-3,
             straight_length=0.1, curved_length=0.0,
             precurvature=((), (), ()), name="rod")
    sc = Scene((t,), Actuation((0.0,), (0.0,)))
    eq = tp.solve(sc, tip_force=[0.0, force, 0.0], options=tp.SolverOptions(order=4))
    expected = force * 0.1**3 / (3 * t.bending_stiffness)
    assert abs(float(eq.tip_position[0, 1]) - expected) / expected < 1e-3
    assert abs(float(eq.tip_position[0, 0])) < 1e-12


def test_pure_tip_moment_bends_into_circle():
    """A straight rod under a tip moment M has curvature M / EI everywhere (exact elastica)."""
    t = Tube(E=E, G=G, inner_diameter=0.0, outer_diameter=1.6e-3,
             straight_length=0.1, curved_length=0.0,
             precurvature=((), (), ()), name="rod")
    sc = Scene((t,), Actuation((0.0,), (0.0,)))
    M = 5e-3
    eq = tp.solve(sc, tip_moment=[0.0, M, 0.0], options=tp.SolverOptions(order=3))
    ref = arc_tip(M / t.bending_stiffness, 0.1)
    assert torch.allclose(eq.tip_position[0], ref, atol=1e-9)


def test_batch_equals_loop():
    sc = tp.load_scene("renda2021_fig3")
    rot = torch.tensor([[0.0, 0.3], [0.1, 1.2], [0.0, 2.5]], dtype=torch.float64)
    ins = torch.tensor([[0.0935, 0.2085], [0.09, 0.17], [0.08, 0.19]], dtype=torch.float64)
    opts = tp.SolverOptions(order=3)
    batch = tp.solve(sc, insertion=ins, rotation=rot, options=opts)
    for b in range(3):
        single = tp.solve(sc, insertion=ins[b], rotation=rot[b], options=opts)
        assert torch.allclose(batch.tip_position[b], single.tip_position[0], atol=1e-12)
        assert torch.allclose(batch.actuation_forces[b], single.actuation_forces[0], atol=1e-9)


def test_float32_matches_float64():
    sc = tp.load_scene("renda2021_fig3")
    rot = torch.tensor([[0.0, 0.5], [0.0, 1.5], [0.0, 2.5]], dtype=torch.float64)
    e64 = tp.solve(sc, rotation=rot, options=tp.SolverOptions(order=3))
    e32 = tp.solve(sc, rotation=rot.float(), options=tp.SolverOptions(order=3))
    assert e32.tip_position.dtype == torch.float32
    assert bool(e32.converged.all())
    assert (e32.tip_position.double() - e64.tip_position).norm(dim=-1).max() < 1e-4


def test_section3b_three_equilibria():
    """Section III-B: two stable mirror equilibria and an unstable symmetric one (paper Fig. 2).
    The symmetric one is reached with method='root' from the torsionless guess."""
    sc = tp.load_scene("renda2021_section3b")
    opts = tp.SolverOptions(order=5)
    stable = tp.solve(sc, options=opts)
    th = math.degrees(float(stable.relative_rotation_at_outer_tip[0, 0]))
    assert bool(stable.stable[0]) and 80 < abs(th) < 90
    mirror = tp.solve(sc, rotation=[0.0, math.pi], options=opts,
                      initial=_mirror(stable.q))
    assert bool(mirror.converged[0])
    th_m = math.degrees(float(mirror.relative_rotation_at_outer_tip[0, 0]))
    assert abs(th + th_m) < 1e-6 and bool(mirror.stable[0])
    saddle = tp.solve(sc, options=tp.SolverOptions(order=5, method="root"))
    assert bool(saddle.converged[0]) and not bool(saddle.stable[0])
    assert abs(abs(math.degrees(float(saddle.relative_rotation_at_outer_tip[0, 0]))) - 180) < 1e-6
    assert float(saddle.energy[0]) > float(stable.energy[0])


def _mirror(q: torch.Tensor) -> torch.Tensor:
    """Mirror a 2-tube solution about the x-z plane: u_x -> -u_x, torsions -> -torsions."""
    N = 2
    B, nq = q.shape
    X = q[:, N:].reshape(B, 2 * N, 2 + N, -1).clone()
    X[:, :, 0] *= -1
    X[:, :, 2:] *= -1
    return torch.cat([-q[:, :N], X.reshape(B, -1)], -1)


def test_order_selection_reports_error_estimate():
    """The automatic order meets the requested tip accuracy against a converged solve (order 8,
    64 Magnus steps), and its a posteriori estimate bounds the true error (measured: true error
    9.4e-8 m at estimate 9.7e-8 m for order 2; 4.2e-10 at 1.0e-9 for order 3)."""
    sc = tp.load_scene("renda2021_fig3")
    ref = tp.solve(sc, options=tp.SolverOptions(order=8, n_magnus=64))
    prev = None
    for acc in (1e-3, 1e-5, 1e-8, 1e-9):
        eq = tp.solve(sc, options=tp.SolverOptions(accuracy=acc))
        err = float((eq.tip_position - ref.tip_position).norm())
        est = float(eq.error_estimate[0])
        assert err <= acc and est <= acc, (acc, eq.order, err, est)
        assert err <= 1.5 * est + 1e-12, (acc, err, est)    # the estimate is not blind
        if prev is not None:
            assert prev.order <= eq.order and int(prev.dofs[0]) <= int(eq.dofs[0])
        prev = eq
    assert prev.order >= 3                                     # 1e-9 is beyond order 2


def test_magnus_step_count_check_bounds_the_pose_error():
    """The automatic Magnus count (docs/accuracy.md): kept when the tip moves less than
    accuracy/2 from half the steps, else doubled. Against the same order's tip with 128 steps
    (4th-order Magnus: ~1e-13 m off here; closed-form check in test_mechanics): the chosen
    count's pose error is within accuracy/2, the counts grow as the accuracy tightens, and the
    reported estimate is not below the pose error (its half-step check is an upper estimate)."""
    sc = tp.load_scene("renda2021_fig3")
    rot = torch.tensor([[0.0, a] for a in (0.3, 1.7, 3.0, 4.2)], dtype=torch.float64)
    counts = []
    for acc in (1e-5, 1e-7, 1e-9):
        fixed = tp.solve(sc, rotation=rot, options=tp.SolverOptions(
            order=3, accuracy=acc, compute_forces=False))
        fine = tp.solve(sc, rotation=rot, options=tp.SolverOptions(
            order=3, n_magnus=128, tol=1e-12, compute_forces=False))
        err = (fixed.tip_position - fine.tip_position).norm(dim=-1)
        assert bool((err <= acc / 2).all()), (acc, err)
        counts.append(fixed.context.discretization.n_magnus)
        auto = tp.solve(sc, rotation=rot, options=tp.SolverOptions(accuracy=acc,
                                                                   compute_forces=False))
        ref = tp.solve(sc, rotation=rot, options=tp.SolverOptions(
            order=auto.order, n_magnus=128, tol=1e-12, compute_forces=False))
        pose_err = (auto.tip_position - ref.tip_position).norm(dim=-1)
        assert bool((pose_err <= auto.error_estimate).all()), (acc, pose_err,
                                                               auto.error_estimate)
    assert counts[0] == 8 and counts == sorted(counts) and counts[-1] > 8, counts


def test_fully_retracted_tube_and_zero_length_sections():
    """A tube entirely in the guide contributes no coordinates; cuts that coincide make
    zero-length sections, which must not make the Hessian singular."""
    sc = two_tubes(lengths=(0.1, 0.15), straight=(0.05, 0.05), D=(0.12, 0.12))
    eq = tp.solve(sc)
    assert bool(eq.converged[0]) and bool(eq.stable[0])
    assert float(eq.tip_position[0, 2]) == pytest.approx(0.03, abs=1e-3)
    # Inner tube's transition exactly at the outer tube's end (coinciding cuts).
    sc2 = two_tubes(lengths=(0.1, 0.2), straight=(0.0, 0.1), D=(0.0, 0.0))
    eq2 = tp.solve(sc2)
    assert bool(eq2.converged[0]) and bool(eq2.stable[0])


def test_continuity_across_section_cut():
    """A 1 um insertion step that moves a cut (the inner transition past the outer end) moves
    the tip by about 1 um, not by a jump."""
    sc = two_tubes(lengths=(0.1, 0.2), straight=(0.0, 0.1), D=(0.0, 0.0), alpha2=0.8)
    opts = tp.SolverOptions(order=4)
    a = tp.solve(sc, insertion=[0.0, 0.0], options=opts)
    b = tp.solve(sc, insertion=[0.0, 1e-6], options=opts)
    assert float((a.tip_position - b.tip_position).norm()) < 1e-5


def test_nonconvergence_is_reported_not_nan():
    sc = tp.load_scene("renda2021_fig3")
    eq = tp.solve(sc, rotation=[0.0, 2.0],
                  options=tp.SolverOptions(order=3, max_iter=1, on_failure="ignore"))
    assert not bool(eq.converged[0])
    assert "residual" in eq.reason[0]
    with pytest.raises(tp.SolverError):
        tp.solve(sc, rotation=[0.0, 2.0],
                 options=tp.SolverOptions(order=3, max_iter=1, on_failure="raise"))


def test_no_grad_solve_returns_ordinary_tensors_and_leaves_caches_usable():
    """A solve without gradients runs in inference mode internally; what it returns (and the
    context its methods use) are ordinary tensors: they can be modified in place and enter
    autograd graphs. A solve called inside the caller's own inference mode, and a loaded one
    (whose load Hessian uses torch.func), give the same numbers, and a later differentiable
    solve on the same (cached) plan still has gradients."""
    scene = tp.load_scene("renda2021_fig3")
    force = torch.tensor([0.0, 0.05, 0.0], dtype=torch.float64)
    eq = tp.solve(scene, tip_force=force)
    for name in ("q", "tip_position", "actuation_forces", "actuation_torques", "stable"):
        assert not getattr(eq, name).is_inference(), name
    assert not any(t.is_inference() for t in eq.context.layout)
    w = torch.ones(3, dtype=torch.float64, requires_grad=True)
    (eq.tip_position[0] * w).sum().backward()            # saves tip_position for backward
    assert torch.equal(w.grad, eq.tip_position[0])
    J = eq.jacobians()                                   # autograd on the stored context
    assert torch.isfinite(J.tip_jacobian).all()
    eq.q.mul_(1.0)                                       # in place: allowed
    with torch.inference_mode():
        eq_inf = tp.solve(scene, tip_force=force)     # (inference tensors there, as torch's)
    assert torch.allclose(eq_inf.tip_position, eq.tip_position, rtol=0, atol=1e-15)
    rot = torch.tensor(scene.actuation.rotation, dtype=torch.float64, requires_grad=True)
    eq_g = tp.solve(scene, rotation=rot, tip_force=force)
    eq_g.tip_position[0, 0].backward()
    assert rot.grad is not None and torch.isfinite(rot.grad).all() and rot.grad.abs().sum() > 0
    assert torch.allclose(eq_g.tip_position.detach(), eq.tip_position, rtol=0, atol=1e-12)


def test_kernel_returns_the_residual_and_hessian_at_its_solution():
    """The kernel works on compact coordinates and expands its outputs: the residual and the
    Hessian it reports are those of the returned coordinates, recomputed here from scratch."""
    from torchpvs import newton
    from torchpvs.implicit import full_hessian
    from torchpvs.mechanics import compact_q, elastic_grad_hess, expand_hessian, expand_q
    from torchpvs.plan import plan_for

    scene = tp.load_scene("renda2021_fig3")
    rot = torch.tensor(scene.actuation.rotation, dtype=torch.float64)
    opts = tp.SolverOptions(order=2, n_magnus=8, compute_forces=False)
    eq0 = tp.solve(scene, rotation=rot, options=opts)
    eq = tp.solve(scene, rotation=rot + torch.tensor([0.0, 0.02], dtype=torch.float64),
                  options=opts, initial=eq0)
    info = eq.context.implicit
    plan = plan_for(scene, torch.float64, torch.device("cpu"))
    ctx = eq.context
    lay, maps = plan.layout(plan.tubes, ctx.insertion, ctx.rotation, ctx.tip_force,
                            ctx.tip_moment, info.loaded, ctx.discretization, eq.q.shape[-1])
    qc = compact_q(eq.q, maps.cidx)
    assert torch.equal(expand_q(qc, maps.cidx, eq.q.shape[-1]), eq.q)
    g, H = elastic_grad_hess(qc, maps)
    H.diagonal(dim1=-2, dim2=-1).add_(1.0 - maps.qmask)
    L = float(lay.ell.amax() + lay.D.amax())
    res, _ = newton.scaled_residual(g, H, torch.tensor([L], dtype=torch.float64))
    assert bool(eq.converged.all()) and float(res) < tp.SolverOptions().tol
    assert float(eq.residual_norm) == pytest.approx(float(res), rel=1e-6, abs=1e-15)
    H = expand_hessian(H, maps.cidx, eq.q.shape[-1])
    assert torch.allclose(full_hessian(info), H, rtol=0, atol=1e-13 * float(H.abs().max()))


@pytest.mark.parametrize("method", ["minimize", "root"])
def test_stable_is_the_smallest_scaled_eigenvalue_above_threshold(method):
    """``stable`` (from the kernel's saddle-test factorization with ``minimize``, from a separate
    Cholesky otherwise) agrees elementwise with its definition, the smallest eigenvalue of the
    Jacobi-scaled stiffness above ``newton.stability_threshold`` (``eigvalsh``), over a batch of
    section III-B equilibria crossing into the multistable range (unstable ones with root)."""
    from torchpvs.newton import stability_threshold

    scene = tp.load_scene("renda2021_section3b")
    a2 = torch.linspace(0.0, math.radians(190.0), 24, dtype=torch.float64)
    rot = torch.stack([torch.zeros_like(a2), a2], -1)
    eq = tp.solve(scene, rotation=rot,
                  options=tp.SolverOptions(method=method, order=3, on_failure="ignore"))
    ok = eq.converged
    assert int(ok.sum()) >= 20
    ev = eq.min_stiffness_eigenvalue
    assert torch.equal(eq.stable[ok], ev[ok] > stability_threshold(torch.float64))
    if method == "root":
        assert not bool(eq.stable[ok].all())     # the sweep does reach unstable equilibria


def test_rotation_predictor_is_a_first_order_step_along_the_branch():
    """Implicit function theorem: along a branch dq*/dalpha = -H^-1 U_q,alpha. The predictor
    (predictor.rotation_predictor, from the warm start's Hessian alone) must land O(dalpha^2)
    from the new equilibrium: for a 2 deg step on the Fig. 3 and three-tube robots its error is
    below 5% of the warm start's own distance, and halving the step divides it by about 4."""
    from envs.robots import rvim_three_tube
    from torchpvs.plan import tube_tensors
    from torchpvs.predictor import rotation_predictor

    opts = tp.SolverOptions(order=2, n_magnus=8, compute_forces=False, tol=1e-13)
    for scene in (tp.load_scene("renda2021_fig3"), rvim_three_tube().scene):
        N = scene.n_tubes
        D = torch.tensor([scene.actuation.insertion], dtype=torch.float64).repeat(3, 1)
        A0 = torch.tensor([scene.actuation.rotation], dtype=torch.float64).repeat(3, 1)
        A0[:, -1] += torch.tensor([0.3, 1.5, 2.8], dtype=torch.float64)
        e0 = tp.solve(scene, insertion=D, rotation=A0, options=opts)
        tubes = tube_tensors(scene, torch.float64, torch.device("cpu"))
        Z = torch.zeros(3, 3, dtype=torch.float64)
        errs = []
        for deg in (2.0, 1.0):
            A1 = A0.clone()
            A1[:, :N - 1] += math.radians(0.5 * deg)     # every tube turns, by different steps
            A1[:, -1] += math.radians(deg)
            e1 = tp.solve(scene, insertion=D, rotation=A1, options=opts)
            pred = rotation_predictor(e0, e0.q.clone(), scene, tubes, D, A1, Z, Z, opts)
            err = (pred - e1.q).norm(dim=-1)
            assert bool((err < 0.05 * (e0.q - e1.q).norm(dim=-1)).all()), err
            errs.append(err)
        ratio = errs[0] / errs[1]
        assert bool(((ratio > 3.0) & (ratio < 5.0)).all()), ratio


def test_warm_rotation_steps_converge_to_the_same_equilibria_in_fewer_iterations():
    """A rotation sweep warm-started from the previous Equilibrium (the predictor applies)
    against the same starts passed as bare coordinates (no predictor): the same tips (1e-10
    m), and fewer Newton iterations in total."""
    scene = tp.load_scene("renda2021_fig3")
    rot = torch.tensor(scene.actuation.rotation, dtype=torch.float64)
    opts = tp.SolverOptions(order=2, n_magnus=8)
    prev = tp.solve(scene, rotation=rot, options=opts)
    with_pred = without = 0
    for k in range(1, 9):
        r = rot + torch.tensor([0.0, math.radians(3.0 * k)], dtype=torch.float64)
        a = tp.solve(scene, rotation=r, options=opts, initial=prev)
        b = tp.solve(scene, rotation=r, options=opts, initial=prev.q)
        assert torch.allclose(a.tip_position, b.tip_position, rtol=0, atol=1e-10)
        with_pred += int(a.iterations[0])
        without += int(b.iterations[0])
        prev = a
    assert with_pred < without, (with_pred, without)


def test_default_guess_is_the_torsionless_bending_on_every_active_section():
    """The cold-start guess (kernel.default_guess, from the compact maps) against
    the same quantity from the full node fields at q = 0: on every active section, the bending
    coefficients are the Legendre projection of the stiffness-weighted precurvature turned by
    the base angles (eq. 31 without torsion); every other coordinate is zero."""
    from envs.robots import rvim_three_tube
    from torchpvs.kernel import default_guess
    from torchpvs.mechanics import node_fields
    from torchpvs.plan import plan_for

    for scene in (tp.load_scene("renda2021_fig3"), rvim_three_tube().scene):
        N = scene.n_tubes
        gen = torch.Generator().manual_seed(1)
        B = 12
        rot = (torch.rand(B, N, generator=gen, dtype=torch.float64) - 0.5) * 6
        D = torch.tensor([scene.actuation.insertion], dtype=torch.float64).repeat(B, 1)
        D = D * (0.4 + 0.6 * torch.rand(B, 1, generator=gen, dtype=torch.float64))
        Z = torch.zeros(B, 3, dtype=torch.float64)
        disc = tp.SolverOptions().discretization(2)
        nq = n_coordinates(N, disc.n_basis)
        plan = plan_for(scene, torch.float64, torch.device("cpu"))
        lay, maps = plan.layout(plan.tubes, D, rot, Z, Z, torch.zeros(B, dtype=torch.bool),
                                disc, nq)
        tab = disc.tables(torch.float64, torch.device("cpu"))
        got = default_guess(lay, maps, tab, disc, N)
        f = node_fields(torch.zeros(B, nq, dtype=torch.float64), lay, tab.xq, tab.phi_q,
                        tab.Q_q)
        EI = lay.EI[:, None, None, :] * lay.present[:, :, None, :]
        u = (EI[..., None] * f.Ru).sum(-2) / EI.sum(-1, keepdim=True).clamp(min=1e-30)
        a = 0.5 * torch.einsum("bsgd,gp,g->bsdp", u, tab.phi_q, tab.wq)
        X = torch.zeros(B, 2 * N, 2 + N, disc.n_basis, dtype=torch.float64)
        X[:, :, :2] = a
        want = torch.cat([torch.zeros(B, N, dtype=torch.float64), X.reshape(B, -1)], -1)
        want = want * lay.qmask
        assert torch.allclose(got, want, rtol=1e-12, atol=1e-12)
        assert bool((got[lay.qmask == 0] == 0).all())


def test_newton_tolerance_follows_the_accuracy():
    """The kernel stops at ``min(tol, accuracy / (100 L))`` (SolverOptions.tol): the default
    tol (1e-9) moves the tip far less than the default accuracy, and a tight accuracy tightens
    the residual with it. Warm 1 deg steps (one Newton iteration lands between the two
    thresholds on most of them). Reference: the same solves converged to tol = 1e-12."""
    sc = tp.load_scene("renda2021_fig3")
    L = max(t.length for t in sc.tubes)
    rot = torch.tensor([[0.0, a] for a in torch.linspace(0.0, 4.3, 16).tolist()],
                       dtype=torch.float64)
    step = torch.tensor([0.0, math.radians(1.0)], dtype=torch.float64)
    fixed = dict(order=3, n_magnus=16, compute_forces=False)
    warm = tp.solve(sc, rotation=rot - step, options=tp.SolverOptions(tol=1e-12, **fixed))
    tight = tp.solve(sc, rotation=rot, initial=warm,                 # the same branch
                     options=tp.SolverOptions(tol=1e-12, **fixed))
    for acc, bound in ((1e-5, 1e-9), (1e-9, 1e-9 / (100 * L))):
        eq = tp.solve(sc, rotation=rot, initial=warm,
                      options=tp.SolverOptions(accuracy=acc, **fixed))
        assert bool(eq.converged.all())
        assert bool((eq.residual_norm < bound).all()), (acc, eq.residual_norm)
        # the residual's effect on the tip: far inside the accuracy (and below 1e-10 m here)
        err = (eq.tip_position - tight.tip_position).norm(dim=-1)
        assert bool((err < min(acc / 100, 1e-10)).all()), (acc, err)


@pytest.mark.parametrize("fused", [False, True], ids=["rounds", "fused"])
def test_energy_output_is_the_energy_at_the_returned_coordinates(monkeypatch, fused):
    """``Equilibrium.energy`` comes from the kernel's last evaluation where it made one (no tip
    load, method "minimize") and is recomputed otherwise; through the driver's rounds it is,
    bit for bit, the elastic energy evaluated afresh at the returned coordinates
    (mechanics.elastic_energy_maps on the same layout); through the fused path
    (torchpvs/fused.py) it is the compiled kernel's sum of the same terms, equal to round-off
    (1e-14 relative). Cold, warm (one iteration) and "root" solves."""
    import torchpvs.solver as solver_mod
    from torchpvs.mechanics import compact_q, elastic_energy_maps
    from torchpvs.plan import plan_for

    if not fused:
        monkeypatch.setattr(solver_mod, "fused_solve", lambda *a, **k: None)
    sc = tp.load_scene("renda2021_fig3")
    # (rotations in (-pi, pi): the layout below is built from them as given)
    rot = torch.tensor([[0.0, a] for a in (0.3, 1.7, 3.0, -2.0)], dtype=torch.float64)
    fixed = dict(order=2, n_magnus=8, compute_forces=False)
    cold = tp.solve(sc, rotation=rot, options=tp.SolverOptions(**fixed))
    warm = tp.solve(sc, rotation=rot + 0.01, initial=cold, options=tp.SolverOptions(**fixed))
    root = tp.solve(sc, rotation=rot, initial=cold,
                    options=tp.SolverOptions(method="root", **fixed))
    plan = plan_for(sc, torch.float64, torch.device("cpu"))
    disc = tp.SolverOptions(**fixed).discretization(2)
    for eq, r in ((cold, rot), (warm, rot + 0.01), (root, rot)):
        assert bool(eq.converged.all())
        B = r.shape[0]
        D = torch.tensor(sc.actuation.insertion, dtype=torch.float64).expand(B, 2)
        zero = torch.zeros(B, 3, dtype=torch.float64)
        with torch.inference_mode():
            _, maps = plan.layout(plan.tubes, D, r, zero, zero,
                                  torch.zeros(B, dtype=torch.bool), disc, eq.q.shape[-1])
            fresh = elastic_energy_maps(compact_q(eq.q, maps.cidx), maps)
        if fused:
            assert torch.allclose(eq.energy, fresh, rtol=1e-14, atol=0), (eq.energy - fresh)
        else:
            assert torch.equal(eq.energy, fresh), (eq.energy - fresh)
