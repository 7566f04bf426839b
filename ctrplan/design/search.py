"""The design search: CMA-ES populations (the ``cma`` package), screens in batches, real plans
only for promising designs, pipelined over the workers.

One covariance-matrix-adaptation evolution strategy per number of designed tubes searches the
unit cube of :mod:`ctrplan.design.space` (bounds [0, 1]); a generation asks every strategy for
its share of ``generation`` candidates (16 by default), screens them all at once (on the
worker pool or Ray: the candidates are independent), tells each strategy the fitness of its
candidates (:meth:`Search.fitness`: targets passing the screen, the goals' clearance, the
screen's tip errors; an entry that collides or an infeasible design ranks last, graded by how
far off it is) and chooses the most promising to plan in full (one job per design and target).
The plans decide which design is chosen and when the search stops; CMA-ES never sees them. A
strategy that stops (cma's termination criteria) restarts from the best design it found.

Scheduling (:mod:`ctrplan.design.runner`): because CMA-ES is told only the screens, the next
generation need not wait for plans. The plan jobs chosen at the end of generation g are
submitted at once and taken into account (cache, records, the choice of later designs, the
stop rule) at the end of generation g + :data:`PLAN_LAG`, never earlier or later, whatever
finished first; each generation waits for its own screens and for exactly the plans due then.
Meanwhile the plans run beside the next generations' screens (screens go first to a free
worker). When the search ends, the plans still in flight are taken in, in the order they were
submitted, before the final plans.

Determinism: ``cma`` draws from numpy's global generator; every call into it swaps in the
strategy's own generator state (seeded from the design seed) and restores the caller's, so
nothing else that runs in this process (planning seeds numpy too) changes the candidates. The
candidates of each generation depend only on the seed and on results taken in at fixed
generations; the generation size does not depend on ``workers``; every evaluation is a pure
function of its design and the seed (plans have count budgets). So the same seed gives the same
design, and the same record of every design evaluated, on any number of workers, on Ray, and
on any machine load, unless the ``time_limit`` cap stopped the search (``time_cap_hit``).

Resuming: after every generation the results taken in so far go to ``OUT/state.json``
(atomic); a rerun with the same scene, targets and settings replays the search and takes each
design it has already evaluated from there (at the same generations as before), so Ctrl-C
loses at most one generation's screens and the plans still in flight (they are recomputed).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

from ctrplan.design.evaluate import EvalSettings
from ctrplan.design.runner import PLAN, SCREEN, Runner, timed_job
from ctrplan.design.space import Decoded, Space, decode, simplicity
from ctrplan.design.strategy import Strategy

log = logging.getLogger("ctrplan")

STATE_FILE = "state.json"
#: The smallest population of one CMA-ES (a generation smaller than this many per tube count
#: is raised to it).
MIN_POPSIZE = 4
#: Generations between choosing designs to plan and taking their plans into account: the
#: plans chosen at the end of generation g are submitted at once and absorbed at the end of
#: generation g + PLAN_LAG, whatever finished first. 1 was the old synchronous schedule (each
#: generation waited for the previous one's longest plan, ~1-3 s, while most workers idled);
#: PLAN_LAG plans overlap PLAN_LAG - 1 further generations of screens, and the schedule
#: simulation on the jobs' measured seconds (benchmarks/bench_design.py scaling) puts 3 at
#: the knee: enough plan jobs in flight (3 generations x <= 6) for 8 workers, while the stop
#: rule learns of a plan only 2 generations later than before (a few extra screens).
PLAN_LAG = 3


def design_key(robot_dict: dict) -> str:
    """A stable key of a robot's tube values."""
    return hashlib.sha1(json.dumps(robot_dict["tubes"], sort_keys=True).encode()).hexdigest()[:16]


class Search:
    """State of one design search (see :func:`ctrplan.design.design`)."""

    def __init__(self, space: Space, scene_spec, targets: np.ndarray, settings: EvalSettings,
                 seed: int, budget: int, plan_budget: int, generation: int, patience: int,
                 time_limit: float, state_path: Path | None, clearance_goal_mm: float, state_key: str,
                 progress: Callable[[int], None] | None = None, plans_per_generation: int = 2,
                 starts: dict | None = None):
        self.space = space
        self.scene_spec = scene_spec
        self.targets = np.asarray(targets, dtype=float)
        self.settings = settings
        self.seed = int(seed)
        self.budget = int(budget)
        self.plan_budget = int(plan_budget)
        self.generation = int(generation)
        self.plans_per_generation = int(plans_per_generation)
        self.starts = starts or {}
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
        self.generations = 0
        self.timings = {"screen_entry": 0.0, "screen_sample": 0.0, "screen_ik": 0.0, "plans": 0.0,
                        "stability": 0.0}
        self.resumed = 0
        #: the runner's log of the last :meth:`run` (:meth:`Runner.schedule`)
        self.schedule: dict = {}
        #: what runs a job (:func:`~ctrplan.design.runner.timed_job`; tests put a stand-in here)
        self.job_fn = timed_job
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
    def _job(self, dec: Decoded, stage: str, todo: list[int] | None = None) -> dict:
        return self.job(dec.robot, stage, todo)

    def job(self, robot, stage: str, todo: list[int] | None = None) -> dict:
        """An evaluation job (:func:`ctrplan.design.evaluate.evaluate_job`) for ``robot``."""
        return {"robot": robot.to_dict(), "scene": self.scene_spec, "targets": self.targets.tolist(),
                "settings": self.settings.__dict__, "seed": self.seed, "stage": stage,
                "todo": todo or []}

    def _strategies(self) -> list[Strategy]:
        """One CMA-ES per number of designed tubes, sharing ``generation`` candidates (at
        least MIN_POPSIZE each)."""
        ks = list(range(max(1, self.space.k_min), self.space.k_max + 1))
        share = [self.generation // len(ks) + (1 if i < self.generation % len(ks) else 0)
                 for i in range(len(ks))]
        # a start fitted to the anatomy is searched closer around (step 0.15 of each range)
        return [Strategy(k, self.space.dim, max(MIN_POPSIZE, m), self.seed * 7 + k,
                         self.starts.get(k, np.full(self.space.dim, 0.5)), 0.15 if k in self.starts else 0.3)
                for k, m in zip(ks, share)]

    # ------------------------------------------------------------------ ranking
    def search_key(self, ev: dict) -> tuple:
        """Ranking of evaluated designs (larger is better): targets reached (planned) or
        passing the screen, clearance bin, closeness of the screen, simplicity."""
        if ev.get("robot") is None or not ev.get("entry_ok", False):
            return (-1, 0.0, -math.inf, 0.0)
        count = ev["reached"] if ev.get("planned") else ev["screen_passed"]
        clear = ev.get("clearance_bin", 0.0) if ev.get("planned") else ev.get("goal_clearance_bin", 0.0)
        return (count, clear, -ev["screen_error"], -ev["simplicity"][1])

    def fitness(self, ev: dict) -> float:
        """What each strategy minimises: an infeasible design ranks last, then a retracted
        start that collides (graded by how deep), then the screen's total tip error beyond the
        tolerance over the targets (each at most 50 mm: a design close to every target beats
        one that reaches some and misses another by far), less a little for the goals'
        clearance (up to 1 mm)."""
        if ev.get("robot") is None:
            return 1e6
        if not ev.get("entry_ok", False):
            return 1e5 + 100.0 * max(0.0, -float(ev.get("entry_clearance_mm") or 0.0))
        tol = self.settings.screen_tolerance_mm
        errs = [100.0 if e is None else e for e in ev.get("screen_errors") or []]
        excess = sum(min(max(e - tol, 0.0), 50.0) for e in errs)
        return excess - 0.1 * min(ev.get("goal_clearance_bin", 0.0), 1.0)

    @staticmethod
    def score(ev: dict) -> tuple:
        """The objective of planned designs, larger is better: targets reached, clearance bin
        (0.25 mm), then simplicity (fewer tubes, less bending, shorter)."""
        n, bend, length = ev["simplicity"]
        return (ev["reached"], ev["clearance_bin"], -n, -round(bend, 3), -round(length, 1))

    # ------------------------------------------------------------------ evaluation
    def _screen_jobs(self, cands: list[tuple[int, np.ndarray]]) -> tuple[list[dict], list, list[dict]]:
        """Evaluation records of the candidates and the screen jobs still to run (a design
        screened before, in this run or a resumed one, is taken from the cache)."""
        evs, todo, pending = [], [], set()
        for k, u in cands:
            dec = decode(self.space, k, u, name=f"design-{len(self.evaluations) + len(evs):04d}")
            ev = {"index": len(self.evaluations) + len(evs), "k": k, "u": [float(x) for x in u],
                  "generation": self.generations,
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
                elif ev["key"] not in pending:      # the same design twice: screened once
                    pending.add(ev["key"])
                    todo.append((ev, dec))
            evs.append(ev)
        return evs, [ev for ev, _ in todo], [self._job(dec, "screen") for _, dec in todo]

    def _absorb_screens(self, evs: list[dict], todo: list[dict], results: list[dict]) -> None:
        for ev, res in zip(todo, results):
            self.cache.setdefault(ev["key"], {})["screen"] = res
            for k, v in res["timings"].items():
                self.timings[k] = self.timings.get(k, 0.0) + v
        for ev in evs:
            if ev["robot"] is not None:
                self._apply_screen(ev, self.cache[ev["key"]]["screen"])

    @staticmethod
    def _apply_screen(ev: dict, s: dict) -> None:
        ev["entry_ok"] = bool(s["entry_ok"])
        ev["entry_clearance_mm"] = s.get("entry_clearance_mm")
        if not ev["entry_ok"]:
            ev["binding"].append("entry")
        errs = np.array([math.inf if e is None else e for e in s["errors"]], dtype=float)
        ev["screen_passed"] = int(np.sum(s["passed"]))
        ev["screen_errors"] = [None if not math.isfinite(e) else float(e) for e in errs]
        ev["screen_error"] = float(np.sum(np.minimum(errs, 100.0)))
        gc = [c for c, p in zip(s.get("goal_clearance_mm", []), s["passed"]) if p and c is not None]
        # optimistic: the goals' clearance bounds the plans' (planned designs use their own)
        ev["goal_clearance_bin"] = float(math.floor(min(gc) / 0.25) * 0.25) if gc else 0.0

    def _choose(self, evs: list[dict]) -> list[dict]:
        """The designs of a generation to plan in full (at most ``plans_per_generation``, within
        the plan budget): the best by the search's ranking that pass the screen for at least
        as many targets as the best plan so far reached, not planned before."""
        best_reached = max((e["reached"] for e in self.evaluations if e["planned"]), default=0)
        seen = {e["key"] for e in self.evaluations if e.get("chosen")}
        order = sorted((e for e in evs if e["entry_ok"] and e["screen_passed"] > 0
                        and e["screen_passed"] >= best_reached),
                       key=lambda e: (self.search_key(e), -e["index"]), reverse=True)
        chosen = []
        for e in order:
            if self.planned >= self.plan_budget or len(chosen) >= self.plans_per_generation:
                break
            if e["key"] in seen:
                continue
            seen.add(e["key"])
            e["chosen"] = True
            chosen.append(e)
            self.planned += 1
        return chosen

    def _plan_jobs(self, chosen: list[dict]) -> tuple[list[dict], list[dict]]:
        """One job per (design, target that passed its screen): the pool plans them side by side."""
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
        return jobs, owners

    def _absorb_plans(self, chosen: list[dict], jobs: list[dict], owners: list[dict],
                      results: list[dict]) -> None:
        merged: dict[str, dict] = {}
        for e, job, res in zip(owners, jobs, results):
            m = merged.get(e["key"])
            if m is None:
                merged[e["key"]] = res
                continue
            for j in job["todo"]:
                for k in ("status", "reached", "clearance_mm", "clearance_estimate_mm", "tip_error_mm",
                          "stable"):
                    m[k][j] = res[k][j]
            m["stability_states"] += res["stability_states"]
            for k, v in res["timings"].items():
                m["timings"][k] = m["timings"].get(k, 0.0) + v
        for key, res in merged.items():
            self.cache[key]["plans"] = res
            for k, v in res["timings"].items():
                self.timings[k] = self.timings.get(k, 0.0) + v
        for e in chosen:
            self._apply_plans(e, self.cache[e["key"]]["plans"])
            e["planned_at"] = self.generations - 1      # the generation whose end took them in

    @staticmethod
    def _apply_plans(e: dict, p: dict) -> None:
        e["planned"] = True
        e["plan"] = {k: p[k] for k in ("status", "reached", "clearance_mm", "tip_error_mm", "stable")}
        e["reached"] = int(np.sum(p["reached"]))
        cl = [c for c, r in zip(p["clearance_mm"], p["reached"]) if r and c is not None]
        est = [c for c, r in zip(p.get("clearance_estimate_mm", p["clearance_mm"]), p["reached"])
               if r and c is not None]
        e["clearance_mm"] = float(min(cl)) if cl else None
        e["clearance_estimate_mm"] = float(min(est)) if est else None
        e["clearance_bin"] = float(math.floor(max(min(est), 0.0) / 0.25) * 0.25) if est else 0.0
        if any(s is False for s in p["stable"]):
            e["binding"].append("stability")

    # ------------------------------------------------------------------ main loop
    def _screen(self, runner: Runner, cands: list) -> list[dict]:
        """Screen the candidates (waits for their screens); returns their records."""
        evs, todo, sjobs = self._screen_jobs(cands)
        tickets = [runner.submit(j, SCREEN) for j in sjobs]
        self._absorb_screens(evs, todo, [runner.result(t) for t in tickets])
        return evs

    def _submit_plans(self, runner: Runner, chosen: list[dict], due: int) -> dict:
        """Submit the plan jobs of the chosen designs now; absorbed at generation ``due``."""
        jobs, owners = self._plan_jobs(chosen)
        return {"due": due, "chosen": chosen, "jobs": jobs, "owners": owners,
                "tickets": [runner.submit(j, PLAN) for j in jobs]}

    def _absorb_batch(self, runner: Runner, batch: dict) -> None:
        """Wait for one batch of plans (in submission order) and take it into account."""
        results = [runner.result(t) for t in batch["tickets"]]
        self._absorb_plans(batch["chosen"], batch["jobs"], batch["owners"], results)

    def _tell(self, asked: list, evs: list[dict]) -> None:
        i = 0
        for st, cs in asked:
            mine = evs[i:i + len(cs)]
            i += len(cs)
            if st is not None:
                st.tell([np.array(e["u"]) for e in mine], [self.fitness(e) for e in mine],
                        self._best_u(st.k))

    def _progress_key(self) -> tuple | None:
        """More targets reached, or more clearance up to the goal (simpler designs of the same
        reach and clearance do not count as progress)."""
        return max(((e["reached"], min(e["clearance_bin"], self.clearance_goal))
                    for e in self.evaluations if e["planned"]), default=None)

    def run(self, workers: int = 1, ray_address: str | None = None,
            finish: Callable[[Runner], None] | None = None, lag: int | None = None,
            runner: Runner | None = None) -> None:
        """Search until the budget (a count) is used, the time cap hits, or every target is
        reached and ``patience`` generations brought no progress. Each generation screens its
        candidates (and waits for them), absorbs the plans due at its end, tells CMA-ES the
        screen fitness (:meth:`fitness`) and submits the plans of the designs it chooses; those
        are absorbed ``lag`` generations later (None: :data:`PLAN_LAG`), so plans run beside later
        screens. At the end every plan in flight is absorbed in submission order.
        ``finish(runner)`` runs on the same workers before they stop (the final plans).
        ``runner``: an entered :class:`Runner` to use (else one for ``workers`` /
        ``ray_address`` is started here and stopped at the end)."""
        lag = PLAN_LAG if lag is None else int(lag)
        t0 = time.perf_counter()
        stale, best_score, T = 0, None, len(self.targets)
        strategies = self._strategies() if self.space.k_max else []
        inflight: list[dict] = []
        own = runner is None
        with (Runner(workers, ray_address, self.job_fn) if own else contextlib.nullcontext(runner)) as runner:
            runner.start_log()
            while len(self.evaluations) < self.budget:
                if time.perf_counter() - t0 > self.time_limit:
                    self.time_cap_hit = True
                    break
                if not self.space.k_max:          # nothing to design: the --from robot as it is
                    asked = [(None, [(0, np.zeros(0))])]
                else:
                    asked = [(st, [(st.k, x) for x in st.ask()]) for st in strategies]
                evs = self._screen(runner, [c for _, cs in asked for c in cs])
                self.evaluations.extend(evs)
                self.generations += 1
                while inflight and inflight[0]["due"] <= self.generations:
                    self._absorb_batch(runner, inflight.pop(0))
                self._tell(asked, evs)
                inflight.append(self._submit_plans(runner, self._choose(evs), self.generations + lag))
                self._save_state()
                if self.progress is not None:
                    self.progress(len(evs))
                cur = self._progress_key()
                if cur is not None and (best_score is None or cur > best_score):
                    best_score, stale = cur, 0
                else:
                    stale += 1
                if not self.space.k_max or (best_score is not None and best_score[0] == T
                                            and stale >= self.patience):
                    break
            for batch in inflight:                # the plans still in flight, in order
                self._absorb_batch(runner, batch)
            self._save_state()
            if finish is not None:
                finish(runner)
            self.schedule = runner.schedule()
            self.schedule["wall_s"] = time.perf_counter() - t0

    def _best_u(self, k: int) -> np.ndarray | None:
        mine = [e for e in self.evaluations if e["k"] == k]
        if not mine:
            return None
        return np.array(min(mine, key=lambda e: (self.fitness(e), e["index"]))["u"])

    def best(self) -> dict | None:
        planned = [e for e in self.evaluations if e["planned"]]
        if not planned:
            return None
        return max(planned, key=lambda e: (self.score(e), -e["index"]))

    def closest(self) -> dict | None:
        """The design that came closest when none was planned with success: the best by the
        search's ranking (entry, then targets passing the screen, then the screen's errors)."""
        live = [e for e in self.evaluations if e["robot"] is not None]
        if not live:
            return None
        return min(live, key=lambda e: (self.fitness(e), e["index"]))
