"""A surrogate's margin alone never refuses a goal: the physics model decides (issue 38 item 2).

Scene: open space (the base frame is the scene frame) and two spheres (radius 4 mm) on either
side of the tip of a seed1 configuration, their surfaces 0.95 mm from the target: the tip
(radius 0.65 mm) is clear of them, but not by the tip's radius + the surrogate's margin (0.5 mm
here). The surrogate is the physics model stating a surrogate error of 0.5 mm (``error_bound:
surrogate``), so whatever the margin blocks, the physics model clears. The approach off the
wall cannot help: between the spheres the tip must move 1.4 mm along the gap to gain the
margin, more than the margin it may shift by.

Oracle: the distance from every capsule of the physics backbone (64 points, along the path
densified to 0.25 mm of the joint metric) to the spheres, in closed form (segment to centre
minus both radii), not ctrplan's collision world or FCL; the spheres' meshes lie inside the true
spheres, so a positive distance to the spheres is a positive distance to the meshes.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

import ctrplan
from ctrplan.collision.scene import Scene, SceneMesh
from ctrplan.planning.planner import Planner, PlannerConfig
from ctrplan.shape.models import load_model

MARGIN = 0.5       # the surrogate's stated error (mm): its margin
SPHERE = 4.0       # sphere radius (mm)


class _StatedSurrogate:
    """The physics model stating a surrogate error of MARGIN (what a network trained on it
    would carry): its margin is the only thing that differs from physics."""

    error_bound = "surrogate"

    def __init__(self, robot):
        self.inner = load_model("physics", robot)
        self.robot = robot
        self.name = "stated_surrogate"
        self.error_quantiles = {"p50": 0.1, "p95": 0.4, "p99": MARGIN, "max": 0.9}

    def shape(self, q, points=20):
        return self.inner.shape(q, points=points)

    def backbone(self, q, points=20):
        return self.shape(q, points).points


def _scene(robot, gap: float):
    """Open space and two spheres whose surfaces are ``gap`` mm from the tip of a fixed seed1
    configuration, on either side of it (perpendicular to the tip's tangent). Returns the scene,
    the target and the spheres' centres (2, 3)."""
    q = robot.sample(1, seed=5)
    pts = load_model("physics", robot).shape(q, points=64).points[0]
    tip, t = pts[-1], pts[-1] - pts[-2]
    t /= np.linalg.norm(t)
    n = np.cross(t, [1.0, 0.0, 0.0])
    n /= np.linalg.norm(n)
    centres = np.stack([tip + (SPHERE + gap) * n, tip - (SPHERE + gap) * n])
    box = trimesh.creation.box((10.0, 10.0, 10.0))
    box.apply_translation((0.0, 0.0, -400.0))
    meshes = [SceneMesh("box", "obstacle", box)]
    for i, c in enumerate(centres):
        s = trimesh.creation.icosphere(subdivisions=4, radius=SPHERE)
        s.apply_translation(c)
        meshes.append(SceneMesh(f"sphere{i}", "obstacle", s))
    scene = Scene(name="spheres", path="<memory>", meshes=tuple(meshes), base_pose=np.eye(4),
                  targets=())
    return scene, tip, centres


def _clearance_to_spheres(robot, path: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """(S,) smallest distance (mm) from the physics tube to the spheres, in closed form, at the
    path's states densified to 0.25 mm of the joint metric (rotations unwrapped in the path)."""
    n = robot.n
    q = [path[0]]
    for a, b in zip(path[:-1], path[1:]):
        metric = 30.0 * np.abs(b[:n] - a[:n]).sum() + np.linalg.norm(b[n:] - a[n:])
        k = max(1, int(np.ceil(metric / 0.25)))
        q.extend(a + (b - a) * (i / k) for i in range(1, k + 1))
    shape = load_model("physics", robot).shape(np.array(q), points=64)
    p0, p1 = shape.points[:, :-1], shape.points[:, 1:]
    r = np.maximum(shape.radius[:, :-1], shape.radius[:, 1:])
    out = np.full(len(q), np.inf)
    for c in centres:
        d = p1 - p0
        u = np.clip(np.einsum("bkj,bkj->bk", c - p0, d) / np.maximum(
            np.einsum("bkj,bkj->bk", d, d), 1e-300), 0.0, 1.0)
        closest = p0 + u[..., None] * d
        dist = np.linalg.norm(c - closest, axis=-1) - SPHERE - r
        out = np.minimum(out, dist.min(axis=1))
    return out


@pytest.fixture(scope="module")
def case():
    robot = ctrplan.load_robot("seed1")
    scene, target, centres = _scene(robot, gap=0.95)
    model = _StatedSurrogate(robot)
    rescued = Planner(robot, scene, model).plan(target, seed=0, time_limit=30.0)
    refused = Planner(robot, scene, model, PlannerConfig(goal_rescue=False)).plan(
        target, seed=0, time_limit=30.0)
    return robot, target, centres, rescued, refused


def test_the_margin_alone_blocks_the_target(case):
    robot, target, centres, _, refused = case
    r_tip = robot.tubes[0].od / 2.0
    gap = np.linalg.norm(centres - target, axis=1).min() - SPHERE
    assert r_tip < gap < r_tip + MARGIN          # free for physics, not with the margin
    assert refused.status.value in ("TARGET_IN_COLLISION", "GOAL_IN_COLLISION"), refused.message


def test_physics_decides_and_the_path_clears_the_spheres(case):
    robot, target, centres, rescued, _ = case
    assert rescued.success, rescued.message
    assert rescued.counts.get("goals_rescued", 0) >= 1 and rescued.counts["rescue_decided"] >= 1
    assert rescued.tip_error_mm <= 1.0 and rescued.goal_shift_mm == 0.0
    tip = np.asarray(rescued.tip_path)[-1]
    assert np.linalg.norm(tip - target) == pytest.approx(rescued.tip_error_mm, abs=1e-6)
    clear = _clearance_to_spheres(robot, np.asarray(rescued.path), centres)
    assert clear.min() > 0.0                              # the physics tube never touches
    assert clear[-1] < MARGIN                             # and the goal needed the rescue
    assert rescued.min_clearance_reference_mm > 0.0


def test_a_target_physics_blocks_stays_refused():
    robot = ctrplan.load_robot("seed1")
    scene, target, _ = _scene(robot, gap=0.4)            # closer than the tip's radius
    r = Planner(robot, scene, _StatedSurrogate(robot)).plan(target, seed=0, time_limit=10.0)
    assert r.status.value == "TARGET_IN_COLLISION", r.message
