"""One plan's working state, shared by the stages (:mod:`ctrplan.planning.stages`,
:mod:`ctrplan.planning.verify`).

A :class:`~ctrplan.planning.planner.Planner` holds what every plan of a robot, scene, model and
configuration shares; :class:`Run` is what one call of :meth:`Planner.plan
<ctrplan.planning.planner.Planner.plan>` works with: the target, the seed, its own validator
(its counters and the branch tracker's remembered equilibria belong to this plan alone), the
clock and the counts. A stage that ends the plan raises :class:`Stop` with the result.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ctrplan.planning.result import PlanResult, PlanStatus
from ctrplan.planning.validator import BatchValidator
from ctrplan.robot import Robot

log = logging.getLogger("ctrplan")


@dataclass
class Run:
    """Everything one plan works with (made by :meth:`Planner.plan
    <ctrplan.planning.planner.Planner.plan>`).

    prep : the Planner (its lazily prepared parts: ``retracted_start()``,
        ``workspace_table()``, ``reference_world()``, ``world0()``, ``physics()``).
    model, reference : the planning model and the reference model
        (:class:`~ctrplan.shape.planning_model.PlanningModel`; reference None: the planning
        model's own check suffices). world : the planning world (margin + sagitta).
    cfg : the PlannerConfig of this plan (the planner's, with this plan's objective).
    planner : the OMPL planner's name; margin_mm : a number or an ErrorProfile.
    """

    prep: Any
    robot: Robot
    scene: Any
    target: np.ndarray
    target_base: np.ndarray
    model: Any
    reference: Any
    world: Any
    validator: BatchValidator
    cfg: Any
    planner: str
    seed: int
    tolerance_mm: float
    time_limit: float
    t_call: float
    margin_mm: Any
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
    tip_goal: Any = None                  # the TipGoal (ctrplan.planning.tipgoal), None: a point

    @property
    def goal(self) -> np.ndarray:
        """The tip's goal in the base frame: the target, or where it was moved to keep the
        margin (:attr:`PlannerConfig.approach <ctrplan.planning.planner.PlannerConfig>`)."""
        return self.target_base if self.goal_base is None else self.goal_base

    def clock(self, stage: str, t0: float) -> None:
        self.timings[stage] = self.timings.get(stage, 0.0) + time.perf_counter() - t0

    def finish(self, status: PlanStatus, message: str, **kw) -> PlanResult:
        self.timings["total"] = time.perf_counter() - self.t_call
        self.counts.update({f"validator_{k}": v for k, v in self.validator.counters.as_dict().items()})
        if self.validator.rescue is not None:   # states the reference decided (rescue.py)
            self.counts["rescue_decided"] = self.validator.rescue.decided
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


class Stop(Exception):
    """A stage ended the plan (carries the result)."""

    def __init__(self, result: PlanResult):
        self.result = result


def tip_margin(run: Run) -> float:
    """The margin (mm) the tip's capsule carries: the profile's value at the tip, or the
    uniform margin."""
    from ctrplan.shape.error_bounds import ErrorProfile

    m = run.margin_mm
    if isinstance(m, ErrorProfile):
        return float(m.at(1.0))
    return float(m or 0.0)


def state_clearance(validator: BatchValidator, field_, q: np.ndarray,
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
