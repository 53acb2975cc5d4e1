"""Test-session setup and what the test modules share.

- a headless matplotlib backend and at most two torch threads for the session;
- ``one_thread``: a fixture pinning torch to one thread for a test, ``one_thread_module`` for a
  module (both restore the previous count; no module sets and restores it by hand); the
  hard-case suite (``tests/hard/``) runs every module under it;
- ``on_fold_branch``: the environment tests' Fig. 3 robot placed along a rotation branch
  that turns unstable under torque control before it ends in a snap;
- ``E, G``: the nitinol moduli of the paper's Table I [Pa], and ``two_tubes``: a two-tube robot
  given overall tube lengths. Test modules import them with ``from conftest import E, G,
  two_tubes`` (this is the suite's only conftest.py, so the name is unambiguous).
"""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")

try:
    import torch
except ImportError:  # pragma: no cover - torch is a hard dependency, but keep scene tests alive
    torch = None

if torch is not None:
    torch.set_num_threads(2)

HARD = Path(__file__).resolve().parent / "hard"


if torch is not None:
    import pytest

    from torchpvs import testing
    from torchpvs.testing import E_NITINOL as E  # noqa: F401 - shared with the test modules
    from torchpvs.testing import G_NITINOL as G

    def two_tubes(L=0.1, k1=9.9, k2=13.8, alpha2=0.0, D=(0.0, 0.0), straight=(0.0, 0.0),
                  lengths=None, G1=G, G2=G):
        """:func:`torchpvs.testing.two_tubes` given overall tube lengths (straight part
        included): ``L`` for both tubes or a pair ``(outer, inner)``, or ``lengths`` (a pair)."""
        L1, L2 = lengths or ((L, L) if isinstance(L, int | float) else L)
        return testing.two_tubes(k1, k2, Ls1=straight[0], Lc1=L1 - straight[0],
                                 Ls2=straight[1], Lc2=L2 - straight[1], D=D,
                                 alpha=(0.0, alpha2), G1=G1, G2=G2)

    @pytest.fixture
    def one_thread():
        """One torch thread for the test (small batches spin-wait badly on two busy cores);
        the previous count is restored after. Use as ``pytestmark =
        pytest.mark.usefixtures("one_thread")`` or as an argument."""
        with testing.one_thread():
            yield

    @pytest.fixture(scope="module")
    def one_thread_module():
        """One torch thread for a whole module, the previous count restored after it: use as
        ``pytestmark = pytest.mark.usefixtures("one_thread_module")`` (module-scoped
        fixtures that solve at set-up wrap their body in ``testing.one_thread()`` instead)."""
        with testing.one_thread():
            yield

    @pytest.fixture(autouse=True, scope="module")
    def _one_thread_in_hard_suite(request):
        """The hard-case suite runs its (mostly single-element) solves on one torch thread."""
        if HARD in Path(str(request.node.path)).resolve().parents:
            with testing.one_thread():
                yield
        else:
            yield

    @pytest.fixture
    def on_fold_branch():
        """``place(env, degrees=(150, 176))`` for the environment tests: robot 0 of a Fig. 3
        ``env`` placed at rest on the branch at ``D = (98.7, 164.5) mm``, outer tube at 0, the
        inner tube turned to each of ``degrees`` in turn (followed from 120 deg in 2 deg
        steps, each solve warm from the last); yields ``(deg, x (1, 4), eq)``. The inner
        tube's rotation stiffness ``dtau_2/dalpha_2`` turns negative near 163 deg on this
        branch (a torque-controlled robot is unstable past it) and the branch ends in a snap
        near 186 deg."""
        import numpy as np

        from envs.robots import solve_batch

        def place(env, degrees=(150, 176)):
            rb, robot = env.task.robots, env.robot
            eq = None
            for deg in range(120, max(degrees) + 1, 2):
                x = np.array([[0.0987, 0.1645, 0.0, np.radians(deg)]])
                eq = solve_batch(robot, x, initial=None if eq is None else eq.q)
                if deg in degrees:
                    rb.set_state(np.array([0]), x, eq=eq, rows=np.array([0]))
                    yield deg, x, eq
        return place
