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
from ctrplan.shape.base import Shape
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
    # the oracle: FCL distances over every capsule-mesh pair (no field, no pruning)
    brute = CollisionWorld(scene, prefilter=False).clearance_exact(validator.shapes(check.states))
    # the prefilter's clearances really are lower bounds of the FCL distances
    assert np.all(np.asarray(check.clearance_mm) <= brute + 1e-9)
    # with a budget that lets it settle, branch and bound finds the exact minimum
    value, exact, measured = path_min_clearance(validator, world, check, None, max_pairs=10**6)
    assert exact
    assert abs(value - float(brute.min())) < 1e-9
    # with a small budget it returns a valid lower bound, never more than the truth
    low, low_exact, used = path_min_clearance(validator, world, check, None, batch=4, max_pairs=3)
    assert not low_exact
    assert used <= 8 and low <= brute.min() + 1e-9
    assert 0.0 < result.min_clearance_mm <= brute.min() + 1e-9


def test_pruned_exact_clearance_equals_all_pairs():
    """clearance_exact prunes capsule-mesh pairs by the field's lower bounds; it must give the
    all-pairs FCL distance, and with ``below`` never more than the truth (and at least
    ``below`` wherever it differs from the truth)."""
    robot = load_robot("seed1")
    scene = load_scene("skull_base")
    model = load_model("physics", robot)
    world, full = CollisionWorld(scene), CollisionWorld(scene, prefilter=False)
    q = np.array([t.config for t in scene.targets[:6]])
    # states along the way in: the shipped target configurations retracted by 0..30 mm
    states = np.concatenate([q + np.r_[np.zeros(3), -np.full(3, d)] for d in (0.0, 10.0, 30.0)])
    states = states[robot.is_valid(states)]
    shape = model.shape(states, points=20)
    free = ~world.collides(shape)
    assert free.sum() >= 6
    shape = Shape(shape.points[free], shape.s[free], shape.radius[free], shape.ok[free])
    truth = full.clearance_exact(shape)
    np.testing.assert_allclose(world.clearance_exact(shape), truth, atol=1e-9)
    cap = float(np.median(truth))
    capped = world.clearance_exact(shape, below=cap)
    assert np.all(capped <= truth + 1e-9)
    below = truth < cap
    np.testing.assert_allclose(capped[below], truth[below], atol=1e-9)
    assert np.all(capped[~below] >= cap - 1e-9)
