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
    result = plan_to_target(robot, scene, scene.targets[1].position, model=model, time_limit=5.0, seed=3,
                            objective="first")
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
    # (the verified states' shapes are those of the equilibria continued along the path, which
    # Newton converged to from another start than the history-free solve above: 1e-9 mm apart)
    assert abs(value - float(brute.min())) < 1e-6
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


# ---------------------------------------------------------------------- the clearance objective
# Oracle: the hard benchmark's independent re-check (benchmarks/hard_problems.verify_path): its
# own interpolation of the returned path at 8x the edge resolution, physics backbones and FCL
# distances (branch and bound over exact capsule-mesh distances); nothing of the optimiser (which
# steers by the distance field's estimate) is used.
import json  # noqa: E402
import sys  # noqa: E402
from pathlib import Path  # noqa: E402

import pytest  # noqa: E402

from ctrplan.errors import InputError  # noqa: E402
from ctrplan.planning import PlanConfig  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from hard_problems import load_problems, verify_path  # noqa: E402

# one worker runs this file (`make test-stat` distributes by xdist group): its module fixtures
# are computed once
pytestmark = pytest.mark.xdist_group("plan_clearance")


@pytest.fixture(scope="module")
def skull_plans():
    """skull_base hard problem 2 planned through RRTConnect with each objective (same seed)."""
    robot = load_robot("seed1")
    scene = load_scene("skull_base")
    prob = load_problems("skull_base")[1]
    plans = {obj: plan_to_target(robot, scene, prob.target, model="physics", seed=0,
                                 start=prob.start, config=PlanConfig(try_direct=False),
                                 objective=obj)
             for obj in ("first", "clearance")}
    return robot, scene, prob, plans


def test_clearance_objective_keeps_farther_from_the_anatomy_than_first(skull_plans):
    robot, scene, prob, plans = skull_plans
    first, best = plans["first"], plans["clearance"]
    assert first.success and best.success
    free_first, clear_first = verify_path(robot, scene, first.path)
    free_best, clear_best = verify_path(robot, scene, best.path)
    # both paths are collision-free in the independent re-check
    assert free_first and free_best
    # the first solution hugs the wall; the optimised one keeps at least 2x (and 0.1 mm) farther
    assert clear_best >= max(2.0 * clear_first, clear_first + 0.1), (clear_first, clear_best)
    # the target is still reached: the optimised goal's tip (scene frame, from the returned
    # backbones) is within the IK's convergence threshold of the target
    assert np.linalg.norm(best.tip_path[-1] - prob.target) <= 0.05 + 1e-6
    assert best.tip_error_mm <= 0.05 + 1e-6
    # the reported minimum (FCL, padded capsules) agrees with the re-check's
    assert best.min_clearance_mm <= clear_best + 1e-6
    assert best.objective == "clearance" and first.objective == "first"
    assert np.isfinite(best.objective_value) and not np.isfinite(first.objective_value)
    # the profile has one value per path state and its minimum is near FCL's minimum
    assert best.clearance_profile.shape == (len(best.path),)
    assert abs(float(best.clearance_profile.min()) - clear_best) < 0.5


def test_clearance_objective_same_seed_same_path(skull_plans):
    robot, scene, prob, plans = skull_plans
    again = plan_to_target(robot, scene, prob.target, model="physics", seed=0, start=prob.start,
                           config=PlanConfig(try_direct=False), objective="clearance")
    assert again.path.tobytes() == plans["clearance"].path.tobytes()


def test_bad_objective_is_an_input_error():
    with pytest.raises(InputError, match="^objective: "):
        PlanConfig(objective="shortest")
    with pytest.raises(InputError, match="^objective: "):
        plan_to_target("seed1", "airway", [0.0, 0.0, 50.0], objective="fast")


def test_calibrated_flag_follows_the_models_error_bound():
    from ctrplan.shape.physics import PhysicsModel

    robot = load_robot("seed1")
    scene = load_scene("airway")
    target = scene.targets[2].position
    nominal = plan_to_target(robot, scene, target, model="physics", seed=0)
    assert nominal.success and nominal.calibrated is False
    measured = PhysicsModel(robot)
    measured.error_quantiles = {"p50": 0.05, "p95": 0.1, "p99": 0.15, "max": 0.2}
    measured.error_bound = "measured"      # where the bound came from (error_bounds)
    calibrated = plan_to_target(robot, scene, target, model=measured, seed=0)
    assert calibrated.calibrated is True and calibrated.margin_mm == pytest.approx(0.15)


def test_cli_objective_and_plan_json_fields(tmp_path, capsys):
    from ctrplan.cli import main

    out = tmp_path / "plan.json"
    assert main(["-q", "plan", "--scene", "airway", "--target", "t03", "--objective", "length",
                 "--out", str(out)]) == 0
    plan = json.loads(out.read_text())
    assert plan["objective"] == "length" and plan["calibrated"] is False
    assert len(plan["clearance_profile"]) == len(plan["path"])
    # the length objective's value is the path's metric length (recomputed here)
    q = np.array(plan["path"])
    d = np.diff(q, axis=0)
    length = 30.0 * np.abs(d[:, :3]).sum(1) + np.linalg.norm(d[:, 3:], axis=1)
    assert plan["objective_value"] == pytest.approx(float(length.sum()), rel=1e-6)
    text = capsys.readouterr().out
    assert "SUCCESS" in text and "nominal model" in text and "ctrplan diagnose" in text
    assert "--margin auto" in text


def test_cli_bad_objective_exits_2_with_one_line(tmp_path, capsys):
    from ctrplan.cli import main

    out = tmp_path / "plan.json"
    code = main(["-q", "plan", "--scene", "airway", "--target", "t03", "--objective", "safest",
                 "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "--objective" in err and "Traceback" not in err
    assert len(err.strip().splitlines()) == 1 and not out.exists()


@pytest.mark.statistical
def test_hard_set_clearance_objective_triples_the_median_clearance():
    """RRTConnect, physics, the whole hard set (17 problems), both objectives, same seeds (the
    plans are the same on any machine): the clearance objective solves >= 95 % and the median
    over plans of each plan's minimum clearance on the planning model is >= 3x the first
    solutions' (issue 18's bar; the committed benchmark, `make bench`: 0.50 vs 0.11 mm). The
    independent re-check of the same objectives is the next test (about 10 s per plan).
    Planning time is compared in the benchmark (same run), not here. About 1 min."""
    from bench_hard import run_one, scenes

    from ctrplan.planning.planner import Planners

    kept = Planners(size=8)      # one planner per scene and objective, as the benchmark keeps
    med = {}
    for objective in ("clearance", "first"):
        recs = [run_one(p, "physics", "rrtconnect", 0, 10.0, objective=objective, recheck=False,
                        planners=kept)
                for s in scenes() for p in load_problems(s)]
        ok = [r["clearance"] for r in recs if r["success"]]
        assert len(recs) == 17
        if objective == "clearance":
            assert len(ok) >= 0.95 * len(recs), recs
        med[objective] = float(np.median(ok))
    assert med["clearance"] >= 3.0 * med["first"], med


@pytest.mark.statistical
def test_hard_set_clearance_objective_keeps_farther_in_the_independent_recheck(tmp_path):
    """The first 2 hard problems per scene, both objectives in the same run, every plan
    re-checked independently (foreign mechanics, exact FCL cylinders, 8x the edge resolution):
    the median of each plan's minimum clearance is >= 1.5x the first solutions' (the committed
    benchmark's 17 problems: 2.1x; the re-check's robot is not the planning model, so neither
    objective's plans keep the planned distance exactly) and every successful path is free in
    the re-check. About 3 min on one core."""
    from bench_hard import run

    res = run(["physics"], ["rrtconnect"], 1, 10.0, 2, tmp_path, objectives=("clearance", "first"))
    rows = {r["objective"]: r for r in res["table"]}
    assert rows["clearance"]["success_rate"] >= 0.95, rows
    assert rows["clearance"]["recheck_clearance_median_mm"] >= \
        1.5 * rows["first"]["recheck_clearance_median_mm"], rows
    assert all(r["recheck_free"] for r in res["records"] if r["success"])


def test_direction_aware_model_plans_with_the_clearance_objective():
    """A calibrated model with friction (shape depends on the direction of motion): the
    optimiser evaluates every state with its edge's direction and the result passes the
    planner's direction-aware verification; the path is re-checked here with the model's own
    capsules, every state with the direction of the edge that reaches it and of the edge that
    leaves it (signs of the unwrapped joint differences, computed here)."""
    from ctrplan.collision.capsules import curvature_bound
    from ctrplan.planning.plan import planning_model_of
    from ctrplan.shape.effects import EffectModel

    robot = load_robot("seed1")
    scene = load_scene("airway")
    cal = EffectModel(robot, "compliant", {"friction": {"lost1": 0.3, "lost2": 0.2, "lost3": 0.1}})
    r = plan_to_target(robot, scene, scene.targets[2].position, model=cal, seed=0)
    assert r.success and r.objective == "clearance"
    assert r.counts["optimizer_trials"] > 0
    pm = planning_model_of(cal)
    world = CollisionWorld(scene, curvature_per_mm=curvature_bound(pm))
    step = np.sign(np.diff(r.path, axis=0)).astype(np.int8)
    step[step == 0] = 1
    for q, d in ((r.path[1:], step), (r.path[:-1], step)):
        for sign in (-1, 1):   # joints that do not move: either way
            dd = np.where(np.diff(r.path, axis=0) == 0, sign, d).astype(np.int8)
            assert not world.collides(pm.shape(q, points=24, direction=dd)).any()


def test_field_clearance_estimate_is_near_fcl_distance():
    """The optimiser steers by an estimate (trilinear interpolation of the distance field's
    stored distance to the nearest surface sample): checked against FCL's exact distance of the
    same capsules on states of a known collision-free path, within one grid spacing."""
    from ctrplan.collision.capsules import curvature_bound
    from ctrplan.planning.optimize import FieldClearance
    from ctrplan.planning.validator import interpolate_path

    robot = load_robot("seed1")
    scene = load_scene("bronchial_tree")
    model = load_model("physics", robot)
    world = CollisionWorld(scene, curvature_per_mm=curvature_bound(model))
    states, _ = interpolate_path(load_problems("bronchial_tree")[0].solution, robot.n, 30.0, 60.0)
    shape = model.shape(states, points=24)
    exact = world.clearance_exact(shape)
    estimate = FieldClearance(world).capsule_clearance(shape).min(axis=1)
    h = max(f.h for f in world.fields)
    assert np.all(exact > 0)
    assert np.max(np.abs(estimate - exact)) <= h, np.c_[exact, estimate]


def test_field_clearance_point_distance_is_the_trilinear_interpolation():
    """The estimate's point distance is the trilinear interpolation of the field's stored
    distances (oracle: scipy's RegularGridInterpolator on the same grid), inf outside every
    grid and for non-finite points, the least over the meshes."""
    from scipy.interpolate import RegularGridInterpolator

    from ctrplan.planning.optimize import FieldClearance

    world = CollisionWorld(load_scene("neuro"))
    fc = FieldClearance(world)
    rng = np.random.default_rng(5)
    want = None
    pts = None
    for origin, h, ub in fc.grids:
        axes = [origin[i] + h * np.arange(ub.shape[i]) for i in range(3)]
        span = np.array(ub.shape) * h
        if pts is None:
            pts = origin + rng.uniform(-0.1, 1.1, (5000, 3)) * span
            pts[:3] = [np.nan, 0.0, 0.0]
            want = np.full(len(pts), np.inf)
        f = RegularGridInterpolator(axes, ub.astype(float), bounds_error=False, fill_value=np.inf)
        inside = np.all((pts >= origin) & (pts < origin + h * (np.array(ub.shape) - 1)), axis=1)
        want[inside] = np.minimum(want[inside], f(pts[inside]))
    got = fc.point_distance(pts)
    assert np.isinf(got[:3]).all()
    np.testing.assert_array_equal(np.isinf(got), np.isinf(want))
    fin = np.isfinite(want)
    assert fin.sum() > 1000 and (~fin).sum() > 500
    np.testing.assert_allclose(got[fin], want[fin], rtol=1e-9, atol=1e-9)


def test_optimiser_stops_at_the_time_cap_with_the_input_path():
    from ctrplan.collision.capsules import curvature_bound
    from ctrplan.planning.optimize import optimize_path

    robot = load_robot("seed1")
    scene = load_scene("skull_base")
    model = load_model("physics", robot)
    world = CollisionWorld(scene, curvature_per_mm=curvature_bound(model))
    prob = load_problems("skull_base")[1]
    v = BatchValidator(robot, model, world)
    res = optimize_path(v, prob.solution, scene.to_base(prob.target[None])[0], deadline=0.0)
    assert res.time_cap_hit and res.trials == 0 and res.accepted == 0
    assert np.allclose(res.path[0], prob.solution[0]) and np.allclose(res.path[-1], prob.solution[-1])
