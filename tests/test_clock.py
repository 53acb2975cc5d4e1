"""The deadlines' clock (torchpvs.clock): wall-clock time less numba's compile time.

Reference: ``time.perf_counter()`` around a call that compiles a new numba function (its first
call); the compile time is what numba's own ``numba:compile`` events span.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest

from torchpvs.clock import compile_seconds, work_clock

numba = pytest.importorskip("numba")


def test_the_work_clock_stands_still_while_numba_compiles():
    """A solve's time limit must not count first use: compiling a new function (on its first
    call) adds its time to :func:`compile_seconds` and not to :func:`work_clock`, which
    otherwise runs with ``time.perf_counter()``."""

    @numba.njit
    def fresh(x):        # defined here: not compiled before its first call, not cached
        s = 0.0
        for i in range(x.shape[0]):
            s += math.sin(x[i]) * math.cos(2 * x[i])
        return s

    c0, w0, t0 = compile_seconds(), work_clock(), time.perf_counter()
    fresh(np.linspace(0, 1, 5))
    c1, w1, t1 = compile_seconds(), work_clock(), time.perf_counter()
    assert c1 - c0 > 0.01                                   # it compiled
    assert (t1 - t0) - (w1 - w0) == pytest.approx(c1 - c0, abs=1e-4)
    assert w1 - w0 < 0.5 * (t1 - t0)
    # no compilation: the two clocks run together
    c2, w2, t2 = compile_seconds(), work_clock(), time.perf_counter()
    fresh(np.linspace(0, 1, 5))
    time.sleep(0.02)
    c3, w3, t3 = compile_seconds(), work_clock(), time.perf_counter()
    assert c3 == c2
    assert (w3 - w2) == pytest.approx(t3 - t2, abs=1e-4)
