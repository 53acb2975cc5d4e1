"""Calibration (torchpvs.calibrate): parameters recovered from tips of an independent model.

Measurements come from the standard Kirchhoff-rod model solved by shooting
(``torchpvs.reference``, which shares nothing with the PVS solver but the scene) on a robot
perturbed from the nominal Fig. 3 robot, plus Gaussian noise and outliers; the fit runs on the
PVS model. References: the perturbation itself (known truth), finite differences of the solve
for the Jacobian."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

import torchpvs
from torchpvs.testing import feasible_actuations, scaled_tubes, standard_tips

SCENE = torchpvs.load_scene("renda2021_fig3")


def _perturbed(scene, k=(1.08, 0.93), E=(1.1, 0.92), G=(0.95, 1.07)):
    return scaled_tubes(scene, precurvature=k, E=E, G=G)


@pytest.fixture(scope="module")
def measured():
    rng = np.random.default_rng(0)
    truth = _perturbed(SCENE)
    offset = np.array([1e-3, 1e-3])          # both carriages' zero 1 mm off
    D, A = feasible_actuations(rng, 36)
    tips = standard_tips(truth, D + offset, A)
    noisy = tips + rng.normal(0.0, 1e-4, tips.shape)     # 0.1 mm per axis
    noisy[[3, 17]] += [[6e-3, -4e-3, 2e-3], [-3e-3, 5e-3, 4e-3]]   # 2 of 36 outliers (5.6 %)
    Dh, Ah = feasible_actuations(rng, 12)
    held = standard_tips(truth, Dh + offset, Ah)
    return dict(D=D, A=A, noisy=noisy, Dh=Dh, Ah=Ah, held=held, offset=offset)


def test_recovers_the_identifiable_parameters_and_predicts_held_out_tips(measured):
    m = measured
    cal = torchpvs.calibrate(SCENE, m["D"], m["A"], m["noisy"],
                             params=("precurvature", "E[1]", "G", "insertion_offset"),
                             huber_scale=3e-4)
    assert cal.converged, cal.reason
    assert cal.identifiability.identifiable
    # tips fix stiffness ratios only: with E[0] held at its nominal value the moduli come out
    # as truth x (nominal E[0] / true E[0]) = truth / 1.1
    E, G = SCENE.tubes[1].E, SCENE.tubes[0].G
    truth = {"precurvature[0]": 1.08, "precurvature[1]": 0.93,
             "E[1]": E * 0.92 / 1.1, "G[0]": G * 0.95 / 1.1, "G[1]": G * 1.07 / 1.1,
             "insertion_offset[0]": 1e-3, "insertion_offset[1]": 1e-3}
    for name, want in truth.items():
        i = cal.names.index(name)
        err = cal.value[i] - want
        tol = {"p": 0.02 * abs(want), "E": 0.05 * abs(want), "G": 0.05 * abs(want),
               "i": 3e-4}[name[0]]                                # 2 %, 5 %, 0.3 mm
        assert abs(err) < tol, (name, cal.value[i], want)
        assert abs(err) < 3 * cal.std[i], (name, err, cal.std[i])  # honest sigmas
    assert not cal.inlier[[3, 17]].any()            # the outliers are recognised
    before = np.sqrt(np.mean(np.sum((torchpvs.solve(
        SCENE, insertion=torch.tensor(m["Dh"]), rotation=torch.tensor(m["Ah"]),
        options=torchpvs.SolverOptions(on_failure="ignore")).tip_position.numpy()
        - m["held"]) ** 2, -1)))
    after = np.sqrt(np.mean(np.sum((cal.predict(m["Dh"], m["Ah"]) - m["held"]) ** 2, -1)))
    assert before > 2e-3 and after < 2e-4, (before, after)   # several mm -> < 0.2 mm


def test_reports_stiffness_scale_as_unidentifiable(measured):
    m = measured
    cal = torchpvs.calibrate(SCENE, m["D"], m["A"], m["noisy"],
                             params=("precurvature", "E", "G", "insertion_offset"),
                             huber_scale=3e-4, max_iter=15)
    groups = cal.identifiability.unidentifiable
    assert len(groups) == 1 and set(groups[0]) == {"E[0]", "E[1]", "G[0]", "G[1]"}
    for name in ("E[0]", "E[1]", "G[0]", "G[1]"):
        assert np.isinf(cal.std[cal.names.index(name)])
    assert np.isfinite(cal.std[cal.names.index("precurvature[0]")])
    assert "NOT identifiable" in cal.report()


def test_exact_data_of_the_model_itself_are_fitted_exactly():
    """Noise-free PVS tips of a robot with changed lengths, precurvature and a rotation
    offset: Gauss-Newton with the implicit-function Jacobian recovers them to 1e-6 relative
    (a wrong Jacobian stalls far from it)."""
    rng = np.random.default_rng(3)
    D, A = feasible_actuations(rng, 12)
    t0, t1 = SCENE.tubes
    truth = dataclasses.replace(SCENE, tubes=(
        dataclasses.replace(t0, straight_length=t0.straight_length + 2e-3),
        dataclasses.replace(t1, curved_length=t1.curved_length - 3e-3,
                            precurvature=tuple(tuple(c * 1.05 for c in ax)
                                               for ax in t1.precurvature))))
    rot_off = np.array([0.0, 0.05])
    tips = torchpvs.solve(truth, insertion=torch.tensor(D), rotation=torch.tensor(A + rot_off),
                          options=torchpvs.SolverOptions(accuracy=1e-9)).tip_position.numpy()
    cal = torchpvs.calibrate(SCENE, D, A, tips, huber_scale=None, tol=1e-10,
                             params=("straight_length[0]", "curved_length[1]",
                                     "precurvature[1]", "rotation_offset[1]"),
                             options=torchpvs.SolverOptions(accuracy=1e-9, on_failure="ignore",
                                                            compute_forces=False))
    want = [t0.straight_length + 2e-3, t1.curved_length - 3e-3, 1.05, 0.05]
    np.testing.assert_allclose(cal.value, want, rtol=1e-6, atol=1e-8)
    assert cal.rms < 1e-8
    assert cal.scene.tubes[1].curved_length == pytest.approx(want[1], rel=1e-6)
    assert cal.rotation_offset[1] == pytest.approx(0.05, rel=1e-6)


def test_jacobian_matches_finite_differences():
    from torchpvs.calibration import _Model, _parse
    rng = np.random.default_rng(1)
    D, A = feasible_actuations(rng, 4)
    PARAMS = ("precurvature[1]", "E[0]", "G[1]", "straight_length[1]", "curved_length[0]",
              "insertion_offset[0]", "rotation_offset[1]")
    specs = _parse(PARAMS, 2)
    assert len(specs) == len(PARAMS)
    opts = torchpvs.SolverOptions(order=4, n_magnus=16, tol=1e-13, on_failure="ignore",
                                  compute_forces=False)
    model = _Model(SCENE, specs, D, A, None, opts)
    z = np.array([1.0, SCENE.tubes[0].E, SCENE.tubes[1].G, SCENE.tubes[1].straight_length,
                  SCENE.tubes[0].curved_length, 0.0, 0.0])
    _, J, conv = model.tips(z, jacobian=True)
    assert conv.all()
    h = np.array([1e-6, 1e-6 * z[1], 1e-6 * z[2], 1e-7, 1e-7, 1e-7, 1e-6])
    for i in range(len(z)):
        zp, zm = z.copy(), z.copy()
        zp[i] += h[i]
        zm[i] -= h[i]
        model.initial = None
        fd = (model.tips(zp, False)[0] - model.tips(zm, False)[0]) / (2 * h[i])
        np.testing.assert_allclose(J[:, :, i], fd, rtol=1e-4,
                                   atol=1e-6 * np.abs(fd).max(), err_msg=PARAMS[i])


def test_least_squares_is_dragged_by_an_outlier_and_huber_is_not():
    rng = np.random.default_rng(5)
    D, A = feasible_actuations(rng, 20)
    truth = _perturbed(SCENE, E=(1.0, 1.0), G=(1.0, 1.0))     # precurvatures 1.08, 0.93
    tips = torchpvs.solve(truth, insertion=torch.tensor(D),
                          rotation=torch.tensor(A)).tip_position.numpy()
    tips = tips + rng.normal(0.0, 1e-4, tips.shape)
    tips[5] += [0.03, 0.0, 0.0]                      # one 30 mm outlier
    kw = dict(params=("precurvature",))
    ls = torchpvs.calibrate(SCENE, D, A, tips, huber_scale=None, **kw)
    hub = torchpvs.calibrate(SCENE, D, A, tips, huber_scale=3e-4, **kw)
    err = lambda c: max(abs(c["precurvature[0]"] - 1.08), abs(c["precurvature[1]"] - 0.93))  # noqa: E731
    assert err(hub) < 0.005 < err(ls), (err(hub), err(ls))
    assert not hub.inlier[5] and hub.inlier.sum() >= 15


PARAMS10 = ("precurvature", "E", "G", "straight_length", "curved_length")


@pytest.mark.parametrize("kwargs, match", [
    (dict(tip=np.zeros((3, 2))), r"tip must have shape \(M, 3\)"),
    (dict(insertion=np.zeros((4, 2))), "insertion has 4 rows but tip has 3"),
    (dict(tip=np.full((3, 3), np.nan)), "tip must be finite"),
    (dict(params=("stiffness",)), "unknown parameter 'stiffness'"),
    (dict(params=("E[2]",)), "names tube 2"),
    (dict(params=("precurvature", "precurvature[0]")), "named twice"),
    (dict(params=PARAMS10), "6 equations for 10 parameters"),
    (dict(weights=[1, -1, 1]), "weights must be"),
    (dict(huber_scale=-1.0), "huber_scale must be a positive length"),
    (dict(bounds={"precurvature": (1.1, 2.0)}), "excludes the scene's value"),
    (dict(bounds={"E": (1.0, 2.0)}), "not among the fitted parameters"),
])
def test_bad_input_names_the_field(kwargs, match):
    args = dict(insertion=np.array([[0.05, 0.07]] * 3), rotation=np.zeros((3, 2)),
                tip=np.zeros((3, 3)))
    if "params" in kwargs and kwargs["params"] is PARAMS10:
        args = {k: v[:2] for k, v in args.items()}
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        torchpvs.calibrate(SCENE, args.pop("insertion"), args.pop("rotation"),
                           args.pop("tip"), **args)
