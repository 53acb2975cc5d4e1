"""HER and the snap penalty: what each way of keeping the penalty costs when sampling.

SB3's ``HerReplayBuffer`` relabels a stored transition with a goal achieved later in its episode
and recomputes the reward with ``env.compute_reward(next_achieved_goal, new_goal, infos)``; by
default (``copy_info_dict=False``) ``infos`` are empty dicts, so a snap flagged only in ``info``
is lost and a relabelled snap step reads reward 0 and done. Options compared, on the same
buffer of real transitions (fig3 robot, force actions, half the robots twisting hard so that
some episodes end in a snap):

* ``none``: the status quo before the fix (the flag ignored): how many relabelled snap steps
  lose their penalty;
* ``(a) flag``: the snap flag as a 4th entry of ``achieved_goal`` (what the envs do);
* ``(b) copy_info_dict``: ``HerReplayBuffer(copy_info_dict=True)`` with the flag in ``info``;
* ``(c) no relabel``: a buffer subclass that keeps the real goal and reward of snap steps.

For each: ms per ``sample(batch_size)`` (median over repeats), the memory the filled buffer
holds beyond its arrays (tracemalloc during the fill), and the fraction of sampled relabelled
snap steps that keep the penalty. Usage::

    python benchmarks/her_snap.py [--transitions 100000] [--batch-size 256] [--repeats 200]
"""

from __future__ import annotations

import argparse
import pickle
import time
import tracemalloc

import numpy as np
import torch


def collect(n_envs: int, steps: int, seed: int):
    """Real transitions ``(obs, next_obs, action, reward, done, infos)`` of ``CTRReachVecEnv``
    (next_obs is the terminal observation where an episode ended, as SB3 stores it)."""
    import envs
    venv = envs.CTRReachVecEnv(n_envs, max_episode_steps=30)
    venv.seed(seed)
    obs = venv.reset()
    rng = np.random.default_rng(seed)
    twist = np.zeros((n_envs, 4))
    twist[: n_envs // 2, 2:] = [-1.0, 1.0]        # drive the relative rotation: snaps
    records = []
    for _ in range(steps):
        a = np.clip(twist + 0.3 * rng.uniform(-1, 1, (n_envs, 4)), -1, 1).astype(np.float32)
        new_obs, rew, done, infos = venv.step(a)
        nxt = {k: v.copy() for k, v in new_obs.items()}
        for i in np.flatnonzero(done):
            for k in nxt:
                nxt[k][i] = infos[i]["terminal_observation"][k]
        records.append((obs, nxt, a, rew, done, infos))
        obs = new_obs
    return venv, records


def make_buffer(option: str, venv, size: int):
    from stable_baselines3 import HerReplayBuffer

    class NoRelabelSnaps(HerReplayBuffer):
        """Option (c): snap steps keep their real goal and reward when relabelled."""

        def _get_virtual_samples(self, batch_indices, env_indices, env=None):
            data = super()._get_virtual_samples(batch_indices, env_indices, env)
            snap = self.next_observations["achieved_goal"][batch_indices, env_indices, 3] > 0.5
            if snap.any():
                goal = self.observations["desired_goal"][batch_indices, env_indices]
                real = self.rewards[batch_indices, env_indices]
                for obs in (data.observations, data.next_observations):
                    obs["desired_goal"][snap] = self.to_torch(goal[snap])
                data.rewards[snap, 0] = self.to_torch(real[snap])
            return data

    cls = NoRelabelSnaps if option == "(c) no relabel" else HerReplayBuffer
    return cls(size, venv.observation_space, venv.action_space, env=venv,
               device="cpu", n_envs=venv.num_envs, n_sampled_goal=4,
               goal_selection_strategy="future",
               copy_info_dict=option == "(b) copy_info_dict")


class _FlagIgnored:
    """The status quo: ``compute_reward`` sees positions only (no flag, no info)."""

    def __init__(self, venv):
        self.venv = venv

    def env_method(self, name, ag, dg, infos, indices=None):
        return self.venv.env_method(name, ag[..., :3], dg[..., :3], [{}] * len(ag),
                                    indices=indices)

    def __getattr__(self, name):
        return getattr(self.venv, name)


def fill(buffer, records, n: int) -> float:
    """Add ``n`` transitions (cycling the records, with fresh info dicts as in training;
    SB3 buffers take the TOTAL size and hold ``size // n_envs`` rows);
    returns the memory [MB] allocated by the fill and still held (the buffer's arrays are
    preallocated, so this is what storing the infos costs)."""
    tracemalloc.start()
    before = tracemalloc.get_traced_memory()[0]
    k = 0
    while k * len(records[0][2]) < n:
        obs, nxt, a, rew, done, infos = records[k % len(records)]
        # an episode must end before its transitions are sampled; the records cycle, so
        # mark the end of each pass through them as done (time limit) for every robot
        last = (k % len(records)) == len(records) - 1
        # a pickle round trip makes every value a new object, as a fresh env step does
        # (deepcopy would share the floats of the records)
        buffer.add(obs, nxt, a, rew, done | last, pickle.loads(pickle.dumps(infos)))
        k += 1
    held = (tracemalloc.get_traced_memory()[0] - before) / 2**20
    tracemalloc.stop()
    return held


def measure(option: str, venv, records, n: int, batch_size: int, repeats: int, penalty: float):
    buffer = make_buffer(option, venv, n)
    if option == "none":
        buffer.env = _FlagIgnored(venv)
    held = fill(buffer, records, n)
    for _ in range(5):
        buffer.sample(batch_size)
    times, kept, total = [], 0, 0
    n_virtual = int(buffer.her_ratio * batch_size)
    for _ in range(repeats):
        t0 = time.perf_counter()
        data = buffer.sample(batch_size)
        times.append(time.perf_counter() - t0)
        snap = data.next_observations["achieved_goal"][-n_virtual:, 3] > 0.5
        r = data.rewards[-n_virtual:, 0]
        kept += int((r[snap] <= penalty + 1e-6).sum())
        total += int(snap.sum())
    return 1e3 * float(np.median(times)), held, kept / max(total, 1), total


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--transitions", type=int, default=100_000)
    p.add_argument("--batch-size", type=int, default=256)
    p.add_argument("--repeats", type=int, default=200)
    p.add_argument("--envs", type=int, default=16)
    p.add_argument("--steps", type=int, default=40)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args()
    torch.set_num_threads(1)
    venv, records = collect(args.envs, args.steps, args.seed)
    n_snaps = sum(int(sum(i["snap_terminated"] for i in r[5])) for r in records)
    print(f"{len(records) * args.envs} real transitions, {n_snaps} snap steps; buffer of "
          f"{args.transitions} transitions, batch {args.batch_size}, {args.repeats} samples")
    penalty = venv.config.snap_penalty
    print(f"{'option':22s} {'ms/sample':>10s} {'MB held':>9s} {'penalty kept':>13s}")
    for option in ("none", "(a) flag", "(b) copy_info_dict", "(c) no relabel"):
        ms, held, kept, total = measure(option, venv, records, args.transitions,
                                        args.batch_size, args.repeats, penalty)
        print(f"{option:22s} {ms:10.2f} {held:9.1f} {kept:9.2f} of {total}")


if __name__ == "__main__":
    main()
