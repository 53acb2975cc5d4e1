"""``torchpvs.options``: the validation of ``SolverOptions``, its helpers, and what each
numerical option does to a solve.

What is tested, and against what:

- bad values of the fields that tests/test_inputs.py and tests/test_solver.py do not already
  cover raise ``ValueError`` naming the field (``options.<field>``), and the documented good
  values (``None`` where allowed) are accepted; the options are frozen;
- ``discretization``: the documented sizes (``n = order + 1`` basis functions, ``2 n + 4`` Gauss
  points by default, 8 Magnus steps when automatic) and explicit values kept;
- ``with_options``/``within_deadline``/``check_time_limit`` against their documented
  behaviour (a copy with fields changed and re-validated; the time limit cut to what is left
  before a ``torchpvs.clock.work_clock`` deadline, at least 1 ms);
- through ``solve``: ``tol`` bounds the tip error against a separately converged solve
  (``tol=1e-14``, 40 Gauss points) by ``tol x L`` (the residual is a strain correction times
  the robot length); ``n_quad`` converges to the same reference; ``method="minimize"``
  returns stable equilibria where ``"root"`` from the same cold guess reaches unstable ones
  (both with a vanishing residual), and ``"root"`` started at a minimum stays there;
  ``on_failure`` raises, warns or stays silent; ``dtype`` sets the output precision;
  ``compute_forces=False`` leaves the forces out; a fixed ``order`` is the order reported.
"""

from __future__ import annotations

import dataclasses
import math
import warnings

import numpy as np
import pytest
import torch

import torchpvs as tp
from torchpvs.clock import work_clock
from torchpvs.options import (
    AccuracyWarning,
    SolverError,
    SolverOptions,
    check_time_limit,
    with_options,
    within_deadline,
)

DT = torch.float64
SC = tp.load_scene("renda2021_fig3")
L_MAX = max(t.length for t in SC.tubes)
ROT = torch.tensor([[0.0, a] for a in (0.3, 1.4, 2.5, 3.6)], dtype=DT)
pytestmark = pytest.mark.usefixtures("one_thread_module")


@pytest.mark.parametrize("field, value", [
    ("order", -1), ("order", 2.0), ("order", "2"),
    ("max_order", 0), ("max_order", 3.5),
    ("force_model", "kirchhoff"),
    ("on_failure", "crash"),
    ("tol", 0.0), ("tol", -1e-9), ("tol", math.nan),
    ("max_iter", 0), ("max_iter", 10.0),
    ("n_quad", 1), ("n_quad", 4.0),
    ("n_magnus", 0), ("n_magnus", 8.0),
    ("backward_ridge", -1e-6), ("backward_ridge", math.inf), ("backward_ridge", math.nan),
    ("dtype", torch.float16), ("dtype", torch.int64), ("dtype", "float64"),
    ("accuracy", 0.0), ("accuracy", math.inf), ("accuracy", math.nan), ("accuracy", "1e-5"),
    # regressions: booleans passed as integers/numbers, an infinite tol, an unchecked
    # singular_tol
    ("order", True), ("max_order", True), ("max_iter", True), ("load_steps", False),
    ("max_total_iter", True), ("n_quad", True), ("n_magnus", True), ("accuracy", True),
    ("tol", True), ("tol", math.inf), ("backward_ridge", True),
    ("singular_tol", -1.0), ("singular_tol", math.nan), ("singular_tol", "0"),
])
def test_bad_values_raise_a_value_error_naming_the_field(field, value):
    with pytest.raises(ValueError, match=rf"options\.{field}\b"):
        SolverOptions(**{field: value})


@pytest.mark.parametrize("field, value", [
    ("order", 0), ("order", None), ("max_order", 1), ("tol", 1e-14), ("max_iter", 1),
    ("n_quad", 2), ("n_quad", None), ("n_magnus", 1), ("n_magnus", None),
    ("backward_ridge", 0.0), ("backward_ridge", 1e-6), ("dtype", torch.float32),
    ("dtype", torch.float64), ("dtype", None), ("method", "root"), ("force_model", "paper"),
    ("on_failure", "raise"), ("on_failure", "ignore"), ("time_limit", None),
    ("singular_tol", 0.0), ("order", np.int64(3)), ("tol", np.float32(1e-9)),
])
def test_documented_values_are_accepted(field, value):
    assert getattr(SolverOptions(**{field: value}), field) == value


def test_options_are_frozen_and_compare_by_value():
    opts = SolverOptions(order=3)
    with pytest.raises(dataclasses.FrozenInstanceError):
        opts.order = 4
    assert opts == SolverOptions(order=3) and opts != SolverOptions(order=4)
    assert hash(opts) == hash(SolverOptions(order=3))


def test_failure_types_are_the_documented_builtin_subclasses():
    assert issubclass(SolverError, RuntimeError)
    assert issubclass(AccuracyWarning, RuntimeWarning)
    assert tp.SolverError is SolverError and tp.AccuracyWarning is AccuracyWarning


@pytest.mark.parametrize("order", [0, 2, 5])
def test_discretization_has_the_documented_sizes(order):
    d = SolverOptions().discretization(order)
    n = order + 1
    assert (d.n_basis, d.n_quad, d.n_magnus) == (n, 2 * n + 4, 8)
    d = SolverOptions(n_quad=7, n_magnus=32).discretization(order)
    assert (d.n_basis, d.n_quad, d.n_magnus) == (n, 7, 32)


def test_with_options_copies_and_revalidates():
    base = SolverOptions(order=3, tol=1e-12)
    changed = with_options(base, accuracy=1e-7)
    assert changed.accuracy == 1e-7 and changed.order == 3 and changed.tol == 1e-12
    assert base.accuracy == SolverOptions().accuracy            # the original is unchanged
    assert with_options(None, order=2) == SolverOptions(order=2)
    with pytest.raises(ValueError, match="options.max_iter"):
        with_options(base, max_iter=0)


def test_within_deadline_cuts_the_time_limit_to_what_is_left():
    """Deadlines are times of :func:`torchpvs.clock.work_clock` (wall clock less numba's
    compile time)."""
    opts = SolverOptions(time_limit=None)
    assert within_deadline(opts, None) is opts
    t0 = work_clock()
    cut = within_deadline(opts, t0 + 5.0)
    t1 = work_clock()
    assert t0 + 5.0 - t1 <= cut.time_limit <= 5.0
    # an earlier own limit is kept; an expired deadline leaves 1 ms, not zero or less
    assert within_deadline(SolverOptions(time_limit=0.5), work_clock() + 5.0
                           ).time_limit == 0.5
    assert within_deadline(opts, work_clock() - 10.0).time_limit == pytest.approx(1e-3)


@pytest.mark.parametrize("value", [0.0, -2.0, math.inf, math.nan, "1", True])
def test_check_time_limit_names_its_argument(value):
    with pytest.raises(ValueError, match="my_limit must be a positive number"):
        check_time_limit(value, "my_limit")


def test_check_time_limit_returns_good_values():
    assert check_time_limit(None) is None and check_time_limit(2) == 2
    assert check_time_limit(0.25) == 0.25


@pytest.fixture(scope="module")
def reference():
    """The converged reference: order 3 and 16 Magnus steps as the solves compared with it,
    residual 1e-14, 40 Gauss points."""
    return tp.solve(SC, rotation=ROT, options=SolverOptions(
        order=3, n_magnus=16, tol=1e-14, n_quad=40, compute_forces=False))


def test_tol_bounds_the_tip_error_by_the_residual_times_the_length(reference):
    """accuracy=1 m so that tol alone sets the residual threshold."""
    errs = []
    for tol in (1e-4, 1e-6, 1e-9):
        eq = tp.solve(SC, rotation=ROT, options=SolverOptions(
            order=3, n_magnus=16, tol=tol, accuracy=1.0, compute_forces=False))
        assert bool(eq.converged.all()) and bool((eq.residual_norm < tol).all())
        err = (eq.tip_position - reference.tip_position).norm(dim=-1)
        assert bool((err <= tol * L_MAX).all()), (tol, err)
        errs.append(float(err.max()))
    assert errs == sorted(errs, reverse=True), errs


def test_n_quad_converges_to_the_reference_quadrature(reference):
    errs = []
    for nq in (4, 6, None):                                  # None: the default, 2 n + 4 = 12
        eq = tp.solve(SC, rotation=ROT, options=SolverOptions(
            order=3, n_magnus=16, tol=1e-14, n_quad=nq, compute_forces=False))
        errs.append(float((eq.tip_position - reference.tip_position).norm(dim=-1).max()))
    assert errs[0] > errs[1] > errs[2] and errs[2] <= 1e-12, errs


def test_minimize_returns_minima_where_root_may_reach_saddles():
    """From the same cold guess the plain Newton root finder reaches unstable equilibria of the
    Fig. 3 robot at alpha2 = 2.5 and 3.6 rad (measured: smallest stiffness eigenvalues -2.9 and
    -4.3); the damped minimizer returns stable ones there. Started at the minima, "root"
    stays at them."""
    opts = dict(order=3, n_magnus=16, compute_forces=False)
    mini = tp.solve(SC, rotation=ROT, options=SolverOptions(method="minimize", **opts))
    root = tp.solve(SC, rotation=ROT, options=SolverOptions(method="root", **opts))
    assert bool(mini.converged.all()) and bool(mini.stable.all())
    assert bool(root.converged.all()) and not bool(root.stable.all())
    unstable = ~root.stable
    assert float((root.tip_position - mini.tip_position).norm(dim=-1)[unstable].min()) > 1e-3
    back = tp.solve(SC, rotation=ROT, initial=mini.q, options=SolverOptions(method="root", **opts))
    assert float((back.tip_position - mini.tip_position).abs().max()) <= 1e-12


def test_on_failure_raises_warns_or_stays_silent():
    kw = dict(rotation=[0.0, 2.0])
    bad = dict(order=3, max_iter=1)
    with pytest.raises(SolverError, match="did not converge"):
        tp.solve(SC, **kw, options=SolverOptions(on_failure="raise", **bad))
    with pytest.warns(RuntimeWarning, match="did not converge"):
        eq = tp.solve(SC, **kw, options=SolverOptions(on_failure="warn", **bad))
    assert not bool(eq.converged[0])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        eq = tp.solve(SC, **kw, options=SolverOptions(on_failure="ignore", **bad))
    assert not bool(eq.converged[0])


def test_dtype_sets_the_output_precision():
    """``dtype=None`` follows the given tensors, else float64; an explicit dtype wins."""
    rot32 = ROT[:1].float()
    assert tp.solve(SC, rotation=rot32).tip_position.dtype == torch.float32
    assert tp.solve(SC).tip_position.dtype == torch.float64
    eq = tp.solve(SC, rotation=rot32, options=SolverOptions(dtype=torch.float64))
    assert eq.tip_position.dtype == torch.float64 and eq.q.dtype == torch.float64
    eq = tp.solve(SC, rotation=ROT[:1], options=SolverOptions(dtype=torch.float32))
    assert eq.tip_position.dtype == torch.float32


def test_compute_forces_false_leaves_the_forces_out():
    eq = tp.solve(SC, options=SolverOptions(compute_forces=False))
    assert eq.actuation_forces is None and eq.actuation_torques is None
    eq = tp.solve(SC)
    assert eq.actuation_forces is not None and bool(torch.isfinite(eq.actuation_forces).all())


@pytest.mark.parametrize("order", [1, 4])
def test_a_fixed_order_is_the_order_solved_at(order):
    eq = tp.solve(SC, options=SolverOptions(order=order, n_magnus=8))
    assert eq.order == order and eq.context.discretization.n_basis == order + 1
    assert eq.context.discretization.n_magnus == 8
