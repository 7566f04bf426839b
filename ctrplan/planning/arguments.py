"""The arguments of a plan, checked: each bad value is an :class:`~ctrplan.errors.ArgumentError`
that names the Python argument (``target``, ``start``, ``time_limit``, ``tolerance_mm``,
``seed``, ``objective``); the command line shows it with its flag (docs/conventions.md, "Names").
"""

from __future__ import annotations

import math

import numpy as np

from ctrplan.errors import ArgumentError
from ctrplan.planning.optimize import OBJECTIVES
from ctrplan.robot import Robot

#: Largest target coordinate (mm) accepted: scenes are at most 2 m across.
MAX_TARGET_MM = 1e6


def check_objective(objective) -> str:
    """An objective name (``clearance``, ``length``, ``first``) or ArgumentError."""
    key = str(objective).strip().lower()
    if key not in OBJECTIVES:
        raise ArgumentError("objective", f"must be one of {', '.join(OBJECTIVES)}, got {objective!r}")
    return key


def check_target(target) -> np.ndarray:
    """A target as a finite (3,) float array (mm), or ArgumentError."""
    try:
        t = np.asarray(target, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ArgumentError("target", f"must be three numbers X,Y,Z (mm), got {target!r}") from None
    if t.shape != (3,):
        raise ArgumentError("target", f"must be three numbers X,Y,Z (mm), got {t.size}")
    if not np.all(np.isfinite(t)):
        raise ArgumentError("target", "must be finite numbers (mm)")
    if np.max(np.abs(t)) > MAX_TARGET_MM:    # (also keeps the distances below finite)
        raise ArgumentError("target", f"{float(np.max(np.abs(t))):.4g} mm is outside the plausible "
                            f"range of a scene coordinate (|X|, |Y|, |Z| <= {MAX_TARGET_MM:g} mm)")
    return t


def check_plan_args(time_limit: float, tolerance_mm: float, seed: int) -> None:
    """``time_limit`` > 0 s, ``tolerance_mm`` > 0 mm (finite numbers), ``seed`` an integer >= 0."""
    if not (isinstance(time_limit, (int, float)) and math.isfinite(time_limit) and time_limit > 0):
        raise ArgumentError("time_limit", f"must be a positive number of seconds, got {time_limit!r}")
    if not (isinstance(tolerance_mm, (int, float)) and math.isfinite(tolerance_mm) and tolerance_mm > 0):
        raise ArgumentError("tolerance_mm", f"must be a positive number (mm), got {tolerance_mm!r}")
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ArgumentError("seed", f"must be a non-negative integer, got {seed!r}")


def check_start(start, robot: Robot, validator=None) -> np.ndarray:
    """A start configuration as a (2n,) array inside the joint constraints, or ArgumentError.
    (``validator`` is not used; kept for callers that pass one.)"""
    words = f"alpha1..alpha{robot.n} rad, beta1..beta{robot.n} mm"
    try:
        q = np.asarray(start, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ArgumentError("start", f"must be 'retracted' or {robot.dof} numbers ({words}), "
                                     f"got {start!r}") from None
    if q.shape != (robot.dof,) or not np.all(np.isfinite(q)):
        raise ArgumentError("start", f"must be 'retracted' or {robot.dof} finite numbers ({words}), "
                                     f"got {q.size}")
    with np.errstate(invalid="ignore"):
        ok = bool(np.all(robot.constraint_violations(q[None]) >= -1e-7))
    if not ok:
        raise ArgumentError("start", f"violates the joint constraints of robot {robot.name!r} "
                                     f"(betas must satisfy the tube order and lengths)")
    return q
