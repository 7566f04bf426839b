"""Approaching a target nearer the anatomy than the tip's radius + margin (PlanConfig.approach).

With a margin at the tip (a calibrated model's error bound, or one the user states), a target
near the wall is approached from inside the lumen instead of refused. Oracle: the distance from
the goal to the scene's meshes by trimesh's exact closest-point query (not ctrplan's fields or
FCL world), and the tip's distance to the target the user asked for computed here.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import ctrplan
from ctrplan.planning.plan import PlanConfig, plan_to_target

MARGIN = 0.8


@pytest.fixture(scope="module")
def airway_case():
    robot = ctrplan.load_robot("seed1")
    scene = ctrplan.load_scene("airway")
    target = np.asarray(scene.targets[0].position, dtype=float)
    near = plan_to_target(robot, scene, target, model="physics", time_limit=20, seed=0,
                          config=PlanConfig(margin_mm=MARGIN))
    refused = plan_to_target(robot, scene, target, model="physics", time_limit=20, seed=0,
                             config=PlanConfig(margin_mm=MARGIN, approach=False))
    return robot, scene, target, near, refused


def _distance_to_anatomy(scene, p: np.ndarray) -> float:
    d = np.inf
    for m in scene.collision_meshes:
        _, dist, _ = trimesh.proximity.closest_point(m.mesh, p[None])
        d = min(d, float(dist[0]))
    return d


def test_target_near_the_wall_is_approached_within_the_margin(airway_case):
    robot, scene, target, near, refused = airway_case
    r_tip = robot.tubes[0].od / 2.0
    # the shipped target lies nearer the wall than the tip's radius + the margin
    assert _distance_to_anatomy(scene, target) < r_tip + MARGIN
    assert not refused.success and refused.status.value in ("TARGET_IN_COLLISION", "GOAL_IN_COLLISION")
    assert near.success, near.message
    goal = np.asarray(near.goal)
    shift = float(np.linalg.norm(goal - target))
    assert near.goal_shift_mm == pytest.approx(shift, abs=1e-9)
    assert 0.0 < shift <= MARGIN + 1e-9                      # never further than the margin
    # the goal keeps the tip's probe clear of the anatomy by more than before
    assert _distance_to_anatomy(scene, goal) > _distance_to_anatomy(scene, target)
    # the reported tip error is the distance to the target asked for, not to the moved goal
    tip = np.asarray(near.tip_path)[-1]
    assert near.tip_error_mm == pytest.approx(float(np.linalg.norm(tip - target)), abs=1e-6)
    assert float(np.linalg.norm(tip - goal)) <= 1.0 + 1e-6    # the goal itself is reached
    js = near.to_json()
    assert js["goal_shift_mm"] == pytest.approx(shift) and len(js["goal"]) == 3


def test_no_margin_no_shift():
    """At margin 0 (the nominal physics model) the target is planned to as given."""
    robot = ctrplan.load_robot("seed1")
    scene = ctrplan.load_scene("airway")
    target = np.asarray(scene.targets[1].position, dtype=float)
    r = plan_to_target(robot, scene, target, model="physics", time_limit=20, seed=0)
    assert r.success and r.goal_shift_mm == 0.0 and r.goal is None
    assert r.tip_error_mm < 1.0
