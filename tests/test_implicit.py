"""Stage 6: gradients through the implicit-function backward — torch.autograd.gradcheck on
every input group (finite differences of the full solve, float64), plus the nn.Module face."""

from __future__ import annotations

import pytest
import torch

import torchpvs as tp

OPTS = tp.SolverOptions(order=3, tol=1e-12)
SCENE = tp.load_scene("renda2021_fig3")
# Away from the Fig. 3 kink (D1 = Ls1 puts the outer transition exactly at the orifice).
INS = torch.tensor([[0.090, 0.2085], [0.085, 0.17]], dtype=torch.float64)
ROT = torch.tensor([[0.0, 1.0], [0.3, 2.0]], dtype=torch.float64)


def _outputs(eq):
    return (eq.tip_position, eq.tip_rotation.flatten(1), eq.energy, eq.actuation_forces,
            eq.actuation_torques, eq.relative_rotation_at_outer_tip)


def test_gradcheck_rotation():
    rot = ROT.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda r: _outputs(tp.solve(SCENE, insertion=INS, rotation=r, options=OPTS)),
        (rot,), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_gradcheck_insertion():
    ins = INS.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(
        lambda d: _outputs(tp.solve(SCENE, insertion=d, rotation=ROT, options=OPTS))[:3],
        (ins,), eps=1e-7, atol=1e-5, rtol=1e-4)


def test_gradcheck_tip_load():
    f = torch.tensor([[0.05, -0.02, 0.01]], dtype=torch.float64, requires_grad=True)
    m = torch.tensor([[0.0, 1e-3, -5e-4]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(
        lambda f_, m_: tp.solve(SCENE, insertion=INS[:1], rotation=ROT[:1], tip_force=f_,
                                tip_moment=m_, options=OPTS).tip_position,
        (f, m), eps=1e-6, atol=1e-6, rtol=1e-4)


@pytest.mark.parametrize("name", ["precurvature", "E", "outer_diameter", "curved_length"])
def test_gradcheck_tube_parameters(name):
    robot = tp.CTR(SCENE, OPTS).learnable(name)
    param = getattr(robot, name)
    scale = {"precurvature": 1.0, "E": 1e10, "outer_diameter": 1e-3, "curved_length": 0.1}[name]

    def f(x):
        setattr(robot, name, torch.nn.Parameter(x * scale))
        # setattr replaces the Parameter; route the tensor in without breaking the graph
        robot._parameters[name] = x * scale
        return robot(INS[:1], ROT[:1]).tip_position

    x0 = (param.detach() / scale).clone().requires_grad_(True)
    assert torch.autograd.gradcheck(f, (x0,), eps=1e-6, atol=1e-6, rtol=1e-4)


def test_ctr_module_learns_and_moves_dtype():
    robot = tp.CTR("renda2021_fig3").learnable("precurvature")
    eq = robot(INS[0], ROT[0])
    eq.tip_position.square().sum().backward()
    assert robot.precurvature.grad is not None
    assert torch.isfinite(robot.precurvature.grad).all()
    r32 = tp.CTR("renda2021_fig3").to(torch.float32)
    e32 = r32(INS[0].float(), ROT[0].float())
    assert e32.tip_position.dtype == torch.float32
    e64 = tp.CTR("renda2021_fig3")(INS[0], ROT[0])
    assert (e32.tip_position.double() - e64.tip_position).norm() < 1e-4


def test_double_backward_raises_clearly():
    rot = ROT[:1].clone().requires_grad_(True)
    eq = tp.solve(SCENE, insertion=INS[:1], rotation=rot, options=OPTS)
    with pytest.raises(RuntimeError, match="second derivatives"):
        torch.autograd.grad(eq.tip_position.sum(), rot, create_graph=True)


def test_no_graph_without_requires_grad():
    eq = tp.solve(SCENE, insertion=INS, rotation=ROT, options=OPTS)
    assert eq.tip_position.grad_fn is None


def test_non_finite_stiffness_warns_instead_of_raising():
    """Regression: an element whose stiffness is not finite (a solve that overflowed, as
    float32 inverse kinematics produced) made the singularity check's eigh raise LinAlgError
    and lost every element's gradient. Now it is named in a warning, its gradient is NaN and
    the other elements' gradients equal a solve without it (reference: that solve)."""
    rot = ROT.clone().requires_grad_(True)
    eq = tp.solve(SCENE, insertion=INS, rotation=rot, options=OPTS)
    eq.context.implicit.Hc[0] = float("nan")    # element 0: no usable stiffness
    with pytest.warns(tp.NearSingularStiffnessWarning, match=r"not finite at 1 element\(s\) \[0\]"):
        (g,) = torch.autograd.grad(eq.tip_position[:, 0].sum(), rot)
    assert bool(torch.isnan(g[0]).all())
    rot1 = ROT[1:].clone().requires_grad_(True)
    (g1,) = torch.autograd.grad(
        tp.solve(SCENE, insertion=INS[1:], rotation=rot1, options=OPTS).tip_position[:, 0].sum(),
        rot1)
    assert torch.allclose(g[1], g1[0], rtol=1e-10, atol=1e-14)


def test_adjoint_factors_solve_the_padded_system():
    """The adjoint factorization works on each element's active coordinates only
    (implicit.AdjointFactors). Reference: a dense solve of the padded Hessian (identity on the
    inactive coordinates), on a batch whose elements have different active coordinates (a tube
    end inside the guide, a short outer tube, the Fig. 3 robot) so that the compaction pads."""
    from torchpvs.implicit import adjoint_factor
    ins = torch.tensor([[0.090, 0.2085], [0.0, 0.05], [0.2, 0.3]], dtype=torch.float64)
    rot = torch.tensor([[0.0, 1.0], [0.3, 2.0], [0.0, -0.5]], dtype=torch.float64)
    eq = tp.solve(SCENE, insertion=ins, rotation=rot, options=OPTS)
    info = eq.context.implicit
    qmask = info.qmask
    assert len(set(qmask.sum(-1).tolist())) > 1           # the compaction pads some elements
    D, A, F, M = (t.detach() for t in eq.context.actuation_and_load)
    factors = adjoint_factor(eq.q.detach(), info, D, A, F, M, eq.context.tubes)
    assert factors.lu.shape[-1] == int(qmask.sum(-1).max()) < qmask.shape[-1]
    rhs = torch.randn(3, qmask.shape[-1], 4, dtype=torch.float64,
                      generator=torch.Generator().manual_seed(0)) * qmask[..., None]
    ref = torch.linalg.solve(info.hessian(), rhs)
    for tangent in (False, True):     # H is symmetric: the tangent and its adjoint agree
        x = factors.solve(rhs, tangent=tangent)
        assert torch.allclose(x, ref, rtol=1e-9, atol=1e-12 * float(ref.abs().max()))
        assert bool((x[qmask == 0] == 0).all())
    sub = factors.rows(torch.tensor([2, 0]))
    assert torch.allclose(sub.solve(rhs[[2, 0]]), ref[[2, 0]], rtol=1e-9,
                          atol=1e-12 * float(ref.abs().max()))
