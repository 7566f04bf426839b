"""Planning: OMPL glue, batched motion validation, plan_to_target on shipped scenes.

Oracles: a returned path re-checked state by state at 4x the planner's edge resolution with
exact FCL; the same seed reproduces a path; geometric facts about targets (farther than the
longest tube, inside a closed obstacle mesh). A small analytic stand-in world (spheres) checks
the validator's batching and every planner quickly.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass

import numpy as np
import pytest

from ctrplan.errors import InputError
from ctrplan.planning import PlanConfig, PlanStatus, plan_to_target
from ctrplan.planning import space as ompl_space
from ctrplan.planning.validator import (
    BatchValidator,
    ValidatorConfig,
    interpolate,
    interpolate_path,
)
from ctrplan.robot import load_robot
from ctrplan.shape.models import load_model


# ---------------------------------------------------------------------- a stand-in world
@dataclass(frozen=True)
class Report:
    collides: np.ndarray
    clearance_mm: np.ndarray
    contact: np.ndarray


class SphereWorld:
    """Spherical obstacles (robot base frame) with the CollisionWorld query interface; counts
    how many queries and states it answered."""

    def __init__(self, spheres):
        self.spheres = [(np.asarray(c, dtype=float), float(r)) for c, r in spheres]
        self.queries = 0
        self.states = 0

    def check(self, shape):
        self.queries += 1
        self.states += len(shape)
        P, R = shape.points, shape.radius
        a, b = P[:, :-1], P[:, 1:]
        rad = np.maximum(R[:, :-1], R[:, 1:])
        clear = np.full(len(P), np.inf)
        contact = np.full(len(P), "", dtype=object)
        for k, (c, r) in enumerate(self.spheres):
            ab = b - a
            t = np.clip(((c - a) * ab).sum(-1) / np.maximum((ab * ab).sum(-1), 1e-12), 0, 1)
            d = (np.linalg.norm(a + t[..., None] * ab - c, axis=-1) - r - rad).min(axis=1)
            better = d < clear
            clear[better] = d[better]
            contact[better] = f"sphere{k}"
        collides = (clear <= 0) | ~np.asarray(shape.ok, dtype=bool)
        contact[~collides] = ""
        return Report(collides, clear, contact)

    def collides(self, shape):
        return self.check(shape).collides

    def first_collision(self, shape):
        c = self.collides(shape)
        return int(np.argmax(c)) if c.any() else -1

    check_exact = check


@dataclass(frozen=True)
class PlainScene:
    """A scene with no meshes: base frame = scene frame shifted by ``offset``."""

    offset: tuple = (10.0, -5.0, 20.0)
    name: str = "spheres"
    meshes: tuple = ()

    def to_scene(self, p):
        return np.asarray(p, dtype=float) + np.asarray(self.offset)

    def to_base(self, p):
        return np.asarray(p, dtype=float) - np.asarray(self.offset)


@pytest.fixture(scope="module")
def robot():
    return load_robot("seed1")


@pytest.fixture(scope="module")
def physics(robot):
    return load_model("physics", robot)


def sphere_problem(robot, physics):
    """A start, a goal and a sphere on the straight line between their tips."""
    start = robot.retracted()
    goal = start.copy()
    goal[robot.n:] = [-180.0, -110.0, -60.0]
    goal[: robot.n] = [2.0, -1.0, 0.5]
    tips = physics.shape(np.stack([start, goal]), points=2).tip
    mid = interpolate(start, goal, robot.n, 50.0, 1.0)
    mid_tip = physics.shape(mid[len(mid) // 2][None], points=2).tip[0]
    return start, goal, tips, SphereWorld([(mid_tip, 3.0)])


# ---------------------------------------------------------------------- validator
def test_edge_is_one_shape_call_and_one_query_and_stops_at_first_collision(robot, physics):
    start, goal, _, world = sphere_problem(robot, physics)
    v = BatchValidator(robot, physics, world, ValidatorConfig(resolution_mm=2.0))
    states = v.edge_states(start, goal)
    assert len(states) > 20
    assert np.allclose(states[0], start) and np.allclose(states[-1], goal)
    assert v.edge_valid(start, goal) is False
    assert v.counters.shape_calls == 1 and world.queries == 1
    k = v.first_invalid(states)
    per_state = [bool(world.collides(physics.shape(s[None], points=v.config.points))[0]) for s in states]
    assert k == per_state.index(True)
    assert 0 < k < len(states) - 1


def test_interpolation_takes_the_shorter_arc_and_respects_resolution(robot):
    n = robot.n
    q0 = robot.retracted()
    q1 = q0.copy()
    q0[0], q1[0] = 3.0, -3.0                          # 0.28 rad apart across +-pi
    q1[n] = q0[n] + 10.0
    states = interpolate(q0, q1, n, 50.0, 1.0)
    assert np.all(np.abs(states[:, 0]) >= 3.0 - 1e-9)  # never passes through 0
    step = np.abs(np.diff(np.unwrap(states[:, 0]))) * 50.0 + np.abs(np.diff(states[:, n]))
    assert step.max() <= 1.0 + 1e-9
    path = np.stack([q0, q1, q0])
    dense, seg = interpolate_path(path, n, 50.0, 1.0)
    assert np.allclose(dense[0], q0) and np.allclose(dense[-1], q0)
    assert set(seg.tolist()) == {0, 1}


# ---------------------------------------------------------------------- OMPL glue
def test_ompl_calls_the_python_motion_validator_and_a_seed_reproduces_the_path(robot, physics):
    start, goal, _, world = sphere_problem(robot, physics)
    runs = []
    for _ in range(2):
        v = BatchValidator(robot, physics, world)
        out = ompl_space.solve(robot, v, start, goal[None], planner="rrtconnect", time_limit=10.0,
                               seed=3, simplify=True)
        assert out.status == "exact"
        assert v.counters.edges > 0 and v.counters.shape_calls >= v.counters.edges
        runs.append(out.path)
    assert np.array_equal(runs[0], runs[1])
    assert np.allclose(runs[0][0], start) and np.allclose(runs[0][-1], goal)
    v = BatchValidator(robot, physics, world)
    for a, b in zip(runs[0][:-1], runs[0][1:]):
        assert v.edge_valid(a, b)


@pytest.mark.parametrize("planner", ["rrtconnect", "rrt", "rrtstar", "bitstar", "kpiece"])
def test_planners_by_name(robot, physics, planner):
    start, goal, _, world = sphere_problem(robot, physics)
    v = BatchValidator(robot, physics, world)
    out = ompl_space.solve(robot, v, start, goal[None], planner=planner, time_limit=10.0, seed=1)
    assert out.status == "exact", planner
    check = v.check_path(out.path, v.config.resolution_mm / 4)
    assert check.ok


def test_unknown_planner_is_an_input_error():
    with pytest.raises(InputError, match="unknown planner"):
        ompl_space.check_planner("astar")
    # PRM deadlocks with Python validity checkers (second C++ thread vs the held GIL): refused
    with pytest.raises(InputError, match="deadlocks"):
        ompl_space.check_planner("PRM")


# ---------------------------------------------------------------------- plan_to_target
@pytest.fixture(scope="module")
def airway():
    from ctrplan.planning.plan import scene_by_name

    return scene_by_name("airway")


#: Always through OMPL (no straight start-goal shortcut), so the real-scene checks below
#: exercise the planner, the simplifier and the verification.
VIA_OMPL = PlanConfig(try_direct=False)


@pytest.fixture(scope="module")
def airway_plan(robot, airway):
    target = airway.targets[2].position
    return plan_to_target(robot, airway, target, model="physics", seed=0, time_limit=10.0,
                          config=VIA_OMPL)


def test_plan_succeeds_and_reaches_the_target(airway_plan, robot, airway):
    r = airway_plan
    assert r.success and r.status is PlanStatus.SUCCESS, r.message
    assert r.tip_error_mm <= 1.0
    assert r.path.shape[1] == robot.dof and len(r.path) >= 2
    assert np.allclose(r.path[0, robot.n:], robot.retracted()[robot.n:])
    assert r.backbones.shape[:2] == (len(r.path), PlanConfig().output_points)
    assert np.allclose(r.tip_path, r.backbones[:, -1])
    assert np.linalg.norm(r.tip_path[-1] - airway.targets[2].position) <= 1.0 + 1e-6
    assert r.min_clearance_mm >= 0.0
    assert set(r.timings) >= {"ik", "planning", "simplification", "verification", "total"}
    assert r.counts["states_validated"] > 0


def test_returned_path_is_collision_free_state_by_state_at_4x_finer_resolution(airway_plan, robot):
    """Independent re-check: own interpolation, one exact FCL query per state."""
    from ctrplan.collision.world import CollisionWorld
    from ctrplan.planning.plan import scene_by_name

    r = airway_plan
    cfg = PlanConfig()
    model = load_model("physics", robot)
    world = CollisionWorld(scene_by_name("airway"))
    res = cfg.validator.resolution_mm / 4
    n = robot.n
    checked = 0
    for a, b in zip(r.path[:-1], r.path[1:]):
        d = b - a
        d[:n] = (d[:n] + math.pi) % (2 * math.pi) - math.pi
        dist = cfg.validator.alpha_weight_mm * np.abs(d[:n]).sum() + np.linalg.norm(d[n:])
        k = max(1, math.ceil(dist / res))
        for t in np.linspace(0.0, 1.0, k + 1):
            q = a + t * d
            assert robot.is_valid(q[None])[0]
            rep = world.check_exact(model.shape(q[None], points=cfg.validator.points))
            assert not rep.collides[0], (t, rep.contact[0])
            checked += 1
    assert checked >= len(r.path)


def test_same_seed_same_path(robot, airway, airway_plan):
    again = plan_to_target(robot, airway, airway.targets[2].position, model="physics", seed=0,
                           time_limit=10.0, config=VIA_OMPL)
    assert again.status is airway_plan.status
    assert airway_plan.counts["direct"] == 0
    assert np.array_equal(again.path, airway_plan.path)


def test_plan_json_has_the_design_fields(airway_plan):
    d = airway_plan.to_json()
    for key in ("success", "status", "path", "tip_path", "tip_error_mm", "planning_time_s",
                "min_clearance_mm", "planner", "seed", "robot", "model", "scene"):
        assert key in d
    assert d["status"] == "SUCCESS" and d["model"] == "physics" and d["scene"] == "airway"
    json.dumps(d, allow_nan=False)


def test_impossible_target_is_unreachable(robot, airway):
    # (how fast this answer comes is measured in benchmarks/, not asserted here)
    r = plan_to_target(robot, airway, airway.to_scene(np.array([0.0, 0.0, 900.0])), model="physics")
    assert r.status is PlanStatus.UNREACHABLE and not r.success
    assert r.counts.get("ik_evaluations", 0) == 0          # decided by the reach bound, no IK
    assert len(r.path) == 0 and r.to_json()["tip_error_mm"] is None


def test_target_behind_the_base_is_unreachable(robot, airway):
    # Within the reach bound but behind the constraint plane: IK finds nothing.
    r = plan_to_target(robot, airway, airway.to_scene(np.array([0.0, 0.0, -40.0])), model="physics")
    assert r.status is PlanStatus.UNREACHABLE, r.message


def test_target_inside_an_obstacle(robot):
    from ctrplan.planning.plan import scene_by_name

    scene = scene_by_name("skull_base")
    carotid = scene.mesh("internal_carotid_right").mesh
    point = carotid.centroid
    assert carotid.contains(point[None])[0]
    r = plan_to_target(robot, scene, point, model="physics")
    assert r.status is PlanStatus.TARGET_IN_COLLISION, r.message
    assert "internal_carotid_right" in r.message


def test_start_in_collision(robot, physics):
    start = robot.retracted()
    tip = physics.shape(start[None], points=2).tip[0]
    world = SphereWorld([(tip * 0.5, 30.0)])          # swallows the whole retracted robot
    r = plan_to_target(robot, PlainScene(), [0, 0, 150], model=physics, world=world)
    assert r.status is PlanStatus.START_IN_COLLISION


@pytest.mark.parametrize("target", [[np.nan, 0, 0], [0, np.inf, 1], [1, 2], "a,b,c"])
def test_bad_targets_raise_input_error(robot, airway, target):
    with pytest.raises(InputError):
        plan_to_target(robot, airway, target, model="physics")


def test_bad_planner_scene_and_time_raise_input_error(robot, airway):
    with pytest.raises(InputError, match="planner"):
        plan_to_target(robot, airway, [0, 0, 0], planner="dijkstra")
    with pytest.raises(InputError):
        plan_to_target(robot, "no_such_scene", [0, 0, 0])
    with pytest.raises(InputError, match="^time_limit: "):      # the Python argument's name
        plan_to_target(robot, airway, [0, 0, 0], time_limit=0)


# ---------------------------------------------------------------------- command line
def test_cli_plan_writes_plan_json(tmp_path):
    from ctrplan.cli import main

    out = tmp_path / "plan.json"
    assert main(["-q", "plan", "--scene", "airway", "--target", "t03", "--model", "physics",
                 "--out", str(out)]) == 0
    plan = json.loads(out.read_text())
    assert plan["success"] and plan["status"] == "SUCCESS" and plan["target_name"] == "mid_trachea_2" and plan["target_id"] == "t03"


@pytest.mark.parametrize("args,needle", [
    (["--scene", "airway", "--target", "nan,0,0"], "--target"),
    (["--scene", "airway", "--target", "1,2"], "--target"),
    (["--scene", "nowhere", "--target", "1,2,3"], "nowhere"),
    (["--scene", "airway", "--target", "1,2,3", "--planner", "magic"], "--planner"),
    (["--scene", "airway", "--target", "0,0,9000"], "UNREACHABLE"),
])
def test_cli_plan_bad_input_exits_2(tmp_path, capsys, args, needle):
    from ctrplan.cli import main

    code = main(["-q", "plan", *args, "--model", "physics", "--out", str(tmp_path / "p.json")])
    err = capsys.readouterr().err
    assert code == 2
    assert needle in err and "Traceback" not in err and len(err.strip().splitlines()) == 1


def test_a_segment_that_fails_the_fine_check_is_replanned(robot, physics):
    from ctrplan.planning.verify import repair

    start, goal, _, world = sphere_problem(robot, physics)
    coarse = BatchValidator(robot, physics, world, ValidatorConfig(resolution_mm=400.0))
    assert coarse.edge_valid(start, goal)               # steps over the sphere
    fine = BatchValidator(robot, physics, world)
    bad = fine.check_path(np.stack([start, goal]), 0.5)
    assert not bad.ok and bad.bad_segments == [0]
    fixed = repair(robot, physics, world, np.stack([start, goal]), bad.bad_segments, PlanConfig(),
                    seed=1, resolution_mm=0.5, budget=10.0)
    assert fixed is not None and np.allclose(fixed[0], start) and np.allclose(fixed[-1], goal)
    assert fine.check_path(fixed, 0.5).ok
