"""Stage 5b — the robot plan: what a solve can reuse from one call to the next.

A :class:`Plan` belongs to one robot (its tubes), dtype and device. It holds the tube tensors
and the layout and ``q``-independent maps of the last insertion state per discretization and
batch shape, so that a call that only changes rotations or loads (a control step at fixed
insertion, a rotation sweep, the re-solves of one call) rebuilds nothing but the angles. It
holds no choice that changes results: a cold solve starts its automatic order at 2 whatever was
solved before (a warm start continues at the order of its initial equilibrium). Quadrature and
basis tables are
cached per discretization (:meth:`torchpvs.sections.Discretization.tables`).

``torchpvs.solve(scene, ...)`` looks the plan up by ``(scene.tubes, dtype, device)``, so casual
users get the reuse too; :class:`torchpvs.CTR` owns one.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Hashable
from dataclasses import dataclass, field

import torch

from .mechanics import Maps, build_layout_and_maps
from .scene import Scene
from .sections import Discretization, Layout, TubeProperties, TubeTensors, tube_rows

__all__ = ["Plan", "plan_for", "tube_tensors"]

ORDER_START, MAGNUS_START = 2, 8


def tube_tensors(scene: Scene, dtype: torch.dtype, device: torch.device) -> TubeTensors:
    """The scene's tube properties as ``(1, N)`` tensors (``coef``: ``(1, N, 3, P)``).

    The one conversion of the tubes (:meth:`TubeProperties.from_tubes`, as
    :class:`torchpvs.CTR`'s buffers) and the one formula of the stiffnesses
    (:meth:`TubeTensors.from_properties`), evaluated in double precision on the CPU and then
    rounded to ``dtype``. The stiffnesses are then the tubes' own
    (:attr:`torchpvs.scene.Tube.bending_stiffness`: the same operations in the same order, and
    for fewer than 8 tubes torch's CPU ``pow`` is libm's, as Python's; for more its vectorized
    ``pow`` may round a fourth power differently in the last bit). In float32 they may differ
    in the last bit from :class:`torchpvs.CTR`'s, which evaluates the formula in its own dtype
    (differentiably)."""
    props = TubeProperties.from_tubes(scene.tubes, torch.float64)
    return TubeTensors.from_properties(*props).map(
        lambda t: t.to(dtype=dtype, device=device))


@dataclass(frozen=True)
class _Memo:
    """Layout and maps of the last insertion state (no-grad solves only)."""

    D: torch.Tensor
    loaded: torch.Tensor
    disc: Discretization
    tubes: TubeTensors
    psi0_guide: torch.Tensor
    lay: Layout
    maps: Maps
    build: object                               # the builder that made them (Kernel.layout)
    extra: dict = field(default_factory=dict)   # constants computed on demand (see cached)


@dataclass(eq=False)
class Plan:
    """Reusable state of one robot for :func:`torchpvs.solve`.

    Attributes:
        tubes: the tube tensors (``(1, N)``, ``coef (1, N, 3, P)``).
    """

    tubes: TubeTensors
    _memo: dict = field(default_factory=dict, repr=False)
    _static: dict = field(default_factory=dict, repr=False)

    def layout(self, tubes: TubeTensors, D, A, F, M, loaded, disc: Discretization,
               nq: int, build=build_layout_and_maps, grad: bool | None = None,
               ) -> tuple[Layout, Maps]:
        """``(lay, maps)`` for a batch (:class:`~torchpvs.sections.Layout`,
        :class:`~torchpvs.mechanics.Maps`); reused from the last call with the same insertions,
        loaded mask, discretization and tube tensors (only angles and loads are replaced).
        ``build``: the kernel's builder (:attr:`torchpvs.kernel.Kernel.layout`; default the
        eager one, :func:`torchpvs.mechanics.build_layout_and_maps`). ``grad``: whether a
        gradient flows through the inputs, where the caller knows (else found here)."""
        if grad is None:
            grad = torch.is_grad_enabled() and any(
                t.requires_grad for t in (D, A, F, M, *tubes.tensors()))
        if not grad:
            kept = self.kept_layout(tubes, D, A, F, M, loaded, disc, build)
            if kept is not None:
                return kept
        lay, maps = build(tubes, D, A, F, M, loaded, disc, nq)
        if not grad:
            self.keep_layout(tubes, D, A, loaded, disc, lay, maps, build)
        return lay, maps

    def kept_layout(self, tubes: TubeTensors, D, A, F, M, loaded, disc: Discretization,
                    build) -> tuple[Layout, Maps] | None:
        """What :meth:`layout` returns without building (no gradient): the kept layout of
        these insertions, loaded mask, discretization, tubes and builder with the angles and
        loads replaced; None where none is kept."""
        memo = self._memo.get((disc, D.shape))
        if (memo is None or memo.D.shape != D.shape or memo.build is not build
                or not _same_tubes(memo.tubes, tubes) or not torch.equal(memo.D, D)
                or not torch.equal(memo.loaded, loaded)):
            return None
        # psi0 = alpha + (twist of the curved material held in the guide).
        lay = memo.lay._replace(psi0=memo.psi0_guide + A, alpha=A, force=F, moment=M)
        return lay, memo.maps._replace(psi0=lay.psi0)

    def keep_layout(self, tubes: TubeTensors, D, A, loaded, disc: Discretization, lay: Layout,
                    maps: Maps, build) -> None:
        """Keep ``(lay, maps)``, built by ``build`` at ``(D, A, loaded, disc)`` for ``tubes``
        without gradient, for :meth:`layout` to reuse (the 4 most recent batch shapes and
        discretizations)."""
        self._memo[(disc, D.shape)] = _Memo(D.clone(), loaded.clone(), disc, tubes,
                                            lay.psi0 - A, lay, maps, build)
        if len(self._memo) > 4:
            self._memo.pop(next(iter(self._memo)))

    def reused_layout(self, tubes: TubeTensors, D, A, loaded,
                      disc: Discretization) -> Layout | None:
        """The layout :meth:`layout` would return without building one: the last one at these
        insertions, loaded mask, discretization and tubes with the rotations ``A`` (and no
        load), or rows of a kept layout of another batch shape that hold every requested row
        (the one-sided forces re-solve both sides of a kink in one batch, and the control
        Jacobians ask for one side); None where there is none (the caller then builds its
        own)."""
        memo = self._memo.get((disc, D.shape))
        if (memo is not None and _same_tubes(memo.tubes, tubes) and torch.equal(memo.D, D)
                and torch.equal(memo.loaded, loaded)):
            zero = torch.zeros_like(memo.lay.force)
            return memo.lay._replace(psi0=memo.psi0_guide + A, alpha=A, force=zero,
                                     moment=zero)
        for (d, shape), memo in self._memo.items():
            if d != disc or shape == D.shape or shape[1:] != D.shape[1:]:
                continue
            hit = ((memo.D[None] == D[:, None]).all(-1)
                   & (memo.loaded[None] == loaded[:, None]))            # (k, B_memo)
            if not bool(hit.any(-1).all()):
                continue
            idx = hit.to(torch.int8).argmax(-1)
            if not _same_tubes(tube_rows(memo.tubes, idx), tubes):
                continue
            zero = torch.zeros(D.shape[0], 3, dtype=D.dtype, device=D.device)
            return type(memo.lay)._make(t[idx] for t in memo.lay)._replace(
                psi0=memo.psi0_guide[idx] + A, alpha=A, force=zero, moment=zero)
        return None

    def static(self, key: Hashable, compute):
        """``compute()`` kept under ``key`` for the plan's life: values that depend on the
        robot and ``key`` only (e.g. the tube arrays of a batch size that the fused path hands
        to compiled code); the 8 most recent keys."""
        if key not in self._static:
            self._static[key] = compute()
            if len(self._static) > 8:
                self._static.pop(next(iter(self._static)))
        return self._static[key]

    def cached(self, disc: Discretization, lay, key: Hashable, compute):
        """``compute()`` for a layout ``lay`` that :meth:`layout` returned for ``disc``, kept
        under ``key`` (what is computed and its parameters, e.g. ``("kinks", delta, tol)``)
        with the layout while it is reused (e.g. the pose constants at the finer Magnus nodes of the
        step-count check); computed afresh, and not kept, for any other layout."""
        memo = self._memo.get((disc, lay.D.shape))
        # A reused layout shares its masks with the memo (only angles and loads are replaced).
        if memo is None or memo.lay.qmask is not lay.qmask:
            return compute()
        if key not in memo.extra:
            memo.extra[key] = compute()
        return memo.extra[key]


def _same_tubes(a: TubeTensors, b: TubeTensors) -> bool:
    # By value, not only identity: the one-sided kink forces re-solve batch rows of the
    # plan's tubes (sections.tube_rows, a new object per call) at the same insertions on
    # every warm solve, and their layout is the same while the values are.
    return a is b or all(x.shape == y.shape and x.dtype == y.dtype and x.device == y.device
                         and torch.equal(x, y)
                         for x, y in zip(a.tensors(), b.tensors(), strict=True))


_PLANS: OrderedDict = OrderedDict()
_MAX_PLANS = 16


def plan_for(scene: Scene, dtype: torch.dtype, device: torch.device) -> Plan:
    """The cached plan of a scene's robot (keyed by ``scene.tubes``, dtype and device; the
    actuation and load of the scene do not matter). A small LRU cache: the 16 most recent."""
    key = (scene.tubes, dtype, torch.device(device))
    plan = _PLANS.get(key)
    if plan is None:
        with torch.inference_mode(False):    # kept across calls, some with autograd
            plan = _PLANS[key] = Plan(tube_tensors(scene, dtype, torch.device(device)))
        if len(_PLANS) > _MAX_PLANS:
            _PLANS.popitem(last=False)
    else:
        _PLANS.move_to_end(key)
    return plan
