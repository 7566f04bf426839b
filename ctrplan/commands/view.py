"""``ctrplan view``: render a plan (from ``ctrplan plan``) as an interactive HTML or a PNG."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from ctrplan.commands._common import POINTS, output_path
from ctrplan.commands._vocab import DEFAULT_OUT
from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")

#: Largest plan.json read (bytes); a plan of 10,000 states is about 2 MB.
MAX_PLAN_BYTES = 64 << 20
#: States per shape call when a plan's tip path is recomputed.
TIP_CHUNK = 10_000


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", help="render a plan.json as interactive HTML or PNG",
                       description="Render the anatomy, the robot along the path, the tip path and "
                                   "the target of a plan written by 'ctrplan plan'. HTML output is "
                                   "self-contained (works offline).")
    p.add_argument("plan", help="plan.json written by 'ctrplan plan'")
    p.add_argument("--out", default=DEFAULT_OUT["view"], help=f"output .html or .png (default {DEFAULT_OUT['view']})")
    p.add_argument("--points", type=POINTS, default=40, help="points per drawn backbone (default 40)")
    p.add_argument("--trajectory", default=None, metavar="TRAJECTORY.csv",
                   help="animate the robot along this trajectory (from 'plan --trajectory'); by "
                        "default the one the plan recorded (plan.json 'trajectory') or "
                        "trajectory.csv beside plan.json, when it is the file the plan wrote "
                        "(same sha256); HTML only")
    p.set_defaults(func=run)


def read_plan(path: str | Path) -> dict:
    """Read and check a plan.json (fields in docs/conventions.md)."""
    from ctrplan.robot import check_regular_file

    path = check_regular_file(path, (".json",), "a plan.json", max_bytes=MAX_PLAN_BYTES)
    try:
        plan = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(str(path), "", "file not found") from None
    except (OSError, UnicodeDecodeError, ValueError, RecursionError) as exc:
        raise InputError(str(path), "", f"not a readable JSON file ({exc.__class__.__name__})") from None
    if not isinstance(plan, dict):
        raise InputError(str(path), "", "expected a JSON object")
    for key in ("scene", "robot", "model", "path"):
        if key not in plan:
            raise InputError(str(path), key, "missing")
    try:
        q = np.asarray(plan["path"], dtype=float)
    except (TypeError, ValueError, OverflowError):
        raise InputError(str(path), "path", "must be a list of configurations") from None
    if q.ndim != 2 or len(q) == 0 or not np.all(np.isfinite(q)):
        raise InputError(str(path), "path", "must be a non-empty list of finite configurations")
    plan["_q"] = q
    for key, width in (("target", None), ("tip_path", 3)):
        v = plan.get(key)
        if v is None:
            continue
        try:
            a = np.asarray(v, dtype=float)
        except (TypeError, ValueError, OverflowError):
            a = np.zeros((0, 0))
        good = a.shape == (3,) if width is None else (a.ndim == 2 and a.shape[1:] == (3,) and len(a))
        if not good or not np.all(np.isfinite(a)):
            raise InputError(str(path), key, "must be X, Y, Z (mm)" if width is None else
                             "must be a non-empty list of finite X, Y, Z points (mm)")
    return plan


def plan_robot(plan: dict, source: str):
    """The robot that made the plan: its recorded ``robot_spec`` (checked against
    ``robot_sha256``); for a plan without one (written before robots were recorded), the shipped
    robot of that name or a robot YAML (a regular ``.yaml`` file; anything else is refused)."""
    from ctrplan.robot import SHIPPED_ROBOTS, load_robot, robot_from_record

    robot = robot_from_record(plan, source)
    if robot is not None:
        return robot
    name = plan["robot"]
    if not isinstance(name, str) or not name:
        raise InputError(source, "robot", "must be a robot name or robot YAML path")
    try:
        robot = load_robot(name)
    except InputError as exc:
        raise InputError(source, "robot", str(exc)) from None
    if name not in SHIPPED_ROBOTS:
        log.warning("%s has no robot_spec: drawing the robot file %s as it is now, which may "
                    "differ from the robot that planned", source, name)
    return robot


def check_scene_field(spec, source: str) -> str:
    """A plan's ``scene``: a shipped scene name or a scene folder (its scene.yaml), nothing else."""
    from ctrplan.collision.scene import anatomy_dir

    if not isinstance(spec, str) or not spec:
        raise InputError(source, "scene", "must be a scene name or folder")
    p = Path(spec)
    if p.is_dir() and (p / "scene.yaml").is_file():
        return spec
    if p.name in ("scene.yaml", "scene.yml") and p.is_file():
        return spec
    if "/" not in spec and "\\" not in spec and (anatomy_dir() / spec / "scene.yaml").is_file():
        return spec
    raise InputError(source, "scene", f"{spec[:80]!r} is not a shipped scene or a scene folder")


def check_model_field(spec, source: str) -> str:
    """A plan's ``model``: a model name or a model file (checked by the model loader)."""
    from ctrplan.shape.models import MODEL_NAMES

    if not isinstance(spec, str) or not spec:
        raise InputError(source, "model", "must be a model name or a model file path")
    if spec in MODEL_NAMES:
        return spec
    from ctrplan.shape.models import check_model_file

    try:
        check_model_file(spec)
    except InputError as exc:
        raise InputError(source, "model", str(exc)) from None
    return spec


def _number(v) -> float | None:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and \
        np.isfinite(v) else None


def plan_notes(plan: dict) -> str:
    """The labels a view's title carries: a tip beyond the tolerance, a goal moved off the
    anatomy (``goal_shift_mm``), a tip pose goal's direction error and standoff, and what the planning model's margin is (a calibrated model's
    measured bound, or an uncalibrated surrogate's ``surrogate_error``)."""
    out = ""
    tip, tol = _number(plan.get("tip_error_mm")), _number(plan.get("tolerance_mm"))
    if plan.get("status") != "SUCCESS" and tip is not None and tol is not None:
        out += f" (tip {tip:.2f} mm from the target, tolerance {tol:g} mm)"
    shift = _number(plan.get("goal_shift_mm"))
    if shift:
        out += f"; goal moved {shift:.2f} mm off the anatomy"
    err, cone = _number(plan.get("direction_error_deg")), _number(plan.get("cone_deg"))
    if err is not None and cone is not None:
        out += f"; tip {err:.1f} deg from the approach (cone {cone:g} deg)"
    standoff = _number(plan.get("standoff_mm"))
    if standoff is not None:
        out += f", standoff {standoff:.2f} mm"
    margin = _number(plan.get("margin_mm")) or 0.0
    if plan.get("calibrated") is True:
        out += f"; calibrated model, margin {margin:.2f} mm"
    elif isinstance(plan.get("surrogate_error"), dict):
        out += (f"; uncalibrated surrogate, margin {margin:.2f} mm"
                + (" (its surrogate error)" if plan.get("margin_auto") is True else ""))
    return out


#: the keys of plan.json's ``tip_goal`` (``TipGoal.record()``)
TIP_GOAL_KEYS = ("position", "direction", "cone_deg", "standoff_mm", "normal")


def plan_goal(plan: dict, source: str):
    """A plan's tip pose goal to draw (:class:`~ctrplan.viz.GoalView`: the surface target, the
    standoff point, the approach direction and the cone) from its ``tip_goal`` record, checked
    as a TipGoal checks its fields (InputError naming the file and ``tip_goal``); None for a
    plan to a point (``tip_goal`` absent or null)."""
    from ctrplan import viz
    from ctrplan.planning.tipgoal import TipGoal

    record = plan.get("tip_goal")
    if record is None:
        return None
    if not isinstance(record, dict) or not set(record) <= set(TIP_GOAL_KEYS) \
            or "position" not in record:
        raise InputError(source, "tip_goal", f"must be an object with position and optionally "
                                             f"{', '.join(TIP_GOAL_KEYS[1:])}")
    try:
        goal = TipGoal(**{k: v for k, v in record.items() if v is not None or k == "position"})
    except InputError as exc:      # (ArgumentError: the record's own field names)
        raise InputError(source, f"tip_goal.{exc.source}", exc.message) from None
    return viz.GoalView(surface=np.asarray(goal.position), point=goal.point(),
                        direction=None if goal.direction is None else np.asarray(goal.direction),
                        cone_deg=goal.cone_deg)


def find_trajectory(plan: dict, source: str, given: str | None) -> Path | None:
    """The trajectory CSV to animate: ``given`` (``--trajectory``), else the file the plan
    recorded (``trajectory.file``, relative to plan.json's folder) or ``trajectory.csv``
    beside plan.json when its sha256 is the recorded one (a warning and no animation when it
    is not: a stale file of another plan). None when there is none."""
    if given is not None:
        return Path(given)
    record = plan.get("trajectory")
    if not isinstance(record, dict):
        return None
    folder = Path(source).parent
    name = record.get("file")
    names = ([name] if isinstance(name, str) and name else []) + ["trajectory.csv"]
    from ctrplan.planning.trajectory import file_sha256

    for cand in dict.fromkeys(folder / n for n in names):
        try:
            if not cand.is_file():
                continue
            same = file_sha256(cand) == record.get("sha256")
        except (OSError, ValueError):     # a name the file system refuses (too long, NUL)
            continue
        if same:
            return cand
        log.warning("%s is not the trajectory %s wrote (sha256 differs): not animated",
                    cand, source)
        return None
    return None


def trajectory_frames(path: Path, plan: dict, robot, source: str):
    """``(t (F,), q (F, 2n))``: :data:`~ctrplan.viz.ANIMATION_FRAMES` samples of a trajectory
    CSV, checked; it must start and end at the plan's first and last path states."""
    from ctrplan import viz
    from ctrplan.planning.trajectory import read_trajectory

    t, q, _ = read_trajectory(path, robot, viz.ANIMATION_FRAMES)
    q_plan = plan["_q"]
    for row, want, what in ((0, q_plan[0], "start"), (-1, q_plan[-1], "end")):
        if not np.allclose(q[row], want, rtol=0.0, atol=1e-6):
            raise InputError(str(path), "", f"does not {what} at the {what} of the plan's path "
                                            f"in {source}: a trajectory of another plan?")
    return t, q


def render_plan(plan: dict, out: Path, points: int = 40, source: str = "plan",
                trajectory: str | None = None) -> None:
    """Recompute the backbones of a plan's path with its model and render them."""
    from ctrplan import viz
    from ctrplan.collision.scene import load_scene
    from ctrplan.robot import check_config_plausible
    from ctrplan.shape.models import load_model

    robot = plan_robot(plan, source)
    q = plan["_q"]
    if q.shape[1] != robot.dof:
        raise InputError(source, "path", f"configurations have {q.shape[1]} values, robot needs {robot.dof}")
    check_config_plausible(q, robot, source, row_offset=0, row_word="path state")
    html = out.suffix.lower() == ".html"
    if trajectory is not None and not html:
        log.warning("--trajectory is animated in an HTML view only: %s is a PNG", out)
    traj = find_trajectory(plan, source, trajectory) if html else None
    frames = trajectory_frames(traj, plan, robot, source) if traj is not None else None
    scene = load_scene(check_scene_field(plan["scene"], source))
    model = load_model(check_model_field(plan["model"], source), robot)
    # Only the drawn states get whole backbones (a plan may have 100,000 states; --points
    # 1000 of each would take gigabytes); the tip path, when the plan lacks it, is computed in
    # chunks with two points per state.
    drawn = viz.pick_frames(len(q), viz.HTML_FRAMES if html else viz.PNG_FRAMES)
    backbones = scene.to_scene(model.backbone(q[drawn], points=points))
    tip_path = plan.get("tip_path")
    if tip_path is None:
        tip_path = np.concatenate([scene.to_scene(model.shape(q[k:k + TIP_CHUNK], points=2).tip)
                                   for k in range(0, len(q), TIP_CHUNK)])
    tip_path = np.asarray(tip_path, dtype=float)
    target = plan.get("target")
    target = np.asarray(target, dtype=float) if target is not None else None
    status = plan.get("status", "")
    title = f"{robot.name} in {scene.name}: {status}".strip().rstrip(":") + plan_notes(plan)
    meshes = viz.scene_meshes(scene)
    goal = plan_goal(plan, source)
    anim = None
    if frames is not None:           # backbones of the animation's frames only
        shape = model.shape(frames[1], points=points)
        anim = viz.Animation(t=frames[0], backbones=scene.to_scene(shape.points),
                             tips=scene.to_scene(shape.tip))
        title += f"; trajectory {anim.duration_s:.2f} s"
    if html:
        viz.plan_html(out, meshes, backbones, tip_path, target, title=title, frames=len(drawn),
                      animation=anim, goal=goal)
    else:
        viz.plan_png(out, meshes, backbones, tip_path, target, title=title, frames=len(drawn),
                     goal=goal)


def run(args: argparse.Namespace) -> int:
    out = output_path(args.out, (".html", ".png"))
    if args.points < 2:
        raise InputError("--points", "", f"must be >= 2 (base and tip), got {args.points}")
    plan = read_plan(args.plan)
    render_plan(plan, out, args.points, source=args.plan, trajectory=args.trajectory)
    log.info("wrote %s", out)
    return 0
