"""Crash-safe plan-batch (issue 24, item 7): 40 jobs, the command killed with SIGKILL five
times at seeded random moments and resumed, ends with the same results (timings aside) as one
uninterrupted run: nothing lost, nothing twice, no worker left running.

Oracle: the uninterrupted run of the same command (plans are seeded and their budgets are
counts, so equal inputs give equal plans); files compared field by field.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from tests.test_interrupt import _env, cli, survivors, without_timings

JOBS = 40


def _targets_csv(path: Path) -> Path:
    from ctrplan.planning.batch import read_targets

    rows = read_targets("examples", ["airway"])[:10]          # x 4 seeds = 40 jobs
    with open(path, "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["scene", "name", "x", "y", "z"])
        for scene, name, (x, y, z) in rows:
            w.writerow([scene, name, repr(x), repr(y), repr(z)])
    return path


def _jobs(folder: Path) -> dict[str, dict]:
    """Complete job files (temporaries of a killed run, names starting with '.', ignored)."""
    out = {}
    for f in sorted((folder / "jobs").glob("[!.]*.json")):
        data = json.loads(f.read_text())       # never torn: a job file is renamed into place whole
        assert data["job_id"] == f.stem
        out[f.stem] = data
    return out


def _table(path: Path, drop: set[str]) -> list[dict]:
    with open(path, newline="") as fh:
        return [{k: v for k, v in row.items() if k not in drop} for row in csv.DictReader(fh)]


@pytest.mark.statistical
def test_plan_batch_killed_5_times_and_resumed_equals_one_run(tmp_path):
    targets = _targets_csv(tmp_path / "targets.csv")
    argv = ["plan-batch", "--targets", str(targets), "--seeds", "4", "--workers", "2"]
    ref = subprocess.run(cli(*argv, "--out", str(tmp_path / "ref")), cwd=tmp_path,
                         capture_output=True, text=True, env=_env(), timeout=900)
    assert ref.returncode == 0, ref.stderr
    want = _jobs(tmp_path / "ref")
    assert len(want) == JOBS

    out = tmp_path / "crash"
    rng = np.random.default_rng(2407)
    kills, progress = 0, []
    for _ in range(5):
        # a random moment while jobs are being finished: after 1-6 more job files, plus
        # 0-0.3 s (so some kills land while the driver writes a job file)
        goal = len(_jobs(out)) + int(rng.integers(1, 7)) if out.exists() else int(rng.integers(1, 7))
        pause = float(rng.uniform(0.0, 0.3))
        proc = subprocess.Popen(cli(*argv, "--out", str(out)), cwd=tmp_path, env=_env(),
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                                start_new_session=True)
        deadline = time.monotonic() + 600
        while proc.poll() is None and time.monotonic() < deadline:
            if out.exists() and len(list((out / "jobs").glob("[!.]*.json"))) >= goal:
                break
            time.sleep(0.05)
        time.sleep(pause)
        if proc.poll() is None:
            os.kill(proc.pid, signal.SIGKILL)        # the command only: its workers must follow
            kills += 1
        proc.wait()
        assert survivors(proc.pid) == [], "a worker outlived its parent"
        done = _jobs(out)
        assert set(done) <= set(want)
        progress.append(len(done))
    assert kills == 5, progress
    assert 0 < progress[-1] < JOBS, progress            # killed in the middle of the work
    assert not (out / "jobs.csv").exists()

    before = len(_jobs(out))
    t0 = time.monotonic()
    final = subprocess.run(cli(*argv, "--out", str(out)), cwd=tmp_path, capture_output=True,
                           text=True, env=_env(), timeout=900)
    assert final.returncode == 0, final.stderr
    assert f"{JOBS} job files ({before} were already done)" in final.stdout, final.stdout
    got = _jobs(out)
    # nothing lost, nothing twice: the same job files, equal but for timings
    assert sorted(got) == sorted(want)
    for k in want:
        assert without_timings(got[k]) == without_timings(want[k]), k
    assert [p.name for p in (out / "jobs").iterdir() if p.name.startswith(".")] == []
    timing_cols = {"planning_time_s"}
    rows = _table(out / "jobs.csv", timing_cols)
    assert len(rows) == JOBS and len({r["job_id"] for r in rows}) == JOBS
    assert rows == _table(tmp_path / "ref" / "jobs.csv", timing_cols)
    summary_cols = {"time_median_s", "time_p90_s", "time_max_s"}
    assert _table(out / "summary.csv", summary_cols) == _table(tmp_path / "ref" / "summary.csv", summary_cols)
    print(f"kills {kills}, job files after each run {progress}, final resume "
          f"{time.monotonic() - t0:.1f} s")
