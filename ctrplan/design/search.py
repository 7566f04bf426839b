"""The design search: seeded random designs, then a (1 + lambda) evolution strategy around the
best, screens in batches, real plans only for promising designs.

Determinism: the candidates of each generation are drawn from one seeded generator and depend
only on the results of earlier generations; generation size does not depend on ``workers``;
every evaluation is a pure function of its design and the seed (plans have count budgets).
So the same seed gives the same design on any number of workers and any machine load, unless
the ``time_limit`` cap stopped the search (``time_cap_hit``).

Resuming: after every generation the results so far go to ``OUT/state.json`` (atomic); a rerun
with the same scene, targets and settings replays the search and takes each design it has
already evaluated from there, so Ctrl-C loses at most one generation.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ctrplan.design.evaluate import EvalSettings, evaluate_job
from ctrplan.design.space import Decoded, Space, decode, simplicity

log = logging.getLogger("ctrplan")

STATE_FILE = "state.json"


def design_key(robot_dict: dict) -> str:
    """A stable key of a robot's tube values."""
    return hashlib.sha1(json.dumps(robot_dict["tubes"], sort_keys=True).encode()).hexdigest()[:16]


class Runner:
    """Runs evaluation jobs in this process, on a spawned process pool (``workers > 1``) or on
    Ray (``ray_address``: the same path as ``plan-batch --ray``,
    :mod:`ctrplan.planning.ray_pool`); results always come back in the order of the jobs."""

    def __init__(self, workers: int, ray_address: str | None = None):
        self.workers = int(workers)
        self.ray_address = ray_address
        self._ex = None
        self._ray = None

    def __enter__(self) -> Runner:
        if self.ray_address:
            from ctrplan.planning.ray_pool import ray_session

            # a local instance gets every core Ray detects (--workers and --ray exclude each other)
            self._ray = ray_session(self.ray_address)
            self._ray.__enter__()
        elif self.workers > 1:
            import multiprocessing as mp
            from concurrent.futures import ProcessPoolExecutor

            # spawn, not fork: numba, torch and OMPL threads do not survive a fork reliably
            self._ex = ProcessPoolExecutor(max_workers=self.workers, mp_context=mp.get_context("spawn"),
                                           initializer=_worker_init)
        return self

    def __exit__(self, *exc) -> None:
        if self._ray is not None:
            ray, self._ray = self._ray, None
            ray.__exit__(*exc)      # shuts down a local instance: its workers end with it
        if self._ex is not None:
            if exc[0] is not None:
                # Ctrl-C or an error: stop every worker now, not after its current design
                # (the executor keeps its processes in a private dict; nothing public does this)
                for proc in list(getattr(self._ex, "_processes", {}).values()):
                    proc.terminate()
            self._ex.shutdown(wait=exc[0] is None, cancel_futures=True)
            self._ex = None

    def map(self, jobs: list[dict]) -> list[dict]:
        if not jobs:
            return []
        if self._ray is not None:
            from ctrplan.planning.ray_pool import ray_map

            return ray_map(evaluate_job, jobs)
        if self._ex is None:
            return [evaluate_job(j) for j in jobs]
        from ctrplan import interrupt

        with interrupt.spawning():   # workers start on demand, SIGINT ignored (Ctrl-C: parent stops them)
            results = self._ex.map(evaluate_job, jobs)
        return list(results)


def _worker_init() -> None:
    import os

    from ctrplan import interrupt

    interrupt.ignore_in_child()   # Ctrl-C reaches the whole process group: the parent stops us
    # one intra-op thread per worker (before torch is imported): the pool is the parallelism
    os.environ.setdefault("OMP_NUM_THREADS", "1")


class Search:
    """State of one design search (see :func:`ctrplan.design.design`)."""

    def __init__(self, space: Space, scene_spec, targets: np.ndarray, settings: EvalSettings,
                 seed: int, budget: int, plan_budget: int, generation: int, patience: int,
                 time_limit: float, state_path: Path | None, clearance_goal_mm: float, state_key: str,
                 progress: Callable[[int], None] | None = None):
        self.space = space
        self.scene_spec = scene_spec
        self.targets = np.asarray(targets, dtype=float)
        self.settings = settings
        self.seed = int(seed)
        self.budget = int(budget)
        self.plan_budget = int(plan_budget)
        self.generation = int(generation)
        self.patience = int(patience)
        self.time_limit = float(time_limit)
        self.state_path = state_path
        self.state_key = state_key
        self.clearance_goal = float(clearance_goal_mm)
        self.progress = progress
        self.cache: dict[str, dict] = {}
        self.evaluations: list[dict] = []
        self.planned = 0
        self.time_cap_hit = False
        self.timings = {"screen_entry": 0.0, "screen_sample": 0.0, "screen_ik": 0.0, "plans": 0.0,
                        "stability": 0.0}
        self.resumed = 0
        self._load_state()

    # ------------------------------------------------------------------ state file
    def _load_state(self) -> None:
        if self.state_path is None or not self.state_path.is_file():
            return
        try:
            data = json.loads(self.state_path.read_text(encoding="utf-8"))
        except (OSError, ValueError):
            return
        if isinstance(data, dict) and data.get("key") == self.state_key and isinstance(data.get("cache"), dict):
            self.cache = data["cache"]
            log.info("resuming: %d designs already evaluated in %s", len(self.cache), self.state_path)

    def _save_state(self) -> None:
        if self.state_path is None:
            return
        from ctrplan.io import write_json_atomic

        write_json_atomic(self.state_path, {"key": self.state_key, "cache": self.cache})

    # ------------------------------------------------------------------ candidates
    def _random(self, rng: np.random.Generator) -> tuple[int, np.ndarray]:
        k = int(rng.integers(self.space.k_min, self.space.k_max + 1))
        return k, rng.uniform(0.0, 1.0, size=self.space.dim)

    def _job(self, dec: Decoded, stage: str, todo: list[int] | None = None) -> dict:
        return {"robot": dec.robot.to_dict(), "scene": self.scene_spec, "targets": self.targets.tolist(),
                "settings": self.settings.__dict__, "seed": self.seed, "stage": stage,
                "todo": todo or []}

    # ------------------------------------------------------------------ ranking
    def search_key(self, ev: dict) -> tuple:
        """Parent selection: targets reached (planned) or passing the screen, clearance bin,
        closeness of the screen, simplicity."""
        if ev.get("robot") is None or not ev.get("entry_ok", False):
            return (-1, 0.0, -math.inf, 0.0)
        count = ev["reached"] if ev.get("planned") else ev["screen_passed"]
        clear = ev.get("clearance_bin", 0.0) if ev.get("planned") else ev.get("goal_clearance_bin", 0.0)
        return (count, clear, -ev["screen_error"], -ev["simplicity"][1])

    @staticmethod
    def score(ev: dict) -> tuple:
        """The objective of planned designs, larger is better: targets reached, clearance bin
        (0.25 mm), then simplicity (fewer tubes, less bending, shorter)."""
        n, bend, length = ev["simplicity"]
        return (ev["reached"], ev["clearance_bin"], -n, -round(bend, 3), -round(length, 1))

    # ------------------------------------------------------------------ evaluation
    def _evaluate(self, runner: Runner, cands: list[tuple[int, np.ndarray]]) -> list[dict]:
        evs = []
        todo_screen = []
        for k, u in cands:
            dec = decode(self.space, k, u, name=f"design-{len(self.evaluations) + len(evs):04d}")
            ev = {"index": len(self.evaluations) + len(evs), "k": k, "u": [float(x) for x in u],
                  "binding": list(dec.binding), "parameters": dec.parameters, "robot": None,
                  "entry_ok": False, "screen_passed": 0, "screen_error": math.inf, "planned": False,
                  "reached": 0, "clearance_bin": 0.0, "clearance_mm": None,
                  "simplicity": [0, 0.0, 0.0]}
            if dec.robot is not None:
                rd = dec.robot.to_dict()
                ev["robot"] = rd
                ev["key"] = design_key(rd)
                ev["simplicity"] = list(simplicity(dec.robot))
                if ev["key"] in self.cache and "screen" in self.cache[ev["key"]]:
                    self.resumed += 1
                else:
                    todo_screen.append((ev, dec))
            evs.append(ev)
        results = runner.map([self._job(dec, "screen") for _, dec in todo_screen])
        for (ev, _), res in zip(todo_screen, results):
            self.cache.setdefault(ev["key"], {})["screen"] = res
            for k, v in res["timings"].items():
                self.timings[k] = self.timings.get(k, 0.0) + v
        for ev in evs:
            if ev["robot"] is None:
                continue
            s = self.cache[ev["key"]]["screen"]
            ev["entry_ok"] = bool(s["entry_ok"])
            if not ev["entry_ok"]:
                ev["binding"].append("entry")
            errs = np.array([math.inf if e is None else e for e in s["errors"]], dtype=float)
            ev["screen_passed"] = int(np.sum(s["passed"]))
            ev["screen_errors"] = [None if not math.isfinite(e) else float(e) for e in errs]
            ev["screen_error"] = float(np.sum(np.minimum(errs, 100.0)))
            gc = [c for c, p in zip(s.get("goal_clearance_mm", []), s["passed"]) if p and c is not None]
            # optimistic: the goals' clearance bounds the plans' (planned designs use their own)
            ev["goal_clearance_bin"] = float(math.floor(min(gc) / 0.25) * 0.25) if gc else 0.0
        return evs

    def _plan_promising(self, runner: Runner, evs: list[dict]) -> None:
        best_reached = max((e["reached"] for e in self.evaluations if e["planned"]), default=0)
        order = sorted((e for e in evs if e["entry_ok"] and e["screen_passed"] > 0
                        and e["screen_passed"] >= best_reached),
                       key=lambda e: (self.search_key(e), -e["index"]), reverse=True)
        chosen = []
        for e in order:
            if self.planned + len(chosen) >= self.plan_budget:
                break
            if len(chosen) >= 2:     # at most two planned designs per generation
                break
            chosen.append(e)
        # one job per (design, target): the pool plans the targets of a design side by side
        jobs, owners = [], []
        for e in chosen:
            c = self.cache[e["key"]]
            if "plans" in c:
                self.resumed += 1
                continue
            todo = [j for j, p in enumerate(c["screen"]["passed"]) if p]
            dec = decode(self.space, e["k"], np.array(e["u"]))
            for j in todo or [None]:
                jobs.append(self._job(dec, "plan", [] if j is None else [j]))
                owners.append(e)
        merged: dict[str, dict] = {}
        for e, job, res in zip(owners, jobs, runner.map(jobs)):
            m = merged.get(e["key"])
            if m is None:
                merged[e["key"]] = res
                continue
            for j in job["todo"]:
                for k in ("status", "reached", "clearance_mm", "tip_error_mm", "stable"):
                    m[k][j] = res[k][j]
            m["stability_states"] += res["stability_states"]
            for k, v in res["timings"].items():
                m["timings"][k] = m["timings"].get(k, 0.0) + v
        for key, res in merged.items():
            self.cache[key]["plans"] = res
            for k, v in res["timings"].items():
                self.timings[k] = self.timings.get(k, 0.0) + v
        for e in chosen:
            p = self.cache[e["key"]]["plans"]
            e["planned"] = True
            e["plan"] = {k: p[k] for k in ("status", "reached", "clearance_mm", "tip_error_mm", "stable")}
            e["reached"] = int(np.sum(p["reached"]))
            cl = [c for c, r in zip(p["clearance_mm"], p["reached"]) if r and c is not None]
            e["clearance_mm"] = float(min(cl)) if cl else None
            e["clearance_bin"] = float(math.floor(min(cl) / 0.25) * 0.25) if cl else 0.0
            if any(s is False for s in p["stable"]):
                e["binding"].append("stability")
        self.planned += len(chosen)

    # ------------------------------------------------------------------ main loop
    def run(self, workers: int = 1, ray_address: str | None = None) -> None:
        rng = np.random.default_rng(self.seed)
        t0 = time.perf_counter()
        n_init = min(self.budget, max(self.generation, self.budget // 3))
        sigma = 0.15
        stale = 0
        best_score = None
        best_key = None
        T = len(self.targets)
        with Runner(workers, ray_address) as runner:
            while len(self.evaluations) < self.budget:
                if time.perf_counter() - t0 > self.time_limit:
                    self.time_cap_hit = True
                    break
                m = min(self.generation, self.budget - len(self.evaluations))
                if not self.space.k_max:
                    m = 1                       # nothing to design: the --from robot as it is
                if len(self.evaluations) < n_init or not self.space.k_max:
                    cands = [self._random(rng) for _ in range(m)]
                else:
                    ranked = sorted(self.evaluations, key=lambda e: (self.search_key(e), -e["index"]),
                                    reverse=True)
                    parents = [e for e in ranked if e["robot"] is not None][:3] or ranked[:1]
                    cands = []
                    for i in range(m):
                        p = parents[0] if i % 2 == 0 or len(parents) == 1 else parents[1 + (i // 2) % (len(parents) - 1)]
                        if rng.uniform() < 0.1:
                            cands.append(self._random(rng))
                            continue
                        u = np.clip(np.array(p["u"]) + sigma * rng.standard_normal(self.space.dim), 0.0, 1.0)
                        cands.append((p["k"], u))
                evs = self._evaluate(runner, cands)
                self._plan_promising(runner, evs)
                self.evaluations.extend(evs)
                self._save_state()
                if self.progress is not None:
                    self.progress(len(evs))
                planned = [e for e in self.evaluations if e["planned"]]
                cur = max((self.score(e) for e in planned), default=None)
                if cur is not None and (best_score is None or cur > best_score):
                    best_score = cur
                    stale = 0
                else:
                    stale += 1
                # step size (1/5 success rule): grow when more than a fifth of the children
                # beat the best design before this generation, shrink otherwise
                if len(self.evaluations) > n_init and best_key is not None:
                    wins = sum(self.search_key(e) > best_key for e in evs)
                    sigma = min(0.3, sigma * 1.5) if wins > 0.2 * len(evs) else max(0.005, sigma * 0.7)
                best_key = max(self.search_key(e) for e in self.evaluations)
                if not self.space.k_max:
                    break
                if (best_score is not None and best_score[0] == T and best_score[1] >= self.clearance_goal
                        and stale >= self.patience):
                    break

    def best(self) -> dict | None:
        planned = [e for e in self.evaluations if e["planned"]]
        if not planned:
            return None
        return max(planned, key=lambda e: (self.score(e), -e["index"]))

