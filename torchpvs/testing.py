"""Test scenes and helpers: scene builders (the paper's robots, seeded random and nested robots),
tip distances, a reference solve on PVS's branch, and one-thread execution. Shared by the test
suite (``tests/``), the benchmarks and users who want the same scenes.

Hard cases: docs/physics.md, "Hard cases the solver must survive". Scenes of the paper:
Renda, Messer, Rucker, Boyer, IEEE RA-L 2021 (sections III-B and III-C / Fig. 3, Table I).
Frames, signs and the scene rules: docs/conventions.md.
"""

from __future__ import annotations

import contextlib
import math

import numpy as np
import torch

import torchpvs
from torchpvs.reference import solve_standard
from torchpvs.scene import Actuation, Load, Scene, Tube

MM = 1e-3
E_NITINOL, G_NITINOL = 58.0e9, 21.5e9          # Table I of Renda et al. 2021
D1_FIG3 = 93.5 * MM
# Fig. 3 sweeps (docs/physics.md, section III-C): D1 = 93.5 mm, alpha1 = 0.
SWEEPS = {
    "full": (208.5 * MM, list(range(0, 281, 20))),      # full overlap, alpha2 = 0..280 deg
    "partial": (170.5 * MM, list(range(0, 201, 20))),   # partial overlap, alpha2 = 0..200 deg
}


def fig3(D2: float = 208.5 * MM, alpha2_deg: float = 80.0, D1: float = D1_FIG3) -> Scene:
    """The paper's Fig. 3 robot at ``D = (D1, D2)``, ``alpha = (0, alpha2)``."""
    return torchpvs.load_scene("renda2021_fig3").with_actuation(
        insertion=[D1, D2], rotation=[0.0, math.radians(alpha2_deg)])


def tip(eq, b: int = 0) -> np.ndarray:
    return eq.tip_position[b].detach().double().cpu().numpy()


def dist(a, b) -> float:
    return float(np.linalg.norm(np.asarray(a, float) - np.asarray(b, float)))


def two_tubes(k1: float, k2: float, *, E1: float = E_NITINOL, E2: float = E_NITINOL,
              od1: float = 2.39 * MM, id1: float = 2.01 * MM, od2: float = 1.6 * MM,
              id2: float = 0.0, Ls1: float = 0.0, Lc1: float = 0.1, Ls2: float = 0.0,
              Lc2: float = 0.15, D=(0.0, 0.0), alpha=(0.0, 0.0), load: Load | None = None,
              G1: float | None = None, G2: float | None = None) -> Scene:
    """A two-tube robot with constant precurvatures ``k1``, ``k2`` [1/m] about y. Shear moduli
    default to nitinol's ratio to ``E`` (Table I)."""
    G1 = E1 * G_NITINOL / E_NITINOL if G1 is None else G1
    G2 = E2 * G_NITINOL / E_NITINOL if G2 is None else G2
    tubes = (Tube(E=E1, G=G1, inner_diameter=id1, outer_diameter=od1,
                  straight_length=Ls1, curved_length=Lc1,
                  precurvature=((), (k1,), ()), name="outer"),
             Tube(E=E2, G=G2, inner_diameter=id2, outer_diameter=od2,
                  straight_length=Ls2, curved_length=Lc2,
                  precurvature=((), (k2,), ()), name="inner"))
    return Scene(tubes, Actuation(tuple(D), tuple(alpha)), load or Load())


def random_scene(seed: int) -> Scene:
    """A seeded random realistic nested nitinol robot (2 tubes for even seeds, 3 for odd): outer
    diameter 1.2-3 mm, walls 0.08-0.25 mm, clearances 0.03-0.1 mm (the innermost tube solid 40 %
    of the time), lengths 50-250 mm with each tube at least 10 mm longer than the one around it
    (capped at 250 mm), a straight part of 0-70 %, constant precurvature 0-25 1/m in y, 30 %: a
    linear term keeping u*_y in [0, 2 u*_y(0)], 20 %: a constant x component up to 5 1/m.
    Insertions ordered D_j >= D_{j-1} >= 0 (10 %: equal to the lower bound, so D_1 = 0 occurs)
    with exposed lengths >= 5 mm; rotations in (-pi, pi)."""
    rng = np.random.default_rng(seed)
    n = 2 if seed % 2 == 0 else 3
    od = (rng.uniform(1.8, 3.0) if n == 3 else rng.uniform(1.2, 3.0)) * MM
    tubes, L_prev = [], 0.0
    for j in range(n):
        wall = rng.uniform(0.08, 0.25) * MM
        idj = od - 2 * wall
        if j == n - 1 and rng.random() < 0.4:
            idj = 0.0
        L = rng.uniform(50, 180) * MM if j == 0 else rng.uniform(min(L_prev + 10 * MM, 0.25),
                                                                  0.25)
        straight = rng.uniform(0.0, 0.7) * L
        curved = L - straight
        k0 = rng.uniform(0.0, 25.0)
        y = [k0]
        x = []
        if rng.random() < 0.3:
            y.append(rng.uniform(-1, 1) * k0 / curved)
        if rng.random() < 0.2:
            x = [rng.uniform(-5, 5)]
        tubes.append(Tube(E=E_NITINOL, G=G_NITINOL, inner_diameter=idj, outer_diameter=od,
                          straight_length=straight, curved_length=curved,
                          precurvature=(tuple(x), tuple(y), ()), name=f"tube{j + 1}"))
        L_prev = L
        od = idj - rng.uniform(0.03, 0.1) * MM
    D, lo = [], 0.0
    for t in tubes:
        d = lo if rng.random() < 0.1 else rng.uniform(lo, t.length - 5 * MM)
        D.append(float(d))
        lo = d
    rot = [float(v) for v in rng.uniform(-math.pi, math.pi, n)]
    return Scene(tuple(tubes), Actuation(tuple(D), tuple(rot)))


def nested_scene(n_tubes: int, seed: int = 0, kappa_max: float = 20.0) -> Scene:
    """A valid ``n_tubes``-tube robot (2..8) for scaling runs: outermost OD 4 mm, walls 0.1-0.15
    mm, clearances 0.03-0.05 mm (innermost solid), each tube 20-30 mm longer than the one around
    it, straight part 40-60 %, precurvature 5-``kappa_max`` 1/m, insertions ordered with each
    tube's precurved part partly exposed (the telescoping layout of a real robot)."""
    rng = np.random.default_rng(1000 + seed)
    od, L = 4.0 * MM, rng.uniform(90, 110) * MM
    tubes = []
    for j in range(n_tubes):
        wall = rng.uniform(0.10, 0.15) * MM
        idj = 0.0 if j == n_tubes - 1 else od - 2 * wall
        straight = rng.uniform(0.4, 0.6) * L
        tubes.append(Tube(E=E_NITINOL, G=G_NITINOL, inner_diameter=idj, outer_diameter=od,
                          straight_length=straight, curved_length=L - straight,
                          precurvature=((), (float(rng.uniform(5.0, kappa_max)),), ()),
                          name=f"tube{j + 1}"))
        od = idj - rng.uniform(0.03, 0.05) * MM
        L += rng.uniform(20, 30) * MM
    # exposed length of tube j: about 40 % of its curved part beyond the previous tube's tip
    D, lo, tip_prev = [], 0.0, 0.0
    for t in tubes:
        exposed = tip_prev + rng.uniform(0.3, 0.5) * t.curved_length
        d = max(lo, t.length - exposed)
        D.append(float(d))
        lo, tip_prev = d, t.length - d
    rot = [float(v) for v in rng.uniform(-math.pi, math.pi, n_tubes)]
    return Scene(tuple(tubes), Actuation(tuple(D), tuple(rot)))


def matched_reference(scene: Scene, pvs, tol: float = 1e-10, seed: int = 0, max_mm: float = 1.0,
                      **kw):
    """The reference equilibrium on PVS's branch (tip within ``max_mm``), or ``None``.

    Guesses: zero torsion (the reference's default), the orifice torsion of the PVS answer
    (``m_j(0) = -tau_alpha_j``, needs ``compute_forces``) and 4 random perturbations. A guess
    only: the reference still converges on its own equations to its own tolerance."""
    p = tip(pvs)

    def ok(r):
        return r.converged and dist(r.tip_position, p) < max_mm * MM

    r = solve_standard(scene, tol=tol, **kw)
    if ok(r):
        return r
    guesses = []
    if pvs.actuation_torques is not None:
        guesses.append(-pvs.actuation_torques[0].detach().double().numpy())
    rng = np.random.default_rng(1000 + seed)
    base = r.y0 if r.converged else np.zeros(r.dofs)
    guesses += [base + 0.1 * rng.standard_normal(r.dofs) for _ in range(4)]
    for g in guesses:
        if len(g) != r.dofs:
            continue
        r2 = solve_standard(scene, tol=tol, initial=g, **kw)
        if ok(r2):
            return r2
    return None


def assert_same_equilibria(a, b, tip_tol: float = 1e-12, force_tol: float = 1e-9) -> None:
    """Assert that two :class:`~torchpvs.Equilibrium` of the same problem are the same
    equilibria (two kernels, or two devices: ``b`` is compared on ``a``'s device): the same
    convergence flags, iteration counts and stability verdicts, tips within ``tip_tol`` [m],
    actuation forces and torques within ``force_tol`` [N, N·m] (NaN where the other is NaN),
    and minimum stiffness eigenvalues within 1e-6 relative."""
    dev = a.tip_position.device
    def at(t):
        return t.to(dev)
    assert torch.equal(a.converged, at(b.converged))
    assert torch.equal(a.iterations, at(b.iterations))
    assert torch.equal(a.stable, at(b.stable))
    assert float((a.tip_position - at(b.tip_position)).abs().max()) <= tip_tol
    for x, y in ((a.actuation_forces, at(b.actuation_forces)),
                 (a.actuation_torques, at(b.actuation_torques))):
        assert torch.equal(torch.isnan(x), torch.isnan(y))
        ok = ~torch.isnan(x)
        assert float((x - y).abs()[ok].max()) <= force_tol
    assert torch.allclose(a.min_stiffness_eigenvalue, at(b.min_stiffness_eigenvalue), rtol=1e-6,
                          atol=1e-12, equal_nan=True)


def spy_results(monkeypatch, module, name: str, real=None) -> list[bool]:
    """Replace ``module.name`` (via pytest's ``monkeypatch``) by a wrapper of ``real`` (default
    the current ``module.name``) that records, per call, whether it returned something other
    than None: which calls a compiled or fused path took rather than handing on. Returns the
    list it appends to."""
    calls: list[bool] = []
    fn = getattr(module, name) if real is None else real

    def spy(*a, **k):
        out = fn(*a, **k)
        calls.append(out is not None)
        return out

    monkeypatch.setattr(module, name, spy)
    return calls


@contextlib.contextmanager
def one_thread():
    """Context manager: one torch thread (tiny solves spin-wait badly on a busy 2-core box)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(n)


def scene_strategy(max_tubes: int = 3):
    """A hypothesis strategy of valid scene dicts (``Scene.from_dict`` input) for property tests:
    1..``max_tubes`` nested nitinol-like tubes (outer diameter 1-4 mm, walls 0.05-0.4 mm, moduli
    down to 1/100 of nitinol's), straight, curved or mixed, precurvature up to 40 1/m in y (with
    optional x and linear terms), insertions equal, free or fully retracted, rotations in
    (-pi, pi), and half the time a tip force up to 2 N. Needs ``hypothesis`` (a dev extra)."""
    from hypothesis import strategies as st

    @st.composite
    def scene_dicts(draw):
        n = draw(st.integers(1, max_tubes))
        od = draw(st.floats(1.0, 4.0)) * MM
        tubes, L = [], draw(st.floats(20.0, 150.0)) * MM
        for j in range(n):
            wall = draw(st.floats(0.05, 0.4)) * MM
            solid = j == n - 1 and draw(st.booleans())
            idj = 0.0 if solid or od - 2 * wall <= 0.1 * MM else od - 2 * wall
            curved_frac = draw(st.sampled_from([0.0, 1.0, draw(st.floats(0.05, 0.95))]))
            pre = {"y": [draw(st.floats(-40.0, 40.0))]}
            if draw(st.booleans()):
                pre["x"] = [draw(st.floats(-10.0, 10.0))]
            if draw(st.booleans()):
                c = pre["y"][0]
                pre["y"].append(draw(st.floats(-1.0, 1.0)) * abs(c) / max(L * curved_frac, 1e-3))
            tubes.append({"E": draw(st.sampled_from([58e9, 58e9, 5.8e9, 0.58e9])), "G": 21.5e9,
                          "inner_diameter": idj, "outer_diameter": od,
                          "straight_length": L * (1 - curved_frac),
                          "curved_length": L * curved_frac, "precurvature": pre})
            if idj <= 0.0:
                break
            od = idj - draw(st.floats(0.02, 0.2)) * MM
            if od <= 0.2 * MM:
                break
            L += draw(st.floats(0.0, 80.0)) * MM
        D, lo = [], 0.0
        for t in tubes:
            L_t = t["straight_length"] + t["curved_length"]
            kind = draw(st.sampled_from(["same", "free", "free", "free", "retracted"]))
            d = lo if kind == "same" else (max(lo, L_t + draw(st.floats(0.0, 10.0)) * MM)
                                           if kind == "retracted" else
                                           lo + draw(st.floats(0.0, 1.0)) * max(L_t - lo, 0.0))
            D.append(d)
            lo = d
        rot = [draw(st.floats(-math.pi, math.pi)) for _ in tubes]
        out = {"tubes": tubes, "actuation": {"insertion": D, "rotation": rot}}
        if draw(st.booleans()):
            out["load"] = {"tip_force": [draw(st.floats(-2.0, 2.0)) for _ in range(3)]}
        return out

    return scene_dicts()


# -- calibration data: a robot that differs from its datasheet, measured by the reference ----

def scaled_tubes(scene: Scene, precurvature=None, E=None, G=None) -> Scene:
    """``scene`` with each tube's precurvature polynomial, ``E`` and ``G`` multiplied by the
    given per-tube factors (``(N,)`` each; ``None`` keeps them): a robot whose tubes differ
    from their datasheet."""
    N = scene.n_tubes
    fk, fE, fG = (np.ones(N) if f is None else np.asarray(f, np.float64)
                  for f in (precurvature, E, G))
    tubes = tuple(Tube(E=t.E * fE[j], G=t.G * fG[j], inner_diameter=t.inner_diameter,
                       outer_diameter=t.outer_diameter, straight_length=t.straight_length,
                       curved_length=t.curved_length, name=t.name,
                       precurvature=tuple(tuple(c * fk[j] for c in ax) for ax in t.precurvature))
                  for j, t in enumerate(scene.tubes))
    return Scene(tubes=tubes, actuation=scene.actuation, load=scene.load)


def feasible_actuations(rng: np.random.Generator, m: int, scene: Scene | None = None,
                        margin: float = 5e-3, max_relative_rotation: float = 2.0
                        ) -> tuple[np.ndarray, np.ndarray]:
    """``m`` seeded commanded actuations ``(D (m, N), alpha (m, N))`` of a nested robot: every
    insertion at least ``margin`` inside its tube and behind the next inner one, each tube
    exposing at least ``margin`` more than the one around it (default: the Fig. 3 robot).
    Rotations: the outer tube's uniform, the others within ``max_relative_rotation`` [rad] of
    it (default 2 rad = 115 deg), away from +-180 deg where long overlaps are bistable and a
    measurement's equilibrium would depend on the path that reached it."""
    scene = scene or torchpvs.load_scene("renda2021_fig3")
    L = np.array([t.length for t in scene.tubes])
    N = len(L)
    D = np.zeros((m, N))
    for i in range(m):
        lo = 0.0
        for j in range(N):
            # tip order: L_j - D_j >= L_{j-1} - D_{j-1} + margin, and D_j >= D_{j-1}
            hi = L[j] - margin if j == 0 else min(L[j] - margin,
                                                  L[j] - (L[j - 1] - D[i, j - 1]) - margin)
            lo_j = max(lo, 0.1 * L[j] if j == 0 else D[i, j - 1] + margin)
            D[i, j] = rng.uniform(lo_j, max(lo_j, hi))
            lo = D[i, j]
    a0 = rng.uniform(-math.pi, math.pi, (m, 1))
    rel = rng.uniform(-max_relative_rotation, max_relative_rotation, (m, N))
    rel[:, 0] = 0.0
    return D, a0 + rel


def standard_tips(scene: Scene, insertion, rotation, tol: float = 1e-10) -> np.ndarray:
    """Tips ``(M, 3)`` [m] of the standard (Kirchhoff-rod) model, solved by shooting
    (:mod:`torchpvs.reference`), at actuations ``(M, N)``: measurements from a model that shares
    nothing with the PVS solver but the scene. Raises if one does not converge."""
    out = []
    for d, a in zip(np.asarray(insertion), np.asarray(rotation), strict=True):
        sol = solve_standard(scene.with_actuation(insertion=list(map(float, d)),
                                                  rotation=list(map(float, a))),
                             tol=tol, compute_forces=False, compute_stability=False)
        if not sol.converged:
            raise RuntimeError(f"reference did not converge at D={d}, alpha={a}: {sol.reason}")
        out.append(sol.tip_position)
    return np.array(out)
