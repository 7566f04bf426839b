"""Batch planning: target files, resumable runs, process pool, Ray, summaries, the command."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from ctrplan.errors import InputError
from ctrplan.planning import PlanStatus
from ctrplan.planning.batch import Job, make_jobs, read_targets, run_batch, summarize


def write_csv(path, header, rows):
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(header)
        w.writerows(rows)
    return str(path)


@pytest.fixture(scope="module")
def airway_targets():
    from ctrplan.planning.plan import scene_by_name

    scene = scene_by_name("airway")
    return [(t.name, tuple(float(v) for v in t.position)) for t in scene.targets[:3]]


def test_read_targets_csv_and_examples(tmp_path, airway_targets):
    (n1, p1), (n2, p2), _ = airway_targets
    f = write_csv(tmp_path / "t.csv", ["scene", "x", "y", "z", "name"],
                  [["airway", *p1, n1], ["skull_base", 1, 2, 3, "s"], ["airway", *p2, ""]])
    t = read_targets(f)
    assert [x[:2] for x in t] == [("airway", n1), ("skull_base", "s"), ("airway", "row4")]
    assert read_targets(f, ["airway"]) == [t[0], t[2]]
    g = write_csv(tmp_path / "g.csv", ["x", "y", "z"], [[*p1]])
    assert read_targets(g, ["airway", "skull_base"]) == [("airway", "row2", p1), ("skull_base", "row2", p1)]
    ex = read_targets("examples", ["airway"])
    assert len(ex) == 12 and all(s == "airway" for s, _, _ in ex)


@pytest.mark.parametrize("header,row,needle", [
    (["scene", "x", "y"], ["airway", 1, 2], "z"),
    (["scene", "x", "y", "z"], ["airway", 1, "nan", 2], "finite"),
    (["scene", "x", "y", "z"], ["airway", 1, "a", 2], "numbers"),
    (["scene", "x", "y", "z"], ["atlantis", 1, 2, 3], "atlantis"),
    (["x", "y", "z"], [1, 2, 3], "scene"),
])
def test_bad_target_files(tmp_path, header, row, needle):
    f = write_csv(tmp_path / "bad.csv", header, [row])
    with pytest.raises(InputError, match=needle):
        read_targets(f)


def test_job_ids_are_readable_and_change_with_the_settings(airway_targets):
    (name, p), *_ = airway_targets
    a = Job("airway", name, p, seed=0)
    assert a.id.startswith(f"airway__{name}__s0__")
    assert Job("airway", name, p, seed=0).id == a.id
    assert Job("airway", name, p, seed=0, time_limit=2.0).id != a.id


def test_summary_rates_and_percentiles():
    rows = summarize([
        {"scene": "a", "success": True, "status": "SUCCESS", "planning_time_s": 1.0},
        {"scene": "a", "success": False, "status": "TIMEOUT", "planning_time_s": 3.0},
        {"scene": "b", "success": True, "status": "SUCCESS", "planning_time_s": 2.0},
    ])
    by = {r["scene"]: r for r in rows}
    assert by["a"]["success_rate"] == 0.5 and by["a"]["time_median_s"] == 2.0
    assert by["all"]["jobs"] == 3 and by["all"]["statuses"] == "SUCCESS:2;TIMEOUT:1"
    # the labels: calibrated jobs and surrogate jobs counted per scene
    sur = {"p50": 0.7, "p95": 1.3, "p99": 1.7, "max": 2.5, "against": "physics:seed1"}
    rows = summarize([
        {"scene": "a", "success": True, "status": "SUCCESS", "calibrated": True},
        {"scene": "a", "success": False, "status": "OUTSIDE_TOLERANCE", "surrogate_error": sur},
        {"scene": "a", "success": True, "status": "SUCCESS", "calibrated": False},
    ])
    assert (rows[0]["calibrated_jobs"], rows[0]["surrogate_jobs"]) == (1, 1)
    assert rows[0]["statuses"] == "OUTSIDE_TOLERANCE:1;SUCCESS:2"


def test_batch_writes_one_json_per_job_and_resumes(tmp_path, airway_targets):
    targets = [("airway", n, p) for n, p in airway_targets[:2]]
    jobs = make_jobs(targets, seeds=[0], model="physics", time_limit=5.0)
    out = tmp_path / "res"
    first = run_batch(jobs, out)
    assert (first.total, first.skipped, first.ran) == (2, 0, 2)
    files = sorted((out / "jobs").glob("*.json"))
    assert [f.stem for f in files] == sorted(j.id for j in jobs)
    for f in files:
        d = json.loads(f.read_text())
        assert d["status"] == "SUCCESS" and d["scene"] == "airway" and d["model"] == "physics"
        assert len(d["path"]) >= 2
    with open(out / "summary.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert rows[0]["scene"] == "airway" and float(rows[0]["success_rate"]) == 1.0
    assert np.isfinite(float(rows[0]["time_p90_s"]))
    with open(out / "jobs.csv") as fh:
        jrows = list(csv.DictReader(fh))
    assert len(jrows) == 2
    # physics: not calibrated, no surrogate error (empty cell), no goal shift recorded
    assert all(r["calibrated"] == "False" and r["surrogate_error_mm"] == "" for r in jrows)
    assert all(float(r["goal_shift_mm"]) >= 0 and r["start_rotated"] in ("True", "False")
               for r in jrows)
    # resumable: nothing left to do; a lost result is recomputed alone
    again = run_batch(jobs, out)
    assert (again.skipped, again.ran) == (2, 0)
    files[0].unlink()
    third = run_batch(jobs, out)
    assert (third.skipped, third.ran) == (1, 1)
    # a truncated job file (not JSON) is not a result: that job runs again, overwriting it
    text = files[1].read_text()
    files[1].write_text(text[: len(text) // 2])
    fourth = run_batch(jobs, out)
    assert (fourth.skipped, fourth.ran) == (1, 1)
    assert json.loads(files[1].read_text())["status"] == "SUCCESS"


def test_bad_job_is_recorded_not_fatal(tmp_path):
    from ctrplan.planning.batch import run_job

    res = run_job(Job("airway", "far", (0.0, 0.0, float("nan")), model="learned"))
    # (the job's field, as the Python argument: job files name no command-line flag)
    assert res.status is PlanStatus.INPUT_ERROR and not res.success and res.message.startswith("target: ")
    assert res.plan is None and res.to_json()["status"] == "INPUT_ERROR"


# Pool and Ray tests use targets beyond the robot's reach: they answer at once, so the tests
# time the machinery (spawned workers, a local Ray instance), not planning.
FAR = (0.0, 0.0, 5000.0)


def test_process_pool(tmp_path):
    jobs = make_jobs([("airway", "far", FAR)], seeds=[0, 1], model="physics", time_limit=5.0)
    s = run_batch(jobs, tmp_path / "pool", workers=2)
    assert s.ran == 2 and s.rows[0]["statuses"] == "UNREACHABLE:2"
    assert len(list((tmp_path / "pool" / "jobs").glob("*.json"))) == 2


def test_ray_local_instance(tmp_path):
    pytest.importorskip("ray")
    jobs = make_jobs([("airway", "far", FAR)], seeds=[0], model="physics", time_limit=5.0)
    s = run_batch(jobs, tmp_path / "ray", workers=1, ray_address="local")
    assert s.ran == 1 and s.rows[0]["statuses"] == "UNREACHABLE:1"
    d = json.loads(next((tmp_path / "ray" / "jobs").glob("*.json")).read_text())
    assert d["status"] == "UNREACHABLE" and d["job_id"] == jobs[0].id


def test_cli_plan_batch(tmp_path, capsys, airway_targets):
    from ctrplan.cli import main

    (n, p), *_ = airway_targets
    f = write_csv(tmp_path / "t.csv", ["x", "y", "z", "name"], [[*p, n]])
    out = tmp_path / "cli"
    assert main(["-q", "plan-batch", "--targets", f, "--scene", "airway", "--out", str(out)]) == 0
    assert "1/1 succeeded" in capsys.readouterr().out
    assert (out / "summary.csv").exists()
    assert main(["-q", "plan-batch", "--targets", f, "--scene", "airway", "--out", str(out)]) == 0
    assert "1 were already done" in capsys.readouterr().out


@pytest.mark.parametrize("args,needle", [
    (["--targets", "missing.csv"], "missing.csv"),
    (["--targets", "examples", "--scene", "atlantis"], "atlantis"),
    (["--targets", "examples", "--planner", "magic"], "--planner"),
    (["--targets", "examples", "--seeds", "0"], "--seeds"),
])
def test_cli_plan_batch_bad_input_exits_2(tmp_path, capsys, args, needle):
    from ctrplan.cli import main

    assert main(["-q", "plan-batch", *args, "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert needle in err and "Traceback" not in err
