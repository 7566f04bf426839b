"""Batched validity of configurations, edges and whole paths (numpy only, no OMPL).

A configuration is valid when it satisfies the joint constraints, the shape model produced a
trustworthy backbone, and the backbone (swept by the tube radii) does not touch the scene.
Validity is a pure function of q: nothing here changes the world.

Edges are straight lines in joint space (rotations along the shorter arc) interpolated so that
the estimated backbone motion between consecutive states is at most ``resolution_mm``; the
estimate is ``alpha_weight_mm * sum|d alpha| + ||d beta||`` (mm), the same metric OMPL uses.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from ctrplan.robot import Robot
from ctrplan.shape.base import Shape

#: Slack (mm) on the joint constraints for interpolated states (round-off only).
JOINT_TOL_MM = 1e-7


@dataclass(frozen=True)
class ValidatorConfig:
    """Settings of :class:`BatchValidator`.

    resolution_mm : largest estimated backbone motion between two checked states of an edge.
    points : backbone points per shape used for collision checking.
    alpha_weight_mm : mm of backbone motion per rad of rotation (the metric's weight). Measured
        on seed1 (4000 random small motions, physics model): the largest displacement of any
        backbone point is at most ~0.95 x the metric with 30 mm/rad (median 0.3 x), so the
        metric bounds the backbone motion in practice and ``resolution_mm`` is a real step.
    cache_size : single-state results kept (OMPL asks again for start/goal states).
    """

    resolution_mm: float = 2.0
    points: int = 24
    alpha_weight_mm: float = 30.0
    cache_size: int = 4096

    def __post_init__(self) -> None:
        if not (self.resolution_mm > 0 and math.isfinite(self.resolution_mm)):
            raise ValueError("resolution_mm must be a positive number")
        if self.points < 2:
            raise ValueError("points must be >= 2")
        if not self.alpha_weight_mm > 0:
            raise ValueError("alpha_weight_mm must be > 0")


@dataclass
class Counters:
    """How much validation work was done (states are configurations turned into shapes)."""

    states: int = 0
    edges: int = 0
    edges_invalid: int = 0
    shape_calls: int = 0
    collision_calls: int = 0
    cache_hits: int = 0
    single_states: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


def wrap(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to (-pi, pi]."""
    return math.pi - np.mod(math.pi - np.asarray(a, dtype=float), 2.0 * math.pi)


def joint_delta(q0: np.ndarray, q1: np.ndarray, n: int) -> np.ndarray:
    """q1 - q0 with rotations along the shorter arc. q0, q1 : (..., 2n)."""
    d = np.asarray(q1, dtype=float) - np.asarray(q0, dtype=float)
    d[..., :n] = wrap(d[..., :n])
    return d


def motion_mm(q0: np.ndarray, q1: np.ndarray, n: int, alpha_weight_mm: float) -> np.ndarray:
    """Estimated backbone motion (mm) between configurations. q0, q1 : (..., 2n) -> (...)."""
    d = joint_delta(q0, q1, n)
    return alpha_weight_mm * np.abs(d[..., :n]).sum(-1) + np.linalg.norm(d[..., n:], axis=-1)


def interpolate(q0: np.ndarray, q1: np.ndarray, n: int, alpha_weight_mm: float,
                resolution_mm: float) -> np.ndarray:
    """States along the edge q0 -> q1, both ends included, at most ``resolution_mm`` apart.

    Returns (k + 1, 2n) with ``k = max(1, ceil(motion / resolution))``; rotations follow the
    shorter arc (as OMPL's SO2 interpolation) and are wrapped to (-pi, pi].
    """
    q0 = np.asarray(q0, dtype=float)
    d = joint_delta(q0, q1, n)
    dist = alpha_weight_mm * np.abs(d[:n]).sum() + np.linalg.norm(d[n:])
    k = max(1, int(math.ceil(dist / resolution_mm - 1e-9)))
    t = np.linspace(0.0, 1.0, k + 1)[:, None]
    out = q0[None, :] + t * d[None, :]
    out[:, :n] = wrap(out[:, :n])
    out[-1, n:] = np.asarray(q1, dtype=float)[n:]  # exact end (no round-off in beta)
    return out


def interpolate_path(path: np.ndarray, n: int, alpha_weight_mm: float,
                     resolution_mm: float) -> tuple[np.ndarray, np.ndarray]:
    """All states of a waypoint path (K, 2n) at ``resolution_mm``.

    Returns (states (S, 2n), segment (S,) int): the segment index each state belongs to
    (a waypoint belongs to the segment that starts at it; the last one to the last segment).
    """
    path = np.atleast_2d(np.asarray(path, dtype=float))
    if len(path) == 1:
        return path.copy(), np.zeros(1, dtype=int)
    states, seg = [], []
    for j in range(len(path) - 1):
        e = interpolate(path[j], path[j + 1], n, alpha_weight_mm, resolution_mm)
        if j < len(path) - 2:
            e = e[:-1]
        states.append(e)
        seg.append(np.full(len(e), j))
    return np.concatenate(states), np.concatenate(seg)


def project_joints(robot: Robot, q: np.ndarray) -> np.ndarray:
    """Move configurations onto the joint-constraint set (alphas wrapped, betas clipped).

    q : (B, 2n). Betas are clipped from the outermost tube inward: each tube between its own
    bounds, behind the tube around it, and far enough out to reach at least as far. The result is
    valid whenever the robot's constraints admit a configuration with that outer tube position.
    """
    q = np.array(q, dtype=float, copy=True)
    n = robot.n
    q[:, :n] = wrap(q[:, :n])
    lo, hi = robot.beta_bounds()
    L = robot.lengths
    b = q[:, n:]
    b[:, -1] = np.clip(b[:, -1], max(lo[-1], -L[-1]), hi[-1])
    for i in range(n - 2, -1, -1):
        lower = np.maximum(lo[i], b[:, i + 1] + L[i + 1] - L[i])
        upper = np.minimum(hi[i], b[:, i + 1])
        b[:, i] = np.minimum(np.maximum(b[:, i], lower), upper)
    q[:, n:] = b
    return q


@dataclass
class PathCheck:
    """Exact (FCL) check of a path at fine resolution.

    states : (S, 2n) checked states; segment : (S,) segment of each; collides : (S,) bool;
    clearance_mm : (S,) signed; contact : (S,) mesh names; first_bad : index of the first bad
    state or -1; bad_segments : sorted segment indices containing a bad state.
    """

    states: np.ndarray
    segment: np.ndarray
    collides: np.ndarray
    clearance_mm: np.ndarray
    contact: np.ndarray
    first_bad: int
    bad_segments: list[int] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return self.first_bad < 0

    @property
    def min_clearance_mm(self) -> float:
        return float(np.min(self.clearance_mm)) if len(self.clearance_mm) else float("nan")


class BatchValidator:
    """Validity of configurations and edges with one shape call and one collision query per batch.

    Parameters
    ----------
    robot : Robot
    model : ShapeModel (``shape(q, points) -> Shape``)
    world : CollisionWorld-like (``collides``, ``first_collision``, ``check_exact`` on a Shape in
        the robot base frame; shapes with ``ok=False`` count as colliding)
    config : ValidatorConfig
    """

    def __init__(self, robot: Robot, model, world, config: ValidatorConfig | None = None):
        self.robot = robot
        self.model = model
        self.world = world
        self.config = config or ValidatorConfig()
        self.n = robot.n
        self.counters = Counters()
        self._cache: OrderedDict[bytes, bool] = OrderedDict()

    # ------------------------------------------------------------------ batches of states
    def joint_valid(self, q: np.ndarray) -> np.ndarray:
        """(B,) bool: finite and inside the joint constraints (with round-off slack)."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        finite = np.all(np.isfinite(q), axis=1)
        with np.errstate(invalid="ignore"):
            ok = np.all(self.robot.constraint_violations(q) >= -JOINT_TOL_MM, axis=1)
        return finite & ok

    def shapes(self, q: np.ndarray, points: int | None = None) -> Shape:
        """Shapes of a batch (one model call). q : (B, 2n)."""
        self.counters.shape_calls += 1
        self.counters.states += len(q)
        return self.model.shape(np.asarray(q, dtype=float), points=points or self.config.points)

    def states_valid(self, q: np.ndarray) -> np.ndarray:
        """(B,) bool validity of a batch: one shape call, one collision query."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        ok = self.joint_valid(q)
        if ok.any():
            idx = np.flatnonzero(ok)
            shape = self.shapes(q[idx])
            self.counters.collision_calls += 1
            ok[idx] = ~np.asarray(self.world.collides(shape), dtype=bool)
        return ok

    def first_invalid(self, q: np.ndarray) -> int:
        """Index of the first invalid state of an ordered batch (B, 2n), or -1 if all are valid.

        Joint limits are checked for all states; the states before the first joint violation go
        through one shape call and one collision query that stops at the first collision.
        """
        q = np.atleast_2d(np.asarray(q, dtype=float))
        jv = self.joint_valid(q)
        k0 = int(np.argmin(jv)) if not jv.all() else len(q)
        if k0 == 0:
            return 0
        shape = self.shapes(q[:k0])
        self.counters.collision_calls += 1
        k = int(self.world.first_collision(shape))
        if k >= 0:
            return k
        return k0 if k0 < len(q) else -1

    # ------------------------------------------------------------------ OMPL callbacks
    def edge_states(self, q0: np.ndarray, q1: np.ndarray, resolution_mm: float | None = None) -> np.ndarray:
        c = self.config
        return interpolate(q0, q1, self.n, c.alpha_weight_mm, resolution_mm or c.resolution_mm)

    def edge_valid(self, q0: np.ndarray, q1: np.ndarray) -> bool:
        """Whether the straight edge q0 -> q1 (both ends included) is valid."""
        self.counters.edges += 1
        ok = self.first_invalid(self.edge_states(q0, q1)) < 0
        if not ok:
            self.counters.edges_invalid += 1
        return ok

    def state_valid(self, q: np.ndarray) -> bool:
        """Validity of one configuration (2n,), cached: OMPL asks per state for starts/goals."""
        key = np.round(np.asarray(q, dtype=float), 12).tobytes()
        hit = self._cache.get(key)
        if hit is not None:
            self.counters.cache_hits += 1
            self._cache.move_to_end(key)
            return hit
        self.counters.single_states += 1
        ok = bool(self.states_valid(np.asarray(q, dtype=float)[None])[0])
        self._cache[key] = ok
        if len(self._cache) > self.config.cache_size:
            self._cache.popitem(last=False)
        return ok

    def remember(self, q: np.ndarray, valid: np.ndarray) -> None:
        """Seed the single-state cache with results already computed in a batch."""
        for row, ok in zip(np.atleast_2d(q), np.atleast_1d(valid)):
            self._cache[np.round(row, 12).tobytes()] = bool(ok)

    def sample_valid(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """Up to ``count`` valid configurations sampled uniformly (one batch)."""
        q = self.robot.sample(count, seed=rng)
        ok = self.states_valid(q)
        self.remember(q, ok)
        return q[ok]

    def sample_valid_near(self, q: np.ndarray, distance: float, count: int,
                          rng: np.random.Generator) -> np.ndarray:
        """Valid configurations within about ``distance`` (metric mm) of q (one batch)."""
        n = self.n
        step = np.empty((count, 2 * n))
        step[:, :n] = rng.uniform(-1, 1, (count, n)) * distance / (n * self.config.alpha_weight_mm)
        step[:, n:] = rng.uniform(-1, 1, (count, n)) * distance / math.sqrt(n)
        cand = project_joints(self.robot, np.asarray(q, dtype=float)[None] + step)
        ok = self.states_valid(cand)
        self.remember(cand, ok)
        return cand[ok]

    def shortcut(self, path: np.ndarray, max_edges: int = 200) -> np.ndarray:
        """Greedy shortcutting: from each kept waypoint jump to the farthest later waypoint
        reachable by a valid straight edge (deterministic; adjacent waypoints are kept as is)."""
        path = np.atleast_2d(np.asarray(path, dtype=float))
        out = [path[0]]
        i, tried = 0, 0
        while i < len(path) - 1:
            nxt = i + 1
            for j in range(len(path) - 1, i + 1, -1):
                if tried >= max_edges:
                    break
                tried += 1
                if self.edge_valid(path[i], path[j]):
                    nxt = j
                    break
            out.append(path[nxt])
            i = nxt
        return np.array(out)

    # ------------------------------------------------------------------ exact path check
    def check_path(self, path: np.ndarray, resolution_mm: float, points: int | None = None,
                   fcl_all: bool = True, chunk: int = 2048) -> PathCheck:
        """Check every state of a path at ``resolution_mm`` with exact verdicts.

        fcl_all : every state through FCL (``world.check_exact``); otherwise ``world.check``,
            whose verdicts are FCL's except where the conservative prefilter proves them.
        """
        c = self.config
        states, seg = interpolate_path(path, self.n, c.alpha_weight_mm, resolution_mm)
        S = len(states)
        collides = np.zeros(S, dtype=bool)
        clearance = np.full(S, np.inf)
        contact = np.full(S, "", dtype=object)
        jv = self.joint_valid(states)
        for a in range(0, S, chunk):
            b = min(S, a + chunk)
            shape = self.shapes(states[a:b], points=points)
            self.counters.collision_calls += 1
            rep = self.world.check_exact(shape) if fcl_all else self.world.check(shape)
            collides[a:b] = np.asarray(rep.collides, dtype=bool)
            clearance[a:b] = np.asarray(rep.clearance_mm, dtype=float)
            contact[a:b] = np.asarray(rep.contact, dtype=object)
        collides |= ~jv
        bad = np.flatnonzero(collides)
        first = int(bad[0]) if len(bad) else -1
        return PathCheck(states, seg, collides, clearance, contact, first,
                         sorted({int(s) for s in seg[bad]}))
