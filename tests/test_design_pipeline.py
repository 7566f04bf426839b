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
