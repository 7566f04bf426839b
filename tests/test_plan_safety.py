"""Plans that are safe for the real robot: margins, the reference re-check, planning models of
calibrated and direction-aware models, determinism under load, and the command line.

Oracles: FCL distances of a model's capsules (independent of the planner), closed-form facts
about the models used (a registration is a rigid transform; a row's shape must not depend on the
other rows), and byte comparison of paths.
"""

from __future__ import annotations

import json
import math
import os
import subprocess
import sys

import numpy as np
import pytest

from ctrplan.cli import main
from ctrplan.planning import PlanConfig, plan_to_target
from ctrplan.planning.plan import planning_model_of, scene_by_name
from ctrplan.planning.validator import BatchValidator, unwrap_path
from ctrplan.shape.base import Shape
from ctrplan.shape.physics import PhysicsModel

from .test_planning import SphereWorld

TARGET = "-8.216,544.457,-5.763"          # an airway target with negative coordinates


@pytest.fixture(scope="module")
def airway():
    return scene_by_name("airway")


class Bounded:
    """The physics model under another name, carrying an error bound (as a learned model would)."""

    def __init__(self, robot, p99):
        self.inner = PhysicsModel(robot)
        self.robot = robot
        self.name = "physics-with-bound"
        self.error_quantiles = {"p50": p99 / 3, "p95": p99 / 1.5, "p99": p99, "max": 2 * p99}

    def shape(self, q, points=20):
        return self.inner.shape(q, points)

    def backbone(self, q, points=20):
        return self.shape(q, points).points


# ---------------------------------------------------------------------- margins
def test_margin_auto_is_the_models_error_bound_and_the_path_keeps_it(seed1, airway):
    from ctrplan.collision.world import CollisionWorld

    model = Bounded(seed1, 0.4)
    r = plan_to_target(seed1, airway, airway.targets[2].position, model=model, seed=0, time_limit=30)
    assert r.success, r.message
    assert r.margin_auto and r.margin_mm == pytest.approx(0.4)
    assert r.reference_model == "physics" and r.counts["reference_states"] > 0
    # oracle: FCL distance of the model's capsules (radius + sagitta bound) along the path
    world = CollisionWorld(airway, prefilter=False, curvature_per_mm=r.curvature_bound_per_mm)
    shapes = model.shape(r.path, points=PlanConfig().validator.points)
    fcl = world.clearance_exact(shapes)
    assert fcl.min() >= 0.4 - 1e-6
    assert r.min_clearance_mm <= fcl.min() + 1e-6
    if r.min_clearance_exact:
        assert r.min_clearance_mm >= 0.4 - 1e-6
    # an explicit margin overrides the bound
    r0 = plan_to_target(seed1, airway, airway.targets[2].position, model=model, seed=0,
                        time_limit=30, config=PlanConfig(margin_mm=0.0))
    assert not r0.margin_auto and r0.margin_mm == 0.0


def test_min_clearance_exact_flag(seed1, airway):
    r = plan_to_target(seed1, airway, airway.targets[1].position, model="physics", seed=3,
                       time_limit=30, config=PlanConfig(clearance_pairs=1))
    assert r.success and not r.min_clearance_exact and r.min_clearance_mm >= 0
    full = plan_to_target(seed1, airway, airway.targets[1].position, model="physics", seed=3,
                          time_limit=30, config=PlanConfig(clearance_pairs=10**6))
    assert full.min_clearance_exact
    assert r.min_clearance_mm <= full.min_clearance_mm + 1e-9
    d = full.to_json()
    assert d["min_clearance_exact"] is True and d["min_clearance_reference_mm"] is not None


# ---------------------------------------------------------------------- models fit to plan with
def test_calibrated_models_plan_without_registration_and_row_by_row(seed1):
    from ctrplan.shape.effects import EffectModel

    reg = {"tx": 30.0, "ty": -20.0, "tz": 5.0, "rx": 0.2, "ry": 0.0, "rz": -0.3}
    cal = EffectModel(seed1, "compliant", {"registration": reg, "friction": {"lost1": 0.3, "lost2": 0.2, "lost3": 0.1}})
    pm = planning_model_of(cal)
    q = seed1.sample(12, seed=4)
    base = EffectModel(seed1, "compliant").shape(q, points=10).points
    # registration never reaches collision checking: without friction effects it is the base model
    nofric = planning_model_of(EffectModel(seed1, "compliant", {"registration": reg}))
    np.testing.assert_allclose(nofric.shape(q, points=10).points, base, atol=1e-9)
    # with friction every row is a pure function of itself, whatever else is in the batch
    whole = pm.shape(q, points=10).points
    for i in (0, 5, 11):
        np.testing.assert_allclose(pm.shape(q[i:i + 1], points=10).points[0], whole[i], atol=1e-9)
        np.testing.assert_allclose(pm.shape(q[::-1], points=10).points[len(q) - 1 - i], whole[i], atol=1e-9)
    assert np.linalg.norm(cal.shape(q, points=10).points - whole, axis=-1).max() > 1.0   # the frame differs


class DirectionModel:
    """A direction-aware stand-in: the physics backbone shifted 3 mm along x times the
    direction of alpha1 (the dead band of a backlash)."""

    needs_direction = True

    def __init__(self, robot):
        self.inner = PhysicsModel(robot)
        self.robot = robot
        self.name = "direction-test"
        self.calls = []

    def shape(self, q, points=20, direction=None):
        assert direction is not None and set(np.unique(direction)) <= {-1, 1}
        self.calls.append(np.array(direction))
        s = self.inner.shape(q, points)
        shift = np.zeros((len(q), 1, 3))
        shift[:, 0, 0] = 3.0 * np.asarray(direction)[:, 0]
        return Shape(s.points + shift, s.s, s.radius, s.ok)


def test_unknown_direction_is_checked_both_ways_known_direction_once(seed1):
    model = DirectionModel(seed1)
    q = seed1.retracted()
    q[seed1.n:] = [-150.0, -100.0, -50.0]
    tip = PhysicsModel(seed1).shape(q[None], points=2).tip[0]
    # a sphere touched only by the backbone shifted to -x (direction -1 of alpha1)
    world = SphereWorld([(tip + np.array([-3.0 - 1.25 - 1.0, 0, 0]), 1.2)])
    v = BatchValidator(seed1, model, world)
    assert not v.states_valid(q[None])[0]               # unknown: worst case of +1 and -1
    q1 = q.copy()
    q1[0] += 1e-4                                        # alpha1 moves +: the +1 branch only
    assert v.edge_valid(q, q1)
    assert not v.edge_valid(q1, q)                       # moving back: the -1 branch touches


# ---------------------------------------------------------------------- path form
def test_unwrapped_rotations_interpolate_as_verified():
    n = 3
    path = np.array([[3.0, 0.0, -3.0, 1, 2, 3], [-3.0, 0.5, 3.0, 1, 2, 3], [-2.0, 0.5, 3.1, 1, 2, 3]])
    out = unwrap_path(path, n)
    assert np.all(np.abs(np.diff(out[:, :n], axis=0)) <= math.pi)
    assert out[1, 0] == pytest.approx(-3.0 + 2 * math.pi) and out[1, 2] == pytest.approx(3.0 - 2 * math.pi)
    np.testing.assert_allclose(np.mod(out[:, :n] - path[:, :n] + math.pi, 2 * math.pi) - math.pi, 0, atol=1e-12)


def test_plan_path_has_continuous_rotations_and_names_the_solver(seed1, airway):
    r = plan_to_target(seed1, airway, airway.targets[2].position, model="physics", seed=0, time_limit=30)
    assert r.success and r.planner == "direct" and r.requested_planner == "rrtconnect"
    assert np.all(np.abs(np.diff(r.path[:, :seed1.n], axis=0)) < math.pi)
    via = plan_to_target(seed1, airway, airway.targets[2].position, model="physics", seed=0,
                         time_limit=30, config=PlanConfig(try_direct=False))
    assert via.success and via.planner == "rrtconnect"


# ---------------------------------------------------------------------- determinism
def _burner():
    code = "import time\nt=time.time()\nwhile time.time()-t<120: pass\n"
    return [subprocess.Popen([sys.executable, "-c", code]) for _ in range(max(2, os.cpu_count() or 2))]


def test_same_seed_same_path_beside_a_cpu_burning_process(seed1):
    """A search with several OMPL slices and goal refreshes gives byte-identical paths with and
    without other processes competing for the CPU (budgets are counts, not seconds)."""
    from benchmarks.hard_problems import load_problems

    prob = load_problems("airway")[0]
    scene = scene_by_name("airway")
    cfg = PlanConfig(try_direct=False)

    def once():
        return plan_to_target(seed1, scene, prob.target, model="physics", seed=7, time_limit=120,
                              config=cfg, start=prob.start)

    quiet = once()
    procs = _burner()
    try:
        loaded = once()
    finally:
        for p in procs:
            p.kill()
            p.wait()
    assert quiet.success and not quiet.time_cap_hit and not loaded.time_cap_hit
    assert quiet.counts["states_validated"] > 1000                  # a real search
    a = json.dumps(quiet.to_json()["path"]).encode()
    b = json.dumps(loaded.to_json()["path"]).encode()
    assert a == b


# ---------------------------------------------------------------------- command line
def _plan(tmp_path, *args, name="p.json"):
    out = tmp_path / name
    code = main(["-q", "plan", "--scene", "airway", "--model", "physics", *args, "--out", str(out)])
    return code, (json.loads(out.read_text()) if out.exists() else None)


def test_cli_target_with_negative_values_in_every_form(tmp_path, capsys):
    code, a = _plan(tmp_path, "--target", TARGET, name="a.json")
    assert code == 0 and a["success"]
    code, b = _plan(tmp_path, "--target", *TARGET.split(","), name="b.json")
    assert code == 0 and b["target"] == a["target"] == [float(v) for v in TARGET.split(",")]
    assert b["path"] == a["path"]
    # the example: parsed as a target (it is out of reach in this scene's frame)
    code, c = _plan(tmp_path, "--target", "-5,20,0", name="c.json")
    err = capsys.readouterr().err
    assert code == 2 and c["status"] == "UNREACHABLE" and c["target"] == [-5.0, 20.0, 0.0]
    assert "expected one argument" not in err and "UNREACHABLE" in err


def test_cli_start_and_margin(tmp_path, capsys):
    code, a = _plan(tmp_path, "--target", TARGET, "--margin", "auto", name="a.json")
    assert code == 0 and a["margin_auto"] and a["margin_mm"] == 0.0      # physics: bound 0
    mid = a["path"][len(a["path"]) // 2]
    start = ",".join(repr(v) for v in mid)
    code, s = _plan(tmp_path, "--target", TARGET, "--start", start, "--margin", "0.3", name="s.json")
    assert code == 0 and s["success"], s["message"]
    assert np.allclose(s["path"][0], mid) and s["margin_mm"] == 0.3 and not s["margin_auto"]
    assert s["min_clearance_mm"] >= 0.3 - 1e-9
    code, r = _plan(tmp_path, "--target", TARGET, "--start", "retracted", name="r.json")
    assert code == 0 and r["path"] == a["path"]
    for bad, needle in ((["--start", "1,2"], "--start"), (["--margin", "-1"], "--margin"),
                        (["--margin", "lots"], "--margin")):
        capsys.readouterr()
        code, _ = _plan(tmp_path, "--target", TARGET, *bad, name="bad.json")
        err = capsys.readouterr().err
        assert code == 2 and needle in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "bad.json").exists()


def test_cli_check_margin_auto_and_number(tmp_path, seed1):
    from ctrplan.robot import write_configs

    q = np.array([t.config for t in scene_by_name("skull_base").targets[:4]])
    cfg = tmp_path / "c.csv"
    write_configs(cfg, seed1, q)
    rows = {}
    for margin in ("auto", "0", "0.5"):
        out = tmp_path / f"v{margin}.csv"
        assert main(["-q", "check", "--scene", "skull_base", "--robot", "seed1", "--configs", str(cfg),
                     "--margin", margin, "--model", "physics", "--out", str(out)]) == 0
        rows[margin] = np.loadtxt(out, delimiter=",", skiprows=1, usecols=1)
    np.testing.assert_allclose(rows["auto"], rows["0"])          # physics: bound 0
    free = rows["0"] > 0.6
    np.testing.assert_allclose(rows["0.5"][free], rows["0"][free] - 0.5, atol=0.05)
