"""Plan to a target: IK goals, OMPL search, simplification, exact verification.

:func:`plan_to_target` is the product's main job. Stages (timed separately):

1. **Checks** — start (the retracted configuration) collision-free, target within reach (the
   tip can never be farther from the base than the longest tube), target not inside anatomy.
2. **IK** — many seeds refined together on the planning model (:mod:`ctrplan.planning.ik`);
   solutions within ``tolerance_mm`` that are collision-free become OMPL goal states.
3. **Planning** — OMPL with the batched motion validator (:mod:`ctrplan.planning.space`);
   more goals are added if a time slice passes without a solution.
4. **Simplification** — vertex reduction and shortcutting with the same validator.
5. **Verification** — every state at ``resolution / verify_factor`` checked with exact FCL;
   a failing segment is re-planned with a finer validator, else the plan is not a success.
"""

from __future__ import annotations

import logging
import math
import os
import time
import weakref
from dataclasses import dataclass, field, replace
from enum import Enum
from typing import Any

import numpy as np

from ctrplan.errors import InputError
from ctrplan.planning import ik as _ik
from ctrplan.planning.goals import (
    GoalSource,
    retracted_start,
    target_blocked,
    target_outside_lumen,
)
from ctrplan.planning.validator import (
    BatchValidator,
    ValidatorConfig,
    interpolate_path,
    motion_mm,
)
from ctrplan.robot import Robot, load_robot

log = logging.getLogger("ctrplan")


class PlanStatus(str, Enum):
    """Outcome of :func:`plan_to_target`."""

    SUCCESS = "SUCCESS"
    UNREACHABLE = "UNREACHABLE"                  # no configuration puts the tip within tolerance
    TARGET_IN_COLLISION = "TARGET_IN_COLLISION"  # the target lies inside anatomy (or outside the lumen)
    START_IN_COLLISION = "START_IN_COLLISION"    # the retracted start configuration collides
    GOAL_IN_COLLISION = "GOAL_IN_COLLISION"      # reachable, but every reaching configuration collides
    TIMEOUT = "TIMEOUT"                          # no collision-free path within the time limit
    VERIFICATION_FAILED = "VERIFICATION_FAILED"  # the path failed the exact check and repair failed


@dataclass(frozen=True)
class PlanConfig:
    """Settings of :func:`plan_to_target` (the defaults are what the benchmarks use).

    validator : edge resolution, backbone points, rotation weight (see ValidatorConfig).
    ik : IK settings; ``ik.seeds`` seeds per round.
    table_size : workspace samples used to seed IK (cached per model).
    max_goals : goal states handed to OMPL per round.
    ik_rounds : IK rounds (each on the next-nearest workspace samples) before giving up on
        finding a collision-free goal; later rounds also run while planning, between slices.
    margin_mm : extra clearance required while planning (the final check uses 0).
    range_mm : longest edge the tree planners add (metric mm); None = OMPL's default.
    verify_factor : verification resolution is ``validator.resolution_mm / verify_factor``.
    verify_points : backbone points in the verification (None = validator.points).
    verify_fcl_all : send every verification state to FCL (``check_exact``). By default the
        world's ``check`` is used: its verdicts are FCL's too, the distance-field prefilter only
        skips FCL where its conservative bound proves a state free or colliding.
    output_step_mm : the returned path is subdivided so states are at most this far apart
        (metric mm); 0 returns the simplified waypoints only.
    output_points : backbone points per returned backbone.
    repair_attempts : re-planning rounds for segments that fail verification.
    optimize : let anytime planners (RRT*, BIT*, PRM) use the whole time limit.
    try_direct : before OMPL, try the straight edge from the start to the nearest goals
        (``counts["direct"]`` says whether it was taken); False always runs the planner.
    """

    validator: ValidatorConfig = field(default_factory=ValidatorConfig)
    ik: _ik.IKConfig = field(default_factory=_ik.IKConfig)
    table_size: int = 8192
    max_goals: int = 12
    ik_rounds: int = 3
    margin_mm: float = 0.0
    range_mm: float | None = 80.0
    verify_factor: int = 4
    verify_points: int | None = None
    verify_fcl_all: bool = False
    output_step_mm: float = 5.0
    output_points: int = 32
    repair_attempts: int = 2
    simplify: bool = True
    optimize: bool = False
    try_direct: bool = True


@dataclass(frozen=True)
class PlanResult:
    """Result of :func:`plan_to_target`.

    path : (K, 2n) configurations (rad, mm) from the start to the goal; consecutive states are
        joined by straight lines in joint space (rotations along the shorter arc). Empty (0, 2n)
        when there is no path.
    backbones : (K, m, 3) mm, scene frame — the planning model's backbone along the path.
    tip_path : (K, 3) mm, scene frame.
    target : (3,) mm, scene frame.
    tip_error_mm : planning model's tip distance to the target at the final configuration
        (nan without a path); tip_error_physics_mm : the same with the physics model.
    min_clearance_mm : smallest clearance (mm) over the verified states of the path: the exact
        FCL minimum when :func:`path_min_clearance` settles it within its budget, otherwise a
        valid lower bound of it (never more than the truth); nan without a path.
    timings : seconds per stage: setup (loading the model, scene and collision world, the
        workspace table and the start configuration: cached per process, so ~0 after the first
        plan), checks, ik, planning, simplification, verification, and total.
    planning_time_s : total minus setup (what a plan costs once the process is warm).
    counts : work done (states validated, edges, goals, IK evaluations, verification states...).
    """

    success: bool
    status: PlanStatus
    message: str
    path: np.ndarray
    backbones: np.ndarray
    tip_path: np.ndarray
    target: np.ndarray
    tip_error_mm: float
    tip_error_physics_mm: float
    min_clearance_mm: float
    planning_time_s: float
    timings: dict[str, float]
    counts: dict[str, int]
    planner: str
    seed: int
    robot: str
    model: str
    scene: str
    tolerance_mm: float
    time_limit_s: float

    def to_json(self) -> dict[str, Any]:
        """The DESIGN.md plan fields (plus diagnostics), JSON-ready (no NaN: null instead)."""
        return {
            "success": bool(self.success),
            "status": self.status.value,
            "message": self.message,
            "path": np.asarray(self.path, dtype=float).tolist(),
            "tip_path": np.asarray(self.tip_path, dtype=float).tolist(),
            "tip_error_mm": _num(self.tip_error_mm),
            "tip_error_physics_mm": _num(self.tip_error_physics_mm),
            "planning_time_s": _num(self.planning_time_s),
            "min_clearance_mm": _num(self.min_clearance_mm),
            "planner": self.planner,
            "seed": int(self.seed),
            "robot": self.robot,
            "model": self.model,
            "scene": self.scene,
            "target": [float(v) for v in self.target],
            "tolerance_mm": float(self.tolerance_mm),
            "time_limit_s": float(self.time_limit_s),
            "timings": {k: float(v) for k, v in self.timings.items()},
            "counts": {k: int(v) for k, v in self.counts.items()},
        }


def _num(v: float) -> float | None:
    return float(v) if v is not None and math.isfinite(float(v)) else None


# ---------------------------------------------------------------------- caches
_MODELS: dict[tuple, Any] = {}
_SCENES: dict[str, Any] = {}
_WORLDS: dict[tuple, tuple[weakref.ref, Any]] = {}


def resolve_model(spec, robot: Robot):
    """A shape model for ``spec`` (name, file or object), cached per (robot, name)."""
    from ctrplan.shape.models import load_model

    if not isinstance(spec, (str, os.PathLike)):
        return spec
    key = (robot, str(spec))
    model = _MODELS.get(key)
    if model is None:
        model = load_model(spec, robot)
        _MODELS[key] = model
    return model


def scene_by_name(spec: str | os.PathLike):
    """``load_scene(spec)``, cached per name/path in this process (meshes load slowly)."""
    from ctrplan.collision.scene import load_scene

    key = str(spec)
    scene = _SCENES.get(key)
    if scene is None:
        scene = _SCENES[key] = load_scene(key)
    return scene


def world_for(scene, margin_mm: float = 0.0):
    """The CollisionWorld of a scene (cached per scene object and margin)."""
    from ctrplan.collision.world import CollisionWorld

    key = (id(scene), float(margin_mm))
    hit = _WORLDS.get(key)
    if hit is not None and hit[0]() is scene:
        return hit[1]
    world = CollisionWorld(scene, margin_mm=margin_mm)
    _WORLDS[key] = (weakref.ref(scene), world)
    return world


def _scene_label(spec, scene) -> str:
    if isinstance(spec, (str, os.PathLike)):
        return str(spec)
    try:
        from ctrplan.collision.scene import list_scenes

        if scene.name in list_scenes():
            return scene.name
    except Exception:  # a stand-in scene object
        pass
    return str(getattr(scene, "path", "") or scene.name)


def _model_label(spec, model) -> str:
    if isinstance(spec, (str, os.PathLike)):
        return str(spec)
    return str(getattr(model, "name", type(model).__name__))


def check_target(target) -> np.ndarray:
    """A target as a finite (3,) float array, or :class:`InputError`."""
    try:
        t = np.asarray(target, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise InputError("--target", "", f"must be three numbers X,Y,Z (mm), got {target!r}") from None
    if t.shape != (3,):
        raise InputError("--target", "", f"must be three numbers X,Y,Z (mm), got {t.size}")
    if not np.all(np.isfinite(t)):
        raise InputError("--target", "", "must be finite numbers (mm)")
    return t


def _check_args(time_limit: float, tolerance_mm: float, seed: int) -> None:
    if not (isinstance(time_limit, (int, float)) and math.isfinite(time_limit) and time_limit > 0):
        raise InputError("--time", "", f"must be a positive number of seconds, got {time_limit!r}")
    if not (isinstance(tolerance_mm, (int, float)) and math.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise InputError("--tolerance", "", f"must be a positive number (mm), got {tolerance_mm!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError("--seed", "", f"must be a non-negative integer, got {seed!r}")


# ---------------------------------------------------------------------- main entry
def plan_to_target(
    robot: Robot | str,
    scene,
    target,
    model="learned",
    planner: str = "rrtconnect",
    time_limit: float = 5.0,
    seed: int = 0,
    tolerance_mm: float = 1.0,
    config: PlanConfig | None = None,
    world=None,
    start=None,
) -> PlanResult:
    """Plan a collision-free motion from the retracted configuration to put the tip at ``target``.

    Parameters
    ----------
    robot : Robot or shipped name / YAML path.
    scene : Scene or shipped name / scene folder.
    target : (3,) mm, scene frame.
    model : "learned", "physics", "rigid", a model file, or a shape model object. Planning,
        IK and verification use this model; the final tip error is also measured with physics.
    planner : one of :data:`ctrplan.planning.space.PLANNERS` (default RRTConnect).
    time_limit : seconds for the call without setup (IK, planning, verification; the planner
        gets what the earlier stages leave, at least half).
    seed : seeds numpy and OMPL; the same seed gives the same path (planners stop at the first
        solution unless ``config.optimize``).
    tolerance_mm : tip-to-target distance accepted (planning model).
    config : PlanConfig.
    world : a CollisionWorld to use instead of building one for the scene (with margin).
    start : (2n,) start configuration; default the retracted one (:func:`retracted_start`).

    Raises
    ------
    InputError
        Unknown robot, scene, model or planner; non-finite target; bad time limit or tolerance.
    """
    t_call = time.perf_counter()
    from ctrplan.planning import space as _space

    cfg = config or PlanConfig()
    _check_args(time_limit, tolerance_mm, seed)
    planner = _space.check_planner(planner)
    target = check_target(target)
    robot = load_robot(robot)
    scene_spec = scene
    if isinstance(scene, (str, os.PathLike)):
        scene = scene_by_name(scene)
    model_spec = model
    model = resolve_model(model, robot)
    if getattr(model, "robot", robot) != robot:
        raise InputError("--model", "", f"the model was made for robot {model.robot.name!r}, "
                         f"not {robot.name!r}")
    if world is None:
        world = world_for(scene, cfg.margin_mm)
    seed = int(seed)
    timings = {"setup": time.perf_counter() - t_call, "checks": 0.0, "ik": 0.0, "planning": 0.0,
               "simplification": 0.0, "verification": 0.0, "total": 0.0}
    counts: dict[str, int] = {}
    n = robot.n
    empty = dict(path=np.zeros((0, 2 * n)), backbones=np.zeros((0, cfg.output_points, 3)),
                 tip_path=np.zeros((0, 3)), tip_error_mm=math.nan, tip_error_physics_mm=math.nan,
                 min_clearance_mm=math.nan)
    meta = dict(target=target, planner=planner, seed=seed, robot=robot.name,
                model=_model_label(model_spec, model), scene=_scene_label(scene_spec, scene),
                tolerance_mm=float(tolerance_mm), time_limit_s=float(time_limit))

    vcfg = cfg.validator
    validator = BatchValidator(robot, model, world, vcfg)

    def finish(status: PlanStatus, message: str, **kw) -> PlanResult:
        timings["total"] = time.perf_counter() - t_call
        counts.update({f"validator_{k}": v for k, v in validator.counters.as_dict().items()})
        fields_ = {**empty, **kw}
        log.debug("plan: %s (%s) in %.3f s", status.value, message, timings["total"])
        return PlanResult(success=status is PlanStatus.SUCCESS, status=status, message=message,
                          planning_time_s=timings["total"] - timings["setup"], timings=dict(timings),
                          counts=dict(counts), **fields_, **meta)

    # 1. checks ------------------------------------------------------------------------
    t0 = time.perf_counter()
    target_base = scene.to_base(target[None])[0]
    reach = _ik.max_reach_mm(robot)
    far = float(np.linalg.norm(target_base)) - reach
    if far > tolerance_mm:
        timings["checks"] = time.perf_counter() - t0
        return finish(PlanStatus.UNREACHABLE,
                      f"the target is {far:.1f} mm beyond the robot's reach ({reach:.1f} mm from the base)")
    if start is None:
        t1 = time.perf_counter()
        start, adjusted = retracted_start(robot, validator, world)   # cached per model/world
        timings["setup"] += time.perf_counter() - t1
        t0 += time.perf_counter() - t1
        counts["start_rotated"] = int(adjusted)
    else:
        start = np.asarray(start, dtype=float).reshape(-1)
        if start.shape != (robot.dof,) or not validator.joint_valid(start[None])[0]:
            raise InputError("start", "", f"must be {robot.dof} values inside the joint constraints "
                             f"of robot {robot.name!r}")
    if not validator.states_valid(start[None])[0]:
        timings["checks"] = time.perf_counter() - t0
        return finish(PlanStatus.START_IN_COLLISION,
                      "the start configuration (retracted, any tube rotation) collides with the scene")
    blocked = target_blocked(scene, world, target, float(robot.tubes[0].od) / 2.0)
    timings["checks"] = time.perf_counter() - t0
    if blocked:
        return finish(PlanStatus.TARGET_IN_COLLISION, blocked)

    # 2. IK goals ----------------------------------------------------------------------
    t0 = time.perf_counter()
    table = _ik.workspace_table(model, cfg.table_size)               # cached per model
    timings["setup"] += time.perf_counter() - t0
    t0 = time.perf_counter()
    source = GoalSource(model, robot, validator, table, target_base, float(tolerance_mm), cfg,
                         np.random.default_rng([seed, 1]))
    goals = source.next()
    while len(goals) == 0 and source.rounds < cfg.ik_rounds:
        goals = source.next()
    timings["ik"] = time.perf_counter() - t0
    counts.update(ik_rounds=source.rounds, ik_reaching=source.reaching,
                  ik_evaluations=source.evaluations, goals=len(goals))
    if len(goals) == 0:
        if source.reaching == 0:
            return finish(PlanStatus.UNREACHABLE,
                          f"no configuration puts the tip within {tolerance_mm:g} mm of the target "
                          f"(best {source.best_error_mm:.2f} mm after {source.rounds} IK rounds)")
        if target_outside_lumen(scene, target):
            return finish(PlanStatus.TARGET_IN_COLLISION, "the target lies outside the lumen walls")
        return finish(PlanStatus.GOAL_IN_COLLISION,
                      f"{source.reaching} configurations reach the target but all of them collide")

    # 3-4. planning and simplification ---------------------------------------------------
    refresh_s = [0.0]

    def more_goals() -> np.ndarray:
        t = time.perf_counter()
        g = source.next()
        refresh_s[0] += time.perf_counter() - t
        return g

    budget = max(0.5 * time_limit,
                 time_limit - (time.perf_counter() - t_call - timings["setup"]))
    t0 = time.perf_counter()
    direct = _direct_path(validator, start, goals) if cfg.try_direct else None
    counts["direct"] = int(direct is not None)
    if direct is not None:
        outcome = _space.OmplOutcome("exact", direct, 0, 0.0, 0.0, len(goals))
    else:
        outcome = _space.solve(robot, validator, start, goals, planner=planner, time_limit=budget,
                               seed=seed, alpha_weight_mm=vcfg.alpha_weight_mm,
                               range_mm=cfg.range_mm, more_goals=more_goals,
                               simplify=cfg.simplify, optimize=cfg.optimize)
    # IK rounds run while planning (goal refresh) count as IK time.
    timings["ik"] += refresh_s[0]
    timings["planning"] = (time.perf_counter() - t0) - outcome.simplification_s - refresh_s[0]
    timings["simplification"] = outcome.simplification_s
    counts.update(goals=outcome.goals_used, ik_rounds=source.rounds, ik_reaching=source.reaching,
                  ik_evaluations=source.evaluations)
    counts["states_validated"] = validator.counters.states
    if outcome.path is None:
        return finish(PlanStatus.TIMEOUT, f"no collision-free path found in {budget:.2f} s "
                      f"({outcome.goals_used} goal configurations)")
    path = outcome.path
    if cfg.simplify and len(path) > 2:
        t0 = time.perf_counter()
        path = validator.shortcut(path)
        timings["simplification"] += time.perf_counter() - t0
    counts["states_validated"] = validator.counters.states

    # 5. exact verification (and repair) ---------------------------------------------------
    t0 = time.perf_counter()
    vres = vcfg.resolution_mm / max(1, cfg.verify_factor)
    vpoints = cfg.verify_points or vcfg.points
    check = validator.check_path(path, vres, points=vpoints, fcl_all=cfg.verify_fcl_all)
    attempts = 0
    while not check.ok and attempts < cfg.repair_attempts:
        attempts += 1
        path = _repair(robot, model, world, path, check.bad_segments, cfg, seed + attempts,
                       vres / (2 * attempts), budget=max(0.5, 0.25 * time_limit))
        if path is None:
            break
        check = validator.check_path(path, vres, points=vpoints, fcl_all=cfg.verify_fcl_all)
    timings["verification"] = time.perf_counter() - t0
    counts.update(verification_states=len(check.states) if path is not None else 0,
                  repairs=attempts, waypoints=0 if path is None else len(path))
    if path is None or not check.ok:
        bad = check.contact[check.first_bad] if check.first_bad >= 0 else ""
        return finish(PlanStatus.VERIFICATION_FAILED,
                      f"the path touches {bad or 'the scene'} when checked exactly at "
                      f"{vres:g} mm and could not be repaired")

    # Output: the path subdivided for display/execution, backbones in the scene frame.
    out_q = path
    if cfg.output_step_mm > 0:
        out_q, _ = interpolate_path(path, n, vcfg.alpha_weight_mm, cfg.output_step_mm)
    shape = model.shape(out_q, points=cfg.output_points)
    backbones = scene.to_scene(shape.points)
    tip_err = float(np.linalg.norm(shape.tip[-1] - target_base))
    tip_err_phys = tip_err
    if getattr(model, "name", "") != "physics":
        phys = resolve_model("physics", robot)
        tip_err_phys = float(np.linalg.norm(phys.shape(out_q[-1:], points=2).tip[0] - target_base))
    counts["path_states"] = len(out_q)
    t0 = time.perf_counter()
    min_clear, exact_calls = path_min_clearance(validator, world, check, vpoints)
    timings["verification"] += time.perf_counter() - t0
    counts["clearance_exact_states"] = exact_calls
    return finish(PlanStatus.SUCCESS, "ok", path=out_q, backbones=backbones,
                  tip_path=backbones[:, -1, :], tip_error_mm=tip_err,
                  tip_error_physics_mm=tip_err_phys, min_clearance_mm=min_clear)


def path_min_clearance(validator: BatchValidator, world, check, points: int | None,
                       batch: int = 16, max_pairs: int = 300) -> tuple[float, int]:
    """Smallest clearance (mm) over the verified states of a path, by branch and bound.

    The world's conservative clearance of every state is a lower bound of its FCL distance.
    States are taken in order of increasing bound and measured exactly
    (:meth:`CollisionWorld.clearance_bounded`, itself a branch and bound over capsule-mesh
    pairs) until the smallest distance found is no larger than the next state's bound: then it
    is the exact minimum. The work is capped at ``max_pairs`` FCL distance queries (about 2 ms
    each; a count, not a time, so the same path always gives the same value); if that does not
    settle it, the result is a valid lower bound, at least 0 (the states passed the exact
    collision check). Returns (value, states measured).
    """
    bounds = np.asarray(check.clearance_mm, dtype=float)
    if len(bounds) == 0:
        return math.nan, 0
    order = np.argsort(bounds, kind="stable")
    best = math.inf
    done, left = 0, int(max_pairs)
    while done < len(order):
        idx = order[done:done + batch]
        shape = validator.shapes(check.states[idx], points=points)
        values, used = world.clearance_bounded(shape, below=best, max_pairs=left)
        best = min(best, float(np.min(values)))
        done += len(idx)
        left -= used
        if done >= len(order) or best <= bounds[order[done]]:
            return max(0.0, best), done
        if left <= 0:
            break
    return max(0.0, min(best, float(bounds[order[done]]))), done


def _direct_path(validator: BatchValidator, start: np.ndarray, goals: np.ndarray,
                 tries: int = 4) -> np.ndarray | None:
    """Start -> goal as one straight edge, if one of the ``tries`` nearest goals allows it.

    In a tube-like lumen this is often the whole answer; it costs a few batched edge checks.
    """
    c = validator.config
    d = motion_mm(start[None], goals, validator.n, c.alpha_weight_mm)
    for k in np.argsort(d, kind="stable")[:tries]:
        if validator.edge_valid(start, goals[k]):
            return np.stack([start, goals[k]])
    return None


def _repair(robot, model, world, path: np.ndarray, bad_segments: list[int], cfg: PlanConfig,
            seed: int, resolution_mm: float, budget: float) -> np.ndarray | None:
    """Re-plan the segments that failed verification with a finer validator; None on failure."""
    from ctrplan.planning import space as _space

    strict = BatchValidator(robot, model, world, replace(cfg.validator, resolution_mm=resolution_mm))
    pieces: list[np.ndarray] = []
    last = 0
    for j in bad_segments:
        pieces.append(path[last:j])
        sub = _space.solve(robot, strict, path[j], path[j + 1][None], planner="rrtconnect",
                           time_limit=budget, seed=seed, alpha_weight_mm=cfg.validator.alpha_weight_mm,
                           range_mm=cfg.range_mm, simplify=cfg.simplify)
        if sub.path is None:
            log.debug("plan: repair of segment %d failed", j)
            return None
        pieces.append(sub.path[:-1])
        last = j + 1
    pieces.append(path[last:])
    return np.concatenate([p for p in pieces if len(p)], axis=0)
