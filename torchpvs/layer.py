"""The equilibrium as a ``torch.nn.Module``, for use inside learning code.

``CTR(scene)`` holds the tube properties as buffers (float64 by default); ``.to(device, dtype)``
moves them, and :meth:`CTR.learnable` turns chosen properties into ``nn.Parameter`` s whose
gradients flow through the implicit-function backward (``torchpvs/implicit.py``).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from .equilibrium import Equilibrium
from .scene import Scene, load_scene
from .sections import TubeTensors
from .solver import SolverOptions, _as_batch, _check_actuation, _solve

__all__ = ["CTR"]

_PROPS = ("E", "G", "inner_diameter", "outer_diameter", "straight_length", "curved_length",
          "precurvature")


class CTR(nn.Module):
    """A concentric tube robot whose ``forward`` returns its (batched) equilibrium.

    Buffers (all ``(N,)`` except ``precurvature (N, 3, P)``), SI units: ``E``, ``G`` [Pa],
    ``inner_diameter``, ``outer_diameter``, ``straight_length``, ``curved_length`` [m],
    ``precurvature`` polynomial coefficients [1/m, 1/m², ...] (conventions.md).

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
        tubes = self.scene.tubes
        P = max(1, max(len(ax) for t in tubes for ax in t.precurvature))
        coef = torch.zeros(len(tubes), 3, P, dtype=dtype)
        for j, t in enumerate(tubes):
            for d, ax in enumerate(t.precurvature):
                if ax:
                    coef[j, d, :len(ax)] = torch.tensor(ax, dtype=dtype)
        for name in _PROPS[:-1]:
            self.register_buffer(name, torch.tensor([getattr(t, name) for t in tubes],
                                                    dtype=dtype))
        self.register_buffer("precurvature", coef)

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

    def tube_tensors(self) -> TubeTensors:
        """Derived stiffnesses and lengths as ``(1, N)`` tensors (differentiable)."""
        second_moment = math.pi * (self.outer_diameter**4 - self.inner_diameter**4) / 64.0
        return TubeTensors(
            EI=(self.E * second_moment)[None],
            GJ=(self.G * 2.0 * second_moment)[None],
            length=(self.straight_length + self.curved_length)[None],
            straight=self.straight_length[None],
            coef=self.precurvature[None],
        )

    def forward(self, insertion: torch.Tensor, rotation: torch.Tensor,
                tip_force: torch.Tensor | None = None, tip_moment: torch.Tensor | None = None,
                initial: Equilibrium | torch.Tensor | None = None) -> Equilibrium:
        """Equilibria for ``insertion``, ``rotation`` of shape ``(N,)`` or ``(B, N)`` and
        optional tip loads ``(3,)``/``(B, 3)`` [N], [N·m] in the base frame."""
        ref = self.E
        dtype, device = ref.dtype, ref.device
        N = self.scene.n_tubes
        D = _as_batch(insertion, N, "insertion", dtype, device)
        A = _as_batch(rotation, N, "rotation", dtype, device)
        zeros = torch.zeros(3, dtype=dtype, device=device)
        F = _as_batch(zeros if tip_force is None else tip_force, 3, "tip_force", dtype, device)
        M = _as_batch(zeros if tip_moment is None else tip_moment, 3, "tip_moment", dtype,
                      device)
        B = max(t.shape[0] for t in (D, A, F, M))
        for name, t in (("insertion", D), ("rotation", A), ("tip_force", F),
                        ("tip_moment", M)):
            if t.shape[0] not in (1, B):
                raise ValueError(f"{name} has batch size {t.shape[0]}, expected 1 or {B}")
        D, A, F, M = (t.expand(B, -1) for t in (D, A, F, M))
        _check_actuation(D.detach(), self.scene)
        return _solve(self.scene, self.tube_tensors(), D, A, F, M, self.options, initial)

    def extra_repr(self) -> str:
        return f"tubes={self.scene.n_tubes}, dtype={self.E.dtype}, device={self.E.device}"
