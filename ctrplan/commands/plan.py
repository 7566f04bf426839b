"""``ctrplan plan``: plan a motion to a target point and write plan.json."""

from __future__ import annotations

import argparse
import logging
import math
import re
from pathlib import Path

from ctrplan.commands._common import (
    POSITIVE,
    SEED,
    add_device_arg,
    add_model_arg,
    device_arg,
    output_path,
)
from ctrplan.commands._vocab import DEFAULT_OUT
from ctrplan.errors import InputError
from ctrplan.io import excerpt, strict_float

log = logging.getLogger("ctrplan")


#: A value such as ``-5,20,0`` or ``-1e-3`` (argparse would take it for an option).
NEGATIVE_VALUE = re.compile(r"^-\.?\d[\d.,eE+\-\s]*$")


def allow_negative_values(p: argparse.ArgumentParser) -> None:
    """Let option values start with a minus sign (``--target -5,20,0``): argparse treats a
    token that starts with ``-`` and is not a plain number as an option unless the parser's
    negative-number pattern accepts it."""
    p._negative_number_matcher = NEGATIVE_VALUE


def add_margin_arg(p: argparse.ArgumentParser, what: str) -> None:
    p.add_argument("--margin", default="auto", metavar="MM|auto",
                   help=f"clearance added to the tube radii {what}, mm; 'auto' (default) = the "
                        "model's error bound (p99 of its held-out deviation: measured on the "
                        "robot for a calibrated model, the surrogate error for the shipped "
                        "learned one; 0 for physics)")


def parse_margin(text) -> float | None:
    """``--margin``: a number >= 0 (mm), or ``auto`` (None)."""
    if text is None or str(text).strip().lower() == "auto":
        return None
    try:
        v = strict_float(text)
    except ValueError:
        raise InputError("--margin", "", f"must be a number (mm) or auto, got {excerpt(text)}") from None
    if not (math.isfinite(v) and v >= 0):
        raise InputError("--margin", "", f"must be a number >= 0 (mm) or auto, got {excerpt(text)}")
    from ctrplan.robot import PLAUSIBLE

    if v > PLAUSIBLE["length"][1]:      # (FCL's geometry breaks down long before 1e300 mm)
        raise InputError("--margin", "", f"{v:.4g} mm is outside the plausible range "
                         f"[0, {PLAUSIBLE['length'][1]:g}] mm")
    return v


def add_planning_args(p: argparse.ArgumentParser) -> None:
    """Options shared by ``plan`` and ``plan-batch``."""
    p.add_argument("--robot", default="seed1",
                   help="shipped robot name (seed1, two_tube_nylon, two_tube_wide) or robot YAML path (default seed1)")
    add_model_arg(p, default="physics")
    add_device_arg(p)
    p.add_argument("--planner", default="rrtconnect",
                   help="rrtconnect (default), rrt, rrtstar, bitstar, kpiece, bkpiece, lbkpiece (prm is refused: it deadlocks with Python validity checkers)")
    p.add_argument("--time", type=POSITIVE, default=5.0, help="time limit per plan, s (default 5)")
    p.add_argument("--tolerance", type=POSITIVE, default=1.0,
                   help="accepted tip-to-target distance, mm (default 1)")
    add_margin_arg(p, "while planning")
    p.add_argument("--objective", default="clearance", metavar="clearance|length|first",
                   help="what the found path is optimised for: 'clearance' (default: keep as far "
                        "from the anatomy as the robot allows), 'length' (short and smooth) or "
                        "'first' (the first solution found, simplified)")


def parse_objective(text) -> str:
    """``--objective``: clearance, length or first (InputError otherwise)."""
    from ctrplan.planning.arguments import check_objective

    return check_objective(text)


def summary_line(plan: dict, model: str, robot: str) -> str:
    """The human summary printed after a plan: status, tip error (and the tolerance when it was
    missed), a goal moved off the anatomy (``goal_shift_mm``), closest approach, what the
    clearance is relative to (a calibrated model; a surrogate of the nominal model padded by
    its surrogate error; or the nominal model and how to calibrate), and a start whose tube
    rotations were changed (``start_rotated``)."""
    status = plan.get("status", "?")
    message = str(plan.get("message", ""))
    shift = float(plan.get("goal_shift_mm") or 0.0)
    moved = (f" (the goal was moved {shift:.2f} mm off the anatomy to keep the tip's margin: "
             f"goal_shift_mm)" if shift > 0 and "goal_shift_mm" not in message else "")
    if not plan.get("path"):
        return f"{status}: {message}{moved}{_start_note(plan)}"
    tip = plan.get("tip_error_mm")
    clear = plan.get("min_clearance_mm")
    head = (f"{status}: tip {'n/a' if tip is None else f'{tip:.3f}'} mm from the target"
            if plan.get("success") else f"{status}: {message}")
    text = (f"{head}{moved}{',' if plan.get('success') else ';'} closest approach "
            f"{'n/a' if clear is None else f'{clear:.2f}'} mm to the anatomy (objective "
            f"{plan.get('objective', '?')})")
    return (text + _pose_note(plan) + _relative_to(plan, model, robot) + _start_note(plan)
            + _motion_note(plan))


def _pose_note(plan: dict) -> str:
    """A tip pose goal's outcome: where the target was snapped to, the tip's direction error
    against the cone and the standoff achieved."""
    parts = []
    if plan.get("snap_distance_mm") is not None:
        parts.append(f"target snapped {plan['snap_distance_mm']:.2f} mm onto "
                     f"{plan.get('snap_mesh') or 'the anatomy'}")
    err, cone = plan.get("direction_error_deg"), plan.get("cone_deg")
    if err is not None and cone is not None:
        parts.append(f"tip direction {err:.1f} deg from the approach (cone {cone:g} deg)")
    if plan.get("standoff_mm") is not None:
        parts.append(f"standoff {plan['standoff_mm']:.2f} mm (asked "
                     f"{float(plan.get('standoff_requested_mm') or 0.0):.2f})")
    return "; " + ", ".join(parts) if parts else ""


def _motion_note(plan: dict) -> str:
    """The trajectory's duration (``duration_s``) and the file it was written to."""
    duration = plan.get("duration_s")
    if duration is None:
        return ""
    traj = plan.get("trajectory") or {}
    where = f" -> {traj['file']}" if traj.get("file") else ""
    return f"; the motion takes {duration:.2f} s within the actuator limits{where}"


def _start_note(plan: dict) -> str:
    """The rotated start (``start_rotated``), with its rotations where the path holds them."""
    if not plan.get("start_rotated"):
        return ""
    path = plan.get("path") or []
    n = len(path[0]) // 2 if path else 0
    rot = (" to alpha = (" + ", ".join(f"{a:.2f}" for a in path[0][:n]) + ") rad" if n else "")
    return (f"; the retracted start collided, so its tube rotations were changed{rot} "
            f"(start_rotated)")


def _relative_to(plan: dict, model: str, robot: str) -> str:
    """What the clearance is relative to, and the margin's origin."""
    from ctrplan.shape.error_bounds import surrogate_of

    margin = float(plan.get("margin_mm") or 0.0)
    if plan.get("calibrated"):
        out = plan.get("outside_measured_states")
        beyond = (f"; {out} of {len(plan.get('path') or [])} states insert a tube beyond the "
                  "measured insertions (the error bound is extrapolated there)" if out else "")
        return (f"; relative to the calibrated model {model!r}, with its error bound as a "
                f"{margin:.2f} mm margin" if plan.get("margin_auto") else
                f"; relative to the calibrated model {model!r}, margin {margin:g} mm") + beyond
    calibrate = (f"). To calibrate: `ctrplan diagnose --robot {robot} --data measured.csv "
                 f"--out report/`, then plan with `--model report/calibrated.yaml --margin auto`")
    sur = plan.get("surrogate_error")
    if isinstance(sur, dict):
        pad = (f"padded by its surrogate error as a {margin:.2f} mm margin"
               if plan.get("margin_auto") else
               f"with the stated margin of {margin:g} mm (its surrogate error: p99 "
               f"{float(sur.get('p99') or 0.0):.2f} mm)")
        return (f"; relative to {model!r}, an uncalibrated surrogate of "
                f"{surrogate_of(sur.get('against'))}, {pad} (the real robot differs from the "
                f"nominal model by an unknown amount" + calibrate)
    stated = f", plus the stated margin of {margin:g} mm" if margin > 0 else ""
    return (f"; relative to the nominal model{stated} (uncalibrated: the real robot differs "
            f"from it by an unknown amount" + calibrate)


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plan", help="plan a collision-free motion to a target point",
        description="Plan a collision-free motion of the robot from its retracted configuration "
                    "(or --start) to put the tip at a target point (mm, scene frame), and write "
                    "plan.json (success, status, path with continuous rotations, tip_path, "
                    "tip_error_mm, planning_time_s, min_clearance_mm and min_clearance_exact "
                    "under the planning model and the reference model, clearance_profile (per "
                    "path state), objective and objective_value, calibrated (whether the model "
                    "carries an error bound measured on a robot), surrogate_error (a surrogate's "
                    "error against the simulated model it imitates, e.g. the shipped learned "
                    "network's, or null), margin_mm, goal_shift_mm, start_rotated, planner = "
                    "what solved it ('direct' for the straight edge), seed, robot, model, scene, "
                    "time_cap_hit, timings, counts). The search budget is a count of validated "
                    "states, so a seed gives the same path on any machine load; --time is a cap. "
                    "SUCCESS means the tip ends within --tolerance of the target (a verified "
                    "path that ends farther, e.g. because the goal was moved off the anatomy "
                    "to keep the margin, is OUTSIDE_TOLERANCE, its path kept). "
                    "Exit code 0 on success, 1 when no plan was found (TIMEOUT, "
                    "OUTSIDE_TOLERANCE, ...), 2 for bad "
                    "input, an unreachable target or a target inside anatomy (plan.json is "
                    "still written for the latter two).")
    p.add_argument("--scene", required=True, help="shipped scene name or scene folder")
    p.add_argument("--target", required=True, nargs="+", metavar="X,Y,Z",
                   help="X,Y,Z or X Y Z in mm (scene frame; negative values welcome: "
                        "--target -5,20,0), or one of the scene's example targets by anatomical name "
                        "(carina, ...) or id (t01, ...): `ctrplan scene list`")
    p.add_argument("--start", default="retracted", nargs="+", metavar="retracted|A1,..,Bn|PLAN.json",
                   help="start configuration: 'retracted' (default; the tube rotations are "
                        "changed only if it collides), 2n values alpha1..alphaN (rad), "
                        "beta1..betaN (mm), comma- or space-separated, or an earlier plan.json "
                        "(its last path state and the branch it records there)")
    p.add_argument("--branch", default=None, metavar="-1|0|+1",
                   help="the equilibrium branch the robot is on at --start, as plan.json records "
                        "it; needed where the model finds two stable equilibria at the start "
                        "(a bistable start: the plan refuses to guess)")
    p.add_argument("--stability-margin", default=None, metavar="S",
                   help="smallest elastic stability of a planned state (det of the shooting "
                        "Jacobian relative to the tubes without their curvatures' interaction: "
                        "1 = as stiff in torsion as the bare tubes, 0 = a fold where the robot "
                        "snaps; default 0.1: the twist responds at most ~10x as strongly as the "
                        "bare tubes'); compliant physics models only")
    add_planning_args(p)
    p.add_argument("--seed", type=SEED, default=0, help="random seed (default 0)")
    p.add_argument("--out", default=DEFAULT_OUT["plan"], help=f"output plan .json (default {DEFAULT_OUT['plan']})")
    p.add_argument("--trajectory", default=None, metavar="TRAJECTORY.csv",
                   help="also write the time-parameterised trajectory along the path: "
                        "t,alpha1..alphaN,beta1..betaN (s, rad, mm) at --rate, within the robot's "
                        "actuator limits (robot YAML 'actuators'), stopping at every corner of "
                        "the path; plan.json gives its duration_s either way")
    p.add_argument("--rate", default=None, metavar="HZ",
                   help="trajectory sampling rate, Hz (default 100)")
    add_tip_goal_args(p)
    allow_negative_values(p)
    p.set_defaults(func=run)


def _numbers(tokens, field: str, count: int | None = None) -> list[float] | None:
    """Comma- and/or space-separated numbers (None if any token is not a number)."""
    parts = [s.strip() for tok in ([tokens] if isinstance(tokens, str) else tokens)
             for s in str(tok).split(",") if s.strip()]
    try:
        vals = [strict_float(s) for s in parts]
    except ValueError:
        return None
    if count is not None and len(vals) != count:
        return None
    if not all(math.isfinite(v) for v in vals):
        raise InputError(field, "", f"must be finite numbers, got {excerpt(' '.join(map(str, tokens)))}")
    return vals


def parse_start(tokens, robot, branch=None) -> object:
    """``--start`` (and ``--branch``): 'retracted', 2n numbers or a plan.json ->
    "retracted" or a :class:`~ctrplan.planning.stability.Start`."""
    import numpy as np

    from ctrplan.planning.stability import Start, check_branch, start_from_plan

    tokens = [tokens] if isinstance(tokens, str) else list(tokens)
    branch = check_branch(branch)
    if len(tokens) == 1 and tokens[0].strip().lower().endswith(".json"):
        start = start_from_plan(tokens[0].strip(), robot)
        return Start(start.q, start.branch if branch is None else branch)
    if len(tokens) == 1 and tokens[0].strip().lower() == "retracted":
        if branch not in (None, 0):
            raise InputError("--branch", "", "applies to a given --start, not the retracted one")
        return "retracted"
    vals = _numbers(tokens, "--start")
    if vals is None or len(vals) != robot.dof:
        raise InputError("--start", "", f"must be 'retracted' or {robot.dof} numbers alpha1..alpha{robot.n} "
                         f"(rad), beta1..beta{robot.n} (mm), got {excerpt(' '.join(tokens))}")
    from ctrplan.robot import check_config_plausible

    check_config_plausible([vals], robot, "--start", row_offset=1, row_word="configuration")
    return Start(np.asarray(vals, dtype=float), branch)


def parse_stability_margin(text) -> float | None:
    """``--stability-margin``: a number >= 0 (None: the default)."""
    if text is None:
        return None
    try:
        v = strict_float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and v >= 0):
        raise InputError("--stability-margin", "", f"must be a number >= 0, got {excerpt(text)}")
    return v


def parse_target(text: str, scene) -> tuple[list[float], str]:
    """``X,Y,Z`` / ``X Y Z`` (mm) or a target name of the scene -> (position, name)."""
    tokens = [text] if isinstance(text, str) else list(text)
    text = " ".join(tokens)
    parts = [s.strip() for tok in tokens for s in str(tok).split(",") if s.strip()]
    if len(parts) == 3:
        try:
            xyz = [strict_float(s) for s in parts]
        except ValueError:
            raise InputError("--target", "", f"must be X,Y,Z in mm or a target name, got {excerpt(text)}") from None
        if not all(math.isfinite(v) for v in xyz):
            raise InputError("--target", "", f"must be finite numbers (mm), got {excerpt(text)}")
        return xyz, ""
    t = scene.find_target(text)
    if t is not None:
        return [float(v) for v in t.position], t.name
    raise InputError("--target", "", f"must be X,Y,Z in mm or a target name of scene {scene.name!r} "
                                     f"({scene.target_names()}), got {excerpt(text)}")


def add_tip_goal_args(p: argparse.ArgumentParser) -> None:
    """``--standoff``, ``--approach`` and ``--cone`` (a tip pose goal)."""
    p.add_argument("--standoff", default=None, metavar="MM",
                   help="stop the tip this far from the tissue, mm, along the surface normal: "
                        "--target is snapped to the nearest wall or obstacle point (the snap "
                        "distance is reported); default 0 (the tip's centre never comes nearer "
                        "than its radius + margin: a smaller standoff is planned there and "
                        "reported as goal_shift_mm)")
    p.add_argument("--approach", default=None, metavar="X,Y,Z|normal",
                   help="the direction the tip must point (scene frame; normalised): 'normal' = "
                        "into the tissue, against the snapped surface's normal; the tip tangent "
                        "must end within --cone of it")
    p.add_argument("--cone", default=None, metavar="DEG",
                   help=f"half-angle of the cone around --approach, degrees in (0, 90] "
                        f"(default {_default_cone():g})")


def _default_cone() -> float:
    from ctrplan.planning.tipgoal import DEFAULT_CONE_DEG

    return DEFAULT_CONE_DEG


def parse_tip_goal_args(standoff, approach, cone) -> tuple:
    """``--standoff`` (mm >= 0 or None), ``--approach`` ("normal", (3,) floats or None) and
    ``--cone`` (deg in (0, 90] or None), each checked (InputError naming the flag):
    :func:`ctrplan.planning.tipgoal.parse_goal_values` (plan-batch's targets CSV uses it too)."""
    from ctrplan.planning.tipgoal import parse_goal_values

    return parse_goal_values(standoff, approach, cone)


def tip_goal(target, scene, standoff, approach, cone) -> tuple:
    """The plan's goal from ``--target`` and the tip pose flags
    (:func:`ctrplan.planning.tipgoal.goal_for_target`, plan-batch's path too): the point when
    none is given, else a TipGoal (snapped to the tissue for --standoff / --approach normal).
    Returns (goal, plan.json's ``snap_distance_mm``, ``snap_mesh``, ``target_given``)."""
    from ctrplan.planning.tipgoal import goal_for_target

    return goal_for_target(target, scene, standoff, approach, cone)


def one_thread() -> None:
    """Planning makes many small model calls: torch's intra-op thread pool only adds latency
    (25x slower on a busy 2-core machine). Set before torch is first imported."""
    import os

    os.environ.setdefault("OMP_NUM_THREADS", "1")


def parse_rate(text) -> float:
    """``--rate``: a sampling rate in Hz (the default when None)."""
    from ctrplan.planning.trajectory import DEFAULT_RATE_HZ, RATE_RANGE, check_rate

    if text is None:
        return DEFAULT_RATE_HZ
    try:
        v = strict_float(text)
    except ValueError:
        v = math.nan
    if not math.isfinite(v):
        raise InputError("--rate", "", f"must be a sampling rate in [{RATE_RANGE[0]:g}, "
                                       f"{RATE_RANGE[1]:g}] Hz, got {excerpt(text)}")
    return check_rate(v, "--rate")


def add_trajectory(plan: dict, result, robot, rate: float, csv_path, plan_path) -> dict:
    """plan.json's ``duration_s`` and ``trajectory`` (rate, samples, time-optimal duration,
    stops, the CSV written, relative to plan.json's folder where it lies inside it, and its
    sha256) for a plan with a path; the CSV is written to ``csv_path`` (atomically) when given.
    A plan without a path gets ``duration_s`` null."""
    from ctrplan.planning.trajectory import file_sha256, plan_trajectory, trajectory_duration

    if not plan.get("path"):
        plan["duration_s"], plan["trajectory"] = None, None
        return plan
    if csv_path is None:          # the duration alone: no samples made (any length)
        duration, optimal = trajectory_duration(robot, result.path, rate)
        plan["duration_s"] = duration
        plan["trajectory"] = {"rate_hz": rate, "time_optimal_s": optimal, "file": None}
        return plan
    traj = plan_trajectory(result, rate, robot=robot)
    traj.write_csv(csv_path, robot)
    plan["duration_s"] = traj.duration_s
    where = Path(csv_path).resolve()
    try:
        name = str(where.relative_to(Path(plan_path).resolve().parent))
    except ValueError:
        name = str(where)
    plan["trajectory"] = {**traj.record(), "file": name, "sha256": file_sha256(csv_path)}
    return plan


def run(args: argparse.Namespace) -> int:
    one_thread()
    from ctrplan.collision.scene import load_scene
    from ctrplan.io import write_json_atomic
    from ctrplan.planning.planner import Planner, PlannerConfig
    from ctrplan.planning.result import PlanStatus
    from ctrplan.planning.space import check_planner
    from ctrplan.robot import load_robot

    out = output_path(args.out, (".json",))
    traj_out = (output_path(args.trajectory, (".csv",), "--trajectory")
                if args.trajectory is not None else None)
    rate = parse_rate(args.rate)
    pose = parse_tip_goal_args(args.standoff, args.approach, args.cone)
    device = device_arg(args.device)
    check_planner(args.planner)
    objective = parse_objective(args.objective)
    if args.seed < 0:
        raise InputError("--seed", "", f"must be >= 0, got {args.seed}")
    robot = load_robot(args.robot)
    scene = load_scene(args.scene)
    target, name = parse_target(args.target, scene)
    goal, snap = tip_goal(target, scene, *pose)
    start = parse_start(args.start, robot, args.branch)
    config = PlannerConfig(margin_mm=parse_margin(args.margin), objective=objective)
    stability = parse_stability_margin(args.stability_margin)
    if stability is not None:
        from dataclasses import replace

        config = replace(config, validator=replace(config.validator, stability_margin=stability))
    import contextlib

    # where a learned model evaluates (torch is imported only for another device than the CPU)
    if device == "cpu":
        where = contextlib.nullcontext()
    else:
        from ctrplan.shape.learned import using_device

        where = using_device(device)
    with where:
        planner = Planner(robot, scene, args.model, config)
        result = planner.plan(goal, seed=args.seed, start=start, planner=args.planner,
                              time_limit=args.time, tolerance_mm=args.tolerance)
    plan = result.to_json()
    plan.update(snap)
    plan["scene"] = args.scene
    plan["robot"] = str(args.robot)   # the name or path given; robot_spec holds the robot itself
    if name:  # the anatomical name where the scene has one; target_id is t01..
        t = scene.find_target(name)
        plan["target_name"], plan["target_id"] = (t.label or t.name), t.name
    add_trajectory(plan, result, robot, rate, traj_out, out)
    write_json_atomic(out, plan)
    log.info("planned in %.2f s (%d states) -> %s", result.planning_time_s, len(plan["path"]),
             out)
    print(summary_line(plan, str(args.model), str(args.robot)))
    if result.status in (PlanStatus.UNREACHABLE, PlanStatus.TARGET_IN_COLLISION):
        raise InputError("--target", "", f"{result.status.value}: {result.message} (wrote {out})")
    return 0 if result.success else 1
