"""Test-session setup: a headless matplotlib backend and at most two torch threads."""

import matplotlib

matplotlib.use("Agg")

try:
    import torch
except ImportError:  # pragma: no cover - torch is a hard dependency, but keep scene tests alive
    torch = None

if torch is not None:
    torch.set_num_threads(2)
