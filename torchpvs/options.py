"""The options of a solve (:class:`SolverOptions`), its failure types and its time bounds."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, replace

import numpy as np
import torch

from .clock import work_clock
from .kernel import KERNELS
from .plan import MAGNUS_START
from .sections import Discretization

__all__ = ["AccuracyWarning", "SolverError", "SolverOptions", "check_time_limit",
           "with_options", "within_deadline"]

_METHODS = ("minimize", "root")
_ON_FAILURE = ("warn", "raise", "ignore")
_FORCE_MODELS = ("energy", "paper")


class SolverError(RuntimeError):
    """Raised when ``options.on_failure == "raise"`` and some element did not converge."""


class AccuracyWarning(RuntimeWarning):
    """An automatic solve converged but its error estimate exceeds ``options.accuracy``."""


def _is_int(v) -> bool:
    # bool is an int subclass: True must not pass as 1 (numpy integers are Integral)
    return isinstance(v, numbers.Integral) and not isinstance(v, (bool, np.bool_))


def _is_number(v) -> bool:
    return isinstance(v, numbers.Real) and not isinstance(v, (bool, np.bool_))


@dataclass(frozen=True)
class SolverOptions:
    """Options of :func:`solve`.

    Attributes:
        accuracy: target tip-position accuracy [m]. With ``order=None`` the basis order is
            chosen automatically: the solve starts at the order of the warm start (``initial``,
            an Equilibrium or coordinates of a basis size) or at 2, estimates the tip error
            by one Newton step of the next order from the solution (its tip change), and raises
            the order until that estimate is within ``accuracy``; the chosen order is reported
            in ``Equilibrium.order``, the estimate in ``Equilibrium.error_estimate``.
        order: polynomial degree of every strain basis (``n = order + 1`` functions per strain
            per section; the paper's "quadratic" is 2). ``None`` = automatic from ``accuracy``.
        max_order: ceiling of the automatic choice.
        method: ``"minimize"`` (default): damped Newton on the energy with a line search, which
            returns a *stable* equilibrium (local minimum) whenever the iteration can reach one;
            ``"root"``: plain Newton on the gradient, which converges to the stationary point
            nearest the initial guess, stable or not (use it with ``initial=`` to reach unstable
            equilibria of multi-stable scenes).
        tol: convergence threshold on the scaled residual ``max_i |g_i| / H_ii * L`` (dimensionless:
            a strain correction times the robot length, i.e. radians). The kernel uses
            ``min(tol, accuracy / (100 L))`` with ``L`` the longest tube, so that the residual
            never limits the requested accuracy. At the default 1e-9 the tip moves by at most
            3e-12 m, and the forces by 2e-10 N, against solves at 1e-12 (Fig. 3 robot, 1024 warm
            configurations: docs/performance.md); 1e-10 cost a second Newton iteration on 2/3
            of warm 1 deg steps there.
        max_iter: Newton iterations per order.
        n_quad: Gauss points per section (default ``2 (order + 1) + 4``).
        n_magnus: 4th-order Magnus steps per section for the backbone pose. ``None``
            (default) = automatic: the warm start's count (else 8) is kept if the tip moves
            less than ``accuracy / 2`` when recomputed with half the steps; otherwise the tip
            is recomputed with twice the steps and the count doubled (and the equilibrium
            re-solved) until the two agree within ``accuracy / 2``. The last tip change is
            added to ``Equilibrium.error_estimate``.
        dtype: ``torch.float64`` (default for physics) or ``torch.float32``; ``None`` = from the
            given tensors, else float64.
        device: torch device; ``None`` = from the given tensors, else CPU.
        on_failure: ``"warn"`` (default), ``"raise"`` (:class:`SolverError`) or ``"ignore"`` when
            an element does not converge. Status is always in ``Equilibrium.converged``/``reason``.
        compute_forces: also compute ``actuation_forces``/``actuation_torques`` (one backward pass).
        force_model: ``"energy"`` (default): ``tau = dU*/d(D, alpha)``, the energy-consistent
            forces of docs/conventions.md (they include the configurational force of precurved
            material entering or leaving the guide); ``"paper"``: the projection of the paper's
            eq. (41) (Renda et al. 2021), which omits the guide's stored bending energy — for
            reproducing the paper's Table II (docs/actuation-forces.md). Defined as the paper
            defines it: two tubes (or one), no tip load, no straight-to-curved transition
            beyond the orifice, the outer tube ending before the inner one; other scenes raise
            ``ValueError``. Its forces/torques carry no gradient and no one-sided kink values.
        backward_ridge: Tikhonov shift added to the (Jacobi-scaled) stiffness in the adjoint
            solve of the implicit backward; 0 = exact gradients. Use a small value (1e-6) to
            regularize gradients at folds.
        load_coordinates: give distal single-tube sections coordinates even without a tip
            load (they are exact without; needed for the tip compliance at zero load and for
            gradients w.r.t. a load that is zero).
        kernel: name of the kernel in :data:`torchpvs.kernel.KERNELS`: ``"compiled"``
            (default: the Newton solve and steps compiled per element by numba, on CPU tensors
            without a tip load; the eager kernel elsewhere, :mod:`torchpvs.compiled`) or
            ``"newton"`` (the eager reference, batched torch on any device; see
            :class:`torchpvs.kernel.Kernel`).
        load_steps: load continuation for loaded elements that do not converge from the
            initial guess: the tip load is ramped up in this many equal steps, each warm-started
            from the last (1 = no ramp). ``Equilibrium.reason`` says how far a failed ramp got.
        max_total_iter: bound on the Newton iterations of one call over every order, Magnus
            refinement and load step (``max_iter`` bounds one kernel call). When it is reached
            the solve stops where it is: unfinished elements are not converged, and converged
            ones whose estimate exceeds ``accuracy`` say so (``accuracy_met``).
        singular_tol: the implicit backward warns (:class:`NearSingularStiffnessWarning`) for
            elements whose scaled stiffness has an eigenvalue below this in magnitude.
        time_limit: [s] wall-clock bound on the Newton iterations of one call (every order,
            load step and Magnus refinement; ``None`` = no bound). Checked before every Newton
            step, so a call overshoots by at most one iteration plus the outputs (forces,
            pose). When it is reached the solve stops like ``max_total_iter``: unfinished
            elements are not converged and their reason says so. Time numba spends compiling
            kernels on their first use is not counted (:func:`torchpvs.clock.work_clock`).
    """

    accuracy: float = 1e-5
    order: int | None = None
    max_order: int = 7
    method: str = "minimize"
    tol: float = 1e-9
    max_iter: int = 60
    n_quad: int | None = None
    n_magnus: int | None = None
    dtype: torch.dtype | None = None
    device: torch.device | str | None = None
    on_failure: str = "warn"
    compute_forces: bool = True
    force_model: str = "energy"
    backward_ridge: float = 0.0
    singular_tol: float = 1e-10
    load_coordinates: bool = False
    kernel: str = "compiled"
    load_steps: int = 8
    max_total_iter: int = 200
    time_limit: float | None = 30.0

    def __post_init__(self) -> None:
        if not (_is_number(self.accuracy) and self.accuracy > 0
                and math.isfinite(self.accuracy)):
            raise ValueError(
                f"options.accuracy must be a positive length [m], got {self.accuracy!r}")
        if self.order is not None and (not _is_int(self.order) or self.order < 0):
            raise ValueError(f"options.order must be an integer >= 0 or None, got {self.order!r}")
        if not _is_int(self.max_order) or self.max_order < 1:
            raise ValueError(f"options.max_order must be an integer >= 1, got {self.max_order!r}")
        if self.method not in _METHODS:
            raise ValueError(f"options.method must be one of {_METHODS}, got {self.method!r}")
        if self.force_model not in _FORCE_MODELS:
            raise ValueError(f"options.force_model must be one of {_FORCE_MODELS}, "
                             f"got {self.force_model!r}")
        if self.on_failure not in _ON_FAILURE:
            raise ValueError(f"options.on_failure must be one of {_ON_FAILURE}, "
                             f"got {self.on_failure!r}")
        if not (_is_number(self.tol) and self.tol > 0 and math.isfinite(self.tol)):
            raise ValueError(f"options.tol must be a finite number > 0, got {self.tol!r}")
        if not _is_int(self.max_iter) or self.max_iter < 1:
            raise ValueError(f"options.max_iter must be an integer >= 1, got {self.max_iter!r}")
        if not _is_int(self.load_steps) or self.load_steps < 1:
            raise ValueError(f"options.load_steps must be an integer >= 1, got {self.load_steps!r}")
        if not _is_int(self.max_total_iter) or self.max_total_iter < 1:
            raise ValueError(f"options.max_total_iter must be an integer >= 1, "
                             f"got {self.max_total_iter!r}")
        if self.time_limit is not None and not (
                isinstance(self.time_limit, (int, float)) and not isinstance(self.time_limit, bool)
                and self.time_limit > 0 and math.isfinite(self.time_limit)):
            raise ValueError(f"options.time_limit must be a positive number of seconds or None, "
                             f"got {self.time_limit!r}")
        if self.n_quad is not None and (not _is_int(self.n_quad) or self.n_quad < 2):
            raise ValueError(f"options.n_quad must be an integer >= 2 or None, got {self.n_quad!r}")
        if self.n_magnus is not None and (not _is_int(self.n_magnus)
                                          or self.n_magnus < 1):
            raise ValueError(
                f"options.n_magnus must be an integer >= 1 or None, got {self.n_magnus!r}")
        if not (_is_number(self.backward_ridge) and self.backward_ridge >= 0
                and math.isfinite(self.backward_ridge)):
            raise ValueError(f"options.backward_ridge must be >= 0, got {self.backward_ridge!r}")
        if not (_is_number(self.singular_tol) and self.singular_tol >= 0
                and math.isfinite(self.singular_tol)):
            raise ValueError(f"options.singular_tol must be a finite number >= 0, "
                             f"got {self.singular_tol!r}")
        if self.kernel not in KERNELS:
            raise ValueError(f"options.kernel must be one of {tuple(KERNELS)}, "
                             f"got {self.kernel!r}")
        if self.dtype not in (None, torch.float32, torch.float64):
            raise ValueError(f"options.dtype must be torch.float32, torch.float64 or None, "
                             f"got {self.dtype!r}")

    def discretization(self, order: int) -> Discretization:
        n = order + 1
        return Discretization(n_basis=n, n_quad=self.n_quad or 2 * n + 4,
                              n_magnus=self.n_magnus or MAGNUS_START)


def check_time_limit(time_limit, name: str = "time_limit") -> float | None:
    """A wall-clock bound [s]: a positive finite number or ``None`` (no bound)."""
    if time_limit is not None and not (isinstance(time_limit, (int, float))
                                       and not isinstance(time_limit, bool)
                                       and time_limit > 0 and math.isfinite(time_limit)):
        raise ValueError(f"{name} must be a positive number of seconds or None, got "
                         f"{time_limit!r}")
    return time_limit


def within_deadline(opts: SolverOptions, deadline: float | None) -> SolverOptions:
    """``opts`` with its ``time_limit`` cut to what is left before ``deadline`` (a
    :func:`~torchpvs.clock.work_clock` value; ``None``: unchanged), so that a call made of many
    solves keeps its own bound. At least 1 ms, so that an expired call still returns a
    verdict."""
    if deadline is None:
        return opts
    left = max(deadline - work_clock(), 1e-3)
    limit = left if opts.time_limit is None else min(opts.time_limit, left)
    return replace(opts, time_limit=limit)


def with_options(options: SolverOptions | None, **changes) -> SolverOptions:
    """A copy of ``options`` (or the defaults) with fields changed."""
    return replace(options or SolverOptions(), **changes)
