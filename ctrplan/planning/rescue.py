"""Goals that only a surrogate's margin blocks: the physics model decides (issue 38).

A surrogate (a network trained on the physics model, ``error_bound: surrogate``) plans with its
error against that model as margin (``--margin auto``). Near a wall the margin can block every
configuration that puts the tip at the target although the physics model it imitates puts the
tube clear of the anatomy there: the plan would end ``TARGET_IN_COLLISION`` or
``GOAL_IN_COLLISION`` because of the surrogate alone. The rule (:class:`GoalRescue`):

1. Target: a target whose tip probe touches the anatomy only with the margin (free in the
   reference world, margin 0) is not refused; the approach off the wall is tried first as
   before, and where it cannot place the goal the target itself is planned to.
2. Goals: when an IK round finds configurations reaching the goal but the planning validator
   rejects all of them, they are checked again with the reference model (physics) in the
   reference world (margin 0, the reference model's sagitta padding, the validator's motion
   floor); those it finds free are the plan's goals ("rescued").
3. Goal region: a state within :data:`GOAL_REGION_MM` of the joint metric of a rescued goal
   that the planning validator rejects is valid exactly when the same reference check finds it
   free (the edges into the goal: their states are judged one by one by that rule).
4. Verification: the planning model's dense check leaves the states it rejects within the
   region grown by one edge resolution (the states between an edge's checked states, the last
   of them in the region) and the motion segments next to them to the reference model
   (``PathCheck.deferred``); the reference
   model's dense check of the whole path (margin 0, its motion between states covered, the
   same check as every plan's) then decides, as it does for every state of every plan.

So a rescued plan is exactly as safe as a physics plan in the goal region and keeps the
surrogate's margin everywhere else. Only for surrogates whose reference is the physics model:
a calibrated model's margin is its measured error against the robot, which no model can
overrule (no rescue there), and a model that tracks equilibrium branches or takes the direction
of motion is not rescued either (its states are not a function of q alone).
"""

from __future__ import annotations

import numpy as np

#: Radius (mm of the joint metric, ``alpha_weight_mm * sum|d alpha| + ||d beta||``) of the goal
#: region around a rescued goal where the reference model decides states the margin rejects.
#: Physical reason: the metric bounds the backbone's motion (about 1 mm per mm, the weight is
#: the largest displacement per rad on seed1), and a rescued goal touches the margin by at most
#: the margin (a surrogate's p99 error, 0.13 mm at the tip of the shipped seed1 network): the
#: edges leaving it must back off that far, on a motion that may run nearly along the wall;
#: 5 mm (2.5 edge resolutions) leaves them 38x that margin, and keeps the region small
#: against the lumens (a few mm wide) so the margin still governs the rest of the path.
GOAL_REGION_MM = 5.0


def allowed(model, reference, reference_label: str) -> bool:
    """Whether a plan with ``model`` may rescue goals: a surrogate (``error_bound:
    surrogate``) re-checked by the physics model, not tracking branches, not direction-aware."""
    return (reference is not None and reference_label == "physics"
            and model.error_bound == "surrogate" and model.effects is None
            and not model.tracks_branches and not model.needs_direction)


class GoalRescue:
    """The reference check that decides states the margin rejects near rescued goals.

    reference : a BatchValidator of the reference model in the reference world (margin 0);
    region_mm : the goal region's radius (joint metric); alpha_weight_mm : the metric's weight.
    """

    def __init__(self, reference, region_mm: float, alpha_weight_mm: float, n: int):
        self.reference = reference
        self.region_mm = float(region_mm)
        self.alpha_weight_mm = float(alpha_weight_mm)
        self.n = int(n)
        self.goals = np.zeros((0, 2 * n))
        #: states the reference check decided (for the plan's counts)
        self.decided = 0

    def add(self, goals: np.ndarray) -> None:
        """Rescued goals (G, 2n) whose regions the reference check decides."""
        self.goals = np.concatenate([self.goals, np.atleast_2d(goals)], axis=0)

    def near(self, q: np.ndarray, extra_mm: float = 0.0) -> np.ndarray:
        """(B,) bool: states q (B, 2n) within the region of a rescued goal (grown by
        ``extra_mm``)."""
        from ctrplan.planning.validator import motion_mm

        q = np.atleast_2d(np.asarray(q, dtype=float))
        if len(self.goals) == 0 or len(q) == 0:
            return np.zeros(len(q), dtype=bool)
        d = motion_mm(q[:, None, :], self.goals[None, :, :], self.n, self.alpha_weight_mm)
        return d.min(axis=1) <= self.region_mm + extra_mm

    def free(self, q: np.ndarray) -> np.ndarray:
        """(B,) bool: the reference model finds states q (B, 2n) valid in the reference world."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        if len(q) == 0:
            return np.zeros(0, dtype=bool)
        self.decided += len(q)
        return np.asarray(self.reference.states_valid(q), dtype=bool)

    def overrule(self, q: np.ndarray, rejected: np.ndarray) -> np.ndarray:
        """(B,) bool: which of the ``rejected`` (B,) states in a goal region the reference
        check finds free (the planning validator's verdict is overruled there)."""
        out = np.zeros(len(rejected), dtype=bool)
        cand = np.flatnonzero(rejected)
        if len(cand) == 0 or len(self.goals) == 0:
            return out
        cand = cand[self.near(q[cand])]
        if len(cand):
            out[cand] = self.free(q[cand])
        return out


def rescue_goals(run, source) -> np.ndarray:
    """Stage 2's rescue: the configurations an IK round found reaching the goal but the
    planning validator rejected, checked with the reference model at margin 0; those free
    become the plan's goals (G, 2n) and the validator's :class:`GoalRescue` decides their
    regions. Empty when the plan may not rescue or none is free."""
    if not run.cfg.goal_rescue or not len(source.rejected):
        return np.zeros((0, run.robot.dof))
    if not allowed(run.model, run.reference, run.meta.get("reference_model", "")):
        return np.zeros((0, run.robot.dof))
    validator = run.validator
    if validator.rescue is None:
        validator.rescue = GoalRescue(reference_validator(run), GOAL_REGION_MM,
                                      run.cfg.validator.alpha_weight_mm, run.robot.n)
    cand = np.array(source.rejected)
    free = validator.rescue.free(cand)
    goals = cand[free][: run.cfg.max_goals]
    if len(goals):
        validator.rescue.add(goals)
        validator.remember(goals, np.ones(len(goals), dtype=bool))
        source.goals.extend(goals)
        run.counts["goals_rescued"] = run.counts.get("goals_rescued", 0) + len(goals)
    return goals


def reference_validator(run):
    """A validator of the reference model in the reference world (margin 0)."""
    from ctrplan.planning.validator import BatchValidator

    return BatchValidator(run.robot, run.reference, run.prep.reference_world(),
                          run.cfg.validator, tracking=False)
