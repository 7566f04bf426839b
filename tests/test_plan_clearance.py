"""The plan's min_clearance_mm is the exact FCL minimum over the verified states (branch and
bound on the prefilter's lower bounds), checked against brute force over every state."""

from __future__ import annotations

import numpy as np

from ctrplan.collision.scene import load_scene
from ctrplan.collision.world import CollisionWorld
from ctrplan.planning import PlanStatus, plan_to_target
from ctrplan.planning.plan import path_min_clearance
from ctrplan.planning.validator import BatchValidator
from ctrplan.robot import load_robot
from ctrplan.shape.models import load_model


def test_min_clearance_is_the_exact_minimum():
    robot = load_robot("seed1")
    scene = load_scene("airway")
    world = CollisionWorld(scene)
    model = load_model("physics", robot)
    result = plan_to_target(robot, scene, scene.targets[1].position, model=model, time_limit=5.0, seed=3)
    assert result.status == PlanStatus.SUCCESS
    validator = BatchValidator(robot, model, world)
    check = validator.check_path(result.path, 1.0, fcl_all=False)
    assert check.ok
    brute = world.clearance_exact(validator.shapes(check.states))
    # the prefilter's clearances really are lower bounds of the FCL distances
    assert np.all(np.asarray(check.clearance_mm) <= brute + 1e-9)
    # with a budget that lets it settle, branch and bound finds the exact minimum
    value, measured = path_min_clearance(validator, world, check, None, budget=len(check.states))
    assert abs(value - float(brute.min())) < 1e-9
    # with a small budget it returns a valid lower bound, never more than the truth
    low, used = path_min_clearance(validator, world, check, None, batch=4, budget=8)
    assert used <= 8 and low <= brute.min() + 1e-9
    assert 0.0 < result.min_clearance_mm <= brute.min() + 1e-9
