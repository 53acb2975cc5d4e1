"""The hard-case suite runs its (mostly single-element) solves on one torch thread."""

import pytest

from torchpvs.testing import one_thread


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    with one_thread():
        yield
