"""``ctrplan shape``: backbones of configurations from a CSV."""

from __future__ import annotations

import argparse

import numpy as np

from ctrplan.commands._common import POINTS, add_model_arg, add_robot_arg, output_path
from ctrplan.errors import InputError


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("shape", help="compute backbones of configurations",
                       description="Compute the backbone of each configuration in a CSV. "
                                   "Writes NPZ (points (B,M,3) mm, s (B,M) mm, ok (B,)) or CSV "
                                   "(one row per configuration: ok, p1_x..pM_z).")
    add_robot_arg(p)
    p.add_argument("--configs", required=True, help="configuration CSV (alpha1..alphaN,beta1..betaN)")
    add_model_arg(p)
    p.add_argument("--points", type=POINTS, default=20, help="points per backbone, base to tip (default 20)")
    p.add_argument("--out", required=True, help="output .npz or .csv")
    p.set_defaults(func=run)


def directions_for(model, q: np.ndarray, path: str) -> np.ndarray | None:
    """The direction of the last motion of each joint for models that need it (from the row
    order of the CSV ``path``, within each ``sweep`` when it has that column); else None."""
    from ctrplan.shape.base import direction_from_rows, needs_direction

    if not needs_direction(model):
        return None
    from ctrplan.io import read_csv_table

    header, body = read_csv_table(path)
    sweep = None
    if "sweep" in header:
        ci = header.index("sweep")
        sweep = np.array([r[ci].strip() if ci < len(r) else "" for r in body], dtype=object)
    return direction_from_rows(q, sweep)


def shape_with_direction(model, q: np.ndarray, path: str, points: int):
    """``model.shape(q, points)``; models that need the direction of the last motion get it
    from the row order of the CSV (within each ``sweep`` when it has that column)."""
    d = directions_for(model, q, path)
    if d is None:
        return model.shape(q, points=points)
    return model.shape(q, points=points, direction=d)


def run(args: argparse.Namespace) -> int:
    from ctrplan.io import atomic_path, write_csv_atomic
    from ctrplan.robot import load_robot, read_configs
    from ctrplan.shape.models import load_model

    out = output_path(args.out, (".npz", ".csv"))
    if args.points < 2:
        raise InputError("--points", "", f"must be >= 2, got {args.points}")
    robot = load_robot(args.robot)
    q = read_configs(args.configs, robot)
    model = load_model(args.model, robot)
    shape = shape_with_direction(model, q, args.configs, args.points)
    if out.suffix.lower() == ".npz":
        with atomic_path(out) as tmp:
            with open(tmp, "wb") as fh:
                np.savez(fh, points=shape.points, s=shape.s, ok=shape.ok, radius=shape.radius)
    else:
        m = args.points
        header = ["ok"] + [f"p{k + 1}_{c}" for k in range(m) for c in "xyz"]
        rows = ([int(ok)] + pts.reshape(-1).tolist() for ok, pts in zip(shape.ok, shape.points))
        write_csv_atomic(out, header, rows)   # streamed row by row
    bad = int((~shape.ok).sum())
    import logging

    logging.getLogger("ctrplan").info(
        "wrote %d backbones (%d points each, model %s) to %s%s", len(q), args.points,
        model.name, out, f"; {bad} did not converge (ok=0)" if bad else "")
    return 0
