"""benchmarks/bench_env.py --breakdown: every stage it names resolves to a function the env
step calls (a rename would otherwise print a silent 0 %), and the shares it prints are of a
real profiled step."""

from __future__ import annotations

import importlib.util
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def _bench():
    spec = importlib.util.spec_from_file_location("bench_env", ROOT / "benchmarks" / "bench_env.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


@pytest.mark.filterwarnings("ignore::RuntimeWarning")
@pytest.mark.parametrize("solver, stages", [
    ("torch", ("solves", "fused path (two compiled calls)", "actuator stiffness",
               "stability margin", "substep count")),
    ("auto", ("solves", "one compiled call each", "actuator stiffness (its rows)",
              "substep count")),
])
def test_the_breakdown_names_stages_that_a_step_calls(capsys, solver, stages):
    bench = _bench()
    bench.breakdown("fig3_two_tube", 4, 2, solver)
    out = capsys.readouterr().out
    rows = {m.group(1).strip(): (float(m.group(2)), float(m.group(4)))
            for m in re.finditer(r"^(\s*[a-zA-Z].*?)\s+(\d+\.\d+)\s+(\d+\.\d+)\s+(\d+)%$", out,
                                 re.M)}
    assert rows["step (all)"] == (1.0, 100.0)
    # the stages every force step goes through: called, and each a part of the step
    for stage in stages:
        calls, share = rows[stage]
        assert calls > 0, stage
        assert 0 <= share <= 100, stage
