"""Batched validity of configurations, edges and whole paths (numpy only, no OMPL).

A configuration is valid when it satisfies the joint constraints, the shape model produced a
trustworthy backbone, and the backbone (swept by the tube radii) does not touch the scene.
Validity is a pure function of q: nothing here changes the world.

Direction of motion. For a model whose shape depends on the direction of the last motion
(``PlanningModel.needs_direction``: friction), validity stays a pure function of q and the motion: a
state on an edge is evaluated with the edge's direction (sign of ``q1 - q0`` per joint); where a
joint's direction is unknown (a joint that does not move on the edge, a single state) both
``+1`` and ``-1`` are checked and the state is valid only if both are (the worst case of the
dead band).

Edges are straight lines in joint space (rotations along the shorter arc) interpolated so that
the estimated backbone motion between consecutive states is at most ``resolution_mm``; the
estimate is ``alpha_weight_mm * sum|d alpha| + ||d beta||`` (mm), the same metric OMPL uses.

Motion between checked states (:meth:`BatchValidator.check_path`, the final verification).
The bound comes from the model along each segment (:mod:`ctrplan.planning.motion`,
:func:`ctrplan.shape.bounds.motion_cover`): the backbones at the segment's two states and their
velocities along it (finite differences) bound how far every backbone point (at a fixed
arc-length fraction) and every capsule's chord pad can move on the segment. The tube radius at
each fraction is that of t0 or of t1 (tube ends move linearly), so the segment is covered when
both end states are at least the largest capsule cover from the anatomy (their conservative
clearances certify it), or when both end states are free with every capsule grown by its own
cover. A segment the clearances do not certify is split into 8 parts checked the second way;
parts that fail it are split again (two levels); a part still not covered fails the path, and
so does a segment whose displacement the velocities do not explain (a jump: a branch switch, a
discontinuous model) or whose backbone moves faster than 250 mm per mm of the metric (a fold).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np

from ctrplan.planning.motion import check_motion, edge_direction, joint_delta
from ctrplan.robot import Robot
from ctrplan.shape.base import Shape
from ctrplan.shape.branches import DEFAULT_STABILITY_MARGIN
from ctrplan.shape.planning_model import planning_model

#: Slack (mm) on the joint constraints for interpolated states (round-off only).
JOINT_TOL_MM = 1e-7


@dataclass(frozen=True)
class ValidatorConfig:
    """Settings of :class:`BatchValidator`.

    resolution_mm : largest estimated backbone motion between two checked states of an edge.
    points : backbone points per shape used for collision checking.
    alpha_weight_mm : mm of backbone motion per rad of rotation (the metric's weight; about the
        largest displacement of a backbone point per mm of this metric on seed1). The motion
        between checked states is bounded from the model by the final path check
        (``motion_bound``).
    cache_size : single-state results kept (OMPL asks again for start/goal states).
    motion_bound : the final path check (:meth:`BatchValidator.check_path`) also covers the
        motion between its states (see the module docstring); False checks the states only.
    motion_floor_mm : with ``motion_bound``, states and edges while planning are checked with
        capsules grown by this much (mm), so that planned paths keep the small clearance the
        motion certificate's last level needs (about 0.01 mm for 0.5 mm segments).
    stability_margin : smallest elastic stability (det of the shooting Jacobian, normalised:
        :mod:`ctrplan.shape.branches`) of a valid state, for models whose shape can depend on
        the motion (compliant unloaded mechanics); edges are checked by continuation of the
        equilibrium (:mod:`ctrplan.planning.tracking`). 0 keeps only stable equilibria reached
        without a snap.
    """

    resolution_mm: float = 2.0
    points: int = 24
    alpha_weight_mm: float = 30.0
    cache_size: int = 4096
    motion_bound: bool = True
    motion_floor_mm: float = 0.02
    stability_margin: float = DEFAULT_STABILITY_MARGIN

    def __post_init__(self) -> None:
        if not (math.isfinite(self.stability_margin) and self.stability_margin >= 0):
            raise ValueError("stability_margin must be a number >= 0")
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
    motion_segments: int = 0

    def as_dict(self) -> dict[str, int]:
        return dict(self.__dict__)


def wrap(a: np.ndarray) -> np.ndarray:
    """Angles wrapped to (-pi, pi]."""
    return math.pi - np.mod(math.pi - np.asarray(a, dtype=float), 2.0 * math.pi)


def motion_mm(q0: np.ndarray, q1: np.ndarray, n: int, alpha_weight_mm: float) -> np.ndarray:
    """Estimated backbone motion (mm) between configurations. q0, q1 : (..., 2n) -> (...)."""
    d = joint_delta(q0, q1, n)
    return alpha_weight_mm * np.abs(d[..., :n]).sum(-1) + np.linalg.norm(d[..., n:], axis=-1)


def unwrap_path(path: np.ndarray, n: int) -> np.ndarray:
    """The path with continuous rotations: each state's alphas are the previous state's plus
    the shorter-arc difference, so linear interpolation between consecutive states is the
    motion the validator checked."""
    out = np.array(np.atleast_2d(path), dtype=float, copy=True)
    if len(out) > 1:
        d = wrap(np.diff(out[:, :n], axis=0))
        out[1:, :n] = out[0, :n] + np.cumsum(d, axis=0)
    return out


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
    #: (S, 2n) direction of motion of each state (direction-aware models), else None
    direction: np.ndarray | None = None
    #: (S, n) 1/mm and (S,): the equilibrium each state was reached on and its stability
    #: (models that track branches, :mod:`ctrplan.planning.tracking`), else None
    uz0: np.ndarray | None = None
    stability: np.ndarray | None = None
    #: (S,) bool: states this check rejected in a rescued goal's region, left to the reference
    #: model's check (:mod:`ctrplan.planning.rescue`), or None
    deferred: np.ndarray | None = None

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
    model : a ShapeModel (``shape(q, points) -> Shape``), used as it is, or a
        :class:`~ctrplan.shape.planning_model.PlanningModel` (what a planner passes: the model
        fit for collision checking)
    world : CollisionWorld-like (``collides``, ``first_collision``, ``check_exact`` on a Shape in
        the robot base frame; shapes with ``ok=False`` count as colliding)
    config : ValidatorConfig
    tracking : True: track the equilibrium along motions where the model's shape can depend on
        them (:mod:`ctrplan.planning.tracking`); False: never (every state the model's own
        equilibrium, no stability margin); or a BranchTracker to share (its remembered states
        and margin).
    """

    def __init__(self, robot: Robot, model, world, config: ValidatorConfig | None = None,
                 tracking=True):
        self.robot = robot
        #: what planning needs from the model (a model given as it is: fit=False)
        self.model = planning_model(model, fit=False)
        #: the model takes the direction of motion (then unknown directions are checked both ways)
        self.directional = self.model.needs_direction
        self.world = world
        self.config = config or ValidatorConfig()
        #: the world of planning-time checks (states, edges): capsules grown by the motion floor
        self.plan_world = world
        if self.config.motion_bound and self.config.motion_floor_mm > 0 and hasattr(world, "with_motion"):
            self.plan_world = world.with_motion(self.config.motion_floor_mm)
        self.n = robot.n
        self.counters = Counters()
        #: a :class:`~ctrplan.planning.rescue.GoalRescue` once a plan rescued goals: it decides
        #: the states this validator rejects in their regions (None: this validator decides all)
        self.rescue = None
        self._cache: OrderedDict[bytes, bool] = OrderedDict()
        from ctrplan.planning.tracking import BranchTracker

        #: the equilibria of reached states and the stability margin, or None
        self.tracker: BranchTracker | None = None
        if isinstance(tracking, BranchTracker):
            self.tracker = tracking
        elif tracking and self.model.tracks_branches:
            self.tracker = BranchTracker(self.model, self.config.stability_margin)

    # ------------------------------------------------------------------ batches of states
    def joint_valid(self, q: np.ndarray) -> np.ndarray:
        """(B,) bool: finite and inside the joint constraints (with round-off slack)."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        finite = np.all(np.isfinite(q), axis=1)
        with np.errstate(invalid="ignore"):
            ok = np.all(self.robot.constraint_violations(q) >= -JOINT_TOL_MM, axis=1)
        return finite & ok

    def shapes(self, q: np.ndarray, points: int | None = None, direction: np.ndarray | None = None,
               uz0: np.ndarray | None = None) -> Shape:
        """Shapes of a batch (one model call). q : (B, 2n); direction : (B, 2n) or (2n,) in
        {-1, +1} (used only by direction-aware models; required by them). With a tracker:
        ``ok`` is False below the stability margin, and ``uz0`` (B, n) gives each state's
        equilibrium (Newton from it) instead of the model's own."""
        self.counters.shape_calls += 1
        self.counters.states += len(q)
        q = np.asarray(q, dtype=float)
        points = points or self.config.points
        d = None
        if self.directional:
            if direction is None:
                raise ValueError("a direction-aware model needs the direction of motion")
            d = np.ascontiguousarray(np.broadcast_to(np.asarray(direction, dtype=np.int8), q.shape))
        if self.tracker is not None:
            return self.tracker.states(q, points, d, uz0).shape
        return self.model.shape(q, points=points, direction=d)

    def anchor(self, q: np.ndarray) -> None:
        """Remember the model's own equilibria of states q (B, 2n) as the ones the robot is
        on there (goals: the tip was computed on them). No-op without a tracker."""
        if self.tracker is not None and len(q):
            q = np.atleast_2d(np.asarray(q, dtype=float))
            d = np.ones(q.shape, dtype=np.int8) if self.directional else None
            self.tracker.register(q, self.tracker.states(q, 2, d).uz0, anchor=True)

    def variants(self, q: np.ndarray, direction: np.ndarray | None = None) -> list[np.ndarray | None]:
        """Directions to evaluate a batch with: [None] for an ordinary model; for a
        direction-aware one the given direction with its unknown (0) entries set to +1 and to
        -1 (one variant when nothing is unknown)."""
        if not self.directional:
            return [None]
        q = np.atleast_2d(q)
        d = np.zeros(q.shape, dtype=np.int8) if direction is None else \
            np.broadcast_to(np.asarray(direction, dtype=np.int8), q.shape)
        if not (d == 0).any():
            return [d]
        return [np.where(d == 0, 1, d).astype(np.int8), np.where(d == 0, -1, d).astype(np.int8)]

    def states_valid(self, q: np.ndarray, direction: np.ndarray | None = None) -> np.ndarray:
        """(B,) bool validity of a batch: one shape call, one collision query (two of each for
        a direction-aware model with unknown directions)."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        ok = self.joint_valid(q)
        if ok.any():
            idx = np.flatnonzero(ok)
            free = np.ones(len(idx), dtype=bool)
            for d in self.variants(q[idx], None if direction is None
                                   else np.broadcast_to(direction, q.shape)[idx]):
                shape = self.shapes(q[idx], direction=d)
                self.counters.collision_calls += 1
                free &= ~np.asarray(self.plan_world.collides(shape), dtype=bool)
            if self.rescue is not None:
                free |= self.rescue.overrule(q[idx], ~free)
            ok[idx] = free
        return ok

    def check_states(self, q: np.ndarray, points: int | None = None,
                     direction: np.ndarray | None = None, exact: bool = False,
                     joints: bool = True, uz0: np.ndarray | None = None):
        """(collides (B,), clearance_mm (B,), contact (B,)) of a batch with the world's
        ``check`` (``check_exact`` if ``exact``): worst case over the direction variants.
        ``joints`` : joint-constraint violations count as collisions (contact "joints")."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        B = len(q)
        collides = ~self.joint_valid(q) if joints else np.zeros(B, dtype=bool)
        clearance = np.full(B, np.inf)
        contact = np.full(B, "", dtype=object)
        contact[collides] = "joints"
        for d in self.variants(q, direction):
            shape = self.shapes(q, points=points, direction=d, uz0=uz0)
            self.counters.collision_calls += 1
            rep = self.world.check_exact(shape) if exact else self.world.check(shape)
            hit = np.asarray(rep.collides, dtype=bool)
            newly = hit & ~collides
            contact[newly] = np.asarray(rep.contact, dtype=object)[newly]
            collides |= hit
            clearance = np.minimum(clearance, np.asarray(rep.clearance_mm, dtype=float))
        return collides, clearance, contact

    def first_invalid(self, q: np.ndarray, direction: np.ndarray | None = None,
                      uz_start: np.ndarray | None = None, end_default: bool = False) -> int:
        """Index of the first invalid state of an ordered batch (B, 2n), or -1 if all are valid.

        Joint limits are checked for all states; the states before the first joint violation go
        through one shape call and one collision query that stops at the first collision.
        direction : (2n,) direction of motion along the batch (direction-aware models).
        With a tracker the batch is a motion (:meth:`BranchTracker.first_invalid`): from
        ``uz_start`` (default: the remembered equilibrium of q[0]), ending, with
        ``end_default``, on the model's own equilibrium of the last state.
        """
        if self.tracker is not None:
            return self.tracker.first_invalid(self, q, direction, uz_start=uz_start,
                                              end_default=end_default)
        q = np.atleast_2d(np.asarray(q, dtype=float))
        jv = self.joint_valid(q)
        k0 = int(np.argmin(jv)) if not jv.all() else len(q)
        if k0 == 0:
            return 0
        first = k0 if k0 < len(q) else -1
        if self.rescue is not None and self.rescue.near(q[:k0]).any():
            return self._first_invalid_rescued(q, k0, first, direction)
        for d in self.variants(q[:k0], direction):
            shape = self.shapes(q[:k0], direction=d)
            self.counters.collision_calls += 1
            k = int(self.plan_world.first_collision(shape))
            if k >= 0:
                first = k if first < 0 else min(first, k)
        return first

    def _first_invalid_rescued(self, q, k0, first, direction) -> int:
        """first_invalid where states lie in a rescued goal's region: every state's verdict,
        those rejected there decided by the rescue's reference check."""
        hit = ~self.states_valid(q[:k0], direction)
        k = int(np.argmax(hit)) if hit.any() else -1
        return first if k < 0 else k

    # ------------------------------------------------------------------ OMPL callbacks
    def edge_states(self, q0: np.ndarray, q1: np.ndarray, resolution_mm: float | None = None) -> np.ndarray:
        c = self.config
        return interpolate(q0, q1, self.n, c.alpha_weight_mm, resolution_mm or c.resolution_mm)

    def edge_valid(self, q0: np.ndarray, q1: np.ndarray) -> bool:
        """Whether the straight edge q0 -> q1 (both ends included) is valid."""
        self.counters.edges += 1
        d = edge_direction(q0, q1, self.n) if self.directional else None
        if self.tracker is not None:
            ok = self.tracker.edge_valid(self, q0, q1)
        else:
            ok = self.first_invalid(self.edge_states(q0, q1), d) < 0
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

    # ------------------------------------------------------------------ motion between states
    def _check_motion(self, states, seg, direction, clearance, collides, contact, points,
                      uz0=None) -> None:
        """Cover the motion between consecutive checked states with a bound derived from the
        model along each segment (:mod:`ctrplan.planning.motion`); the first state of a
        segment that is not covered is marked as colliding (contact: the mesh, or "motion").
        uz0 : (S, n) the equilibrium of each state reached by continuation (branch tracking):
        the states between them are solved from it, so the cover follows the robot's branch."""
        if not hasattr(self.world, "with_motion"):
            return
        check_motion(self, states, clearance, collides, contact, points, uz0)

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
        path = np.atleast_2d(np.asarray(path, dtype=float))
        direction = None
        if self.directional and len(path) > 1:
            dirs = np.array([edge_direction(a, b, self.n) for a, b in zip(path[:-1], path[1:])])
            direction = dirs[seg]
            # a waypoint joins two edges: its direction is unknown where they differ
            joins = np.flatnonzero(np.r_[False, seg[1:] != seg[:-1]])
            for i in joins:
                direction[i] = np.where(dirs[seg[i] - 1] == dirs[seg[i]], dirs[seg[i]], 0)
        collides = np.zeros(S, dtype=bool)
        clearance = np.full(S, np.inf)
        contact = np.full(S, "", dtype=object)
        jv = self.joint_valid(states)
        track = None
        if self.tracker is not None:      # the path as one motion: its shapes by continuation
            track = self.tracker.path(self, path, states, seg, self.variants(states, direction),
                                      points or self.config.points)
            self.counters.shape_calls += len(track.shapes)
            self.counters.states += S * len(track.shapes)
        for a in range(0, S, chunk):
            b = min(S, a + chunk)
            variants = [None] * len(track.shapes) if track is not None else \
                self.variants(states[a:b], None if direction is None else direction[a:b])
            for vi, d in enumerate(variants):
                shape = track.shapes[vi][a:b] if track is not None else \
                    self.shapes(states[a:b], points=points, direction=d)
                self.counters.collision_calls += 1
                rep = self.world.check_exact(shape) if fcl_all else self.world.check(shape)
                hit = np.asarray(rep.collides, dtype=bool)
                newly = hit & ~collides[a:b]
                contact[a:b][newly] = np.asarray(rep.contact, dtype=object)[newly]
                collides[a:b] |= hit
                clearance[a:b] = np.minimum(clearance[a:b], np.asarray(rep.clearance_mm, dtype=float))
        collides |= ~jv
        if track is not None:          # (their shapes are ok=False: the world said "model")
            why = track.why != ""
            contact[why] = track.why[why]
            collides |= why
        deferred = self._deferred(states, collides & jv)
        collides &= ~deferred
        contact[deferred] = ""
        if c.motion_bound and not collides.any() and S > 1:
            self._check_motion(states, seg, direction, clearance, collides, contact, points,
                               None if track is None else track.uz0)
            if deferred.any():    # the motion next to a deferred state: the reference's too
                near = deferred[:-1] | deferred[1:]
                collides[:-1][near] = False
                contact[:-1][near] = ""
        bad = np.flatnonzero(collides)
        first = int(bad[0]) if len(bad) else -1
        return PathCheck(states, seg, collides, clearance, contact, first,
                         sorted({int(s) for s in seg[bad]}), direction,
                         None if track is None else track.uz0,
                         None if track is None else track.stability, deferred)

    def _deferred(self, states: np.ndarray, rejected: np.ndarray) -> np.ndarray:
        """(S,) bool: rejected states in a rescued goal's region, left to the reference
        model's dense check (:mod:`ctrplan.planning.rescue`; all False without a rescue)."""
        if self.rescue is None or not rejected.any():
            return np.zeros(len(states), dtype=bool)
        near = np.zeros(len(states), dtype=bool)
        idx = np.flatnonzero(rejected)
        # grown by one edge resolution: the states between an edge's checked states
        near[idx] = self.rescue.near(states[idx], self.config.resolution_mm)
        return near
