"""Simulated measurements: experiment designs and data with hidden effects.

Experiment designs (like the study the calibration workflow is modelled on), each a list of
sweeps; a sweep is one continuous motion, rows in order of motion:

``feed``            tube 1 (innermost) is fed from fully retracted to fully extended and back,
                    the other joints held (first sweep at all alpha = 0, then random rotations).
``inner_rotation``  tube 1 turns a full turn forward and back, at a held insertion per sweep.
``outer_rotation``  tube n (outermost) does the same.
``random_walk``     every joint moves back and forth along a piecewise-linear random path
                    through valid configurations (rotation legs of 0.1 to 0.5 turn, alternating direction).

``time`` is the row index times ``dt`` (s), continuous over the whole data set.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping, Sequence

import numpy as np

from ctrplan.errors import InputError
from ctrplan.measured import MeasuredData
from ctrplan.robot import Robot

log = logging.getLogger("ctrplan")

EXPERIMENTS = ("feed", "inner_rotation", "outer_rotation", "random_walk")


def _held_config(robot: Robot, rng: np.random.Generator, first: bool) -> np.ndarray:
    q = robot.sample(1, rng)[0]
    if first:
        q[: robot.n] = 0.0
    return q


def _feed_range(robot: Robot, q: np.ndarray) -> tuple[float, float]:
    """Range of beta1 that keeps q valid with the other joints held."""
    n = robot.n
    lo_b, hi_b = robot.beta_bounds()
    L = robot.lengths
    lo = lo_b[0]
    hi = hi_b[0]
    if n > 1:
        lo = max(lo, q[n + 1] + L[1] - L[0])
        hi = min(hi, q[n + 1])
    return lo, hi


def experiment(name: str, robot: Robot, rows: int, sweeps: int = 4,
               seed: int | np.random.Generator | None = 0) -> tuple[np.ndarray, np.ndarray]:
    """Configurations ``(rows, 2n)`` and sweep ids ``(rows,)`` of one experiment design."""
    if name not in EXPERIMENTS:
        raise InputError("--experiment", name, f"unknown experiment; known: {', '.join(EXPERIMENTS)}")
    rng = np.random.default_rng(seed)
    n = robot.n
    sweeps = max(1, min(int(sweeps), max(1, rows // 4)))
    per = np.full(sweeps, rows // sweeps)
    per[: rows - per.sum()] += 1
    qs: list[np.ndarray] = []
    ids: list[np.ndarray] = []
    for k in range(sweeps):
        m = int(per[k])
        if m == 0:
            continue
        half = np.concatenate([np.linspace(0.0, 1.0, (m + 1) // 2),
                               np.linspace(1.0, 0.0, m - (m + 1) // 2 + 1)[1:]])  # there and back
        if name == "feed":
            for _ in range(100):
                q0 = _held_config(robot, rng, first=k == 0)
                # hold the outer tubes well extended so the inner tube has room to travel
                q0[n + 1:] = 0.0 if k == 0 else q0[n + 1:] * 0.3
                lo, hi = _feed_range(robot, q0)
                q0[n] = hi
                if hi - lo > 1.0 and robot.is_valid(q0[None])[0]:
                    break
            q = np.repeat(q0[None], m, axis=0)
            q[:, n] = lo + (hi - lo) * half
        elif name in ("inner_rotation", "outer_rotation"):
            q0 = _held_config(robot, rng, first=k == 0)
            if k == 0:
                q0[n:] = robot.beta_bounds()[1]  # fully extended
                q0[n:] = np.clip(q0[n:], *robot.beta_bounds())
                if not robot.is_valid(q0[None])[0]:
                    q0 = _held_config(robot, rng, first=True)
            j = 0 if name == "inner_rotation" else n - 1
            q = np.repeat(q0[None], m, axis=0)
            q[:, j] = q0[j] + 2.0 * math.pi * half
        else:  # random_walk
            legs = max(2, m // 12)
            way = robot.sample(legs + 1, rng)
            # alternate the direction of every rotation leg: back and forth
            sign = rng.choice([-1.0, 1.0], size=n) * (-1.0) ** np.arange(legs)[:, None]
            steps = sign * rng.uniform(0.2 * math.pi, math.pi, (legs, n))
            a = np.cumsum(np.concatenate([way[:1, :n], steps]), axis=0)
            way[:, :n] = a
            t = np.linspace(0.0, legs, m)
            q = np.stack([np.interp(t, np.arange(legs + 1), way[:, c]) for c in range(2 * n)], axis=1)
        qs.append(q)
        ids.append(np.full(m, f"{name}{k + 1}", dtype=object))
    q = np.concatenate(qs)
    ok = robot.is_valid(q)
    if not ok.all():  # interpolation stays in the (convex) valid set; guard against round-off
        q = q[ok]
        ids = [np.concatenate(ids)[ok]]
    return q, np.concatenate(ids)


def design(robot: Robot, experiments: Sequence[str], rows: int, sweeps: int = 4,
           seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Several experiments one after the other, ``rows`` rows each."""
    rng = np.random.default_rng(seed)
    parts = [experiment(e, robot, rows, sweeps, rng) for e in experiments]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def measure(model, q: np.ndarray, sweep: np.ndarray | None = None, noise_mm: float = 0.0,
            points: int = 0, seed: int = 0, dt: float = 0.1) -> MeasuredData:
    """Simulated measurements of ``q`` (rows in order of motion) by a shape model.

    model : an :class:`~ctrplan.shape.effects.EffectModel` (or any shape model).
    noise_mm : standard deviation of Gaussian noise per coordinate (mm), seeded by ``seed``.
    points : record that many backbone points per row (0: tip only).
    Rows whose shape is not finite are dropped (logged); non-converged shapes are kept.
    """
    if noise_mm < 0 or not math.isfinite(noise_mm):
        raise InputError("--noise", "", f"must be a finite number >= 0, got {noise_mm}")
    m = max(2, int(points))
    shp = _shapes(model, q, m, sweep)
    pts = np.asarray(shp.points, dtype=float)
    good = np.all(np.isfinite(pts), axis=(1, 2))
    bad_conv = int((~np.asarray(shp.ok) & good).sum())
    if bad_conv:
        log.warning("%d of %d simulated shapes did not converge (kept)", bad_conv, len(q))
    if not good.all():
        log.warning("dropping %d rows whose simulated shape is not finite", int((~good).sum()))
    rng = np.random.default_rng(seed)
    pts = pts + rng.normal(0.0, noise_mm, pts.shape) if noise_mm > 0 else pts
    time = np.arange(len(q)) * dt
    data = MeasuredData(q=q, tip=pts[:, -1, :].copy(), time=time,
                        sweep=None if sweep is None else np.asarray(sweep, dtype=object),
                        points=pts if points else None)
    return data.subset(good) if not good.all() else data


def _shapes(model, q: np.ndarray, m: int, sweep: np.ndarray | None, big: int = 4000):
    """Shapes of rows in order of motion; big batches go over every core (the order-dependent
    joint stage, i.e. friction, runs first on the whole sequence)."""
    from ctrplan.shape.effects import EffectModel, prepare

    if len(q) < big:
        kw = {"sweep": sweep} if sweep is not None and _accepts_sweep(model) else {}
        return model.shape(q, m, **kw)
    from ctrplan.shape.dataset import simulate_shapes

    if isinstance(model, EffectModel):
        joint = {k: v for k, v in model.effects.items() if k in ("friction", "joint_offset")}
        q = prepare(model.robot, model.base, joint, q, sweep).q
        rest = {k: v for k, v in model.effects.items() if k not in joint}
        model = model.with_effects(rest)
    return simulate_shapes(model, q, m)


def _accepts_sweep(model) -> bool:
    import inspect

    try:
        return "sweep" in inspect.signature(model.shape).parameters
    except (TypeError, ValueError):
        return False


def simulate(robot: Robot, q: np.ndarray, effects: Mapping[str, Mapping[str, float]] | None = None,
             base: str = "rigid", sweep: np.ndarray | None = None, noise_mm: float = 0.0,
             points: int = 0, seed: int = 0, step_mm: float | None = None) -> MeasuredData:
    """Measured data with hidden ``effects`` on a ``base`` model (see :func:`measure`).

    step_mm : integrator step of the simulated "truth" (default: the model's default).
    """
    from ctrplan.shape.effects import EffectModel
    from ctrplan.shape.physics import PhysicsConfig

    cfg = PhysicsConfig(step_mm=step_mm) if step_mm else None
    model = EffectModel(robot, base, effects, cfg)
    return measure(model, q, sweep, noise_mm, points, seed)
