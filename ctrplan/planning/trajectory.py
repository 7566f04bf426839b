"""Time parameterisation of a verified path: joint values over time within the actuator limits.

A plan's ``path`` is a polyline in joint space (rotations unwrapped): the motion that was
verified is the linear interpolation between consecutive states. The trajectory follows that
polyline exactly and stays within every joint's speed and acceleration limit
(:meth:`ctrplan.robot.Robot.joint_limits`, the robot YAML's ``actuators``):

1. **Stops.** Consecutive states on one straight line, same direction (the subdivision of one
   edge), are merged into one segment; every other state is a corner. The motion stops (zero
   velocity) at every corner: a polyline has no tangent at a corner, so following it with a
   finite acceleration needs zero speed there. A merged state lies within
   :data:`COLLINEAR_TOL` (rad or mm, per joint) of its segment: round-off of the subdivision.
2. **One segment, one scalar problem.** On a segment ``q(s) = q0 + s (q1 - q0)``, s in [0, 1],
   joint j's limits read ``|dq_j| |s'| <= v_j``, ``|dq_j| |s''| <= a_j``: the path-constrained
   problem is exactly the scalar one with ``|s'| <= min_j v_j / |dq_j|`` and ``|s''| <= min_j
   a_j / |dq_j|``. Ruckig (a well-kept, analytic, time-optimal trajectory generator; its
   object stays in this module) solves it rest to rest with unlimited jerk: the time-optimal
   bang-coast-bang profile, whose duration is :attr:`Trajectory.time_optimal_s` summed over
   segments. The geometric path is the segment itself, so the motion never leaves it: every
   state is ``q0 + s (q1 - q0)`` with s in [0, 1] (checked), by construction.
3. **Samples on a grid, corners on samples.** Each segment's duration is rounded up to a whole
   number of sample periods (``1 / rate_hz``) by slowing its profile uniformly in time
   (``s(t / k)``, k >= 1: speeds divide by k, accelerations by k^2, so every limit still
   holds). The stops then fall exactly on samples, and two consecutive samples always lie on
   one segment. Hence **interpolating linearly between consecutive samples stays on the
   verified polyline** (a segment is convex; the chord of two of its points is part of it),
   and on the part of it between the two samples (s is monotone on a rest-to-rest profile).
   A controller that interpolates with higher-order splines may overshoot a corner; stream
   the samples with linear interpolation (or at the same rate).
4. **Limits between samples.** The forward difference of two samples is the mean velocity
   over the period, the second difference over h^2 a hat-weighted mean of the acceleration:
   both lie within the limits exactly (up to round-off), whatever the rate.

The rounding costs at most one sample period per segment: ``duration_s <= time_optimal_s +
segments / rate_hz``. Units: t s, q rad and mm (``q = [alpha_1..n, beta_1..n]``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ctrplan.errors import InputError
from ctrplan.robot import Robot, robot_from_dict

#: Default sampling rate (Hz) of a trajectory: the rate at which CTR controllers commonly
#: stream set-points (10 ms); the rounding to whole periods then costs at most 10 ms a segment.
DEFAULT_RATE_HZ = 100.0
#: Accepted sampling rates (Hz).
RATE_RANGE = (1.0, 10_000.0)
#: Most samples one trajectory may have (~3 h at 100 Hz; 56 MB of samples for three tubes).
MAX_SAMPLES = 1_000_000
#: Largest per-joint distance (rad or mm) of a state from the straight line through its
#: neighbours for it to be merged into one segment (a state farther away is a corner, where the
#: motion stops); also the length below which a segment counts as no motion.
COLLINEAR_TOL = 1e-9


@dataclass(frozen=True)
class Trajectory:
    """A time-parameterised path.

    t : (T,) s, ``k / rate_hz``; q : (T, 2n) rad and mm, the joint values at t (rotations
    unwrapped, as in the path); qd, qdd : (T, 2n) their velocities (rad/s, mm/s) and
    accelerations (rad/s^2, mm/s^2) from the profile (at a stop and at a switch of the
    acceleration, the value of the segment or phase that starts there).
    duration_s : t[-1]; time_optimal_s : the sum over segments of the time-optimal duration the
    trajectory generator reports (before rounding to whole sample periods).
    stops : (S + 1, 2n) the states where the motion is at rest (the first and the last path
    state and every corner); stop_index : (S + 1,) int, their sample indices.
    max_speed, max_accel : (2n,) the joint limits used (:meth:`Robot.joint_limits`).
    """

    t: np.ndarray
    q: np.ndarray
    qd: np.ndarray
    qdd: np.ndarray
    rate_hz: float
    duration_s: float
    time_optimal_s: float
    stops: np.ndarray
    stop_index: np.ndarray
    max_speed: np.ndarray
    max_accel: np.ndarray

    @property
    def samples(self) -> int:
        return len(self.t)

    def write_csv(self, path: Any, robot: Robot) -> None:
        """Write ``trajectory.csv`` atomically: header ``t,alpha1..alphaN,beta1..betaN``, one
        row per sample (s, rad, mm; floats written exactly, as ``repr``)."""
        from ctrplan.io import atomic_path

        with atomic_path(path) as tmp:
            try:
                with open(tmp, "w", encoding="utf-8", newline="") as fh:
                    fh.write(",".join(["t", *robot.column_names]) + "\n")
                    for k in range(0, self.samples, 10_000):      # a block of rows at a time
                        block = np.column_stack([self.t[k:k + 10_000], self.q[k:k + 10_000]])
                        fh.write("".join(",".join(map(repr, r)) + "\n" for r in block.tolist()))
            except OSError as exc:
                raise InputError(str(path), "", f"cannot write ({exc.strerror})") from None

    def record(self) -> dict[str, Any]:
        """The plan.json fields of a trajectory (besides ``duration_s``)."""
        return {"rate_hz": float(self.rate_hz), "samples": int(self.samples),
                "time_optimal_s": float(self.time_optimal_s), "stops": int(len(self.stops))}


def check_rate(rate_hz: Any, source: str = "rate_hz") -> float:
    """A sampling rate (Hz): a finite number in :data:`RATE_RANGE`, else InputError."""
    lo, hi = RATE_RANGE
    ok = isinstance(rate_hz, (int, float)) and not isinstance(rate_hz, bool)
    if not (ok and math.isfinite(rate_hz) and lo <= rate_hz <= hi):
        raise InputError(source, "", f"must be a sampling rate in [{lo:g}, {hi:g}] Hz, got "
                                     f"{str(rate_hz)[:40]}")
    return float(rate_hz)


def stop_indices(path: np.ndarray, tol: float = COLLINEAR_TOL) -> np.ndarray:
    """Indices of the states of ``path`` (K, 2n) where the motion stops: the first, the last,
    and every state that is not within ``tol`` (per joint) of the straight line, in the same
    direction, from the previous stop to the next kept state. States that do not move from the
    previous stop (all joints within ``tol``) are dropped. Returns (S + 1,) int, increasing."""
    path = np.asarray(path, dtype=float)
    keep = [0]
    for k in range(1, len(path)):
        if np.max(np.abs(path[k] - path[keep[-1]])) > tol:
            keep.append(k)
    if len(keep) > 1 and keep[-1] != len(path) - 1:
        keep[-1] = len(path) - 1           # the path ends at its last state, exactly
    out = [keep[0]]
    run = [keep[0]]                        # the current straight run, first state = last stop
    for k in keep[1:]:
        if len(run) > 1 and not _on_chord(path[run[0]], path[run[1:]], path[k], tol):
            out.append(run[-1])
            run = [run[-1]]
        run.append(k)
    if len(keep) > 1:
        out.append(keep[-1])
    return np.asarray(out, dtype=int)


def _on_chord(a: np.ndarray, mids: np.ndarray, b: np.ndarray, tol: float) -> bool:
    """Whether the states ``mids`` (M, 2n) lie within ``tol`` (per joint) of the segment a -> b,
    in order along it (so the motion a -> mids -> b is the straight motion a -> b)."""
    c = b - a
    u = (mids - a) @ c / float(c @ c)
    if np.any(u <= 0.0) or np.any(u >= 1.0) or np.any(np.diff(u) <= 0.0):
        return False
    return bool(np.max(np.abs(a + u[:, None] * c[None, :] - mids)) <= tol)


def _profile(distance: float, speed: float, accel: float):
    """Ruckig's time-optimal rest-to-rest profile of one scalar from 0 to ``distance`` with
    ``|v| <= speed``, ``|a| <= accel`` and unlimited jerk."""
    from ruckig import InputParameter, Result, Ruckig
    from ruckig import Trajectory as RuckigTrajectory

    inp = InputParameter(1)
    inp.current_position, inp.target_position = [0.0], [distance]
    inp.current_velocity = inp.current_acceleration = [0.0]
    inp.target_velocity = inp.target_acceleration = [0.0]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [speed], [accel], [math.inf]
    out = RuckigTrajectory(1)
    result = Ruckig(1).calculate(inp, out)
    if result not in (Result.Working, Result.Finished):
        raise RuntimeError(f"ruckig could not time the segment ({result})")
    return out


def _segment(dq: np.ndarray, vmax: np.ndarray, amax: np.ndarray, rate: float):
    """The profile of one segment ``dq`` (2n,): (ruckig trajectory of s in units of ``scale``,
    scale, time-optimal duration s, sample periods m, time stretch k >= 1)."""
    moving = np.abs(dq) > 0
    # s in seconds of the slowest joint at full speed: speed limit 1, well scaled for ruckig
    scale = float(np.max(np.abs(dq[moving]) / vmax[moving]))
    accel = float(np.min(amax[moving] / np.abs(dq[moving]))) * scale
    prof = _profile(scale, 1.0, accel)
    t_opt = float(prof.duration)
    m = max(1, math.ceil(t_opt * rate))
    return prof, scale, t_opt, m, max(1.0, m / (rate * t_opt))


def _timed(robot: Robot, path: np.ndarray, rate_hz: float, tol: float):
    """(rate, stops (S + 1, 2n), segment profiles, limits) of a path; see _segment."""
    rate = check_rate(rate_hz)
    path = np.atleast_2d(np.asarray(path, dtype=float))
    if path.ndim != 2 or path.shape[1] != robot.dof or len(path) == 0:
        raise InputError("path", "", f"must be (K >= 1, {robot.dof}) configurations of robot "
                                     f"{robot.name!r}, got shape {path.shape}")
    if not np.all(np.isfinite(path)):
        raise InputError("path", "", "must be finite")
    vmax, amax = robot.joint_limits()
    stops = path[stop_indices(path, tol)]
    segs = [_segment(b - a, vmax, amax, rate) for a, b in zip(stops[:-1], stops[1:])]
    return rate, stops, segs, vmax, amax


def trajectory_duration(robot: Robot, path: np.ndarray, rate_hz: float = DEFAULT_RATE_HZ,
                        tol: float = COLLINEAR_TOL) -> tuple[float, float]:
    """``(duration_s, time_optimal_s)`` of :func:`time_parameterize`'s trajectory, without
    sampling it (any length)."""
    rate, _, segs, _, _ = _timed(robot, path, rate_hz, tol)
    return sum(s[3] for s in segs) / rate, float(sum(s[2] for s in segs))


def time_parameterize(robot: Robot, path: np.ndarray, rate_hz: float = DEFAULT_RATE_HZ,
                      tol: float = COLLINEAR_TOL) -> Trajectory:
    """The trajectory along ``path`` (K, 2n; rad, mm, rotations unwrapped: a plan's ``path``)
    within ``robot``'s joint limits, sampled at ``rate_hz`` (module docstring: how it never
    leaves the path, and why linear interpolation between its samples does not either)."""
    rate, stops, segs, vmax, amax = _timed(robot, path, rate_hz, tol)
    total = 1 + sum(s[3] for s in segs)
    if total > MAX_SAMPLES:
        raise InputError("trajectory", "samples", f"{total} samples at {rate:g} Hz is more than "
                         f"{MAX_SAMPLES}: lower the rate or check the robot's actuator limits")
    q = np.empty((total, robot.dof))
    qd, qdd = np.zeros_like(q), np.zeros_like(q)
    q[0] = stops[0]
    start = [0]
    for (a, b), (prof, scale, t_opt, m, k) in zip(zip(stops[:-1], stops[1:]), segs):
        k0, dq = start[-1], b - a
        s, v, acc = np.empty(m), np.empty(m), np.empty(m)
        for i in range(m):                       # samples 1..m of the segment
            p = prof.at_time(min((i + 1) / (rate * k), t_opt))
            s[i], v[i], acc[i] = p[0][0], p[1][0], p[2][0]
        s, v, acc = s / scale, v / (scale * k), acc / (scale * k * k)   # s in [0, 1], per s
        if np.any(s < -1e-9) or np.any(s > 1 + 1e-9) or np.any(np.diff(s) < -1e-12):
            raise RuntimeError("the segment profile left [0, 1] or went back")
        q[k0 + 1:k0 + m + 1] = a + np.clip(s, 0.0, 1.0)[:, None] * dq[None, :]
        q[k0 + m] = b                            # the stop itself, exactly
        qd[k0 + 1:k0 + m + 1] = v[:, None] * dq[None, :]
        qdd[k0 + 1:k0 + m + 1] = acc[:, None] * dq[None, :]
        qd[k0 + m] = 0.0
        p0 = prof.at_time(0.0)                   # the acceleration the segment starts with
        qdd[k0] = p0[2][0] / (scale * k * k) * dq
        qdd[k0 + m] = 0.0
        start.append(k0 + m)
    t = np.arange(total) / rate
    return Trajectory(t=t, q=q, qd=qd, qdd=qdd, rate_hz=rate, duration_s=float(t[-1]),
                      time_optimal_s=float(sum(s[2] for s in segs)), stops=stops,
                      stop_index=np.asarray(start, dtype=int), max_speed=vmax, max_accel=amax)


def plan_trajectory(result: Any, rate_hz: float = DEFAULT_RATE_HZ,
                    robot: Robot | None = None) -> Trajectory:
    """The trajectory of a :class:`~ctrplan.planning.plan.PlanResult` (its ``path``) with the
    limits of ``robot``, by default the robot that planned it (``result.robot_spec``, with its
    ``actuators``). Its ``duration_s`` is what plan.json's ``duration_s`` reports
    (``dataclasses.replace(result, duration_s=traj.duration_s)`` records it in the result)."""
    if robot is None:
        spec = getattr(result, "robot_spec", None)
        if spec is None:
            raise InputError("plan", "robot_spec", "the result records no robot: pass robot=")
        robot = robot_from_dict(spec, source="plan: robot_spec")
    path = np.asarray(result.path, dtype=float)
    if path.size == 0:
        raise InputError("plan", "path", f"no path to time ({getattr(result, 'status', '?')})")
    return time_parameterize(robot, path, rate_hz)


def file_sha256(path: Any) -> str:
    """sha256 (hex) of a file's bytes, read in blocks: plan.json's ``trajectory.sha256``."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def read_trajectory(path: Any, robot: Robot, frames: int) -> tuple[np.ndarray, np.ndarray, int]:
    """``frames`` samples spread evenly over a trajectory CSV (:meth:`Trajectory.write_csv`:
    ``t`` in s from 0, strictly increasing; the robot's configurations, plausible and within
    its joint constraints): ``(t (F,), q (F, 2n), rows)``, the first and the last row included.
    The file is streamed twice (checked and counted, then picked): memory stays bounded by a
    chunk whatever its length. Errors name the file, the column and the row."""
    count = 0
    last_t = -math.inf
    for first, t, _q in _chunks(path, robot):
        if count == 0 and t[0] < 0:
            raise InputError(str(path), "t (row 2)", f"must start at 0 s or later, got {t[0]:g}")
        step = np.diff(np.concatenate([[last_t], t]))
        if np.any(step <= 0):
            k = int(np.argmax(step <= 0))
            raise InputError(str(path), f"t (row {first + k})", "times must increase strictly")
        last_t, count = float(t[-1]), count + len(t)
    idx = np.unique(np.linspace(0, count - 1, min(max(frames, 2), count)).round().astype(int))
    out_t, out_q, done = [], [], 0
    for _, t, q in _chunks(path, robot):
        sel = idx[(idx >= done) & (idx < done + len(t))] - done
        out_t.append(t[sel])
        out_q.append(q[sel])
        done += len(t)
    return np.concatenate(out_t), np.concatenate(out_q), count


def _chunks(path: Any, robot: Robot):
    """(first row number, t (k,), q (k, 2n)) per chunk of a trajectory CSV, checked."""
    from ctrplan.io import check_tube_columns, iter_csv_rows, parse_float_columns

    for header, first, rows in iter_csv_rows(path, "configs"):
        if first == 2:
            check_tube_columns(path, header, robot)
        if not rows:
            raise InputError(str(path), "rows", "no samples (only a header)")
        a = parse_float_columns(path, header, rows, ["t", *robot.column_names], first_row=first)
        q = a[:, 1:]
        robot.check_plausible(q, str(path), row_offset=first)
        ok = robot.is_valid(q)
        if not ok.all():
            k = int(np.argmin(ok))
            raise InputError(str(path), f"row {k + first}", "violates the joint constraints of "
                                                            f"robot {robot.name!r}")
        yield first, a[:, 0], q
