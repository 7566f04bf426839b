"""Reachability maps: which points of the anatomy's surface the robot can put its tip at.

``ctrplan scene reach`` (:func:`reach_map`) samples the surface (:func:`ctrplan.collision.surface.
sample_surface`: area-weighted, seeded, or a region near named targets) and decides per point
whether the robot reaches it: a :class:`~ctrplan.planning.tipgoal.TipGoal` at the point with
its normal (into the lumen), ``standoff_mm`` (the tip at ``point + standoff_mm * normal``, the
**goal**; a standoff below the tip's radius + margin is planned at that distance, as ``plan``
does) and, with an approach, the tip's tangent within ``cone_deg`` of the approach direction
(``normal``: straight at the surface, ``-normal``; or a fixed direction in the scene frame).

Two stages:

1. **Screen** (:func:`screen`, in the driving process): batched IK over all points at once,
   in the rounds a plan's IK goals are found in (the planner's ``ik_rounds`` rounds of
   ``ik.seeds`` workspace samples nearest each goal, collision-free ones first; a round only
   for the points not passed yet; without a direction every seed of every point refined toward
   its own goal in one :func:`~ctrplan.planning.ik.solve_ik`, with one by
   :func:`~ctrplan.planning.ik.solve_ik_cone` per point), then the direction filter and the
   planning world's collision check of the converged configurations. A point passes when one
   configuration puts the tip within the tolerance of the goal, its direction within the cone
   (:func:`~ctrplan.planning.tipgoal.tip_frames`, the same tangent the plan reports),
   collision-free.
2. **Plan**: a full plan (:meth:`Planner.plan <ctrplan.planning.planner.Planner.plan>`, the
   retracted start, the same seed for every point) to every point that passed, on the same
   pool / Ray path as plan-batch (:func:`~ctrplan.planning.batch.run_tasks`). The map's verdict
   is the plan's: ``reachable`` only for a plan with status SUCCESS (the tip within the
   tolerance of the goal and, with a cone, its direction within it). A point that fails the
   screen is ``reachable = false`` with status ``NO_POSE`` and is not planned.

Resumable like plan-batch: each point's result is written durably to ``<out>/points/<id>.json``
as it is decided (the id is the point's index plus a hash of the point and every setting); a
rerun with the same settings skips the points whose file exists and decides the rest.
``reach.csv``, ``reach.html`` and ``reach.png`` are written (atomically) only once every point
is decided, so an interrupted run leaves no partial map.
"""

from __future__ import annotations

import hashlib
import json
import logging
import math
from dataclasses import asdict, dataclass, replace
from pathlib import Path

import numpy as np

from ctrplan.errors import ArgumentError, InputError

log = logging.getLogger("ctrplan")

#: Status of a point the screen found no pose for (it is not planned).
NO_POSE = "NO_POSE"


@dataclass(frozen=True)
class ReachSettings:
    """One map's settings (all of them go into each point's id).

    scene, robot, model : as for ``plan`` (names or paths).
    standoff_mm : the goal lies this far from the surface point along its normal (mm).
    approach : "" (no direction goal), "normal" (the tip pointing at the surface: its tangent
        within ``cone_deg`` of ``-normal``) or "x,y,z" (a fixed tangent, scene frame).
    cone_deg : half-angle of the approach cone (deg, in (0, 90]); required with an approach.
    tolerance_mm, time_limit, planner, margin, objective : each plan's, as for ``plan``.
    seed : the surface sample's and every plan's seed.
    ik_seeds : IK seeds per point and round in the screen (None: the planner's, ``ik.seeds``;
        rounds: ``ik_rounds``, as a plan's goal rounds).
    """

    scene: str
    robot: str = "seed1"
    model: str = "physics"
    standoff_mm: float = 2.0
    approach: str = ""
    cone_deg: float | None = None
    tolerance_mm: float = 1.0
    time_limit: float = 2.0
    planner: str = "rrtconnect"
    margin: str = "auto"
    objective: str = "clearance"
    seed: int = 0
    ik_seeds: int | None = None

    def __post_init__(self) -> None:
        if not (math.isfinite(self.standoff_mm) and self.standoff_mm >= 0):
            raise ArgumentError("standoff_mm", f"must be a number >= 0 (mm), got {self.standoff_mm!r}")
        if self.approach and self.cone_deg is None:
            raise ArgumentError("cone_deg", "an approach direction needs a cone (deg)")
        if self.cone_deg is not None and not self.approach:
            raise ArgumentError("cone_deg", "a cone needs an approach direction (approach)")
        if self.cone_deg is not None and not (0 < self.cone_deg <= 90):
            raise ArgumentError("cone_deg", f"must be in (0, 90] deg, got {self.cone_deg!r}")
        if self.approach and self.approach != "normal":
            parse_direction(self.approach)
        if self.ik_seeds is not None and not (isinstance(self.ik_seeds, int) and self.ik_seeds >= 1):
            raise ArgumentError("ik_seeds", f"must be an integer >= 1 or None, got {self.ik_seeds!r}")


def parse_direction(text: str) -> np.ndarray:
    """A unit direction from ``"x,y,z"``; ArgumentError naming ``approach`` otherwise."""
    try:
        v = np.array([float(x) for x in str(text).split(",")], dtype=float)
    except ValueError:
        v = np.zeros(0)
    if v.shape != (3,) or not np.all(np.isfinite(v)) or not np.linalg.norm(v) > 0:
        raise ArgumentError("approach", f"must be 'normal' or a non-zero direction X,Y,Z, got {text!r}")
    return v / np.linalg.norm(v)


def approach_directions(settings: ReachSettings, normals: np.ndarray) -> np.ndarray | None:
    """(P, 3) unit tip tangents asked for (scene frame), or None without an approach."""
    if not settings.approach:
        return None
    if settings.approach == "normal":
        return -np.asarray(normals, dtype=float)
    return np.repeat(parse_direction(settings.approach)[None], len(normals), axis=0)


def region_points(scene, region: str | None = None, near_targets: bool = False) -> np.ndarray | None:
    """The points a sampled region lies around ((K, 3) mm, scene frame), for
    :func:`~ctrplan.collision.surface.sample_surface`'s ``near``: the named targets in
    ``region`` (names or ids, comma-separated), every named target with ``near_targets``, or
    None (the whole surface). ArgumentError naming ``region`` / ``near_targets`` otherwise."""
    if region and near_targets:
        raise ArgumentError("region", "give `region` or `near_targets`, not both")
    if near_targets:
        pts = scene.target_positions()
        if not len(pts):
            raise ArgumentError("near_targets", f"scene {scene.name!r} has no named targets")
        return pts
    if not region:
        return None
    pts = []
    for name in (n.strip() for n in str(region).split(",")):
        t = scene.find_target(name) if name else None
        if t is None:
            raise ArgumentError("region", f"no target {name!r} in scene {scene.name!r} "
                                          f"({scene.target_names()})")
        pts.append(np.asarray(t.position, dtype=float))
    return np.array(pts)


def point_id(settings: ReachSettings, index: int, point, normal) -> str:
    """``p<index>__<hash>``: the hash covers the point, its normal and every setting."""
    spec = json.dumps({"settings": asdict(settings), "point": [float(v) for v in point],
                       "normal": [float(v) for v in normal]}, sort_keys=True)
    return f"p{int(index):05d}__{hashlib.sha1(spec.encode()).hexdigest()[:10]}"


# ---------------------------------------------------------------------- the screen
@dataclass(frozen=True)
class ScreenResult:
    """Per point (P,): passed; best tip error (mm) of the IK; direction error (deg) and
    clearance (mm) of the best passing configuration (nan where none passed)."""

    passed: np.ndarray
    tip_error_mm: np.ndarray
    direction_error_deg: np.ndarray
    clearance_mm: np.ndarray


def planned_goals(planner, points: np.ndarray, normals: np.ndarray, standoff_mm: float) -> np.ndarray:
    """(P, 3) mm, scene frame: where a plan puts the tip for a TipGoal at ``points`` with
    ``normals`` and ``standoff_mm`` (at least the tip's radius + margin +
    :data:`~ctrplan.planning.tipgoal.CONTACT_PAD_MM` off the surface, as the planner does)."""
    from ctrplan.planning.run import tip_margin
    from ctrplan.planning.tipgoal import CONTACT_PAD_MM

    least = float(planner.robot.tubes[0].od) / 2.0 + tip_margin(planner) + CONTACT_PAD_MM
    return points + max(float(standoff_mm), least) * normals


def screen_seeds(planner, targets: np.ndarray, axes: np.ndarray | None, cone_deg: float | None,
                 seeds: int, round_: int, alpha_weight_mm: float) -> np.ndarray:
    """IK seeds (P, S, 2n) for round ``round_`` of every target (P, 3) mm, base frame, chosen as
    the planner's goal rounds choose them (:class:`~ctrplan.planning.goals.GoalSource`): among
    the next ``2 S`` workspace samples nearest the target (with a direction: the ``2 S`` of the
    next ``8 S`` nearest counting ``alpha_weight_mm`` mm per rad of tangent beyond the cone, one
    batched shape call for all targets), the collision-free ones first."""
    from ctrplan.planning.tipgoal import angle_deg, tip_frames

    table = planner.workspace_table()
    pool = 2 * seeds
    if axes is None:
        cand = np.stack([table.nearest(g, pool, skip=round_ * pool) for g in targets])
    else:
        cone = math.radians(float(cone_deg))
        wide = np.stack([table.nearest(g, 4 * pool, skip=round_ * 4 * pool) for g in targets])
        W = wide.shape[1]
        tip, t, ok = tip_frames(planner.model, wide.reshape(-1, wide.shape[-1]))
        beyond = np.maximum(0.0, np.radians(angle_deg(t, np.repeat(axes, W, axis=0))) - cone)
        cost = np.linalg.norm(tip - np.repeat(targets, W, axis=0), axis=1) + alpha_weight_mm * beyond
        cost = np.where(ok, cost, np.inf).reshape(len(targets), W)
        order = np.argsort(cost, axis=1, kind="stable")[:, :pool]
        cand = np.take_along_axis(wide, order[:, :, None], axis=1)
    P, C, d = cand.shape
    free = planner.validator(tracking=False).states_valid(cand.reshape(-1, d)).reshape(P, C)
    order = np.argsort(~free, axis=1, kind="stable")[:, :seeds]
    return np.take_along_axis(cand, order[:, :, None], axis=1)


def screen_ik(planner, targets: np.ndarray, q0: np.ndarray, axes: np.ndarray | None,
              cone_deg: float | None, ikc) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IK toward every target (P, 3) mm, base frame, from its seeds ``q0`` (P, S, 2n):
    (q (P*S, 2n), tips (P*S, 3) base frame (NaN where the model failed), owner (P*S,)).

    Without a direction (``axes`` None) one :func:`~ctrplan.planning.ik.solve_ik` refines the
    seeds of all targets together (each row toward its own target); with one (``axes`` (P, 3)
    unit, base frame) :func:`~ctrplan.planning.ik.solve_ik_cone` per target (its seeds
    batched)."""
    from ctrplan.planning.ik import solve_ik, solve_ik_cone

    robot, model = planner.robot, planner.model
    P, S, d = q0.shape
    owner = np.repeat(np.arange(P), S)
    if axes is None:
        res = solve_ik(model, robot, targets[owner], q0.reshape(-1, d), ikc)
        return res.q, np.where(np.isfinite(res.error_mm)[:, None], res.tip, np.nan), owner
    qs, tips = [], []
    for p in range(P):
        res = solve_ik_cone(model, robot, targets[p], q0[p], axes[p], math.radians(float(cone_deg)), ikc)
        qs.append(res.q)
        tips.append(np.where(np.isfinite(res.error_mm)[:, None], res.tip, np.nan))
    return np.concatenate(qs), np.concatenate(tips), owner


def screen(planner, goals: np.ndarray, directions: np.ndarray | None, cone_deg: float | None,
           tolerance_mm: float, seeds: int | None = None, planned: np.ndarray | None = None,
           rounds: int | None = None) -> ScreenResult:
    """The screen (module docstring) of goals (P, 3) mm, scene frame, with tip tangents
    ``directions`` (P, 3) scene frame (None: any direction) within ``cone_deg``. ``planned``
    (P, 3): where IK puts the tip when that differs from the goal (a standoff below the tip's
    radius + margin); the tolerance applies to ``goals``. ``seeds`` per round and ``rounds``
    (None: the planner's ``ik.seeds`` and ``ik_rounds``, so the screen searches as widely as a
    plan's goal rounds); a round runs only for the points not passed yet."""
    from ctrplan.planning.tipgoal import to_base_vectors

    goals = np.asarray(goals, dtype=float).reshape(-1, 3)
    planned = goals if planned is None else np.asarray(planned, dtype=float).reshape(-1, 3)
    P = len(goals)
    cfg = planner.config
    seeds = int(seeds or cfg.ik.seeds)
    rounds = int(rounds or cfg.ik_rounds)
    out = ScreenResult(np.zeros(P, bool), np.full(P, np.nan), np.full(P, np.nan), np.full(P, np.nan))
    scene = planner.scene
    axes = None if directions is None else to_base_vectors(scene, np.asarray(directions, dtype=float))
    ikc = replace(cfg.ik, stop_mm=min(cfg.ik.stop_mm, 0.1 * tolerance_mm))
    for r in range(rounds):
        left = np.flatnonzero(~out.passed)
        if len(left) == 0:
            break
        base = scene.to_base(planned[left])
        ax = None if axes is None else axes[left]
        q0 = screen_seeds(planner, base, ax, cone_deg, seeds, r, ikc.alpha_weight_mm)
        q, tip, owner = screen_ik(planner, base, q0, ax, cone_deg, ikc)
        got = _judge(planner, q, tip, owner, goals[left],
                     None if directions is None else np.asarray(directions, dtype=float)[left],
                     cone_deg, tolerance_mm)
        out.tip_error_mm[left] = np.fmin(out.tip_error_mm[left], got.tip_error_mm)
        new = left[got.passed]
        out.passed[new] = True
        out.direction_error_deg[new] = got.direction_error_deg[got.passed]
        out.clearance_mm[new] = got.clearance_mm[got.passed]
    return out


def _judge(planner, q, tip, owner, goals, directions, cone_deg, tolerance_mm) -> ScreenResult:
    """Which of the targets ``goals`` (P, 3) scene frame the IK rows (q, tips in the base
    frame, owner) reach: the tip within the tolerance, in the joint limits, the direction in
    the cone, collision-free in the planning world; per target the best values."""
    from ctrplan.planning.tipgoal import angle_deg, tip_frames, to_scene_vectors

    scene = planner.scene
    P = len(goals)
    err = np.linalg.norm(tip - scene.to_base(goals)[owner], axis=1)
    err = np.where(np.isfinite(err), err, np.inf)
    best_err = np.full(P, np.inf)
    np.minimum.at(best_err, owner, err)
    validator = planner.validator(tracking=False)
    ok = (err <= tolerance_mm) & validator.joint_valid(q)
    dir_err = np.full(len(err), np.nan)
    idx = np.flatnonzero(ok)
    if directions is not None and len(idx):
        _, t, good = tip_frames(planner.model, q[idx])
        dir_err[idx] = angle_deg(to_scene_vectors(scene, t), directions[owner[idx]])
        ok[idx] &= good & (dir_err[idx] <= cone_deg)
    clear = np.full(len(err), -np.inf)
    idx = np.flatnonzero(ok)
    if len(idx):
        collides, clearance, _ = validator.check_states(q[idx])
        ok[idx] &= ~np.asarray(collides, dtype=bool)
        clear[idx] = np.where(ok[idx], np.asarray(clearance, dtype=float), -np.inf)
    passed = np.zeros(P, dtype=bool)
    np.logical_or.at(passed, owner, ok)
    best_clear = np.full(P, -np.inf)
    np.maximum.at(best_clear, owner, clear)
    best_dir = np.full(P, np.nan)
    for p in np.flatnonzero(passed):      # the direction error of the clearest passing pose
        rows = np.flatnonzero((owner == p) & ok)
        best_dir[p] = dir_err[rows[np.argmax(clear[rows])]]
    return ScreenResult(passed=passed, tip_error_mm=np.where(np.isfinite(best_err), best_err, np.nan),
                        direction_error_deg=best_dir, clearance_mm=np.where(passed, best_clear, np.nan))


# ---------------------------------------------------------------------- one point's plan
def plan_point(task: dict, planners=None) -> dict:
    """Plan to one screened point (a task dict: ``settings``, ``id``, ``position``, ``normal``,
    ``direction``) with a planner of ``planners`` (None: this worker's); the point's result
    fields."""
    from ctrplan.planning.planner import PlannerConfig, worker_planners
    from ctrplan.planning.tipgoal import TipGoal

    s = ReachSettings(**task["settings"])
    planners = planners if planners is not None else worker_planners()
    margin = None if s.margin == "auto" else float(s.margin)
    planner = planners.get(s.robot, s.scene, s.model, PlannerConfig(margin_mm=margin, objective=s.objective))
    goal = TipGoal(position=task["position"], normal=task["normal"], standoff_mm=s.standoff_mm,
                   direction=task.get("direction"), cone_deg=s.cone_deg if task.get("direction") else None)
    result = planner.plan(goal, seed=s.seed, planner=s.planner, time_limit=s.time_limit,
                          tolerance_mm=s.tolerance_mm)
    status = result.status.value
    return {"id": task["id"], "status": status, "reachable": status == "SUCCESS",
            "planned": True, "message": result.message,
            "tip_error_mm": _num(result.tip_error_mm),
            "direction_error_deg": _num(getattr(result, "direction_error_deg", None)),
            "clearance_mm": _num(result.min_clearance_mm),
            "planning_time_s": _num(result.planning_time_s),
            "goal_shift_mm": _num(getattr(result, "goal_shift_mm", None))}


def _plan_point_json(task: dict) -> dict:
    """plan_point in a worker process (pool or Ray) with the worker's planners."""
    return plan_point(task)


def _num(v) -> float | None:
    if v is None:
        return None
    v = float(v)
    return v if math.isfinite(v) else None


# ---------------------------------------------------------------------- the map
@dataclass(frozen=True)
class ReachSummary:
    """What a map run did: points in total, skipped (already decided), screened out now,
    planned now, reachable in total; rows: one dict per point (reach.csv's columns)."""

    total: int
    skipped: int
    screened_out: int
    planned: int
    reachable: int
    rows: list[dict]
    out: Path


#: reach.csv's columns, in order (docs/conventions.md describes each).
COLUMNS = ("point", "mesh", "x", "y", "z", "nx", "ny", "nz", "goal_x", "goal_y", "goal_z",
           "standoff_mm", "cone_deg", "reachable", "status", "screen", "screen_clearance_mm",
           "tip_error_mm", "direction_error_deg", "clearance_mm", "planning_time_s", "id")


def reach_map(settings: ReachSettings, samples, out, workers: int = 1,
              ray_address: str | None = None, planners=None) -> ReachSummary:
    """Decide every sampled point (module docstring) and write ``out``/reach.csv (the views are
    the command's: :mod:`ctrplan.commands.reach`). ``samples``: a
    :class:`~ctrplan.collision.surface.SurfaceSamples` in the scene's frame; ``workers`` /
    ``ray_address``: where the plans run (:func:`~ctrplan.planning.batch.run_tasks`);
    ``planners``: the in-process :class:`~ctrplan.planning.planner.Planners` (None: this run's)."""
    from ctrplan.io import write_csv_atomic
    from ctrplan.planning.batch import _folder_lock
    from ctrplan.planning.planner import Planners

    out = Path(out)
    pdir = out / "points"
    pdir.mkdir(parents=True, exist_ok=True)
    pts, nrm = np.asarray(samples.points, float), np.asarray(samples.normals, float)
    ids = [point_id(settings, i, p, n) for i, (p, n) in enumerate(zip(pts, nrm))]
    with _folder_lock(out, "scene reach"):
        for stale in pdir.glob(".*"):          # temporaries of a run that was killed
            if stale.is_file():
                stale.unlink()
        done: dict[str, dict] = {}
        for i, pid in enumerate(ids):
            data = read_point_file(pdir / f"{pid}.json", pid, pts[i])
            if data is not None:
                done[pid] = data
        todo = [i for i, pid in enumerate(ids) if pid not in done]
        screened_out = planned = 0
        if todo:
            for name in ("reach.csv", "reach.html", "reach.png"):
                (out / name).unlink(missing_ok=True)
            planners = planners if planners is not None else Planners()
            log.info("reach: screening %d points (%d already decided)", len(todo), len(ids) - len(todo))
            screened_out, planned = _decide(settings, samples, ids, todo, pdir, done, planners,
                                            workers, ray_address)
        rows = [csv_row(done[pid]) for pid in ids]
        write_csv_atomic(out / "reach.csv", COLUMNS,
                         [["" if r[c] is None else r[c] for c in COLUMNS] for r in rows])
    return ReachSummary(total=len(ids), skipped=len(ids) - len(todo), screened_out=screened_out,
                        planned=planned, reachable=sum(bool(r["reachable"]) for r in rows), rows=rows,
                        out=out)


def _decide(settings, samples, ids, todo, pdir, done, planners, workers, ray_address) -> tuple[int, int]:
    """Screen the points ``todo`` (indices), record the screened-out ones, plan the rest on the
    pool / Ray path; every decided point's file is written as it is decided and put in
    ``done``. Returns (screened out, planned)."""
    from ctrplan import interrupt, progress
    from ctrplan.planning.batch import run_tasks, write_job_file
    from ctrplan.planning.planner import PlannerConfig

    pts, nrm = np.asarray(samples.points, float), np.asarray(samples.normals, float)
    goals = pts + settings.standoff_mm * nrm
    dirs = approach_directions(settings, nrm)
    margin = None if settings.margin == "auto" else float(settings.margin)
    planner = planners.get(settings.robot, settings.scene, settings.model,
                           PlannerConfig(margin_mm=margin, objective=settings.objective))
    sc = screen(planner, goals[todo], None if dirs is None else dirs[todo], settings.cone_deg,
                settings.tolerance_mm, settings.ik_seeds,
                planned=planned_goals(planner, pts[todo], nrm[todo], settings.standoff_mm))
    interrupt.check()
    base: dict[str, dict] = {}
    tasks = []
    for k, i in enumerate(todo):
        base[ids[i]] = {**_point_fields(settings, i, ids[i], samples, goals, dirs),
                        "screen": bool(sc.passed[k]), "screen_clearance_mm": _num(sc.clearance_mm[k]),
                        "screen_tip_error_mm": _num(sc.tip_error_mm[k]),
                        "screen_direction_error_deg": _num(sc.direction_error_deg[k])}
        if sc.passed[k]:
            tasks.append({"settings": asdict(settings), "id": ids[i], "position": pts[i].tolist(),
                          "normal": nrm[i].tolist(),
                          "direction": None if dirs is None else dirs[i].tolist()})
        else:   # decided now: no pose
            rec = {**base[ids[i]], "status": NO_POSE, "reachable": False, "planned": False,
                   "message": "the screen found no collision-free pose with the tip at the goal "
                              "(and its direction in the cone)",
                   "tip_error_mm": None, "direction_error_deg": None, "clearance_mm": None,
                   "planning_time_s": None, "goal_shift_mm": None}
            write_job_file(pdir / f"{ids[i]}.json", rec)
            done[ids[i]] = rec
    bar = progress.bar(total=len(tasks), desc="reach", unit="point")

    def record(res: dict) -> None:
        rec = {**base[res["id"]], **res}
        write_job_file(pdir / f"{res['id']}.json", rec)
        done[res["id"]] = rec
        bar.update(1)

    try:
        if workers <= 1 and not ray_address:     # in this process, with the caller's planners
            run_tasks(lambda t: plan_point(t, planners), tasks, 1, None, record)
        else:
            run_tasks(_plan_point_json, tasks, workers, ray_address, record)
    finally:
        bar.close()
    return len(todo) - len(tasks), len(tasks)


def _point_fields(settings: ReachSettings, i: int, pid: str, samples, goals, dirs) -> dict:
    return {"id": pid, "point": int(i), "mesh": str(samples.mesh[i]),
            "position": [float(v) for v in samples.points[i]],
            "normal": [float(v) for v in samples.normals[i]],
            "goal": [float(v) for v in goals[i]],
            "direction": None if dirs is None else [float(v) for v in dirs[i]],
            "standoff_mm": float(settings.standoff_mm), "cone_deg": settings.cone_deg,
            "settings": asdict(settings)}


def csv_row(rec: dict) -> dict:
    """A point's reach.csv row (a dict keyed by :data:`COLUMNS`)."""
    x, y, z = rec["position"]
    nx, ny, nz = rec["normal"]
    gx, gy, gz = rec["goal"]
    return {"point": rec["point"], "mesh": rec["mesh"], "x": x, "y": y, "z": z, "nx": nx, "ny": ny,
            "nz": nz, "goal_x": gx, "goal_y": gy, "goal_z": gz, "standoff_mm": rec["standoff_mm"],
            "cone_deg": rec["cone_deg"], "reachable": int(bool(rec["reachable"])),
            "status": rec["status"], "screen": int(bool(rec["screen"])),
            "screen_clearance_mm": rec.get("screen_clearance_mm"),
            "tip_error_mm": rec.get("tip_error_mm"), "direction_error_deg": rec.get("direction_error_deg"),
            "clearance_mm": rec.get("clearance_mm"), "planning_time_s": rec.get("planning_time_s"),
            "id": rec["id"]}


# ---------------------------------------------------------------------- resume


def read_point_file(path: Path, pid: str, position=None) -> dict | None:
    """The decided result of point ``pid`` in ``path``, or None when it must be decided (no
    file, not JSON, another point). A file of this point with a field that does not hold, or
    (``position`` (3,) given) another position than the sampled point's, is refused
    (InputError naming the file and field): it may have been edited."""
    try:
        data = json.loads(Path(path).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    if not isinstance(data, dict) or data.get("id") != pid or "status" not in data:
        return None
    data = validate_point(path, data)
    if position is not None and not np.allclose(data["position"], position, rtol=0, atol=1e-9):
        raise InputError(str(path), "position", "is not the sampled point's (delete the file to "
                                                "decide the point again)")
    return data


def validate_point(path, data: dict) -> dict:
    """``data`` when every field reach.csv uses holds; InputError naming the file and field."""
    from ctrplan.planning.result import PlanStatus

    hint = "(delete the file to decide the point again)"

    def bad(field: str, what: str) -> InputError:
        return InputError(str(path), field, f"{what} {hint}")

    statuses = {s.value for s in PlanStatus} | {NO_POSE}
    if data.get("status") not in statuses:
        raise bad("status", f"must be one of {', '.join(sorted(statuses))}")
    for key in ("reachable", "screen", "planned"):
        if not isinstance(data.get(key), bool):
            raise bad(key, "must be true or false")
    if data["reachable"] != (data["status"] == "SUCCESS"):
        raise bad("reachable", f"must be {str(data['status'] == 'SUCCESS').lower()} for status {data['status']}")
    if data["status"] == NO_POSE and (data["screen"] or data["planned"]):
        raise bad("screen", f"a point of status {NO_POSE} failed the screen and was not planned")
    for key in ("position", "normal", "goal"):
        v = data.get(key)
        if not (isinstance(v, list) and len(v) == 3 and all(_finite(x) for x in v)):
            raise bad(key, "must be three finite numbers (mm)")
    if not isinstance(data.get("point"), int) or isinstance(data.get("point"), bool) or data["point"] < 0:
        raise bad("point", "must be an index >= 0")
    if not isinstance(data.get("mesh"), str):
        raise bad("mesh", "must be a mesh name")
    for key in ("standoff_mm", "cone_deg", "screen_clearance_mm", "tip_error_mm",
                "direction_error_deg", "clearance_mm", "planning_time_s"):
        v = data.get(key)
        if v is not None and not _finite(v):
            raise bad(key, "must be a finite number or null")
    return data


def _finite(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(float(v))
