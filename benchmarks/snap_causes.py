"""What the environment's snaps are: for every snap of a policy's evaluation episodes, follow
the equilibrium along the control step that snapped and report whether a fold lies on it.

    python benchmarks/snap_causes.py --policy training/policies/tqc_force.zip \
        [--episodes 500] [--seed 12345] [--batch 50]

The episodes are those of ``python -m training.evaluate`` with the same seed and batch (the
same starts and goals). A force-env step flags a snap (``envs.dynamics.RobotBatch._run``) on a
tip jump the carriage motion does not explain, on a twist release, or on a non-positive
margin. For each flagged robot this script records the state before the step (actuation and
coordinates) and after it, solves the start again warm from its coordinates, and runs
:func:`torchpvs.continuation` along the straight actuation path between the two, with the
environment's solver options. Printed per snap: the margin before the step, the tip jump the
environment saw, the folds on the path (where in the step, the jump, their kind) and the tip
motion of a direct warm solve at the step's end (what the environment's plant computes).

* a fold on the path: the equilibrium the robot was on ceases to exist during the step: a
  snap of the model, which a controller avoids only by staying away from the fold;
* no fold: the branch continues; the tip moved fast but continuously (a soft region near a
  fold) and the environment's jump test flagged it.

Also printed: what a policy could have seen one step ahead. For the state before each snapped
step and for every hundredth ordinary robot-step of the same episodes: the observation's
stability margin (the smallest eigenvalue of the Jacobi-scaled Hessian in the coordinates)
and the smallest eigenvalue of the actuator stiffness's rotation block ``dtau_alpha /
dalpha`` [N·m/rad] (:func:`torchpvs.jacobians.actuator_stiffness`, unclipped; the
environment clips ``K`` to its positive part for the carriage dynamics and does not observe
it). The fraction of ordinary steps at or below each snapped step's value says how well the
quantity would separate the two.
"""

from __future__ import annotations

import argparse

import numpy as np
import torch

import torchpvs


def record_snaps(policy_path: str, episodes: int, seed: int, batch: int
                 ) -> tuple[list[tuple], list[tuple]]:
    """``(snapped, ordinary)``: ``(x0, q0, x1, tip0, tip1, margin0)`` of every snapped
    robot-step of the evaluation, and ``(x0, q0, margin0)`` of every hundredth other one."""
    import envs.dynamics as dyn
    from training.evaluate import load_policy, policy_env, rollout

    rows, ordinary = [], []
    run = dyn.RobotBatch._run
    count = [0]

    def recording_run(self, n, propose, stiffness, accept=None):
        x0, q0, tip0, m0 = self.x.copy(), self.q.copy(), self.tip.copy(), self.margin.copy()
        flags = run(self, n, propose, stiffness, accept)
        for i in np.flatnonzero(flags.snapped):
            rows.append((x0[i], q0[i], self.x[i].copy(), tip0[i], self.tip[i].copy(), m0[i]))
        for i in np.flatnonzero(~flags.snapped & ~flags.solver_failure):
            count[0] += 1
            if count[0] % 100 == 0:
                ordinary.append((x0[i], q0[i], m0[i]))
        return flags

    dyn.RobotBatch._run = recording_run
    try:
        venv, _ = policy_env(policy_path, batch)
        res = rollout(load_policy(policy_path, venv), venv, episodes, seed=seed,
                      progress=False)
    finally:
        dyn.RobotBatch._run = run
    print(f"{policy_path}: {int(np.sum(res['snap']))} snapped episodes of {episodes}, "
          f"{len(rows)} snapped steps recorded")
    return rows, ordinary


def rotation_stiffness(scene, x: np.ndarray, q: np.ndarray, opts) -> float:
    """Smallest eigenvalue [N·m/rad] of the actuator stiffness's rotation block at the
    equilibrium of actuation ``x`` warm from coordinates ``q``."""
    from torchpvs.jacobians import actuator_stiffness
    N = scene.n_tubes
    eq = torchpvs.solve(scene, insertion=x[:N], rotation=x[N:],
                        initial=torch.as_tensor(q)[None], options=opts)
    K = actuator_stiffness(eq)[0, N:, N:]
    return float(torch.linalg.eigvalsh(0.5 * (K + K.T))[0])


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--policy", required=True)
    ap.add_argument("--robot", default="fig3_two_tube")
    ap.add_argument("--episodes", type=int, default=500)
    ap.add_argument("--seed", type=int, default=12345)
    ap.add_argument("--batch", type=int, default=50)
    args = ap.parse_args(argv)
    torch.set_num_threads(1)
    import envs.robots as robots
    scene = robots.make_robot(args.robot).scene
    opts = robots.ENV_SOLVER_OPTIONS
    N = scene.n_tubes
    with_fold = 0
    rows, ordinary = record_snaps(args.policy, args.episodes, args.seed, args.batch)
    base_m = np.array([m for _, _, m in ordinary])
    base_k = np.array([rotation_stiffness(scene, x, q, opts) for x, q, _ in ordinary])
    for x0, q0, x1, tip0, tip1, m0 in rows:
        start = torchpvs.solve(scene, insertion=x0[:N], rotation=x0[N:],
                               initial=torch.as_tensor(q0)[None], options=opts)
        path = torchpvs.ActuationPath(insertion=np.stack([x0[:N], x1[:N]]),
                                      rotation=np.stack([x0[N:], x1[N:]]))
        cont = torchpvs.continuation(scene, path, options=opts, initial=start,
                                     max_step=0.01, time_limit=120)
        end = torchpvs.solve(scene, insertion=x1[:N], rotation=x1[N:], initial=start,
                             options=opts)
        folds = [f"s = {f.s:.3f}: {1e3 * f.tip_jump:.1f} mm ({f.kind})" for f in cont.folds]
        with_fold += bool(folds)
        moved = 1e3 * float(np.linalg.norm(end.tip_position[0].numpy() - tip0))
        k0 = rotation_stiffness(scene, x0, q0, opts)
        print(f"margin before {m0:.3f} (ordinary steps at or below: "
              f"{np.mean(base_m <= m0):.0%}), rotation stiffness {k0:.2e} N·m/rad "
              f"({np.mean(base_k <= k0):.0%}); env tip jump "
              f"{1e3 * np.linalg.norm(tip1 - tip0):.1f} mm; folds on the step: "
              f"{folds or 'none'}; direct warm solve: tip moved {moved:.1f} mm")
    print(f"{with_fold} of {len(rows)} snapped steps cross a fold of the model")
    print(f"ordinary steps sampled: {len(ordinary)}; margin median {np.median(base_m):.3f}, "
          f"rotation stiffness median {np.median(base_k):.2e} N·m/rad, 5th percentile "
          f"{np.percentile(base_k, 5):.2e}")


if __name__ == "__main__":
    main()
