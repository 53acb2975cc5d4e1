"""Batched solves on a GPU against the CPU kernels, measured in one run on one machine.

    python benchmarks/cuda_throughput.py [--batches 1 64 1024 16384 65536] [--repeat 3]
                                         [--robots fig3 three_tube] [--cpu-max 16384]
                                         [--json out.json]

For each robot and batch size ``B``: one batched ``torchpvs.solve`` of ``B`` configurations
(the Fig. 3 robot at rotations alpha2 in [0, 170] deg, on the stable branch; the three-tube
robot ``torchpvs.testing.nested_scene(3, seed=1)`` with rotations spread by 0.5 rad), cold and
warm (from the equilibria 1 deg away), default options (automatic order and Magnus steps,
forces and stability included), on

* ``cuda``: the eager kernel on the GPU (float64 and float32; at ``B >= 4096`` float64 also
  with the CPU's cache-sized chunks, ``batch_linalg.CHUNK_BYTES``, instead of the GPU's);
* ``cpu compiled``: the default CPU kernel (numba, elements across ``torch.get_num_threads()``
  threads);
* ``cpu eager``: the eager kernel on the CPU (the reference), up to ``--cpu-max`` elements.

It prints the time per solve [us] (best of ``--repeat`` calls after one untimed call, CUDA
synchronized), the ratio of each CPU kernel to the GPU, the largest tip difference of every run
from the CPU float64 eager solve of the same configurations (float32's error is what its speed
buys), and the GPU's peak memory per 1,000 elements above what was allocated before the case
(the robot plan's cached layout of the last batch stays allocated between calls). Needs a CUDA
device; not run in CI.
"""

from __future__ import annotations

import argparse
import json
import math
import platform
import time

import torch

import torchpvs as tp
from torchpvs import SolverOptions, batch_linalg
from torchpvs.testing import fig3, nested_scene


def workload(robot: str, B: int):
    """``(scene, rotations (B, N), rotations 1 deg away (B, N))``, float64 on the CPU."""
    if robot == "fig3":
        scene = fig3()
        a2 = torch.linspace(0.0, math.radians(170.0), B, dtype=torch.float64)
        rot = torch.stack([torch.zeros_like(a2), a2], -1)
    else:
        scene = nested_scene(3, seed=1)
        g = torch.Generator().manual_seed(0)
        rot = torch.tensor(scene.actuation.rotation, dtype=torch.float64) + 0.5 * torch.rand(
            B, scene.n_tubes, generator=g, dtype=torch.float64)
    near = rot.clone()
    near[:, -1] -= math.radians(1.0)
    return scene, rot, near


def timed(fn, repeat: int, cuda: bool) -> tuple[float, object]:
    out = fn()
    best = math.inf
    for _ in range(repeat):
        if cuda:
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        out = fn()
        if cuda:
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - t0)
    return best, out


def run_case(scene, rot, near, device: str, kernel: str, dtype, repeat: int):
    """Cold and warm per-solve times [s] and the warm solve's tips, converged count."""
    opts = SolverOptions(device=device, kernel=kernel, dtype=dtype)
    r, n = rot.to(device=device, dtype=dtype), near.to(device=device, dtype=dtype)
    cuda = device.startswith("cuda")
    if cuda:
        torch.cuda.reset_peak_memory_stats()
        # what earlier cases left allocated (the plans' cached layouts) is not this case's
        base = torch.cuda.memory_allocated()
    t_cold, eq_cold = timed(lambda: tp.solve(scene, rotation=r, options=opts), repeat, cuda)
    start = tp.solve(scene, rotation=n, options=opts)
    t_warm, eq = timed(lambda: tp.solve(scene, rotation=r, options=opts, initial=start),
                       repeat, cuda)
    peak = torch.cuda.max_memory_allocated() - base if cuda else float("nan")
    B = rot.shape[0]
    return {"cold_us": 1e6 * t_cold / B, "warm_us": 1e6 * t_warm / B,
            "converged": int(eq.converged.sum()), "converged_cold": int(eq_cold.converged.sum()),
            "tips": eq.tip_position.detach().double().cpu(), "peak_bytes_per_elem": peak / B,
            "iterations": float(eq.iterations.double().mean())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--batches", type=int, nargs="+", default=[1, 64, 1024, 16384, 65536])
    ap.add_argument("--robots", nargs="+", default=["fig3", "three_tube"],
                    choices=["fig3", "three_tube"])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--cpu-max", type=int, default=16384,
                    help="largest batch also run on the compiled CPU kernel")
    ap.add_argument("--eager-max", type=int, default=4096,
                    help="largest batch also run on the eager CPU kernel (the reference)")
    ap.add_argument("--gpu-chunk-mib", type=float, default=None,
                    help="batch_linalg.GPU_CHUNK_BYTES for the run, in MiB (default: as is)")
    ap.add_argument("--no-cpu-chunks", action="store_true",
                    help="skip the A/B run with the CPU's chunk size on the GPU")
    ap.add_argument("--json", default=None)
    a = ap.parse_args()
    if a.gpu_chunk_mib is not None:
        batch_linalg.GPU_CHUNK_BYTES = int(a.gpu_chunk_mib * 2**20)
    if not torch.cuda.is_available():
        raise SystemExit("cuda_throughput.py needs a CUDA device (torch.cuda.is_available() is "
                         "False)")
    props = torch.cuda.get_device_properties(0)
    print(f"# {props.name}, {props.total_memory / 2**30:.0f} GiB; torch {torch.__version__}; "
          f"CPU: {platform.processor() or platform.machine()}, "
          f"{torch.get_num_threads()} torch threads; Python {platform.python_version()}; "
          f"GPU chunks of {batch_linalg.GPU_CHUNK_BYTES / 2**20:g} MiB of Hessians")
    rows = []
    hdr = (f"{'robot':10} {'B':>6} {'run':22} {'cold us':>9} {'warm us':>9} {'its':>5} "
           f"{'conv':>6} {'tip err m':>9} {'GPU x':>7} {'MiB/1k':>7}")
    print(hdr)
    for robot in a.robots:
        for B in a.batches:
            scene, rot, near = workload(robot, B)
            cases = [("cuda float64", "cuda", "compiled", torch.float64),
                     ("cuda float32", "cuda", "compiled", torch.float32)]
            if B <= a.cpu_max:
                cases.append(("cpu compiled float64", "cpu", "compiled", torch.float64))
            if B <= a.eager_max:
                cases.append(("cpu eager float64", "cpu", "newton", torch.float64))
            if B >= 4096 and not a.no_cpu_chunks:
                cases.append(("cuda float64 cpu-chunks", "cuda", "compiled", torch.float64))
            res = {}
            for name, dev, kern, dt in cases:
                # the A/B of the GPU's chunk size: the CPU's cache-sized chunks on the GPU
                gpu_chunk = batch_linalg.GPU_CHUNK_BYTES
                if name.endswith("cpu-chunks"):
                    batch_linalg.GPU_CHUNK_BYTES = batch_linalg.CHUNK_BYTES
                try:
                    res[name] = run_case(scene, rot, near, dev, kern, dt, a.repeat)
                finally:
                    batch_linalg.GPU_CHUNK_BYTES = gpu_chunk
            ref = (res.get("cpu eager float64") or res.get("cpu compiled float64")
                   or res["cuda float64"])
            gpu = res["cuda float64"]["warm_us"]
            for name, r in res.items():
                err = float((r["tips"] - ref["tips"]).abs().max())
                ratio = r["warm_us"] / gpu
                mib = (r["peak_bytes_per_elem"] * 1000 / 2**20
                       if not math.isnan(r["peak_bytes_per_elem"]) else float("nan"))
                print(f"{robot:10} {B:6d} {name:22} {r['cold_us']:9.2f} {r['warm_us']:9.2f} "
                      f"{r['iterations']:5.2f} {r['converged']:6d} {err:9.1e} {ratio:7.2f} "
                      f"{mib:7.2f}", flush=True)
                rows.append({"robot": robot, "B": B, "run": name, "tip_err_m": err,
                             **{k: v for k, v in r.items() if k != "tips"}})
    print("# GPU x: this run's warm time per solve / the GPU float64 run's (> 1: the GPU is "
          "faster); tip err: against the CPU eager float64 solve of the same configurations (the "
          "compiled one above --eager-max, the GPU float64 one above --cpu-max)")
    if a.json:
        with open(a.json, "w") as f:
            json.dump({"device": props.name, "torch": torch.__version__,
                       "threads": torch.get_num_threads(), "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main()
