"""Hard case: large tip loads (docs/physics.md, "Hard cases"), up to the load where the
standard-model
reference itself fails.

Both solvers follow the loaded branch of the paper's Fig. 3 robot (Renda et al. 2021, section
III-C, alpha2 = 80 deg) by continuation in the load: PVS warm-starts from the previous load; the
reference (torchpvs.reference, shooting) is given the PVS orifice moments as its guess —
``m_j(0) = -tau_alpha_j`` and ``mb_xy(0) = (p_tip x F)_xy`` (the moment balance of the free part)
— and converges on its own equations to its own tolerance, or fails. Pass: wherever the
reference converges, PVS converged, is stable and within the default accuracy (1e-5 m) of it;
beyond, PVS never returns NaN and reports its status.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest

import torchpvs as tp
from torchpvs import SolverOptions
from torchpvs.reference import solve_standard
from torchpvs.testing import dist, fig3, tip

SC = fig3(alpha2_deg=80.0)
TIP_TOL = 1e-5
LATERAL = [5.0, 50.0, 200.0, 500.0, 1000.0]     # [N] along +x



def ladder(direction, loads, options=None):
    """Yield ``(F, pvs, reference)`` along the load ladder."""
    prev = None
    for F in loads:
        f = F * np.asarray(direction, float)
        sc = SC.with_load(tip_force=f)
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            p = tp.solve(sc, initial=prev, options=options)
        guess = np.r_[-p.actuation_torques[0].numpy(), np.cross(tip(p), f)[:2]]
        r = solve_standard(sc, initial=guess, compute_forces=False, compute_stability=False)
        yield F, p, r
        if bool(p.converged[0]):
            prev = p


def check_ladder(direction, loads, min_compared):
    compared = []
    for F, p, r in ladder(direction, loads):
        assert np.isfinite(tip(p)).all() and np.isfinite(p.energy[0].item()), F
        # The reference fails: no convergence, or convergence to another equilibrium than the
        # continued branch (its energy U* differs: measured -9.6 J vs -78.5 J at 1000 N oblique,
        # where PVS at order 5 and 7 with 64 Magnus steps agrees with itself to 4e-6 m).
        off = r.converged and abs(r.energy - float(p.energy[0])) > 1e-3 * abs(r.energy)
        if not r.converged or off:
            print(f"\nreference fails at {F} N (converged {r.converged}, residual "
                  f"{r.residual_norm:.1e}, U* {r.energy:.4g} J vs PVS {float(p.energy[0]):.4g} J);"
                  f" PVS converged {bool(p.converged[0])}, error estimate "
                  f"{float(p.error_estimate[0]):.1e} m")
            break
        assert bool(p.converged[0]) and bool(p.stable[0]), (F, p.reason)
        err = dist(tip(p), r.tip_position)
        assert err < TIP_TOL, (F, err)
        compared.append((F, err))
    print(f"\ncompared {direction}: " + ", ".join(f"{F:g} N: {e:.1e} m" for F, e in compared))
    assert len(compared) >= min_compared


def test_large_lateral_tip_force():
    """+x force 5..1000 N at the tip (the robot bends ~90 deg over toward the load); measured:
    the reference converges up to 500 N (PVS within 2.2e-6 m) and fails at 1000 N."""
    check_ladder((1.0, 0.0, 0.0), LATERAL, min_compared=4)


@pytest.mark.slow
def test_large_axial_and_oblique_tip_force():
    """Compressive (-z) force to 50 N (100 N: test_accuracy_delivered_under_large_axial_force) and
    an oblique force up to
    1000 N, where the reference leaves the branch (measured: PVS within 3.2e-6 m up to 500 N)."""
    check_ladder((0.0, 0.0, -1.0), [5.0, 20.0, 50.0], min_compared=3)
    check_ladder((-0.6, 0.6, -0.53), [1.0, 5.0, 20.0, 50.0, 100.0, 200.0, 500.0, 1000.0],
                 min_compared=3)


def test_accuracy_delivered_under_large_axial_force():
    """SolverOptions.accuracy is the target tip accuracy [m] and error_estimate its a posteriori
    estimate: the true error must not exceed the requested accuracy. (Was a strict xfail while
    the estimate compared two converged orders: it stopped at order 3, 3.0e-5 m from the
    reference; the one-step estimate at order + 1 sees the error and raises the order.)"""
    prev = None
    for F in (5.0, 20.0, 50.0, 100.0):
        sc = SC.with_load(tip_force=[0.0, 0.0, -F])
        prev = tp.solve(sc, initial=prev)
    guess = np.r_[-prev.actuation_torques[0].numpy(), np.cross(tip(prev), [0, 0, -100.0])[:2]]
    r = solve_standard(sc, initial=guess, tol=1e-12, compute_forces=False,
                       compute_stability=False)
    fine = tp.solve(sc, initial=prev, options=SolverOptions(order=7, n_magnus=64))
    assert r.converged and dist(tip(fine), r.tip_position) < 1e-7     # the truth is settled
    err = dist(tip(prev), r.tip_position)
    assert err <= 1e-5, (err, prev.order, float(prev.error_estimate[0]))
    print(f"100 N axial: order {prev.order}, error {err:.2e} m, estimate "
          f"{float(prev.error_estimate[0]):.2e} m")
