"""The clock of the wall-clock limits: ``time.perf_counter()`` less numba's compile time.

Every ``time_limit`` of the library (:class:`~torchpvs.SolverOptions`, continuation, force
control, inverse kinematics) bounds the work of a call. The first call of a compiled kernel in
a process whose cache is empty compiles it (numba, tens of seconds: docs/performance.md, *First
use*); that is not the call's work, yet on ``time.perf_counter()`` a first solve with a tip load
on a fresh installation compiled for 42 s and stopped at its 30 s limit, short of its accuracy
request (and the same solve met it once compiled). numba reports each compilation as an event
(``numba.core.event``, kind ``"numba:compile"``); :func:`work_clock` stands still while one runs.

The compile time is a per-process total, like numba's own dispatchers and caches (numba
compiles under one process-wide lock, so compilations never overlap).
"""

from __future__ import annotations

import time

__all__ = ["compile_seconds", "work_clock"]


class _CompileTimer:
    """numba's ``numba:compile`` listener: the time spent in outermost compilations (nested
    ones, of the functions a function calls, are part of their caller's)."""

    def __init__(self) -> None:
        self.total = 0.0
        self.depth = 0
        self.start = 0.0

    def on_start(self, event) -> None:
        if self.depth == 0:
            self.start = time.perf_counter()
        self.depth += 1

    def on_end(self, event) -> None:
        self.depth -= 1
        if self.depth == 0:
            self.total += time.perf_counter() - self.start

    def seconds(self) -> float:
        """The compile time so far [s], a compilation under way included."""
        return self.total + (time.perf_counter() - self.start if self.depth else 0.0)


def _register() -> _CompileTimer:
    timer = _CompileTimer()
    try:
        from numba.core import event
    except ImportError:       # no numba: nothing compiles
        return timer

    class Listener(event.Listener):
        def on_start(self, ev) -> None:
            timer.on_start(ev)

        def on_end(self, ev) -> None:
            timer.on_end(ev)

    event.register("numba:compile", Listener())
    return timer


_TIMER = _register()


def compile_seconds() -> float:
    """numba's compile time in this process so far [s]."""
    return _TIMER.seconds()


def work_clock() -> float:
    """``time.perf_counter()`` less :func:`compile_seconds` [s]: the clock every deadline of
    the library is set and checked on."""
    return time.perf_counter() - _TIMER.seconds()
