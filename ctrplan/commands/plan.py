"""``ctrplan plan``: plan a motion to a target point and write plan.json."""

from __future__ import annotations

import argparse
import logging
import math

from ctrplan.commands._common import add_model_arg, output_path
from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")


def add_planning_args(p: argparse.ArgumentParser) -> None:
    """Options shared by ``plan`` and ``plan-batch``."""
    p.add_argument("--robot", default="seed1",
                   help="shipped robot name (seed1, two_tube_nylon) or robot YAML path (default seed1)")
    add_model_arg(p, default="learned")
    p.add_argument("--planner", default="rrtconnect",
                   help="rrtconnect (default), rrt, rrtstar, bitstar, prm, prmstar, kpiece, bkpiece, lbkpiece")
    p.add_argument("--time", type=float, default=5.0, help="time limit per plan, s (default 5)")
    p.add_argument("--tolerance", type=float, default=1.0,
                   help="accepted tip-to-target distance, mm (default 1)")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plan", help="plan a collision-free motion to a target point",
        description="Plan a collision-free motion of the robot from its retracted configuration "
                    "to put the tip at a target point (mm, scene frame), and write plan.json "
                    "(success, status, path, tip_path, tip_error_mm, planning_time_s, "
                    "min_clearance_mm, planner, seed, robot, model, scene, timings, counts). "
                    "Exit code 0 on success, 1 when no plan was found (TIMEOUT, ...), 2 for bad "
                    "input, an unreachable target or a target inside anatomy (plan.json is "
                    "still written for the latter two).")
    p.add_argument("--scene", required=True, help="shipped scene name or scene folder")
    p.add_argument("--target", required=True,
                   help="X,Y,Z in mm (scene frame), or the name of one of the scene's example targets")
    add_planning_args(p)
    p.add_argument("--seed", type=int, default=0, help="random seed (default 0)")
    p.add_argument("--out", required=True, help="output plan .json")
    p.set_defaults(func=run)


def parse_target(text: str, scene) -> tuple[list[float], str]:
    """``X,Y,Z`` (mm) or a target name of the scene -> (position, name)."""
    parts = [s.strip() for s in str(text).split(",")]
    if len(parts) == 3:
        try:
            xyz = [float(s) for s in parts]
        except ValueError:
            raise InputError("--target", "", f"must be X,Y,Z in mm or a target name, got {text!r}") from None
        if not all(math.isfinite(v) for v in xyz):
            raise InputError("--target", "", f"must be finite numbers (mm), got {text!r}")
        return xyz, ""
    names = {t.name: t for t in scene.targets}
    if text in names:
        return [float(v) for v in names[text].position], text
    raise InputError("--target", "", f"must be X,Y,Z in mm or a target name of scene {scene.name!r} "
                                     f"({', '.join(names) or 'none'}), got {text!r}")


def one_thread() -> None:
    """Planning makes many small model calls: torch's intra-op thread pool only adds latency
    (25x slower on a busy 2-core machine). Set before torch is first imported."""
    import os

    os.environ.setdefault("OMP_NUM_THREADS", "1")


def run(args: argparse.Namespace) -> int:
    one_thread()
    from ctrplan.io import write_json_atomic
    from ctrplan.planning.plan import PlanStatus, plan_to_target, scene_by_name
    from ctrplan.planning.space import check_planner
    from ctrplan.robot import load_robot

    out = output_path(args.out, (".json",))
    check_planner(args.planner)
    if args.seed < 0:
        raise InputError("--seed", "", f"must be >= 0, got {args.seed}")
    robot = load_robot(args.robot)
    scene = scene_by_name(args.scene)
    target, name = parse_target(args.target, scene)
    result = plan_to_target(robot, scene, target, model=args.model, planner=args.planner,
                            time_limit=args.time, seed=args.seed, tolerance_mm=args.tolerance)
    plan = result.to_json()
    plan["scene"] = args.scene
    if name:
        plan["target_name"] = name
    write_json_atomic(out, plan)
    log.info("%s: %s in %.2f s (tip error %s mm, %d states) -> %s", result.status.value,
             result.message, result.planning_time_s,
             "n/a" if plan["tip_error_mm"] is None else f"{plan['tip_error_mm']:.3f}",
             len(plan["path"]), out)
    if result.status in (PlanStatus.UNREACHABLE, PlanStatus.TARGET_IN_COLLISION):
        raise InputError("--target", "", f"{result.status.value}: {result.message} (wrote {out})")
    return 0 if result.success else 1
