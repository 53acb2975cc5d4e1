"""Test-session setup: a headless matplotlib backend and at most two torch threads."""

import matplotlib

matplotlib.use("Agg")

try:
    import torch
except ImportError:  # pragma: no cover - torch is a hard dependency, but keep scene tests alive
    torch = None

if torch is not None:
    torch.set_num_threads(2)


if torch is not None:
    import pytest

    @pytest.fixture
    def one_thread():
        """One torch thread for the test (small batches spin-wait badly on two busy cores);
        the previous count is restored after. Use as ``pytestmark =
        pytest.mark.usefixtures("one_thread")`` or as an argument."""
        from torchpvs.testing import one_thread as _one

        with _one():
            yield
