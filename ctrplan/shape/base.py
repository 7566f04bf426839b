"""The shape-model protocol and the batched shape result shared by every model."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numba as nb
import numpy as np

from ctrplan.robot import Robot


@dataclass(frozen=True)
class Shape:
    """Backbones of a batch of configurations, in the robot base frame.

    points : (B, m, 3) float, mm — evenly spaced in arc length from s = 0 (constraint plane)
        to the tip, inclusive.
    s : (B, m) float, mm — arc length of each point.
    radius : (B, m) float, mm — outer radius of the outermost tube present at each point.
    ok : (B,) bool — False where the model could not produce a trustworthy shape (the shooting
        did not converge, or a point, arc length, radius or pad is not finite); callers must treat such shapes as invalid.
    pad : (B, m - 1) float, mm, or None — the model's bound of the distance between its
        continuous backbone and the chord between consecutive points (sagitta of its curvature
        bound, tangent jumps, loads, polynomial bound; see :mod:`ctrplan.shape.bounds`). Collision
        capsules grow by it. None: the model states no bound (the points are taken as a polyline
        unless the collision world is given a curvature bound).
    """

    points: np.ndarray
    s: np.ndarray
    radius: np.ndarray
    ok: np.ndarray
    pad: np.ndarray | None = None

    def __post_init__(self) -> None:
        # Every model's result passes here: a shape with a non-finite point, arc length, radius
        # or pad (a model file edited to a zero span, an overflowing solver) is never "ok", so
        # collision checking counts it as a collision instead of reporting it free.
        pts = np.asarray(self.points, dtype=float)
        ok = np.asarray(self.ok, dtype=bool)
        if pts.ndim != 3 or len(pts) != len(ok):
            return
        fin = np.isfinite(pts).all(axis=(1, 2))
        for extra in (self.s, self.radius, self.pad):
            if extra is not None:
                a = np.asarray(extra, dtype=float)
                if a.ndim >= 1 and len(a) == len(ok):
                    fin &= np.isfinite(a.reshape(len(a), -1)).all(axis=1)
        if not fin.all():
            object.__setattr__(self, "ok", ok & fin)

    @property
    def tip(self) -> np.ndarray:
        """(B, 3) tip positions, mm."""
        return self.points[:, -1, :]

    def __len__(self) -> int:
        return int(self.points.shape[0])

    def __getitem__(self, index) -> Shape:
        """The configurations ``index`` selects (a slice, integer array or boolean mask), every
        per-configuration field included (the pad too: a sub-batch keeps its capsules)."""
        if isinstance(index, (int, np.integer)):
            index = slice(int(index), int(index) + 1 or None)
        return Shape(points=self.points[index], s=self.s[index], radius=self.radius[index],
                     ok=np.asarray(self.ok)[index],
                     pad=None if self.pad is None else self.pad[index])


@runtime_checkable
class ShapeModel(Protocol):
    """Anything that turns configurations into backbones (physics or learned).

    What planning needs beyond these four (the direction of motion, an error bound, a curvature
    bound, ...) is optional; :func:`ctrplan.shape.planning_model.planning_model` reads it once
    into a typed :class:`~ctrplan.shape.planning_model.PlanningModel` (its docstring lists the
    optional attributes)."""

    robot: Robot
    name: str

    def shape(self, q: np.ndarray, points: int = 20) -> Shape:
        """Backbones with radii and status. q : (B, 2n) float, rad and mm."""
        ...

    def backbone(self, q: np.ndarray, points: int = 20) -> np.ndarray:
        """(B, points, 3) backbone points, mm, robot base frame."""
        ...


def radius_along(robot: Robot, q: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Outer radius (mm) of the outermost tube present at arc lengths ``s``.

    q : (B, 2n); s : (B, m) mm. Returns (B, m). A tube is present up to and including its
    distal end; past the tip the innermost tube's radius is used.
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    n = robot.n
    s = np.atleast_2d(np.asarray(s, dtype=float))
    rows = np.broadcast_shapes((len(q),), (len(s),))[0]             # (B, n) ends, (B, m) s
    ends = np.ascontiguousarray(np.broadcast_to(q[:, n:] + robot.lengths, (rows, n)))
    s = np.ascontiguousarray(np.broadcast_to(s, (rows, s.shape[1])))
    out = np.empty(s.shape)
    _radius_along(ends, robot.array("od") / 2.0, s, out)
    return out


@nb.njit(cache=True)
def _radius_along(ends, half_od, s, out):
    """out[b, j] = half_od of the outermost tube present at s[b, j] (tubes innermost first: the
    largest index i with s <= ends[b, i] + 1e-9; 0 where none is)."""
    B, m = s.shape
    n = ends.shape[1]
    for b in range(B):
        for j in range(m):
            idx = 0
            for i in range(n):
                if s[b, j] <= ends[b, i] + 1e-9:
                    idx = i
            out[b, j] = half_od[idx]


def check_q(robot: Robot, q: np.ndarray) -> np.ndarray:
    """Coerce q to a finite float (B, 2n) array or raise ValueError."""
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:
        q = q[None, :]
    if q.ndim != 2 or q.shape[1] != robot.dof:
        raise ValueError(f"q must have shape (B, {robot.dof}) for robot {robot.name!r}, got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError("q contains NaN or infinite values")
    return q


# --- Cross-model contracts (direction of motion, error bounds) -------------------------------
#
# Direction of motion.  Models whose output depends on the direction of the last motion of each
# joint (friction / hysteresis: an EffectModel with friction, a direction-aware LearnedModel) set
# ``needs_direction = True`` and take ``shape(q, points, direction=D)`` with ``D`` of shape
# (B, 2n) in {-1, 0, +1}: the sign of the last nonzero motion of each joint, same layout as q
# (alpha_1..n, beta_1..n); 0 = unknown / never moved.  Callers pass ``direction=`` only to models
# with ``needs_direction``; other models need not accept it.
#
# Error bound.  A model may carry ``error_quantiles``: a dict with keys p50, p95, p99, max (mm),
# the held-out quantiles of its max deviation along the shaft (learned models) or of its tip
# residual (calibrated models), or None.  ``model_error_bound`` is the margin planning uses.
# ``error_bound`` ("measured" / "surrogate") says where the bound was measured: only a measured
# one makes the model calibrated (``ctrplan.shape.error_bounds``).

def needs_direction(model) -> bool:
    """True when ``model.shape`` must be given the direction of the last motion."""
    return bool(getattr(model, "needs_direction", False))


def direction_from_rows(q: np.ndarray, sweep: np.ndarray | None = None,
                        tol: float = 1e-9) -> np.ndarray:
    """Direction of the last motion of each joint, from rows taken in order of motion.

    q : (B, 2n); sweep : (B,) ids or None (one sweep). Returns (B, 2n) in {-1, 0, +1}: for row k
    the sign of the last change larger than ``tol`` among rows <= k of the same sweep (0 before
    the first change). Rotations are compared on the circle (wrapped differences).
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    b, d = q.shape
    out = np.zeros((b, d), dtype=np.int8)
    if b == 0:
        return out
    n = d // 2
    diff = np.diff(q, axis=0)
    diff[:, :n] = (diff[:, :n] + np.pi) % (2 * np.pi) - np.pi
    step = np.where(diff > tol, 1, np.where(diff < -tol, -1, 0)).astype(np.int8)
    # row k's candidate is the step into it; a new sweep resets (candidate 0, marked); each
    # row then takes the latest marked or nonzero candidate at or before it (a forward fill)
    cand = np.zeros((b, d), dtype=np.int8)
    cand[1:] = step
    reset = np.zeros(b, dtype=bool)
    reset[0] = True
    if sweep is not None:
        sw = np.asarray(sweep)
        reset[1:] = sw[1:] != sw[:-1]
        cand[reset] = 0
    mark = (cand != 0) | reset[:, None]
    src = np.maximum.accumulate(np.where(mark, np.arange(b)[:, None], 0), axis=0)
    out[:] = np.take_along_axis(cand, src, axis=0)
    return out


def model_error_bound(model, quantile: str = "p99") -> float:
    """The model's error bound (mm) for use as a planning margin: ``error_quantiles[quantile]``,
    or 0.0 when the model carries none (the physics model is its own reference)."""
    eq = getattr(model, "error_quantiles", None)
    if not eq:
        return 0.0
    v = float(eq.get(quantile, eq.get("max", 0.0)))
    if not np.isfinite(v) or v < 0:
        raise ValueError(f"model error quantile {quantile} must be a finite value >= 0, got {v}")
    return v
