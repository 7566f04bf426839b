"""Local path optimisation for clearance (or length): every iterate collision-free.

After the search has found and simplified a path, :func:`optimize_path` moves its states away
from the anatomy (objective ``clearance``) or toward a short, smooth path (``length``). It
follows Kuntz et al., "Planning high-quality motions for concentric tube robots in point clouds
via parallel sampling and optimization" (IROS 2019): the cost is the integral of
``1 / clearance`` along the path, minimised locally from a feasible path, anytime, with every
accepted iterate collision-free. Here:

- The path is resampled into states about ``spacing_mm`` apart (metric mm, the OMPL distance
  ``alpha_weight * |d alpha| + |d beta|``); the start stays fixed, every other state moves.
- Cost ``sum_i sum_k phi(c_ik) + smooth * sum_i |z_(i+1) - z_i|^2``: ``c_ik`` is the clearance
  (mm) of capsule ``k`` of state ``i`` (the collision capsules: radius + sagitta bound + margin),
  ``phi(c) = 1/c - 1/cap_mm`` below ``cap_mm`` (0 beyond), ``z`` the configuration in metric
  units (rotations times ``alpha_weight_mm``). Summing over capsules, not only the closest one,
  pushes the whole shaft toward the middle of the lumen where it has room. The ``length``
  objective keeps only the smoothness term (which shortens the path and evens its spacing).
- Clearances for the *cost* come from the world's distance fields (trilinear interpolation of
  the stored distance to the nearest surface sample; an estimate, never a safety verdict); the
  gradient from forward differences in q, all states x (2n + 1) configurations in one batched
  shape call.
- The goal state moves only in the null space of the tip Jacobian and is pulled back onto the
  target by Gauss-Newton steps: its tip error may not exceed ``max(initial error,
  goal_tol_mm)``, otherwise the goal keeps its previous value; a step whose goal move brings
  the closest approach closer is retried with the goal kept.
- A step (the largest state move is ``step`` mm) is accepted only if the cost decreases, the
  smallest estimated clearance over the path does not, and the whole new path passes the validator's collision check (exact verdicts: FCL where the
  conservative prefilter does not prove them) at ``check_resolution_mm``; otherwise the step is
  halved. The number of trials is the budget (``iterations``, a count), so a seed gives the
  same path on any load.

numpy only; the collision API used is the world's (``capsules``, ``fields``) and the
validator's (``first_invalid``, ``shapes``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numba as nb
import numpy as np

from ctrplan.planning.validator import (
    BatchValidator,
    edge_direction,
    interpolate,
    interpolate_path,
    motion_mm,
    project_joints,
    unwrap_path,
)

OBJECTIVES = ("clearance", "length", "first")


@dataclass(frozen=True)
class OptimizeConfig:
    """Settings of :func:`optimize_path`.

    iterations : step trials (each one batched gradient or one candidate check; a count).
    spacing_mm : state spacing of the optimised path (metric mm); at most ``max_states`` states.
    step_mm : initial largest state move per step (metric mm); grows x1.5 after an accepted
        step up to ``max_step_mm``, halves after a rejected one, stops below ``min_step_mm``.
    cap_mm : clearances above this exert no push (mm).
    floor_mm : clearances below this count as this (mm; the estimate is not exact).
    smooth : weight of the smoothness term (per mm^2 of state difference).
    fd_alpha, fd_beta : forward-difference steps (rad, mm).
    goal_tol_mm : the goal's tip error may grow up to this (or stays at most its initial value
        if that is larger).
    """

    iterations: int = 14
    spacing_mm: float = 10.0
    max_states: int = 32
    step_mm: float = 3.0
    max_step_mm: float = 4.0
    min_step_mm: float = 0.05
    cap_mm: float = 6.0
    floor_mm: float = 0.02
    smooth: float = 0.02
    fd_alpha: float = 2e-3
    fd_beta: float = 0.05
    goal_tol_mm: float = 0.05


@dataclass(frozen=True)
class OptimizeResult:
    """Outcome of :func:`optimize_path`.

    path : (K, 2n) the optimised waypoints (rotations unwrapped), start and goal included;
        the input path when nothing improved. history : accepted iterates, oldest first (the
        input path resampled is the first), for a caller that must fall back.
    cost_before, cost_after : the optimiser's cost of the resampled input and of ``path``.
    accepted, trials, evaluations : steps accepted, step trials, configurations evaluated.
    tip_error_mm : the goal state's tip error (mm, robot base frame) of ``path``.
    time_cap_hit : the wall-clock cap stopped it before its budget of trials was spent (the
        result then depends on the machine's load).
    """

    path: np.ndarray
    history: list
    cost_before: float
    cost_after: float
    accepted: int
    trials: int
    evaluations: int
    tip_error_mm: float
    time_cap_hit: bool = False


@nb.njit(cache=True)
def _trilinear_min(p, origin, h, ub, out):
    """out[i] = min(out[i], trilinear interpolation of ``ub`` (nx, ny, nz) at point p[i]) for
    the points inside the grid's cells (origin (3,), spacing h); the others are left alone."""
    nx, ny, nz = ub.shape
    for i in range(p.shape[0]):
        x = (p[i, 0] - origin[0]) / h
        y = (p[i, 1] - origin[1]) / h
        z = (p[i, 2] - origin[2]) / h
        if not (x >= 0.0 and y >= 0.0 and z >= 0.0):     # NaN too
            continue
        fx, fy, fz = math.floor(x), math.floor(y), math.floor(z)
        if fx >= nx - 1 or fy >= ny - 1 or fz >= nz - 1:
            continue
        ix, iy, iz = int(fx), int(fy), int(fz)
        tx, ty, tz = x - fx, y - fy, z - fz
        val = 0.0
        for dx in range(2):
            wx = tx if dx else 1.0 - tx
            for dy in range(2):
                wy = ty if dy else 1.0 - ty
                for dz in range(2):
                    wz = tz if dz else 1.0 - tz
                    val += wx * wy * wz * ub[ix + dx, iy + dy, iz + dz]
        if val < out[i]:
            out[i] = val


class FieldClearance:
    """Estimated clearance of capsule chains from a collision world's distance fields.

    For the optimiser's cost only (not a bound): the distance of a point to a mesh is the
    trilinear interpolation of the field's ``ub`` (near the surface: the exact distance to the
    nearest surface sample), the minimum over meshes; points outside every field's grid are far
    (inf). A capsule's clearance is the smallest of the distances at its two ends and its middle,
    minus its radius.
    """

    def __init__(self, world):
        self.world = world
        self.grids = [(np.asarray(f.origin, dtype=float), float(f.h), np.asarray(f.ub, dtype=np.float32))
                      for f in world.fields]

    def point_distance(self, p: np.ndarray) -> np.ndarray:
        """(N,) estimated distance (mm) from points (N, 3), scene frame, to the nearest mesh."""
        p = np.ascontiguousarray(p, dtype=float)
        out = np.full(len(p), np.inf)
        for origin, h, ub in self.grids:
            _trilinear_min(p, origin, h, ub, out)
        return out

    def capsule_clearance(self, shape) -> np.ndarray:
        """(B, K) estimated clearance (mm) of each collision capsule of ``shape`` (robot base
        frame; the world's margin and sagitta padding included in the radii)."""
        caps = self.world.capsules(shape)
        B, K = caps.radius.shape
        pts = np.concatenate([caps.a, 0.5 * (caps.a + caps.b), caps.b], axis=1).reshape(-1, 3)
        d = self.point_distance(pts).reshape(B, 3, K).min(axis=1)
        c = d - caps.radius
        ok = np.asarray(shape.ok, dtype=bool)
        c[~ok] = -np.inf
        return c


def _barrier(c: np.ndarray, cfg: OptimizeConfig) -> np.ndarray:
    """(B,) sum over capsules of 1/c - 1/cap (c clipped at the floor, 0 beyond the cap)."""
    cc = np.maximum(c, cfg.floor_mm)
    return np.where(cc < cfg.cap_mm, 1.0 / cc - 1.0 / cfg.cap_mm, 0.0).sum(axis=-1)


def resample(path: np.ndarray, n: int, alpha_weight_mm: float, spacing_mm: float,
             max_states: int) -> np.ndarray:
    """The waypoint path (K, 2n) as states at most ``spacing_mm`` apart (widened so there are
    at most ``max_states``), rotations unwrapped; the waypoints stay states of the result."""
    path = unwrap_path(np.atleast_2d(np.asarray(path, dtype=float)), n)
    length = float(motion_mm(path[:-1], path[1:], n, alpha_weight_mm).sum()) if len(path) > 1 else 0.0
    step = max(spacing_mm, length / max(1, max_states - 1))
    states, _ = interpolate_path(path, n, alpha_weight_mm, step)
    return unwrap_path(states, n)


class _Problem:
    """The optimisation problem over one path (the start fixed)."""

    def __init__(self, validator: BatchValidator, field: FieldClearance | None, target_base,
                 cfg: OptimizeConfig, objective: str, check_resolution_mm: float):
        self.v = validator
        self.field = field
        self.target = np.asarray(target_base, dtype=float)
        self.cfg = cfg
        self.objective = objective
        self.res = float(check_resolution_mm)
        n = validator.n
        self.n = n
        self.w = np.concatenate([np.full(n, validator.config.alpha_weight_mm), np.ones(n)])
        self.evaluations = 0

    # -------------------------------------------------------------- model calls
    def _shape(self, q: np.ndarray, direction=None):
        self.evaluations += len(q)
        return self.v.shapes(q, direction=direction)

    def _directions(self, path: np.ndarray) -> list:
        """Per state: the direction to evaluate it with (direction-aware models: the edge it
        ends; +1 where unknown), else None."""
        if not self.v.directional:
            return [None]
        d = np.array([edge_direction(a, b, self.n) for a, b in zip(path[:-1], path[1:])])
        d = np.concatenate([d[:1], d], axis=0)
        return [np.where(d == 0, 1, d).astype(np.int8)]

    def state_costs(self, q: np.ndarray, direction=None) -> tuple[np.ndarray, np.ndarray]:
        """(barrier cost (B,), tips (B, 3)) of states q (B, 2n); ``self.last_min`` keeps each
        state's smallest estimated capsule clearance (B,) (inf without the field)."""
        shape = self._shape(q, direction)
        ok = np.asarray(shape.ok, dtype=bool)
        if self.objective != "clearance" or self.field is None:
            cost = np.zeros(len(q))
            self.last_min = np.full(len(q), np.inf)
        else:
            c = self.field.capsule_clearance(shape)
            cost = _barrier(c, self.cfg)
            self.last_min = c.min(axis=1)
        return np.where(ok, cost, np.inf), shape.tip

    def smooth_cost(self, z: np.ndarray) -> float:
        return float(self.cfg.smooth * np.sum(np.diff(z, axis=0) ** 2))

    def total(self, path: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
        """(path cost, per-state barrier costs (K,), tips (K, 3)); ``self.path_min``: the
        smallest estimated clearance over the moving states."""
        dirs = self._directions(path)[0]
        costs, tips = self.state_costs(path[1:], None if dirs is None else dirs[1:])
        self.path_min = float(np.min(self.last_min)) if len(self.last_min) else math.inf
        costs = np.concatenate([[0.0], costs])
        return float(costs.sum()) + self.smooth_cost(path * self.w), costs, \
            np.concatenate([np.full((1, 3), np.nan), tips])

    def gradient(self, path: np.ndarray, costs: np.ndarray,
                 tip: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(gradient of the cost in metric units (K, 2n), tip Jacobian of the goal (3, 2n) in
        metric units); the start row is 0."""
        c = self.cfg
        n, K = self.n, len(path)
        z = path * self.w
        G = np.zeros_like(path)
        # smoothness: d/dz_i of smooth * sum |z_(i+1) - z_i|^2
        dz = np.diff(z, axis=0)
        G[:-1] -= 2.0 * c.smooth * dz
        G[1:] += 2.0 * c.smooth * dz
        h = np.concatenate([np.full(n, c.fd_alpha), np.full(n, -c.fd_beta)])
        q = path[1:]
        stack = np.repeat(q[:, None, :], 2 * n, axis=1) + np.diag(h)[None]
        dirs = self._directions(path)[0]
        # forward differences of the goal's tip always; of the barrier for clearance only
        if self.objective == "clearance" and self.field is not None:
            flat = stack.reshape(-1, 2 * n)
            d = None if dirs is None else np.repeat(dirs[1:], 2 * n, axis=0)
            cost_p, tips_p = self.state_costs(flat, d)
            cost_p = cost_p.reshape(K - 1, 2 * n)
            tips_goal = tips_p.reshape(K - 1, 2 * n, 3)[-1]
            base = costs[1:, None]
            with np.errstate(invalid="ignore"):
                g = np.where(np.isfinite(cost_p), (cost_p - base) / h[None], 0.0)
            G[1:] += g / self.w[None]
        else:
            d = None if dirs is None else np.repeat(dirs[-1:], 2 * n, axis=0)
            _, tips_goal = self.state_costs(stack[-1], d)
        J = (tips_goal - np.asarray(tip, dtype=float)[None]).T / (h * self.w)[None]  # (3, 2n) per metric unit
        G[0] = 0.0
        return G, J

    # -------------------------------------------------------------- constraints
    def project(self, old: np.ndarray, cand: np.ndarray) -> np.ndarray:
        """Candidate states inside the joint constraints (betas projected; rotations kept
        continuous)."""
        out = project_joints(self.v.robot, cand)
        out[:, :self.n] = cand[:, :self.n]
        out[0] = old[0]
        return out

    def goal_onto_target(self, goal: np.ndarray, J: np.ndarray, tol: float, direction=None,
                         tries: int = 3) -> tuple[np.ndarray, float]:
        """Gauss-Newton steps of the goal (2n,) back onto the target, aiming at a fifth of the
        tolerance (the tip error stays near the IK's): (goal, tip error)."""
        n = self.n
        Jq = J * self.w[None]                    # per q unit
        best = (goal, np.inf)
        for k in range(tries + 1):
            tip = self._shape(goal[None], direction).tip
            err = float(np.linalg.norm(tip[0] - self.target))
            if err < best[1]:
                best = (goal, err)
            if err <= 0.2 * tol or k == tries:
                return best
            step = np.linalg.lstsq(Jq, self.target - tip[0], rcond=None)[0]
            nxt = project_joints(self.v.robot, (goal + step)[None])[0]
            nxt[:n] = goal[:n] + step[:n]
            goal = nxt
        return goal, err

    def path_valid(self, path: np.ndarray) -> bool:
        """Whether every edge of ``path`` passes the validator's check at the check resolution
        (exact verdicts; direction-aware models: each edge with its direction)."""
        c = self.v.config
        if self.v.tracker is not None:
            # a motion: continued from the start, ending on the equilibrium the goal's tip is
            # computed on (branch tracking, ctrplan.planning.tracking)
            states, seg = interpolate_path(path, self.n, c.alpha_weight_mm, self.res)
            d = None
            if self.v.directional and len(path) > 1:
                d = np.array([edge_direction(a, b, self.n) for a, b in zip(path[:-1], path[1:])])[seg]
            return self.v.first_invalid(states, d, end_default=True) < 0
        if not self.v.directional:
            states, _ = interpolate_path(path, self.n, c.alpha_weight_mm, self.res)
            return self.v.first_invalid(states) < 0
        for a, b in zip(path[:-1], path[1:]):
            states = interpolate(a, b, self.n, c.alpha_weight_mm, self.res)
            if self.v.first_invalid(states, edge_direction(a, b, self.n)) >= 0:
                return False
        return True


def _descent(prob, path, costs, tip, keep_goal: bool):
    """The cost's gradient G (K, 2n), the tip Jacobian J of the goal state and the descent
    direction D (largest row: 1 mm in the metric; None where the gradient vanishes). The goal
    moves only along the tip's null space (not at all with ``keep_goal``)."""
    G, J = prob.gradient(path, costs, tip)
    JJ = J @ J.T
    if np.linalg.cond(JJ) < 1e12 and not keep_goal:
        G[-1] -= J.T @ np.linalg.solve(JJ, J @ G[-1])
    else:
        G[-1] = 0.0
    norm = float(np.max(np.linalg.norm(G, axis=1)))
    return G, J, (-G / norm if norm > 0 else None)


def optimize_path(validator: BatchValidator, path: np.ndarray, target_base: np.ndarray,
                  objective: str = "clearance", config: OptimizeConfig | None = None,
                  check_resolution_mm: float | None = None,
                  goal_tol_mm: float | None = None, deadline: float = math.inf,
                  keep_goal: bool = False) -> OptimizeResult:
    """Optimise a collision-free waypoint path (K, 2n) for ``objective`` (see the module
    docstring). ``target_base`` (3,) mm, robot base frame: the goal's tip target.
    ``check_resolution_mm`` : edge resolution of the collision check of every iterate (default:
    the validator's). ``deadline`` : a ``time.perf_counter()`` value; only a cap (the budget is
    ``config.iterations`` trials). ``keep_goal`` : the goal state never moves (a goal whose tip
    direction matters). Returns the best accepted iterate (the resampled input if none)."""
    cfg = config or OptimizeConfig()
    if objective not in ("clearance", "length"):
        raise ValueError(f"objective must be 'clearance' or 'length', got {objective!r}")
    n = validator.n
    w_mm = validator.config.alpha_weight_mm
    field = FieldClearance(validator.world) if objective == "clearance" else None
    prob = _Problem(validator, field, target_base, cfg, objective,
                    check_resolution_mm or validator.config.resolution_mm)
    path = resample(path, n, w_mm, cfg.spacing_mm, cfg.max_states)
    cost, costs, tips = prob.total(path)
    least = prob.path_min
    err0 = float(np.linalg.norm(tips[-1] - prob.target)) if len(path) > 1 else 0.0
    tol = max(err0, cfg.goal_tol_mm if goal_tol_mm is None else goal_tol_mm)
    history = [path]
    cost0 = cost
    err = err0
    if len(path) < 2 or not math.isfinite(cost):
        return OptimizeResult(path, history, cost0, cost, 0, 0, prob.evaluations, err0)
    step = cfg.step_mm
    accepted = trials = 0
    G = J = None
    capped = False
    pin = False          # retry a step with the goal kept where it is
    while trials < cfg.iterations and step >= cfg.min_step_mm:
        if time.perf_counter() >= deadline:
            capped = True
            break
        if G is None:
            G, J, D = _descent(prob, path, costs, tips[-1], keep_goal)
            if D is None:
                break
        trials += 1
        cand = path + step * D / prob.w[None]
        cand = prob.project(path, cand)
        cerr = err
        if pin:
            cand[-1] = path[-1]
        moved = bool(np.any(cand[-1] != path[-1]))
        if moved:                                   # the goal moved: back onto the target
            dirs = prob._directions(cand)[0]
            cand[-1], cerr = prob.goal_onto_target(cand[-1], J, tol,
                                                   None if dirs is None else dirs[-1:])
            if cerr > tol:
                cand[-1] = path[-1]
                cerr = err
        ccost, ccosts, ctips = prob.total(cand)
        # the cost must fall without the closest approach getting closer (the sum over all
        # capsules could otherwise trade the minimum for the rest)
        closer = prob.path_min < least - 1e-3
        if ccost < cost and not closer and prob.path_valid(cand):
            path, cost, costs, tips, err = cand, ccost, ccosts, ctips, cerr
            least = max(least, prob.path_min)
            history.append(path)
            accepted += 1
            step = min(step * 1.5, cfg.max_step_mm)
            G, pin = None, False
        elif closer and moved:
            pin = True       # the goal's move (its tip capsule turning) came closer: keep it
        else:
            step *= 0.5
    return OptimizeResult(path, history, cost0, cost, accepted, trials, prob.evaluations, err,
                          capped)


def clearance_integral(profile_mm: np.ndarray, path: np.ndarray, n: int,
                       alpha_weight_mm: float, floor_mm: float = 1e-3) -> float:
    """Kuntz et al.'s objective on a path: the integral of 1/clearance over the metric arc
    length (trapezoid rule over the states; clearances below ``floor_mm`` count as it).
    profile_mm : (K,) clearance at each state of ``path`` (K, 2n). Dimensionless."""
    c = np.maximum(np.asarray(profile_mm, dtype=float), floor_mm)
    if len(c) < 2:
        return 0.0
    ds = motion_mm(path[:-1], path[1:], n, alpha_weight_mm)
    return float(np.sum(0.5 * (1.0 / c[:-1] + 1.0 / c[1:]) * ds))
