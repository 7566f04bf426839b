"""``ctrplan plan-batch``: plan to many targets in many scenes (resumable; pool or Ray)."""

from __future__ import annotations

import argparse
import logging

from ctrplan.commands._common import WORKERS, int_arg
from ctrplan.commands._vocab import DEFAULT_OUT
from ctrplan.commands.plan import add_planning_args, one_thread
from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "plan-batch", help="plan to many targets over many scenes (resumable, process pool or Ray)",
        description="Plan every target (x 'seeds') of a CSV (columns x,y,z in mm, scene frame, and "
                    "optionally scene,name; and a tip pose goal per row: standoff_mm, approach "
                    "('normal' or a direction 'X Y Z') and cone_deg, as plan's --standoff, "
                    "--approach and --cone) or, with '--targets examples', every example target of "
                    "the shipped scenes. Writes OUT/jobs/<id>.json per job, OUT/jobs.csv and "
                    "OUT/summary.csv (success rate and planning-time median/p90 per scene). Jobs "
                    "whose JSON exists are skipped, so an interrupted batch resumes. Runs in a "
                    "local process pool (--workers) or on Ray (--ray ADDRESS, 'local' starts a "
                    "local instance).")
    p.add_argument("--targets", required=True, help="targets CSV, or 'examples'")
    p.add_argument("--scene", nargs="+", default=[], metavar="S",
                   help="scenes: restrict the targets to these, or the scene(s) of a CSV without "
                        "a scene column")
    add_planning_args(p)
    p.add_argument("--seeds", type=int_arg(1, 100_000), default=1, help="seeds per target: 0..K-1 (default 1)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=WORKERS, default=1, help="local worker processes (default 1)")
    where.add_argument("--ray", default=None, metavar="ADDRESS",
                       help="run on a Ray cluster at ADDRESS ('local' starts one here)")
    p.add_argument("--out", default=DEFAULT_OUT["plan-batch"], help=f"output folder (default {DEFAULT_OUT['plan-batch']})")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    one_thread()
    from pathlib import Path

    from ctrplan.planning.batch import make_jobs, read_targets, run_batch
    from ctrplan.planning.space import check_planner
    from ctrplan.robot import load_robot
    from ctrplan.shape.models import MODEL_NAMES

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError("--out", "", f"{args.out!r} exists and is not a folder")
    if args.seeds < 1:
        raise InputError("--seeds", "", f"must be >= 1, got {args.seeds}")
    if args.workers < 1:
        raise InputError("--workers", "", f"must be >= 1, got {args.workers}")
    if not args.time > 0:
        raise InputError("--time", "", f"must be > 0 s, got {args.time}")
    if not args.tolerance > 0:
        raise InputError("--tolerance", "", f"must be > 0 mm, got {args.tolerance}")
    planner = check_planner(args.planner)
    load_robot(args.robot)
    if args.model not in MODEL_NAMES and not Path(args.model).exists():
        raise InputError("--model", "", f"{args.model!r} is not a model name "
                                        f"({', '.join(MODEL_NAMES)}) or an existing file")
    from ctrplan.commands.plan import parse_margin, parse_objective

    margin = parse_margin(args.margin)
    objective = parse_objective(args.objective)
    targets = read_targets(args.targets, args.scene)
    jobs = make_jobs(targets, seeds=range(args.seeds), robot=args.robot,
                     model=args.model, planner=planner, time_limit=float(args.time),
                     tolerance_mm=float(args.tolerance),
                     margin="auto" if margin is None else repr(margin), objective=objective)
    summary = run_batch(jobs, out, workers=args.workers, ray_address=args.ray)
    for row in summary.rows:
        print(f"{row['scene']:>16}: {row['success']}/{row['jobs']} succeeded "
              f"({100 * row['success_rate']:.0f}%), planning time median {row['time_median_s']:.2f} s, "
              f"p90 {row['time_p90_s']:.2f} s  [{row['statuses']}]")
    print(f"wrote {summary.out / 'summary.csv'}, {summary.out / 'jobs.csv'} and "
          f"{summary.total} job files ({summary.skipped} were already done)")
    return 0
