"""Plan to a target: IK goals, OMPL search, simplification, verification on two models.

:func:`plan_to_target` is the product's main job in one call; :class:`~ctrplan.planning.planner.Planner`
is the same job prepared once for many plans (``Planner(robot, scene, model, config).plan(target,
seed=...)``: the robot, scene, models, collision worlds, workspace table and start resolved
once). A plan reads as its five stages (timed separately; :mod:`ctrplan.planning.stages`,
:mod:`ctrplan.planning.verify`):

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
(:func:`~ctrplan.shape.planning_model.planning_model`: no sensor registration, friction a pure
function of q and the direction of motion). Capsules are padded by the sagitta bound of the
model's curvature bound (they cover the continuous backbone) and by the margin
(``PlannerConfig.margin_mm``; ``None`` = ``auto``: the planning model's error bound).

Determinism. Search budgets are counts (states validated, IK rounds, simplifier rounds, FCL
distance queries); the time limit is only a cap, reported as ``time_cap_hit`` when it stopped
the search. The same seed gives the same path on any machine load unless the cap was hit, and
a plan does not depend on the plans made before it.

Names kept here for callers of earlier versions: :class:`PlanConfig` (= ``PlannerConfig``),
:class:`PlanResult`, :class:`PlanStatus`, :func:`planning_model_of`, :func:`world_for`,
:func:`path_min_clearance`, :func:`scene_by_name` and :func:`resolve_model` (both load anew:
nothing is cached per process; keep the scene, the model or a Planner instead).
"""

from __future__ import annotations

import os

from ctrplan.collision.world import world_for
from ctrplan.planning.arguments import (
    MAX_TARGET_MM,
    check_objective,
    check_plan_args,
    check_start,
    check_target,
)
from ctrplan.planning.planner import PlanConfig, Planner, PlannerConfig, Planners
from ctrplan.planning.result import PlanResult, PlanStatus, robot_record_of
from ctrplan.planning.tipgoal import TipGoal, split_goal
from ctrplan.planning.verify import path_min_clearance
from ctrplan.robot import Robot

__all__ = ["MAX_TARGET_MM", "PlanConfig", "PlanResult", "PlanStatus", "Planner", "PlannerConfig",
           "Planners", "TipGoal", "check_objective", "check_start", "check_target", "path_min_clearance",
           "plan_to_target", "planning_model_of", "resolve_model", "robot_record_of",
           "scene_by_name", "world_for"]


def plan_to_target(
    robot: Robot | str,
    scene,
    target,
    model="physics",
    planner: str = "rrtconnect",
    time_limit: float = 5.0,
    seed: int = 0,
    tolerance_mm: float = 1.0,
    config: PlannerConfig | None = None,
    world=None,
    start=None,
    objective: str | None = None,
) -> PlanResult:
    """Plan a collision-free motion from the start configuration to put the tip at ``target``:
    ``Planner(robot, scene, model, config, world=world).plan(target, seed, start, planner=...,
    time_limit=..., tolerance_mm=..., objective=...)`` in one call (see
    :class:`~ctrplan.planning.planner.Planner` and :meth:`~ctrplan.planning.planner.Planner.plan`
    for every argument). For many plans keep a Planner: this call prepares one every time.

    Raises
    ------
    InputError
        Unknown robot, scene, model or planner; non-finite target; bad time limit, tolerance,
        margin or start (an :class:`~ctrplan.errors.ArgumentError` naming the argument).
    """
    from ctrplan.planning.space import check_planner

    # the arguments first (as before the planner existed: the same error for the same input)
    if objective is not None:
        check_objective(objective)
    check_plan_args(time_limit, tolerance_mm, seed)
    check_planner(planner)
    split_goal(target)
    prepared = Planner(robot, scene, model, config, world=world)
    return prepared.plan(target, seed=seed, start=start, planner=planner, time_limit=time_limit,
                         tolerance_mm=tolerance_mm, objective=objective)


def planning_model_of(model):
    """The model fit for collision checking (the shape model of
    :func:`ctrplan.shape.planning_model.planning_model`)."""
    from ctrplan.shape.planning_model import planning_model

    return planning_model(model).shape_model


def scene_by_name(spec: str | os.PathLike):
    """``load_scene(spec)`` (loaded anew each call: keep the scene, or a
    :class:`~ctrplan.planning.planner.Planners`)."""
    from ctrplan.collision.scene import load_scene

    return load_scene(spec)


def resolve_model(spec, robot: Robot):
    """``load_model(spec, robot)`` (a name or file loaded anew each call; an object returned
    as it is)."""
    from ctrplan.shape.models import load_model

    return load_model(spec, robot)
