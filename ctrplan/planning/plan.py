"""Plan to a target: IK goals, OMPL search, simplification, verification on two models.

:func:`plan_to_target` is the product's main job. It reads as its five stages (timed
separately):

1. **Checks** — the start (the retracted configuration, or the one given) collision-free, the
   target within reach (the tip can never be farther from the base than the longest tube), the
   target not inside anatomy.
2. **IK** — many seeds refined together on the planning model (:mod:`ctrplan.planning.ik`);
   solutions within ``tolerance_mm`` that are collision-free become OMPL goal states.
3. **Planning** — the straight edge to the nearest goals, else OMPL with the batched motion
   validator (:mod:`ctrplan.planning.space`); more goals are added after a slice without a
   solution.
4. **Simplification** — vertex reduction and shortcutting with the same validator; then
   **optimisation** for the objective (:mod:`ctrplan.planning.optimize`; ``clearance`` by
   default: the path and its goal configuration are moved away from the anatomy, every accepted
   iterate collision-free; ``first`` keeps the first solution). IK goals are handed to the
   planner in order of clearance for the ``clearance`` objective.
5. **Verification** — every state at ``resolution / verify_factor`` checked with exact verdicts
   on the planning model (a failing segment is re-planned with a finer validator), then again
   with the reference model (physics, or the calibrated model itself) at margin 0.

Safety. The planning model is made fit for collision checking
(:func:`planning_model_of`: no sensor registration, friction a pure function of q and the
direction of motion). Capsules are padded by the sagitta bound of the model's curvature bound
(they cover the continuous backbone) and by the margin (``PlanConfig.margin_mm``; ``None`` =
``auto``: the planning model's error bound, :func:`~ctrplan.shape.base.model_error_bound`).

Determinism. Search budgets are counts (states validated, IK rounds, simplifier rounds, FCL
distance queries); the time limit is only a cap, reported as ``time_cap_hit`` when it stopped
the search. The same seed gives the same path on any machine load unless the cap was hit.
"""

from __future__ import annotations

import logging
import math
import os
import time
from dataclasses import dataclass, field, replace
from enum import Enum
from typing import Any

import numpy as np

from ctrplan.errors import InputError
from ctrplan.objcache import Bounded, owned
from ctrplan.planning import hints as _hints
from ctrplan.planning import ik as _ik
from ctrplan.planning import optimize as _opt
from ctrplan.planning import stability as _stab
from ctrplan.planning.goals import (
    GoalSource,
    retracted_start,
    target_blocked,
    target_outside_lumen,
)
from ctrplan.planning.validator import (
    BatchValidator,
    PathCheck,
    ValidatorConfig,
    edge_direction,
    interpolate_path,
    motion_mm,
    unwrap_path,
)
from ctrplan.robot import Robot, load_robot

log = logging.getLogger("ctrplan")


class PlanStatus(str, Enum):
    """Outcome of :func:`plan_to_target`."""

    SUCCESS = "SUCCESS"
    UNREACHABLE = "UNREACHABLE"                  # no configuration puts the tip within tolerance
    TARGET_IN_COLLISION = "TARGET_IN_COLLISION"  # the target lies inside anatomy (or outside the lumen)
    START_IN_COLLISION = "START_IN_COLLISION"    # the start configuration collides
    GOAL_IN_COLLISION = "GOAL_IN_COLLISION"      # reachable, but every reaching configuration collides
    TIMEOUT = "TIMEOUT"                          # no collision-free path within the budget
    VERIFICATION_FAILED = "VERIFICATION_FAILED"  # the path failed an exact check and repair failed
    OUTSIDE_TOLERANCE = "OUTSIDE_TOLERANCE"      # a verified path, but its tip ends beyond tolerance_mm
    UNSTABLE_ONLY = "UNSTABLE_ONLY"              # paths exist only through a fold or below the stability margin
    INPUT_ERROR = "INPUT_ERROR"                  # bad input (batch jobs; plan_to_target raises InputError)


@dataclass(frozen=True)
class PlanConfig:
    """Settings of :func:`plan_to_target` (the defaults are what the benchmarks use).

    validator : edge resolution, backbone points, rotation weight (see ValidatorConfig).
    ik : IK settings; ``ik.seeds`` seeds per round.
    table_size : workspace samples used to seed IK (cached per model).
    max_goals : goal states handed to OMPL per round.
    ik_rounds : IK rounds (each on the next-nearest workspace samples) before giving up on
        finding a collision-free goal; later rounds also run while planning, between slices.
    margin_mm : clearance (mm) added to every capsule while planning and in the planning
        model's verification; ``None`` = auto: the planning model's error bound (p99 of its
        held-out deviation; 0 for physics). The reference re-check uses margin 0.
    sagitta : pad capsules by the sagitta bound of the model's curvature bound (False checks
        only the chords between backbone samples: not safe, for comparisons).
    max_states : the search budget in states validated (deterministic); the time limit is a cap.
    repair_states : the same for each repair of a segment that failed verification.
    range_mm : longest edge the tree planners add (metric mm); None = OMPL's default.
    verify_factor : verification resolution is ``validator.resolution_mm / verify_factor``.
    verify_points : backbone points in the verification (None = validator.points).
    verify_fcl_all : send every verification state to FCL (``check_exact``). By default the
        world's ``check`` is used: its verdicts are FCL's too, the distance-field prefilter only
        skips FCL where its conservative bound proves a state free or colliding.
    reference : re-verify the final path with this model at margin 0: "physics" (default; a
        calibrated model is re-verified with itself), or None to skip.
    clearance_pairs : FCL distance queries allowed for each reported minimum clearance.
    output_step_mm : the returned path is subdivided so states are at most this far apart
        (metric mm); 0 returns the simplified waypoints only.
    output_points : backbone points per returned backbone.
    repair_attempts : re-planning rounds for segments that fail verification.
    optimize : let anytime planners (RRT*, BIT*) use the whole budget.
    try_direct : before OMPL, try the straight edge from the start to the nearest goals
        (``planner`` is then ``"direct"``); False always runs the planner.
    objective : what the found path is optimised for: ``"clearance"`` (default: keep as far
        from the anatomy as the robot allows; Kuntz et al.'s integral of 1/clearance),
        ``"length"`` (short and smooth) or ``"first"`` (the first solution, simplified).
    optimizer : the local optimiser's settings (a count of step trials, not a time).
    goals_by_clearance : with the clearance objective, hand IK goals to the planner in order of
        their (estimated) clearance instead of their tip error.
    approach : with a margin at the tip (a model's error bound, or a stated margin), a target
        nearer the anatomy than the tip's radius + margin is approached instead of refused: the
        goal moves into the lumen, along the distance field's gradient, until the tip keeps its
        margin, by at most that margin (the model's own error there). ``goal_shift_mm`` in
        plan.json says by how much; ``tip_error_mm`` stays the distance to the target asked
        for, and the tolerance applies to it: a shift that leaves the tip farther than
        ``tolerance_mm`` from the target gives ``OUTSIDE_TOLERANCE``, not SUCCESS.
    """

    validator: ValidatorConfig = field(default_factory=ValidatorConfig)
    ik: _ik.IKConfig = field(default_factory=_ik.IKConfig)
    table_size: int = 8192
    max_goals: int = 12
    ik_rounds: int = 3
    margin_mm: float | None = None
    sagitta: bool = True
    max_states: int = 300_000
    repair_states: int = 50_000
    range_mm: float | None = 80.0
    verify_factor: int = 4
    verify_points: int | None = None
    verify_fcl_all: bool = False
    reference: str | None = "physics"
    clearance_pairs: int = 300
    output_step_mm: float = 5.0
    output_points: int = 32
    repair_attempts: int = 2
    simplify: bool = True
    optimize: bool = False
    try_direct: bool = True
    objective: str = "clearance"
    optimizer: _opt.OptimizeConfig = field(default_factory=_opt.OptimizeConfig)
    goals_by_clearance: bool = True
    approach: bool = True

    def __post_init__(self) -> None:
        check_objective(self.objective)
        if self.margin_mm is not None and not (math.isfinite(self.margin_mm) and self.margin_mm >= 0):
            raise InputError("--margin", "", f"must be a number >= 0 (mm) or auto, got {self.margin_mm!r}")
        if not (isinstance(self.max_states, int) and self.max_states > 0):
            raise InputError("max_states", "", f"must be a positive integer, got {self.max_states!r}")


@dataclass(frozen=True)
class PlanResult:
    """Result of :func:`plan_to_target`.

    path : (K, 2n) configurations (rad, mm) from the start to the goal; rotations are
        continuous (unwrapped), so linear interpolation between consecutive states is exactly
        the motion that was verified. Empty (0, 2n) when there is no path.
    backbones : (K, m, 3) mm, scene frame — the planning model's backbone along the path.
    tip_path : (K, 3) mm, scene frame.
    target : (3,) mm, scene frame.
    tip_error_mm : planning model's tip distance to the target at the final configuration
        (nan without a path); tip_error_physics_mm : the same with the physics model.
    min_clearance_mm : smallest distance (mm) from the tube (capsules of radius + sagitta
        bound, margin not included) to the anatomy over the verified states, planning model;
        ``min_clearance_exact`` says whether it is FCL's exact minimum (True) or a lower bound
        (False: the distance-query budget did not settle it). nan without a path.
    min_clearance_reference_mm, min_clearance_reference_exact : the same for the reference
        model (``reference_model``: physics, or the calibrated model) at margin 0.
    planner : what solved it: the OMPL planner's name, or ``"direct"`` for the straight edge.
    margin_mm : the margin used (mm); ``margin_auto`` whether it came from the model's bound.
    time_cap_hit : the wall-clock cap stopped the search (the result may depend on load).
    timings : seconds per stage: setup (loading the model, scene and collision world, the
        workspace table and the start configuration: cached per process, so ~0 after the first
        plan), checks, ik, planning, simplification, verification, and total.
    planning_time_s : total minus setup (what a plan costs once the process is warm).
    counts : work done (states validated, edges, goals, IK evaluations, verification states...).
    objective : what the path was optimised for (``clearance``, ``length``, ``first``);
        objective_value : its value on the returned path: for ``clearance`` the integral of
        1/clearance over the metric arc length (dimensionless, smaller is better; clearances
        from ``clearance_profile``), for ``length`` the metric length (mm), nan for ``first``.
    clearance_profile : (K,) mm, one per ``path`` state: the planning model's tube (capsules
        of radius + sagitta bound, margin not included) to the anatomy, estimated from the
        distance fields (the interpolated distance to the nearest surface sample; within about
        the field's sample spacing of FCL's distance; ``min_clearance_mm`` is FCL's).
    calibrated : whether the planning model carries an error bound measured on a robot
        (``error_bound: measured``: ``diagnose`` output, a model trained with ``--real`` on
        measurements; :func:`~ctrplan.shape.error_bounds.is_calibrated`); if not, clearances
        are relative to the nominal model only.
    surrogate_error : for a surrogate (a network fitted to a simulated model, such as the
        shipped ``learned`` one, ``error_bound: surrogate``): its held-out deviation from that
        model, ``{p50, p95, p99, max}`` mm and ``against`` (the simulated data); the margin
        ``--margin auto`` pads with, never called calibrated. None for other models.
    measured_insertion, outside_measured_states : the calibrated model's measured insertions
        ({"min": [n], "max": [n]} mm, where its error bound was measured) and the number of
        ``path`` states inserting a tube beyond them by more than
        :data:`~ctrplan.shape.error_bounds.MEASURED_SLACK_MM`
        (the margin is extrapolated there); None for a model without them.
    goal_shift_mm, goal : where the tip was planned to when a target nearer the anatomy than
        the tip's radius + margin was approached (:attr:`PlanConfig.approach`): the goal
        (scene frame, mm) and its distance from ``target`` (0.0 and None otherwise). The
        tolerance applies to ``target``, not to the moved goal: a tip that ends farther than
        ``tolerance_mm`` from the target is ``OUTSIDE_TOLERANCE`` (not a success; the verified
        path is kept).
    start_rotated : the retracted start collided, so its tube rotations were changed (to the
        free rotations with the most clearance; the start used is ``path[0]``).
    branch, stability : per ``path`` state, the equilibrium branch the robot is on (reached by
        continuation from the start: 0 the model finds one stable equilibrium there, +1 / -1
        the one of two with the larger / smaller base torsion of tube 1) and its elastic
        stability (det of the shooting Jacobian, normalised: 1 without curvature interaction,
        0 at a fold; :mod:`ctrplan.shape.branches`), of the planning model, or of the reference
        model where only that one is compliant mechanics; None when neither is (rigid,
        learned, loaded).
    duration_s : the duration (s) of the time-parameterised trajectory along ``path`` within
        the robot's actuator limits (:func:`ctrplan.planning.trajectory.plan_trajectory`);
        nan (null in plan.json) until one is made.
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
    min_clearance_exact: bool = False
    min_clearance_reference_mm: float = math.nan
    min_clearance_reference_exact: bool = False
    reference_model: str = ""
    margin_mm: float = 0.0
    margin_auto: bool = False
    curvature_bound_per_mm: float = 0.0
    time_cap_hit: bool = False
    requested_planner: str = ""
    objective: str = "clearance"
    objective_value: float = math.nan
    clearance_profile: np.ndarray = field(default_factory=lambda: np.zeros(0))
    calibrated: bool = False
    goal_shift_mm: float = 0.0
    goal: list | None = None
    robot_spec: dict | None = None
    measured_insertion: dict | None = None
    outside_measured_states: int | None = None
    surrogate_error: dict | None = None
    start_rotated: bool = False
    branch: list | None = None
    stability: list | None = None
    duration_s: float = math.nan

    def to_json(self) -> dict[str, Any]:
        """The plan.json fields of docs/conventions.md (plus diagnostics), JSON-ready (no NaN: null instead)."""
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
            "min_clearance_exact": bool(self.min_clearance_exact),
            "min_clearance_reference_mm": _num(self.min_clearance_reference_mm),
            "min_clearance_reference_exact": bool(self.min_clearance_reference_exact),
            "reference_model": self.reference_model,
            "margin_mm": float(self.margin_mm),
            "margin_auto": bool(self.margin_auto),
            "curvature_bound_per_mm": float(self.curvature_bound_per_mm),
            "planner": self.planner,
            "requested_planner": self.requested_planner,
            "objective": self.objective,
            "objective_value": _num(self.objective_value),
            # the trajectory's duration (ctrplan.planning.trajectory), null when none was made
            "duration_s": _num(self.duration_s),
            "clearance_profile": [_num(v) for v in np.asarray(self.clearance_profile, dtype=float)],
            # per path state: the equilibrium branch and its stability (None: not tracked)
            "branch": list(self.branch) if self.branch is not None else [None] * len(self.path),
            "stability": list(self.stability) if self.stability is not None else [None] * len(self.path),
            "calibrated": bool(self.calibrated),
            "surrogate_error": None if self.surrogate_error is None else dict(self.surrogate_error),
            "start_rotated": bool(self.start_rotated),
            "goal_shift_mm": float(self.goal_shift_mm),
            "goal": None if self.goal is None else [float(v) for v in self.goal],
            "measured_insertion": self.measured_insertion,
            "outside_measured_states": self.outside_measured_states,
            "seed": int(self.seed),
            "robot": self.robot,
            # the robot itself (tube values + digest): view and re-checks use it, never a look-up
            **({} if self.robot_spec is None else robot_record_of(self.robot_spec)),
            "model": self.model,
            "scene": self.scene,
            "target": [float(v) for v in self.target],
            "tolerance_mm": float(self.tolerance_mm),
            "time_limit_s": float(self.time_limit_s),
            "time_cap_hit": bool(self.time_cap_hit),
            "timings": {k: float(v) for k, v in self.timings.items()},
            "counts": {k: int(v) for k, v in self.counts.items()},
        }


def check_objective(objective) -> str:
    """An objective name (``clearance``, ``length``, ``first``) or :class:`InputError`."""
    key = str(objective).strip().lower()
    if key not in _opt.OBJECTIVES:
        raise InputError("--objective", "", f"must be one of {', '.join(_opt.OBJECTIVES)}, "
                         f"got {objective!r}")
    return key


def robot_record_of(spec: dict) -> dict[str, Any]:
    """``robot_spec`` and ``robot_sha256`` for plan.json (:func:`ctrplan.robot.robot_record`)."""
    from ctrplan.robot import robot_digest

    return {"robot_spec": spec, "robot_sha256": robot_digest(spec)}


def _num(v: float) -> float | None:
    return float(v) if v is not None and math.isfinite(float(v)) else None


# ---------------------------------------------------------------------- caches
# Nothing here keeps alive what the caller dropped (a long-running service loads scenes per
# request): models and scenes looked up by name are kept in small LRU caches, and what is
# derived from an object (its world, its planning model) is cached on that object
# (:mod:`ctrplan.objcache`), freed with it.
_MODELS = Bounded(8)
_SCENES = Bounded(4)


def resolve_model(spec, robot: Robot):
    """A shape model for ``spec`` (name, file or object), cached per (robot, name) (the 8 most
    recently used)."""
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
    """``load_scene(spec)``, cached per name/path in this process (meshes load slowly; the 4
    most recently used)."""
    from ctrplan.collision.scene import load_scene

    key = str(spec)
    scene = _SCENES.get(key)
    if scene is None:
        scene = _SCENES[key] = load_scene(key)
    return scene


def world_for(scene, margin_mm=0.0, curvature_per_mm: float = 0.0):
    """A CollisionWorld of a scene with this margin and curvature bound, over the scene's exact
    models and distance fields (built once per scene object and cached on it).
    margin_mm : a number or an ErrorProfile (:func:`ctrplan.shape.error_bounds.auto_margin`)."""
    from ctrplan.collision.world import CollisionWorld

    # The scene caches the geometry (exact models, fields), not the world: a world refers to
    # its scene, and a scene -> world -> scene cycle would keep both (and their memory) alive
    # until a full garbage collection. Worlds themselves are cheap.
    cache = owned(scene)
    geometry = cache.get("world_geometry") if cache is not None else None
    world = CollisionWorld(scene, margin_mm=margin_mm, curvature_per_mm=curvature_per_mm,
                           geometry=geometry)
    if cache is not None:
        cache["world_geometry"] = world.geometry
    return world


class _RowwiseModel:
    """A calibrated model whose friction depends on the order of the rows, made a pure function
    of each row (every row its own motion): the stand-in for ``planning_model()`` on models
    that do not have it yet."""

    needs_direction = False

    def __init__(self, inner):
        self.inner = inner
        self.robot = inner.robot
        self.name = inner.name
        self.effects = getattr(inner, "effects", None)
        self.error_quantiles = getattr(inner, "error_quantiles", None)
        self.error_profile = getattr(inner, "error_profile", None)
        self.error_bound = getattr(inner, "error_bound", None)
        self.measured_insertion = getattr(inner, "measured_insertion", None)

    def shape(self, q, points: int = 20):
        q = np.atleast_2d(np.asarray(q, dtype=float))
        return self.inner.shape(q, points=points, sweep=np.arange(len(q)))

    def backbone(self, q, points: int = 20):
        return self.shape(q, points).points


def planning_model_of(model):
    """The model fit for collision checking: ``model.planning_model()`` when it has one (no
    sensor registration, friction a pure function of q and the direction of motion); for a
    calibrated model without it, the same effects without ``registration`` and with each row
    its own motion; otherwise the model itself. Cached on the model object."""
    cache = owned(model)
    hit = cache.get("planning_model") if cache is not None else None
    if hit is not None:
        return model if hit is _SAME else hit
    make = getattr(model, "planning_model", None)
    if callable(make):
        pm = make()
    else:
        effects = getattr(model, "effects", None)
        pm = model
        if isinstance(effects, dict) and hasattr(model, "with_effects") and (
                "registration" in effects or "friction" in effects):
            pm = model.with_effects({k: v for k, v in effects.items() if k != "registration"})
            if getattr(model, "error_quantiles", None) is not None:
                pm.error_quantiles = model.error_quantiles
            if getattr(model, "error_profile", None) is not None:
                pm.error_profile = model.error_profile
            pm.error_bound = getattr(model, "error_bound", None)
            if "friction" in effects:
                pm = _RowwiseModel(pm)
    if cache is not None:    # (the model itself is not stored in its own cache: no cycle)
        cache["planning_model"] = _SAME if pm is model else pm
    return pm


_SAME = object()


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
    if np.max(np.abs(t)) > MAX_TARGET_MM:    # (also keeps the distances below finite)
        raise InputError("--target", "", f"{float(np.max(np.abs(t))):.4g} mm is outside the plausible "
                         f"range of a scene coordinate (|X|, |Y|, |Z| <= {MAX_TARGET_MM:g} mm)")
    return t


#: Largest target coordinate (mm) accepted: scenes are at most 2 m across.
MAX_TARGET_MM = 1e6


def _check_args(time_limit: float, tolerance_mm: float, seed: int) -> None:
    if not (isinstance(time_limit, (int, float)) and math.isfinite(time_limit) and time_limit > 0):
        raise InputError("--time", "", f"must be a positive number of seconds, got {time_limit!r}")
    if not (isinstance(tolerance_mm, (int, float)) and math.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise InputError("--tolerance", "", f"must be a positive number (mm), got {tolerance_mm!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InputError("--seed", "", f"must be a non-negative integer, got {seed!r}")


# ---------------------------------------------------------------------- main entry
@dataclass
class _Run:
    """Everything one :func:`plan_to_target` call works with (built by :func:`_prepare`)."""

    robot: Robot
    scene: Any
    target: np.ndarray
    target_base: np.ndarray
    model: Any                  # the planning model
    reference: Any              # the reference model (None: the planning model itself)
    world: Any                  # margin + sagitta
    validator: BatchValidator
    cfg: PlanConfig
    planner: str
    seed: int
    tolerance_mm: float
    time_limit: float
    t_call: float
    margin_mm: Any              # float or ErrorProfile
    margin_auto: bool
    curvature: float
    meta: dict
    timings: dict = field(default_factory=dict)
    counts: dict = field(default_factory=dict)
    deadline: float = math.inf
    time_cap_hit: bool = False
    goal_base: np.ndarray | None = None   # where the tip is planned to (None: target_base)
    start_branch: int | None = None       # the branch given with the start (Start.branch)
    start_uz: dict = field(default_factory=dict)   # id(model) -> the start's equilibrium

    @property
    def goal(self) -> np.ndarray:
        """The tip's goal in the base frame: the target, or where it was moved to keep the
        margin (:attr:`PlanConfig.approach`)."""
        return self.target_base if self.goal_base is None else self.goal_base

    def clock(self, stage: str, t0: float) -> None:
        self.timings[stage] = self.timings.get(stage, 0.0) + time.perf_counter() - t0

    def finish(self, status: PlanStatus, message: str, **kw) -> PlanResult:
        self.timings["total"] = time.perf_counter() - self.t_call
        self.counts.update({f"validator_{k}": v for k, v in self.validator.counters.as_dict().items()})
        n = self.robot.n
        fields_ = dict(path=np.zeros((0, 2 * n)), backbones=np.zeros((0, self.cfg.output_points, 3)),
                       tip_path=np.zeros((0, 3)), tip_error_mm=math.nan,
                       tip_error_physics_mm=math.nan, min_clearance_mm=math.nan)
        fields_.update(kw)
        rng = self.meta.get("measured_insertion")
        if rng is not None and len(fields_["path"]):
            from ctrplan.shape.error_bounds import measured_text, outside_measured

            out = outside_measured(fields_["path"], rng, n)
            fields_["outside_measured_states"] = out
            if out:
                log.warning("%d of %d path states insert a tube beyond the insertions the model's "
                            "error bound was measured on (%s): the margin is extrapolated there; "
                            "measure the robot over those insertions", out,
                            len(fields_["path"]), measured_text(rng))
        log.debug("plan: %s (%s) in %.3f s", status.value, message, self.timings["total"])
        return PlanResult(success=status is PlanStatus.SUCCESS, status=status, message=message,
                          planning_time_s=self.timings["total"] - self.timings["setup"],
                          timings=dict(self.timings), counts=dict(self.counts),
                          time_cap_hit=self.time_cap_hit, **fields_, **self.meta)


class _Stop(Exception):
    """A stage ended the plan (carries the result)."""

    def __init__(self, result: PlanResult):
        self.result = result


def plan_to_target(
    robot: Robot | str,
    scene,
    target,
    model="physics",
    planner: str = "rrtconnect",
    time_limit: float = 5.0,
    seed: int = 0,
    tolerance_mm: float = 1.0,
    config: PlanConfig | None = None,
    world=None,
    start=None,
    objective: str | None = None,
) -> PlanResult:
    """Plan a collision-free motion from the start configuration to put the tip at ``target``.

    Parameters
    ----------
    robot : Robot or shipped name / YAML path.
    scene : Scene or shipped name / scene folder.
    target : (3,) mm, scene frame.
    model : "physics" (default: its own reference, margin 0), "learned" (an uncalibrated
        surrogate of the physics model; plans with its surrogate error as margin: ~1.7 mm for
        the shipped seed1 network, so targets closer than that to the anatomy are approached
        or refused), "rigid", a model file, or a shape model object. Planning,
        IK and the first verification use its planning model (:func:`planning_model_of`);
        the final path is re-verified with ``config.reference`` (physics; a calibrated model
        with itself) and the final tip error is also measured with physics.
    planner : one of :data:`ctrplan.planning.space.PLANNERS` (default RRTConnect).
    time_limit : a wall-clock cap (s) for the call without setup; the search budget is
        ``config.max_states`` states validated, so a seed's result does not depend on load
        unless the cap is hit (``time_cap_hit``).
    seed : seeds numpy and OMPL; the same seed gives the same path (planners stop at the first
        solution unless ``config.optimize``).
    tolerance_mm : tip-to-target distance accepted (planning model).
    config : PlanConfig.
    world : a CollisionWorld to use instead of building one for the scene (it then carries the
        margin and curvature bound; ``config.margin_mm`` is only reported).
    start : (2n,) start configuration, or None / "retracted" for the retracted one
        (:func:`retracted_start`), or a :class:`~ctrplan.planning.stability.Start` (the
        configuration with the branch the robot is on there; needed where the model finds two
        stable equilibria at the start, e.g. ``start_from_plan("plan.json", robot)``: the last
        state of an earlier plan).
    objective : ``"clearance"`` (the default of :class:`PlanConfig`), ``"length"`` or
        ``"first"``; None uses ``config.objective``.

    Raises
    ------
    InputError
        Unknown robot, scene, model or planner; non-finite target; bad time limit, tolerance,
        margin or start.
    """
    if objective is not None:
        config = replace(config or PlanConfig(), objective=check_objective(objective))
    run = _prepare(robot, scene, target, model, planner, time_limit, seed, tolerance_mm,
                   config, world)
    try:
        start = _stage_checks(run, start)                              # 1. checks
        source, goals = _stage_ik(run)                                 # 2. IK goals
        path, solver = _stage_planning(run, start, source, goals)      # 3. planning
        path = _stage_simplification(run, path)                        # 4. simplification
        optimized = _stage_optimization(run, path)                     #    + objective
        check, ref_check, path = _verify_optimized(run, path, optimized)  # 5. verification
    except _Stop as stop:
        return stop.result
    return _output(run, path, solver, check, ref_check)


def _prepare(robot, scene, target, model, planner, time_limit, seed, tolerance_mm, config,
             world) -> _Run:
    """Inputs checked, models, scene, collision world and validator (cached per process)."""
    t_call = time.perf_counter()
    from ctrplan.collision.capsules import curvature_bound
    from ctrplan.planning import space as _space
    from ctrplan.shape.error_bounds import auto_margin, is_calibrated, margin_peak, surrogate_error

    cfg = config or PlanConfig()
    _check_args(time_limit, tolerance_mm, seed)
    requested = _space.check_planner(planner)
    target = check_target(target)
    robot = load_robot(robot)
    scene_spec = scene
    if isinstance(scene, (str, os.PathLike)):
        scene = scene_by_name(scene)
    model_spec = model
    given = resolve_model(model, robot)
    if getattr(given, "robot", robot) != robot and not _same_tubes(given.robot, robot):
        raise InputError("--model", "", f"the model was made for robot {given.robot.name!r}, "
                         f"not {robot.name!r}")
    pmodel = planning_model_of(given)
    try:
        auto = cfg.margin_mm is None
        margin = auto_margin(pmodel) if auto else float(cfg.margin_mm)   # number or profile
    except ValueError as exc:
        raise InputError("--margin", "", f"auto: {exc}") from None
    curvature = curvature_bound(pmodel) if cfg.sagitta else 0.0
    if world is None:
        world = world_for(scene, margin, curvature)
    # The reference re-check: physics at margin 0; a calibrated model is its own reference
    # (re-checked at margin 0 when planning used a margin); the planning model itself needs
    # no second check (its margin-padded check implies the margin-0 one). A calibrated model
    # planned without a margin (no error bound in its file, or --margin 0) gets the physics
    # re-check as its second check.
    reference, ref_label = None, ""
    if cfg.reference is not None:
        if (isinstance(getattr(given, "effects", None), dict) and cfg.reference == "physics"
                and margin_peak(margin) > 0):
            ref_label = _model_label(model_spec, given)
            reference = pmodel
        else:
            ref_label = str(cfg.reference)
            if getattr(pmodel, "name", "") != cfg.reference or margin_peak(margin) > 0:
                reference = planning_model_of(resolve_model(cfg.reference, robot))
    meta = dict(target=target, planner=requested, requested_planner=requested, seed=int(seed),
                robot=robot.name, robot_spec=robot.to_dict(), model=_model_label(model_spec, given),
                scene=_scene_label(scene_spec, scene), tolerance_mm=float(tolerance_mm),
                time_limit_s=float(time_limit), margin_mm=margin_peak(margin), margin_auto=auto,
                curvature_bound_per_mm=float(curvature), reference_model=ref_label,
                objective=cfg.objective, calibrated=is_calibrated(given) or is_calibrated(pmodel),
                surrogate_error=surrogate_error(given) or surrogate_error(pmodel),
                measured_insertion=(getattr(given, "measured_insertion", None)
                                    or getattr(pmodel, "measured_insertion", None)))
    run = _Run(robot=robot, scene=scene, target=target, target_base=scene.to_base(target[None])[0],
               model=pmodel, reference=reference, world=world,
               validator=BatchValidator(robot, pmodel, world, cfg.validator), cfg=cfg,
               planner=requested, seed=int(seed), tolerance_mm=float(tolerance_mm),
               time_limit=float(time_limit), t_call=t_call, margin_mm=margin, margin_auto=auto,
               curvature=curvature, meta=meta)
    run.timings = {"setup": time.perf_counter() - t_call, "checks": 0.0, "ik": 0.0,
                   "planning": 0.0, "simplification": 0.0, "optimization": 0.0,
                   "verification": 0.0, "total": 0.0}
    return run


def _same_tubes(a: Robot, b: Robot) -> bool:
    return a.n == b.n and np.allclose(a.lengths, b.lengths)


def _start_collision_hint(robot, validator, start) -> str:
    """What the user can do about a start configuration in collision: where it touches, how
    deep, how far the start reaches past the base and the outer tube's radius (the base must
    lie inside the lumen by more than that radius, and the lumen must hold the start)."""
    try:
        _, clearance, contact = validator.check_states(start[None], exact=True, joints=False)
        points = validator.shapes(start[None]).points[0]
    except Exception:  # the hint is a courtesy: never let it hide the status itself
        return ""
    reach = float(np.linalg.norm(points - points[0], axis=1).max())
    radius = float(max(t.od for t in robot.tubes)) / 2.0
    mesh = str(contact[0]) or "the anatomy"
    depth = float(clearance[0])
    where = f" ({-depth:.2f} mm into {mesh})" if np.isfinite(depth) and depth < 0 else ""
    return (f"{where}; it reaches {reach:.1f} mm past the base with an outer radius of "
            f"{radius:.2f} mm: place base_pose inside the lumen by more than that radius, with "
            f"room for the start ahead of it (check it with `ctrplan check`), or give --start")


def _start_equilibria(run: _Run, start: np.ndarray) -> str:
    """The equilibrium the robot is on at the start, for the planning model and the reference
    model where they track branches (InputError for a bistable start without its branch),
    remembered by the validator. Returns why the start is below the stability margin, or ""."""
    from ctrplan.shape.branches import tracks_branches

    for model in (run.model, run.reference):
        if model is not None and tracks_branches(model) and id(model) not in run.start_uz:
            run.start_uz[id(model)] = _stab.resolve_start(model, start, run.start_branch)
    tracker = run.validator.tracker
    if tracker is None:
        return ""
    uz = run.start_uz[id(run.model)]
    tracker.register(start[None], uz[None], anchor=True)
    at = tracker.states(start[None], 2, np.ones((1, run.robot.dof), dtype=np.int8)
                        if run.validator.directional else None, uz[None])
    if not at.shape.ok[0] and at.continued[0]:
        return (f"the start's elastic stability {float(at.stability[0]):.3g} is below the "
                f"stability margin {tracker.margin:g} (lower it with --stability-margin)")
    return ""


def _start_free(validator: BatchValidator, start: np.ndarray, uz0) -> bool:
    """Whether the start is collision-free (on its equilibrium ``uz0`` where known)."""
    if uz0 is None or validator.tracker is None:
        return bool(validator.states_valid(start[None])[0])
    d = np.ones((1, len(start)), dtype=np.int8) if validator.directional else None
    shape = validator.shapes(start[None], direction=d, uz0=np.asarray(uz0)[None])
    return bool(validator.joint_valid(start[None])[0]) and not bool(
        np.asarray(validator.plan_world.collides(shape))[0])


def _stage_checks(run: _Run, start) -> np.ndarray:
    """Stage 1: reach, start configuration, target. Returns the start (2n,)."""
    t0 = time.perf_counter()
    robot, validator = run.robot, run.validator
    reach = _ik.max_reach_mm(robot)
    far = float(np.linalg.norm(run.target_base)) - reach
    if far > run.tolerance_mm:
        run.clock("checks", t0)
        raise _Stop(run.finish(PlanStatus.UNREACHABLE, f"the target is {far:.1f} mm beyond the "
                               f"robot's reach ({reach:.1f} mm from the base)"))
    retracted = start is None or (isinstance(start, str) and start == "retracted")
    if retracted:
        t1 = time.perf_counter()
        start, adjusted = retracted_start(robot, validator, run.world)  # cached per model/world
        run.timings["setup"] += time.perf_counter() - t1
        t0 += time.perf_counter() - t1
        run.counts["start_rotated"] = int(adjusted)
        run.meta["start_rotated"] = bool(adjusted)
    else:
        if isinstance(start, _stab.Start):
            run.start_branch, start = start.branch, start.q
        start = check_start(start, robot, validator)
    # The cap counts from here: setup (loading, caches) is not part of the plan's time.
    run.deadline = time.perf_counter() + run.time_limit
    unstable = _start_equilibria(run, start)
    if unstable:
        run.clock("checks", t0)
        raise _Stop(run.finish(PlanStatus.UNSTABLE_ONLY, unstable))
    if not _start_free(validator, start, run.start_uz.get(id(run.model))):
        run.clock("checks", t0)
        which = "retracted, any tube rotation" if retracted else "given with --start"
        raise _Stop(run.finish(PlanStatus.START_IN_COLLISION,
                               f"the start configuration ({which}) collides with the scene"
                               + (_hints.margin_start_hint(
                                   run, start, retracted,
                                   lambda: world_for(run.scene, 0.0, run.curvature))
                                  or _start_collision_hint(robot, validator, start))))
    tip_radius = float(robot.tubes[0].od) / 2.0
    blocked = target_blocked(run.scene, run.world, run.target, tip_radius)
    if blocked and run.cfg.approach:
        moved = _approach_goal(run, tip_radius)
        if moved is not None:
            blocked = ""
    run.clock("checks", t0)
    if blocked:
        raise _Stop(run.finish(PlanStatus.TARGET_IN_COLLISION, blocked))
    return start


def _tip_margin(run: _Run) -> float:
    """The margin (mm) the tip's capsule carries: the profile's value at the tip, or the
    uniform margin."""
    from ctrplan.shape.error_bounds import ErrorProfile

    m = run.margin_mm
    if isinstance(m, ErrorProfile):
        return float(m.at(1.0))
    return float(m or 0.0)


def _approach_goal(run: _Run, tip_radius: float, steps: int = 48) -> np.ndarray | None:
    """Move the goal from a target nearer the anatomy than ``tip_radius`` + the tip's margin
    into the lumen along the distance field's gradient (central differences), until the
    tip's probe is free in the padded world, by at most the tip's margin. Returns the goal in
    the scene frame (and sets ``run.goal_base``), or None (no margin, no field, or not free
    within the allowed shift). Deterministic: a fixed number of steps."""
    from ctrplan.planning.optimize import FieldClearance

    allowed = _tip_margin(run)
    if allowed <= 0 or not getattr(run.world, "fields", None):
        return None
    field_ = FieldClearance(run.world)
    target = np.asarray(run.target, dtype=float)
    p = target.copy()
    h = 0.05
    eye = np.eye(3)
    step = allowed / 8.0
    for _ in range(steps):
        if not target_blocked(run.scene, run.world, p, tip_radius):
            break
        probes = np.concatenate([p + h * eye, p - h * eye])
        d = field_.point_distance(probes)
        if not np.all(np.isfinite(d)):
            return None
        g = (d[:3] - d[3:]) / (2 * h)
        norm = float(np.linalg.norm(g))
        if norm < 1e-9:
            return None
        q = p + step * g / norm
        if np.linalg.norm(q - target) > allowed:
            return None
        p = q
    else:
        return None
    if np.array_equal(p, target) or target_outside_lumen(run.scene, p):
        return None
    run.goal_base = run.scene.to_base(p[None])[0]
    run.meta["goal_shift_mm"] = float(np.linalg.norm(p - target))
    run.meta["goal"] = [float(v) for v in p]
    return p


def check_start(start, robot: Robot, validator: BatchValidator | None = None) -> np.ndarray:
    """A start configuration as a (2n,) array inside the joint constraints, or InputError."""
    try:
        q = np.asarray(start, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise InputError("--start", "", f"must be 'retracted' or {robot.dof} numbers "
                         f"(alpha1..alpha{robot.n} rad, beta1..beta{robot.n} mm), got {start!r}") from None
    if q.shape != (robot.dof,) or not np.all(np.isfinite(q)):
        raise InputError("--start", "", f"must be 'retracted' or {robot.dof} finite numbers "
                         f"(alpha1..alpha{robot.n} rad, beta1..beta{robot.n} mm), got {q.size}")
    with np.errstate(invalid="ignore"):
        ok = bool(np.all(robot.constraint_violations(q[None]) >= -1e-7))
    if not ok:
        raise InputError("--start", "", f"violates the joint constraints of robot {robot.name!r} "
                         f"(betas must satisfy the tube order and lengths)")
    return q


def _stage_ik(run: _Run) -> tuple[GoalSource, np.ndarray]:
    """Stage 2: IK rounds until collision-free goals exist (or the reason there are none)."""
    t0 = time.perf_counter()
    table = _ik.workspace_table(run.model, run.cfg.table_size)         # cached per model
    run.timings["setup"] += time.perf_counter() - t0
    run.deadline += time.perf_counter() - t0
    t0 = time.perf_counter()
    rank = None
    if run.cfg.objective == "clearance" and run.cfg.goals_by_clearance:
        field_ = _opt.FieldClearance(run.world)

        def rank(q: np.ndarray) -> np.ndarray:   # goals with more room first
            return _state_clearance(run.validator, field_, q)
    source = GoalSource(run.model, run.robot, run.validator, table, run.goal,
                        run.tolerance_mm, run.cfg, np.random.default_rng([run.seed, 1]), rank=rank)
    goals = source.next()
    while len(goals) == 0 and source.rounds < run.cfg.ik_rounds:
        goals = source.next()
    if len(goals) == 0 and source.reaching > 0 and run.cfg.approach:
        # every configuration reaching the goal collides with the margin: approach from further
        # inside the lumen (the tip probe thicker by a part of the margin), within the margin
        tip_radius = float(run.robot.tubes[0].od) / 2.0
        allowed = _tip_margin(run)
        for extra in (0.25 * allowed, 0.5 * allowed, allowed):
            if extra <= 0 or _approach_goal(run, tip_radius + extra) is None:
                continue
            source = GoalSource(run.model, run.robot, run.validator, table, run.goal,
                                run.tolerance_mm, run.cfg, np.random.default_rng([run.seed, 1]),
                                rank=rank)
            goals = source.next()
            while len(goals) == 0 and source.rounds < run.cfg.ik_rounds:
                goals = source.next()
            if len(goals):
                break
    run.clock("ik", t0)
    run.counts.update(ik_rounds=source.rounds, ik_reaching=source.reaching,
                      ik_evaluations=source.evaluations, goals=len(goals))
    if len(goals) == 0:
        if source.reaching == 0:
            raise _Stop(run.finish(
                PlanStatus.UNREACHABLE, f"no configuration puts the tip within {run.tolerance_mm:g} "
                f"mm of the target (best {source.best_error_mm:.2f} mm after {source.rounds} IK rounds)"))
        if target_outside_lumen(run.scene, run.target):
            raise _Stop(run.finish(PlanStatus.TARGET_IN_COLLISION, "the target lies outside the lumen walls"))
        if run.validator.tracker is not None and len(source.rejected) and _relaxed(run).states_valid(
                np.array(source.rejected)).any():
            raise _Stop(run.finish(PlanStatus.UNSTABLE_ONLY, "every collision-free configuration "
                                   "reaching the target is below the stability margin "
                                   f"{run.validator.tracker.margin:g}"))
        raise _Stop(run.finish(PlanStatus.GOAL_IN_COLLISION, f"{source.reaching} configurations "
                               "reach the target but all of them collide"))
    return source, goals


def _stage_planning(run: _Run, start: np.ndarray, source: GoalSource,
                    goals: np.ndarray) -> tuple[np.ndarray, str]:
    """Stage 3: the straight edge to one of the nearest goals, else OMPL. Returns (waypoints,
    what solved it)."""
    from ctrplan.planning import space as _space

    cfg, validator = run.cfg, run.validator
    t0 = time.perf_counter()
    direct = _direct_path(validator, start, goals) if cfg.try_direct else None
    run.counts["direct"] = int(direct is not None)
    if direct is not None:
        run.clock("planning", t0)
        run.counts["states_validated"] = validator.counters.states
        return direct, "direct"
    refresh_s = [0.0]

    def more_goals() -> np.ndarray:
        t = time.perf_counter()
        g = source.next()
        refresh_s[0] += time.perf_counter() - t
        return g

    outcome = _space.solve(run.robot, validator, start, goals, planner=run.planner,
                           time_limit=max(0.0, run.deadline - time.perf_counter()),
                           seed=run.seed, alpha_weight_mm=cfg.validator.alpha_weight_mm,
                           range_mm=cfg.range_mm, more_goals=more_goals, simplify=cfg.simplify,
                           optimize=cfg.optimize, max_states=cfg.max_states)
    run.time_cap_hit |= outcome.time_cap_hit
    # IK rounds run while planning (goal refresh) count as IK time.
    run.timings["ik"] += refresh_s[0]
    run.timings["planning"] += (time.perf_counter() - t0) - outcome.simplification_s - refresh_s[0]
    run.timings["simplification"] += outcome.simplification_s
    run.counts.update(goals=outcome.goals_used, ik_rounds=source.rounds,
                      ik_reaching=source.reaching, ik_evaluations=source.evaluations,
                      states_validated=validator.counters.states)
    if outcome.path is None:
        why = (f"the time cap of {run.time_limit:.2f} s" if outcome.time_cap_hit
               else f"the budget of {cfg.max_states} states")
        if _only_unstable(run, start, source):
            raise _Stop(run.finish(PlanStatus.UNSTABLE_ONLY, f"no path within {why} keeps the "
                                   f"stability margin {validator.tracker.margin:g} and its "
                                   "equilibrium branch; the same search without that constraint "
                                   "finds one, below the margin or through a fold (where the "
                                   "robot would snap)"))
        raise _Stop(run.finish(PlanStatus.TIMEOUT, f"no collision-free path found within {why} "
                               f"({outcome.goals_used} goal configurations)"))
    return outcome.path, run.planner


def _relaxed(run: _Run) -> BatchValidator:
    """The planning validator without branch tracking and stability margin."""
    return BatchValidator(run.robot, run.model, run.world, run.cfg.validator, tracking=False)


def _only_unstable(run: _Run, start: np.ndarray, source: GoalSource) -> bool:
    """After a search without a path: whether the stability constraint is what stopped it,
    established by the same search (budget, seed, goals) without it finding a path. Only run
    when the constraint rejected a state or edge during the search."""
    from ctrplan.planning import space as _space

    tracker = run.validator.tracker
    if tracker is None or not tracker.counters.any or not len(source.goals):
        return False
    cfg = run.cfg
    t0 = time.perf_counter()
    out = _space.solve(run.robot, _relaxed(run), start, np.array(source.goals), planner=run.planner,
                       time_limit=run.time_limit, seed=run.seed,
                       alpha_weight_mm=cfg.validator.alpha_weight_mm, range_mm=cfg.range_mm,
                       simplify=False, optimize=cfg.optimize, max_states=cfg.max_states)
    run.clock("planning", t0)
    run.counts["unstable_only_check"] = 1
    return out.path is not None


def _stage_simplification(run: _Run, path: np.ndarray) -> np.ndarray:
    """Stage 4: greedy shortcutting with the same validator (a count of edges, not a time)."""
    if run.cfg.simplify and len(path) > 2:
        t0 = time.perf_counter()
        path = run.validator.shortcut(path)
        run.clock("simplification", t0)
    run.counts["states_validated"] = run.validator.counters.states
    return path


def _state_clearance(validator: BatchValidator, field_, q: np.ndarray,
                     direction: np.ndarray | None = None, uz0: np.ndarray | None = None) -> np.ndarray:
    """(B,) estimated clearance (mm, the world's padded capsules) of states q (B, 2n): the
    distance-field estimate of :class:`~ctrplan.planning.optimize.FieldClearance`, the worst
    case over a direction-aware model's unknown directions."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    out = np.full(len(q), np.inf)
    for d in validator.variants(q, direction):
        shape = validator.shapes(q, direction=d, uz0=uz0)
        out = np.minimum(out, field_.capsule_clearance(shape).min(axis=1))
    return out


def _stage_optimization(run: _Run, path: np.ndarray) -> list[np.ndarray]:
    """Stage 4b: the local optimiser for the objective. Returns the optimised path and an
    earlier iterate (best first) for stage 5 to try before the simplified path; empty for
    ``first`` or when no step was accepted. Every iterate passed the validator's edge check
    (the planner's own: exact verdicts, same padding and margin, at the edge resolution)."""
    cfg = run.cfg
    if cfg.objective == "first" or len(path) < 2:
        return []
    t0 = time.perf_counter()
    # the optimised goal's tip error stays within max(its IK error, 0.4 x the IK's threshold)
    res = _opt.optimize_path(run.validator, path, run.goal, cfg.objective, cfg.optimizer,
                             goal_tol_mm=0.4 * min(cfg.ik.stop_mm, 0.1 * run.tolerance_mm),
                             deadline=run.deadline)
    run.clock("optimization", t0)
    run.time_cap_hit |= res.time_cap_hit
    run.counts.update(optimizer_accepted=res.accepted, optimizer_trials=res.trials,
                      optimizer_evaluations=res.evaluations,
                      states_validated=run.validator.counters.states)
    if not res.accepted:
        return []
    return [res.path] + ([res.history[len(res.history) // 2]] if len(res.history) > 2 else [])


def _verify_optimized(run: _Run, path: np.ndarray,
                      optimized: list[np.ndarray]) -> tuple[PathCheck, PathCheck | None, np.ndarray]:
    """Stage 5 on the optimised path; if it fails there (or in the reference model's check),
    on the earlier iterate, then on the simplified path (with repairs, as without an
    objective)."""
    for k, candidate in enumerate(optimized):
        try:
            return _stage_verification(run, candidate, repair=False)
        except _Stop:
            run.counts["optimizer_fallbacks"] = k + 1
            log.debug("plan: optimised path %d failed verification; trying the next", k)
    return _stage_verification(run, path)


def _stage_verification(run: _Run, path: np.ndarray,
                        repair: bool = True) -> tuple[PathCheck, PathCheck | None, np.ndarray]:
    """Stage 5: exact check on the planning model at the fine resolution (failing segments
    re-planned unless ``repair`` is False), then the reference model's check at margin 0."""
    cfg, validator = run.cfg, run.validator
    t0 = time.perf_counter()
    vres = cfg.validator.resolution_mm / max(1, cfg.verify_factor)
    vpoints = cfg.verify_points or cfg.validator.points
    check = validator.check_path(path, vres, points=vpoints, fcl_all=cfg.verify_fcl_all)
    attempts = 0
    while not check.ok and repair and attempts < cfg.repair_attempts:
        attempts += 1
        repaired = _repair(run.robot, run.model, run.world, path, check.bad_segments, cfg,
                           run.seed + attempts, vres / (2 * attempts),
                           budget=max(0.5, run.deadline - time.perf_counter()),
                           tracker=_remember_waypoints(validator, path, check))
        if repaired is None:
            break
        path = repaired
        check = validator.check_path(path, vres, points=vpoints, fcl_all=cfg.verify_fcl_all)
    run.counts.update(verification_states=len(check.states), repairs=attempts, waypoints=len(path))
    if not check.ok:
        run.clock("verification", t0)
        bad = check.contact[check.first_bad] if check.first_bad >= 0 else ""
        if bad in _UNSTABLE_WHY:
            raise _Stop(run.finish(PlanStatus.VERIFICATION_FAILED, f"the path {_UNSTABLE_WHY[bad]} "
                                   f"when checked at {vres:g} mm and could not be repaired"))
        raise _Stop(run.finish(PlanStatus.VERIFICATION_FAILED, f"the path touches {bad or 'the scene'} "
                               f"when checked exactly at {vres:g} mm and could not be repaired"))
    ref_check = None
    if run.reference is not None:
        ref_val = _reference_validator(run, path[0])
        ref_check = ref_val.check_path(path, vres, points=vpoints, fcl_all=cfg.verify_fcl_all)
        run.counts["reference_states"] = len(ref_check.states)
        if not ref_check.ok:
            run.clock("verification", t0)
            bad = ref_check.contact[ref_check.first_bad]
            raise _Stop(run.finish(PlanStatus.VERIFICATION_FAILED,
                                   f"the {run.meta['reference_model']} model's backbone along the "
                                   f"path touches {bad or 'the scene'} (checked at {vres:g} mm)"))
    run.clock("verification", t0)
    return check, ref_check, path


def _reference_validator(run: _Run, start: np.ndarray) -> BatchValidator:
    from ctrplan.collision.capsules import curvature_bound

    ref = run.reference
    curvature = curvature_bound(ref) if run.cfg.sagitta else 0.0
    world = world_for(run.scene, 0.0, curvature)
    val = BatchValidator(run.robot, ref, world, run.cfg.validator)
    if val.tracker is not None and id(ref) in run.start_uz:   # the path starts on its branch
        val.tracker.register(start[None], run.start_uz[id(ref)][None], anchor=True)
    return val


def _output(run: _Run, path: np.ndarray, solver: str, check: PathCheck,
            ref_check: PathCheck | None) -> PlanResult:
    """The path subdivided for execution (rotations unwrapped), backbones in the scene frame,
    tip errors and the clearances under both models."""
    cfg, n = run.cfg, run.robot.n
    t0 = time.perf_counter()
    out_q = path
    seg = np.minimum(np.arange(len(path)), max(0, len(path) - 2))
    if cfg.output_step_mm > 0:
        out_q, seg = interpolate_path(path, n, cfg.validator.alpha_weight_mm, cfg.output_step_mm)
    out_q = unwrap_path(out_q, n)
    eq = _output_equilibria(run, out_q, check, ref_check)
    profile, value = _profile(run, path, out_q, seg, eq.get("uz0"))
    shape = eq["shape"] if "shape" in eq else run.model.shape(out_q, points=cfg.output_points)
    backbones = run.scene.to_scene(shape.points)
    tip_err = float(np.linalg.norm(shape.tip[-1] - run.target_base))
    tip_err_phys = tip_err
    if getattr(run.model, "name", "") != "physics":
        phys = resolve_model("physics", run.robot)
        tip_err_phys = float(np.linalg.norm(phys.shape(out_q[-1:], points=2).tip[0] - run.target_base))
    run.counts["path_states"] = len(out_q)
    vpoints = cfg.verify_points or cfg.validator.points
    clear, exact, calls = path_min_clearance(run.validator, run.world, check, vpoints,
                                             max_pairs=cfg.clearance_pairs)
    run.counts["clearance_exact_states"] = calls
    from ctrplan.shape.error_bounds import margin_least

    # the padded capsules' clearance plus the smallest margin along the shaft: a lower bound
    extra = dict(min_clearance_mm=clear + margin_least(run.margin_mm) if math.isfinite(clear) else clear,
                 min_clearance_exact=exact)
    if ref_check is not None:
        ref_val = _reference_validator(run, path[0])
        rc, rexact, _ = path_min_clearance(ref_val, ref_val.world, ref_check, vpoints,
                                           max_pairs=cfg.clearance_pairs)
        extra.update(min_clearance_reference_mm=rc, min_clearance_reference_exact=rexact)
    elif cfg.reference is not None:   # the planning model is the reference, margin 0
        extra.update(min_clearance_reference_mm=extra["min_clearance_mm"],
                     min_clearance_reference_exact=exact)
    run.clock("verification", t0)
    run.meta["planner"] = solver
    # SUCCESS means the tip within the tolerance of the target asked for (planning model),
    # whatever moved the goal (the approach off the wall, the optimiser)
    status, message = PlanStatus.SUCCESS, "ok"
    if not tip_err <= run.tolerance_mm:
        status = PlanStatus.OUTSIDE_TOLERANCE
        message = _hints.outside_tolerance(run, tip_err, _tip_margin(run))
    return run.finish(status, message, path=out_q, backbones=backbones,
                      tip_path=backbones[:, -1, :], tip_error_mm=tip_err,
                      tip_error_physics_mm=tip_err_phys, clearance_profile=profile,
                      objective_value=value, branch=eq.get("branch"),
                      stability=eq.get("stability"), **extra)


def _output_equilibria(run: _Run, out_q: np.ndarray, check: PathCheck,
                       ref_check: PathCheck | None) -> dict:
    """Per output state, the equilibrium the robot is on (continued from the verified state
    before it: :func:`~ctrplan.planning.stability.output_equilibria`), its branch label and
    stability: of the planning model (then also its shapes, ``shape``, and ``uz0``) or else
    of the reference model where one of them tracks branches; {} otherwise."""
    from ctrplan.shape.branches import tracks_branches

    cfg, n = run.cfg, run.robot.n
    for model, chk, own in ((run.model, check, True), (run.reference, ref_check, False)):
        if model is None or chk is None or chk.uz0 is None or not tracks_branches(model):
            continue
        # (a direction-aware model's output shapes are its shapes without a direction of
        # motion, as the tip error always was: the continued equilibrium moves with them)
        t, labels = _stab.output_equilibria(model, out_q, chk.states, chk.uz0, n,
                                            cfg.validator.alpha_weight_mm, cfg.output_points)
        out = {"branch": [int(v) for v in labels], "stability": _stab.stability_list(t.stability)}
        if own:
            out.update(shape=t.shape, uz0=t.uz0)
        return out
    return {}


def _profile(run: _Run, path: np.ndarray, out_q: np.ndarray, seg: np.ndarray,
             uz0: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """(clearance profile (K,) mm over the output states, margin not included; the objective's
    value on the path). uz0 : (K, n) the states' equilibria (branch tracking), or None."""
    n, w = run.robot.n, run.cfg.validator.alpha_weight_mm
    direction = None
    if run.validator.directional and len(path) > 1:
        dirs = np.array([edge_direction(a, b, n) for a, b in zip(path[:-1], path[1:])])
        direction = dirs[seg]
        joins = np.flatnonzero(np.r_[False, seg[1:] != seg[:-1]])
        direction[joins] = 0        # a waypoint joins two edges: both directions checked
    profile = _state_clearance(run.validator, _opt.FieldClearance(run.world), out_q, direction, uz0)
    from ctrplan.shape.error_bounds import margin_least

    # measured with capsules grown by the margin: add back the smallest margin along the shaft
    # (the whole margin where it is uniform), which keeps it a clearance of the tube itself
    profile = profile + margin_least(run.margin_mm)
    if run.cfg.objective == "clearance":
        value = _opt.clearance_integral(profile, out_q, n, w)
    elif run.cfg.objective == "length":
        value = float(motion_mm(out_q[:-1], out_q[1:], n, w).sum()) if len(out_q) > 1 else 0.0
    else:
        value = math.nan
    return profile, value


def path_min_clearance(validator: BatchValidator, world, check, points: int | None,
                       batch: int = 16, max_pairs: int = 300) -> tuple[float, bool, int]:
    """Smallest clearance (mm) over the verified states of a path, by branch and bound.

    The world's conservative clearance of every state is a lower bound of its FCL distance.
    States are taken in order of increasing bound and measured exactly
    (:meth:`CollisionWorld.clearance_bounded`, itself a branch and bound over capsule-mesh
    pairs) until the smallest distance found is no larger than the next state's bound: then it
    is the exact minimum. The work is capped at ``max_pairs`` FCL distance queries (about 2 ms
    each; a count, not a time, so the same path always gives the same value); if that does not
    settle it, the result is a valid lower bound, at least 0 (the states passed the exact
    collision check). Returns (value, exact, states measured).
    """
    bounds = np.asarray(check.clearance_mm, dtype=float)
    if len(bounds) == 0:
        return math.nan, False, 0
    direction = getattr(check, "direction", None)
    uz = getattr(check, "uz0", None)          # the states' equilibria (branch tracking)
    order = np.argsort(bounds, kind="stable")
    best = math.inf
    done, left = 0, int(max_pairs)
    settled = True
    while done < len(order):
        idx = order[done:done + batch]
        for d in validator.variants(check.states[idx], None if direction is None else direction[idx]):
            shape = validator.shapes(check.states[idx], points=points, direction=d,
                                     uz0=None if uz is None else uz[idx])
            values, used = world.clearance_bounded(shape, below=best, max_pairs=left)
            best = min(best, float(np.min(values)))
            left -= used
            settled &= left > 0
        done += len(idx)
        if done >= len(order) or best <= bounds[order[done]]:
            return max(0.0, best), bool(settled and best >= 0), done
        if left <= 0:
            break
    return max(0.0, min(best, float(bounds[order[done]]))), False, done


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


#: what a path failing the branch tracking does (the contacts of :mod:`ctrplan.planning.tracking`)
_UNSTABLE_WHY = {"fold": "crosses a fold of the equilibrium branch (the robot would snap there)",
                 "stability": "falls below the stability margin",
                 "branch": "arrives on another equilibrium branch than the one planned"}


def _remember_waypoints(validator: BatchValidator, path: np.ndarray, check: PathCheck):
    """The validator's tracker (None without), with every waypoint the exact check reached
    on its branch remembered with that equilibrium (so a repair connects to it)."""
    tracker = validator.tracker
    if tracker is None or check.uz0 is None:
        return tracker
    firsts = np.flatnonzero(np.r_[True, check.segment[1:] != check.segment[:-1]])
    for j, i in zip(check.segment[firsts], firsts):
        if tracker.lookup(path[j]) is None and check.contact[i] not in _UNSTABLE_WHY:
            tracker.register(path[j][None], check.uz0[i][None])
    return tracker


def _repair(robot, model, world, path: np.ndarray, bad_segments: list[int], cfg: PlanConfig,
            seed: int, resolution_mm: float, budget: float, tracker=None) -> np.ndarray | None:
    """Re-plan the segments that failed verification with a finer validator; None on failure.
    Each segment's search is budgeted in states (``cfg.repair_states``); ``budget`` (s) is a cap.
    ``tracker`` : the planning validator's branch tracker (its remembered equilibria)."""
    from ctrplan.planning import space as _space

    strict = BatchValidator(robot, model, world, replace(cfg.validator, resolution_mm=resolution_mm),
                            tracking=tracker if tracker is not None else True)
    pieces: list[np.ndarray] = []
    last = 0
    for j in bad_segments:
        pieces.append(path[last:j])
        sub = _space.solve(robot, strict, path[j], path[j + 1][None], planner="rrtconnect",
                           time_limit=budget, seed=seed, alpha_weight_mm=cfg.validator.alpha_weight_mm,
                           range_mm=cfg.range_mm, simplify=cfg.simplify, max_states=cfg.repair_states)
        if sub.path is None:
            log.debug("plan: repair of segment %d failed", j)
            return None
        pieces.append(sub.path[:-1])
        last = j + 1
    pieces.append(path[last:])
    return np.concatenate([p for p in pieces if len(p)], axis=0)
