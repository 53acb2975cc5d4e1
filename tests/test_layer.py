"""torchpvs.CTR (torchpvs/layer.py): the robot's cached plan never answers for other properties.

Reference: a fresh ``CTR`` built with the edited property (no cache to go stale), and
``torchpvs.solve`` on the scene with that property changed (its own plan, keyed on
``scene.tubes``). Regression: the plan used to be keyed on ``id(tensor)`` and the version
counter, so a reassigned tensor that reused a freed id, or a write through ``.data`` (which does
not bump the version), returned the equilibrium of the old properties.
"""

from __future__ import annotations

import dataclasses

import pytest
import torch

import torchpvs as tp

SC = tp.load_scene("renda2021_fig3")
INS = torch.tensor(SC.actuation.insertion, dtype=torch.float64)
ROT = torch.tensor(SC.actuation.rotation, dtype=torch.float64)
E_NEW = 30e9   # Pa, tube 2 (the scene has 58 GPa): moves the tip by about 2 mm


def _reference_tip() -> torch.Tensor:
    tubes = list(SC.tubes)
    tubes[1] = dataclasses.replace(tubes[1], E=E_NEW)
    return tp.solve(dataclasses.replace(SC, tubes=tuple(tubes))).tip_position


def _edit_reassign_reused_id(robot):
    E1 = robot.E.clone()
    E1[1] = E_NEW
    robot.E = E1
    del E1
    robot.E = robot.E.clone()        # a new tensor: may reuse a freed id, version 0


def _edit_data(robot):
    robot.E.data[1] = E_NEW          # no version bump


def _edit_learnable_data(robot):
    robot.learnable("E")
    with torch.no_grad():
        robot(INS, ROT)              # the cached plan of the parameter's values
    robot.E.data[1] = E_NEW


@pytest.mark.parametrize("edit", [_edit_reassign_reused_id, _edit_data, _edit_learnable_data])
def test_edited_properties_are_never_answered_from_the_cache(edit):
    ref = _reference_tip()
    with torch.no_grad():
        robot = tp.CTR(SC)
        old = robot(INS, ROT).tip_position
        assert float((old - ref).norm()) > 1e-3          # the edit matters
        edit(robot)
        tip = robot(INS, ROT).tip_position
        fresh = tp.CTR(SC)
        fresh.E[1] = E_NEW
        tip_fresh = fresh(INS, ROT).tip_position
    assert float((tip - tip_fresh).norm()) < 1e-15
    assert float((tip - ref).norm()) < 1e-12


def test_unchanged_properties_keep_the_plan_and_a_restored_value_matches():
    """The cache still serves repeated calls (same plan object), and editing then restoring a
    value answers for the restored value."""
    with torch.no_grad():
        robot = tp.CTR(SC)
        a = robot(INS, ROT).tip_position
        plan = robot._plan
        b = robot(INS, ROT).tip_position
        assert robot._plan is plan and torch.equal(a, b)
        robot.E.data[1] = E_NEW
        robot(INS, ROT)
        robot.E.data[1] = SC.tubes[1].E
        c = robot(INS, ROT).tip_position
    assert robot._plan is not plan
    assert float((c - a).norm()) < 1e-15
