"""The plan's side of elastic stability: the start's branch, UNSTABLE_ONLY, the path's labels.

Used by the plan's stages (:mod:`ctrplan.planning.stages`; the validator's side is
:mod:`ctrplan.planning.tracking`, the model's :mod:`ctrplan.shape.branches`).

- :class:`Start` : a start configuration with the branch the robot is on there. Where the model
  finds two stable equilibria at the start (a bistable start) the plan needs the branch, from
  the user (``branch``: the ``branch`` plan.json records for that state; :func:`start_from_plan`
  reads the last state of an earlier plan) and refuses to guess otherwise.
- :func:`output_equilibria` : the equilibrium, ``branch`` label and ``stability`` of each
  output state, continued from the nearest verified state of the path.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass

import numpy as np

from ctrplan.errors import ArgumentError, InputError
from ctrplan.planning.validator import motion_mm
from ctrplan.shape import branches as _br
from ctrplan.shape.planning_model import planning_model

#: accepted ``branch`` values of a start (plan.json's labels)
BRANCHES = (-1, 0, 1)


@dataclass(frozen=True)
class Start:
    """A start configuration q (2n,) rad and mm, and the branch the robot is on there (None:
    unknown, fine where the model finds one stable equilibrium; -1, 0, +1: plan.json's label,
    :mod:`ctrplan.shape.branches`)."""

    q: np.ndarray
    branch: int | None = None


def check_branch(value, source: str = "branch", field: str = "") -> int | None:
    """A branch label (-1, 0, +1, or None) or InputError (naming the argument ``branch``, or
    ``source`` and ``field``: a file's)."""
    if value is None:
        return None
    try:
        b = int(str(value).strip().replace("+", ""))
    except (TypeError, ValueError):
        b = None
    if b not in BRANCHES or isinstance(value, bool) or (isinstance(value, float) and value != b):
        why = f"must be -1, 0 or +1 (the branch plan.json records), got {str(value)[:40]!r}"
        if source == "branch" and not field:
            raise ArgumentError("branch", why)
        raise InputError(source, field, why)
    return b


def start_from_plan(path: str | os.PathLike, robot) -> Start:
    """The last state of an earlier plan (plan.json): its configuration and its ``branch``.
    The plan must have been made for the same robot (``robot_sha256``)."""
    from ctrplan.io import load_json
    from ctrplan.robot import check_regular_file, robot_digest

    src = str(path)
    check_regular_file(path, (".json",), "a plan.json", max_bytes=64 << 20)
    plan = load_json(path)
    if not isinstance(plan, dict):
        raise InputError(src, "", "expected a plan.json object")
    try:
        q = np.asarray(plan.get("path"), dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise InputError(src, "path", "must be a list of configurations") from None
    if q.ndim != 2 or len(q) == 0 or q.shape[1] != robot.dof or not np.all(np.isfinite(q)):
        raise InputError(src, "path", f"must be a non-empty list of {robot.dof} finite numbers "
                                      f"per state (robot {robot.name!r})")
    digest = plan.get("robot_sha256")
    if digest is not None and digest != robot_digest(robot.to_dict()):
        raise InputError(src, "robot_sha256", f"the plan was made for another robot than "
                                              f"{robot.name!r} (give its --robot)")
    labels = plan.get("branch")
    branch = None
    if isinstance(labels, list) and len(labels) == len(q):
        branch = check_branch(labels[-1], src, "branch")
    elif labels is not None:
        raise InputError(src, "branch", "must be a list with one label per path state")
    return Start(q=q[-1].copy(), branch=branch)


def resolve_start(model, q: np.ndarray, branch: int | None) -> np.ndarray:
    """The equilibrium (uz0 (n,), 1/mm) the robot is on at the start q (2n,) for a model that
    tracks branches. Where the model finds two stable equilibria, ``branch`` picks one (None
    or 0: ArgumentError naming ``start``, the plan does not guess); where it finds one,
    ``branch`` must be None or 0."""
    model = planning_model(model, fit=False)
    first, second = model.stable_equilibria(q[None])
    if not np.all(np.isfinite(first)):
        raise ArgumentError("start", "the model finds no stable equilibrium at the start "
                                     "configuration")
    if not np.all(np.isfinite(second)):
        if branch not in (None, 0):
            raise ArgumentError("start", f"`branch` {branch:+d} given, but the model finds one "
                                         f"stable equilibrium at the start (its branch is 0)")
        return first[0]
    labels = _br.label_of(np.concatenate([first, second]), np.concatenate([first, second]),
                          np.concatenate([second, first]), model.robot)
    if branch in (None, 0):
        tips = model.settle(np.repeat(q[None], 2, axis=0), np.concatenate([first, second]), 2)
        gap = float(np.linalg.norm(tips.shape.tip[0] - tips.shape.tip[1]))
        raise ArgumentError("start", f"the start is bistable (two stable equilibria, tips "
                                     f"{gap:.1f} mm apart): the robot's shape depends on how it "
                                     f"got there; give its `branch` (+1 or -1, as plan.json "
                                     f"records it), or the `start` of the plan.json that "
                                     f"brought it there")
    return (first if labels[0] == branch else second)[0]


def output_equilibria(model, path_states: np.ndarray, checked: np.ndarray, checked_uz: np.ndarray,
                      n: int, alpha_weight_mm: float, points: int,
                      direction: np.ndarray | None = None):
    """The output states' equilibria, continued (a two-state chain each) from the verified
    state just before them along the path. path_states (K, 2n) and checked (S, 2n) are two
    samplings of the same path from its start; checked_uz (S, n) the verified equilibria.
    Returns (:class:`~ctrplan.shape.branches.Tracked` of the output states, labels (K,))."""
    def along(x):
        return np.concatenate([[0.0], np.cumsum(motion_mm(x[:-1], x[1:], n, alpha_weight_mm))])

    ua, ub = along(path_states), along(np.asarray(checked, dtype=float))
    j = np.clip(np.searchsorted(ub, ua + 1e-9, side="right") - 1, 0, len(checked) - 1)
    K = len(path_states)
    rows = np.empty((2 * K, path_states.shape[1]))
    rows[0::2], rows[1::2] = checked[j], path_states
    starts = np.zeros(2 * K, dtype=bool)
    starts[0::2] = True
    x0 = np.full((2 * K, checked_uz.shape[1]), np.nan)
    x0[0::2] = checked_uz[j]
    d = None if direction is None else np.repeat(direction, 2, axis=0)
    model = planning_model(model, fit=False)
    t = model.solve(rows, points, d, uz_init=x0, chain=starts)[1::2]
    labels = model.branch_labels(path_states, t.uz0, direction)
    return t, labels


def stability_list(values) -> list:
    """JSON-ready per-state values (None where not finite)."""
    return [float(v) if v is not None and math.isfinite(float(v)) else None for v in values]
