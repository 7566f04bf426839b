"""``ctrplan design`` on the procedural scene ``design_bend``.

Oracles that share no code with what they test:

- the scene by construction: a single tube of curvature 1/R (R the bend radius) and curved
  length R pi/2 reaches every target (the targets are its tip positions); the shipped robots
  reach none (plans with small budgets);
- strain ``od/2 x curvature`` and the radial nesting gaps computed by hand from robot.yaml;
- closed form: a single tube is an exact circular arc after its straight part, so every state
  of every returned path (interpolated here, linearly, 1 mm / 0.02 rad) has a backbone we write
  down by hand; it must stay inside the analytic lumen (distance to the swept centre line plus
  the tube radius below the lumen radius, up to the mesh's discretisation) and end at the
  target;
- stability re-checked by solving the compliant model densely along each path with the
  bistability probe (no snapping state, a stable equilibrium everywhere);
- the same seed gives the same robot.yaml bytes, and a rerun resumes from the state file.
"""

from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import yaml

from ctrplan import PhysicsConfig, PhysicsModel, load_robot, plan_to_target
from ctrplan.design import Bounds, DesignConfig, design, resolve_scene
from ctrplan.planning import PlanConfig

# one worker runs this file (`make test-stat` distributes by xdist group): its module fixtures
# are computed once
pytestmark = pytest.mark.xdist_group("design")


# the scene's construction, restated here (anatomy: a 90 degree bend of radius 30 mm, lumen
# radius 3 mm, swept 0..30 mm along +z; targets at the bend's end)
R, LUMEN, SWEEP, END = 30.0, 3.0, 30.0, math.radians(102.0)
DEPTHS = (3.0, 8.0, 13.0, 18.0, 23.0, 27.0)
NAMES = ",".join(f"t{k + 1:02d}" for k in range(len(DEPTHS)))
MESH_TOL = 0.35   # marching cubes at 0.5 mm + decimation + smooth union, mm


@pytest.fixture(scope="module")
def scene():
    return resolve_scene("design_bend")


def test_scene_targets_are_the_construction(scene):
    pts = np.array([t.position for t in scene.targets])
    expect = np.array([[R, 0.0, R + d] for d in DEPTHS])
    assert np.allclose(pts, expect, atol=1e-3)
    assert np.allclose(scene.base_pose, np.eye(4))


def lumen_distance(p: np.ndarray) -> np.ndarray:
    """Distance (N,) mm from points (N, 3) to the lumen's centre-line set: the bend arc
    swept along +z by 0..SWEEP, plus the entry segment z in [-6, 0] on the axis."""
    t = np.linspace(0.0, END, 1500)
    c = np.stack([R * (1 - np.cos(t)), np.zeros_like(t), R * np.sin(t)], axis=1)     # (K, 3)
    dx = p[:, None, 0] - c[None, :, 0]
    dy = p[:, None, 1]
    dz = p[:, None, 2] - c[None, :, 2]
    dz = dz - np.clip(dz, 0.0, SWEEP)          # vertical segment c + s e_z, s in [0, SWEEP]
    d = np.sqrt(dx**2 + dy**2 + dz**2).min(axis=1)
    ez = p[:, 2] - np.clip(p[:, 2], -6.0, 0.0)
    d_entry = np.sqrt(p[:, 0] ** 2 + p[:, 1] ** 2 + ez**2)
    return np.minimum(d, d_entry)


def single_tube_backbone(tube: dict, q: np.ndarray, m: int = 60) -> np.ndarray:
    """Closed form: straight for the part out of the plane, then an arc of the precurvature
    bending toward the tube's rotated +x. q = (alpha, beta); (m, 3) mm, base frame."""
    alpha, beta = float(q[0]), float(q[1])
    k, S, C = tube["curvature"], tube["straight_length"], tube["curved_length"]
    d = beta + S
    s = np.linspace(0.0, d + C, m)
    th = k * np.clip(s - d, 0.0, None)
    r = np.where(th > 0, (1 - np.cos(th)) / k, 0.0)
    z = np.minimum(s, d) + np.where(th > 0, np.sin(th) / k, 0.0)
    return np.stack([math.cos(alpha) * r, math.sin(alpha) * r, z], axis=1)


def dense(path: np.ndarray, n: int) -> np.ndarray:
    out = [path[0]]
    for a, b in zip(path[:-1], path[1:]):
        k = int(max(1, math.ceil(max(np.abs(b - a)[:n].max() / 0.02, np.abs(b - a)[n:].max() / 1.0))))
        out.extend(a + (b - a) * j / k for j in range(1, k + 1))
    return np.array(out)


def check_design(result, out: Path | None = None, strain_limit: float = 0.06, min_gap: float = 0.05):
    """The oracles on a design result (robot read back from robot.yaml when written)."""
    if out is not None:
        spec = yaml.safe_load((out / "robot.yaml").read_text())
        robot = load_robot(out / "robot.yaml")
    else:
        spec = result.robot.to_dict()
        robot = result.robot
    tubes = spec["tubes"]
    for t in tubes:                                      # strain by hand
        assert t["od"] / 2 * abs(t["curvature"]) <= strain_limit + 1e-12
    for a, b in zip(tubes[:-1], tubes[1:]):              # nesting by hand
        assert (b["id"] - a["od"]) / 2 >= min_gap - 1e-12
    for t in result.targets:
        if not t.reached:
            continue
        path = np.asarray(t.plan.path)
        states = dense(path, robot.n)
        assert robot.is_valid(states).all()
        # stability: the compliant model with the bistability probe along the whole path
        m = PhysicsModel(robot, config=PhysicsConfig(probe_bistable=True))
        sh = m.shape(states, points=8)
        assert sh.ok.all()
        assert not m.last_info.bistable.any() and not (m.last_info.branch == -1).any()
        if len(tubes) == 1:                              # closed form inside the analytic lumen
            pts = np.concatenate([single_tube_backbone(tubes[0], q) for q in states])
            assert (lumen_distance(pts) + tubes[0]["od"] / 2 <= LUMEN + MESH_TOL).all(), t.name
            tip = single_tube_backbone(tubes[0], path[-1])[-1]
            assert np.linalg.norm(tip - t.position) <= 1.0 + 1e-6


def test_shipped_robots_reach_no_target(scene):
    cfg = PlanConfig(max_states=3000, ik_rounds=1)
    for robot in ("seed1", "two_tube_nylon"):
        for t in scene.targets:
            r = plan_to_target(robot, scene, t.position, seed=0, time_limit=5.0, config=cfg)
            assert not r.success, (robot, t.name)


def test_the_construction_reaches_every_target(scene):
    from ctrplan.robot import Robot, Tube

    robot = Robot("construction", (Tube(1.0, 0.8, 40.0, R * math.pi / 2, 1 / R, 60000.0, 0.33),))
    for t in scene.targets:
        r = plan_to_target(robot, scene, t.position, seed=0, time_limit=10.0,
                           config=PlanConfig(max_states=20000))
        assert r.success, (t.name, r.status)


QUICK = DesignConfig(tubes=1, budget=48, generation=8,
                     bounds=Bounds(curvature=(0.0, 0.06), curved_length=(10.0, 100.0),
                                   straight_length=(20.0, 120.0)))


@pytest.fixture(scope="module")
def quick(tmp_path_factory):
    out = tmp_path_factory.mktemp("design")
    result = design("design_bend", NAMES, QUICK, out=out, progress=False)
    from ctrplan.design.report import write_outputs

    write_outputs(result, out)
    return result, out


def test_quick_design_reaches_every_target_within_the_constraints(quick):
    result, out = quick
    assert result.success, result.message
    assert result.reached == len(DEPTHS)
    assert all(t.clearance_mm > 0 for t in result.targets)
    check_design(result, out)
    doc = __import__("json").loads((out / "design.json").read_text())
    assert doc["reached"] == len(DEPTHS) and len(doc["evaluations"]) == result.counts["evaluations"]
    assert all((out / t["path_file"]).is_file() for t in doc["targets"])
    assert (out / "coverage.png").read_bytes()[:4] == b"\x89PNG"
    assert (out / "paths.png").read_bytes()[:4] == b"\x89PNG" and (out / "paths.html").is_file()
    plan = __import__("json").loads((out / doc["targets"][0]["path_file"]).read_text())
    assert load_robot(plan["robot"]) == load_robot(out / "robot.yaml")
    from ctrplan.robot import robot_from_record  # view draws the recorded robot (digest checked)

    assert robot_from_record(plan, "plan.json") == load_robot(out / "robot.yaml")


def test_rerun_resumes_from_the_state_file_with_the_same_design(quick, tmp_path):
    result, out = quick
    again = design("design_bend", NAMES, QUICK, out=out, progress=False)
    assert again.counts["resumed"] >= result.counts["evaluations"] - 1
    again.robot.save(tmp_path / "r.yaml")
    assert (tmp_path / "r.yaml").read_bytes() == (out / "robot.yaml").read_bytes()


def test_one_and_two_workers_give_the_same_design_and_records(quick, tmp_path):
    """The pipelined search (plans absorbed PLAN_LAG generations after they are chosen) on a
    pool of 2: the same robot.yaml bytes and the same record of every design evaluated."""
    result, out = quick
    two = design("design_bend", NAMES, replace(QUICK, workers=2), progress=False)
    two.robot.save(tmp_path / "r.yaml")
    assert (tmp_path / "r.yaml").read_bytes() == (out / "robot.yaml").read_bytes()
    dump = __import__("json").dumps
    assert dump(two.evaluations, sort_keys=True) == dump(result.evaluations, sort_keys=True)
    # the lag is exercised: some plans were taken in generations after they were chosen
    assert any(e.get("planned_at", -1) > e["generation"] for e in result.evaluations)


QUICK_CLI = ["--tubes", "1", "--budget", "48", "--generation", "8", "--curvature", "0,0.06", "--curved-length", "10,100",
             "--straight-length", "20,120"]   # QUICK on the command line


def _evaluated(doc: dict) -> list:
    return [(e["parameters"], e["binding"], e["screen_passed"], e["planned"], e["reached"],
             e.get("clearance_mm")) for e in doc["evaluations"]]


@pytest.mark.statistical
def test_ray_local_gives_the_same_design_as_one_worker(quick, tmp_path, capsys):
    """``design --ray local`` (the plan-batch Ray path, a local instance) evaluates the same
    designs in the same order and returns the same robot.yaml bytes as the in-process run."""
    pytest.importorskip("ray")
    from ctrplan.cli import main

    result, out = quick
    rc = main(["-q", "design", "--scene", "design_bend", "--targets", NAMES, *QUICK_CLI,
               "--ray", "local", "--out", str(tmp_path / "ray")])
    assert rc == 0, capsys.readouterr().err
    assert (tmp_path / "ray" / "robot.yaml").read_bytes() == (out / "robot.yaml").read_bytes()
    doc = __import__("json").loads((tmp_path / "ray" / "design.json").read_text())
    one = __import__("json").loads((out / "design.json").read_text())
    assert len(doc["evaluations"]) == result.counts["evaluations"]
    assert _evaluated(doc) == _evaluated(one)


def test_ray_missing_is_one_line_exit_2(tmp_path, capsys, monkeypatch):
    """Without ray installed, --ray is bad input: one line naming --ray, exit 2, nothing written."""
    import sys

    from ctrplan.cli import main

    monkeypatch.setitem(sys.modules, "ray", None)       # import ray -> ImportError
    out = tmp_path / "d"
    rc = main(["-q", "design", "--scene", "design_bend", "--targets", "t01", "--budget", "1",
               "--ray", "local", "--out", str(out)])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1 and "--ray" in err and "ray is not installed" in err
    assert "Traceback" not in err and not out.exists()


def test_ray_and_workers_exclude_each_other(tmp_path, capsys):
    from ctrplan.cli import main
    from ctrplan.errors import InputError

    with pytest.raises(InputError, match="--workers"):
        DesignConfig(workers=2, ray_address="local")
    with pytest.raises(InputError, match="--ray"):
        DesignConfig(ray_address="  ")
    code = main(["-q", "design", "--scene", "design_bend", "--targets", "t01", "--workers", "2",
                 "--ray", "local", "--out", str(tmp_path / "d")])
    assert code == 2 and "not allowed with argument" in capsys.readouterr().err
    assert not (tmp_path / "d").exists()


@pytest.mark.statistical
def test_same_seed_same_design_from_scratch(quick, tmp_path):
    _, out = quick
    fresh = design("design_bend", NAMES, QUICK, progress=False)
    fresh.robot.save(tmp_path / "r.yaml")
    assert (tmp_path / "r.yaml").read_bytes() == (out / "robot.yaml").read_bytes()


def test_from_robot_is_kept(scene, tmp_path):
    """--from: the user's tube is kept as the outermost; a tube is designed inside it."""
    (tmp_path / "outer.yaml").write_text(
        "name: mine\ntubes:\n  - {od: 2.5, id: 2.2, straight_length: 30, curved_length: 10, "
        "curvature: 0.0, youngs_modulus: 60000, poisson_ratio: 0.33}\n")
    cfg = DesignConfig(tubes=2, budget=8, generation=8, plan_budget=1)
    r = design("design_bend", "t01", cfg, start_from=tmp_path / "outer.yaml", progress=False)
    for e in r.evaluations:
        if e["robot"] is not None:
            outer = e["robot"]["tubes"][-1]
            assert (outer["od"], outer["id"], outer["curvature"]) == (2.5, 2.2, 0.0)
            assert len(e["robot"]["tubes"]) in (1, 2)


@pytest.mark.statistical
def test_default_design_on_design_bend(tmp_path, capsys):
    """The acceptance run: default settings (seed 0), through the CLI; >= 90 % of the targets
    with >= 0.5 mm clearance, every constraint, the independent re-check of each plan, the
    same design again for the same seed on 2 workers, and the design loads in `plan`."""
    import sys

    from ctrplan.cli import main

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from hard_problems import verify_path

    out = tmp_path / "a"
    rc = main(["-q", "design", "--scene", "design_bend", "--targets", NAMES, "--out", str(out)])
    assert rc == 0
    doc = __import__("json").loads((out / "design.json").read_text())
    reached = [t for t in doc["targets"] if t["reached"] and t["clearance_mm"] >= 0.5]
    assert len(reached) >= math.ceil(0.9 * len(DEPTHS))
    robot = load_robot(out / "robot.yaml")
    scene = resolve_scene("design_bend")
    for t in reached:
        plan = __import__("json").loads((out / t["path_file"]).read_text())
        free, _ = verify_path(robot, scene, np.array(plan["path"]))
        assert free, t["name"]
    again = design("design_bend", NAMES, DesignConfig(workers=2), progress=False)
    again.robot.save(tmp_path / "b.yaml")
    assert (tmp_path / "b.yaml").read_bytes() == (out / "robot.yaml").read_bytes()
    check_design(again)
    target = ",".join(str(v) for v in doc["targets"][0]["position"])
    assert main(["-q", "plan", "--scene", scene.path, "--robot", str(out / "robot.yaml"),
                 "--target", target, "--out", str(tmp_path / "p.json")]) == 0
    assert main(["-q", "view", str(out / reached[0]["path_file"]), "--out", str(tmp_path / "v.png")]) == 0


@pytest.mark.statistical
def test_interrupted_search_resumes_to_the_same_design(quick, tmp_path, monkeypatch):
    """Ctrl-C after the first generation: the state file keeps it; the rerun evaluates only
    what is left and ends with the same design as the uninterrupted run."""
    from ctrplan import progress

    _, out = quick
    real = progress.bar

    class Stop:
        """The design search's bar: Ctrl-C at its first update (a generation's end)."""
        def __init__(self, *a, **k):
            self.inner = real(*a, **k)

        def update(self, n):
            raise KeyboardInterrupt

        def close(self):
            self.inner.close()

    def bar(*a, **k):
        # other bars (closing the scene's meshes while it loads) run as usual
        return Stop(*a, **k) if k.get("desc") == "design" else real(*a, **k)

    monkeypatch.setattr(progress, "bar", bar)
    with pytest.raises(KeyboardInterrupt):
        design("design_bend", NAMES, QUICK, out=tmp_path / "d")
    monkeypatch.setattr(progress, "bar", real)
    assert (tmp_path / "d" / "state.json").is_file()
    again = design("design_bend", NAMES, QUICK, out=tmp_path / "d", progress=False)
    assert again.counts["resumed"] >= QUICK.generation
    again.robot.save(tmp_path / "r.yaml")
    assert (tmp_path / "r.yaml").read_bytes() == (out / "robot.yaml").read_bytes()


def test_stability_check_rejects_a_snapping_path():
    """two_tube_nylon with deep overlap of the curved sections: rotating the inner tube through
    180 deg passes states with two stable equilibria (the snap; tests/test_stability.py shows
    the untwisted 180 deg state is unstable under an independent energy oracle), while inserting
    with the curvatures aligned is stable throughout."""
    from ctrplan.design.evaluate import EvalSettings, stable_along

    rb = load_robot("two_tube_nylon")
    s = EvalSettings()
    assert not stable_along(rb, np.array([[0.0, 0, -150, -60], [math.pi, 0, -150, -60]]), s)[0]
    ok, states = stable_along(rb, np.array([[0.3, 0.3, -150, -60], [0.3, 0.3, -100, -20]]), s)
    assert ok and states >= 40          # interpolated at 1 mm: 40 mm of insertion


def test_every_decoded_design_meets_the_hard_constraints_by_hand():
    """200 random points of the design space (1-3 tubes): each robot decoded satisfies strain,
    nesting gap, length and stroke limits computed here from its tube values, and a repair
    that hits a limit is named (strain: curvature exactly at limit / (od / 2))."""
    from ctrplan.design.space import Bounds, decode, load_stock, make_space

    b = Bounds(strain_limit=0.05, min_gap_mm=0.1, max_length_mm=300.0, max_stroke_mm=200.0)
    stock = load_stock()
    rng = np.random.default_rng(3)
    named = set()
    for tubes in (1, 2, 3):
        space = make_space(b, stock, (), tubes)
        for _ in range(70):
            k = int(rng.integers(1, tubes + 1))
            dec = decode(space, k, rng.uniform(size=space.dim))
            named |= set(dec.binding)
            if dec.robot is None:
                continue
            t = dec.robot.tubes
            assert len(t) == k
            for x in t:
                assert x.od / 2 * x.curvature <= 0.05 + 1e-9
                assert x.straight_length + x.curved_length <= 300.0 + 1e-6
                assert x.straight_length <= 200.0 + 1e-9
                assert (x.od, x.id) in stock
                if "strain" in dec.binding and abs(x.od / 2 * x.curvature - 0.05) < 1e-6:
                    named.add("strain-at-limit")
            for a, c in zip(t[:-1], t[1:]):
                assert (c.id - a.od) / 2 >= 0.1 - 1e-12
    assert {"strain", "strain-at-limit", "stroke"} <= named
