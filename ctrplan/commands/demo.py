"""``ctrplan demo``: the main job on the shipped defaults.

Plans the ``seed1`` robot with the physics model to a shipped target in a shipped scene, prints
a short summary, and writes ``plan.json``, ``demo.png`` and a self-contained ``demo.html``.
"""

from __future__ import annotations

import argparse
import logging
import time
from pathlib import Path

from ctrplan.commands._common import POSITIVE, SEED
from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")

DEFAULT_SCENE = "airway"
DEFAULT_ROBOT = "seed1"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("demo", help="plan on the shipped defaults and write a figure and an HTML view",
                       description="Plan the seed1 robot (physics model) to a shipped target in a "
                                   "shipped scene; print a summary; write plan.json, demo.png and "
                                   "demo.html (interactive, works offline) to --out.")
    p.add_argument("--scene", default=DEFAULT_SCENE, help=f"shipped scene or folder (default {DEFAULT_SCENE})")
    p.add_argument("--robot", default=DEFAULT_ROBOT, help=f"robot (default {DEFAULT_ROBOT})")
    p.add_argument("--target", default=None, help="target in the scene: anatomical name or id t01.. (default: the first one)")
    p.add_argument("--model", default="physics", help="shape model (default physics: margin 0; 'learned', an uncalibrated surrogate of the physics model, plans with its surrogate error as margin)")
    p.add_argument("--time", type=POSITIVE, default=5.0, help="planning time limit, s (default 5)")
    p.add_argument("--seed", type=SEED, default=0)
    p.add_argument("--out", default="demo_out", help="output folder (default demo_out)")
    p.set_defaults(func=run)


def _mm(v) -> str:
    return "n/a" if v is None else f"{v:.3f} mm"


def run(args: argparse.Namespace) -> int:
    from ctrplan.commands.plan import one_thread, summary_line
    from ctrplan.shape.physics import compile_in_background

    one_thread()
    compile_in_background()   # a fresh install compiles the mechanics kernel meanwhile
    from ctrplan.collision.scene import load_scene
    from ctrplan.commands.view import render_plan
    from ctrplan.io import write_json_atomic
    from ctrplan.planning.plan import plan_to_target
    from ctrplan.robot import load_robot

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError("--out", "", f"{args.out!r} exists and is not a folder")
    t0 = time.perf_counter()
    robot = load_robot(args.robot)
    scene = load_scene(args.scene)
    if not scene.targets:
        raise InputError(str(args.scene), "targets", "the scene has no example targets")
    if args.target is None:
        target = scene.targets[0]
    else:
        target = scene.find_target(args.target)
        if target is None:
            raise InputError("--target", "", f"no target {args.target!r} in scene {scene.name!r} "
                                             f"(have: {scene.target_names()})")
    result = plan_to_target(robot, scene, target.position, model=args.model,
                            time_limit=args.time, seed=args.seed)
    plan = result.to_json()
    plan["target"] = [float(v) for v in target.position]
    plan["target_name"], plan["target_id"] = (target.label or target.name), target.name
    out.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out / "plan.json", plan)
    files = [out / "plan.json"]
    if len(plan.get("path") or []):
        import numpy as np

        plan["_q"] = np.asarray(plan["path"], dtype=float)
        render_plan(plan, out / "demo.png")
        render_plan(plan, out / "demo.html")
        files += [out / "demo.png", out / "demo.html"]
    print(f"ctrplan demo: robot {robot.name}, scene {scene.name}, target {target.display} "
          f"{tuple(round(float(v), 1) for v in target.position)} mm, model {plan.get('model')}")
    print(f"  status {plan['status']}  success {plan['success']}  planning time "
          f"{plan['planning_time_s']:.2f} s  tip error {_mm(plan['tip_error_mm'])}  "
          f"min clearance {_mm(plan['min_clearance_mm'])}  path {len(plan['path'] or [])} states")
    print("  " + summary_line(plan, str(args.model), str(args.robot)))
    print("  wrote " + ", ".join(str(f) for f in files) + f"  ({time.perf_counter() - t0:.1f} s total)")
    return 0 if plan["success"] else 1
