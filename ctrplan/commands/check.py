"""``ctrplan check``: collision verdicts of configurations in a scene."""

from __future__ import annotations

import argparse
import logging

from ctrplan.commands._common import add_model_arg, add_robot_arg, output_path
from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("check", help="collision-check configurations in a scene",
                       description="Compute each configuration's backbone, sweep it into capsules "
                                   "and check it against the scene's wall and obstacle meshes. "
                                   "Writes a CSV with collides (0/1), clearance_mm (signed, "
                                   "conservative: negative = penetration depth where known) and "
                                   "contact (mesh name, 'model' if the shape model failed, or empty).")
    p.add_argument("--scene", required=True, help="shipped scene name or scene folder")
    add_robot_arg(p)
    p.add_argument("--configs", required=True, help="configuration CSV (alpha1..alphaN,beta1..betaN)")
    add_model_arg(p)
    p.add_argument("--points", type=int, default=21, help="backbone points (capsules + 1, default 21)")
    p.add_argument("--margin", type=float, default=0.0, help="safety margin added to the tube radii, mm")
    p.add_argument("--exact", action="store_true", help="every verdict from FCL (no prefilter)")
    p.add_argument("--out", required=True, help="output verdicts .csv")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ctrplan.collision.world import CollisionWorld
    from ctrplan.io import write_csv_atomic
    from ctrplan.progress import bar
    from ctrplan.robot import load_robot, read_configs
    from ctrplan.shape.models import load_model

    out = output_path(args.out, (".csv",))
    if args.points < 2:
        raise InputError("--points", "", f"must be >= 2, got {args.points}")
    if not args.margin >= 0:
        raise InputError("--margin", "", f"must be >= 0, got {args.margin}")
    robot = load_robot(args.robot)
    q = read_configs(args.configs, robot)
    model = load_model(args.model, robot)
    world = CollisionWorld(args.scene, margin_mm=args.margin)
    from ctrplan.commands.shape import directions_for

    world.fields  # noqa: B018 (prepare the distance fields first: progress shown per mesh)
    # in chunks: a progress bar on a terminal, Ctrl-C between chunks, bounded memory
    chunk = 20_000
    collides = np.zeros(len(q), dtype=bool)
    clearance = np.zeros(len(q))
    contact = np.empty(len(q), dtype=object)
    fcl_calls = 0
    direction = directions_for(model, q, args.configs)
    with bar(total=len(q), desc="check", unit="config") as pbar:
        for k in range(0, len(q), chunk):
            if direction is None:
                shape = model.shape(q[k:k + chunk], points=args.points)
            else:
                shape = model.shape(q[k:k + chunk], points=args.points,
                                    direction=direction[k:k + chunk])
            report = world.check_exact(shape) if args.exact else world.check(shape)
            collides[k:k + chunk] = report.collides
            clearance[k:k + chunk] = report.clearance_mm
            contact[k:k + chunk] = report.contact
            fcl_calls += report.fcl_calls
            pbar.update(len(shape.ok))
    rows = ([int(c), round(float(d), 4), str(n)] for c, d, n in zip(collides, clearance, contact))
    write_csv_atomic(out, ["collides", "clearance_mm", "contact"], rows)
    log.info("checked %d configurations in %s: %d collide (%d sent to FCL); wrote %s",
             len(q), world.scene.name, int(collides.sum()), fcl_calls, out)
    return 0
