"""OMPL glue: the joint space of an n-tube robot, a batched motion validator, planners by name.

This is the only module that imports ``ompl``; everything it hands out is numpy. The PyPI
``ompl`` 2.x wheels use nanobind: Python subclasses of ``ompl.base.MotionValidator``,
``StateValidityChecker`` and ``ValidStateSampler`` are called from C++ through trampolines.

State space. ``q = [alpha_1..alpha_n, beta_1..beta_n]`` is a compound of n ``SO2`` spaces
(rotations wrap to (-pi, pi]) weighted by ``alpha_weight_mm`` (mm of backbone motion per rad)
and one bounded ``RealVector(n)`` of translations (mm, weight 1), so OMPL's distance
``sum_i w |d alpha_i| + ||d beta||`` is an estimate of backbone motion in mm. The box bounds of
beta come from the robot; the coupled joint constraints of docs/conventions.md are enforced by the
validity checks (the constraint set is convex in beta, so a straight edge between two valid
configurations never leaves it).

Validity. Every edge is checked by ``checker.edge_valid`` (:class:`ctrplan.planning.validator.BatchValidator`) — one batched shape call and
one batched collision query over all interpolated states, both end states included (OMPL's
RRTConnect grows its goal tree with the new state as the *first* argument). OMPL still calls
the per-state checker for start/goal states and for samples of some planners (BIT*); that
call goes through a cache, and samplers validate samples in batches.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass
from typing import Protocol

import numpy as np
import ompl.base as ob
import ompl.geometric as og
import ompl.util as ou

from ctrplan import interrupt
from ctrplan.errors import ArgumentError
from ctrplan.robot import Robot

log = logging.getLogger("ctrplan")

# OMPL logs to stdout through its own handler; keep it to errors (BIT* warns on every setup).
ou.setLogLevel(ou.LOG_ERROR)

#: Planner names accepted by :func:`make_planner` (lower case) -> OMPL geometric class.
PLANNERS: dict[str, str] = {
    "rrtconnect": "RRTConnect",
    "rrt": "RRT",
    "rrtstar": "RRTstar",
    "bitstar": "BITstar",
    "kpiece": "KPIECE1",
    "bkpiece": "BKPIECE1",
    "lbkpiece": "LBKPIECE1",
}


#: Planners refused with the reason: OMPL's PRM checks for a solution in a second C++ thread that
#: calls the Python motion validator, while the OMPL 2.x bindings keep the GIL held in the main
#: thread's ``solve`` (waiting for PRM's graph lock): a deadlock, seen in the hard benchmark.
UNSAFE_PLANNERS = {
    "prm": "OMPL's PRM validates edges from a second thread and deadlocks with Python validity "
           "checkers in the OMPL 2.x bindings; use rrtconnect, rrt, rrtstar, bitstar or kpiece",
}
UNSAFE_PLANNERS["prmstar"] = UNSAFE_PLANNERS["prm"]


def check_planner(name: str) -> str:
    """Normalise a planner name (case-insensitive) or raise ArgumentError (``planner``)."""
    key = str(name).strip().lower()
    if key in UNSAFE_PLANNERS:
        raise ArgumentError("planner", f"{name!r}: {UNSAFE_PLANNERS[key]}")
    if key not in PLANNERS:
        raise ArgumentError("planner", f"unknown planner {name!r} (choose from {', '.join(PLANNERS)})")
    return key


def seed_ompl(seed: int) -> None:
    """Seed OMPL's global generator so the RNGs created next are reproducible.

    Why: ``RNG.setSeed`` logs an error once random numbers have been drawn in this process
    ("changing seed now will not lead to deterministic sampling"), but it still reseeds the
    generator of per-instance seeds; every planning call creates its RNGs in the same order after
    this call, so the same seed gives the same samples. OMPL ignores seed 0, hence the offset.
    """
    level = ou.getLogLevel()
    ou.setLogLevel(ou.LOG_NONE)
    try:
        ou.RNG.setSeed(int(seed) % (2**31 - 2) + 1)
    finally:
        ou.setLogLevel(level)


class Checker(Protocol):
    """What the OMPL callbacks need (implemented by :class:`ctrplan.planning.validator.BatchValidator`)."""

    def edge_valid(self, q0: np.ndarray, q1: np.ndarray) -> bool: ...

    def state_valid(self, q: np.ndarray) -> bool: ...

    def sample_valid(self, count: int, rng: np.random.Generator) -> np.ndarray: ...

    def sample_valid_near(self, q: np.ndarray, distance: float, count: int,
                          rng: np.random.Generator) -> np.ndarray: ...


class JointSpace:
    """The OMPL state space and space information of a robot.

    Parameters
    ----------
    robot : Robot
    alpha_weight_mm : float
        Weight of each rotation in OMPL's distance (mm of backbone motion per rad).
    """

    def __init__(self, robot: Robot, alpha_weight_mm: float):
        self.robot = robot
        self.n = robot.n
        self.alpha_weight_mm = float(alpha_weight_mm)
        space = ob.CompoundStateSpace()
        for _ in range(self.n):
            space.addSubspace(ob.SO2StateSpace(), self.alpha_weight_mm)
        rv = ob.RealVectorStateSpace(self.n)
        lo, hi = robot.beta_bounds()
        bounds = ob.RealVectorBounds(self.n)
        for i in range(self.n):
            bounds.setLow(i, float(lo[i]))
            # A degenerate (zero-width) range upsets OMPL's samplers; widen it by a hair.
            bounds.setHigh(i, float(max(hi[i], lo[i] + 1e-9)))
        rv.setBounds(bounds)
        space.addSubspace(rv, 1.0)
        self.space = space
        self.si = ob.SpaceInformation(space)

    def to_q(self, state) -> np.ndarray:
        """(2n,) configuration of an OMPL state."""
        n = self.n
        rv = state[n]
        return np.array([state[i].value for i in range(n)] + [rv[j] for j in range(n)], dtype=float)

    def set_state(self, state, q: np.ndarray) -> None:
        """Write a (2n,) configuration into an OMPL state (alphas wrapped to (-pi, pi])."""
        n = self.n
        for i in range(n):
            a = float(q[i])
            state[i].value = math.pi - math.fmod(math.fmod(math.pi - a, 2 * math.pi) + 2 * math.pi, 2 * math.pi)
        rv = state[n]
        for j in range(n):
            rv[j] = float(q[n + j])

    def new_state(self, q: np.ndarray):
        s = self.si.allocState()
        self.set_state(s, q)
        return s


class _Link:
    """What the callbacks reach: the joint space, the checker, the first exception raised.

    The OMPL objects hold the Python callbacks (C++ shared pointers) and the callbacks hold this
    link; :meth:`detach` breaks that cycle after planning, which the garbage collector cannot see.
    """

    def __init__(self, js: JointSpace, checker: Checker, seed: int) -> None:
        self.js: JointSpace | None = js
        self.checker: Checker | None = checker
        self.seed = int(seed)
        self.exc: BaseException | None = None

    def detach(self) -> None:
        self.js = None
        self.checker = None


class _MotionValidator(ob.MotionValidator):
    """checkMotion(s1, s2): the whole edge in one batched shape call + one collision query."""

    def __init__(self, si, link: _Link):
        super().__init__(si)
        self.link = link

    def checkMotion(self, s1, s2):  # noqa: N802 - OMPL's name
        link = self.link
        if link.exc is not None or link.checker is None or interrupt.requested():
            return False
        try:
            return bool(link.checker.edge_valid(link.js.to_q(s1), link.js.to_q(s2)))
        except BaseException as exc:  # an exception must not cross into C++
            link.exc = exc
            return False


class _StateChecker(ob.StateValidityChecker):
    """isValid(s): one state (cached in the checker); OMPL uses it for starts, goals, samples."""

    def __init__(self, si, link: _Link):
        super().__init__(si)
        self.link = link

    def isValid(self, s):  # noqa: N802 - OMPL's name
        link = self.link
        if link.exc is not None or link.checker is None or interrupt.requested():
            return False
        try:
            return bool(link.checker.state_valid(link.js.to_q(s)))
        except BaseException as exc:
            link.exc = exc
            return False


class _BatchSampler(ob.ValidStateSampler):
    """Valid samples drawn and validated in batches (one shape + collision call per batch)."""

    batch = 64

    def __init__(self, si, link: _Link):
        super().__init__(si)
        self.link = link
        self.rng = np.random.default_rng([link.seed, 7])
        self.buffer: list[np.ndarray] = []

    def sample(self, s):
        link = self.link
        if link.exc is not None or link.checker is None or interrupt.requested():
            return False
        try:
            tries = 0
            while not self.buffer and tries < 8:
                self.buffer = list(link.checker.sample_valid(self.batch, self.rng))
                tries += 1
            if not self.buffer:
                return False
            link.js.set_state(s, self.buffer.pop())
            return True
        except BaseException as exc:
            link.exc = exc
            return False

    def sampleNear(self, s, near, distance):  # noqa: N802 - OMPL's name
        link = self.link
        if link.exc is not None or link.checker is None or interrupt.requested():
            return False
        try:
            q = link.checker.sample_valid_near(link.js.to_q(near), float(distance), 16, self.rng)
            if len(q) == 0:
                return False
            link.js.set_state(s, q[0])
            return True
        except BaseException as exc:
            link.exc = exc
            return False


def make_planner(name: str, si, range_mm: float | None = None):
    """An OMPL geometric planner by name (see :data:`PLANNERS`)."""
    key = check_planner(name)
    cls = getattr(og, PLANNERS[key])
    planner = cls(si)
    if range_mm is not None and hasattr(planner, "setRange"):
        planner.setRange(float(range_mm))
    return planner


@dataclass(frozen=True)
class OmplOutcome:
    """What one OMPL run produced.

    status : "exact", "approximate" or "timeout" (no path).
    path : (K, 2n) waypoints from start to a goal (exact solutions only), else None.
    goal_index : index (into all goals handed over) of the goal the path ends at, or -1.
    planning_s, simplification_s : wall-clock seconds of the stages.
    goals_used : number of goal states given to OMPL.
    states : states the checker validated during the run (planning and simplification).
    time_cap_hit : the wall-clock cap stopped the run before its state budget was spent (the
        result then depends on the machine's speed and load).
    """

    status: str
    path: np.ndarray | None
    goal_index: int
    planning_s: float
    simplification_s: float
    goals_used: int
    states: int = 0
    time_cap_hit: bool = False


def _states_of(checker) -> int:
    counters = getattr(checker, "counters", None)
    return int(getattr(counters, "states", 0))


def solve(
    robot: Robot,
    checker: Checker,
    start: np.ndarray,
    goals: np.ndarray,
    planner: str = "rrtconnect",
    time_limit: float = 5.0,
    seed: int = 0,
    alpha_weight_mm: float = 30.0,
    range_mm: float | None = None,
    more_goals=None,
    slices: tuple[float, ...] = (0.4, 0.3, 0.3),
    simplify: bool = True,
    simplify_rounds: int = 3,
    optimize: bool = False,
    max_states: int | None = None,
) -> OmplOutcome:
    """Plan from ``start`` (2n,) to any of ``goals`` (G, 2n) with OMPL.

    Budget. With ``max_states``, the budget is the number of states the checker validates
    (``checker.counters.states``): the run is split into ``slices`` of that budget and
    ``time_limit`` is only a wall-clock cap (``time_cap_hit`` says when it stopped the run). The
    same seed then gives the same path on any machine load (every offered planner is
    single-threaded). Without
    ``max_states``, the slices are fractions of ``time_limit`` (the result depends on speed).

    After a slice without a solution ``more_goals()`` (if given) may return extra goal
    configurations ``(G', 2n)``, which are added to the goal set before planning resumes
    (tree-based planners keep their trees between slices). Unless ``optimize``, planning stops
    at the first exact solution (anytime planners included). The solution is then simplified
    (``simplify_rounds`` rounds of vertex reduction and collapsing close vertices; counted, not
    timed) with the same validator.
    """
    seed_ompl(seed)
    js = JointSpace(robot, alpha_weight_mm)
    link = _Link(js, checker, seed)
    try:
        # Python callbacks run inside OMPL's C++ code: a SIGINT / SIGTERM is only recorded
        # there (the callbacks then answer "invalid" and the planner stops at once) and
        # raised when control is back here
        with interrupt.deferred():
            return _solve(js, link, start, goals, planner, time_limit, range_mm, more_goals,
                          slices, simplify, simplify_rounds, optimize, max_states)
    finally:
        link.detach()
        js.si.clearValidStateSamplerAllocator()


def _solve(js: JointSpace, link: _Link, start, goals, planner, time_limit, range_mm, more_goals,
           slices, simplify, simplify_rounds, optimize, max_states) -> OmplOutcome:
    pdef, goal_set, all_goals, pl = _problem(js, link, start, goals, planner, range_mm, optimize)
    t0 = time.perf_counter()
    s0 = _states_of(link.checker)
    status, cap_hit = _run_slices(js, link, pdef, goal_set, all_goals, pl, t0, time_limit,
                                  more_goals, slices, optimize, max_states)
    planning_s = time.perf_counter() - t0
    if link.exc is not None:
        raise link.exc
    if not pdef.hasExactSolution():
        approx = pdef.hasApproximateSolution()
        log.debug("planner %s: %s after %.2f s", planner, status, planning_s)
        return OmplOutcome("approximate" if approx else "timeout", None, -1, planning_s, 0.0,
                           len(all_goals), _states_of(link.checker) - s0, cap_hit)
    path = pdef.getSolutionPath()
    t1 = time.perf_counter()
    if simplify and path.getStateCount() > 2:
        _simplify(js, link, path, simplify_rounds)
    simplification_s = time.perf_counter() - t1
    q = np.array([js.to_q(s) for s in path.getStates()])
    end_q = q[-1]
    dists = [float(np.max(np.abs(_wrapdiff(g, end_q, js.n)))) for g in all_goals]
    goal_index = int(np.argmin(dists)) if dists else -1
    if goal_index >= 0 and dists[goal_index] < 1e-6:
        q[-1] = all_goals[goal_index]  # exact goal values (no round trip through the state)
    return OmplOutcome("exact", q, goal_index, planning_s, simplification_s, len(all_goals),
                       _states_of(link.checker) - s0, cap_hit)


def _problem(js: JointSpace, link: _Link, start, goals, planner, range_mm, optimize):
    """The space's checkers and sampler, the problem (start, goal states, objective) and the
    planner, set up. Returns (problem definition, goal set, goals (list), planner)."""
    si = js.si
    si.setStateValidityChecker(_StateChecker(si, link))
    si.setMotionValidator(_MotionValidator(si, link))
    si.setValidStateSamplerAllocator(lambda si_: _BatchSampler(si_, link))
    si.setup()
    # KPIECE-family planners need a projection: the translations (OMPL's default projection
    # of the RealVector subspace).
    js.space.registerDefaultProjection(ob.SubspaceProjectionEvaluator(js.space, js.n))

    pdef = ob.ProblemDefinition(si)
    pdef.addStartState(js.new_state(start))
    goal_set = ob.GoalStates(si)
    all_goals = [np.asarray(g, dtype=float) for g in np.atleast_2d(goals)]
    for g in all_goals:
        goal_set.addState(js.new_state(g))
    pdef.setGoal(goal_set)
    if check_planner(planner) == "bitstar":
        # BIT*'s informed sampler for path length supports only RealVector/SE(n) spaces; wrapping
        # the objective makes OMPL fall back to its generic rejection sampler.
        obj = ob.MultiOptimizationObjective(si)
        obj.addObjective(ob.PathLengthOptimizationObjective(si), 1.0)
    else:
        obj = ob.PathLengthOptimizationObjective(si)
    if not optimize:
        # Any path is good enough: anytime planners (RRT*, BIT*) add their solution to the
        # problem only when they stop, so the exact-solution condition alone never fires for
        # them and they would run to the cap.
        obj.setCostThreshold(ob.Cost(math.inf))
    pdef.setOptimizationObjective(obj)
    pl = make_planner(planner, si, range_mm)
    pl.setProblemDefinition(pdef)
    pl.setup()
    return pdef, goal_set, all_goals, pl


def _run_slices(js: JointSpace, link: _Link, pdef, goal_set, all_goals: list, pl, t0: float,
                time_limit, more_goals, slices, optimize, max_states):
    """Solve in slices of the state budget (or of the time), adding goals between slices.
    Returns (OMPL's last status, whether the wall-clock cap stopped the run)."""
    checker = link.checker
    s0 = _states_of(checker)
    deadline = t0 + float(time_limit)
    fractions = list(slices) or [1.0]
    status = None
    cap_hit = False
    done = 0.0
    for k, frac in enumerate(fractions):
        last = k == len(fractions) - 1
        if time.perf_counter() >= deadline:
            cap_hit = max_states is not None
            break
        if max_states is not None:
            done = 1.0 if last else min(1.0, done + frac)
            limit = s0 + int(round(done * int(max_states)))
            if _states_of(checker) >= limit:
                continue

            def stop(limit=limit) -> bool:
                return _states_of(checker) >= limit or time.perf_counter() >= deadline

            ptc = ob.PlannerTerminationCondition(stop)
        else:
            remaining = deadline - time.perf_counter()
            budget = remaining if last else min(remaining, frac * float(time_limit))
            ptc = ob.timedPlannerTerminationCondition(budget)
        if not optimize:
            ptc = ob.plannerOrTerminationCondition(ptc, ob.exactSolnPlannerTerminationCondition(pdef))
        ptc = ob.plannerOrTerminationCondition(ptc, ob.PlannerTerminationCondition(interrupt.requested))
        status = pl.solve(ptc)
        if link.exc is not None:
            raise link.exc
        interrupt.check()
        if pdef.hasExactSolution():
            break
        if max_states is not None and time.perf_counter() >= deadline:
            cap_hit = True
            break
        if more_goals is not None and not last:
            extra = more_goals()
            if extra is not None and len(extra):
                for g in np.atleast_2d(extra):
                    all_goals.append(np.asarray(g, dtype=float))
                    goal_set.addState(js.new_state(g))
                log.debug("planner: added %d goal states after slice %d", len(extra), k + 1)
    return status, cap_hit


def _simplify(js: JointSpace, link: _Link, path, rounds: int) -> None:
    """Simplify an OMPL path in place: a fixed number of rounds of vertex reduction and
    collapsing close vertices with the same validator."""
    ps = og.PathSimplifier(js.si)
    # Why not simplifyMax: its B-spline smoothing validates single states outside our
    # batched edge checks. These two steps only use checkMotion on few edges; a fixed
    # number of rounds (not a time) keeps the result independent of the machine's speed.
    for _ in range(max(0, int(rounds))):
        changed = ps.reduceVertices(path)
        changed |= ps.collapseCloseVertices(path)
        if link.exc is not None:
            raise link.exc
        interrupt.check()
        if not changed:
            break


def _wrapdiff(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    d = np.asarray(a, dtype=float) - np.asarray(b, dtype=float)
    d[:n] = (d[:n] + math.pi) % (2 * math.pi) - math.pi
    return d
