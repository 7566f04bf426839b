"""The stages of a plan before verification: checks, IK goals, the search, simplification and
the local optimisation (stage 5, verification and the output, is :mod:`ctrplan.planning.verify`).

Each stage takes the plan's :class:`~ctrplan.planning.run.Run`, records its time and counts in
it, and either returns what the next stage needs or raises :class:`~ctrplan.planning.run.Stop`
with the result (a status that ends the plan). :meth:`ctrplan.planning.planner.Planner.plan`
runs them in order; see :mod:`ctrplan.planning.plan` for what each stage does.
"""

from __future__ import annotations

import math
import time

import numpy as np

from ctrplan.planning import hints as _hints
from ctrplan.planning import ik as _ik
from ctrplan.planning import optimize as _opt
from ctrplan.planning import rescue as _rescue
from ctrplan.planning import stability as _stab
from ctrplan.planning.arguments import check_start
from ctrplan.planning.goals import GoalSource, target_blocked, target_outside_lumen
from ctrplan.planning.result import PlanStatus
from ctrplan.planning.run import Run, Stop, state_clearance, tip_margin
from ctrplan.planning.validator import BatchValidator, motion_mm


def _start_collision_hint(robot, validator, start) -> str:
    """What the user can do about a start configuration in collision: where it touches, how
    deep, how far the start reaches past the base and the outer tube's radius (the base must
    lie inside the lumen by more than that radius, and the lumen must hold the start)."""
    try:
        _, clearance, contact = validator.check_states(start[None], exact=True, joints=False)
        points = validator.shapes(start[None]).points[0]
    except Exception:  # the hint is a courtesy: never let it hide the status itself
        return ""
    reach = float(np.linalg.norm(points - points[0], axis=1).max())
    radius = float(max(t.od for t in robot.tubes)) / 2.0
    mesh = str(contact[0]) or "the anatomy"
    depth = float(clearance[0])
    where = f" ({-depth:.2f} mm into {mesh})" if np.isfinite(depth) and depth < 0 else ""
    return (f"{where}; it reaches {reach:.1f} mm past the base with an outer radius of "
            f"{radius:.2f} mm: place base_pose inside the lumen by more than that radius, with "
            f"room for the start ahead of it (check it with `ctrplan check`), or give --start")


def _start_equilibria(run: Run, start: np.ndarray) -> str:
    """The equilibrium the robot is on at the start, for the planning model and the reference
    model where they track branches (InputError for a bistable start without its branch),
    remembered by the validator. Returns why the start is below the stability margin, or ""."""
    for model in (run.model, run.reference):
        if model is not None and model.tracks_branches and id(model) not in run.start_uz:
            run.start_uz[id(model)] = _stab.resolve_start(model, start, run.start_branch)
    tracker = run.validator.tracker
    if tracker is None:
        return ""
    uz = run.start_uz[id(run.model)]
    tracker.register(start[None], uz[None], anchor=True)
    at = tracker.states(start[None], 2, np.ones((1, run.robot.dof), dtype=np.int8)
                        if run.validator.directional else None, uz[None])
    if not at.shape.ok[0] and at.continued[0]:
        return (f"the start's elastic stability {float(at.stability[0]):.3g} is below the "
                f"stability margin {tracker.margin:g} (lower it with --stability-margin)")
    return ""


def _start_free(validator: BatchValidator, start: np.ndarray, uz0) -> bool:
    """Whether the start is collision-free (on its equilibrium ``uz0`` where known)."""
    if uz0 is None or validator.tracker is None:
        return bool(validator.states_valid(start[None])[0])
    d = np.ones((1, len(start)), dtype=np.int8) if validator.directional else None
    shape = validator.shapes(start[None], direction=d, uz0=np.asarray(uz0)[None])
    return bool(validator.joint_valid(start[None])[0]) and not bool(
        np.asarray(validator.plan_world.collides(shape))[0])


def checks(run: Run, start) -> np.ndarray:
    """Stage 1: reach, start configuration, target. Returns the start (2n,)."""
    t0 = time.perf_counter()
    robot, validator = run.robot, run.validator
    reach = _ik.max_reach_mm(robot)
    far = float(np.linalg.norm(run.target_base)) - reach
    if far > run.tolerance_mm:
        run.clock("checks", t0)
        raise Stop(run.finish(PlanStatus.UNREACHABLE, f"the target is {far:.1f} mm beyond the "
                               f"robot's reach ({reach:.1f} mm from the base)"))
    retracted = start is None or (isinstance(start, str) and start == "retracted")
    if retracted:
        t1 = time.perf_counter()
        start, adjusted = run.prep.retracted_start()   # computed once per planner
        run.timings["setup"] += time.perf_counter() - t1
        t0 += time.perf_counter() - t1
        run.counts["start_rotated"] = int(adjusted)
        run.meta["start_rotated"] = bool(adjusted)
    else:
        if isinstance(start, _stab.Start):
            run.start_branch, start = start.branch, start.q
        start = check_start(start, robot, validator)
    # The cap counts from here: setup (loading, caches) is not part of the plan's time.
    run.deadline = time.perf_counter() + run.time_limit
    unstable = _start_equilibria(run, start)
    if unstable:
        run.clock("checks", t0)
        raise Stop(run.finish(PlanStatus.UNSTABLE_ONLY, unstable))
    if not _start_free(validator, start, run.start_uz.get(id(run.model))):
        run.clock("checks", t0)
        which = "retracted, any tube rotation" if retracted else "given with --start"
        raise Stop(run.finish(PlanStatus.START_IN_COLLISION,
                               f"the start configuration ({which}) collides with the scene"
                               + (_hints.margin_start_hint(run, start, retracted, run.prep.world0)
                                  or _start_collision_hint(robot, validator, start))))
    tip_radius = float(robot.tubes[0].od) / 2.0
    if run.tip_goal is not None and run.tip_goal.back is not None:
        blocked = _standoff_goal(run, tip_radius)
    else:
        blocked = target_blocked(run.scene, run.world, run.target, tip_radius)
    if blocked and run.cfg.approach and run.tip_goal is None:
        moved = _approach_goal(run, tip_radius)
        if moved is not None:
            blocked = ""
    if blocked and _margin_alone(run, tip_radius):
        blocked = ""          # planned to as given; the reference model decides (rescue.py)
        run.counts["target_rescued"] = 1
    run.clock("checks", t0)
    if blocked:
        raise Stop(run.finish(PlanStatus.TARGET_IN_COLLISION, blocked))
    return start


def _margin_alone(run: Run, tip_radius: float) -> bool:
    """Whether only a surrogate's margin blocks the target: its tip probe is free in the
    reference world (margin 0) and the plan may rescue goals (:mod:`ctrplan.planning.rescue`)."""
    if not run.cfg.goal_rescue or (run.tip_goal is not None and run.tip_goal.back is not None):
        return False
    if not _rescue.allowed(run.model, run.reference, run.meta.get("reference_model", "")):
        return False
    return not target_blocked(run.scene, run.prep.reference_world(), run.target, tip_radius)


def _standoff_goal(run: Run, tip_radius: float) -> str:
    """A tip goal standing off a surface (:class:`~ctrplan.planning.tipgoal.TipGoal` with a
    normal or a direction): the tip's centre stays at least its radius + margin +
    :data:`~ctrplan.planning.tipgoal.CONTACT_PAD_MM` from the surface point, along the goal's
    normal (a smaller standoff, 0 = touching, is planned there and reported as
    ``goal_shift_mm``). Returns why the tip cannot be at the planned point ("" if it can)."""
    from ctrplan.planning.tipgoal import CONTACT_PAD_MM

    goal = run.tip_goal
    least = tip_radius + tip_margin(run) + CONTACT_PAD_MM
    if goal.standoff_mm < least:
        p = goal.point(least)
        run.goal_base = run.scene.to_base(p[None])[0]
        run.meta["goal_shift_mm"] = float(least - goal.standoff_mm)
        run.meta["goal"] = [float(v) for v in p]
    else:
        p = run.target
    blocked = target_blocked(run.scene, run.world, p, tip_radius)
    return f"{blocked} (at the standoff point {_xyz(p)})" if blocked else ""


def _xyz(p) -> str:
    return "(" + ", ".join(f"{float(v):.2f}" for v in p) + ") mm"


def _approach_goal(run: Run, tip_radius: float, steps: int = 48) -> np.ndarray | None:
    """Move the goal from a target nearer the anatomy than ``tip_radius`` + the tip's margin
    into the lumen along the distance field's gradient (central differences), until the
    tip's probe is free in the padded world, by at most the tip's margin. Returns the goal in
    the scene frame (and sets ``run.goal_base``), or None (no margin, no field, or not free
    within the allowed shift). Deterministic: a fixed number of steps."""
    allowed = tip_margin(run)
    if allowed <= 0 or not getattr(run.world, "fields", None):
        return None
    field_ = _opt.FieldClearance(run.world)
    target = np.asarray(run.target, dtype=float)
    p = target.copy()
    h = 0.05
    eye = np.eye(3)
    step = allowed / 8.0
    for _ in range(steps):
        if not target_blocked(run.scene, run.world, p, tip_radius):
            break
        probes = np.concatenate([p + h * eye, p - h * eye])
        d = field_.point_distance(probes)
        if not np.all(np.isfinite(d)):
            return None
        g = (d[:3] - d[3:]) / (2 * h)
        norm = float(np.linalg.norm(g))
        if norm < 1e-9:
            return None
        q = p + step * g / norm
        if np.linalg.norm(q - target) > allowed:
            return None
        p = q
    else:
        return None
    if np.array_equal(p, target) or target_outside_lumen(run.scene, p):
        return None
    run.goal_base = run.scene.to_base(p[None])[0]
    run.meta["goal_shift_mm"] = float(np.linalg.norm(p - target))
    run.meta["goal"] = [float(v) for v in p]
    return p


def ik_goals(run: Run) -> tuple[GoalSource, np.ndarray]:
    """Stage 2: IK rounds until collision-free goals exist (or the reason there are none)."""
    t0 = time.perf_counter()
    table = run.prep.workspace_table()                    # built once per planner
    run.timings["setup"] += time.perf_counter() - t0
    run.deadline += time.perf_counter() - t0
    t0 = time.perf_counter()
    rank = None
    if run.cfg.objective == "clearance" and run.cfg.goals_by_clearance:
        field_ = _opt.FieldClearance(run.world)

        def rank(q: np.ndarray) -> np.ndarray:   # goals with more room first
            return state_clearance(run.validator, field_, q)
    source = GoalSource(run.model, run.robot, run.validator, table, run.goal,
                        run.tolerance_mm, run.cfg, np.random.default_rng([run.seed, 1]), rank=rank,
                        **_cone(run))
    goals = source.next()
    while len(goals) == 0 and source.rounds < run.cfg.ik_rounds:
        goals = source.next()
    if len(goals) == 0 and source.reaching > 0:
        # only the planning model rejects them? a surrogate's reference decides (rescue.py)
        goals = _rescue.rescue_goals(run, source)
    if len(goals) == 0 and source.reaching > 0 and run.cfg.approach and run.tip_goal is None:
        # every configuration reaching the goal collides with the margin: approach from further
        # inside the lumen (the tip probe thicker by a part of the margin), within the margin
        tip_radius = float(run.robot.tubes[0].od) / 2.0
        allowed = tip_margin(run)
        for extra in (0.25 * allowed, 0.5 * allowed, allowed):
            if extra <= 0 or _approach_goal(run, tip_radius + extra) is None:
                continue
            source = GoalSource(run.model, run.robot, run.validator, table, run.goal,
                                run.tolerance_mm, run.cfg, np.random.default_rng([run.seed, 1]),
                                rank=rank)
            goals = source.next()
            while len(goals) == 0 and source.rounds < run.cfg.ik_rounds:
                goals = source.next()
            if len(goals):
                break
    run.clock("ik", t0)
    run.counts.update(ik_rounds=source.rounds, ik_reaching=source.reaching,
                      ik_evaluations=source.evaluations, goals=len(goals))
    if len(goals) == 0:
        if source.reaching == 0 and source.axis is not None:
            off = (f"; the best reaching it points {source.best_angle_deg:.1f} deg off the approach"
                   if math.isfinite(source.best_angle_deg) else "")
            raise Stop(run.finish(
                PlanStatus.UNREACHABLE, f"no configuration puts the tip within {run.tolerance_mm:g} "
                f"mm of the target with its direction within the cone of {run.tip_goal.cone_deg:g} "
                f"deg (best {source.best_error_mm:.2f} mm after {source.rounds} IK rounds{off})"))
        if source.reaching == 0:
            raise Stop(run.finish(
                PlanStatus.UNREACHABLE, f"no configuration puts the tip within {run.tolerance_mm:g} "
                f"mm of the target (best {source.best_error_mm:.2f} mm after {source.rounds} IK rounds)"))
        if target_outside_lumen(run.scene, run.target):
            raise Stop(run.finish(PlanStatus.TARGET_IN_COLLISION, "the target lies outside the lumen walls"))
        if run.validator.tracker is not None and len(source.rejected) and relaxed(run).states_valid(
                np.array(source.rejected)).any():
            raise Stop(run.finish(PlanStatus.UNSTABLE_ONLY, "every collision-free configuration "
                                   "reaching the target is below the stability margin "
                                   f"{run.validator.tracker.margin:g}"))
        raise Stop(run.finish(PlanStatus.GOAL_IN_COLLISION, f"{source.reaching} configurations "
                               "reach the target but all of them collide"))
    return source, goals


def _cone(run: Run) -> dict:
    """A tip pose goal's axis (base frame) and cone (rad) for the goal source ({} without)."""
    goal = run.tip_goal
    if goal is None or goal.direction is None:
        return {}
    from ctrplan.planning.tipgoal import to_base_vectors

    return dict(axis=to_base_vectors(run.scene, np.asarray(goal.direction)), cone_rad=goal.cone_rad)


def search(run: Run, start: np.ndarray, source: GoalSource,
                    goals: np.ndarray) -> tuple[np.ndarray, str]:
    """Stage 3: the straight edge to one of the nearest goals, else OMPL. Returns (waypoints,
    what solved it)."""
    from ctrplan.planning import space as _space

    cfg, validator = run.cfg, run.validator
    t0 = time.perf_counter()
    direct = _direct_path(validator, start, goals) if cfg.try_direct else None
    run.counts["direct"] = int(direct is not None)
    if direct is not None:
        run.clock("planning", t0)
        run.counts["states_validated"] = validator.counters.states
        return direct, "direct"
    refresh_s = [0.0]

    def more_goals() -> np.ndarray:
        t = time.perf_counter()
        g = source.next()
        refresh_s[0] += time.perf_counter() - t
        return g

    outcome = _space.solve(run.robot, validator, start, goals, planner=run.planner,
                           time_limit=max(0.0, run.deadline - time.perf_counter()),
                           seed=run.seed, alpha_weight_mm=cfg.validator.alpha_weight_mm,
                           range_mm=cfg.range_mm, more_goals=more_goals, simplify=cfg.simplify,
                           optimize=cfg.optimize, max_states=cfg.max_states)
    run.time_cap_hit |= outcome.time_cap_hit
    # IK rounds run while planning (goal refresh) count as IK time.
    run.timings["ik"] += refresh_s[0]
    run.timings["planning"] += (time.perf_counter() - t0) - outcome.simplification_s - refresh_s[0]
    run.timings["simplification"] += outcome.simplification_s
    run.counts.update(goals=outcome.goals_used, ik_rounds=source.rounds,
                      ik_reaching=source.reaching, ik_evaluations=source.evaluations,
                      states_validated=validator.counters.states)
    if outcome.path is None:
        why = (f"the time cap of {run.time_limit:.2f} s" if outcome.time_cap_hit
               else f"the budget of {cfg.max_states} states")
        if _only_unstable(run, start, source):
            raise Stop(run.finish(PlanStatus.UNSTABLE_ONLY, f"no path within {why} keeps the "
                                   f"stability margin {validator.tracker.margin:g} and its "
                                   "equilibrium branch; the same search without that constraint "
                                   "finds one, below the margin or through a fold (where the "
                                   "robot would snap)"))
        raise Stop(run.finish(PlanStatus.TIMEOUT, f"no collision-free path found within {why} "
                               f"({outcome.goals_used} goal configurations)"))
    return outcome.path, run.planner


def relaxed(run: Run) -> BatchValidator:
    """The planning validator without branch tracking and stability margin."""
    return BatchValidator(run.robot, run.model, run.world, run.cfg.validator, tracking=False)


def _only_unstable(run: Run, start: np.ndarray, source: GoalSource) -> bool:
    """After a search without a path: whether the stability constraint is what stopped it,
    established by the same search (budget, seed, goals) without it finding a path. Only run
    when the constraint rejected a state or edge during the search."""
    from ctrplan.planning import space as _space

    tracker = run.validator.tracker
    if tracker is None or not tracker.counters.any or not len(source.goals):
        return False
    cfg = run.cfg
    t0 = time.perf_counter()
    out = _space.solve(run.robot, relaxed(run), start, np.array(source.goals), planner=run.planner,
                       time_limit=run.time_limit, seed=run.seed,
                       alpha_weight_mm=cfg.validator.alpha_weight_mm, range_mm=cfg.range_mm,
                       simplify=False, optimize=cfg.optimize, max_states=cfg.max_states)
    run.clock("planning", t0)
    run.counts["unstable_only_check"] = 1
    return out.path is not None


def simplify(run: Run, path: np.ndarray) -> np.ndarray:
    """Stage 4: greedy shortcutting with the same validator (a count of edges, not a time)."""
    if run.cfg.simplify and len(path) > 2:
        t0 = time.perf_counter()
        path = run.validator.shortcut(path)
        run.clock("simplification", t0)
    run.counts["states_validated"] = run.validator.counters.states
    return path


def optimize(run: Run, path: np.ndarray) -> list[np.ndarray]:
    """Stage 4b: the local optimiser for the objective. Returns the optimised path and an
    earlier iterate (best first) for stage 5 to try before the simplified path; empty for
    ``first`` or when no step was accepted. Every iterate passed the validator's edge check
    (the planner's own: exact verdicts, same padding and margin, at the edge resolution)."""
    cfg = run.cfg
    if cfg.objective == "first" or len(path) < 2:
        return []
    t0 = time.perf_counter()
    # the optimised goal's tip error stays within max(its IK error, 0.4 x the IK's threshold)
    # a goal with a direction keeps its IK configuration (whose tangent is within the cone)
    keep = run.tip_goal is not None and run.tip_goal.direction is not None
    res = _opt.optimize_path(run.validator, path, run.goal, cfg.objective, cfg.optimizer,
                             goal_tol_mm=0.4 * min(cfg.ik.stop_mm, 0.1 * run.tolerance_mm),
                             deadline=run.deadline, keep_goal=keep)
    run.clock("optimization", t0)
    run.time_cap_hit |= res.time_cap_hit
    run.counts.update(optimizer_accepted=res.accepted, optimizer_trials=res.trials,
                      optimizer_evaluations=res.evaluations,
                      states_validated=run.validator.counters.states)
    if not res.accepted:
        return []
    return [res.path] + ([res.history[len(res.history) // 2]] if len(res.history) > 2 else [])


def _direct_path(validator: BatchValidator, start: np.ndarray, goals: np.ndarray,
                 tries: int = 4) -> np.ndarray | None:
    """Start -> goal as one straight edge, if one of the ``tries`` nearest goals allows it.

    In a tube-like lumen this is often the whole answer; it costs a few batched edge checks.
    """
    c = validator.config
    d = motion_mm(start[None], goals, validator.n, c.alpha_weight_mm)
    for k in np.argsort(d, kind="stable")[:tries]:
        if validator.edge_valid(start, goals[k]):
            return np.stack([start, goals[k]])
    return None
