"""Planning: OMPL glue (state space, batched motion validator, goals), IK, plan_to_target.

Public names: :func:`plan_to_target`, :class:`PlanResult`, :class:`PlanStatus`,
:class:`PlanConfig`, and for a start on a given equilibrium branch :class:`Start` and
:func:`start_from_plan` (:mod:`ctrplan.planning.stability`). ``ompl`` is imported only by :mod:`ctrplan.planning.space`, when planning
starts.
"""

from ctrplan.planning.plan import PlanConfig, PlanResult, PlanStatus, plan_to_target
from ctrplan.planning.stability import Start, start_from_plan

__all__ = ["PlanConfig", "PlanResult", "PlanStatus", "Start", "plan_to_target", "start_from_plan"]
