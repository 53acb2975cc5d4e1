"""Peer benchmark: torchpvs against a compiled C++ CTR library, timed in one process.

    python benchmarks/peer_cpp.py --peer PATH [--configs 16] [--repeat 5] [--batch 1024]
                                  [--max-deg 170] [--smoothing 1e-9] [--build-dir DIR]
                                  [--rebuild] [--json out.json]

The peer: H. Gilbert's C++ kinematics templates, ``ReferenceCannulaKinematics/`` of
https://github.com/medlabprojects/ConcentricTubeMexLibrary (``--peer`` or ``$CTR_PEER``: the
checkout, the folder that contains ``ReferenceCannulaKinematics/``). Not run in CI.

Build: our driver ``benchmarks/peer_cpp/driver.cpp`` plus the peer's ``Rk8_Coeffs.cpp`` and
``TaggedInterval.cpp`` into one shared library loaded with ctypes, so that both sides run in
this process, interleaved round by round. Requirements: g++ (``--cxx``), Eigen 3 headers
(Debian/Ubuntu ``apt install libeigen3-dev``) and Boost headers (``apt install libboost-dev``;
the peer uses boost::mpl, fusion, container, io). Flags: ``-O3 -DNDEBUG -Dlinux -march=native
-std=c++17 -fPIC -shared -include iterator -w`` (the peer's Makefile uses ``-O3 -DNDEBUG -Dlinux``
plus ``-g -fsanitize=address -flto``; the sanitizer is a debugging aid that slows the code and
is left out, ``-march=native`` matches numba's host-CPU code; ``-include iterator``:
TaggedInterval.h uses std::ostream_iterator without including <iterator>). The library is
cached under ``--build-dir`` (default ``~/.cache/torchpvs/peer_cpp``), keyed by a hash of the
sources, flags and compiler, and rebuilt only when one of them changes.

Robot: the Fig. 3 scene (``renda2021_fig3``), its parameters passed from Python (peer order:
innermost tube first, ``Beta = -D``, ``L`` = total, ``Lt`` = straight length, precurvature
``(u*x, u*y)``). The peer has no guide: its tubes are free at ``s < 0``; a scene is accepted
only when every tube's curved part lies beyond the orifice (``D_j <= straight_length_j``), where
both models are the same. The peer smooths the precurvature over 1 mm at each end of the
curved part; ``--smoothing`` (default 1e-9 m, a step as in torchpvs) sets that width.

Workload: ``--configs`` configurations, the last tube's rotation spread over [0, ``--max-deg``]
deg (control_step.py's sweep, to 170 deg by default: above 180 deg the Fig. 3 robot is bistable
and cold solves of the two codes may pick different branches), the rest as in the scene; one
torch thread. The equilibria 1 deg away that the warm cases start from are followed along the
branch from rotation 0 in steps of at most 1 deg, on both sides, so that both solve the same
equilibrium. Cases (B = 1):

* warm: the solve at each configuration from the equilibrium 1 deg away. Peer: shooting
  Newton on the tip angles ``PsiL`` with ``Zta = d psi(base)/d PsiL`` from the library (a
  backtracking line search, full steps when warm) until ``max_j |psi_j(base) - alpha_j| <
  1e-10`` rad, started at the neighbour's ``PsiL``; tip position returned. torchpvs:
  ``torchpvs.solve(scene, rotation=..., initial=eq)``, default ``SolverOptions`` (the compiled
  kernel; its forces and stability included, as a user gets them).
* cold: the same solves without a warm start (peer: ``PsiL = alpha``; torchpvs: no
  ``initial``). A cold shooting Newton can converge to another (possibly unstable) equilibrium;
  such configurations are counted and printed with the peer's stability measure.
* control step: warm solve + the tip Jacobian w.r.t. the actuators. Peer: the library's
  body Jacobian ``GetTipJacobianForTube1`` (per ``PsiL, Beta``) at the solution, mapped to the
  actuators through ``Zta`` (``dPsiL = Zpp^-1 (dalpha - Zpb dBeta)``, the elimination of its
  own ``GetTipComplianceForTube1``) and rotated to the base frame (its fwkin_*.m), 6 x 2N.
  torchpvs: ``solve(...).jacobians(compliance=False)`` (stiffness, tip and force Jacobians).
* B = ``--batch`` warm, per solve: one batched torchpvs call (the configurations repeated),
  against the peer's single warm solve (the peer has no batched solve).

The peer runs each case with every evaluation strategy of the driver (solve: geometry in every
Newton integration, or torsion only then one geometry integration; control step: Jacobian
options in every integration, or a lighter Newton then one Jacobian integration) and its best is
the figure. Its solves run in one C++ loop per call (one ctypes call per case and round);
torchpvs's in a Python loop, one ``torchpvs.solve`` per configuration, as a user calls it.
Timings: best of ``--repeat`` rounds, each round timing peer then torchpvs per case (after one
untimed call of each). Targets: torchpvs/peer <= 1 warm, cold and control step, <= 0.1 at
B = ``--batch`` against the peer's warm solve.

Agreement printed: the largest tip distance [m] between peer and torchpvs (warm; torchpvs at
default and at 1e-9 m accuracy; cold where both reach the same equilibrium), and the position
rows of the tip Jacobians per column (torchpvs ``tip_jacobian[:, :3]`` in ``(D, alpha)``,
outermost first) against the peer's library Jacobian and against finite differences of the
peer's own solves. Known findings on the Fig. 3 robot: the rotation columns agree; the peer
library's insertion columns disagree with its own finite differences (``integrate_impl`` skips
the transition at the innermost tube's base -- its own test compensates for that term -- and
with a near-step smoothing the precurvature-ramp terms are wrong too); and at D_1 = the outer
tube's straight length the tip has a kink in D_1: torchpvs reports the retracting side there
(its closed form against both one-sided differences is printed), and the peer's differences
are taken on that side. Run on an idle machine.
"""

from __future__ import annotations

import argparse
import ctypes
import hashlib
import json
import math
import os
import shutil
import subprocess
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch
from fast_path import bench_scene  # a sibling script (run from benchmarks/)

import torchpvs

HERE = Path(__file__).resolve().parent
DRIVER = HERE / "peer_cpp" / "driver.cpp"
PEER_URL = "https://github.com/medlabprojects/ConcentricTubeMexLibrary"
PEER_SOURCES = ("Rk8_Coeffs.cpp", "TaggedInterval.cpp")
CXXFLAGS = ["-O3", "-DNDEBUG", "-Dlinux", "-march=native", "-std=c++17", "-fPIC", "-shared",
            "-include", "iterator", "-w"]
EIGEN_DIRS = ["/usr/include/eigen3", "/usr/local/include/eigen3", "/opt/homebrew/include/eigen3"]
TOL = 1e-10          # peer shooting tolerance [rad]
MAX_ITER = 50
SOLVE_STRATEGIES = {0: "geometry in every integration", 1: "torsion, then geometry"}
CONTROL_STRATEGIES = {2: "Jacobian in every integration", 3: "geometry, then Jacobian",
                      4: "torsion, then Jacobian"}
TARGETS = {"warm": 1.0, "cold": 1.0, "control": 1.0, "batch": 0.1}


def fail(msg: str, code: int = 2):
    print(f"peer_cpp.py: {msg}", file=sys.stderr)
    sys.exit(code)


# --- the peer's build -------------------------------------------------------------------------
def peer_dir(arg: str | None) -> Path:
    src = arg or os.environ.get("CTR_PEER")
    if not src:
        fail("no peer checkout: pass --peer PATH or set CTR_PEER to the folder that contains "
             "ReferenceCannulaKinematics/, e.g.\n"
             f"    git clone {PEER_URL} ~/src/ConcentricTubeMexLibrary\n"
             "    python benchmarks/peer_cpp.py --peer ~/src/ConcentricTubeMexLibrary")
    root = Path(src).expanduser().resolve()
    kin = root / "ReferenceCannulaKinematics"
    if not (kin / "Kinematics.h").is_file():
        if (root / "Kinematics.h").is_file():   # given the folder itself
            return root
        fail(f"{root} does not contain ReferenceCannulaKinematics/Kinematics.h "
             f"(a checkout of {PEER_URL})")
    return kin


def _header_found(cxx: str, header: str, includes: list[str]) -> bool:
    code = f"#include <{header}>\n"
    r = subprocess.run([cxx, "-E", "-x", "c++", "-", "-o", os.devnull, *includes],
                       input=code, text=True, capture_output=True)
    return r.returncode == 0


def check_toolchain(cxx: str) -> list[str]:
    """The ``-I`` flags for Eigen; exits 2 naming what is missing."""
    if shutil.which(cxx) is None:
        fail(f"C++ compiler {cxx!r} not found (install g++, e.g. apt install g++, or pass --cxx)")
    eigen = [f"-I{d}" for d in EIGEN_DIRS if Path(d, "Eigen", "Dense").is_file()][:1]
    if not _header_found(cxx, "Eigen/Dense", eigen):
        fail("header <Eigen/Dense> not found (looked in the compiler's paths and "
             f"{', '.join(EIGEN_DIRS)}): install Eigen 3 (Debian/Ubuntu: apt install "
             "libeigen3-dev)")
    for h in ("boost/container/static_vector.hpp", "boost/fusion/container.hpp",
              "boost/mpl/vector.hpp", "boost/io/ios_state.hpp"):
        if not _header_found(cxx, h, []):
            fail(f"header <{h}> not found: install the Boost headers "
                 "(Debian/Ubuntu: apt install libboost-dev)")
    return eigen


def build(peer: Path, cxx: str, build_dir: Path, rebuild: bool) -> Path:
    """The driver's shared library, built into ``build_dir/<hash>/`` unless already there."""
    flags = list(CXXFLAGS)
    h = hashlib.sha256()
    version = subprocess.run([cxx, "--version"], capture_output=True, text=True).stdout
    h.update(version.encode())
    h.update(" ".join(flags).encode())
    h.update(DRIVER.read_bytes())
    for f in sorted(peer.glob("*.h")) + [peer / s for s in PEER_SOURCES]:
        h.update(f.name.encode())
        h.update(f.read_bytes())
    out_dir = build_dir / h.hexdigest()[:16]
    lib = out_dir / "libpeer_cpp.so"
    if lib.is_file() and not rebuild:
        return lib
    eigen = check_toolchain(cxx)
    out_dir.mkdir(parents=True, exist_ok=True)
    tmp = out_dir / f"libpeer_cpp.{os.getpid()}.tmp.so"
    cmd = [cxx, *flags, f"-I{peer}", *eigen, str(DRIVER), *(str(peer / s) for s in PEER_SOURCES),
           "-o", str(tmp)]
    print(f"building the peer driver into {out_dir} (about 30 s) ...", file=sys.stderr,
          flush=True)
    r = subprocess.run(cmd, capture_output=True, text=True)
    if r.returncode != 0:
        fail("the peer driver did not build:\n  " + " ".join(cmd) + "\n"
             + "\n".join(r.stderr.splitlines()[-30:]))
    os.replace(tmp, lib)
    (out_dir / "build_command.txt").write_text(" ".join(cmd) + "\n")
    return lib


class Peer:
    """The ctypes side of driver.cpp for one robot (arrays in peer order: innermost first)."""

    def __init__(self, lib_path: Path, scene, smoothing: float):
        self.lib = lib = ctypes.CDLL(str(lib_path))
        D, I = ctypes.POINTER(ctypes.c_double), ctypes.POINTER(ctypes.c_int)
        lib.peer_abi_version.restype = ctypes.c_int
        if lib.peer_abi_version() != 2:
            fail(f"{lib_path}: unexpected driver version (pass --rebuild)")
        lib.peer_create.restype = ctypes.c_void_p
        lib.peer_create.argtypes = [ctypes.c_int] + [D] * 8 + [ctypes.c_double]
        lib.peer_destroy.argtypes = [ctypes.c_void_p]
        lib.peer_solve_many.restype = ctypes.c_int
        lib.peer_solve_many.argtypes = [ctypes.c_void_p, ctypes.c_int, D, D, D, ctypes.c_double,
                                        ctypes.c_int, ctypes.c_int, D, D, D, I, I, D]
        tubes = scene.tubes[::-1]
        self.n = n = len(tubes)
        cols = {"L": [t.length for t in tubes], "Lt": [t.straight_length for t in tubes],
                "OD": [t.outer_diameter for t in tubes], "ID": [t.inner_diameter for t in tubes],
                "kx": [_const(t.precurvature[0]) for t in tubes],
                "ky": [_const(t.precurvature[1]) for t in tubes],
                "E": [t.E for t in tubes], "G": [t.G for t in tubes]}
        self._keep = [np.ascontiguousarray(v, dtype=np.float64) for v in cols.values()]
        self.h = lib.peer_create(n, *(_ptr(a) for a in self._keep), float(smoothing))
        if not self.h:
            fail(f"the peer driver supports 2 or 3 tubes, not {n}")

    def __del__(self):
        if getattr(self, "h", None):
            self.lib.peer_destroy(self.h)

    def prepare(self, alpha: np.ndarray, beta: np.ndarray, psi0: np.ndarray, strategy: int):
        """A zero-argument call solving every configuration (rows, peer order), and its outputs."""
        m, n = alpha.shape
        a, b, p0 = (np.ascontiguousarray(x, dtype=np.float64) for x in (alpha, beta, psi0))
        out = {"tip": np.zeros((m, 3)), "jac": np.zeros((m, 6, 2 * n)), "psi": np.zeros((m, n)),
               "iters": np.zeros(m, dtype=np.int32), "evals": np.zeros(m, dtype=np.int32),
               "stability": np.zeros(m)}
        args = (self.h, m, _ptr(a), _ptr(b), _ptr(p0), TOL, MAX_ITER, strategy,
                _ptr(out["tip"]), _ptr(out["jac"]), _ptr(out["psi"]),
                out["iters"].ctypes.data_as(ctypes.POINTER(ctypes.c_int)),
                out["evals"].ctypes.data_as(ctypes.POINTER(ctypes.c_int)), _ptr(out["stability"]))
        keep = (a, b, p0)

        def call():
            _ = keep
            return self.lib.peer_solve_many(*args)
        return call, out


def _ptr(a: np.ndarray):
    return a.ctypes.data_as(ctypes.POINTER(ctypes.c_double))


def _const(coeffs) -> float:
    c = list(coeffs) or [0.0]
    if any(x != 0.0 for x in c[1:]):
        raise ValueError("the peer driver takes constant precurvature only")
    return float(c[0])


def check_scene(scene) -> None:
    """The scenes on which the peer's model is torchpvs's (exits 2 otherwise)."""
    for j, t in enumerate(scene.tubes):
        ux, uy, uz = t.precurvature
        if any(c != 0.0 for c in (*ux[1:], *uy[1:], *uz)):
            fail(f"tubes[{j}]: the peer driver takes constant u*x, u*y and no u*z")
        if scene.actuation.insertion[j] > t.straight_length + 1e-12:
            fail(f"tubes[{j}]: D ({scene.actuation.insertion[j]} m) exceeds the straight length "
                 f"({t.straight_length} m): its curved part would enter the guide, which the "
                 "peer does not model")
    if any(scene.load.tip_force) or any(scene.load.tip_moment):
        fail("the scene has a tip load; this benchmark compares unloaded robots")


# --- the benchmark ----------------------------------------------------------------------------
def time_rounds(cases: dict, repeat: int) -> dict:
    """Best time [s] of each ``cases[name] = (peer_fn, torchpvs_fn)``: one untimed call each,
    then ``repeat`` rounds, every round timing the peer then torchpvs for each case in turn."""
    best = {k: [math.inf, math.inf] for k in cases}
    for fns in cases.values():
        for fn in fns:
            if fn is not None:
                fn()
    for _ in range(repeat):
        for k, fns in cases.items():
            for i, fn in enumerate(fns):
                if fn is None:
                    continue
                t0 = time.perf_counter()
                fn()
                best[k][i] = min(best[k][i], time.perf_counter() - t0)
    return best


def bench(args, lib_path: Path) -> dict:
    scene = bench_scene("fig3")
    check_scene(scene)
    N, C = scene.n_tubes, args.configs
    step = math.radians(1.0)
    base = torch.tensor(scene.actuation.rotation, dtype=torch.float64)
    rot0 = base.repeat(C, 1)
    rot0[:, -1] = torch.linspace(0, math.radians(args.max_deg), C, dtype=torch.float64) - step
    rot1 = rot0.clone()
    rot1[:, -1] += step
    ins = torch.tensor(scene.actuation.insertion, dtype=torch.float64)

    # Peer arrays (innermost first, Beta = -D).
    peer = Peer(lib_path, scene, args.smoothing)
    a0, a1 = rot0.numpy()[:, ::-1].copy(), rot1.numpy()[:, ::-1].copy()
    beta = np.repeat(-ins.numpy()[::-1][None], C, 0).copy()

    # Warm starts on the same branch for both: followed from the scene's other rotations with
    # the last one at 0 in steps of at most 1 deg (above 180 deg the Fig. 3 robot is bistable,
    # and a cold solve of either code may land on the other branch).
    warm, psi0 = [], np.zeros((C, N))
    prev_eq, prev_psi, prev_angle = None, a0[:1].copy(), 0.0
    prev_psi[0, 0] = 0.0
    for i in range(C):
        target = float(rot0[i, -1])
        n_steps = max(1, math.ceil(abs(target - prev_angle) / step - 1e-9))
        for t in np.linspace(prev_angle, target, n_steps + 1)[1:]:
            r = rot0[i].clone()
            r[-1] = float(t)
            prev_eq = torchpvs.solve(scene, rotation=r[None], initial=prev_eq)
            ap = r.numpy()[::-1].copy()[None]
            call, o = peer.prepare(ap, beta[:1], prev_psi, 0)
            if call():
                fail(f"peer: the branch-following solve at {math.degrees(t):.1f} deg failed")
            prev_psi = o["psi"].copy()
        warm.append(prev_eq)
        psi0[i] = prev_psi[0]
        prev_angle = target
    pairs = list(zip(rot1, warm, strict=True))
    B = args.batch
    reps = -(-B // C)
    R0, R1 = rot0.repeat(reps, 1)[:B], rot1.repeat(reps, 1)[:B]
    same = len({e.q.shape[-1] for e in warm}) == 1
    q0 = torch.cat([e.q for e in warm]) if same else None
    E0 = torchpvs.solve(scene, rotation=R0, initial=q0.repeat(reps, 1)[:B] if same else None)

    peer_calls = {}
    for s in SOLVE_STRATEGIES:
        peer_calls[("warm", s)] = peer.prepare(a1, beta, psi0, s)
        peer_calls[("cold", s)] = peer.prepare(a1, beta, a1, s)
    for s in CONTROL_STRATEGIES:
        peer_calls[("control", s)] = peer.prepare(a1, beta, psi0, s)
    tip_only = torchpvs.SolverOptions(compute_forces=False)
    # torchpvs.Tracker: the control loop's fused warm step at the discretization its first
    # (default) solve chose; one tracker per configuration, each placed on the warm
    # equilibrium and restored to it before every timed step (restore is part of the time)
    trackers = [torchpvs.Tracker(scene, rotation=r0[None], initial=e)
                for r0, e in zip(rot0, warm, strict=True)]
    snaps = [t.snapshot() for t in trackers]
    ins_np = ins.numpy()
    rot1_np = rot1.numpy()

    def tracker_steps(jacobians=False):
        out = []
        for t, s, r in zip(trackers, snaps, rot1_np, strict=True):
            t.restore(s)
            out.append(t.step(ins_np, r, jacobians=jacobians))
        return out
    batch_tracker = torchpvs.Tracker(scene, rotation=R0, initial=E0)
    batch_snap = batch_tracker.snapshot()
    ins_B, R1_np = np.repeat(ins_np[None], B, 0), R1.numpy()

    def tracker_batch():
        batch_tracker.restore(batch_snap)
        return batch_tracker.step(ins_B, R1_np)
    tp = {
        "warm": lambda: [torchpvs.solve(scene, rotation=r[None], initial=e) for r, e in pairs],
        # what the peer computes: the tip alone, no actuation forces (at the Fig. 3 scene's
        # insertion the outer tube's curved part starts at the orifice, a kink whose
        # one-sided forces take a second, two-sided evaluation)
        "warm_tip": lambda: [torchpvs.solve(scene, rotation=r[None], initial=e,
                                            options=tip_only) for r, e in pairs],
        "cold": lambda: [torchpvs.solve(scene, rotation=r[None]) for r, _ in pairs],
        "control": lambda: [torchpvs.solve(scene, rotation=r[None], initial=e)
                            .jacobians(compliance=False) for r, e in pairs],
        "batch": lambda: torchpvs.solve(scene, rotation=R1, initial=E0),
        "tracker": tracker_steps,
        "tracker_control": lambda: tracker_steps(jacobians=True),
        "tracker_batch": tracker_batch,
    }
    cases = {f"peer_{k}_{s}": (fn, None) for (k, s), (fn, _) in peer_calls.items()}
    # interleave: each torchpvs case right after the peer's strategies for it
    ordered = {}
    for k in ("warm", "cold", "control", "batch"):
        for name, v in cases.items():
            if name.startswith(f"peer_{k}_"):
                ordered[name] = v
        ordered[f"torchpvs_{k}"] = (None, tp[k])
        if k == "warm":
            ordered["torchpvs_warm_tip"] = (None, tp["warm_tip"])
            ordered["torchpvs_tracker"] = (None, tp["tracker"])
        if k == "control":
            ordered["torchpvs_tracker_control"] = (None, tp["tracker_control"])
        if k == "batch":
            ordered["torchpvs_tracker_batch"] = (None, tp["tracker_batch"])
    best = time_rounds(ordered, args.repeat)

    out = {"robot": "fig3", "tubes": N, "configs": C, "max_deg": args.max_deg,
           "batch": B, "repeat": args.repeat, "smoothing": args.smoothing, "tol_rad": TOL}
    for k, strategies in (("warm", SOLVE_STRATEGIES), ("cold", SOLVE_STRATEGIES),
                          ("control", CONTROL_STRATEGIES)):
        t = {s: best[f"peer_{k}_{s}"][0] / C for s in strategies}
        s_best = min(t, key=t.get)
        _, o = peer_calls[(k, s_best)]
        if np.any(o["iters"] < 0):
            fail(f"peer: {np.sum(o['iters'] < 0)} {k} solves did not converge")
        out[f"peer_{k}_ms"] = 1e3 * t[s_best]
        out[f"peer_{k}_strategy"] = strategies[s_best]
        out[f"peer_{k}_strategy_ms"] = {strategies[s]: 1e3 * v for s, v in t.items()}
        out[f"peer_{k}_newton_steps"] = float(o["iters"].mean())
        out[f"peer_{k}_integrations"] = float(o["evals"].mean())
        out[f"torchpvs_{k}_ms"] = 1e3 * best[f"torchpvs_{k}"][1] / C
    out["torchpvs_batch_ms"] = 1e3 * best["torchpvs_batch"][1] / B
    out["torchpvs_warm_tip_ms"] = 1e3 * best["torchpvs_warm_tip"][1] / C
    out["warm_tip_ratio"] = out["torchpvs_warm_tip_ms"] / out["peer_warm_ms"]
    out["torchpvs_tracker_ms"] = 1e3 * best["torchpvs_tracker"][1] / C
    out["tracker_ratio"] = out["torchpvs_tracker_ms"] / out["peer_warm_ms"]
    out["torchpvs_tracker_control_ms"] = 1e3 * best["torchpvs_tracker_control"][1] / C
    out["tracker_control_ratio"] = out["torchpvs_tracker_control_ms"] / out["peer_control_ms"]
    out["torchpvs_tracker_batch_ms"] = 1e3 * best["torchpvs_tracker_batch"][1] / B
    out["tracker_batch_ratio"] = out["torchpvs_tracker_batch_ms"] / out["peer_warm_ms"]
    out["tracker_order"], out["tracker_n_magnus"] = trackers[0].order, trackers[0].n_magnus
    out["peer_batch_ms"] = out["peer_warm_ms"]
    for k in TARGETS:
        out[f"{k}_ratio"] = out[f"torchpvs_{k}_ms"] / out[f"peer_{k}_ms"]
        out[f"{k}_target"] = TARGETS[k]
        out[f"{k}_met"] = out[f"{k}_ratio"] <= TARGETS[k]

    # Agreement. Warm: the same branch on both sides by construction. Cold: each code's own
    # answer, which may be another equilibrium (a cold shooting Newton can also converge to an
    # unstable one); those are counted and left out of the cold figure.
    warm1 = [torchpvs.solve(scene, rotation=r[None], initial=e) for r, e in pairs]
    tip_w = np.stack([e.tip_position[0].numpy() for e in warm1])
    tip_c = np.stack([torchpvs.solve(scene, rotation=r[None]).tip_position[0].numpy()
                      for r, _ in pairs])
    q1 = torch.cat([e.q for e in warm1]) if len({e.q.shape[-1] for e in warm1}) == 1 else None
    tight = torchpvs.solve(scene, rotation=rot1, initial=q1,
                           options=torchpvs.SolverOptions(accuracy=1e-9))
    tip_t = tight.tip_position.numpy()
    pw = peer_calls[("warm", 0)][1]["tip"]
    pc, pc_stab = peer_calls[("cold", 0)][1]["tip"], peer_calls[("cold", 0)][1]["stability"]
    dist = lambda a, b: np.linalg.norm(a - b, axis=1)  # noqa: E731
    d_w, d_c, d_t = dist(pw, tip_w), dist(pc, tip_c), dist(pw, tip_t)
    same_c = d_c < 1e-5
    out["tip_max_diff_warm_m"] = float(d_w.max())
    tip_tr = np.concatenate([st.tip for st in tracker_steps()])
    out["tip_max_diff_tracker_m"] = float(dist(pw, tip_tr).max())
    out["tip_max_diff_tight_m"] = float(d_t.max())
    out["torchpvs_tight_converged"] = bool(tight.converged.all())
    out["tip_max_diff_cold_m"] = float(d_c[same_c].max()) if same_c.any() else None
    out["cold_other_equilibrium"] = int((~same_c).sum())
    out["cold_other_peer_stability"] = pc_stab[~same_c].tolist()
    out["cold_other_deg"] = [round(math.degrees(float(rot1[i, -1])), 2)
                             for i in np.nonzero(~same_c)[0]]
    out["peer_warm_stability_min"] = float(peer_calls[("warm", 0)][1]["stability"].min())
    out["tip_diff_warm_per_config_m"] = d_w.tolist()
    out["torchpvs_error_estimate_max_m"] = float(max(float(e.error_estimate.max())
                                                     for e in warm1))

    # Tip Jacobians, position rows, in torchpvs's columns (D_1..D_N, alpha_1..alpha_N),
    # outermost first. Peer: (alpha, Beta) innermost first, Beta = -D.
    to_tp = lambda J: np.concatenate([-J[..., N:][..., ::-1], J[..., :N][..., ::-1]], -1)  # noqa: E731
    J_peer = to_tp(peer_calls[("control", 2)][1]["jac"][:, :3])
    J_tp = np.stack([e.jacobians(compliance=False).tip_jacobian[0, :3].numpy() for e in warm1])
    J_fd = to_tp(peer_fd_jacobian(peer, a1, beta, peer_calls[("warm", 0)][1]))
    per_col = lambda d: d.max(axis=(0, 1)).tolist()  # noqa: E731
    out["jacobian_columns"] = ([f"D_{j + 1}" for j in range(N)]
                               + [f"alpha_{j + 1}" for j in range(N)])
    out["jacobian_scale"] = per_col(abs(J_tp))
    out["jacobian_diff_peer_tp"] = per_col(abs(J_peer - J_tp))
    out["jacobian_diff_peerfd_tp"] = per_col(abs(J_fd - J_tp))
    out["jacobian_diff_peer_peerfd"] = per_col(abs(J_peer - J_fd))
    out["insertion_kinks"] = [j + 1 for j, t in enumerate(scene.tubes)
                              if abs(scene.actuation.insertion[j] - t.straight_length) < 1e-12
                              and t.is_precurved]
    # At such a kink: torchpvs's closed form against its own one-sided differences.
    tight_opt = torchpvs.SolverOptions(accuracy=1e-9)
    h = 1e-6
    for j in out["insertion_kinks"]:
        sides = {}
        for name, sgn in (("advancing", -1.0), ("retracting", 1.0)):
            d = []
            for (r, _), e in zip(pairs, warm1, strict=True):
                x0 = ins.clone()[None]
                x1 = x0.clone()
                x1[0, j - 1] += sgn * h
                e0 = torchpvs.solve(scene, rotation=r[None], insertion=x0, initial=e,
                                    options=tight_opt)
                e1 = torchpvs.solve(scene, rotation=r[None], insertion=x1, initial=e0,
                                    options=tight_opt)
                fd = ((e1.tip_position - e0.tip_position)[0] / (sgn * h)).numpy()
                Jc = e.jacobians(compliance=False).tip_jacobian[0, :3, j - 1].numpy()
                d.append(float(np.abs(fd - Jc).max()))
            sides[name] = max(d)
        out[f"torchpvs_kink_D{j}_closed_form_vs_fd"] = sides
    return out


def peer_fd_jacobian(peer: Peer, alpha: np.ndarray, beta: np.ndarray, base: dict,
                     h_rot: float = 1e-5, h_ins: float = 1e-6) -> np.ndarray:
    """The peer's actuator tip-position Jacobian by finite differences of its own solves
    ``(m, 3, 2N)`` (peer columns: alpha, then Beta, innermost first), warm from ``base``.
    Rotations: central differences. Insertions: second-order one-sided differences towards
    smaller Beta (retracting the tube, the side torchpvs reports at a kink): at the Fig. 3
    insertion the outer tube's curved part starts exactly at the orifice and the tip is not
    differentiable in that D (a kink)."""
    m, N = alpha.shape
    rows_a, rows_b, rows_p = [], [], []
    for j in range(N):
        for d in (h_rot, -h_rot):
            a = alpha.copy()
            a[:, j] += d
            rows_a.append(a), rows_b.append(beta), rows_p.append(base["psi"])
    for j in range(N):
        for d in (-h_ins, -2 * h_ins):
            b = beta.copy()
            b[:, j] += d
            rows_a.append(alpha), rows_b.append(b), rows_p.append(base["psi"])
    call, o = peer.prepare(np.concatenate(rows_a), np.concatenate(rows_b),
                           np.concatenate(rows_p), 0)
    if call():
        fail("peer: a finite-difference solve did not converge")
    tips = o["tip"].reshape(-1, m, 3)   # (4N, m, 3)
    f0 = base["tip"]
    J = np.zeros((m, 3, 2 * N))
    for j in range(N):
        J[:, :, j] = (tips[2 * j] - tips[2 * j + 1]) / (2 * h_rot)
        f1, f2 = tips[2 * N + 2 * j], tips[2 * N + 2 * j + 1]
        J[:, :, N + j] = (-3 * f0 + 4 * f1 - f2) / (-2 * h_ins)
    return J


def _print(r: dict) -> None:
    print(f"\n== {r['robot']} ({r['tubes']} tubes), {r['configs']} configurations (last tube's "
          f"rotation 0..{r['max_deg']:g} deg), one thread, best of {r['repeat']}; peer "
          f"smoothing {r['smoothing']:g} m, shooting tol {r['tol_rad']:g} rad")
    print(f"{'case':<30}{'peer ms':>10}{'torchpvs ms':>13}{'tpvs/peer':>11}{'target':>9}"
          f"{'met':>5}")
    rows = [("warm B=1 (1 deg step)", "warm"), ("cold B=1", "cold"),
            ("control step B=1 (solve+J)", "control"),
            (f"B={r['batch']} warm, per solve", "batch")]
    for label, k in rows:
        print(f"{label:<30}{r[f'peer_{k}_ms']:>10.4f}{r[f'torchpvs_{k}_ms']:>13.4f}"
              f"{r[f'{k}_ratio']:>11.2f}{'<= ' + format(r[f'{k}_target'], 'g'):>9}"
              f"{'yes' if r[f'{k}_met'] else 'no':>5}")
    print(f"{'warm B=1, tip only':<30}{r['peer_warm_ms']:>10.4f}{r['torchpvs_warm_tip_ms']:>13.4f}"
          f"{r['warm_tip_ratio']:>11.2f}{'-':>9}{'-':>5}")
    print(f"{'Tracker.step B=1 (tip only)':<30}{r['peer_warm_ms']:>10.4f}"
          f"{r['torchpvs_tracker_ms']:>13.4f}{r['tracker_ratio']:>11.2f}{'-':>9}{'-':>5}")
    print(f"{'Tracker control step B=1':<30}{r['peer_control_ms']:>10.4f}"
          f"{r['torchpvs_tracker_control_ms']:>13.4f}{r['tracker_control_ratio']:>11.2f}"
          f"{'-':>9}{'-':>5}")
    label = f"Tracker.step B={r['batch']}, per solve"
    print(f"{label:<30}{r['peer_warm_ms']:>10.4f}{r['torchpvs_tracker_batch_ms']:>13.4f}"
          f"{r['tracker_batch_ratio']:>11.2f}{'-':>9}{'-':>5}")
    print("  (B = batch rows: the peer figure is its single warm solve; tip only: torchpvs "
          "without actuation forces, SolverOptions(compute_forces=False), the peer's output;\n"
          f"   Tracker: torchpvs.Tracker's fused warm step at the discretization of its first "
          f"solve, order {r['tracker_order']}, {r['tracker_n_magnus']} Magnus steps, no "
          f"order check; tips {r['tip_max_diff_tracker_m']:.2e} m from the peer's; its control "
          f"step: step(jacobians=True), the tip Jacobian and the actuator stiffness)")
    for k in ("warm", "cold", "control"):
        alts = ", ".join(f"{s} {v:.4f}" for s, v in r[f"peer_{k}_strategy_ms"].items())
        print(f"peer {k}: {r[f'peer_{k}_newton_steps']:.2f} Newton steps, "
              f"{r[f'peer_{k}_integrations']:.2f} integrations per solve; best strategy "
              f"'{r[f'peer_{k}_strategy']}' (ms: {alts})")
    cold = (f"{r['tip_max_diff_cold_m']:.2e} m" if r["tip_max_diff_cold_m"] is not None
            else "-")
    print(f"tip distance peer vs torchpvs, max over configurations: warm "
          f"{r['tip_max_diff_warm_m']:.2e} m (torchpvs default options; its error estimate <= "
          f"{r['torchpvs_error_estimate_max_m']:.1e} m), vs torchpvs at accuracy 1e-9 "
          f"{r['tip_max_diff_tight_m']:.2e} m; cold {cold}")
    if r["cold_other_equilibrium"]:
        print(f"  cold: at {r['cold_other_equilibrium']} of {r['configs']} configurations "
              f"(last rotation {r['cold_other_deg']} deg) the two reach different equilibria "
              f"(peer stability measure det(dpsi0/dPsiL) there: "
              f"{', '.join(f'{v:.2g}' for v in r['cold_other_peer_stability'])}; on the warm "
              f"branch >= {r['peer_warm_stability_min']:.2g}); left out of the cold distance")
    print("tip Jacobian d(tip position)/d(D, alpha), max |diff| over configurations "
          "(torchpvs: jacobians(compliance=False); peer: library = GetTipJacobianForTube1 "
          "through Zta, FD = finite differences of its solves):")
    print(f"{'column':<16}{'largest':>9}{'lib vs tpvs':>13}{'FD vs tpvs':>12}{'lib vs FD':>11}")
    for k, name in enumerate(r["jacobian_columns"]):
        unit = "[m/m]" if name.startswith("D") else "[m/rad]"
        print(f"{name + ' ' + unit:<16}{r['jacobian_scale'][k]:>9.4f}"
              f"{r['jacobian_diff_peer_tp'][k]:>13.1e}{r['jacobian_diff_peerfd_tp'][k]:>12.1e}"
              f"{r['jacobian_diff_peer_peerfd'][k]:>11.1e}")
    for j in r["insertion_kinks"]:
        print(f"  D_{j}: tube {j}'s curved part starts exactly at the orifice, where the tip has a "
              f"kink in D_{j} (one-sided derivatives differ); torchpvs reports the retracting "
              f"side, the peer FD is taken on it")
        sd = r[f"torchpvs_kink_D{j}_closed_form_vs_fd"]
        print(f"  D_{j}: torchpvs closed form vs its own one-sided differences (accuracy 1e-9): "
              f"advancing {sd['advancing']:.1e}, retracting {sd['retracting']:.1e} m/m")


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--peer", help="checkout of ConcentricTubeMexLibrary (default: $CTR_PEER)")
    ap.add_argument("--configs", type=int, default=16)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--batch", type=int, default=1024)
    ap.add_argument("--max-deg", type=float, default=170.0,
                    help="largest rotation of the last tube [deg] (default 170: the Fig. 3 "
                         "robot is bistable above 180)")
    ap.add_argument("--smoothing", type=float, default=1e-9,
                    help="the peer's precurvature smoothing width [m] (its default: 1e-3)")
    ap.add_argument("--build-dir", default=str(Path.home() / ".cache" / "torchpvs" / "peer_cpp"))
    ap.add_argument("--cxx", default="g++")
    ap.add_argument("--rebuild", action="store_true", help="rebuild the driver even if cached")
    ap.add_argument("--json", help="write the figures to this JSON file")
    args = ap.parse_args(argv)
    if args.configs < 1 or args.repeat < 1 or args.batch < 1:
        fail("--configs, --repeat and --batch must be positive")
    if not args.smoothing > 0:
        fail("--smoothing must be a positive width [m] (0 gives the peer NaNs at the step)")
    peer = peer_dir(args.peer)
    lib = build(peer, args.cxx, Path(args.build_dir).expanduser(), args.rebuild)
    torch.set_num_threads(1)
    warnings.filterwarnings("ignore")
    r = bench(args, lib)
    r["peer_library"] = str(lib)
    _print(r)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(r, f, indent=1)
    return r


if __name__ == "__main__":
    main()
