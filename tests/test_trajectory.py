"""Trajectories (ctrplan.planning.trajectory, plan --trajectory, view): checked against oracles
that share no code with them or with the trajectory generator (ruckig).

- On the path: every sample of trajectory.csv, and every point of the straight line between two
  consecutive samples (what a controller streaming the samples with linear interpolation
  executes), lies on the verified polyline. The bound: a joint-space deviation of ``d`` mm of
  the planner's metric (``alpha_weight_mm * sum|d alpha| + |d beta|``) moves no backbone point
  more than ``MAX_SPEED * d`` (the fastest motion per metric mm the motion verification
  accepts), and the verification leaves ``MOTION_SLACK_MM`` of motion unexplained; so the
  deviation must stay below ``MOTION_SLACK_MM / MAX_SPEED`` (4e-6 mm of metric). Distances are
  upper bounds (a projection in scaled joint coordinates), and since the distance to a segment
  is convex, the larger of two samples' distances to one segment bounds their whole chord's.
- Within every limit: the first difference of the samples over the period h is the mean
  velocity over the period, the second difference over h^2 a mean of the acceleration
  weighted by a hat of unit mass: both lie within the limits exactly for the continuous
  motion, so the only tolerance is round-off (the CSV holds exact reprs).
- Time-optimal: the time-optimal rest-to-rest motion along a straight joint-space segment is a
  bang-coast-bang profile in closed form; the library's reported optimum must match it, and
  the trajectory's duration stay within 10 % of it.
- The profile (qd, qdd) integrates to the positions (trapezoid rule, scipy).
"""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from ctrplan import cli
from ctrplan.robot import load_robot, robot_from_dict
from ctrplan.shape.bounds import MAX_SPEED, MOTION_SLACK_MM

#: mm of backbone motion per rad of rotation in the planner's metric (ValidatorConfig default)
ALPHA_WEIGHT_MM = 30.0
#: largest deviation (mm of metric) from the polyline: no backbone point moves more than the
#: motion verification's unexplained slack
BOUND_METRIC_MM = MOTION_SLACK_MM / MAX_SPEED


# ---------------------------------------------------------------------------- oracles
def read_csv(path: Path) -> tuple[list[str], np.ndarray]:
    with open(path, newline="", encoding="utf-8") as fh:
        rows = list(csv.reader(fh))
    return rows[0], np.array([[float(c) for c in r] for r in rows[1:]])


def metric(d: np.ndarray, n: int) -> np.ndarray:
    return ALPHA_WEIGHT_MM * np.abs(d[..., :n]).sum(-1) + np.linalg.norm(d[..., n:], axis=-1)


def segment_distances(x: np.ndarray, poly: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Upper bounds of the metric distance of each state x (T, 2n) to each segment of the
    polyline (K, 2n), and the arc position (segment index + fraction) of the projection:
    (T, K - 1) each."""
    n = x.shape[1] // 2
    w = np.r_[np.full(n, ALPHA_WEIGHT_MM), np.ones(n)]
    a, b = poly[:-1] * w, poly[1:] * w
    c = b - a
    xs = x * w
    u = np.einsum("tkj,kj->tk", xs[:, None, :] - a[None], c) / np.maximum((c * c).sum(-1), 1e-300)
    u = np.clip(u, 0.0, 1.0)
    near = a[None] + u[..., None] * c[None]
    dist = metric((xs[:, None, :] - near) / w, n)
    return dist, np.arange(len(c))[None, :] + u


def straight_runs(path: np.ndarray) -> np.ndarray:
    """Indices of the path states that end a straight run: consecutive pieces whose directions
    (scaled joint coordinates) agree to a cosine of 1 - 1e-12 are one straight run (a plan's
    path is an edge subdivided at a resolution)."""
    n = path.shape[1] // 2
    w = np.r_[np.full(n, ALPHA_WEIGHT_MM), np.ones(n)]
    d = np.diff(path * w, axis=0)
    length = np.linalg.norm(d, axis=1)
    keep = [0]
    for k in range(1, len(d)):
        if length[k - 1] == 0 or length[k] == 0 or d[k - 1] @ d[k] < (1 - 1e-12) * length[k - 1] * length[k]:
            keep.append(k)
    return np.array(keep + [len(path) - 1])


def check_on_polyline(q: np.ndarray, path: np.ndarray) -> float:
    """The largest metric deviation from the path's polyline of the samples and of the chords
    between consecutive samples; also checks that the samples go along it in order. Measured
    against the polyline of the path's straight runs, plus how far the states inside a run lie
    from it (the distance to a segment is convex, so a run's pieces lie no farther from their
    run's chord than their end states)."""
    ends = straight_runs(path)
    poly = path[ends]
    inside = 0.0
    for i, (a, b) in enumerate(zip(ends[:-1], ends[1:])):
        if b > a + 1:
            inside = max(inside, float(segment_distances(path[a + 1:b], poly[i:i + 2])[0].max()))
    dist, arc = segment_distances(q, poly)
    pair = np.maximum(dist[:-1], dist[1:])            # bounds the chord k -> k+1, per segment
    worst = float(pair.min(axis=1).max()) if len(q) > 1 else float(dist.min())
    pos = arc[np.arange(len(q)), dist.argmin(axis=1)]
    assert pos[0] == 0.0 and pos[-1] == pytest.approx(len(poly) - 1, abs=1e-9)
    assert np.all(np.diff(pos) >= -1e-9), "the trajectory goes back along the path"
    return worst + inside


def check_limits(t: np.ndarray, q: np.ndarray, vmax: np.ndarray, amax: np.ndarray) -> None:
    """Finite differences of the samples within the limits (round-off only: 4 ulp / h^2)."""
    h = float(t[1] - t[0])
    assert np.allclose(np.diff(t), h, rtol=0, atol=1e-9)
    ulp = np.spacing(np.abs(q).max(axis=0) + 1.0)
    vel = np.diff(q, axis=0) / h
    acc = np.diff(q, 2, axis=0) / h**2
    assert np.all(np.abs(vel) <= vmax * (1 + 1e-12) + 2 * ulp / h), np.abs(vel).max(0) / vmax
    assert np.all(np.abs(acc) <= amax * (1 + 1e-12) + 4 * ulp / h**2), np.abs(acc).max(0) / amax


def bang_coast_bang(dq: np.ndarray, vmax: np.ndarray, amax: np.ndarray) -> float:
    """Closed-form time-optimal rest-to-rest duration along the straight segment dq."""
    m = np.abs(dq) > 0
    v = np.min(vmax[m] / np.abs(dq[m]))        # path speed limit, segments per second
    a = np.min(amax[m] / np.abs(dq[m]))
    return 1.0 / v + v / a if v * v / a <= 1.0 else 2.0 * math.sqrt(1.0 / a)


def random_path(robot, rng, corners: int) -> tuple[np.ndarray, np.ndarray]:
    """A polyline through ``corners + 2`` valid states with each edge cut into 1-6 collinear
    pieces (as plan.json's subdivided path): (path (K, 2n), its true stops (S + 1, 2n))."""
    stops = robot.sample(corners + 2, seed=rng)
    stops[:, :robot.n] += rng.integers(-3, 4, size=(len(stops), robot.n)) * 2 * np.pi  # unwrapped
    pieces = [stops[:1]]
    for a, b in zip(stops[:-1], stops[1:]):
        k = int(rng.integers(1, 7))
        pieces.append(a + np.linspace(0, 1, k + 1)[1:, None] * (b - a))
    return np.concatenate(pieces), stops


def with_actuators(robot, acts):
    d = robot.to_dict()
    d["actuators"] = acts
    return robot_from_dict(d, "test.yaml")


# ---------------------------------------------------------------------------- library
@pytest.mark.parametrize("case", range(12))
def test_trajectory_stays_on_the_path_within_the_limits_and_near_the_optimum(tmp_path, case):
    from ctrplan.planning.trajectory import time_parameterize

    rng = np.random.default_rng(900 + case)
    acts = ([{"rotation": {"max_speed": float(rng.uniform(0.2, 3)),
                           "max_accel": float(rng.uniform(0.5, 20))},
              "translation": {"max_speed": float(rng.uniform(2, 40)),
                              "max_accel": float(rng.uniform(5, 200))}} for _ in range(3)]
            if case % 3 else {})
    robot = with_actuators(load_robot("seed1"), acts)
    vmax, amax = robot.joint_limits()
    rate = [100.0, 50.0, 250.0, 30.0][case % 4]
    path, stops = random_path(robot, rng, corners=int(rng.integers(0, 6)))
    traj = time_parameterize(robot, path, rate)
    traj.write_csv(tmp_path / "t.csv", robot)
    header, data = read_csv(tmp_path / "t.csv")
    assert header == ["t", *robot.column_names]
    t, q = data[:, 0], data[:, 1:]
    assert np.array_equal(t, np.arange(len(t)) / rate) and t[-1] == traj.duration_s
    assert np.array_equal(q[0], path[0]) and np.array_equal(q[-1], path[-1])
    assert check_on_polyline(q, path) < BOUND_METRIC_MM
    check_limits(t, q, vmax, amax)
    assert robot.is_valid(q).all()
    # at rest at every corner: the corner is a sample and its neighbours are on its two sides
    for s in stops[1:-1]:
        assert np.any(np.all(np.abs(q - s) <= 1e-9, axis=1))
    # time-optimal: the library's optimum is the closed form; the trajectory within 10 % of it
    optimum = sum(bang_coast_bang(b - a, vmax, amax) for a, b in zip(stops[:-1], stops[1:]))
    assert traj.time_optimal_s == pytest.approx(optimum, rel=1e-9)
    assert optimum - 1e-9 <= traj.duration_s <= optimum + (len(stops) - 1) / rate + 1e-9
    assert traj.duration_s <= 1.1 * traj.time_optimal_s


def test_profile_velocities_integrate_to_the_positions():
    """qd integrated by the trapezoid rule (scipy) from the start gives the positions: on each
    period the rule errs by h^2/8 times the jump of the acceleration inside it, and the
    acceleration of one joint varies by at most 4 a_max per segment (0, +A, 0, -A, 0)."""
    from scipy.integrate import cumulative_trapezoid

    from ctrplan.planning.trajectory import time_parameterize

    robot = load_robot("seed1")
    vmax, amax = robot.joint_limits()
    path, stops = random_path(robot, np.random.default_rng(7), corners=4)
    traj = time_parameterize(robot, path, 100.0)
    h, segs = 1.0 / traj.rate_hz, len(stops) - 1
    q_int = path[0] + cumulative_trapezoid(traj.qd, traj.t, axis=0, initial=0.0)
    assert np.all(np.abs(q_int - traj.q) <= h**2 / 8 * 4 * amax * segs + 1e-9)
    v_int = cumulative_trapezoid(traj.qdd, traj.t, axis=0, initial=0.0)
    assert np.all(np.abs(v_int - traj.qd) <= h / 2 * 4 * amax * segs + 1e-9)
    assert np.all(np.abs(traj.qd) <= vmax * (1 + 1e-9)) and np.all(np.abs(traj.qdd) <= amax * (1 + 1e-9))
    assert np.all(traj.qd[traj.stop_index] == 0.0)


def test_a_path_that_does_not_move_is_one_sample_and_a_straight_one_has_no_corner():
    from ctrplan.planning.trajectory import time_parameterize

    robot = load_robot("seed1")
    q0 = robot.retracted()
    traj = time_parameterize(robot, np.stack([q0, q0, q0]), 100.0)
    assert traj.samples == 1 and traj.duration_s == 0.0
    q1 = q0 + np.r_[0.5, 0.0, 0.0, 20.0, 10.0, 5.0]
    line = q0 + np.linspace(0, 1, 30)[:, None] * (q1 - q0)
    traj = time_parameterize(robot, line, 100.0)
    assert len(traj.stops) == 2


def test_actuators_round_trip_and_defaults():
    robot = load_robot("seed1")
    assert "actuators" not in robot.to_dict()         # the defaults: digests of old plans hold
    one = with_actuators(robot, {"rotation": {"max_speed": 2.0}})
    assert one.joint_limits()[0].tolist() == [2.0] * 3 + [10.0] * 3
    assert robot_from_dict(yaml.safe_load(yaml.safe_dump(one.to_dict())), "r.yaml") == one
    per = with_actuators(robot, [{}, {"translation": {"max_accel": 7.5}}, {}])
    assert per.joint_limits()[1].tolist() == [5.0] * 3 + [50.0, 7.5, 50.0]
    assert robot_from_dict(per.to_dict(), "r.yaml") == per
    assert with_actuators(robot, [{}, {}, {}]) == robot


def test_plan_trajectory_uses_the_recorded_robot_and_refuses_a_result_without_a_path():
    """The Python API: the limits of the robot recorded in the result (its robot_spec)."""
    from types import SimpleNamespace

    import ctrplan

    robot = with_actuators(load_robot("seed1"), {"translation": {"max_speed": 2.0}})
    q0 = robot.retracted()
    path = np.stack([q0, q0 + np.r_[0, 0, 0, 40.0, 30.0, 20.0]])
    result = SimpleNamespace(path=path, robot_spec=robot.to_dict(), status="SUCCESS")
    traj = ctrplan.plan_trajectory(result, rate_hz=50)
    assert isinstance(traj, ctrplan.Trajectory)
    # 40 mm at 2 mm/s (the recorded limit, not the default 10 mm/s) plus the ramps
    assert traj.time_optimal_s == pytest.approx(40.0 / 2.0 + 2.0 / 50.0, rel=1e-9)
    with pytest.raises(ctrplan.InputError, match="no path"):
        ctrplan.plan_trajectory(SimpleNamespace(path=np.zeros((0, 6)), robot_spec=robot.to_dict(),
                                                status="TIMEOUT"))


@pytest.mark.parametrize("acts,field,says", [
    ({"rotation": {"max_sped": 1.0}}, "actuators.rotation.max_sped", "unknown key"),
    ({"spin": {}}, "actuators.spin", "unknown key"),
    ([{}, {}], "actuators", "one entry per tube"),
    ({"translation": {"max_speed": 0}}, "actuators.translation.max_speed", "plausible range"),
    ({"translation": {"max_accel": ".inf"}}, "actuators.translation.max_accel", "must be a number"),
    ([{}, {"rotation": {"max_speed": -1}}, {}], "actuators[1].rotation.max_speed", "plausible range"),
    ("fast", "actuators", "must be a mapping"),
])
def test_bad_actuators_are_refused_with_one_line_naming_file_and_field(tmp_path, capsys, acts,
                                                                       field, says):
    d = load_robot("seed1").to_dict()
    d["actuators"] = acts
    robot = tmp_path / "r.yaml"
    robot.write_text(yaml.safe_dump(d), encoding="utf-8")
    cfg = tmp_path / "c.csv"
    cfg.write_text("alpha1,alpha2,alpha3,beta1,beta2,beta3\n0,0,0,-150,-100,-50\n", encoding="utf-8")
    rc = cli.main(["shape", "--robot", str(robot), "--configs", str(cfg), "--out",
                   str(tmp_path / "s.npz")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "Traceback" not in err
    assert f"{robot}: {field}: " in err and says in err
    assert not (tmp_path / "s.npz").exists()


# ---------------------------------------------------------------------------- command line
@pytest.fixture(scope="module")
def planned(tmp_path_factory):
    """plan (airway, carina) with a robot YAML whose actuators are not the defaults, and its
    trajectory; then the view."""
    folder = tmp_path_factory.mktemp("traj")
    d = load_robot("seed1").to_dict()
    d["actuators"] = {"rotation": {"max_speed": 0.8, "max_accel": 4.0},
                      "translation": {"max_speed": 12.0, "max_accel": 40.0}}
    (folder / "robot.yaml").write_text(yaml.safe_dump(d), encoding="utf-8")
    rc = cli.main(["plan", "--robot", str(folder / "robot.yaml"), "--scene", "airway",
                   "--target", "carina", "--time", "5", "--seed", "0", "--out",
                   str(folder / "plan.json"), "--trajectory", str(folder / "trajectory.csv")])
    assert rc == 0
    return folder


def test_plan_writes_a_trajectory_on_the_verified_path_within_the_limits(planned):
    plan = json.loads((planned / "plan.json").read_text(encoding="utf-8"))
    robot = robot_from_dict(plan["robot_spec"], "plan.json")
    assert robot.joint_limits()[0].tolist() == [0.8] * 3 + [12.0] * 3   # the YAML's, recorded
    vmax, amax = robot.joint_limits()
    header, data = read_csv(planned / "trajectory.csv")
    assert header == ["t", "alpha1", "alpha2", "alpha3", "beta1", "beta2", "beta3"]
    t, q = data[:, 0], data[:, 1:]
    path = np.asarray(plan["path"])
    assert check_on_polyline(q, path) < BOUND_METRIC_MM
    check_limits(t, q, vmax, amax)
    rec = plan["trajectory"]
    assert plan["duration_s"] == t[-1] and rec["rate_hz"] == 100.0 and rec["samples"] == len(t)
    assert plan["duration_s"] <= 1.1 * rec["time_optimal_s"]
    assert rec["file"] == "trajectory.csv"


def test_view_animates_the_trajectory_and_ignores_a_stale_one(planned, capsys):
    out = planned / "plan.html"
    assert cli.main(["view", str(planned / "plan.json"), "--out", str(out)]) == 0
    html = out.read_text(encoding="utf-8")
    assert html.count("robot at t") == 61 and "sliders" in html    # 60 frames + the trace
    # an edited trajectory.csv is not the plan's: drawn without animation, with a warning
    lines = (planned / "trajectory.csv").read_text(encoding="utf-8").splitlines()
    (planned / "other").mkdir()
    (planned / "other" / "plan.json").write_text((planned / "plan.json").read_text())
    (planned / "other" / "trajectory.csv").write_text("\n".join(lines[:-1]) + "\n")
    stale = planned / "other" / "plan.html"
    assert cli.main(["view", str(planned / "other" / "plan.json"), "--out", str(stale)]) == 0
    assert "robot at t" not in stale.read_text(encoding="utf-8")
    assert "sha256 differs" in capsys.readouterr().err


def test_view_refuses_a_trajectory_of_another_plan(planned, tmp_path, capsys):
    lines = (planned / "trajectory.csv").read_text(encoding="utf-8").splitlines()
    (tmp_path / "t.csv").write_text("\n".join(lines[:-1]) + "\n", encoding="utf-8")
    rc = cli.main(["view", str(planned / "plan.json"), "--trajectory", str(tmp_path / "t.csv"),
                   "--out", str(tmp_path / "v.html")])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and "\n" not in err and "does not end at the end of the plan" in err
    assert not (tmp_path / "v.html").exists()


# ---------------------------------------------------------------------------- real browser
def _colour_columns(png: Path, rgb_hex: str, tol: int = 45) -> np.ndarray:
    """Pixel columns (x) of the pixels within ``tol`` of a colour."""
    import matplotlib.image as mpimg

    img = mpimg.imread(str(png))[..., :3]
    if img.dtype != np.uint8:
        img = (img * 255).round().astype(int)
    rgb = np.array([int(rgb_hex[i:i + 2], 16) for i in (1, 3, 5)])
    return np.nonzero(np.all(np.abs(img.astype(int) - rgb) <= tol, axis=-1))[1]


def test_animated_view_plays_offline_in_a_real_browser(tmp_path):
    """The animated HTML view in headless Chromium, made to jump to its last frame by Plotly's
    own animate call: it loads nothing from the network, and the moving robot (drawn at the
    first frame's place, where the static robot stands) is drawn 60 mm away along x, over a
    hundred pixels across the screen from the static one."""
    import trimesh

    from ctrplan import viz
    from tests.browser import find_chromium, screenshot

    chromium = find_chromium()
    if chromium is None:
        pytest.skip("no Chromium installed")
    tube = trimesh.creation.cylinder(radius=40.0, height=120.0, sections=24)
    meshes = [viz.ViewMesh("lumen", "wall", np.asarray(tube.vertices), np.asarray(tube.faces))]
    s = np.linspace(0, 1, 20)
    xs = np.linspace(-30.0, 30.0, 10)
    moving = np.stack([np.stack([x + 0 * s, 0 * s, -50 + 100 * s], axis=1) for x in xs])
    anim = viz.Animation(t=np.linspace(0, 4.5, 10), backbones=moving, tips=moving[:, -1])
    html = tmp_path / "view.html"
    viz.plan_html(html, meshes, moving[[0]], None, None, title="animated", animation=anim)
    text = html.read_text(encoding="utf-8")
    assert text.count("robot at t") == 11
    jump = ("<script>window.addEventListener('load', function () { setTimeout(function () {"
            "Plotly.animate(document.querySelector('.plotly-graph-div'), ['9'], {frame: "
            "{duration: 0, redraw: true}, transition: {duration: 0}, mode: 'immediate'});"
            "}, 1000); });</script></body>")
    (tmp_path / "last.html").write_text(text.replace("</body>", jump), encoding="utf-8")
    last = tmp_path / "last.png"
    assert screenshot(tmp_path / "last.html", last, chromium, budget_ms=4000) == []
    still = _colour_columns(last, viz.ROBOT_COLOUR)
    moved = _colour_columns(last, viz.MOVING_COLOUR)
    assert len(still) > 50 and len(moved) > 50, "a robot is not drawn"
    assert abs(np.median(moved) - np.median(still)) > 100, (np.median(still), np.median(moved))
