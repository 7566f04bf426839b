"""Start and goal configurations: target checks, the retracted start, IK goal rounds.

Used by the plan's stages (:mod:`ctrplan.planning.stages`); numpy only (no OMPL).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from ctrplan.planning import ik as _ik
from ctrplan.planning.validator import BatchValidator, motion_mm
from ctrplan.robot import Robot


# ---------------------------------------------------------------------- target checks
def target_blocked(scene, world, target_scene: np.ndarray, tip_radius_mm: float) -> str:
    """Why the tip cannot be at the target ("" if it can): inside a (closed) obstacle mesh, or
    closer to anatomy than the tip's radius."""
    from ctrplan.collision.scene import inside_mesh
    from ctrplan.shape.base import Shape

    p = np.asarray(target_scene, dtype=float)[None]
    for m in getattr(scene, "meshes", ()):
        if m.role == "obstacle" and bool(inside_mesh(m, p)[0]):
            return f"the target lies inside {m.name!r}"
    # A probe as thick as the tip, at the target: does it touch anything?
    pb = scene.to_base(p)[0]
    pts = np.stack([pb, pb + np.array([0.0, 0.0, 1e-3])])[None]
    probe = Shape(points=pts, s=np.array([[0.0, 1e-3]]), radius=np.full((1, 2), tip_radius_mm),
                  ok=np.array([True]))
    rep = world.check(probe)
    if bool(np.asarray(rep.collides)[0]):
        contact = str(np.asarray(rep.contact)[0]) or "anatomy"
        margin = float(getattr(world, "margin_mm", 0.0) or 0.0)
        if margin > 0:
            return (f"the target is within the tip radius ({tip_radius_mm:g} mm) + margin "
                    f"({margin:.3g} mm) of {contact!r}")
        return f"the target is within the tip radius ({tip_radius_mm:g} mm) of {contact!r}"
    return ""


def target_outside_lumen(scene, target_scene: np.ndarray) -> bool:
    """Whether the target lies outside the scene's wall meshes (a ray test, so it is only run
    to explain why no collision-free goal exists)."""
    if not any(m.role == "wall" for m in getattr(scene, "meshes", ())):
        return False
    try:
        from ctrplan.collision.scene import inside_walls
    except ImportError:  # pragma: no cover - the collision stage ships inside_walls
        return False
    return not bool(inside_walls(scene, np.asarray(target_scene, dtype=float)[None])[0])


# ---------------------------------------------------------------------- start
def retracted_start(robot: Robot, validator: BatchValidator, world=None, samples: int = 512,
                    seed: int = 0) -> tuple[np.ndarray, bool]:
    """The retracted configuration (``robot.retracted()``), with its tube rotations changed
    only if it collides: then the rotations (same translations) with the largest clearance
    among ``samples`` fixed random ones are used (the pre-curved tubes partly cancel when turned
    against each other, which straightens the retracted robot inside a narrow lumen).

    A pure function of the robot and the validator's model and world (``world`` is not used:
    the validator's is; kept for callers that pass one). A
    :class:`~ctrplan.planning.planner.Planner` computes it once, with a validator of its own.
    Returns (q (2n,), adjusted). If no rotation is free, the plain retracted configuration.
    """
    q0 = robot.retracted()
    if validator.states_valid(q0[None])[0]:
        return q0, False
    n = robot.n
    rng = np.random.default_rng(seed)
    q = np.repeat(q0[None], samples, axis=0)
    q[:, :n] = rng.uniform(-math.pi, math.pi, (samples, n))
    collides, clearance, _ = validator.check_states(q)
    free = ~collides
    if not free.any():
        return q0, False
    clear = np.where(free, clearance, -np.inf)
    return q[int(np.argmax(clear))], True


# ---------------------------------------------------------------------- goals
@dataclass
class GoalSource:
    """IK rounds on demand: each round takes the next-nearest workspace samples as seeds."""

    model: Any
    robot: Robot
    validator: BatchValidator
    table: _ik.WorkspaceTable
    target_base: np.ndarray
    tolerance_mm: float
    config: Any  # PlannerConfig
    rng: np.random.Generator
    #: optional score of goal configurations (G, 2n) -> (G,): each round's goals (the same
    #: ones) are handed out highest first (e.g. their clearance); None keeps the order of
    #: increasing tip error
    rank: Any = None
    #: a tip pose goal's axis (3,) unit, base frame, and cone (rad): goals keep the tip's
    #: tangent within it (None: position only)
    axis: Any = None
    cone_rad: float | None = None
    rounds: int = 0
    reaching: int = 0
    evaluations: int = 0
    best_error_mm: float = math.inf
    #: the smallest tangent angle (deg) from the axis among configurations reaching the target
    best_angle_deg: float = math.inf
    goals: list[np.ndarray] = field(default_factory=list)
    #: configurations that reached the target but failed the validator (for the status)
    rejected: list[np.ndarray] = field(default_factory=list)

    def _seeds(self, count: int) -> np.ndarray:
        """IK seeds for this round: among the next ``pool`` workspace samples nearest the
        target, the collision-free ones first (IK from a free configuration nearby tends to stay
        free), then jittered copies of them, then the colliding ones."""
        pool = 2 * count
        if self.axis is not None:
            cand = self._cone_seeds(pool)
        else:
            cand = self.table.nearest(self.target_base, pool, skip=self.rounds * pool)
        if len(cand) == 0:
            return cand
        free = self.validator.states_valid(cand)
        good, bad = cand[free], cand[~free]
        out = [good[:count]]
        need = count - len(out[0])
        if need > 0 and len(good):
            jit = good[self.rng.integers(0, len(good), need)].copy()
            n = self.robot.n
            jit[:, :n] += self.rng.normal(0, 0.1, (need, n))
            jit[:, n:] += self.rng.normal(0, 2.0, (need, n))
            out.append(_ik.project_joints(self.robot, jit))
            need = 0
        if need > 0:
            out.append(bad[:need])
        return np.concatenate(out, axis=0)

    def _cone_seeds(self, pool: int) -> np.ndarray:
        """For a goal with a direction: among the next ``4 pool`` workspace samples nearest the
        target, the ``pool`` whose tips are nearest it counting ``alpha_weight_mm`` mm per rad
        of the tangent beyond the cone (one batched shape call)."""
        from ctrplan.planning.tipgoal import angle_deg, tip_frames

        wide = self.table.nearest(self.target_base, 4 * pool, skip=self.rounds * 4 * pool)
        if len(wide) == 0:
            return wide
        tip, t, ok = tip_frames(self.model, wide)
        beyond = np.maximum(0.0, np.radians(angle_deg(t, self.axis)) - self.cone_rad)
        cost = np.linalg.norm(tip - self.target_base[None], axis=1) \
            + self.config.ik.alpha_weight_mm * beyond
        cost = np.where(ok, cost, np.inf)
        return wide[np.argsort(cost, kind="stable")[:pool]]

    def _solve(self, seeds: np.ndarray, ikc) -> _ik.IKResult:
        if self.axis is None:
            return _ik.solve_ik(self.model, self.robot, self.target_base, seeds, ikc)
        return _ik.solve_ik_cone(self.model, self.robot, self.target_base, seeds, self.axis,
                                 self.cone_rad, ikc)

    def next(self) -> np.ndarray:
        """Run one IK round; return new collision-free goal configurations (G, 2n)."""
        c = self.config
        seeds = self._seeds(c.ik.seeds)
        self.rounds += 1
        if len(seeds) == 0:
            return np.zeros((0, self.robot.dof))
        ikc = replace(c.ik, stop_mm=min(c.ik.stop_mm, 0.1 * self.tolerance_mm))
        res = self._solve(seeds, ikc)
        self.evaluations += res.evaluations
        if np.isfinite(res.error_mm).any():
            self.best_error_mm = min(self.best_error_mm, float(np.nanmin(res.error_mm)))
        reach = res.error_mm <= self.tolerance_mm
        if self.axis is not None:   # goals outside the cone are rejected
            within = res.angle_deg <= np.degrees(self.cone_rad)
            if (reach & np.isfinite(res.angle_deg)).any():
                self.best_angle_deg = min(self.best_angle_deg, float(np.min(
                    np.where(reach, res.angle_deg, np.inf))))
            reach &= within
        reach &= self.validator.joint_valid(res.q)
        self.reaching += int(reach.sum())
        if not reach.any():
            return np.zeros((0, self.robot.dof))
        q, err = res.q[reach], res.error_mm[reach]
        # Prefer converged seeds: looser ones (up to the tolerance) only when none converged.
        precise = err <= max(2.0 * ikc.stop_mm, 0.1 * self.tolerance_mm)
        if precise.any():
            q, err = q[precise], err[precise]
        order = np.argsort(err, kind="stable")
        q = q[order]
        # Drop near-duplicates (seeds that converged to the same configuration).
        keep: list[np.ndarray] = []
        w = c.validator.alpha_weight_mm
        for row in q:
            if all(motion_mm(row, k, self.robot.n, w) > 2.0 for k in keep + self.goals):
                keep.append(row)
        if not keep:
            return np.zeros((0, self.robot.dof))
        cand = np.array(keep)
        ok = self.validator.states_valid(cand)
        self.validator.remember(cand, ok)
        self.rejected.extend(cand[~ok][: c.max_goals])
        new = cand[ok][: c.max_goals]
        if self.rank is not None and len(new) > 1:   # the same goals, best ranked first
            new = new[np.argsort(-np.asarray(self.rank(new), dtype=float), kind="stable")]
        self.validator.anchor(new)   # the robot is on the equilibrium the tip was computed on
        self.goals.extend(new)
        return new
