"""Batch planning over many scenes and targets: jobs, resumable runs, pools, Ray, summaries.

A job is one plan (:meth:`Planner.plan <ctrplan.planning.planner.Planner.plan>`). Its id is readable
(``<scene>__<target>__s<seed>``) plus a short hash of everything that defines it, so a rerun
with the same settings skips jobs whose JSON already exists and a changed setting makes new
jobs. Results go to ``<out>/jobs/<id>.json`` (written atomically by the driver as each job
finishes), ``<out>/jobs.csv`` (one row per job) and ``<out>/summary.csv`` (success rate and
planning-time percentiles per scene, then all scenes).

Workers: in-process (``workers=1``), a local process pool (``workers>1``, spawned processes),
or Ray (``ray_address``: a cluster address, or ``"local"`` to start a local instance). Whoever
runs jobs keeps :class:`~ctrplan.planning.planner.Planners` (one Planner per robot, scene, model
and settings, the scenes by name): the in-process run its own, each worker process its own
(:func:`~ctrplan.planning.planner.worker_planners`). A plan does not depend on the plans made before it, so a job's result
does not depend on which worker ran it.
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import logging
import math
import os
import re
from collections.abc import Iterable, Sequence
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ctrplan.errors import ArgumentError, InputError

log = logging.getLogger("ctrplan")

#: ``--targets examples``: every example target of the shipped scenes.
EXAMPLES = "examples"
#: a Job's tip pose goal fields, in the order of the targets CSV's columns
#: (:data:`ctrplan.planning.tipgoal.CSV_NAMES`: standoff_mm, approach, cone_deg)
GOAL_FIELDS = ("goal_standoff_mm", "goal_approach", "goal_cone_deg")


@dataclass(frozen=True)
class Job:
    """One planning problem. target : (x, y, z) mm, scene frame."""

    scene: str
    target_name: str
    target: tuple[float, float, float]
    seed: int = 0
    robot: str = "seed1"
    model: str = "physics"
    planner: str = "rrtconnect"
    time_limit: float = 5.0
    tolerance_mm: float = 1.0
    margin: str = "auto"          # "auto" or a number of mm (as text)
    objective: str = "clearance"  # clearance, length or first
    # a tip pose goal (the targets CSV's standoff_mm, approach, cone_deg; None: not given):
    # mm >= 0; "normal" or "x,y,z" (scene frame); half-angle deg. All None: a point goal.
    goal_standoff_mm: float | None = None
    goal_approach: str | None = None
    goal_cone_deg: float | None = None

    @property
    def has_tip_goal(self) -> bool:
        return any(getattr(self, k) is not None for k in GOAL_FIELDS)

    @property
    def id(self) -> str:
        # the goal is part of the key where given (a changed goal is a new job); a point goal
        # hashes as before the goal fields existed, so earlier batches still resume
        spec = json.dumps({k: v for k, v in asdict(self).items()
                           if not (k in GOAL_FIELDS and v is None)}, sort_keys=True)
        digest = hashlib.sha1(spec.encode()).hexdigest()[:8]
        return f"{_safe(Path(self.scene).name)}__{_safe(self.target_name)}__s{self.seed}__{digest}"


def _safe(s: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", str(s)).strip("_") or "x"


# ---------------------------------------------------------------------- inputs
def check_scene_spec(spec: str) -> str:
    """A shipped scene name or a scene folder (or its scene.yaml); InputError otherwise.

    Checked without loading the meshes, so a batch fails fast on a typo.
    """
    from ctrplan.collision.scene import anatomy_dir, list_scenes

    p = Path(spec)
    try:   # a name the file system cannot hold (too long, NUL) names no scene either
        if p.is_file() and p.name.endswith((".yaml", ".yml")):
            return spec
        if p.is_dir() and (p / "scene.yaml").is_file():
            return spec
        if "/" not in spec and os.sep not in spec and (anatomy_dir() / spec / "scene.yaml").is_file():
            return spec
    except (OSError, ValueError):
        pass
    raise InputError(spec, "", f"no such scene folder, and not a shipped scene "
                               f"({', '.join(list_scenes()) or 'none found'})")


def read_targets(targets: str, scenes: Sequence[str] = ()) -> list[tuple]:
    """Targets as (scene, name, (x, y, z)), with a fourth element for a row with a tip pose
    goal: the Job's goal fields (:data:`GOAL_FIELDS`) as a dict.

    ``targets`` is a CSV with columns ``x,y,z`` (mm, scene frame) and optionally ``scene`` and
    ``name``, or ``"examples"`` for the example targets of the shipped scenes. ``scenes``
    restricts the examples / CSV rows to those scenes, and supplies the scene of CSV rows
    without a ``scene`` column (each target then goes to every listed scene). Optional columns
    ``standoff_mm``, ``approach`` (``normal`` or a direction ``X Y Z``) and ``cone_deg`` give a
    row a tip pose goal, as ``plan --standoff/--approach/--cone`` (:func:`_row_goal`); a row
    leaving them empty plans to its point.
    """
    from ctrplan.collision.scene import list_scenes, load_scene

    for s in scenes:
        check_scene_spec(s)
    out: list[tuple] = []
    path = targets
    if path == EXAMPLES:
        for s in scenes or list_scenes():
            scene = load_scene(s)
            for t in scene.targets:
                out.append((s, t.name, tuple(float(v) for v in t.position)))
        if not out:
            raise ArgumentError("targets", "no example targets found (no shipped scenes?)")
        return out
    from ctrplan.io import read_csv_table

    header, rows = read_csv_table(path)
    cols = {h.strip().lower(): i for i, h in enumerate(header)}
    for c in ("x", "y", "z"):
        if c not in cols:
            raise InputError(path, c, "missing column (need x,y,z and optionally scene,name)")
    if "scene" not in cols and not scenes:
        raise InputError(path, "scene", "missing column; or give the scene with --scene")
    if not rows:
        raise InputError(path, "rows", "no targets (only a header)")
    for k, row in enumerate(rows):
        where = f"row {k + 2}"
        try:
            xyz = tuple(float(row[cols[c]]) for c in ("x", "y", "z"))
        except (ValueError, IndexError):
            raise InputError(path, where, "x, y, z must be numbers (mm)") from None
        if not all(math.isfinite(v) for v in xyz):
            raise InputError(path, where, "x, y, z must be finite numbers (mm)")
        name = row[cols["name"]].strip() if "name" in cols and cols["name"] < len(row) else ""
        name = name or f"row{k + 2}"
        goal = _row_goal(path, where, row, cols)
        extra = () if goal is None else (goal,)
        if "scene" in cols:
            s = row[cols["scene"]].strip() if cols["scene"] < len(row) else ""
            if not s:
                raise InputError(path, f"{where}: scene", "empty")
            if scenes and s not in scenes:
                continue
            try:
                check_scene_spec(s)
            except InputError as exc:
                raise InputError(path, f"{where}: scene", f"{s!r}: {exc.message}") from None
            out.append((s, name, xyz, *extra))
        else:
            out.extend((s, name, xyz, *extra) for s in scenes)
    if not out:
        raise InputError(path, "scene", "no rows for the scenes given with --scene")
    return out


def _row_goal(path: str, where: str, row: list[str], cols: dict[str, int]) -> dict | None:
    """A targets CSV row's tip pose goal (the Job's :data:`GOAL_FIELDS`), or None when its
    ``standoff_mm``, ``approach`` and ``cone_deg`` cells are absent or empty. Checked as
    ``plan --standoff/--approach/--cone`` are
    (:func:`~ctrplan.planning.tipgoal.parse_goal_values`); InputError naming the file, the row
    and the column otherwise."""
    from ctrplan.planning.tipgoal import CSV_NAMES, parse_goal_values

    cells = [row[cols[c]].strip() if c in cols and cols[c] < len(row) else "" for c in CSV_NAMES]
    if not any(cells):
        return None
    standoff, approach, cone = parse_goal_values(
        *(c or None for c in cells), names=CSV_NAMES,
        error=lambda column, message: InputError(path, f"{where}: {column}", message))
    if approach is not None and approach != "normal":
        approach = ",".join(repr(float(v)) for v in approach)
    return dict(zip(GOAL_FIELDS, (standoff, approach, cone)))


def make_jobs(targets: Iterable[tuple], seeds: Sequence[int] = (0,), **settings: Any) -> list[Job]:
    """One job per target and seed. ``targets``: (scene, name, (x, y, z)) or, with a tip pose
    goal, (scene, name, (x, y, z), {goal field: value}) as :func:`read_targets` gives them;
    ``settings`` are Job fields (robot, model, planner, ...)."""
    return [Job(scene=t[0], target_name=t[1], target=tuple(t[2]), seed=int(seed),
                **(t[3] if len(t) > 3 and t[3] else {}), **settings)
            for t in targets for seed in seeds]


# ---------------------------------------------------------------------- one job
@dataclass(frozen=True)
class JobResult:
    """What one job produced.

    job : the Job. status : a :class:`~ctrplan.planning.result.PlanStatus` (``INPUT_ERROR`` when
    the job's input was bad: one bad row does not stop a batch). message : why.
    plan : the plan.json fields (:meth:`PlanResult.to_json`), or None for bad input.
    """

    job: Job
    status: Any  # PlanStatus (imported lazily: the batch module stays light)
    message: str
    plan: dict | None = None

    @property
    def success(self) -> bool:
        return self.status.value == "SUCCESS"

    def to_json(self) -> dict:
        """The job's JSON file: the plan fields plus the job's fields and id."""
        base = {"job_id": self.job.id, **asdict(self.job), "target": list(self.job.target)}
        plan = dict(self.plan) if self.plan is not None else {}
        plan.update(success=self.success, status=self.status.value, message=self.message)
        plan["scene"] = self.job.scene
        out = {**plan, **base}
        if self.plan is not None:   # what solved it ("direct" for the straight edge)
            out["planner"] = self.plan["planner"]
        return out


def run_job(job: Job | dict, planners=None) -> JobResult:
    """Run one job (in any process) with a planner from ``planners`` (a
    :class:`~ctrplan.planning.planner.Planners`; None: a new one, kept for this job only).
    Bad input becomes status ``INPUT_ERROR`` with the message (naming the Job's field)."""
    from ctrplan.planning.planner import PlannerConfig, Planners
    from ctrplan.planning.result import PlanStatus

    if isinstance(job, dict):
        job = Job(**{**job, "target": tuple(job["target"])})
    try:
        margin = None if str(job.margin).strip().lower() == "auto" else float(job.margin)
    except ValueError:
        return JobResult(job, PlanStatus.INPUT_ERROR, f"margin: must be a number or auto, got {job.margin!r}")
    planners = planners if planners is not None else Planners(size=1)
    try:
        config = PlannerConfig(margin_mm=margin, objective=job.objective)
        planner = planners.get(job.robot, job.scene, job.model, config)
        goal, snap = _job_goal(job, planner.scene)
        result = planner.plan(goal, seed=job.seed, planner=job.planner,
                              time_limit=job.time_limit, tolerance_mm=job.tolerance_mm)
    except InputError as exc:
        return JobResult(job, PlanStatus.INPUT_ERROR, str(exc))
    return JobResult(job, result.status, result.message, {**result.to_json(), **snap})


def _job_goal(job: Job, scene) -> tuple:
    """The job's goal and plan.json's snap record: ``plan``'s path
    (:func:`~ctrplan.planning.tipgoal.goal_for_target`: the point, or a TipGoal snapped to the
    tissue for a standoff / approach normal), its values checked again (a Job made in Python
    did not pass the CSV reader)."""
    if not job.has_tip_goal:
        return job.target, {}
    from ctrplan.planning.tipgoal import CSV_NAMES, goal_for_target, parse_goal_values

    values = parse_goal_values(job.goal_standoff_mm, job.goal_approach, job.goal_cone_deg,
                               names=CSV_NAMES)
    return goal_for_target(job.target, scene, *values, field="target", names=CSV_NAMES)


def _run_job_json(job: dict) -> dict:
    """run_job in a worker process (pool or Ray) with the worker's planners
    (:func:`~ctrplan.planning.planner.worker_planners`): the JSON-ready dict crosses the
    process boundary."""
    from ctrplan.planning.planner import worker_planners

    return run_job(job, worker_planners()).to_json()


# ---------------------------------------------------------------------- a batch
@dataclass(frozen=True)
class BatchSummary:
    """What a batch did: jobs in total, skipped (already done), run now, and per-scene rows."""

    total: int
    skipped: int
    ran: int
    rows: list[dict]
    out: Path


def _done(path: Path, job: Job) -> dict | None:
    """The finished result of ``job`` in its job file, or None when the job must run: no file,
    not JSON (a truncated file: job files are written atomically, so only damage from outside
    truncates one) or not a result of this job (another id, no status); the rerun overwrites
    it. A result of this job with a field that fails :func:`validate_job_file` is refused
    (InputError naming the file and field): it may have been edited, and is never trusted."""
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("job_id") != job.id or "status" not in data:
        return None
    from ctrplan.planning.jobfile import validate_job_file  # an edited file is not trusted

    return validate_job_file(path, data, job)


def run_batch(jobs: Sequence[Job], out: str | os.PathLike, workers: int = 1,
              ray_address: str | None = None) -> BatchSummary:
    """Run the jobs not finished yet, write one JSON per job, jobs.csv and summary.csv.

    Crash-safe: each job's JSON is written to a temporary file, flushed to disk (fsync) and
    renamed into place, so a job file is either complete or absent whenever the run is killed
    (SIGKILL, power loss); a rerun skips the complete ones and redoes the rest (their
    temporary files are removed). ``jobs.csv`` and ``summary.csv`` describe the whole job list
    and exist only after a run that finished it. One run at a time per folder (a lock file).
    """
    from ctrplan import progress

    out = Path(out)
    jobs_dir = out / "jobs"
    jobs_dir.mkdir(parents=True, exist_ok=True)
    with _folder_lock(out):
        for stale in jobs_dir.glob(".*"):      # temporaries of a run that was killed
            if stale.is_file():
                stale.unlink()
        results: dict[str, dict] = {}
        todo: list[Job] = []
        seen: set[str] = set()
        for job in jobs:
            if job.id in seen:
                continue
            seen.add(job.id)
            data = _done(jobs_dir / f"{job.id}.json", job)
            if data is not None:
                results[job.id] = data
            else:
                todo.append(job)
        skipped = len(results)
        if skipped:
            log.info("plan-batch: %d of %d jobs already done in %s, running %d", skipped, len(seen),
                     out, len(todo))
        if todo:   # the tables of an earlier run no longer describe the job list
            for name in ("jobs.csv", "summary.csv"):
                (out / name).unlink(missing_ok=True)

        bar = progress.bar(total=len(todo), desc="plan-batch", unit="job")

        def record(res: dict) -> None:
            if res["job_id"] in results:     # never twice
                return
            write_job_file(jobs_dir / f"{res['job_id']}.json", res)
            results[res["job_id"]] = res
            bar.update(1)
            bar.set_postfix_str(f"{res.get('status', '')}")

        try:
            if not todo:
                pass
            elif ray_address:
                _run_ray(todo, ray_address, workers, record)
            elif workers <= 1:
                from ctrplan import interrupt
                from ctrplan.planning.planner import Planners

                planners = Planners()      # this run's, dropped with it
                for job in todo:
                    record(run_job(job, planners).to_json())
                    interrupt.check()
            else:
                _run_pool(todo, workers, record)
        finally:
            bar.close()
        ordered = [results[j] for j in dict.fromkeys(job.id for job in jobs) if j in results]
        rows = summarize(ordered)
        write_tables(out, ordered, rows)
    return BatchSummary(total=len(seen), skipped=skipped, ran=len(todo), rows=rows, out=out)


def write_job_file(path: Path, res: dict) -> None:
    """Write one job's JSON durably: temporary file, fsync, rename, fsync of the folder."""
    import tempfile

    from ctrplan import interrupt

    text = json.dumps(res, indent=2, allow_nan=False) + "\n"
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    interrupt.pending_added(tmp)
    try:
        with os.fdopen(fd, "w", encoding="utf-8") as fh:
            fh.write(text)
            fh.flush()
            os.fsync(fh.fileno())
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    finally:
        interrupt.pending_removed(tmp)
    dfd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dfd)
    finally:
        os.close(dfd)


@contextlib.contextmanager
def _folder_lock(out: Path, what: str = "plan-batch"):
    """An exclusive lock on ``out/.lock`` for the run (released by the OS if the process dies);
    ``what`` names the command in the refusal."""
    try:
        import fcntl
    except ImportError:  # pragma: no cover - not POSIX
        yield
        return
    path = out / ".lock"
    while True:
        fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            os.close(fd)
            raise ArgumentError("out", f"another {what} is writing to {str(out)!r} "
                                          f"(wait for it, or use another folder)") from None
        try:   # the file may have been removed by the run that held it: lock the one there now
            if os.stat(path).st_ino == os.fstat(fd).st_ino:
                break
        except FileNotFoundError:
            pass
        os.close(fd)
    try:
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(path)      # removed while still held: the folder keeps only results
        os.close(fd)


def run_tasks(fn, args: Sequence[dict], workers: int = 1, ray_address: str | None = None,
              record=None) -> None:
    """``record(fn(a))`` for every ``a`` in ``args`` (JSON-ready dicts), as each finishes: on Ray
    (``ray_address``), a pool of ``workers`` spawned processes, or in this process
    (``workers <= 1``). The one parallel path of plan-batch and ``scene reach``: ``fn`` is a
    module-level function (it crosses the process boundary by name) that keeps its state in
    the worker (:func:`~ctrplan.planning.planner.worker_planners`)."""
    from ctrplan import interrupt

    if not args:
        return
    if ray_address:
        from ctrplan.planning.ray_pool import ray_as_completed, ray_session

        with ray_session(ray_address, num_cpus=max(1, workers)), \
                contextlib.closing(ray_as_completed(fn, list(args))) as results:
            for _, res in results:
                record(res)
    elif workers <= 1:
        for a in args:
            record(fn(a))
            interrupt.check()
    else:
        _run_pool(args, workers, record, fn)


def _run_pool(todo: Sequence[Any], workers: int, record, fn=None) -> None:
    """Run the jobs (or ``fn`` over argument dicts) in a pool of spawned worker processes,
    recording each result as it comes.

    On SIGINT / SIGTERM (KeyboardInterrupt here) or any error the workers are killed at once
    (:func:`ctrplan.interrupt.stop_pool`: a job in the middle of planning is not waited for)
    and joined, so no worker outlives the command; workers ignore Ctrl-C themselves and die
    with the parent if it is killed (:func:`ctrplan.interrupt.ignore_in_child`)."""
    from ctrplan import interrupt

    # spawn, not fork: torch, numba and OMPL threads do not survive a fork reliably. The
    # workers start with SIGINT blocked (interrupt.worker_context); a Ctrl-C while they start
    # is raised once the pool exists, so that the clean-up below stops them.
    pool = None
    finished = False
    try:
        with interrupt.spawning():
            pool = interrupt.worker_context("spawn").Pool(
                processes=max(1, min(workers, len(todo))), initializer=_worker_init)
        args = [asdict(job) for job in todo] if fn is None else list(todo)
        for res in pool.imap_unordered(fn or _run_job_json, args):
            record(res)
            interrupt.check()
        finished = True
    finally:
        if pool is not None:
            if finished:
                pool.close()
                pool.join()
            else:
                interrupt.stop_pool(pool)


def _worker_init() -> None:
    from ctrplan import interrupt

    interrupt.ignore_in_child()
    # One intra-op thread per worker (before torch is imported): the pool is the parallelism.
    os.environ.setdefault("OMP_NUM_THREADS", "1")


def _run_ray(todo: Sequence[Job], address: str, workers: int, record) -> None:
    # the one Ray path of every command (design too): ctrplan.planning.ray_pool
    from ctrplan.planning.ray_pool import ray_as_completed, ray_session

    with ray_session(address, num_cpus=max(1, workers)), \
            contextlib.closing(ray_as_completed(_run_job_json, [asdict(job) for job in todo])) as results:
        for _, res in results:
            record(res)


# ---------------------------------------------------------------------- tables
JOB_COLUMNS = ("job_id", "scene", "target_name", "x", "y", "z", "seed", "robot", "model", "planner",
               "status", "success", "planning_time_s", "tip_error_mm", "min_clearance_mm", "min_clearance_exact",
               "min_clearance_reference_mm", "margin_mm", "objective", "objective_value", "calibrated",
               "surrogate_error_mm", "goal_shift_mm", "start_rotated", "outside_measured_states",
               "message")
#: jobs.csv's tip pose goal columns, after JOB_COLUMNS when a job of the batch has a tip goal:
#: the goal asked (the targets CSV's standoff_mm, approach, cone_deg) and what the plan
#: achieved (plan.json's standoff_mm, direction_error_deg, snap_distance_mm)
GOAL_COLUMNS = (*GOAL_FIELDS, "standoff_mm", "direction_error_deg", "snap_distance_mm")


def _has_tip_goal(r: dict) -> bool:
    return any(r.get(k) is not None for k in GOAL_FIELDS)


def summarize(results: Sequence[dict]) -> list[dict]:
    """Per-scene rows (then ``all``): jobs, successes, success rate, time median/p90/max,
    the count of each status, the jobs planned with a calibrated model and with an uncalibrated
    surrogate (``surrogate_error``), and the path states beyond the calibrated model's measured
    insertions summed over the jobs (empty when no job's model records them)."""
    by_scene: dict[str, list[dict]] = {}
    for r in results:
        by_scene.setdefault(str(r.get("scene")), []).append(r)
    rows = []
    groups = [(s, by_scene[s]) for s in sorted(by_scene)]
    if len(groups) != 1:
        groups.append(("all", list(results)))
    for scene, rs in groups:
        ok = [bool(r.get("success")) for r in rs]
        t = np.array([r["planning_time_s"] for r in rs if r.get("planning_time_s") is not None], dtype=float)
        statuses: dict[str, int] = {}
        for r in rs:
            statuses[str(r.get("status"))] = statuses.get(str(r.get("status")), 0) + 1
        rows.append({
            "scene": scene,
            "jobs": len(rs),
            "success": int(sum(ok)),
            "success_rate": float(np.mean(ok)) if rs else float("nan"),
            "time_median_s": float(np.median(t)) if len(t) else float("nan"),
            "time_p90_s": float(np.percentile(t, 90)) if len(t) else float("nan"),
            "time_max_s": float(np.max(t)) if len(t) else float("nan"),
            "statuses": ";".join(f"{k}:{v}" for k, v in sorted(statuses.items())),
            # the labels: jobs planned with a model whose error bound was measured on a robot,
            # and with an uncalibrated surrogate (padded by its surrogate error with margin auto)
            "calibrated_jobs": sum(bool(r.get("calibrated")) for r in rs),
            "surrogate_jobs": sum(isinstance(r.get("surrogate_error"), dict) for r in rs),
            "outside_measured_states": _sum_counts(r.get("outside_measured_states") for r in rs),
        })
        if any(_has_tip_goal(r) for r in results):
            rows[-1].update(_goal_summary(rs))
    return rows


def _goal_summary(rs: Sequence[dict]) -> dict:
    """summary.csv's tip pose goal columns: the jobs with a tip goal, and the median and the
    largest of their achieved direction errors (deg; "" when none has one)."""
    goals = [r for r in rs if _has_tip_goal(r)]
    err = [float(r["direction_error_deg"]) for r in goals
           if isinstance(r.get("direction_error_deg"), (int, float))]
    return {"tip_goal_jobs": len(goals),
            "direction_error_deg_median": float(np.median(err)) if err else "",
            "direction_error_deg_max": float(np.max(err)) if err else ""}


def _sum_counts(counts) -> int | str:
    """Sum of the counts that are recorded; "" when none is (a model without a measured range)."""
    known = [int(c) for c in counts if c is not None]
    return sum(known) if known else ""


def write_tables(out: Path, results: Sequence[dict], rows: Sequence[dict]) -> None:
    """``jobs.csv`` (one row per job) and ``summary.csv`` (per scene) in ``out``."""
    from ctrplan.io import write_csv_atomic

    columns = JOB_COLUMNS + (GOAL_COLUMNS if any(_has_tip_goal(r) for r in results) else ())
    job_rows = []
    for r in results:
        x, y, z = (list(r.get("target") or [None] * 3) + [None] * 3)[:3]
        sur = r.get("surrogate_error")
        vals = {**r, "x": x, "y": y, "z": z, "success": int(bool(r.get("success"))),
                # the surrogate's p99 (mm): what --margin auto pads an uncalibrated surrogate by
                "surrogate_error_mm": sur.get("p99") if isinstance(sur, dict) else None}
        job_rows.append(["" if vals.get(c) is None else vals.get(c) for c in columns])
    write_csv_atomic(out / "jobs.csv", columns, job_rows)
    cols = list(rows[0].keys()) if rows else ["scene", "jobs", "success", "success_rate"]
    write_csv_atomic(out / "summary.csv", cols, [[r[c] for c in cols] for r in rows])
