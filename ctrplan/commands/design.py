"""``ctrplan design``: design a tube set for a scene and its targets."""

from __future__ import annotations

import argparse

from ctrplan.commands._common import NONNEGATIVE, POSITIVE, SEED, WORKERS, float_arg, int_arg
from ctrplan.commands._vocab import DEFAULT_OUT


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "design", help="design a tube set that reaches the targets of a scene",
        description="Read the anatomy first (the corridor from the entry to each target: widths, "
                    "bends, the room the retracted robot has at the entry) and derive the ranges to "
                    "search from it; then search tube curvatures, curved and straight lengths and "
                    "stock sizes (CMA-ES populations of 16 designs per generation) for the "
                    "design that reaches the most targets by a verified collision-free, elastically "
                    "stable plan from the scene's entry, then has the most clearance, then is the "
                    "simplest. Writes OUT/robot.yaml (loads in every command), OUT/design.json, "
                    "OUT/report.md, OUT/coverage.png and OUT/paths/<target>.json. The search "
                    "state goes to OUT/state.json after every generation: rerunning the same "
                    "command resumes. Evaluations run in this process, on a local process pool "
                    "(--workers K) or on Ray (--ray ADDRESS, 'local' starts a Ray instance here; "
                    "the same Ray path as plan-batch). Budgets are counts, so a seed gives the same "
                    "design on any load, number of workers or Ray; --time is a cap. Exit 0 when every target is "
                    "reached, 1 otherwise, 2 for bad input. For each target not reached the output "
                    "says what blocks it, where, and which single constraint to relax.")
    p.add_argument("--scene", required=True, help="shipped scene name (or design_bend) or scene folder")
    p.add_argument("--targets", required=True,
                   help="comma-separated names of the scene's targets, or a CSV (x,y,z[,name], mm, scene frame)")
    p.add_argument("--tubes", type=int_arg(1, 3), default=2, help="largest number of tubes, 1-3 (default 2)")
    p.add_argument("--from", dest="start_from", default=None, metavar="ROBOT",
                   help="keep this robot's tubes (outermost) and design tubes inside them")
    p.add_argument("--seed", type=SEED, default=0, help="random seed (default 0)")
    p.add_argument("--budget", type=int_arg(1, 10_000_000), default=400,
                   help="designs screened (default 400; at most 24 of them are planned in full)")
    p.add_argument("--generation", type=int_arg(2, 100_000), default=16,
                   help="designs per generation, screened in parallel (default 16; the same on any "
                        "number of workers)")
    p.add_argument("--time", type=POSITIVE, default=1200.0, help="wall-clock cap, s (default 1200)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=WORKERS, default=1, help="local worker processes (default 1)")
    where.add_argument("--ray", default=None, metavar="ADDRESS",
                       help="evaluate on a Ray cluster at ADDRESS ('local' starts one here with every "
                            "core); the same code path as plan-batch --ray, the same design as --workers 1. "
                            "Needs pip install 'ctrplan[ray]'")
    p.add_argument("--strain-limit", type=float_arg(0.0, 1.0, lo_open=True, hi_open=True), default=None,
                   help="recoverable strain of the tube material (default 0.06, nitinol)")
    p.add_argument("--min-gap", type=NONNEGATIVE, default=None, help="minimum radial gap between tubes, mm (default 0.05)")
    p.add_argument("--max-length", type=POSITIVE, default=None, help="longest tube, mm (default 400)")
    p.add_argument("--max-stroke", type=POSITIVE, default=None, help="longest translation stroke, mm (default 250)")
    p.add_argument("--curvature", default=None, metavar="MIN,MAX", help="curvature bounds, 1/mm (default 0,0.08)")
    p.add_argument("--curved-length", default=None, metavar="MIN,MAX", help="curved length bounds, mm (default 5,150)")
    p.add_argument("--straight-length", default=None, metavar="MIN,MAX",
                   help="straight length bounds, mm (default 10,300)")
    p.add_argument("--no-derive", dest="derive", action="store_false",
                   help="search the bounds as given instead of the ranges derived from the anatomy "
                        "(corridor widths, bends and the room at the entry)")
    p.add_argument("--stock", default=None, help="CSV of stock tube sizes (od_mm,id_mm); default the shipped table")
    p.add_argument("--out", default=DEFAULT_OUT["design"], help=f"output folder (default {DEFAULT_OUT['design']})")
    p.set_defaults(func=run)


def _pair(text: str | None, field: str, default: tuple[float, float]) -> tuple[float, float]:
    from ctrplan.errors import InputError
    from ctrplan.io import excerpt, strict_float

    if text is None:
        return default
    try:
        lo, hi = (strict_float(v) for v in text.split(","))
    except ValueError:
        raise InputError(field, "", f"must be MIN,MAX, got {excerpt(text)}") from None
    return lo, hi


def run(args: argparse.Namespace) -> int:
    from ctrplan.commands.plan import one_thread

    one_thread()
    from dataclasses import replace
    from pathlib import Path

    from ctrplan.design import DesignConfig, design
    from ctrplan.design.report import write_outputs
    from ctrplan.design.space import Bounds
    from ctrplan.errors import InputError

    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError("--out", "", f"{args.out!r} exists and is not a folder")
    b = Bounds()
    b = replace(b, curvature=_pair(args.curvature, "--curvature", b.curvature),
                curved_length=_pair(args.curved_length, "--curved-length", b.curved_length),
                straight_length=_pair(args.straight_length, "--straight-length", b.straight_length))
    for name, attr in (("strain_limit", "strain_limit"), ("min_gap", "min_gap_mm"),
                       ("max_length", "max_length_mm"), ("max_stroke", "max_stroke_mm")):
        v = getattr(args, name)
        if v is not None:
            b = replace(b, **{attr: float(v)})
    cfg = DesignConfig(tubes=args.tubes, seed=args.seed, budget=args.budget, time_limit=args.time,
                       generation=args.generation,
                       workers=args.workers, ray_address=args.ray, bounds=b, stock=args.stock,
                       derive=args.derive)
    result = design(args.scene, args.targets, cfg, start_from=args.start_from, out=out)
    write_outputs(result, out)
    print(f"{result.message} ({result.status.value}); binding: {', '.join(result.binding) or 'none'}")
    from ctrplan.design.explain import summary_line

    for t in result.targets:
        c = f"{t.clearance_mm:.2f} mm" if t.reached else "-"
        print(f"  {t.name}: {'reached' if t.reached else t.status}, clearance {c}")
    for b in result.blocked:
        print("  " + summary_line(b))
    written = ([out / "robot.yaml"] if result.robot is not None else []) + [out / "design.json", out / "report.md"]
    print("wrote " + ", ".join(str(p) for p in written))
    return 0 if result.success else 1
