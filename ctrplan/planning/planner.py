"""A prepared planner: robot, scene, model and settings resolved once, then ``plan(target)``.

:class:`Planner` is built once from ``(robot, scene, model, PlannerConfig)`` and owns what every
plan of that setup shares: the robot, the scene and its collision worlds (the planning world with
the margin and the model's curvature bound; the margin-0 worlds of the reference re-check and of
the start-collision hint), the planning model and the reference model
(:class:`~ctrplan.shape.planning_model.PlanningModel`), the IK workspace table and the retracted
start (both built when a plan first needs them). :meth:`Planner.plan` makes one plan
(:mod:`ctrplan.planning.stages`, :mod:`ctrplan.planning.verify`) with a validator of its own,
so a plan does not depend on the plans made before it: the same seed gives the same plan, first
or hundredth. This is the shape of cuRobo's ``MotionGen(config)`` (prepare once, plan per
request) and MPlib's ``Planner``, with ctrplan's typed :class:`~ctrplan.planning.result.PlanResult`.

Nothing is cached per process: whoever plans many times keeps the planner (or, for many
setups, a :class:`Planners`: what one batch run or one worker process keeps), and a dropped
planner frees what it held. ``plan_to_target`` (:mod:`ctrplan.planning.plan`) is the one-call
wrapper.
"""

from __future__ import annotations

import math
import os
import time
from collections import OrderedDict
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ctrplan.errors import ArgumentError
from ctrplan.planning import ik as _ik
from ctrplan.planning import optimize as _opt
from ctrplan.planning import stages as _stages
from ctrplan.planning import verify as _verify
from ctrplan.planning.arguments import check_objective, check_plan_args
from ctrplan.planning.result import PlanResult
from ctrplan.planning.run import Run, Stop
from ctrplan.planning.tipgoal import split_goal
from ctrplan.planning.validator import BatchValidator, ValidatorConfig
from ctrplan.robot import Robot, load_robot
from ctrplan.shape.planning_model import PlanningModel, planning_model


@dataclass(frozen=True)
class PlannerConfig:
    """What a :class:`Planner` prepares and how it plans (the defaults are what the benchmarks
    use). Frozen and hashable: a key of the planners a worker keeps (:class:`Planners`).

    validator : edge resolution, backbone points, rotation weight (see ValidatorConfig).
    ik : IK settings; ``ik.seeds`` seeds per round.
    table_size : workspace samples used to seed IK (built once per planner).
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
    clearance_pairs : capsule-mesh pair distances allowed for each reported minimum clearance.
    output_step_mm : the returned path is subdivided so states are at most this far apart
        (metric mm); 0 returns the simplified waypoints only.
    output_points : backbone points per returned backbone.
    repair_attempts : re-planning rounds for segments that fail verification.
    optimize : let anytime planners (RRT*, BIT*) use the whole budget.
    try_direct : before OMPL, try the straight edge from the start to the nearest goals
        (``planner`` is then ``"direct"``); False always runs the planner.
    objective : what the found path is optimised for: ``"clearance"`` (default: keep as far
        from the anatomy as the robot allows; Kuntz et al.'s integral of 1/clearance),
        ``"length"`` (short and smooth) or ``"first"`` (the first solution, simplified); a
        plan may ask for another (:meth:`Planner.plan`'s ``objective``).
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
    goal_rescue : a surrogate's target or goals that only its margin blocks are decided by
        the physics model at margin 0 (:mod:`ctrplan.planning.rescue`: the target planned to
        as given, IK goals the physics model finds free, the states near them judged by it,
        the whole path re-verified by it as always); False refuses them
        (``TARGET_IN_COLLISION`` / ``GOAL_IN_COLLISION``).
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
    goal_rescue: bool = True

    def __post_init__(self) -> None:
        check_objective(self.objective)
        if self.margin_mm is not None and not (math.isfinite(self.margin_mm) and self.margin_mm >= 0):
            raise ArgumentError("margin_mm", f"must be a number >= 0 (mm) or None (auto), got {self.margin_mm!r}")
        if not (isinstance(self.max_states, int) and self.max_states > 0):
            raise ArgumentError("max_states", f"must be a positive integer, got {self.max_states!r}")


class Planner:
    """Plans for one robot, scene and model with one configuration (module docstring).

    Parameters
    ----------
    robot : Robot or shipped name / YAML path.
    scene : Scene or shipped name / scene folder.
    model : "physics" (default: its own reference, margin 0), "learned" (an uncalibrated
        surrogate of the physics model; plans with its surrogate error as margin: ~1.7 mm for
        the shipped seed1 network, so targets closer than that to the anatomy are approached
        or refused), "rigid", a model file, or a shape model object. Planning, IK and the first
        verification use its planning model (:func:`~ctrplan.shape.planning_model.planning_model`);
        the final path is re-verified with ``config.reference`` (physics; a calibrated model
        with itself) and the final tip error is also measured with physics.
    config : PlannerConfig (default: the benchmarks' settings).
    world : a CollisionWorld to use instead of building one for the scene (it then carries the
        margin and curvature bound; ``config.margin_mm`` is only reported).

    Raises
    ------
    InputError
        Unknown robot, scene or model; a model made for another robot; a malformed error bound
        with ``margin_mm=None`` (auto).
    """

    def __init__(self, robot: Robot | str, scene, model: Any = "physics",
                 config: PlannerConfig | None = None, *, world=None):
        from ctrplan.collision.scene import load_scene
        from ctrplan.collision.world import world_for
        from ctrplan.shape.error_bounds import margin_peak
        from ctrplan.shape.models import load_model

        t0 = time.perf_counter()
        self.config = cfg = config or PlannerConfig()
        self.robot = load_robot(robot)
        self.scene = load_scene(scene) if isinstance(scene, (str, os.PathLike)) else scene
        #: how plan.json names the scene: the name or folder given, else the scene's name
        self.scene_label = _scene_label(scene, self.scene)
        named = isinstance(model, (str, os.PathLike))
        self.model: PlanningModel = planning_model(load_model(model, self.robot),
                                                   label=str(model) if named else None)
        if self.model.robot is not None and self.model.robot != self.robot and not _same_tubes(
                self.model.robot, self.robot):
            raise ArgumentError("model", f"the model was made for robot {self.model.robot.name!r}, "
                                         f"not {self.robot.name!r}")
        self.margin_auto = cfg.margin_mm is None
        try:   # a number, or the model's error profile
            self.margin_mm = self.model.auto_margin() if self.margin_auto else float(cfg.margin_mm)
        except ValueError as exc:
            raise ArgumentError("margin_mm", f"auto: {exc}") from None
        #: the planning model's curvature bound (1/mm) padding the capsules (0 without sagitta)
        self.curvature = self.model.curvature_bound if cfg.sagitta else 0.0
        self.world = world if world is not None else world_for(self.scene, self.margin_mm,
                                                               self.curvature)
        self._physics = None
        self.reference, self.reference_label = self._reference(margin_peak(self.margin_mm))
        self._table: _ik.WorkspaceTable | None = None
        self._start: tuple[np.ndarray, bool] | None = None
        self._worlds: dict[str, Any] = {}
        self._unbilled = time.perf_counter() - t0     # setup time, billed to the next plan

    # ------------------------------------------------------------------ what plans share
    def _reference(self, peak: float) -> tuple[PlanningModel | None, str]:
        """The reference re-check's model and label: physics at margin 0; a calibrated model is
        its own reference (re-checked at margin 0 when planning used a margin); the planning
        model itself needs no second check (its margin-padded check implies the margin-0 one).
        A calibrated model planned without a margin (no error bound in its file, or margin 0)
        gets the physics re-check as its second check."""
        ref = self.config.reference
        if ref is None:
            return None, ""
        if self.model.effects is not None and ref == "physics" and peak > 0:
            return self.model, self.model.label
        if self.model.name == ref and peak <= 0:
            return None, str(ref)
        other = self.physics() if ref == "physics" else _load(ref, self.robot)
        return planning_model(other, label=str(ref)), str(ref)

    def physics(self):
        """The physics model of the robot (the reference's and the physics tip error's)."""
        if self._physics is None:
            self._physics = _load("physics", self.robot)
        return self._physics

    def validator(self, tracking=True) -> BatchValidator:
        """A new validator of the planning model in the planning world (one per plan: its
        counters and remembered equilibria belong to that plan)."""
        return BatchValidator(self.robot, self.model, self.world, self.config.validator,
                              tracking=tracking)

    def workspace_table(self) -> _ik.WorkspaceTable:
        """The IK seeds' workspace table (``config.table_size`` samples), built on first use."""
        if self._table is None:
            self._table = _ik.workspace_table(self.model, self.config.table_size)
        return self._table

    def retracted_start(self) -> tuple[np.ndarray, bool]:
        """The retracted start (:func:`~ctrplan.planning.goals.retracted_start`, with a
        validator of its own), computed on first use: (q (2n,), whether its rotations were
        changed)."""
        if self._start is None:
            from ctrplan.planning.goals import retracted_start

            self._start = retracted_start(self.robot, self.validator(), self.world)
        q, adjusted = self._start
        return q.copy(), adjusted

    def reference_world(self):
        """The reference re-check's world: margin 0, the reference model's curvature bound."""
        if "reference" not in self._worlds:
            from ctrplan.collision.world import world_for

            k = self.reference.curvature_bound if self.config.sagitta else 0.0
            self._worlds["reference"] = world_for(self.scene, 0.0, k)
        return self._worlds["reference"]

    def world0(self):
        """The planning world without the margin (the start-collision hint's)."""
        if "margin0" not in self._worlds:
            from ctrplan.collision.world import world_for

            self._worlds["margin0"] = world_for(self.scene, 0.0, self.curvature)
        return self._worlds["margin0"]

    # ------------------------------------------------------------------ a plan
    def plan(self, target, seed: int = 0, start=None, *, planner: str = "rrtconnect",
             time_limit: float = 5.0, tolerance_mm: float = 1.0,
             objective: str | None = None) -> PlanResult:
        """Plan a collision-free motion from the start configuration to put the tip at ``target``.

        target : (3,) mm, scene frame.
        seed : seeds numpy and OMPL; the same seed gives the same path (planners stop at the
            first solution unless ``config.optimize``).
        start : (2n,) start configuration, or None / "retracted" for the retracted one
            (:meth:`retracted_start`), or a :class:`~ctrplan.planning.stability.Start` (the
            configuration with the branch the robot is on there; needed where the model finds
            two stable equilibria at the start, e.g. ``start_from_plan("plan.json", robot)``:
            the last state of an earlier plan).
        planner : one of :data:`ctrplan.planning.space.PLANNERS` (default RRTConnect).
        time_limit : a wall-clock cap (s) for the plan without setup; the search budget is
            ``config.max_states`` states validated, so a seed's result does not depend on load
            unless the cap is hit (``time_cap_hit``).
        tolerance_mm : tip-to-target distance accepted (planning model).
        objective : ``"clearance"``, ``"length"`` or ``"first"``; None: ``config.objective``.

        Raises InputError for a bad target, start, time limit, tolerance, seed, planner or
        objective (an :class:`~ctrplan.errors.ArgumentError` naming the argument).
        """
        run = self._run(target, seed, planner, time_limit, tolerance_mm, objective)
        try:
            start = _stages.checks(run, start)                                # 1. checks
            source, goals = _stages.ik_goals(run)                             # 2. IK goals
            path, solver = _stages.search(run, start, source, goals)          # 3. planning
            path = _stages.simplify(run, path)                                # 4. simplification
            optimized = _stages.optimize(run, path)                           #    + objective
            check, ref_check, path = _verify.verify_optimized(run, path, optimized)  # 5.
        except Stop as stop:
            return stop.result
        return _verify.output(run, path, solver, check, ref_check)

    def _run(self, target, seed, planner, time_limit, tolerance_mm, objective) -> Run:
        """The plan's working state, its arguments checked."""
        from ctrplan.planning.space import check_planner

        # the plan's clock starts with the setup not billed yet (the planner's preparation):
        # timings' total = setup + the stages
        t_call, self._unbilled = time.perf_counter() - self._unbilled, 0.0
        check_plan_args(time_limit, tolerance_mm, seed)
        requested = check_planner(planner)
        target, tip_goal = split_goal(target)
        cfg = self.config
        if objective is not None and check_objective(objective) != cfg.objective:
            cfg = replace(cfg, objective=check_objective(objective))
        m = self.model
        meta = dict(target=target, planner=requested, requested_planner=requested, seed=int(seed),
                    robot=self.robot.name, robot_spec=self.robot.to_dict(), model=m.label,
                    scene=self.scene_label, tolerance_mm=float(tolerance_mm),
                    time_limit_s=float(time_limit), margin_mm=_peak(self.margin_mm),
                    margin_auto=self.margin_auto, curvature_bound_per_mm=float(self.curvature),
                    reference_model=self.reference_label, objective=cfg.objective,
                    calibrated=m.calibrated, surrogate_error=m.surrogate_error,
                    measured_insertion=m.measured_insertion)
        if tip_goal is not None:
            meta.update(_tip_goal_meta(tip_goal))
        run = Run(prep=self, robot=self.robot, scene=self.scene, target=target,
                  target_base=self.scene.to_base(target[None])[0], model=m,
                  reference=self.reference, world=self.world, validator=self.validator(),
                  cfg=cfg, planner=requested, seed=int(seed), tolerance_mm=float(tolerance_mm),
                  time_limit=float(time_limit), t_call=t_call, margin_mm=self.margin_mm,
                  margin_auto=self.margin_auto, curvature=self.curvature, meta=meta,
                  tip_goal=tip_goal)
        run.timings = {"setup": time.perf_counter() - t_call, "checks": 0.0, "ik": 0.0, "planning": 0.0,
                       "simplification": 0.0, "optimization": 0.0, "verification": 0.0,
                       "total": 0.0}
        return run


def _tip_goal_meta(goal) -> dict:
    """plan.json's record of a :class:`~ctrplan.planning.tipgoal.TipGoal` (the goal as given
    and the standoff asked for; what the plan achieved is added by the output)."""
    return dict(tip_goal=goal.record(), standoff_requested_mm=goal.standoff_mm,
                cone_deg=goal.cone_deg,
                approach_direction=None if goal.direction is None else list(goal.direction))


#: ``PlanConfig``: the name of :class:`PlannerConfig` before there was a Planner (kept).
PlanConfig = PlannerConfig


class Planners:
    """The planners one owner keeps (a batch run, a worker process), by (robot, scene, model,
    config), and the scenes it loaded by name: the ``size`` most recently used of each.
    Owned by whoever plans, never by the process (a plan-batch worker keeps one; module
    docstring)."""

    def __init__(self, size: int = 4):
        self.size = int(size)
        self._planners: OrderedDict = OrderedDict()
        self._scenes: OrderedDict = OrderedDict()

    def scene(self, spec):
        """The scene of a shipped name or folder (loaded once), or ``spec`` itself."""
        if not isinstance(spec, (str, os.PathLike)):
            return spec
        from ctrplan.collision.scene import load_scene

        return _lru(self._scenes, str(spec), lambda: load_scene(spec), self.size)

    def get(self, robot, scene, model="physics", config: PlannerConfig | None = None) -> Planner:
        """The planner of (robot, scene, model, config), built on first use. Robot, scene and
        model given by name or path are keys by that name; objects by identity."""
        config = config or PlannerConfig()
        key = (_spec_key(robot), _spec_key(scene), _spec_key(model), config)
        return _lru(self._planners, key,
                    lambda: Planner(robot, self.scene(scene), model, config), self.size)


#: The planners of this worker process: a plan-batch or design worker (process pool or Ray),
#: created by the first job the worker runs, kept for its next jobs, gone with the worker. The
#: process that runs the command never uses it (its in-process paths own their Planners), so
#: it is per-worker state, not a cache of the library (allow-listed in tests/test_structure.py).
_WORKER_PLANNERS: Planners | None = None


def worker_planners() -> Planners:
    """The :class:`Planners` of this worker process (see :data:`_WORKER_PLANNERS`)."""
    global _WORKER_PLANNERS
    if _WORKER_PLANNERS is None:
        _WORKER_PLANNERS = Planners()
    return _WORKER_PLANNERS


def _lru(store: OrderedDict, key, make, size: int):
    if key in store:
        store.move_to_end(key)
        return store[key]
    value = store[key] = make()
    while len(store) > size:
        store.popitem(last=False)
    return value


def _spec_key(spec):
    return str(spec) if isinstance(spec, (str, os.PathLike)) else ("id", id(spec))


def _load(spec, robot: Robot):
    from ctrplan.shape.models import load_model

    return load_model(spec, robot)


def _peak(margin) -> float:
    from ctrplan.shape.error_bounds import margin_peak

    return margin_peak(margin)


def _same_tubes(a: Robot, b: Robot) -> bool:
    return a.n == b.n and np.allclose(a.lengths, b.lengths)


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
