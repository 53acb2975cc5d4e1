"""Where the compiled Newton's time goes, per robot: the whole damped Newton of a batch against
its parts (the energy at orders 0, 1 and 2, the Cholesky factor and solve), timed in one process.

    python benchmarks/newton_anatomy.py [--robot fig3_two_tube] [--batch 64] [--repeat 5]

The batch is what the force environment solves each step: ``--batch`` random feasible
actuations of the robot with the environment's solver options, each solved warm from its
equilibrium after a small random actuator move (0.1 mm, 0.6 deg rms). The compiled Newton's
arguments are captured from that solve (:func:`torchpvs.compiled._newton_serial`) and the same
arrays are then timed: the whole Newton (fresh copies per round), and the numba functions it
calls, per robot, best of ``--repeat`` rounds. One thread. Printed: microseconds per robot,
the mean iteration count and an estimate of the Newton from its parts (evaluations: one of
order 2 per iterate, ``iterations + 1``; a factor per iteration and one for the saddle test;
the line search's order-0 evaluations are counted separately), which tells how much of the
Newton is arithmetic in those parts and how much is elsewhere.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--robot", default="fig3_two_tube")
    p.add_argument("--batch", type=int, default=64)
    p.add_argument("--repeat", type=int, default=5)
    p.add_argument("--seed", type=int, default=0)
    args = p.parse_args(argv)
    torch.set_num_threads(1)

    from numba import njit

    import torchpvs.compiled as C
    from envs.robots import make_robot, solve_batch

    robot = make_robot(args.robot)
    rng = np.random.default_rng(args.seed)
    x = robot.sample_actuation(rng, args.batch)
    eq = solve_batch(robot, x)
    N = robot.n_tubes
    x2 = x + rng.normal(size=x.shape) * np.array([1e-4] * N + [0.01] * N)
    captured = {}
    newton = C._newton_serial

    def spy(*a):
        captured["args"] = [np.copy(v) if isinstance(v, np.ndarray) else v for v in a]
        return newton(*a)

    C._newton_serial = spy
    try:
        solve_batch(robot, x2, initial=eq.q)
    finally:
        C._newton_serial = newton
    if "args" not in captured:
        raise SystemExit("the solve did not run the compiled Newton (is numba installed?)")
    a = captured["args"]
    (q, qm, psi0, bvec, h, us, EIw, EIws, GJw, Hsec, guide, gconst, phi, Qb, LD) = a[:15]
    B, nc = q.shape

    def fresh():
        return [np.copy(v) if isinstance(v, np.ndarray) else v for v in a]

    run = fresh()
    newton(*run)
    iters = run[23].astype(float)

    @njit(nogil=True)
    def energies(order, reps, g, H):
        s = 0.0
        for _ in range(reps):
            for b in range(q.shape[0]):
                s += C.evaluate(q[b], qm[b], psi0[b], bvec[b], h[b], us[b], EIw[b], EIws[b],
                                GJw[b], Hsec[b], guide[b], gconst[b], phi, Qb, order, g[b], H[b])
        return s

    @njit(nogil=True)
    def factors(A, rhs, reps, x):
        L = np.zeros_like(A[0])
        ok = 0
        for _ in range(reps):
            for b in range(A.shape[0]):
                ok += C.cholesky(A[b], L)
                C.cho_solve(L, rhs[b], x[b])
        return ok

    g = np.zeros((B, nc))
    H = np.zeros((B, nc, nc))
    energies(2, 1, g, H)
    A = H + np.eye(nc) * (1e-9 * np.abs(H).max())    # the Hessians at the solution
    rhs = np.ascontiguousarray(g)
    xs = np.zeros_like(rhs)
    factors(A, rhs, 1, xs)

    def best(fn):
        times = []
        for _ in range(args.repeat):
            t = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t)
        return min(times)

    reps = 10
    t_newton = best(lambda: [newton(*fresh()) for _ in range(reps)]) / reps / B * 1e6
    t_copy = best(lambda: [fresh() for _ in range(reps)]) / reps / B * 1e6
    t_e = {o: best(lambda o=o: energies(o, reps, g, H)) / reps / B * 1e6 for o in (0, 1, 2)}
    t_f = best(lambda: factors(A, rhs, reps, xs)) / reps / B * 1e6
    it = float(iters.mean())
    est = (it + 1) * t_e[2] + (it + 1) * t_f
    print(f"{args.robot}: B = {B}, {nc} compact coordinates, {h.shape[1]} sections, "
          f"{phi.shape[0]} nodes per section, mean Newton iterations {it:.2f}")
    print(f"  whole compiled Newton      {t_newton - t_copy:8.2f} us per robot "
          f"(argument copies {t_copy:.2f} us subtracted)")
    for o in (0, 1, 2):
        print(f"  energy, order {o}           {t_e[o]:8.2f} us")
    print(f"  Cholesky factor + solve    {t_f:8.2f} us")
    print(f"  (iterations + 1) x (order-2 energy + factor) = {est:.2f} us, "
          f"{est / max(t_newton - t_copy, 1e-9):.0%} of the Newton; the rest is line-search "
          f"energies (order 0) and the per-iteration bookkeeping")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
