"""The solver on an accelerator (CUDA) against the same solve on the CPU.

Reference: the CPU eager kernel (``kernel="newton"``), which the rest of the suite checks against
closed forms, the paper's tables and the independent standard-model solver. On a GPU the same
eager kernel runs (the compiled kernel is CPU-only), so both devices run the same iteration and
must give the same equilibria up to floating-point summation order: tips within 1e-12 m, forces
within 1e-9 N (N m), the same convergence flags, iteration counts, orders and stability
verdicts, gradients of the implicit backward within 1e-8 (relative), and every output on the
requested device.

These tests need a CUDA device and are skipped without one (CI has none). Run them on a GPU
machine with ``python -m pytest tests/test_device.py`` (docs/performance.md, "On a GPU", gives
the last run's result).
"""

from __future__ import annotations

import dataclasses
import math
import os

import pytest
import torch

import torchpvs as tp
from torchpvs import SolverOptions
from torchpvs.testing import SWEEPS, assert_same_equilibria, fig3, nested_scene, random_scene

# TORCHPVS_TEST_DEVICES (comma-separated, e.g. "cpu" or "cuda:1") replaces the default; "cpu"
# checks this module itself on a machine without a GPU (the CPU's default, compiled kernel
# against the eager one).
DEVICES = ([d.strip() for d in os.environ["TORCHPVS_TEST_DEVICES"].split(",")]
           if os.environ.get("TORCHPVS_TEST_DEVICES") else
           [pytest.param("cuda", marks=pytest.mark.skipif(not torch.cuda.is_available(),
                                                          reason="no CUDA device"))])
pytestmark = pytest.mark.parametrize("device", DEVICES)


def on(device, scene, dtype=torch.float64, **kw):
    """The same solve on the CPU (eager kernel) and on ``device``."""
    opts = kw.pop("options", None) or SolverOptions()
    cpu = tp.solve(scene, **{k: v.cpu() for k, v in kw.items()},
                   options=dataclasses.replace(opts, kernel="newton", dtype=dtype, device="cpu"))
    dev = tp.solve(scene, **{k: v.to(device) for k, v in kw.items()},
                   options=dataclasses.replace(opts, dtype=dtype, device=device))
    return cpu, dev


def assert_same(cpu, dev, device, tip_tol=1e-12, force_tol=1e-9):
    """Every output on ``device``, the same order, and the same equilibria
    (:func:`torchpvs.testing.assert_same_equilibria`)."""
    for name in ("tip_position", "actuation_forces", "actuation_torques", "converged",
                 "iterations", "stable", "min_stiffness_eigenvalue"):
        assert getattr(dev, name).device.type == torch.device(device).type, name
    assert cpu.order == dev.order
    assert_same_equilibria(cpu, dev, tip_tol, force_tol)


@pytest.mark.parametrize("sweep", sorted(SWEEPS))
def test_fig3_sweeps_cold_and_warm(device, sweep):
    """The paper's Fig. 3 sweeps (section III-C) as one batch, cold then warm 1 deg on; the
    full-overlap sweep passes the bistable range (unstable equilibria, stability verdicts)."""
    D2, alphas = SWEEPS[sweep]
    scene = fig3(D2=D2)
    rot = torch.tensor([[0.0, math.radians(a)] for a in alphas], dtype=torch.float64)
    cpu, dev = on(device, scene, rotation=rot)
    assert_same(cpu, dev, device)
    rot2 = rot + torch.tensor([0.0, math.radians(1.0)], dtype=torch.float64)
    cpu2 = tp.solve(scene, rotation=rot2, initial=cpu,
                    options=SolverOptions(kernel="newton", device="cpu"))
    dev2 = tp.solve(scene, rotation=rot2.to(device), initial=dev,
                    options=SolverOptions(device=device))
    assert_same(cpu2, dev2, device)


@pytest.mark.parametrize("seed", range(6))
def test_random_robots(device, seed):
    """Seeded random two- and three-tube robots (torchpvs.testing.random_scene)."""
    cpu, dev = on(device, random_scene(seed))
    assert_same(cpu, dev, device)


def test_three_tubes_batched(device):
    scene = nested_scene(3, seed=1)
    g = torch.Generator().manual_seed(0)
    rot = torch.tensor(scene.actuation.rotation, dtype=torch.float64) + 0.5 * torch.rand(
        32, 3, generator=g, dtype=torch.float64)
    cpu, dev = on(device, scene, rotation=rot)
    assert_same(cpu, dev, device)


def test_tip_load(device):
    """A dead tip force and moment (the load ramp, the load coordinates)."""
    F = torch.tensor([[0.0, 0.3, -0.1], [0.2, 0.0, 0.0]], dtype=torch.float64)
    M = torch.tensor([[0.0, 0.0, 0.002], [0.0, -0.001, 0.0]], dtype=torch.float64)
    cpu, dev = on(device, fig3(), tip_force=F, tip_moment=M)
    assert_same(cpu, dev, device)


def test_float32(device):
    """float32 on the device against float32 on the CPU (both far from float64's agreement:
    the tolerance is float32's, 1e-6 m on a ~0.2 m robot)."""
    rot = torch.tensor([[0.0, math.radians(a)] for a in range(0, 181, 30)])
    cpu, dev = on(device, fig3(), dtype=torch.float32, rotation=rot)
    assert dev.tip_position.dtype == torch.float32
    assert torch.equal(cpu.converged, dev.converged.cpu())
    assert torch.equal(cpu.stable, dev.stable.cpu())
    assert float((cpu.tip_position - dev.tip_position.cpu()).abs().max()) <= 1e-6


def test_implicit_backward(device):
    """Gradients of the tip through the implicit backward, w.r.t. insertion, rotation and the
    tip force, on the device against the CPU."""
    def grads(dev):
        D = torch.tensor([[0.0935, 0.2085], [0.09, 0.18]], dtype=torch.float64, device=dev)
        A = torch.tensor([[0.0, 1.4], [0.3, 2.0]], dtype=torch.float64, device=dev)
        F = torch.tensor([[0.0, 0.1, 0.0], [0.05, 0.0, 0.0]], dtype=torch.float64, device=dev)
        for t in (D, A, F):
            t.requires_grad_(True)
        opts = SolverOptions(device=dev, kernel="newton" if dev == "cpu" else "compiled")
        eq = tp.solve("renda2021_fig3", insertion=D, rotation=A, tip_force=F, options=opts)
        w = torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64, device=dev)
        (eq.tip_position * w).sum().backward()
        return [t.grad.cpu() for t in (D, A, F)]

    for g_cpu, g_dev in zip(grads("cpu"), grads(device), strict=True):
        assert torch.allclose(g_cpu, g_dev, rtol=1e-8, atol=1e-12 * float(g_cpu.abs().max()))


def test_ctr_layer_learnable(device):
    """``CTR`` with learnable precurvature and E on the device: forward, backward, and the
    gradients against the CPU layer."""
    def run(dev):
        ctr = tp.CTR("renda2021_fig3").learnable("precurvature", "E").to(dev)
        D = torch.tensor([[0.0935, 0.2085]], dtype=torch.float64, device=dev)
        A = torch.tensor([[0.0, 0.8]], dtype=torch.float64, device=dev)
        eq = ctr(D, A)
        eq.tip_position.sum().backward()
        return {n: p.grad.cpu() for n, p in ctr.named_parameters()}, eq

    g_cpu, _ = run("cpu")
    g_dev, eq = run(device)
    assert eq.tip_position.device.type == torch.device(device).type
    assert g_cpu.keys() == g_dev.keys() and g_cpu
    for n in g_cpu:
        assert torch.allclose(g_cpu[n], g_dev[n], rtol=1e-8,
                              atol=1e-12 * float(g_cpu[n].abs().max())), n


def test_control_jacobians(device):
    """The closed-form control step (actuator stiffness, tip and force Jacobians, tip
    compliance) on the device against the CPU."""
    rot = torch.tensor([[0.0, 0.5], [0.0, 1.2]], dtype=torch.float64)
    D = torch.tensor([[0.09, 0.2], [0.08, 0.19]], dtype=torch.float64)
    cpu, dev = on(device, fig3(), insertion=D, rotation=rot)
    jc, jd = cpu.jacobians(), dev.jacobians()
    for f in dataclasses.fields(jc):
        a, b = getattr(jc, f.name), getattr(jd, f.name)
        if not isinstance(a, torch.Tensor):
            continue
        assert b.device.type == torch.device(device).type, f.name
        scale = float(a.abs().max())
        assert torch.allclose(a, b.cpu(), rtol=1e-7, atol=1e-9 * scale), f.name


def test_inverse_kinematics(device):
    """Goals on the device give actuations on the device that reach them, as on the CPU (the
    seeded starts are drawn on the CPU's generator, so both runs start alike)."""
    scene = tp.load_scene("renda2021_fig3")
    goals = tp.solve(scene, insertion=torch.tensor([[0.08, 0.19], [0.06, 0.17]]).double(),
                     rotation=torch.tensor([[0.3, 1.0], [-0.5, 2.0]]).double()).tip_position
    cpu = tp.inverse_kinematics(scene, goals, starts=3, seed=1,
                                options=SolverOptions(order=2, n_magnus=8, kernel="newton",
                                                      compute_forces=False,
                                                      on_failure="ignore"))
    dev = tp.inverse_kinematics(scene, goals.to(device), starts=3, seed=1)
    assert dev.tip.device.type == dev.insertion.device.type == torch.device(device).type
    assert torch.equal(cpu.solved, dev.solved.cpu()) and bool(cpu.solved.all())
    assert float(dev.error.max()) < 1e-4
    assert torch.allclose(cpu.insertion, dev.insertion.cpu(), atol=1e-6)


def test_force_control(device):
    """A commanded torque on the inner tube (its rotation free) and a commanded insertion
    force: the equilibrium found on the device matches the CPU's."""
    kw = dict(forces=[float("nan"), -0.05], torques=[float("nan"), 0.002])
    cpu = tp.solve_force_controlled("renda2021_fig3", **kw,
                                    options=SolverOptions(kernel="newton", device="cpu"))
    dev = tp.solve_force_controlled("renda2021_fig3", **kw, options=SolverOptions(device=device))
    assert dev.equilibrium.tip_position.device.type == torch.device(device).type
    assert torch.equal(cpu.converged, dev.converged.cpu()) and bool(cpu.converged.all())
    assert float((cpu.equilibrium.tip_position
                  - dev.equilibrium.tip_position.cpu()).abs().max()) <= 1e-9


def test_continuation_finds_the_fold(device):
    """The Fig. 3 full-overlap rotation sweep snaps (section III-C); the fold is found at the
    same place on both devices."""
    path = {"rotation": [[0.0, 0.0], [0.0, math.radians(300)]]}
    runs = [tp.continuation(tp.testing.fig3(), path,
                            options=SolverOptions(kernel="newton", device="cpu")),
            tp.continuation(tp.testing.fig3(), path, options=SolverOptions(device=device))]
    cpu, dev = runs
    assert len(cpu.folds) == len(dev.folds) >= 1
    for a, b in zip(cpu.folds, dev.folds, strict=True):
        assert abs(a.s - b.s) <= 2e-4
