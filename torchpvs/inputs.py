"""Input checks and canonical batches shared by :func:`torchpvs.solve`, :class:`torchpvs.CTR`
and the solvers built on them: every actuation and load becomes a ``(B, ...)`` tensor of one
dtype and device, or a ``ValueError`` that names the field and the rule."""

from __future__ import annotations

import numpy as np
import torch

from .scene import Scene

__all__ = ["as_batch", "batch_inputs", "check_actuation", "check_float_dtypes", "scene_inputs"]


def _values(t: torch.Tensor):
    """``t``'s values for a check: a numpy view of a CPU tensor (a check there costs about a
    microsecond instead of a few torch dispatches, which bound a single solve), else ``t``."""
    return t.detach().numpy() if t.device.type == "cpu" else t


_NUMPY_DTYPES = {torch.float64: np.float64, torch.float32: np.float32}


def _plain_numbers(x) -> bool:
    """A tuple or list of Python floats and ints, or a numpy float array: what a scene's
    defaults and most callers pass (converted through numpy, a few microseconds cheaper per
    field than ``torch.as_tensor``, which bounds a single solve)."""
    if isinstance(x, np.ndarray):
        return x.dtype.kind in "fiu"
    if isinstance(x, (tuple, list)):
        for v in x:
            if not isinstance(v, (float, int)) or isinstance(v, bool):
                return False
        return True
    return False


def as_batch(x, n: int, name: str, dtype, device) -> torch.Tensor:
    np_dtype = _NUMPY_DTYPES.get(dtype)
    if np_dtype is not None and torch.device(device).type == "cpu" and _plain_numbers(x):
        a = np.asarray(x, dtype=np_dtype)
        if a.ndim == 1:
            a = a[None]
        if a.ndim != 2 or a.shape[-1] != n:
            raise ValueError(f"{name} must have shape ({n},) or (B, {n}), got {a.shape}")
        if not np.isfinite(a).all():
            raise ValueError(f"{name} must be finite")
        return torch.from_numpy(a)
    t = torch.as_tensor(x, dtype=dtype, device=device)
    if t.ndim == 1:
        t = t[None]
    if t.ndim != 2 or t.shape[-1] != n:
        raise ValueError(f"{name} must have shape ({n},) or (B, {n}), got {tuple(t.shape)}")
    v = _values(t)
    finite = np.isfinite(v).all() if isinstance(v, np.ndarray) else torch.isfinite(v).all()
    if not finite:
        raise ValueError(f"{name} must be finite")
    return t


def check_actuation(D: torch.Tensor, scene: Scene) -> None:
    v = _values(D)
    if isinstance(v, np.ndarray) and v.shape[0] == 1:
        # one row (a single solve): its few numbers in Python, not two array reductions
        row = v[0].tolist()
        if any(d < 0 for d in row):
            raise ValueError("insertion: every D_j must be >= 0 (docs/conventions.md)")
        if any(b < a for a, b in zip(row, row[1:], strict=False)):
            raise ValueError("insertion: D_j must be >= D_{j-1} for every batch element "
                             "(an inner tube's base lies behind the outer one's)")
        return
    if (v < 0).any():
        raise ValueError("insertion: every D_j must be >= 0 (docs/conventions.md)")
    if scene.n_tubes > 1 and (v[:, 1:] < v[:, :-1]).any():
        raise ValueError("insertion: D_j must be >= D_{j-1} for every batch element "
                         "(an inner tube's base lies behind the outer one's)")


def check_float_dtypes(**inputs) -> None:
    """Refuse floating-point tensors of a dtype the solver does not run in (half, bfloat16,
    complex), naming the field; integers and Python numbers are converted."""
    for name, x in inputs.items():
        if isinstance(x, torch.Tensor) and x.dtype not in (torch.float32, torch.float64) \
                and (x.is_floating_point() or x.is_complex()):
            raise ValueError(f"{name}: dtype {x.dtype} is not supported; the solver runs in "
                             f"torch.float32 or torch.float64 (convert the input, or set "
                             f"SolverOptions(dtype=...))")


def scene_inputs(scene: Scene, insertion, rotation, tip_force, tip_moment, *, dtype=None,
                 device=None, **others) -> tuple[torch.Tensor, ...]:
    """The one canonicalisation of a solve's inputs (:func:`torchpvs.solve`,
    :func:`torchpvs.solve_force_controlled`): the scene's actuation and load where an input is
    ``None``, then :func:`batch_inputs` in one dtype and device. Every tensor input, the
    ``others`` too (e.g. commanded forces), is first checked by :func:`check_float_dtypes`
    under its own name. The dtype is ``dtype`` (``SolverOptions.dtype``) or else that of the
    first floating-point tensor among the inputs (``others`` first), float64 without one; the
    device is ``device`` or else that of the first tensor, the CPU without one. Returns
    ``(D, alpha, F, M, dtype, device)``."""
    named = {**others, "insertion": insertion, "rotation": rotation, "tip_force": tip_force,
             "tip_moment": tip_moment}
    check_float_dtypes(**named)
    tensors = [x for x in named.values() if isinstance(x, torch.Tensor)]
    if dtype is None:
        dtype = next((x.dtype for x in tensors if x.is_floating_point()), torch.float64)
    device = torch.device(device) if device is not None else (
        tensors[0].device if tensors else torch.device("cpu"))
    D, A, F, M = batch_inputs(
        scene, scene.actuation.insertion if insertion is None else insertion,
        scene.actuation.rotation if rotation is None else rotation,
        scene.load.tip_force if tip_force is None else tip_force,
        scene.load.tip_moment if tip_moment is None else tip_moment, dtype, device)
    return D, A, F, M, dtype, device


def batch_inputs(scene: Scene, insertion, rotation, tip_force, tip_moment, dtype, device,
                 contiguous: bool = True) -> tuple[torch.Tensor, ...]:
    """``(D (B, N), alpha (B, N), F (B, 3), M (B, 3))`` from inputs of shape ``(n,)`` or
    ``(B, n)`` (none ``None``), broadcast to the largest batch ``B``, with every field's
    shape, batch size and finiteness checked and the actuation's ordering
    (:func:`check_actuation`). ``contiguous=False`` keeps broadcast views (an autograd caller
    whose gradients flow back to the ``(1, n)`` rows)."""
    N = scene.n_tubes
    D = as_batch(insertion, N, "insertion", dtype, device)
    A = as_batch(rotation, N, "rotation", dtype, device)
    F = as_batch(tip_force, 3, "tip_force", dtype, device)
    M = as_batch(tip_moment, 3, "tip_moment", dtype, device)
    sizes = [t.shape[0] for t in (D, A, F, M)]
    if min(sizes) == 0:
        raise ValueError("insertion, rotation, tip_force, tip_moment: batch size 0; give at least "
                         "one row (shape (B, ...) with B >= 1)")
    B = max(sizes)
    for name, t in (("insertion", D), ("rotation", A), ("tip_force", F), ("tip_moment", M)):
        if t.shape[0] not in (1, B):
            raise ValueError(f"{name} has batch size {t.shape[0]}, expected 1 or {B}")
    out = tuple(t if t.shape[0] == B else t.expand(B, -1) for t in (D, A, F, M))
    if contiguous:
        out = tuple(t if t.is_contiguous() else t.contiguous() for t in out)
    check_actuation(out[0].detach(), scene)
    return out
