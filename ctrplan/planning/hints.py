"""What a plan tells its user about its labels and goals (issue 35, item 4).

The messages a plan gives when the margin is what makes the start collide, and when a verified
path's tip ends beyond the tolerance (status ``OUTSIDE_TOLERANCE``: SUCCESS means the tip within
``tolerance_mm`` of the target asked for, not of a goal moved off the wall to keep the tip's
margin). ``run`` is the plan's working state (:class:`ctrplan.planning.run.Run`): its margin,
model labels (``meta``), scene and validator settings.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np


def margin_words(run: Any) -> str:
    """What the margin is, in words: --margin X, or auto from the calibrated model's measured
    bound, from a surrogate's surrogate error, or from a bound of unstated origin."""
    if not run.margin_auto:
        return f"--margin {float(run.cfg.margin_mm or 0.0):g}"
    if run.meta.get("calibrated"):
        return f"--margin auto: the error bound of the calibrated model {run.meta['model']!r}"
    if run.meta.get("surrogate_error"):
        return f"--margin auto: the surrogate error of the model {run.meta['model']!r}"
    return "--margin auto: the model's error bound"


def margin_start_hint(run: Any, start: np.ndarray, retracted: bool,
                      world0: Callable[[], Any]) -> str:
    """When a margin makes the start collide: the same start (for the retracted one: any tube
    rotation, as the planner would choose) checked at margin 0 with the planning model. The
    hint names the margin and how to lower it; "" when there is no margin or the start collides
    at margin 0 too (then the base pose is the cause: the caller's own hint). ``world0`` : makes the
    scene's collision world at margin 0 (same curvature bound)."""
    from ctrplan.planning.goals import retracted_start
    from ctrplan.planning.validator import BatchValidator
    from ctrplan.shape.error_bounds import margin_peak

    peak = margin_peak(run.margin_mm)
    if peak <= 0:
        return ""
    try:
        world0 = world0()
        v0 = BatchValidator(run.robot, run.model, world0, run.cfg.validator)
        q = retracted_start(run.robot, v0, world0)[0] if retracted else start
        if not v0.states_valid(q[None])[0]:
            return ""
    except Exception:  # the hint is a courtesy: never let it hide the status itself
        return ""
    return (f"; it collides only with the {peak:.2f} mm margin ({margin_words(run)}): at "
            f"margin 0 it is free. Lower the margin with --margin MM (0 checks the model's "
            f"backbone alone), plan with a model whose error bound is smaller, or give --start")


def outside_tolerance(run: Any, tip_err: float, tip_margin: float) -> str:
    """Why a verified path's tip ends ``tip_err`` mm from the target, beyond the tolerance, and
    what the user can do (a larger --tolerance that accepts it, or a smaller margin).
    ``tip_margin`` : the margin (mm) the tip's capsule carries."""

    text = (f"the tip ends {tip_err:.3f} mm from the target, beyond the tolerance of "
            f"{run.tolerance_mm:g} mm (the verified path is in plan.json)")
    shift = float(run.meta.get("goal_shift_mm") or 0.0)
    if shift > 0:
        accept = math.ceil(tip_err * 100.0) / 100.0
        return (text + f": the goal was moved {shift:.2f} mm off the anatomy (goal_shift_mm) to "
                f"keep the tip's {tip_margin:.2f} mm margin ({margin_words(run)}); accept "
                f"it with --tolerance {accept:g}, or lower the margin with --margin MM")
    return text + ": no goal configuration was found closer to the target"
