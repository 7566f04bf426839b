"""Branch tracking and the stability margin in the validator: a path is a motion.

A state the planner reaches is a configuration *and* the equilibrium the robot is in there,
the one continued along the checked edges from the start (:mod:`ctrplan.shape.branches`).
:class:`BranchTracker` keeps that equilibrium (``uz0``) for every state the planner reached
(the start, the goals, every state at the end of a valid edge), and checks motions by
continuation:

- an edge is checked from the end whose equilibrium is known (OMPL's RRTConnect grows its goal
  tree backwards from the goals): the robot's shapes along it are the continued ones; the edge
  is invalid where the branch ends (a fold) or the stability falls below the margin; when both
  ends are known, continuing from one must arrive at the other's equilibrium (two trees, or
  two path states, connect only on the same branch); the reached end is remembered;
- a path (:meth:`BatchValidator.check_path`) is checked as one motion from its start, each
  waypoint on the equilibrium it was reached with, and it must end on the equilibrium the
  model's shape gives at the end (the one the goal's tip was computed on), or the goal's;
- a single state (samples, goals, the start) needs stability >= the margin at the model's own
  equilibrium (its edges are checked as above).

Nothing here applies to models whose shapes cannot depend on history (rigid, learned, loaded:
:func:`~ctrplan.shape.branches.tracks_branches`); the validator then has no tracker.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace

import numpy as np

from ctrplan.shape import branches as _br

#: why a state fails the tracking check (the contact name the validator reports)
FOLD = "fold"              # the branch ended before this state: the robot snaps
UNSTABLE = "stability"     # below the stability margin
BRANCH = "branch"          # reached on another equilibrium than the one the path relies on


@dataclass
class TrackCounters:
    """What the stability constraint rejected (states and edges)."""

    folds: int = 0
    below_margin: int = 0
    branch_mismatch: int = 0

    @property
    def any(self) -> bool:
        return bool(self.folds or self.below_margin or self.branch_mismatch)


@dataclass
class PathTrack:
    """The tracked shapes of a path's checked states: one Shape per direction variant, the
    equilibria (S, n) and stability (S,) of the first variant, and why a state fails ('' if it
    does not)."""

    shapes: list
    uz0: np.ndarray
    stability: np.ndarray
    why: np.ndarray


def _wrapped(q: np.ndarray, n: int) -> np.ndarray:
    q = np.array(q, dtype=float, copy=True)
    q[..., :n] = math.pi - np.mod(math.pi - q[..., :n], 2.0 * math.pi)
    return q


@dataclass
class BranchTracker:
    """Equilibria of the states reached, and the margin (see the module docstring).

    model : the planning model (:class:`~ctrplan.shape.planning_model.PlanningModel`), one
        that tracks branches.
    margin : smallest stability (det J) of a valid state.
    """

    model: object
    margin: float
    counters: TrackCounters = field(default_factory=TrackCounters)
    _eq: dict = field(default_factory=dict)
    _anchors: list = field(default_factory=list)

    def __post_init__(self) -> None:
        from ctrplan.shape.planning_model import planning_model

        self.model = planning_model(self.model, fit=False)
        self.n = self.model.robot.n

    # ---------------------------------------------------------------- equilibria of states
    def key(self, q: np.ndarray) -> bytes:
        return np.round(_wrapped(q, self.n), 9).tobytes()

    def register(self, q: np.ndarray, uz0: np.ndarray, anchor: bool = False) -> None:
        """Remember the equilibria uz0 (B, n) of states q (B, 2n). ``anchor``: states given
        from outside the planner (the start, goals), also found again when handed back with
        their rotations re-wrapped (a few ulps off)."""
        for row, u in zip(np.atleast_2d(q), np.atleast_2d(uz0)):
            self._eq[self.key(row)] = np.array(u, dtype=float)
            if anchor:
                self._anchors.append((_wrapped(row, self.n), np.array(u, dtype=float)))

    def lookup(self, q: np.ndarray) -> np.ndarray | None:
        """The remembered equilibrium of state q (2n,), or None. Keys are the state rounded to
        1e-9 (OMPL hands back the states it was given; an anchor is also matched to 1e-9 in
        every joint, rotations on the circle, in case a rounding boundary lies between two
        copies)."""
        u = self._eq.get(self.key(q))
        if u is None:
            w = _wrapped(q, self.n)
            for row, uz in self._anchors:
                d = row - w
                d[:self.n] = math.pi - np.mod(math.pi - d[:self.n], 2.0 * math.pi)
                if np.max(np.abs(d)) <= 1e-9:
                    return uz.copy()
        return None if u is None else u.copy()

    # ---------------------------------------------------------------- shapes
    def margin_ok(self, t: _br.Tracked) -> np.ndarray:
        with np.errstate(invalid="ignore"):
            return t.continued & (t.stability >= self.margin)

    def states(self, q: np.ndarray, points: int, direction=None, uz0=None) -> _br.Tracked:
        """The model's own equilibria of q (B, 2n) (or those reached from ``uz0``), with
        ``shape.ok`` False below the margin."""
        if uz0 is None:
            t = self.model.solve(q, points, direction)
        else:
            t = self.model.settle(q, uz0, points, direction)
        good = self.margin_ok(t)
        self.counters.below_margin += int(np.sum(np.asarray(t.shape.ok, bool) & ~good))
        return replace(t, shape=replace(t.shape, ok=np.asarray(t.shape.ok, bool) & good))

    def chain(self, q: np.ndarray, starts: np.ndarray, uz_init: np.ndarray, points: int,
              direction=None) -> tuple[_br.Tracked, np.ndarray]:
        """Continue the rows of q (B, 2n) (chains begin at ``starts`` from ``uz_init``).
        Returns the tracked shapes (``ok`` False where failing) and why each row fails."""
        t = self.model.solve(q, points, direction, uz_init=uz_init, chain=starts)
        why = np.full(len(q), "", dtype=object)
        with np.errstate(invalid="ignore"):
            low = t.continued & ~(t.stability >= self.margin)
        why[low] = UNSTABLE
        why[~t.continued] = FOLD
        return replace(t, shape=replace(t.shape, ok=np.asarray(t.shape.ok, bool) & (why == ""))), why

    def same(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return _br.same_equilibrium(a, b, self.model.robot)

    # ---------------------------------------------------------------- edges
    def edge_valid(self, validator, q0: np.ndarray, q1: np.ndarray) -> bool:
        """The edge q0 -> q1 checked as a motion (module docstring)."""
        from ctrplan.planning.motion import edge_direction

        states = validator.edge_states(q0, q1)
        # the robot moves q0 -> q1 whichever end the continuation starts from
        d = edge_direction(q0, q1, self.n) if validator.directional else None
        u0, u1 = self.lookup(q0), self.lookup(q1)
        if u0 is None and u1 is not None:
            states, u0, u1 = states[::-1], u1, None
        return self.first_invalid(validator, states, d, uz_start=u0, uz_end=u1, remember=True) < 0

    def first_invalid(self, validator, q: np.ndarray, direction=None, uz_start=None, uz_end=None,
                      end_default: bool = False, remember: bool = False) -> int:
        """Index of the first invalid state of the motion q (B, 2n) (joints, continuation,
        margin, collision), or -1. The motion starts on ``uz_start`` (default: the remembered
        equilibrium of q[0], else the model's own); it must end on ``uz_end`` (or, with
        ``end_default``, on the model's own equilibrium there) when given. ``remember``: a
        valid motion's end state is remembered with the equilibrium reached."""
        q = np.atleast_2d(np.asarray(q, dtype=float))
        B = len(q)
        jv = validator.joint_valid(q)
        k0 = int(np.argmin(jv)) if not jv.all() else B
        if k0 == 0:
            return 0
        first = k0 if k0 < B else -1
        qs = q[:k0]
        if uz_start is None:
            uz_start = self.lookup(qs[0])
        x0 = np.full((k0, self.n), np.nan)
        if uz_start is not None:
            x0[0] = uz_start
        starts = np.zeros(k0, dtype=bool)
        starts[0] = True
        end_uz = None
        for d in validator.variants(qs, direction):
            t, why = self.chain(qs, starts, x0, validator.config.points, d)
            validator.counters.shape_calls += 1
            validator.counters.states += k0
            self._count(why)
            bad = np.flatnonzero(why != "")
            if len(bad):
                first = int(bad[0]) if first < 0 else min(first, int(bad[0]))
                continue
            if first < 0 and (uz_end is not None or end_default):
                ref = uz_end if uz_end is not None else \
                    self.model.solve(qs[-1:], 2, None if d is None else d[-1:]).uz0[0]
                at = self.model.settle(qs[-1:], ref[None], 2, None if d is None else d[-1:])
                if not (at.continued[0] and self.same(at.uz0[0], t.uz0[-1])):
                    self.counters.branch_mismatch += 1
                    first = k0 - 1
                    continue
            validator.counters.collision_calls += 1
            k = int(validator.plan_world.first_collision(t.shape))
            if k >= 0:
                first = k if first < 0 else min(first, k)
            if end_uz is None:
                end_uz = t.uz0[-1]
        if first < 0 and remember and end_uz is not None and self.lookup(qs[-1]) is None:
            self.register(qs[-1:], end_uz[None])
        return first

    def _count(self, why: np.ndarray) -> None:
        self.counters.folds += int(np.any(why == FOLD))
        self.counters.below_margin += int(np.any(why == UNSTABLE))

    # ---------------------------------------------------------------- paths
    def path(self, validator, path: np.ndarray, states: np.ndarray, seg: np.ndarray,
             variants: list, points: int) -> PathTrack:
        """A path's checked states as one motion (module docstring): each segment continues
        the previous one; a waypoint with a remembered equilibrium restarts there after the
        arrival was compared with it; the end is compared with the model's own equilibrium
        (or the remembered one)."""
        path = np.atleast_2d(np.asarray(path, dtype=float))
        S, W = len(states), len(path)
        rows, starts, xin, owner, checks = [], [], [], [], []
        for j in range(max(1, W - 1)):
            idx = np.flatnonzero(seg == j)
            reg = self.lookup(path[j])
            if j == 0 or reg is not None:
                if j > 0 and len(rows):            # the arrival at waypoint j, to compare
                    checks.append((len(rows), len(rows) + 1))
                    rows.append(idx[0])
                    starts.append(False)
                    xin.append(np.full(self.n, np.nan))
                    owner.append(-1)
                rows.append(idx[0])
                starts.append(True)
                xin.append(reg if reg is not None else np.full(self.n, np.nan))
                owner.append(idx[0])
                idx = idx[1:]
            for i in idx:
                rows.append(i)
                starts.append(False)
                xin.append(np.full(self.n, np.nan))
                owner.append(i)
        rows = np.asarray(rows, dtype=int)
        owner = np.asarray(owner)
        keep = owner >= 0
        why = np.full(S, "", dtype=object)
        shapes, uz0, stab = [], None, None
        for d in variants:
            dd = None if d is None else np.asarray(d)[rows]
            t, w = self.chain(states[rows], np.asarray(starts), np.asarray(xin), points, dd)
            self._count(w)
            for arrive, restart in checks:
                # the arrival row duplicates waypoint j; the state before it ends segment j - 1
                if t.continued[arrive] and not self.same(t.uz0[arrive], t.uz0[restart]):
                    w[arrive - 1] = w[arrive - 1] or BRANCH
                    self.counters.branch_mismatch += 1
            wk = w[keep]
            tk = t[keep]
            end = S - 1
            if wk[end] == "":
                reg = self.lookup(path[-1]) if W > 1 else None
                ref = reg if reg is not None else \
                    self.model.solve(states[-1:], 2, None if dd is None else dd[-1:]).uz0[0]
                at = self.model.settle(states[-1:], ref[None], 2, None if dd is None else dd[-1:])
                if not (at.continued[0] and self.same(at.uz0[0], tk.uz0[end])):
                    wk[end] = BRANCH
                    self.counters.branch_mismatch += 1
            why = np.where(why == "", wk, why)
            shapes.append(replace(tk.shape, ok=np.asarray(tk.shape.ok, bool) & (wk == "")))
            if uz0 is None:
                uz0, stab = tk.uz0, tk.stability
        return PathTrack(shapes, uz0, stab, why)
