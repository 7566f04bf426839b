"""Validation of a ``plan-batch`` job file read back on resume.

A job file (``<out>/jobs/<id>.json``) is an output of an earlier run, but on resume it is input:
it may have been edited, truncated or replaced. A file that is not JSON (truncated) or not a
result of the job is not counted: the job runs again. Before a result is counted as done, every
field the batch uses is checked here: the job's own settings must equal the job being resumed
(so an edited robot, model, scene or target is never trusted), the status must be one of the
plan statuses and agree with ``success``, numbers must be finite numbers or null, the path must
be configurations of the recorded robot within the plausible ranges, and a recorded robot must
match its digest. Anything else is an :class:`~ctrplan.errors.InputError` naming the file and
the field, with how to recover (delete the file and the job runs again).
"""

from __future__ import annotations

import math
from dataclasses import asdict
from pathlib import Path
from typing import Any

from ctrplan.errors import InputError

#: Fields that hold a number (mm, s) or null in a job file.
NUMBER_FIELDS = ("planning_time_s", "tip_error_mm", "tip_error_physics_mm", "min_clearance_mm",
                 "min_clearance_reference_mm", "margin_mm", "objective_value", "goal_shift_mm",
                 "direction_error_deg", "standoff_mm", "snap_distance_mm")
#: Fields that hold true/false when present.
BOOL_FIELDS = ("min_clearance_exact", "min_clearance_reference_exact", "calibrated",
               "margin_auto", "time_cap_hit", "start_rotated")
#: Longest text accepted in a job file's string fields (a message is one line).
MAX_TEXT = 4000


def validate_job_file(path: str | Path, data: Any, job: Any) -> dict:
    """``data`` (the parsed job file at ``path``) when it is a trustworthy result of ``job`` (a
    :class:`~ctrplan.planning.batch.Job`); InputError naming the file and field otherwise."""
    from ctrplan.planning.result import PlanStatus

    src = str(path)
    hint = "(delete the file to run the job again)"

    def bad(field: str, what: str) -> InputError:
        return InputError(src, field, f"{what} {hint}")

    if not isinstance(data, dict):
        raise bad("", "expected a JSON object")
    if data.get("job_id") != job.id:
        raise bad("job_id", f"is not {job.id!r}")
    for key, want in asdict(job).items():
        have = data.get(key)
        if key == "planner" and "requested_planner" in data:
            have = data["requested_planner"]      # "planner" holds what solved it ("direct")
        if key == "target":
            want = [float(v) for v in want]
            ok = (isinstance(have, list) and len(have) == 3
                  and all(_is_number(v) for v in have) and [float(v) for v in have] == want)
        else:
            ok = type(have) is type(want) and have == want
        if not ok:
            raise bad(key, f"differs from the job being resumed ({str(have)[:60]!r} instead of "
                           f"{str(want)[:60]!r})")
    statuses = {s.value for s in PlanStatus}
    status = data.get("status")
    if not isinstance(status, str) or status not in statuses:
        raise bad("status", f"must be one of {', '.join(sorted(statuses))}, got {str(status)[:40]!r}")
    if not isinstance(data.get("success"), bool) or data["success"] != (status == "SUCCESS"):
        raise bad("success", f"must be {str(status == 'SUCCESS').lower()} for status {status}")
    msg = data.get("message", "")
    if not isinstance(msg, str) or len(msg) > MAX_TEXT:
        raise bad("message", f"must be text of at most {MAX_TEXT} characters")
    if data.get("scene") != job.scene:
        raise bad("scene", f"is not the job's scene {job.scene!r}")
    for key in NUMBER_FIELDS:
        v = data.get(key)
        if v is not None and not (_is_number(v) and math.isfinite(float(v))):
            raise bad(key, f"must be a finite number or null, got {str(v)[:40]!r}")
    sur = data.get("surrogate_error")
    if sur is not None and not (isinstance(sur, dict) and all(
            _is_number(sur.get(k)) and math.isfinite(float(sur[k])) and float(sur[k]) >= 0
            for k in ("p50", "p95", "p99", "max"))):
        raise bad("surrogate_error", "must be null or {p50, p95, p99, max} (mm, finite, >= 0)")
    if sur is not None and data.get("calibrated") is True:
        raise bad("surrogate_error", "a calibrated plan has no surrogate error")
    c = data.get("outside_measured_states")
    if c is not None and not (isinstance(c, int) and not isinstance(c, bool) and c >= 0):
        raise bad("outside_measured_states", f"must be a count (an integer >= 0) or null, got "
                                             f"{str(c)[:40]!r}")
    t = data.get("planning_time_s")
    if t is not None and float(t) < 0:
        raise bad("planning_time_s", f"must be >= 0, got {t!r}")
    for key in BOOL_FIELDS:
        if key in data and not isinstance(data[key], bool):
            raise bad(key, f"must be true or false, got {str(data[key])[:40]!r}")
    why = branch_fields_problem(data)
    if why:
        raise bad(*why)
    _check_robot_and_path(data, src, hint, status)
    return data


def branch_fields_problem(data: dict) -> tuple[str, str] | None:
    """What is wrong with a plan's per-state ``branch`` and ``stability`` (field, why), or
    None: when present, lists as long as ``path`` of -1 / 0 / +1 (or null) and of finite
    numbers (or null)."""
    path = data.get("path")
    count = len(path) if isinstance(path, list) else None
    for key, good in (("branch", lambda v: v is None or (type(v) is int and v in (-1, 0, 1))),
                      ("stability", lambda v: v is None or (_is_number(v) and math.isfinite(float(v))))):
        if key not in data:
            continue
        vals = data[key]
        if not isinstance(vals, list) or (count is not None and len(vals) != count):
            return key, "must be a list with one value per path state"
        for v in vals:
            if not good(v):
                return key, (f"values must be -1, 0, +1 or null, got {str(v)[:20]!r}" if key == "branch"
                             else f"values must be finite numbers or null, got {str(v)[:20]!r}")
    return None


def _check_robot_and_path(data: dict, src: str, hint: str, status: str) -> None:
    """The recorded robot (``robot_spec`` + ``robot_sha256``) and the path's configurations."""
    import numpy as np

    from ctrplan.robot import check_config_plausible, robot_from_record

    try:
        robot = robot_from_record(data, src)
    except InputError as exc:
        raise InputError(exc.source, exc.field, f"{exc.message} {hint}") from None
    path = data.get("path")
    if path is None:
        if status == "SUCCESS":
            raise InputError(src, "path", f"missing for a successful job {hint}")
        return
    try:
        q = np.asarray(path, dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise InputError(src, "path", f"must be a list of configurations {hint}") from None
    if q.size == 0 and status != "SUCCESS":
        return
    if q.ndim != 2 or len(q) == 0 or not np.all(np.isfinite(q)):
        raise InputError(src, "path", f"must be a non-empty list of finite configurations {hint}")
    if robot is not None:
        if q.shape[1] != robot.dof:
            raise InputError(src, "path", f"configurations have {q.shape[1]} values, the recorded "
                                          f"robot needs {robot.dof} {hint}")
        try:
            check_config_plausible(q, robot, src, row_offset=0, row_word="path state")
        except InputError as exc:
            raise InputError(src, exc.field, f"{exc.message} {hint}") from None


def _is_number(v: Any) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)
