"""``ctrplan check``: collision verdicts of configurations in a scene."""

from __future__ import annotations

import argparse
import itertools
import logging

from ctrplan.commands._common import (
    POINTS,
    add_device_arg,
    add_model_arg,
    add_robot_arg,
    device_arg,
    output_path,
)
from ctrplan.commands._vocab import DEFAULT_OUT
from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")

#: Configurations per chunk: memory is bounded by one chunk whatever the file's size.
CHUNK = 20_000


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("check", help="collision-check configurations in a scene",
                       description="Compute each configuration's backbone, sweep it into capsules "
                                   "and check it against the scene's wall and obstacle meshes. "
                                   "Capsules are padded by the model's bound of the distance "
                                   "between its continuous backbone and the chords (sagitta, "
                                   "kinks where tubes end, the learned polynomial's bound) and "
                                   "by --margin; a calibrated model is checked without its "
                                   "sensor registration, friction as a pure function of each row. "
                                   "Writes a CSV with collides (0/1), clearance_mm (signed, "
                                   "conservative: negative = penetration depth where known) and "
                                   "contact (mesh name, 'model' if the shape model failed, or empty).")
    p.add_argument("--scene", required=True, help="shipped scene name or scene folder")
    add_robot_arg(p)
    p.add_argument("--configs", required=True, help="configuration CSV (alpha1..alphaN,beta1..betaN)")
    add_model_arg(p)
    add_device_arg(p)
    p.add_argument("--points", type=POINTS, default=21, help="backbone points (capsules + 1, default 21)")
    p.add_argument("--margin", default="auto", metavar="MM|auto",
                   help="safety margin added to the tube radii, mm; 'auto' (default) = the "
                        "model's error bound: the p99 of its held-out deviation at each "
                        "capsule's arc length (error_profile), else the uniform p99 of its "
                        "error_quantiles (the surrogate error for the shipped learned model, "
                        "an uncalibrated surrogate of the physics model); 0 for a model without "
                        "a bound")
    p.add_argument("--exact", action="store_true", help="every verdict from FCL (no prefilter)")
    p.add_argument("--out", default=DEFAULT_OUT["check"], help=f"output verdicts .csv (default {DEFAULT_OUT['check']})")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    import numpy as np

    from ctrplan.collision.world import CollisionWorld
    from ctrplan.commands.plan import parse_margin
    from ctrplan.io import iter_configs, write_csv_atomic
    from ctrplan.planning.validator import BatchValidator
    from ctrplan.progress import bar
    from ctrplan.robot import load_robot
    from ctrplan.shape.error_bounds import MEASURED_SLACK_MM, margin_peak, outside_measured
    from ctrplan.shape.models import load_model
    from ctrplan.shape.planning_model import planning_model

    out = output_path(args.out, (".csv",))
    margin = parse_margin(args.margin)
    robot = load_robot(args.robot)
    # the file's header and first rows are checked before the scene is prepared
    configs = iter_configs(args.configs, robot, chunk_rows=CHUNK)
    first = next(configs)
    model = planning_model(load_model(args.model, robot, device=device_arg(args.device)))   # fit for collision checking
    auto = margin is None
    if auto:
        try:
            margin = model.auto_margin()
        except ValueError as exc:
            raise InputError("--margin", "", f"auto: {exc}") from None
    world = CollisionWorld(args.scene, margin_mm=margin, curvature_per_mm=model.curvature_bound)
    world.fields  # noqa: B018 (prepare the distance fields first: progress shown per mesh)
    # Rows are independent configurations: a direction-aware model gets both directions
    # (worst case), so every verdict is a pure function of its row.
    validator = BatchValidator(robot, model, world)
    # streamed in chunks: bounded memory whatever the file's size, a progress bar on a
    # terminal, Ctrl-C between chunks; the output is written atomically at the end
    counts = [0, 0, 0]
    measured = model.measured_insertion

    def rows():
        with bar(total=None, desc="check", unit="config") as pbar:
            for q, _ in itertools.chain([first], configs):
                c, d, n = validator.check_states(q, points=args.points, exact=args.exact, joints=False)
                counts[0] += len(c)
                counts[1] += int(np.sum(c))
                if measured is not None:
                    counts[2] += outside_measured(q, measured, robot.n)
                pbar.update(len(c))
                yield from ([int(ci), round(float(di), 4), str(ni)] for ci, di, ni in zip(c, d, n))

    write_csv_atomic(out, ["collides", "clearance_mm", "contact"], rows())
    log.info("checked %d configurations in %s (margin %s, curvature bound %.4g 1/mm): "
             "%d collide; wrote %s", counts[0], world.scene.name,
             (f"up to {margin_peak(margin):.3g} mm along the shaft" if world.margin_profile is not None
              else f"{margin_peak(margin):.3g} mm"), world.curvature_per_mm, counts[1], out)
    if counts[2]:
        log.warning("%d of %d configurations insert a tube beyond the insertions the model's "
                    "error bound was measured on (more than %g mm): the model and its bound are "
                    "extrapolated there", counts[2], counts[0], MEASURED_SLACK_MM)
    kind = model.error_bound
    if auto and kind == "surrogate":
        log.info("the margin is the model's surrogate error (its deviation from the simulated "
                 "model it imitates), not a bound measured on the robot: verdicts are relative "
                 "to the nominal model (uncalibrated); calibrate with `ctrplan diagnose`")
    elif auto and kind is None:
        log.info("the model carries no error bound (uncalibrated): verdicts are relative to the "
                 "nominal model; calibrate with `ctrplan diagnose` for a margin")
    return 0
