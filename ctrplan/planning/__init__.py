"""Planning: OMPL glue (state space, batched motion validator, goals), IK, the Planner.

Public names: :class:`Planner` and :class:`PlannerConfig` (prepared once, ``plan(target,
seed=...)`` many times; :mod:`ctrplan.planning.planner`), :func:`plan_to_target` (one call),
:class:`PlanResult`, :class:`PlanStatus`, :class:`PlanConfig` (the former name of
PlannerConfig), and for a start on a given equilibrium branch :class:`Start` and
:func:`start_from_plan` (:mod:`ctrplan.planning.stability`). ``ompl`` is imported only by
:mod:`ctrplan.planning.space`, when planning starts.
"""

from ctrplan.planning.plan import plan_to_target
from ctrplan.planning.planner import PlanConfig, Planner, PlannerConfig
from ctrplan.planning.result import PlanResult, PlanStatus
from ctrplan.planning.stability import Start, start_from_plan

__all__ = ["PlanConfig", "PlanResult", "PlanStatus", "Planner", "PlannerConfig", "Start",
           "plan_to_target", "start_from_plan"]
