"""Robot presets for the reaching environments: a scene, stroke limits and actuator scales.

A :class:`Robot` is the physical system an environment drives: the tubes (a
:class:`torchpvs.Scene`, whose actuation is only a default), the carriages' stroke limits and the
force/torque scales that map a normalized action in ``[-1, 1]`` to newtons and newton-metres.

The force scales are *measured*, not guessed: ``1.5 x`` the 99th percentile of ``|dU*/dx|`` over
stable equilibria sampled uniformly from the reachable workspace (``measure_force_scales``; the
stored values were produced by ``python -m envs.robots`` and a test re-measures them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch

import torchpvs
from torchpvs import Actuation, Scene, Tube
from torchpvs.plan import Plan, plan_for
from torchpvs.solver import solve_tensors

__all__ = ["Robot", "fig3_two_tube", "rvim_three_tube", "ROBOTS", "make_robot", "solve_batch",
           "RobotSolver", "measure_force_scales", "ENV_SOLVER_OPTIONS"]


@dataclass(frozen=True)
class Robot:
    """A robot for the environments.

    Attributes:
        name: preset name.
        scene: the tubes (outermost first); ``scene.actuation`` is the default home pose.
        insertion_min, insertion_max: ``(N,)`` [m] stroke of each carriage (``D_j``), before the
            nesting rules of docs/conventions.md (``D_j >= D_{j-1}``) and the tip-order rule
            ``L_j - D_j >= L_{j-1} - D_{j-1}`` are applied.
        force_scale: ``(N,)`` [N] the actuator force at action ``+-1`` (insertion carriages).
        torque_scale: ``(N,)`` [N·m] the actuator torque at action ``+-1`` (rotation stages).
        margin_scale: a typical stability margin (the median over the workspace of
            ``Equilibrium.min_stiffness_eigenvalue``, the smallest eigenvalue of the
            dimensionless, Jacobi-scaled stiffness) used to normalize it in observations.
        min_exposed: [m] the innermost tube keeps at least this much beyond the orifice.
    """

    name: str
    scene: Scene
    insertion_min: tuple[float, ...]
    insertion_max: tuple[float, ...]
    force_scale: tuple[float, ...]
    torque_scale: tuple[float, ...]
    margin_scale: float = 0.3
    min_exposed: float = 5e-3
    notes: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        n = self.scene.n_tubes
        for name in ("insertion_min", "insertion_max", "force_scale", "torque_scale"):
            v = getattr(self, name)
            if len(v) != n:
                raise ValueError(f"Robot.{name} must have {n} entries (one per tube), got {len(v)}")
            if not all(math.isfinite(x) for x in v):
                raise ValueError(f"Robot.{name} must be finite, got {v}")
        for j, (lo, hi) in enumerate(zip(self.insertion_min, self.insertion_max, strict=True)):
            if not 0.0 <= lo <= hi:
                raise ValueError(f"Robot.insertion_min[{j}] ({lo}) must satisfy "
                                 f"0 <= insertion_min <= insertion_max ({hi})")
        for name in ("force_scale", "torque_scale"):
            for j, v in enumerate(getattr(self, name)):
                if not v > 0:
                    raise ValueError(f"Robot.{name}[{j}] must be > 0 (the force/torque at "
                                     f"action +-1), got {v!r}")

    @property
    def n_tubes(self) -> int:
        return self.scene.n_tubes

    @property
    def lengths(self) -> np.ndarray:
        """``(N,)`` [m] total tube lengths."""
        return np.array([t.length for t in self.scene.tubes])

    @property
    def reach(self) -> float:
        """[m] a length scale of the workspace: the longest possible exposed length."""
        return float(max(L - lo for L, lo in zip(self.lengths, self.insertion_min, strict=True)))

    @property
    def action_scale(self) -> np.ndarray:
        """``(2N,)`` [N, N·m]: ``tau = action * action_scale``."""
        return np.array(self.force_scale + self.torque_scale)

    # -- the feasible set of actuator coordinates -----------------------------------------
    def bounds(self, D_prev: np.ndarray, j: int) -> tuple[np.ndarray, np.ndarray]:
        """Feasible interval of ``D_j`` given the outer tube's ``D_{j-1}`` (``(B,)`` arrays)."""
        L = self.lengths
        lo = np.full_like(D_prev, self.insertion_min[j])
        hi = np.full_like(D_prev, min(self.insertion_max[j], L[j] - self.min_exposed))
        if j > 0:
            lo = np.maximum(lo, D_prev)                        # bases ordered
            hi = np.minimum(hi, D_prev + (L[j] - L[j - 1]))    # tips ordered
        return lo, np.maximum(lo, hi)

    def constraints(self) -> tuple[np.ndarray, np.ndarray]:
        """The feasible set of insertions as ``G D <= c`` (``G (4N - 2, N)``, ``c`` [m]), rows
        in this order: for each carriage ``j`` its lower then upper stroke end
        (``-D_j <= -insertion_min_j``, ``D_j <= min(insertion_max_j, L_j - min_exposed)``);
        then for each pair ``(j-1, j)`` the nesting stop ``D_{j-1} - D_j <= 0`` and the
        tip-order stop ``D_j - D_{j-1} <= L_j - L_{j-1}`` (the rules of :meth:`bounds`)."""
        N, L = self.n_tubes, self.lengths
        rows, c = [], []
        for j in range(N):
            e = np.zeros(N)
            e[j] = 1.0
            rows += [-e, e]
            c += [-self.insertion_min[j], min(self.insertion_max[j], L[j] - self.min_exposed)]
        for j in range(1, N):
            e = np.zeros(N)
            e[j - 1], e[j] = 1.0, -1.0
            rows += [e, -e]
            c += [0.0, L[j] - L[j - 1]]
        return np.array(rows).reshape(len(rows), N), np.array(c)

    def project(self, D: np.ndarray, tol: float = 0.0
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Project insertions ``(B, N)`` onto the feasible set, outermost tube first (each
        carriage stops against its stroke ends and against its neighbour). Values within
        ``tol`` [m] of a limit are put on it (a contact solve leaves round-off either side).

        Returns ``(D, at_lower, at_upper)``; the flags say which limit is active.
        """
        D = np.array(D, dtype=np.float64, copy=True)
        lower = np.zeros(D.shape, dtype=bool)
        upper = np.zeros(D.shape, dtype=bool)
        prev = np.zeros(D.shape[0])
        for j in range(self.n_tubes):
            lo, hi = self.bounds(prev, j)
            lower[:, j] = D[:, j] <= lo + tol
            upper[:, j] = D[:, j] >= hi - tol
            D[:, j] = np.where(lower[:, j], lo, np.where(upper[:, j], hi, D[:, j]))
            prev = D[:, j]
        return D, lower, upper

    def sample_actuation(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """``(n, 2N)`` actuator coordinates ``(D, alpha)``: ``D`` uniform on the feasible set
        through its lower-triangular box map (each ``D_j`` uniform on its interval given the
        outer ones), ``alpha`` uniform on ``[-pi, pi)``."""
        N = self.n_tubes
        D = np.zeros((n, N))
        prev = np.zeros(n)
        for j in range(N):
            lo, hi = self.bounds(prev, j)
            D[:, j] = lo + (hi - lo) * rng.random(n)
            prev = D[:, j]
        A = rng.uniform(-math.pi, math.pi, size=(n, N))
        return np.concatenate([D, A], -1)


def _tube(name, E, G, di, do, L, Lc, kappa) -> Tube:
    return Tube(E=E, G=G, inner_diameter=di, outer_diameter=do, straight_length=L - Lc,
                curved_length=Lc, precurvature=((), (kappa,), ()), name=name)


def fig3_two_tube() -> Robot:
    """The paper's Fig. 3 robot (Renda et al. 2021, Table I): outer NiTi tube 93.5 + 92.3 mm,
    kappa 9.9 1/m; inner rod 218.5 + 85 mm, kappa 13.8 1/m. Strokes keep 5 mm of the inner
    tube exposed; the tips stay ordered."""
    scene = torchpvs.load_scene("renda2021_fig3")
    scene = scene.with_actuation(insertion=[60e-3, 150e-3], rotation=[0.0, 0.0])
    return Robot(name="fig3_two_tube", scene=scene, insertion_min=(0.0, 0.0),
                 insertion_max=(180e-3, 298.5e-3), force_scale=_SCALES["fig3_two_tube"][0],
                 torque_scale=_SCALES["fig3_two_tube"][1], margin_scale=0.31,
                 notes="Renda et al. RA-L 2021, Table I / Fig. 3")


def rvim_three_tube() -> Robot:
    """A three-tube robot with published laboratory dimensions (the "RViM lab" tube set of
    Iyengar et al.'s gym-ctr-reach, ``ctr_2``: E = 75 GPa, G = 25 GPa): outer 1.83/2.39 mm,
    173 mm, fully curved, kappa 10.8 1/m; middle 1.4/1.8 mm, 275 mm (114 curved), 11.68 1/m;
    inner 0.7/1.1 mm, 309 mm (145 curved), 13.52 1/m."""
    E, G = 75e9, 25e9
    tubes = (_tube("outer", E, G, 1.83e-3, 2.39e-3, 173e-3, 173e-3, 10.8),
             _tube("middle", E, G, 1.4e-3, 1.8e-3, 275e-3, 114e-3, 11.68),
             _tube("inner", E, G, 0.7e-3, 1.1e-3, 309e-3, 145e-3, 13.52))
    scene = Scene(tubes, Actuation((100e-3, 180e-3, 200e-3), (0.0, 0.0, 0.0)))
    return Robot(name="rvim_three_tube", scene=scene, insertion_min=(0.0, 0.0, 0.0),
                 insertion_max=(168e-3, 270e-3, 304e-3),
                 force_scale=_SCALES["rvim_three_tube"][0],
                 torque_scale=_SCALES["rvim_three_tube"][1], margin_scale=0.18,
                 notes="gym-ctr-reach ctr_2 (RViM lab tubes)")


# Measured by `python -m envs.robots` (n = 512 samples, seed 0): 1.5 x p99 |dU*/dx|; the
# margin scales are the medians printed by the same command.
_SCALES: dict[str, tuple[tuple[float, ...], tuple[float, ...]]] = {
    "fig3_two_tube": ((3.92, 4.51), (0.146, 0.146)),
    "rvim_three_tube": ((6.88, 4.43, 0.987), (0.255, 0.234, 0.0598)),
}

ROBOTS = {"fig3_two_tube": fig3_two_tube, "rvim_three_tube": rvim_three_tube}


def make_robot(robot: str | Robot | Scene, **overrides) -> Robot:
    """A preset by name, a :class:`Robot`, or any scene (file path, built-in name or
    :class:`~torchpvs.Scene`) with default strokes and measured scales."""
    if isinstance(robot, Robot):
        base = robot
    elif isinstance(robot, str) and robot in ROBOTS:
        base = ROBOTS[robot]()
    else:
        if isinstance(robot, str) and not (Path(robot).suffix in (".yaml", ".yml", ".json")
                                           or Path(robot).exists()
                                           or robot in torchpvs.builtin_scenes()):
            raise torchpvs.SceneError(
                f"unknown robot {robot!r}: the env robots are {sorted(ROBOTS)}; robot= also "
                f"takes a torchpvs scene (built-in: {', '.join(torchpvs.builtin_scenes())}), a "
                f"scene file (.yaml, .yml, .json), a Scene or an envs.Robot")
        scene = torchpvs.load_scene(robot) if isinstance(robot, str) else robot
        if not isinstance(scene, Scene):
            raise TypeError(f"robot must be a preset name {sorted(ROBOTS)}, a Robot, a Scene or "
                            f"a scene path, got {type(robot).__name__}")
        L = [t.length for t in scene.tubes]
        n = scene.n_tubes
        base = Robot(name="custom", scene=scene, insertion_min=(0.0,) * n,
                     insertion_max=tuple(x - 5e-3 for x in L), force_scale=(1.0,) * n,
                     torque_scale=(0.01,) * n)
        f, t, m = measure_force_scales(base, n=128)
        base = Robot(**{**base.__dict__, "force_scale": _load_free(f, 1.0, 1e-9),
                        "torque_scale": _load_free(t, 0.01, 1e-12), "margin_scale": m})
    if overrides:
        base = Robot(**{**base.__dict__, **overrides})
    return base


def _load_free(scales: tuple[float, ...], default: float, floor: float) -> tuple[float, ...]:
    """Scales for the actuators that carry no elastic load anywhere in the workspace (the base
    rotation of a one-tube robot is a rigid rotation: ``dU*/dalpha = 0``; a straight tube's
    insertion too): the largest measured scale of the same kind, else ``default``. With no
    load the scale only sets units: the carriage moves at its target speed at action +-1
    whatever the scale (the damping is ``scale / speed``). ``floor`` [N or N·m] is the
    round-off level below which a measured scale counts as no load."""
    loaded = [v for v in scales if v > floor]
    fill = max(loaded) if loaded else default
    return tuple(v if v > floor else fill for v in scales)


def solve_batch(robot: Robot, x: np.ndarray, initial=None, options=None):
    """Solve the equilibria at actuator coordinates ``x (B, 2N)``; returns the Equilibrium."""
    N = robot.n_tubes
    x = np.asarray(x, dtype=np.float64)
    if x.ndim != 2 or x.shape[0] < 1 or x.shape[1] != 2 * N:
        raise ValueError(f"x must have shape (B, {2 * N}) with a batch size B >= 1 (insertions "
                         f"then rotations of each of {N} tube(s)), got shape {x.shape}")
    xt = torch.as_tensor(x, dtype=torch.float64)
    return torchpvs.solve(robot.scene, insertion=xt[:, :N], rotation=xt[:, N:],
                          options=options or ENV_SOLVER_OPTIONS, initial=initial)


class RobotSolver:
    """The solves of one robot's batch, at actuations the batch itself produced.

    :func:`solve_batch` (``torchpvs.solve``) looks the robot's :class:`~torchpvs.plan.Plan` up
    by hashing ``scene.tubes`` and re-checks every input (shape, finiteness, nesting) on each
    call; a robot batch solves once or more per substep at actuations it projected onto the
    feasible set itself (:meth:`Robot.project`) from validated actions. This holds the plan
    (the same object ``torchpvs.solve`` uses for the scene, looked up once) and the scene's load
    as tensors, and calls the solve proper (``torchpvs.solver.solve_tensors``) with them: the
    same computation as :func:`solve_batch`, bit for bit, without the per-call lookup and
    checks. Callers validate what they did not produce (``RobotBatch.set_state`` checks its
    ``x``)."""

    def __init__(self, robot: Robot):
        self.robot = robot
        # float64 on the CPU, the energy force model: what solve_batch's solve runs with
        # ENV_SOLVER_OPTIONS (no dtype, device or paper-model scope check to repeat)
        self.plan: Plan = plan_for(robot.scene, torch.float64, torch.device("cpu"))
        load = robot.scene.load
        self._F = torch.tensor([load.tip_force], dtype=torch.float64)
        self._M = torch.tensor([load.tip_moment], dtype=torch.float64)

    def __call__(self, x: np.ndarray, initial=None):
        """The equilibria at feasible, finite actuator coordinates ``x (B, 2N)``."""
        N = self.robot.n_tubes
        xt = torch.as_tensor(x, dtype=torch.float64)
        k = xt.shape[0]
        D, A = xt[:, :N].contiguous(), xt[:, N:].contiguous()
        F, M = (t.expand(k, -1).contiguous() for t in (self._F, self._M))
        return solve_tensors(self.robot.scene, self.plan.tubes, D, A, F, M, ENV_SOLVER_OPTIONS,
                             initial, self.plan)


# Fixed order 2 and 8 Magnus steps: tip errors below 1e-3 mm on the Fig. 3 sweeps (docs) at a
# fraction of the cost of the automatic choice; the environments' tolerances are >= 0.1 mm.
# No wall-clock limit: an episode must be the same on a loaded machine as on an idle one (a
# 100-robot plant solve took over the default 30 s with four jobs on two cores, and the
# sampling then rejected every robot); max_total_iter bounds the work instead.
ENV_SOLVER_OPTIONS = torchpvs.SolverOptions(order=2, n_magnus=8, on_failure="ignore",
                                            time_limit=None)


def measure_force_scales(robot: Robot, n: int = 512, seed: int = 0,
                         quantile: float = 0.99, factor: float = 1.5):
    """``factor x`` the ``quantile`` of ``|tau_D|`` and ``|tau_alpha|`` per tube over ``n``
    uniformly sampled stable equilibria, and the median stability margin. Returns
    ``(force_scale, torque_scale, margin_scale)``."""
    rng = np.random.default_rng(seed)
    x = robot.sample_actuation(rng, n)
    eq = solve_batch(robot, x)
    ok = (eq.converged & eq.stable).numpy()
    g = torch.cat([eq.actuation_forces, eq.actuation_torques], -1).numpy()[ok]
    s = factor * np.quantile(np.abs(g), quantile, axis=0)
    N = robot.n_tubes
    margin = float(f"{np.median(eq.min_stiffness_eigenvalue.numpy()[ok]):.2g}")
    return (tuple(float(f"{v:.3g}") for v in s[:N]), tuple(float(f"{v:.3g}") for v in s[N:]),
            margin)


if __name__ == "__main__":  # pragma: no cover - regenerates _SCALES
    for name, make in ROBOTS.items():
        print(name, measure_force_scales(make()))
