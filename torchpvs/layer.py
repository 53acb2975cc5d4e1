"""The equilibrium as a ``torch.nn.Module``, for use inside learning code.

``CTR(scene)`` holds the tube properties as buffers (float64 by default); ``.to(device, dtype)``
moves them, and :meth:`CTR.learnable` turns chosen properties into ``nn.Parameter`` s whose
gradients flow through the implicit-function backward (``torchpvs/implicit.py``).
"""

from __future__ import annotations

import torch
from torch import nn

from .equilibrium import Equilibrium
from .inputs import batch_inputs
from .options import SolverOptions
from .plan import Plan
from .scene import Scene, SceneError, check_tube_numbers, load_scene
from .sections import TubeProperties, TubeTensors
from .solver import solve_tensors

__all__ = ["CTR"]

_PROPS = TubeProperties._fields


class CTR(nn.Module):
    """A concentric tube robot whose ``forward`` returns its (batched) equilibrium.

    Buffers (all ``(N,)`` except ``precurvature (N, 3, P)``), SI units: ``E``, ``G`` [Pa],
    ``inner_diameter``, ``outer_diameter``, ``straight_length``, ``curved_length`` [m],
    ``precurvature`` polynomial coefficients [1/m, 1/m², ...] (docs/conventions.md).

    Example::

        robot = torchpvs.CTR("renda2021_fig3").learnable("precurvature")
        eq = robot(insertion, rotation)              # (B, N) each
        loss = (eq.tip_position - target).square().sum()
        loss.backward()                              # robot.precurvature.grad
    """

    def __init__(self, scene: Scene | str, options: SolverOptions | None = None,
                 dtype: torch.dtype = torch.float64):
        super().__init__()
        self.scene = scene if isinstance(scene, Scene) else load_scene(scene)
        self.options = options or SolverOptions()
        props = TubeProperties.from_tubes(self.scene.tubes, dtype)
        for name, value in zip(_PROPS, props, strict=True):
            self.register_buffer(name, value)
        # The robot's plan (layout reuse between calls at the same insertions); valid while the
        # properties keep the values it was built from and need no gradient (_solver_tubes).
        self._plan: Plan | None = None
        self._plan_values: tuple[torch.Tensor, ...] | None = None

    def learnable(self, *names: str) -> CTR:
        """Turn the named buffers into ``nn.Parameter`` s (returns ``self``)."""
        for name in names:
            if name not in _PROPS:
                raise ValueError(f"CTR.learnable: unknown property {name!r}; one of {_PROPS}")
            value = getattr(self, name)
            if isinstance(value, nn.Parameter):
                continue
            del self._buffers[name]
            self.register_parameter(name, nn.Parameter(value.detach().clone()))
        return self

    def _properties(self) -> TubeProperties:
        """The current buffers/parameters as :class:`~torchpvs.sections.TubeProperties`."""
        return TubeProperties(*(getattr(self, name) for name in _PROPS))

    def tube_tensors(self) -> TubeTensors:
        """Derived stiffnesses and lengths as ``(1, N)`` tensors (differentiable)."""
        return TubeTensors.from_properties(*self._properties())

    def _check_properties(self) -> None:
        """The scene rules on the current buffers/parameters: the one validator of tube
        properties (:func:`torchpvs.scene.check_tube_numbers`) on their values (one copy to
        the host), its message prefixed with ``CTR:`` (a ``ValueError``)."""
        props = self._properties()
        with torch.no_grad():
            flat = torch.cat([t.detach().reshape(-1) for t in props]).tolist()
        values, at = {}, 0
        for name, t in zip(props._fields, props, strict=True):
            values[name] = flat[at:at + t.numel()]
            at += t.numel()
        pc = values.pop("precurvature")
        N = len(values["E"])
        per_tube = len(pc) // N if N else 0
        inner = values["inner_diameter"]
        try:
            for j in range(N):
                check_tube_numbers(j, **{name: v[j] for name, v in values.items()},
                                   outer_inner_diameter=inner[j - 1] if j else None,
                                   precurvature=pc[j * per_tube:(j + 1) * per_tube])
        except SceneError as e:
            raise ValueError(f"CTR: {e}") from None

    def _solver_tubes(self) -> tuple[TubeTensors, Plan | None]:
        """Tube tensors for a solve and the plan to reuse: fresh differentiable ones and no
        plan while a property needs a gradient; else the cached plan while every property
        holds the values (dtype, device) it was built from, a new plan otherwise.

        The cache is keyed on the values themselves (a copy, compared with ``torch.equal``: 7
        small tensors per call). Neither ``id(tensor)`` (reused after a free) nor the version
        counter (not bumped by writes through ``.data``) identifies the properties.
        """
        props = [getattr(self, name) for name in _PROPS]
        if torch.is_grad_enabled() and any(t.requires_grad for t in props):
            return self.tube_tensors(), None
        old = self._plan_values
        with torch.no_grad():
            same = old is not None and all(
                a.shape == b.shape and a.dtype == b.dtype and a.device == b.device
                and torch.equal(a, b) for a, b in zip(old, props, strict=True))
        if not same:
            # The plan is built from the copy, so a later in-place write to a property cannot
            # reach the plan's tube tensors through a view either. Kept across calls, some
            # with autograd: no inference tensors (as torchpvs.plan.plan_for).
            with torch.no_grad(), torch.inference_mode(False):
                values = tuple(t.detach().clone() for t in props)
                self._plan = Plan(TubeTensors.from_properties(*values))
            self._plan_values = values
        return self._plan.tubes, self._plan

    def forward(self, insertion: torch.Tensor, rotation: torch.Tensor,
                tip_force: torch.Tensor | None = None, tip_moment: torch.Tensor | None = None,
                initial: Equilibrium | torch.Tensor | None = None) -> Equilibrium:
        """Equilibria for ``insertion``, ``rotation`` of shape ``(N,)`` or ``(B, N)`` and
        optional tip loads ``(3,)``/``(B, 3)`` [N], [N·m] in the base frame."""
        ref = self.E
        dtype, device = ref.dtype, ref.device
        zeros = torch.zeros(3, dtype=dtype, device=device)
        # broadcast views: gradients reach (1, N) inputs through the expand
        D, A, F, M = batch_inputs(self.scene, insertion, rotation,
                                  zeros if tip_force is None else tip_force,
                                  zeros if tip_moment is None else tip_moment, dtype, device,
                                  contiguous=False)
        self._check_properties()
        tubes, plan = self._solver_tubes()
        return solve_tensors(self.scene, tubes, D, A, F, M, self.options, initial, plan)

    def extra_repr(self) -> str:
        return f"tubes={self.scene.n_tubes}, dtype={self.E.dtype}, device={self.E.device}"
