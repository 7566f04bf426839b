"""plan-batch with tip pose goals (issue 39's note: targets with standoff_mm / approach /
cone_deg) and ``view`` of a plan with a tip goal.

Oracles: the values written into each CSV here (parsing); the foreign generator's tip frame
(``tests/foreign``, nothing of ctrplan) and a brute-force closest point over every triangle of
the scene (``tests/test_tipgoal``) for the achieved tip direction and standoff; the job id
scheme restated here (sha1 of the job's settings) for the key of a point job; the cone's
geometry (every rim point at the half-angle from the axis, seen from the apex) computed here.
"""

from __future__ import annotations

import csv
import hashlib
import json

import numpy as np
import pytest

from ctrplan.errors import InputError
from ctrplan.planning.batch import Job, make_jobs, read_targets, run_batch
from tests.test_tipgoal import angle, brute_snap, foreign_tip_frame

HEADER = ["scene", "name", "x", "y", "z", "standoff_mm", "approach", "cone_deg"]


def write_csv(path, header, rows) -> str:
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)
    return str(path)


# ---------------------------------------------------------------------- the targets CSV
def test_targets_csv_reads_tip_goals(tmp_path):
    f = write_csv(tmp_path / "t.csv", HEADER, [
        ["airway", "a", 1, 2, 3, "2", "normal", "15"],
        ["airway", "b", 1, 2, 3, "", "0 0 -2", ""],          # a direction, spaces
        ["airway", "c", 1, 2, 3, "0.5", "1,0,0", "30"],      # a direction, quoted commas
        ["airway", "d", 1, 2, 3, "1.5", "", ""],             # a standoff along the normal
        ["airway", "e", 1, 2, 3, "", "", ""],                # a point
    ])
    rows = read_targets(f)
    assert rows[0] == ("airway", "a", (1.0, 2.0, 3.0), {
        "goal_standoff_mm": 2.0, "goal_approach": "normal", "goal_cone_deg": 15.0})
    assert rows[1][3] == {"goal_standoff_mm": None, "goal_approach": "0.0,0.0,-2.0",
                          "goal_cone_deg": None}
    assert rows[2][3] == {"goal_standoff_mm": 0.5, "goal_approach": "1.0,0.0,0.0",
                          "goal_cone_deg": 30.0}
    assert rows[3][3] == {"goal_standoff_mm": 1.5, "goal_approach": None, "goal_cone_deg": None}
    assert rows[4] == ("airway", "e", (1.0, 2.0, 3.0))            # a point row, as before
    jobs = make_jobs(rows, seeds=[0, 1])
    assert len(jobs) == 10 and jobs[0].goal_cone_deg == 15.0 and jobs[1].seed == 1
    assert not jobs[8].has_tip_goal and jobs[0].has_tip_goal
    # a CSV without the goal columns reads as it always did
    g = write_csv(tmp_path / "g.csv", ["x", "y", "z"], [[1, 2, 3]])
    assert read_targets(g, ["airway"]) == [("airway", "row2", (1.0, 2.0, 3.0))]


@pytest.mark.parametrize("cells,column,needle", [
    (["-1", "", ""], "standoff_mm", "distance in [0, 1000] mm"),
    (["abc", "", ""], "standoff_mm", "distance"),
    (["2000", "", ""], "standoff_mm", "distance"),
    (["nan", "", ""], "standoff_mm", "distance"),
    (["", "up", ""], "approach", "non-zero direction"),
    (["", "0 0 0", ""], "approach", "non-zero direction"),
    (["", "1 2", ""], "approach", "non-zero direction"),
    (["", "1 nan 0", ""], "approach", "finite"),
    (["", "normal", "0"], "cone_deg", "(0, 90]"),
    (["", "normal", "91"], "cone_deg", "(0, 90]"),
    (["", "normal", "wide"], "cone_deg", "(0, 90]"),
    (["2", "", "10"], "cone_deg", "needs approach"),
])
def test_bad_tip_goal_cells_name_file_row_and_column(tmp_path, cells, column, needle):
    f = write_csv(tmp_path / "bad.csv", HEADER, [["airway", "a", 1, 2, 3, "", "", ""],
                                                 ["airway", "b", 1, 2, 3, *cells]])
    with pytest.raises(InputError) as info:
        read_targets(f)
    msg = str(info.value)
    assert msg.startswith(f"{f}: row 3: {column}: ") and needle in msg and "\n" not in msg


def test_cli_bad_tip_goal_exits_2_writing_nothing(tmp_path, capsys):
    from ctrplan.cli import main

    f = write_csv(tmp_path / "bad.csv", HEADER, [["airway", "a", 1, 2, 3, "", "normal", "95"]])
    out = tmp_path / "o"
    assert main(["-q", "plan-batch", "--targets", f, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "row 2: cone_deg" in err and f in err
    assert "Traceback" not in err and not out.exists()


# ---------------------------------------------------------------------- job keys
def test_the_goal_is_part_of_the_job_key(tmp_path):
    p = (1.0, 2.0, 3.0)
    point = Job("airway", "a", p)
    # a point job keeps the key it had before jobs had goals (earlier batches resume): the
    # scheme restated here, over the settings of that time
    old = {"scene": "airway", "target_name": "a", "target": list(p), "seed": 0, "robot": "seed1",
           "model": "physics", "planner": "rrtconnect", "time_limit": 5.0, "tolerance_mm": 1.0,
           "margin": "auto", "objective": "clearance"}
    digest = hashlib.sha1(json.dumps(old, sort_keys=True).encode()).hexdigest()[:8]
    assert point.id == f"airway__a__s0__{digest}"
    goal = Job("airway", "a", p, goal_standoff_mm=2.0, goal_approach="normal", goal_cone_deg=15.0)
    changed = [Job("airway", "a", p, goal_standoff_mm=3.0, goal_approach="normal", goal_cone_deg=15.0),
               Job("airway", "a", p, goal_standoff_mm=2.0, goal_approach="0.0,0.0,1.0", goal_cone_deg=15.0),
               Job("airway", "a", p, goal_standoff_mm=2.0, goal_approach="normal", goal_cone_deg=20.0),
               Job("airway", "a", p, goal_standoff_mm=2.0, goal_approach="normal")]
    ids = {point.id, goal.id, *(j.id for j in changed)}
    assert len(ids) == 6
    # a result of the goal job is never taken for a job with another goal: its file is
    # another job's (not done), and one relabelled as this job is refused on its goal field
    from ctrplan.planning.batch import JobResult, _done
    from ctrplan.planning.jobfile import validate_job_file
    from ctrplan.planning.result import PlanStatus

    data = JobResult(goal, PlanStatus.UNREACHABLE, "x").to_json()
    path = tmp_path / f"{goal.id}.json"
    path.write_text(json.dumps(data))
    assert _done(path, changed[2]) is None
    with pytest.raises(InputError, match="goal_cone_deg: differs"):
        validate_job_file(path, {**data, "job_id": changed[2].id}, changed[2])


def test_a_goal_job_crosses_the_process_boundary_as_a_dict():
    """The pool and Ray run a job from its dict (``asdict``): the goal comes along, and a point
    farther than MAX_SNAP_MM from every surface with a standoff is that job's INPUT_ERROR
    (naming the target and the CSV's columns), not the batch's."""
    from dataclasses import asdict

    from ctrplan.planning.batch import _run_job_json
    from ctrplan.planning.plan import scene_by_name
    from ctrplan.planning.tipgoal import MAX_SNAP_MM

    scene = scene_by_name("airway")
    base = np.asarray(scene.base_pose[:3, 3], dtype=float)      # inside the lumen
    from tests.test_tipgoal import brute_snap

    d, _, _ = brute_snap(scene, base)
    assert d > MAX_SNAP_MM                                      # the oracle's premise
    job = Job("airway", "free", tuple(base), goal_standoff_mm=2.0)
    res = _run_job_json(asdict(job))
    assert res["job_id"] == job.id and res["goal_standoff_mm"] == 2.0
    assert res["status"] == "INPUT_ERROR" and res["message"].startswith("target: ")
    assert "standoff_mm / approach normal" in res["message"]


# ---------------------------------------------------------------------- a small batch
@pytest.fixture(scope="module")
def goal_batch(tmp_path_factory):
    """plan-batch on airway: the carina with standoff 2 mm, approach normal, cone 15 deg, and
    t03 as a point (seed 0)."""
    from ctrplan.cli import main
    from ctrplan.collision.scene import load_scene

    scene = load_scene("airway")
    c, p = scene.find_target("carina").position, scene.find_target("t03").position
    tmp = tmp_path_factory.mktemp("goals")
    f = write_csv(tmp / "t.csv", HEADER, [["airway", "carina", *c, "2", "normal", "15"],
                                          ["airway", "t03", *p, "", "", ""]])
    out = tmp / "out"
    rc = main(["-q", "plan-batch", "--targets", f, "--time", "10", "--out", str(out)])
    return dict(rc=rc, csv=f, out=out, scene=scene, carina=np.asarray(c), t03=np.asarray(p))


def _job_file(out, name) -> tuple[str, dict]:
    (path,) = (out / "jobs").glob(f"airway__{name}__*.json")
    return str(path), json.loads(path.read_text())


def test_batch_plans_the_tip_goal_into_its_cone(goal_batch):
    from tests.foreign.recheck import load_scene as foreign_scene

    assert goal_batch["rc"] == 0
    _, goal = _job_file(goal_batch["out"], "carina")
    _, point = _job_file(goal_batch["out"], "t03")
    assert goal["status"] == "SUCCESS" and point["status"] == "SUCCESS"
    fs = foreign_scene("airway")
    R, o = fs.pose[:3, :3], fs.pose[:3, 3]
    # the goal row: the tip frame of the last path state by the foreign generator
    ftip, ft = foreign_tip_frame("seed1", np.asarray(goal["path"][-1]))
    tip, tangent = R @ ftip[0] + o, R @ ft[0]
    _, q, n = brute_snap(goal_batch["scene"], goal_batch["carina"])
    n = n if np.dot(tip - q, n) > 0 else -n           # the normal toward the lumen (the tip)
    assert angle(tangent, -n)[0] <= 15.0               # within the cone around approach normal
    assert abs(float(np.dot(tip - q, n)) - 2.0) < 0.2   # at the standoff
    assert np.linalg.norm(tip - (q + 2.0 * n)) <= goal["tolerance_mm"]
    # plan.json records the goal as `plan` does
    assert goal["direction_error_deg"] <= 15.0 and goal["cone_deg"] == 15.0
    assert abs(goal["standoff_mm"] - 2.0) < 0.2 and goal["goal_shift_mm"] >= 0.0
    assert goal["snap_mesh"] == "trachea" and np.allclose(goal["tip_goal"]["position"], q, atol=1e-6)
    assert goal["target"] == [float(v) for v in goal_batch["carina"]]   # the row's point
    # the point row plans to its point, no goal recorded
    ftip, _ = foreign_tip_frame("seed1", np.asarray(point["path"][-1]))
    assert np.linalg.norm(R @ ftip[0] + o - goal_batch["t03"]) <= point["tolerance_mm"]
    assert point["tip_goal"] is None and point["goal_approach"] is None
    # the tables carry the goal columns
    with open(goal_batch["out"] / "jobs.csv") as fh:
        rows = {r["target_name"]: r for r in csv.DictReader(fh)}
    assert rows["carina"]["goal_approach"] == "normal" and float(rows["carina"]["goal_cone_deg"]) == 15
    assert float(rows["carina"]["direction_error_deg"]) == pytest.approx(goal["direction_error_deg"])
    assert rows["t03"]["goal_approach"] == "" and rows["t03"]["direction_error_deg"] == ""
    with open(goal_batch["out"] / "summary.csv") as fh:
        (summary,) = list(csv.DictReader(fh))
    assert summary["tip_goal_jobs"] == "1"
    assert float(summary["direction_error_deg_max"]) == pytest.approx(goal["direction_error_deg"])


def test_batch_resumes_by_goal(goal_batch):
    rows = read_targets(goal_batch["csv"])
    jobs = make_jobs(rows, seeds=[0], time_limit=10.0)
    again = run_batch(jobs, goal_batch["out"])
    assert (again.skipped, again.ran) == (2, 0)
    # another cone: the point job is done, the goal job is new (not taken from the old result)
    wider = [rows[0][:3] + ({**rows[0][3], "goal_cone_deg": 30.0},), rows[1]]
    todo = [j for j in make_jobs(wider, seeds=[0], time_limit=10.0)
            if not (goal_batch["out"] / "jobs" / f"{j.id}.json").exists()]
    assert [j.target_name for j in todo] == ["carina"]


# ---------------------------------------------------------------------- view
def _cone_check(lines: dict, point: np.ndarray, direction: np.ndarray, cone_deg: float) -> None:
    """Every cone outline point is the apex (the standoff point) or at ``cone_deg`` from the
    axis back along the approach, seen from the apex; the approach line ends at the point."""
    cone = lines["cone"][np.all(np.isfinite(lines["cone"]), axis=1)]
    rim = cone[np.linalg.norm(cone - point, axis=1) > 1e-9]
    assert len(rim) >= 40 and len(cone) > len(rim)          # the rim and lines from the apex
    assert np.allclose(angle(rim - point, np.broadcast_to(-direction, rim.shape)), cone_deg,
                       atol=1e-6)
    approach = lines["approach"]
    assert np.allclose(approach[-1], point) and angle(approach[-1] - approach[0], direction)[0] < 1e-6


GOAL_PLAN = {"tip_goal": {"position": [1.0, 2.0, 3.0], "direction": [0.0, 0.6, -0.8],
                          "cone_deg": 20.0, "standoff_mm": 2.0, "normal": [0.0, 0.0, 1.0]}}


def test_view_draws_the_approach_cone_and_the_standoff():
    import matplotlib

    matplotlib.use("Agg")
    from ctrplan import viz
    from ctrplan.commands.view import plan_goal

    goal = plan_goal(GOAL_PLAN, "p.json")
    point = np.array([1.0, 2.0, 5.0])                        # position + 2 mm along the normal
    assert np.allclose(goal.point, point) and np.allclose(goal.surface, [1, 2, 3])
    d = np.array([0.0, 0.6, -0.8])
    bb = np.stack([np.linspace([0, 0, -40], point, 20)] * 3)
    fig = viz.plan_figure([], bb, bb[-1], point, goal=goal)
    traces = {t.name: t for t in fig.data}
    lines = {k: np.column_stack([np.asarray(traces[name][c], dtype=float) for c in "xyz"])
             for k, name in (("cone", "approach cone"), ("approach", "approach direction"),
                             ("standoff", "standoff (surface target to tip goal)"))}
    _cone_check(lines, point, d, 20.0)
    assert np.allclose(lines["standoff"], [[1, 2, 3], point])
    assert "surface target" in traces and "standoff point (tip goal)" in traces
    png = viz.plan_png_figure([], bb, bb[-1], point, goal=goal)
    art = {ln.get_label(): np.column_stack(ln.get_data_3d()) for ln in png.axes[0].get_lines()}
    _cone_check({"cone": art["approach cone"], "approach": art["approach direction"]}, point, d, 20.0)
    # a plan to a point draws as before: no goal
    assert plan_goal({"tip_goal": None}, "p.json") is None
    plain = viz.plan_figure([], bb, bb[-1], point)
    assert not {"approach cone", "approach direction"} & {t.name for t in plain.data}
    import matplotlib.pyplot as plt

    plt.close("all")


@pytest.mark.parametrize("record,field", [
    ({"position": [1, 2, 3], "direction": [0, 0, 0]}, "tip_goal.direction"),
    ({"position": [1, 2, 3], "cone_deg": 10}, "tip_goal.cone_deg"),
    ({"position": [1, 2, "x"]}, "tip_goal.position"),
    ({"position": [1, 2, 3], "colour": 1}, "tip_goal"),
    ([1, 2, 3], "tip_goal"),
])
def test_view_refuses_a_bad_tip_goal(record, field):
    from ctrplan.commands.view import plan_goal

    with pytest.raises(InputError) as info:
        plan_goal({"tip_goal": record}, "p.json")
    assert str(info.value).startswith(f"p.json: {field}: ")


def test_view_of_a_batch_goal_job(goal_batch, tmp_path):
    from ctrplan.cli import main
    from ctrplan.commands.view import plan_goal

    src, goal = _job_file(goal_batch["out"], "carina")
    _, q, n = brute_snap(goal_batch["scene"], goal_batch["carina"])
    g = plan_goal(goal, src)
    assert np.allclose(g.surface, q, atol=1e-6)
    assert np.isclose(np.linalg.norm(g.point - q), 2.0) and angle(g.direction, n)[0] > 179.0
    from ctrplan.commands.view import plan_notes

    assert "cone 15 deg" in plan_notes(goal) and "standoff 2.0" in plan_notes(goal)
    assert main(["-q", "view", src, "--out", str(tmp_path / "v.png")]) == 0
    assert (tmp_path / "v.png").stat().st_size > 0
