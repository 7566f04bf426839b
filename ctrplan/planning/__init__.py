"""Planning: OMPL glue (state space, batched motion validator, goals), IK, plan_to_target.

Public names: :func:`plan_to_target`, :class:`PlanResult`, :class:`PlanStatus`,
:class:`PlanConfig`. ``ompl`` is imported only by :mod:`ctrplan.planning.space`, when planning
starts.
"""

from ctrplan.planning.plan import PlanConfig, PlanResult, PlanStatus, plan_to_target

__all__ = ["PlanConfig", "PlanResult", "PlanStatus", "plan_to_target"]
