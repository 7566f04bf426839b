"""One design, evaluated: batched pre-screen, then real plans, then the stability check.

Everything here is a pure function of (design, targets, settings, seed), so evaluations can
run in any process in any order (:mod:`ctrplan.design.search` collects them in order).

Stages (timed separately, ``timings``):

1. **screen_entry** — the retracted start (alpha 0 and all tubes rotated together by k x 45
   deg) must be collision-free with the planning margin (``entry`` binds otherwise).
2. **screen_sample** — ``screen_samples`` configurations sampled (seeded) and solved in one
   batch by the physics model, checked in one batch against the scene (distance field, then
   FCL for the uncertain ones); the collision-free tips are the sampled tip workspace.
3. **screen_ik** — per target, the nearest free sampled tips seed a batched IK; a target
   passes the screen when a collision-free IK solution is within ``screen_tolerance_mm``.
4. **plans** — (promising designs only) one :class:`~ctrplan.planning.planner.Planner` per
   design (physics model, the settings' margin, auto unless set, and state budget), a plan
   from the retracted start for each target that passed the screen (:func:`plan_target`, the
   one place design plans); in the search the first path found (objective ``first``, cheap),
   for the chosen design the clearance objective.
5. **stability** — every successful path is interpolated densely (``stability_step_mm`` /
   ``stability_step_rad``) and solved by the compliant model with the bistability probe: a
   state with two stable equilibria (snapping) or none stable fails the plan (``stability``).
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from ctrplan.robot import Robot


@dataclass(frozen=True)
class EvalSettings:
    """Settings of one evaluation (taken from :class:`~ctrplan.design.DesignConfig`)."""

    screen_samples: int = 1024
    screen_points: int = 16
    screen_ik_seeds: int = 8
    screen_tolerance_mm: float = 2.0
    tolerance_mm: float = 1.0
    margin_mm: float | None = None
    plan_time_s: float = 10.0
    plan_states: int = 30_000
    stability_step_mm: float = 1.0
    stability_step_rad: float = 0.02
    curvature_bound: float = 0.1


# ------------------------------------------------------------------ a job's context
def context(scene_spec, settings: EvalSettings, planners=None):
    """(scene, world): the scene (``planners`` keeps scenes loaded by name: the Runner's own,
    or the worker process's, :func:`~ctrplan.planning.planner.worker_planners`) and one
    CollisionWorld padded for the largest curvature any design may have (conservative for every
    design), over the geometry kept on the scene object
    (:func:`ctrplan.collision.world.world_for`), so nothing outlives the scene."""
    from ctrplan.collision.world import world_for
    from ctrplan.planning.planner import worker_planners

    scene = (planners if planners is not None else worker_planners()).scene(scene_spec)
    return scene, world_for(scene, settings.margin_mm or 0.0, settings.curvature_bound)


def _shape(model, q, points):
    """Backbones of configurations q (B, 2n) in one batched physics call."""
    return model.shape(np.atleast_2d(q), points=points)


def screen(robot: Robot, scene, world, targets_base: np.ndarray, settings: EvalSettings,
           seed: int) -> dict:
    """Stages 1-3. Returns ``entry_ok``, ``entry_clearance_mm`` (the best start rotation's
    clearance; negative: a lower bound of its penetration), ``errors`` (T,) mm (None: nothing free near),
    ``passed`` (T,) bool, ``goal_clearance_mm`` (T,) (the largest conservative clearance of a
    collision-free IK goal within tolerance; None where none) and ``timings``."""
    from ctrplan.planning.ik import IKConfig, solve_ik
    from ctrplan.shape.physics import PhysicsModel

    t0 = time.perf_counter()
    timings: dict[str, float] = {}
    model = PhysicsModel(robot)
    T = len(targets_base)
    q0 = robot.retracted()
    rots = np.array([q0] + [np.concatenate([np.full(robot.n, a), q0[robot.n:]])
                            for a in np.arange(1, 8) * math.pi / 4])
    rep0 = world.check(_shape(model, rots, settings.screen_points))
    free0 = ~np.asarray(rep0.collides, dtype=bool)
    # the best rotation's clearance (negative: a lower bound of its penetration depth)
    entry_clearance = float(np.max(rep0.clearance_mm))
    timings["screen_entry"] = time.perf_counter() - t0
    if not free0.any():
        return {"entry_ok": False, "entry_clearance_mm": entry_clearance, "errors": [None] * T,
                "passed": [False] * T, "goal_clearance_mm": [None] * T, "timings": timings}
    t1 = time.perf_counter()
    q = robot.sample(settings.screen_samples, seed=seed)
    sh = _shape(model, q, settings.screen_points)
    free = ~world.collides(sh) & np.asarray(sh.ok, dtype=bool)
    tips = sh.tip
    timings["screen_sample"] = time.perf_counter() - t1
    t2 = time.perf_counter()
    errors = np.full(T, math.inf)
    goal_clear = np.full(T, math.nan)
    pool = np.flatnonzero(free) if free.any() else np.arange(len(q))
    cfg = IKConfig(max_iter=15)
    for j in range(T):
        d = np.linalg.norm(tips[pool] - targets_base[j], axis=1)
        near = pool[np.argsort(d, kind="stable")[: settings.screen_ik_seeds]]
        res = solve_ik(model, robot, targets_base[j], q[near], cfg)
        ok = np.isfinite(res.error_mm)
        if ok.any():
            sol = res.q[ok]
            rep = world.check(_shape(model, sol, settings.screen_points))
            fr = ~rep.collides
            err = res.error_mm[ok][fr]
            if len(err):
                errors[j] = float(err.min())
                # clearance at the goals that reach (a bound the whole path cannot beat)
                within = err <= settings.screen_tolerance_mm
                if within.any():
                    goal_clear[j] = float(np.max(np.asarray(rep.clearance_mm)[fr][within]))
        if not math.isfinite(errors[j]) and free.any():
            # no free IK solution: the free sampled tip workspace's distance (a smooth signal)
            errors[j] = float(d.min()) + 10.0
    timings["screen_ik"] = time.perf_counter() - t2
    return {"entry_ok": True, "entry_clearance_mm": entry_clearance,
            "errors": [float(e) if math.isfinite(e) else None for e in errors],
            "passed": (errors <= settings.screen_tolerance_mm).tolist(),
            "goal_clearance_mm": [float(c) if math.isfinite(c) else None for c in goal_clear],
            "timings": timings}


def dense_path(path: np.ndarray, n: int, step_mm: float, step_rad: float) -> np.ndarray:
    """(K, 2n) path states interpolated linearly so that consecutive states differ by at most
    ``step_mm`` in every beta and ``step_rad`` in every alpha (the verified motion is the
    linear interpolation between path states)."""
    path = np.atleast_2d(np.asarray(path, dtype=float))
    out = [path[:1]]
    for a, b in zip(path[:-1], path[1:]):
        d = np.abs(b - a)
        m = int(max(1, math.ceil(max(d[:n].max() / step_rad, d[n:].max() / step_mm))))
        t = np.linspace(0.0, 1.0, m + 1)[1:, None]
        out.append(a + t * (b - a))
    return np.concatenate(out)


def stable_along(robot: Robot, path: np.ndarray, settings: EvalSettings) -> tuple[bool, int]:
    """Whether every densely interpolated state of ``path`` has one stable equilibrium of the
    compliant model (not bistable, a stable one found, solver converged); and the number of
    states checked."""
    from ctrplan.shape.physics import PhysicsConfig, PhysicsModel

    states = dense_path(path, robot.n, settings.stability_step_mm, settings.stability_step_rad)
    model = PhysicsModel(robot, config=PhysicsConfig(probe_bistable=True))
    sh = model.shape(states, points=8)
    info = model.last_info
    ok = np.asarray(sh.ok, dtype=bool)
    if info is not None and info.branch is not None:
        ok &= ~np.asarray(info.bistable, dtype=bool) & (np.asarray(info.branch) != -1)
    return bool(ok.all()), int(len(states))


def design_planner(robot: Robot, scene, settings: EvalSettings):
    """The Planner of one design: physics model, the settings' margin and state budget."""
    from ctrplan.planning.planner import Planner, PlannerConfig

    cfg = PlannerConfig(max_states=settings.plan_states, margin_mm=settings.margin_mm)
    return Planner(robot, scene, "physics", cfg)


def plan_target(planner, target: np.ndarray, settings: EvalSettings, seed: int, objective: str):
    """The one place design plans: a PlanResult of the design's ``planner``
    (:func:`design_planner`) from the retracted start to ``target`` (scene frame) with the
    settings' tolerance and time cap and the path ``objective`` (``first`` in the search,
    ``clearance`` for the chosen design)."""
    return planner.plan(target, seed=seed, time_limit=settings.plan_time_s,
                        tolerance_mm=settings.tolerance_mm, objective=objective)


def plans(robot: Robot, scene, targets_scene: np.ndarray, todo: list[int], settings: EvalSettings,
          seed: int, keep: bool = False, objective: str = "first") -> dict:
    """Stages 4-5 for the targets ``todo`` (:func:`plan_target` with ``objective``, then the
    stability check). Returns per target (T lists) ``status``,
    ``reached``, ``clearance_mm`` (conservative: the plans' minimum clearance, planning and
    reference model), ``clearance_estimate_mm`` (FCL's exact minimum where the plan settled it,
    else the distance fields' estimate at the path's states, not between them: what designs
    are ranked by, not a bound),
    ``tip_error_mm``, ``stable``; ``results`` (PlanResults,
    only with ``keep``) and ``timings``."""
    T = len(targets_scene)
    out = {"status": ["NOT_TRIED"] * T, "reached": [False] * T, "clearance_mm": [None] * T,
           "clearance_estimate_mm": [None] * T,
           "tip_error_mm": [None] * T, "stable": [None] * T, "results": [None] * T,
           "stability_states": 0}
    t_plan = t_stab = 0.0
    planner = design_planner(robot, scene, settings) if todo else None
    for j in todo:
        t0 = time.perf_counter()
        r = plan_target(planner, targets_scene[j], settings, seed, objective)
        t_plan += time.perf_counter() - t0
        out["status"][j] = r.status.value
        if keep:
            out["results"][j] = r
        if not r.success:
            continue
        t1 = time.perf_counter()
        stable, k = stable_along(robot, r.path, settings)
        t_stab += time.perf_counter() - t1
        out["stability_states"] += k
        out["stable"][j] = stable
        out["tip_error_mm"][j] = float(r.tip_error_physics_mm) if math.isfinite(r.tip_error_physics_mm) \
            else float(r.tip_error_mm)
        c = r.min_clearance_reference_mm if math.isfinite(r.min_clearance_reference_mm) else r.min_clearance_mm
        out["clearance_mm"][j] = float(min(c, r.min_clearance_mm))
        # for ranking designs: FCL's minimum where it settled it, else the distance fields'
        # estimate along the path (a lower bound of 0 says nothing about the design)
        prof = np.asarray(r.clearance_profile, dtype=float)
        est = r.min_clearance_mm if r.min_clearance_exact or not len(prof) else float(prof.min())
        out["clearance_estimate_mm"][j] = float(est)
        if stable:
            out["reached"][j] = True
        else:
            out["status"][j] = "UNSTABLE"
    out["timings"] = {"plans": t_plan, "stability": t_stab}
    if not keep:
        del out["results"]
    return out


def evaluate_job(job: dict, planners=None) -> dict:
    """Worker entry point: ``job`` has ``robot`` (dict), ``scene`` (spec), ``targets`` (T, 3
    scene frame), ``settings`` (dict), ``seed``, ``stage`` ("screen", "plan" or "final": the
    chosen design's plans with the clearance objective, PlanResults kept) and, for plans,
    ``todo``. ``planners`` : what keeps the scene (None: this worker process's). Returns a
    JSON-ready dict (with PlanResults for "final")."""
    from ctrplan.robot import robot_from_dict

    settings = EvalSettings(**job["settings"])
    robot = robot_from_dict(job["robot"], "<design>")
    scene, world = context(job["scene"], settings, planners)
    targets = np.asarray(job["targets"], dtype=float)
    if job["stage"] == "screen":
        return screen(robot, scene, world, scene.to_base(targets), settings, int(job["seed"]))
    if job["stage"] == "final":      # the chosen design: clearance objective, PlanResults kept
        return plans(robot, scene, targets, list(job["todo"]), settings, int(job["seed"]), keep=True,
                     objective="clearance")
    return plans(robot, scene, targets, list(job["todo"]), settings, int(job["seed"]))
