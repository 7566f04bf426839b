"""The design search's pipelined schedule: plans absorbed at fixed generations, whatever ran first.

Oracles:

- a stand-in evaluation (:func:`stand_in`, no planning: results are hashes of the design, plan
  jobs sleep so that jobs submitted earlier finish later) run in this process and on a pool of
  3 workers: the jobs finish in different orders (checked from the stand-in's own log), yet
  every record of the search (chosen designs, plans, when each plan was taken in) is the same;
- the lag rule restated here: a design chosen at the end of generation g is taken into account
  at the end of generation g + PLAN_LAG (or at the last generation, when the search ends before).

The real search on 1 and 2 workers: tests/test_design.py.
"""

from __future__ import annotations

import hashlib
import json
import os
import time

import numpy as np
import pytest

from ctrplan.design import Bounds
from ctrplan.design.evaluate import EvalSettings
from ctrplan.design.search import PLAN_LAG, Search
from ctrplan.design.space import load_stock, make_space

pytestmark = pytest.mark.xdist_group("design")

T = 3


def _h(job: dict, salt: str) -> int:
    text = json.dumps(job["robot"]["tubes"], sort_keys=True) + salt
    return int(hashlib.sha1(text.encode()).hexdigest()[:12], 16)


def stand_in(job: dict, planners=None) -> tuple[dict, dict]:
    """A deterministic evaluation of a design (no physics): screens pass a target when a hash of
    the design says so; a plan reaches a passing target two times in three. A plan job sleeps
    longer the earlier its target and design hash, so on a pool later jobs overtake earlier
    ones. Each finished job appends a line to the log file named by ``job["scene"]``."""
    t0 = time.perf_counter()
    if job["stage"] == "screen":
        errs = [(_h(job, f"e{j}") % 1000) / 100.0 for j in range(T)]       # 0 .. 10 mm
        res = {"entry_ok": _h(job, "entry") % 5 != 0, "entry_clearance_mm": 0.1, "errors": errs,
               "passed": [e <= 4.0 for e in errs], "goal_clearance_mm": [0.3] * T,
               "timings": {"screen_ik": 0.0}}
    else:
        (j,) = job["todo"]
        time.sleep(0.02 * (T - j) + 0.03 * (_h(job, "sleep") % 3))
        reached = _h(job, f"r{j}") % 3 != 0
        res = {k: [None] * T for k in ("clearance_mm", "clearance_estimate_mm", "tip_error_mm", "stable")}
        res.update(status=["NOT_TRIED"] * T, reached=[False] * T, stability_states=1,
                   timings={"plans": 0.0})
        res["status"][j] = "SUCCESS" if reached else "FAILED"
        res["reached"][j] = reached
        res["stable"][j] = True if reached else None
        res["clearance_mm"][j] = res["clearance_estimate_mm"][j] = 0.25 * (_h(job, f"c{j}") % 4) if reached else None
    with open(job["scene"], "a", encoding="utf-8") as f:     # one short append: one line
        f.write(f"{job['stage']} {_h(job, '')} {job['todo']} {os.getpid()}\n")
    return res, {"load_s": 0.0, "job_s": time.perf_counter() - t0}


def _search(log_path, lag_budget: int = 128) -> Search:
    space = make_space(Bounds(), load_stock(None), (), 2)
    s = Search(space, str(log_path), np.zeros((T, 3)), EvalSettings(), seed=11, budget=lag_budget,
               plan_budget=12, generation=16, patience=2, time_limit=1e9, state_path=None,
               clearance_goal_mm=0.5, state_key="stand-in")
    s.job_fn = stand_in
    return s


def _records(s: Search) -> list:
    return json.loads(json.dumps(s.evaluations, sort_keys=True, default=str))


def test_plans_are_taken_in_at_fixed_generations_whatever_finishes_first(tmp_path):
    one, pool = _search(tmp_path / "one.log"), _search(tmp_path / "pool.log")
    one.run(workers=1)
    pool.run(workers=3)
    plan_lines = {n: [ln.split()[1:3] for ln in (tmp_path / f"{n}.log").read_text().splitlines()
                      if ln.startswith("plan")] for n in ("one", "pool")}
    # the same plan jobs ran, finishing in another order on the pool
    assert sorted(plan_lines["one"]) == sorted(plan_lines["pool"]) and plan_lines["one"]
    assert plan_lines["one"] != plan_lines["pool"]
    assert _records(one) == _records(pool)
    chosen = [e for e in one.evaluations if e.get("chosen")]
    assert len(chosen) >= 4 and all(e["planned"] for e in chosen)
    assert {e["generation"] for e in chosen} != {0}
    last = one.generations - 1
    for e in chosen:      # chosen at the end of generation g, taken in at the end of g + PLAN_LAG
        assert e["planned_at"] == min(e["generation"] + PLAN_LAG, last), e["index"]
    assert not any(e["planned"] for e in one.evaluations if not e.get("chosen"))


def _log(jobs, waits, caller=()):
    """A schedule log: submit ``jobs`` [(priority, seconds)] in order, then wait for ``waits``."""
    ev = [{"event": "submit", "ticket": t, "stage": "x", "priority": p} for t, (p, _) in enumerate(jobs)]
    ev += [{"event": "caller", "s": s} for s in caller]
    ev += [{"event": "wait", "ticket": t} for t in waits]
    return {"events": ev, "seconds": {t: {"cpu_s": d, "load_cpu_s": 0.0} for t, (_, d) in enumerate(jobs)}}


def test_schedule_simulation_by_hand():
    """benchmarks/design_schedule.py against makespans worked out by hand."""
    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
    from design_schedule import simulate

    ten = _log([(1, 1.0)] * 10, range(10))
    assert [simulate(ten, w) for w in (1, 3, 10)] == [10.0, 4.0, 1.0]      # ceil(10 / w) s
    assert simulate(ten, 3, startup_s=0.5) == 4.5
    # a worker that frees up takes the best priority queued: the 3 s plan first (it was alone
    # when submitted), then the short screens before the second plan
    mixed = _log([(1, 3.0), (0, 1.0), (0, 1.0), (1, 2.0)], [1, 2, 3])
    assert simulate(mixed, 1) == 7.0 and simulate(mixed, 2) == 4.0
    # the caller's own time runs beside the workers
    assert simulate(_log([(0, 2.0)], [0], caller=[1.5]), 1) == 2.0
    assert simulate(_log([(0, 2.0)], [0], caller=[3.0]), 1) == 3.0
