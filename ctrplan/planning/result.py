"""What a plan returns: :class:`PlanStatus` and the typed :class:`PlanResult` (plan.json).

Made by :meth:`ctrplan.planning.planner.Planner.plan` (and the one-call wrapper
:func:`ctrplan.planning.plan.plan_to_target`); :meth:`PlanResult.to_json` is plan.json, whose
fields docs/conventions.md describes (their CLI flags and Python names side by side there).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from enum import Enum
from typing import Any

import numpy as np


class PlanStatus(str, Enum):
    """Outcome of a plan (:meth:`~ctrplan.planning.planner.Planner.plan`)."""

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
class PlanResult:
    """Result of a plan (:meth:`~ctrplan.planning.planner.Planner.plan`).

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
        ``min_clearance_exact`` says whether it is the exact minimum (True) or a lower bound
        (False: the distance-query budget did not settle it). nan without a path.
    min_clearance_reference_mm, min_clearance_reference_exact : the same for the reference
        model (``reference_model``: physics, or the calibrated model) at margin 0.
    planner : what solved it: the OMPL planner's name, or ``"direct"`` for the straight edge.
    margin_mm : the margin used (mm); ``margin_auto`` whether it came from the model's bound.
    time_cap_hit : the wall-clock cap stopped the search (the result may depend on load).
    timings : seconds per stage: setup (loading the model, scene and collision world, the
        workspace table and the retracted start: done once per
        :class:`~ctrplan.planning.planner.Planner`, so ~0 for its later plans), checks, ik,
        planning, simplification, verification, and total.
    planning_time_s : total minus setup (what a plan costs once the planner is prepared).
    counts : work done (states validated, edges, goals, IK evaluations, verification states...).
    objective : what the path was optimised for (``clearance``, ``length``, ``first``);
        objective_value : its value on the returned path: for ``clearance`` the integral of
        1/clearance over the metric arc length (dimensionless, smaller is better; clearances
        from ``clearance_profile``), for ``length`` the metric length (mm), nan for ``first``.
    clearance_profile : (K,) mm, one per ``path`` state: the planning model's tube (capsules
        of radius + sagitta bound, margin not included) to the anatomy, estimated from the
        distance fields (the interpolated distance to the nearest surface sample; within about
        the field's sample spacing of the exact distance; ``min_clearance_mm`` is exact).
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
        the tip's radius + margin was approached (:attr:`PlannerConfig.approach <ctrplan.planning.planner.PlannerConfig>`): the goal
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
    tip_direction : (3,) unit tip tangent at the final state (scene frame; planning model,
        :func:`~ctrplan.planning.tipgoal.tip_frames`), None without a path.
    tip_goal, approach_direction, cone_deg, standoff_requested_mm : a
        :class:`~ctrplan.planning.tipgoal.TipGoal`'s record (``TipGoal.record()``), its
        direction (scene frame, unit), cone (deg) and standoff (mm) as asked; None for a point.
    direction_error_deg : the angle (deg) between ``tip_direction`` and ``approach_direction``
        (nan without a direction or a path). A tip outside the cone is not SUCCESS
        (``OUTSIDE_TOLERANCE``).
    standoff_mm : the standoff achieved: the final tip's distance from the goal's surface point
        along its normal (or back along its direction), planning model; nan for a point goal.
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
    tip_direction: np.ndarray | None = None
    direction_error_deg: float = math.nan
    standoff_mm: float = math.nan
    standoff_requested_mm: float | None = None
    cone_deg: float | None = None
    approach_direction: list | None = None
    tip_goal: dict | None = None

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
            # tip pose goals (ctrplan.planning.tipgoal): the goal, and what the plan achieved
            "tip_goal": None if self.tip_goal is None else dict(self.tip_goal),
            "tip_direction": _vec(self.tip_direction),
            "approach_direction": _vec(self.approach_direction),
            "cone_deg": None if self.cone_deg is None else float(self.cone_deg),
            "direction_error_deg": _num(self.direction_error_deg),
            "standoff_requested_mm": (None if self.standoff_requested_mm is None
                                      else float(self.standoff_requested_mm)),
            "standoff_mm": _num(self.standoff_mm),
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


def robot_record_of(spec: dict) -> dict[str, Any]:
    """``robot_spec`` and ``robot_sha256`` for plan.json (:func:`ctrplan.robot.robot_record`)."""
    from ctrplan.robot import robot_digest

    return {"robot_spec": spec, "robot_sha256": robot_digest(spec)}


def _vec(v) -> list | None:
    if v is None:
        return None
    a = np.asarray(v, dtype=float).reshape(-1)
    return [float(x) for x in a] if a.size and np.all(np.isfinite(a)) else None


def _num(v: float) -> float | None:
    return float(v) if v is not None and math.isfinite(float(v)) else None
