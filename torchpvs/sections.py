"""Stage 2 — scene + actuation -> sections: where the free backbone is cut, what each part holds.

The backbone beyond the orifice, ``s in [0, s_tip]``, is cut at every tube end ``l_j = L_j - D_j``
and every straight-to-curved transition ``tau_j = Ls_j - D_j`` that lies on the tube. With ``N``
tubes there are at most ``2N`` cuts, so every batch element gets the same *number* of sections,
``S = 2N``, obtained by sorting the ``2N`` candidate cuts clipped to ``[0, l_j]``; sections of zero
length simply carry no coordinates. Elements may therefore have different layouts (different
tubes, transitions and lengths per section) in one batched tensor.

Coordinates (``q``, all strains in 1/m so that the stiffness has one unit, J·m²):

* ``w_j`` — the uniform twist rate of tube ``j`` inside the guide (torsion only there: the exact
  solution in the straight guide has constant torsional moment), active when ``D_j > 0`` and the
  tube reaches the free space;
* per section ``k``: bending curvature of the shared backbone in a twist-free (Bishop) frame,
  ``u(s) = sum_p phi_p(xi) a_{k,:,p}`` (2 x n), and each present tube's torsion
  ``psi_j'(s) = sum_p phi_p(xi) c_{k,j,p}`` (N x n), ``phi_p`` normalized Legendre polynomials.

Sections holding a single tube with no load beyond them are *prescribed*: their strain equals the
precurvature exactly (the paper's ``p_2 = 1``), so they carry no coordinates.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, fields
from typing import NamedTuple

import torch

from .basis import gauss_legendre, legendre_basis

__all__ = ["Discretization", "Layout", "Tables", "TubeProperties", "TubeTensors", "build_layout",
           "n_coordinates"]


class TubeProperties(NamedTuple):
    """The tubes' material and geometry as tensors, one entry per tube (outermost first), SI
    units: ``E``, ``G`` ``(N,)`` [Pa]; ``inner_diameter``, ``outer_diameter``,
    ``straight_length``, ``curved_length`` ``(N,)`` [m]; ``precurvature`` ``(N, 3, P)``
    polynomial coefficients [1/m, 1/m², ...] in the arc length from the start of the curved
    part (docs/conventions.md), zero-padded to the longest (``P >= 1``).

    :meth:`from_tubes` is the one conversion of :class:`torchpvs.scene.Tube` s to tensors
    (:class:`torchpvs.CTR` keeps these as its buffers; :func:`torchpvs.plan.tube_tensors`
    derives the stiffnesses from them, :meth:`TubeTensors.from_properties`)."""

    E: torch.Tensor
    G: torch.Tensor
    inner_diameter: torch.Tensor
    outer_diameter: torch.Tensor
    straight_length: torch.Tensor
    curved_length: torch.Tensor
    precurvature: torch.Tensor

    @classmethod
    def from_tubes(cls, tubes, dtype: torch.dtype,
                   device: torch.device | str | None = None) -> TubeProperties:
        """The properties of ``tubes`` (:class:`torchpvs.scene.Tube` s, validated), each
        Python float rounded once to ``dtype``."""
        return cls(*(torch.tensor([getattr(t, name) for t in tubes], dtype=dtype, device=device)
                     for name in cls._fields[:-1]),
                   precurvature=precurvature_coefficients(tubes, dtype, device))


@dataclass(frozen=True)
class TubeTensors:
    """Tube properties as tensors, broadcastable to ``(B, N)`` (``coef``: ``(B, N, 3, P)``).

    ``EI``, ``GJ`` [N·m²]; ``length``, ``straight`` [m]; ``coef`` precurvature polynomial
    coefficients in the arc length from the start of the curved part (docs/conventions.md).
    """

    EI: torch.Tensor
    GJ: torch.Tensor
    length: torch.Tensor
    straight: torch.Tensor
    coef: torch.Tensor

    def tensors(self) -> tuple[torch.Tensor, ...]:
        """The properties as a flat tuple, in field order (for an ``autograd.Function``, which
        takes its differentiable inputs one by one; :meth:`from_tensors` is the inverse)."""
        return tuple(getattr(self, f.name) for f in fields(self))

    @classmethod
    def from_tensors(cls, tensors) -> TubeTensors:
        """The inverse of :meth:`tensors`: properties matched to the fields by name order."""
        return cls(*tensors)

    def map(self, fn) -> TubeTensors:
        """``fn`` applied to every property (e.g. ``detach``)."""
        return TubeTensors(*(fn(t) for t in self.tensors()))

    @classmethod
    def from_properties(cls, E, G, inner_diameter, outer_diameter, straight_length,
                        curved_length, precurvature) -> TubeTensors:
        """From the per-tube material and geometry tensors of :class:`TubeProperties` (``(N,)``
        each, ``precurvature (N, 3, P)``; e.g. :class:`torchpvs.CTR`'s buffers, passed as
        ``from_properties(*props)``), differentiably: ``EI = E I``, ``GJ = 2 G I`` with
        ``I = pi (OD^4 - ID^4) / 64`` (the formulas of :class:`torchpvs.scene.Tube`, in the
        same order), as ``(1, N)`` tensors."""
        second_moment = math.pi * (outer_diameter**4 - inner_diameter**4) / 64.0
        return cls(EI=(E * second_moment)[None], GJ=(G * 2.0 * second_moment)[None],
                   length=(straight_length + curved_length)[None],
                   straight=straight_length[None], coef=precurvature[None])


def precurvature_coefficients(tubes, dtype: torch.dtype,
                              device: torch.device | str | None = None) -> torch.Tensor:
    """The precurvature polynomials of ``tubes`` (:class:`torchpvs.scene.Tube` s) as one
    ``(N, 3, P)`` tensor, ``P`` the longest polynomial (at least 1), zero-padded."""
    P = max(1, max(len(ax) for t in tubes for ax in t.precurvature))
    coef = torch.zeros(len(tubes), 3, P, dtype=dtype, device=device)
    for j, t in enumerate(tubes):
        for d, ax in enumerate(t.precurvature):
            if ax:
                coef[j, d, :len(ax)] = torch.tensor(ax, dtype=dtype, device=device)
    return coef


def tube_rows(tubes: TubeTensors, rows) -> TubeTensors:
    """The tube tensors of batch ``rows`` (an index tensor): shared ``(1, N)`` properties as
    they are, per-element ones (a batch of different robots, ``(B, N)``) indexed, so that a
    subset of a batch keeps its own robots."""
    return tubes.map(lambda t: t if t.shape[0] == 1 else t[rows])


class Tables(NamedTuple):
    """The quadrature and basis tables of one :class:`Discretization`, on a section's
    normalized coordinate ``xi in [-1, 1]`` (dimensionless; ``Q = n_quad`` energy nodes, ``n =
    n_basis`` basis functions, ``G = 2 n_magnus`` Magnus points). Shared, read-only constants
    (:meth:`Discretization.tables` caches them): never written into.

    Attributes:
        xq: ``(Q,)`` Gauss–Legendre nodes of the energy quadrature.
        wq: ``(Q,)`` their weights (summing to 2; a section of length ``h`` weighs ``h/2 wq``).
        phi_q: ``(Q, n)`` the normalized Legendre basis at ``xq``
            (:func:`torchpvs.basis.legendre_basis`).
        Q_q: ``(Q, n)`` its integrals ``int_{-1}^{xi} phi_p`` at ``xq``.
        xm: ``(G,)`` the Magnus points: the two Gauss points of each of ``n_magnus`` equal
            steps of ``[-1, 1]``.
        phi_m, Q_m: ``(G, n)`` the basis and its integrals at ``xm``.
    """

    xq: torch.Tensor
    wq: torch.Tensor
    phi_q: torch.Tensor
    Q_q: torch.Tensor
    xm: torch.Tensor
    phi_m: torch.Tensor
    Q_m: torch.Tensor


@dataclass(frozen=True)
class Discretization:
    """Static discretization choices: basis functions per strain, quadrature and Magnus steps."""

    n_basis: int
    n_quad: int
    n_magnus: int

    def tables(self, dtype: torch.dtype, device: torch.device) -> Tables:
        """Quadrature nodes/weights and basis values (:class:`Tables`, cached per dtype and
        device)."""
        return _tables(self, dtype, torch.device(device))


@functools.lru_cache(maxsize=64)
def _tables(disc: Discretization, dtype: torch.dtype, device: torch.device) -> Tables:
    # Read-only constants: callers never write into them. Ordinary tensors even when first
    # asked for in inference mode, since cached values later enter autograd graphs.
    with torch.inference_mode(False):
        xq, wq = gauss_legendre(disc.n_quad, dtype=dtype, device=device)
        phi_q, Q_q = legendre_basis(xq, disc.n_basis)
        # Magnus sub-steps: n_magnus equal pieces of [-1, 1], two Gauss points each.
        m = disc.n_magnus
        centers = -1.0 + (2.0 * torch.arange(m, dtype=dtype, device=device) + 1.0) / m
        off = (1.0 / m) / 3.0**0.5
        xm = torch.stack([centers - off, centers + off], -1).reshape(-1)
        phi_m, Q_m = legendre_basis(xm, disc.n_basis)
        return Tables(xq=xq, wq=wq, phi_q=phi_q, Q_q=Q_q, xm=xm, phi_m=phi_m, Q_m=Q_m)


def n_coordinates(n_tubes: int, n_basis: int) -> int:
    """Length of ``q``: ``N`` guide twists + ``2N`` sections x ``(2 + N) n`` strain coefficients."""
    return n_tubes + 2 * n_tubes * (2 + n_tubes) * n_basis


def _poly_antiderivative_value(coef: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """``int_0^t sum_p coef_p x^p dx`` with ``coef (..., P)`` and ``t (...)``."""
    out = torch.zeros_like(t)
    P = coef.shape[-1]
    for p in range(P - 1, -1, -1):
        out = (out + coef[..., p] / (p + 1)) * t
    return out


class Layout(NamedTuple):
    """Sections, masks and fixed quantities of a batch at given insertions (every field has the
    leading batch dim ``B``, so a layout can be indexed, detached or ``vmap``-ed as a whole;
    ``S = 2N`` section slots, some of them empty; masks are float 0/1).

    ``EI``, ``GJ`` ``(B, N)`` [N·m²] stiffnesses; ``D``, ``alpha`` ``(B, N)`` [m, rad] the
    actuation; ``coef`` ``(B, N, 3, P)`` precurvature polynomials [1/m] in the arc length from
    the transition; ``tau`` ``(B, N)`` [m] transition positions on the backbone (``Ls - D``);
    ``ell`` ``(B, N)`` [m] exposed lengths; ``start``, ``h`` ``(B, S)`` [m] section starts and
    lengths; ``present``, ``curved`` ``(B, S, N)`` tube j in section s, and curved there;
    ``active`` ``(B, S)`` sections with coordinates; ``presc`` ``(B, S)`` single-tube sections at
    their precurvature (no coordinates); ``qmask`` ``(B, nq)`` active coordinates; ``psi0``
    ``(B, N)`` [rad] tube angles at the orifice; ``guide_const`` ``(B,)`` [J] bending energy
    stored in the guide; ``W`` ``(B, S, Q)`` [m] quadrature weights of the energy; ``force``,
    ``moment`` ``(B, 3)`` [N, N·m] tip load (base frame); ``tip_tube`` ``(B, N)`` one-hot tube
    forming the tip; ``s_tip`` ``(B,)`` [m] tip arc length; ``before_l1`` ``(B, S)`` sections
    ending at or before the outer tube's end; ``loaded`` ``(B,)`` nonzero tip load.
    """

    EI: torch.Tensor
    GJ: torch.Tensor
    D: torch.Tensor
    alpha: torch.Tensor
    coef: torch.Tensor
    tau: torch.Tensor
    ell: torch.Tensor
    start: torch.Tensor
    h: torch.Tensor
    present: torch.Tensor
    curved: torch.Tensor
    active: torch.Tensor
    presc: torch.Tensor
    qmask: torch.Tensor
    psi0: torch.Tensor
    guide_const: torch.Tensor
    W: torch.Tensor
    force: torch.Tensor
    moment: torch.Tensor
    tip_tube: torch.Tensor
    s_tip: torch.Tensor
    before_l1: torch.Tensor
    loaded: torch.Tensor


def build_layout(tubes: TubeTensors, D: torch.Tensor, alpha: torch.Tensor,
                 force: torch.Tensor, moment: torch.Tensor, loaded: torch.Tensor,
                 disc: Discretization, *, min_section: float = 1e-12) -> Layout:
    """Sections, masks and fixed quantities for a batch.

    Args:
        tubes: properties, broadcastable to ``(B, N)``.
        D, alpha: ``(B, N)`` insertions [m] and base rotations [rad].
        force, moment: ``(B, 3)`` tip load [N], [N·m], base frame.
        loaded: ``(B,)`` bool, whether the element has a nonzero tip load.
        disc: the discretization.
        min_section: sections shorter than this [m] get no coordinates.

    Returns the :class:`Layout`; everything is differentiable w.r.t. ``D``, ``alpha`` and the
    tube tensors.
    """
    B, N = D.shape
    dtype, device = D.dtype, D.device
    EI = tubes.EI.expand(B, N)
    GJ = tubes.GJ.expand(B, N)
    L = tubes.length.expand(B, N)
    Ls = tubes.straight.expand(B, N)
    coef = tubes.coef.expand(B, N, 3, tubes.coef.shape[-1])

    ell = torch.clamp(L - D, min=0.0)                      # exposed lengths (B, N)
    tau = Ls - D                                           # transition positions on the backbone
    tau_clip = torch.minimum(torch.clamp(tau, min=0.0), ell)
    cuts, _ = torch.sort(torch.cat([ell, tau_clip], -1), dim=-1)   # (B, S)
    S = 2 * N
    start = torch.cat([torch.zeros_like(cuts[:, :1]), cuts[:, :-1]], -1)
    h = cuts - start
    nonempty = h > min_section
    mid = (start + 0.5 * h).detach()
    present = (mid[..., None] < ell.detach()[:, None, :]) & nonempty[..., None]   # (B, S, N)
    curved = (mid[..., None] > tau.detach()[:, None, :]) & present
    n_present = present.sum(-1)
    multi = n_present >= 2
    active = nonempty & (multi | loaded[:, None])
    presc = nonempty & ~active & (n_present == 1)

    # Coordinate mask (B, nq): guide twists, then per section (2 + N) x n.
    n = disc.n_basis
    w_mask = (D > 0) & (ell > 0)
    sec_mask = torch.cat([active[..., None].expand(B, S, 2),
                          present & active[..., None]], -1)          # (B, S, 2 + N)
    qmask = torch.cat([w_mask, sec_mask[..., None].expand(B, S, 2 + N, n).reshape(B, -1)], -1)

    # Fixed guide quantities: twist of precurved material and the bending energy it stores
    # while held straight (1/2 EI |u*_xy|^2 per metre, docs/physics.md).
    guided = torch.minimum(D, L)                                    # guided material length
    t_guide = torch.clamp(guided - Ls, min=0.0)                     # curved part inside the guide
    psi0 = alpha + _poly_antiderivative_value(coef[..., 2, :], t_guide)
    xg, wg = gauss_legendre(max(2, coef.shape[-1] + 1), dtype=dtype, device=device)
    tg = 0.5 * (xg + 1.0) * t_guide[..., None]                      # (B, N, G)
    uxy = _poly_eval(coef[..., :2, :, None], tg[..., None, :])      # (B, N, 2, G)
    guide_const = (0.5 * EI * (0.5 * t_guide) * ((uxy**2).sum(-2) * wg).sum(-1)).sum(-1)

    # Quadrature weights for the energy (only active sections store coordinate-dependent energy).
    tab = disc.tables(dtype, device)
    W = 0.5 * h[..., None] * tab.wq * active[..., None]

    # The tube forming the tip: the largest exposed length, ties -> innermost.
    idx = torch.arange(N, device=device, dtype=dtype)
    score = ell.detach() + 1e-9 * idx * (ell.detach().amax(-1, keepdim=True) + 1e-12)
    # (a comparison rather than one_hot, which has no vmap rule)
    tip_tube = (torch.arange(N, device=device) == score.argmax(-1, keepdim=True)).to(dtype)
    s_tip = ell.amax(-1)
    # Sections that end at or before the outer tube's distal end (for theta_j(l_1)).
    before_l1 = (cuts.detach() <= ell.detach()[:, :1] + 1e-12).to(dtype)

    f = lambda m: m.to(dtype)  # noqa: E731 - masks as float for arithmetic
    return Layout(EI=EI, GJ=GJ, D=D, alpha=alpha, coef=coef, tau=tau, ell=ell, start=start, h=h,
                  present=f(present), curved=f(curved), active=f(active), presc=f(presc),
                  qmask=f(qmask), psi0=psi0, guide_const=guide_const, W=W, force=force,
                  moment=moment, tip_tube=tip_tube, s_tip=s_tip, before_l1=before_l1,
                  loaded=f(loaded))


def _poly_eval(coef: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Horner: ``coef (..., P, G?)`` broadcast against ``t``; coefficients on dim -2 when ``t``
    carries a trailing node dim (see callers), else on dim -1."""
    P = coef.shape[-2]
    # (the shape by broadcast_tensors: torch.broadcast_shapes imports sympy on its first call,
    # 0.4-0.9 s that the first layout with a graph of a process paid)
    out = torch.zeros(torch.broadcast_tensors(coef[..., 0, :], t)[0].shape,
                      dtype=t.dtype, device=t.device)
    for p in range(P - 1, -1, -1):
        out = out * t + coef[..., p, :]
    return out
