"""``ctrplan view``: render a plan (from ``ctrplan plan``) as an interactive HTML or a PNG."""

from __future__ import annotations

import argparse
import json
import logging
from pathlib import Path

import numpy as np

from ctrplan.commands._common import POINTS, output_path
from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("view", help="render a plan.json as interactive HTML or PNG",
                       description="Render the anatomy, the robot along the path, the tip path and "
                                   "the target of a plan written by 'ctrplan plan'. HTML output is "
                                   "self-contained (works offline).")
    p.add_argument("plan", help="plan.json written by 'ctrplan plan'")
    p.add_argument("--out", required=True, help="output .html or .png")
    p.add_argument("--points", type=POINTS, default=40, help="points per drawn backbone (default 40)")
    p.set_defaults(func=run)


def read_plan(path: str | Path) -> dict:
    """Read and check a plan.json (fields in docs/conventions.md)."""
    path = Path(path)
    try:
        plan = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError(str(path), "", "file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(str(path), "", f"not a readable JSON file ({exc.__class__.__name__})") from None
    if not isinstance(plan, dict):
        raise InputError(str(path), "", "expected a JSON object")
    for key in ("scene", "robot", "model", "path"):
        if key not in plan:
            raise InputError(str(path), key, "missing")
    try:
        q = np.asarray(plan["path"], dtype=float)
    except (TypeError, ValueError):
        raise InputError(str(path), "path", "must be a list of configurations") from None
    if q.ndim != 2 or len(q) == 0 or not np.all(np.isfinite(q)):
        raise InputError(str(path), "path", "must be a non-empty list of finite configurations")
    plan["_q"] = q
    return plan


def render_plan(plan: dict, out: Path, points: int = 40, source: str = "plan") -> None:
    """Recompute the backbones of a plan's path with its model and render them."""
    from ctrplan import viz
    from ctrplan.collision.scene import load_scene
    from ctrplan.robot import load_robot
    from ctrplan.shape.models import load_model

    robot = load_robot(plan["robot"])
    q = plan["_q"]
    if q.shape[1] != robot.dof:
        raise InputError(source, "path", f"configurations have {q.shape[1]} values, robot needs {robot.dof}")
    scene = load_scene(plan["scene"])
    model = load_model(plan["model"], robot)
    backbones = scene.to_scene(model.backbone(q, points=points))
    tip_path = np.asarray(plan.get("tip_path") or backbones[:, -1], dtype=float)
    target = plan.get("target")
    target = np.asarray(target, dtype=float) if target is not None else None
    status = plan.get("status", "")
    title = f"{robot.name} in {scene.name}: {status}".strip().rstrip(":")
    meshes = viz.scene_meshes(scene)
    if out.suffix.lower() == ".html":
        viz.plan_html(out, meshes, backbones, tip_path, target, title=title)
    else:
        viz.plan_png(out, meshes, backbones, tip_path, target, title=title)


def run(args: argparse.Namespace) -> int:
    out = output_path(args.out, (".html", ".png"))
    if args.points < 2:
        raise InputError("--points", "", f"must be >= 2 (base and tip), got {args.points}")
    plan = read_plan(args.plan)
    render_plan(plan, out, args.points, source=args.plan)
    log.info("wrote %s", out)
    return 0
