"""Stage 5 of a plan, verification, and its output.

The path is checked at ``resolution / verify_factor`` with exact verdicts on the planning model
(its motion between checked states covered, its equilibrium branch continued; a failing segment
is re-planned with a finer validator, :func:`repair`), then with the reference model at margin
0; the optimised path is tried first and the simplified one last (:func:`verify_optimized`).
:func:`output` subdivides the verified path for execution and measures it: tip errors, the
clearances under both models (:func:`path_min_clearance`, the exact minimum by branch and
bound), the clearance profile, each state's branch and stability.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import replace
from typing import Any

import numpy as np

from ctrplan.planning import hints as _hints
from ctrplan.planning import optimize as _opt
from ctrplan.planning import stability as _stab
from ctrplan.planning.result import PlanResult, PlanStatus
from ctrplan.planning.run import Run, Stop, state_clearance, tip_margin
from ctrplan.planning.validator import (
    BatchValidator,
    PathCheck,
    edge_direction,
    interpolate_path,
    motion_mm,
    unwrap_path,
)

log = logging.getLogger("ctrplan")


def verify_optimized(run: Run, path: np.ndarray,
                      optimized: list[np.ndarray]) -> tuple[PathCheck, PathCheck | None, np.ndarray]:
    """Stage 5 on the optimised path; if it fails there (or in the reference model's check),
    on the earlier iterate, then on the simplified path (with repairs, as without an
    objective)."""
    for k, candidate in enumerate(optimized):
        try:
            return _verification(run, candidate, allow_repair=False)
        except Stop:
            run.counts["optimizer_fallbacks"] = k + 1
            log.debug("plan: optimised path %d failed verification; trying the next", k)
    return _verification(run, path)


def _verification(run: Run, path: np.ndarray,
                        allow_repair: bool = True) -> tuple[PathCheck, PathCheck | None, np.ndarray]:
    """Stage 5: exact check on the planning model at the fine resolution (failing segments
    re-planned unless ``allow_repair`` is False; the parameter was ``repair``, which shadowed
    :func:`repair` and made every repair a TypeError), then the reference model's check at
    margin 0."""
    cfg, validator = run.cfg, run.validator
    t0 = time.perf_counter()
    vres = cfg.validator.resolution_mm / max(1, cfg.verify_factor)
    vpoints = cfg.verify_points or cfg.validator.points
    check = validator.check_path(path, vres, points=vpoints, fcl_all=cfg.verify_fcl_all)
    attempts = 0
    while not check.ok and allow_repair and attempts < cfg.repair_attempts:
        attempts += 1
        repaired = repair(run.robot, run.model, run.world, path, check.bad_segments, cfg,
                           run.seed + attempts, vres / (2 * attempts),
                           budget=max(0.5, run.deadline - time.perf_counter()),
                           tracker=_remember_waypoints(validator, path, check),
                           rescue=validator.rescue)
        if repaired is None:
            break
        path = repaired
        check = validator.check_path(path, vres, points=vpoints, fcl_all=cfg.verify_fcl_all)
    run.counts.update(verification_states=len(check.states), repairs=attempts, waypoints=len(path))
    if check.deferred is not None and check.deferred.any():
        # states of a rescued goal's region: the reference model's check below decides them
        run.counts["verification_deferred"] = int(check.deferred.sum())
    if not check.ok:
        run.clock("verification", t0)
        bad = check.contact[check.first_bad] if check.first_bad >= 0 else ""
        if bad in _UNSTABLE_WHY:
            raise Stop(run.finish(PlanStatus.VERIFICATION_FAILED, f"the path {_UNSTABLE_WHY[bad]} "
                                   f"when checked at {vres:g} mm and could not be repaired"))
        raise Stop(run.finish(PlanStatus.VERIFICATION_FAILED, f"the path touches {bad or 'the scene'} "
                               f"when checked exactly at {vres:g} mm and could not be repaired"))
    ref_check = None
    if run.reference is not None:
        ref_val = _reference_validator(run, path[0])
        ref_check = ref_val.check_path(path, vres, points=vpoints, fcl_all=cfg.verify_fcl_all)
        run.counts["reference_states"] = len(ref_check.states)
        if not ref_check.ok:
            run.clock("verification", t0)
            bad = ref_check.contact[ref_check.first_bad]
            raise Stop(run.finish(PlanStatus.VERIFICATION_FAILED,
                                   f"the {run.meta['reference_model']} model's backbone along the "
                                   f"path touches {bad or 'the scene'} (checked at {vres:g} mm)"))
    run.clock("verification", t0)
    return check, ref_check, path


def _reference_validator(run: Run, start: np.ndarray) -> BatchValidator:
    """The reference model's validator at margin 0, its path starting on its branch."""
    ref = run.reference
    val = BatchValidator(run.robot, ref, run.prep.reference_world(), run.cfg.validator)
    if val.tracker is not None and id(ref) in run.start_uz:   # the path starts on its branch
        val.tracker.register(start[None], run.start_uz[id(ref)][None], anchor=True)
    return val


def output(run: Run, path: np.ndarray, solver: str, check: PathCheck,
            ref_check: PathCheck | None) -> PlanResult:
    """The path subdivided for execution (rotations unwrapped), backbones in the scene frame,
    tip errors and the clearances under both models."""
    cfg, n = run.cfg, run.robot.n
    t0 = time.perf_counter()
    out_q = path
    seg = np.minimum(np.arange(len(path)), max(0, len(path) - 2))
    if cfg.output_step_mm > 0:
        out_q, seg = interpolate_path(path, n, cfg.validator.alpha_weight_mm, cfg.output_step_mm)
    out_q = unwrap_path(out_q, n)
    eq = _output_equilibria(run, out_q, check, ref_check)
    profile, value = _profile(run, path, out_q, seg, eq.get("uz0"))
    shape = eq["shape"] if "shape" in eq else run.model.shape(out_q, points=cfg.output_points)
    backbones = run.scene.to_scene(shape.points)
    tip_err = float(np.linalg.norm(shape.tip[-1] - run.target_base))
    tip_err_phys = tip_err
    if run.model.name != "physics":
        phys = run.prep.physics()
        tip_err_phys = float(np.linalg.norm(phys.shape(out_q[-1:], points=2).tip[0] - run.target_base))
    run.counts["path_states"] = len(out_q)
    vpoints = cfg.verify_points or cfg.validator.points
    clear, exact, calls = path_min_clearance(run.validator, run.world, check, vpoints,
                                             max_pairs=cfg.clearance_pairs)
    run.counts["clearance_exact_states"] = calls
    from ctrplan.shape.error_bounds import margin_least

    # the padded capsules' clearance plus the smallest margin along the shaft: a lower bound
    extra = dict(min_clearance_mm=clear + margin_least(run.margin_mm) if math.isfinite(clear) else clear,
                 min_clearance_exact=exact)
    if ref_check is not None:
        ref_val = _reference_validator(run, path[0])
        rc, rexact, _ = path_min_clearance(ref_val, ref_val.world, ref_check, vpoints,
                                           max_pairs=cfg.clearance_pairs)
        extra.update(min_clearance_reference_mm=rc, min_clearance_reference_exact=rexact)
    elif cfg.reference is not None:   # the planning model is the reference, margin 0
        extra.update(min_clearance_reference_mm=extra["min_clearance_mm"],
                     min_clearance_reference_exact=exact)
    run.clock("verification", t0)
    run.meta["planner"] = solver
    # SUCCESS means the tip within the tolerance of the target asked for (planning model),
    # whatever moved the goal (the approach off the wall, the optimiser)
    status, message = PlanStatus.SUCCESS, "ok"
    pose = tip_pose(run, out_q[-1], eq.get("uz0"))
    if not tip_err <= run.tolerance_mm:
        status = PlanStatus.OUTSIDE_TOLERANCE
        message = _hints.outside_tolerance(run, tip_err, tip_margin(run))
    elif run.tip_goal is not None and run.tip_goal.cone_deg is not None and not (
            pose["direction_error_deg"] <= run.tip_goal.cone_deg):
        status = PlanStatus.OUTSIDE_TOLERANCE
        message = (f"the tip points {pose['direction_error_deg']:.2f} deg from the approach "
                   f"direction, outside the cone of {run.tip_goal.cone_deg:g} deg "
                   f"(direction_error_deg); the verified path is kept")
    return run.finish(status, message, **pose, path=out_q, backbones=backbones,
                      tip_path=backbones[:, -1, :], tip_error_mm=tip_err,
                      tip_error_physics_mm=tip_err_phys, clearance_profile=profile,
                      objective_value=value, branch=eq.get("branch"),
                      stability=eq.get("stability"), **extra)


def tip_pose(run: Run, q: np.ndarray, uz0=None) -> dict:
    """The final state's tip pose for plan.json: ``tip_direction`` (scene frame, unit; the
    planning model's tip tangent on the equilibrium the robot is on, ``uz0`` (B, n) the output
    states' where tracked), ``direction_error_deg`` (against a TipGoal's direction) and
    ``standoff_mm`` (the tip's distance from a TipGoal's surface point along its normal, or
    back along its direction)."""
    from ctrplan.planning.tipgoal import TANGENT_POINTS, angle_deg, tip_tangents, to_scene_vectors

    q = np.asarray(q, dtype=float)[None]
    if uz0 is not None and run.model.tracks_branches:
        pts = run.model.settle(q, np.asarray(uz0)[-1:], TANGENT_POINTS).shape.points
    else:
        pts = run.model.shape(q, points=TANGENT_POINTS).points
    t = to_scene_vectors(run.scene, tip_tangents(pts))[0]
    tip = run.scene.to_scene(pts[:, -1])[0]
    out = dict(tip_direction=t, direction_error_deg=math.nan, standoff_mm=math.nan)
    goal = run.tip_goal
    if goal is None:
        return out
    if goal.direction is not None:
        out["direction_error_deg"] = float(angle_deg(t[None], np.asarray(goal.direction))[0])
    back = goal.back
    if back is not None:
        out["standoff_mm"] = float(np.dot(tip - np.asarray(goal.position), back))
    return out


def _output_equilibria(run: Run, out_q: np.ndarray, check: PathCheck,
                       ref_check: PathCheck | None) -> dict:
    """Per output state, the equilibrium the robot is on (continued from the verified state
    before it: :func:`~ctrplan.planning.stability.output_equilibria`), its branch label and
    stability: of the planning model (then also its shapes, ``shape``, and ``uz0``) or else
    of the reference model where one of them tracks branches; {} otherwise."""
    cfg, n = run.cfg, run.robot.n
    for model, chk, own in ((run.model, check, True), (run.reference, ref_check, False)):
        if model is None or chk is None or chk.uz0 is None or not model.tracks_branches:
            continue
        # (a direction-aware model's output shapes are its shapes without a direction of
        # motion, as the tip error always was: the continued equilibrium moves with them)
        t, labels = _stab.output_equilibria(model, out_q, chk.states, chk.uz0, n,
                                            cfg.validator.alpha_weight_mm, cfg.output_points)
        out = {"branch": [int(v) for v in labels], "stability": _stab.stability_list(t.stability)}
        if own:
            out.update(shape=t.shape, uz0=t.uz0)
        return out
    return {}


def _profile(run: Run, path: np.ndarray, out_q: np.ndarray, seg: np.ndarray,
             uz0: np.ndarray | None = None) -> tuple[np.ndarray, float]:
    """(clearance profile (K,) mm over the output states, margin not included; the objective's
    value on the path). uz0 : (K, n) the states' equilibria (branch tracking), or None."""
    n, w = run.robot.n, run.cfg.validator.alpha_weight_mm
    direction = None
    if run.validator.directional and len(path) > 1:
        dirs = np.array([edge_direction(a, b, n) for a, b in zip(path[:-1], path[1:])])
        direction = dirs[seg]
        joins = np.flatnonzero(np.r_[False, seg[1:] != seg[:-1]])
        direction[joins] = 0        # a waypoint joins two edges: both directions checked
    profile = state_clearance(run.validator, _opt.FieldClearance(run.world), out_q, direction, uz0)
    from ctrplan.shape.error_bounds import margin_least

    # measured with capsules grown by the margin: add back the smallest margin along the shaft
    # (the whole margin where it is uniform), which keeps it a clearance of the tube itself
    profile = profile + margin_least(run.margin_mm)
    if run.cfg.objective == "clearance":
        value = _opt.clearance_integral(profile, out_q, n, w)
    elif run.cfg.objective == "length":
        value = float(motion_mm(out_q[:-1], out_q[1:], n, w).sum()) if len(out_q) > 1 else 0.0
    else:
        value = math.nan
    return profile, value


def path_min_clearance(validator: BatchValidator, world, check, points: int | None,
                       batch: int = 16, max_pairs: int = 300) -> tuple[float, bool, int]:
    """Smallest clearance (mm) over the verified states of a path, by branch and bound.

    The world's conservative clearance of every state is a lower bound of its exact distance.
    States are taken in order of increasing bound and measured exactly
    (:meth:`CollisionWorld.clearance_bounded`, itself a branch and bound over capsule-mesh
    pairs) until the smallest distance found is no larger than the next state's bound: then it
    is the exact minimum. The work is capped at ``max_pairs`` pair distances (a count, not a
    time, so the same path always gives the same value); if that does not
    settle it, the result is a valid lower bound, at least 0 (the states passed the exact
    collision check). Returns (value, exact, states measured).
    """
    bounds = np.asarray(check.clearance_mm, dtype=float)
    if len(bounds) == 0:
        return math.nan, False, 0
    direction = getattr(check, "direction", None)
    uz = getattr(check, "uz0", None)          # the states' equilibria (branch tracking)
    order = np.argsort(bounds, kind="stable")
    best = math.inf
    done, left = 0, int(max_pairs)
    settled = True
    while done < len(order):
        idx = order[done:done + batch]
        for d in validator.variants(check.states[idx], None if direction is None else direction[idx]):
            shape = validator.shapes(check.states[idx], points=points, direction=d,
                                     uz0=None if uz is None else uz[idx])
            values, used = world.clearance_bounded(shape, below=best, max_pairs=left)
            best = min(best, float(np.min(values)))
            left -= used
            settled &= left > 0
        done += len(idx)
        if done >= len(order) or best <= bounds[order[done]]:
            return max(0.0, best), bool(settled and best >= 0), done
        if left <= 0:
            break
    return max(0.0, min(best, float(bounds[order[done]]))), False, done


#: what a path failing the branch tracking does (the contacts of :mod:`ctrplan.planning.tracking`)
_UNSTABLE_WHY = {"fold": "crosses a fold of the equilibrium branch (the robot would snap there)",
                 "stability": "falls below the stability margin",
                 "branch": "arrives on another equilibrium branch than the one planned"}


def _remember_waypoints(validator: BatchValidator, path: np.ndarray, check: PathCheck):
    """The validator's tracker (None without), with every waypoint the exact check reached
    on its branch remembered with that equilibrium (so a repair connects to it)."""
    tracker = validator.tracker
    if tracker is None or check.uz0 is None:
        return tracker
    firsts = np.flatnonzero(np.r_[True, check.segment[1:] != check.segment[:-1]])
    for j, i in zip(check.segment[firsts], firsts):
        if tracker.lookup(path[j]) is None and check.contact[i] not in _UNSTABLE_WHY:
            tracker.register(path[j][None], check.uz0[i][None])
    return tracker


def repair(robot, model, world, path: np.ndarray, bad_segments: list[int], cfg: Any,
            seed: int, resolution_mm: float, budget: float, tracker=None,
            rescue=None) -> np.ndarray | None:
    """Re-plan the segments that failed verification with a finer validator; None on failure.
    Each segment's search is budgeted in states (``cfg.repair_states``); ``budget`` (s) is a cap.
    ``tracker`` : the planning validator's branch tracker (its remembered equilibria);
    ``rescue`` : its :class:`~ctrplan.planning.rescue.GoalRescue` (rescued goals' regions)."""
    from ctrplan.planning import space as _space

    strict = BatchValidator(robot, model, world, replace(cfg.validator, resolution_mm=resolution_mm),
                            tracking=tracker if tracker is not None else True)
    strict.rescue = rescue
    pieces: list[np.ndarray] = []
    last = 0
    for j in bad_segments:
        pieces.append(path[last:j])
        sub = _space.solve(robot, strict, path[j], path[j + 1][None], planner="rrtconnect",
                           time_limit=budget, seed=seed, alpha_weight_mm=cfg.validator.alpha_weight_mm,
                           range_mm=cfg.range_mm, simplify=cfg.simplify, max_states=cfg.repair_states)
        if sub.path is None:
            log.debug("plan: repair of segment %d failed", j)
            return None
        pieces.append(sub.path[:-1])
        last = j + 1
    pieces.append(path[last:])
    return np.concatenate([p for p in pieces if len(p)], axis=0)
