"""``ctrplan diagnose``: find, name and fit the effects missing from the model."""

from __future__ import annotations

import argparse
import json
import logging

from ctrplan.commands._common import FRACTION, NONNEGATIVE, SEED, add_robot_arg, float_arg
from ctrplan.commands._vocab import DEFAULT_OUT, DeprecatedAlias, add_mechanics_model_arg, base_of
from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "diagnose", help="name the effects missing from the model and fit them",
        description="Compare the mechanics model with measured data: fit the candidate effects "
                    "on fit sweeps, choose effects and forms on validation sweeps, report the "
                    "error on test sweeps used for nothing else. calibrated.yaml holds every "
                    "effect that lowers the validation error; report.json names only those "
                    "with evidence (BIC and validation error) and lists the rest as partial. "
                    "Writes report.json, report.md, PNG plots and the calibrated model "
                    "(calibrated.yaml for --model; calibrated_robot.yaml for --robot).")
    add_robot_arg(p)
    p.add_argument("--data", required=True, help="measured CSV (format: docs/conventions.md)")
    add_mechanics_model_arg(p, "rigid", "mechanics model the effects are added to")
    p.add_argument("--effects", default=None,
                   help="comma-separated candidate effects (default: all)")
    p.add_argument("--holdout", type=FRACTION, default=0.25,
                   help="fraction of the sweeps held out for test, and as many for validation "
                        "(default 0.25; fewer than 8 sweeps: blocks of every sweep, with the "
                        "rows within the motion's autocorrelation length of a test block left "
                        "out); --best compares its candidates on the same test rows")
    p.add_argument("--bic-threshold", type=NONNEGATIVE, default=10.0,
                   help="a named effect must lower BIC by more than this (default 10)")
    p.add_argument("--min-gain", type=float_arg(0.0, 1.0, hi_open=True), default=0.05,
                   help="and cut the validation mean tip error by at least this fraction "
                        "(default 0.05)")
    p.add_argument("--seed", type=SEED, default=0, help="seed of the sweep split (default 0)")
    p.add_argument("--best", action="store_true",
                   help="also build the best model of the robot: on the same split (the "
                        "--holdout fit / validation / test rows) fit a learned residual over the "
                        "calibrated model (direction-aware when the rows show motion) and a learned "
                        "model alone (shapes measured), compare nominal, calibrated, calibrated + "
                        "learned and learned on the untouched test rows and write the winner "
                        "as best_model.yaml or best_model.pt (with error_quantiles cross-fitted over "
                        "two folds of the test rows and, where shapes are measured, error_profile; "
                        "use with --model) and the comparison as best_model.json / best_model.md")
    p.add_argument("--test-fraction", type=FRACTION, dest="holdout", action=DeprecatedAlias,
                   new="--holdout", help=argparse.SUPPRESS)
    p.add_argument("--out", default=DEFAULT_OUT["diagnose"], help=f"output folder (default {DEFAULT_OUT['diagnose']})")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ctrplan.calibration.diagnose import diagnose
    from ctrplan.measured import read_measured
    from ctrplan.robot import load_robot

    if not 0 < args.holdout < 1:
        raise InputError("--holdout", "", f"must be in (0, 1), got {args.holdout}")
    robot = load_robot(args.robot)
    data = read_measured(args.data, robot)
    cands = None
    if args.effects:
        cands = [c.strip() for c in args.effects.split(",") if c.strip()]
    best = None
    if args.best:
        from ctrplan.calibration.best import best_model

        best = best_model(robot, data, out=args.out, base=base_of(args.model), holdout=args.holdout,
                          seed=args.seed, diagnose_kwargs=dict(
                              candidates=cands, bic_threshold=args.bic_threshold,
                              min_gain=args.min_gain))
        rep = best.report
    else:
        rep = diagnose(robot, data, base=base_of(args.model), candidates=cands, holdout=args.holdout,
                       seed=args.seed, bic_threshold=args.bic_threshold, min_gain=args.min_gain,
                       out=args.out)
    extra = {} if best is None else {"best": {
        "winner": best.winner, "file": best.files.get("best_model"),
        "test_mean_mm": {k: round(v["mean_mm"], 4) for k, v in best.candidates.items()}}}
    print(json.dumps({"headline": rep.headline(), "status": rep.status.value,
                      "conclusion": rep.conclusion, "effects": rep.effects,
                      "error_before_mm": round(rep.error_before_mm, 4),
                      "error_after_mm": round(rep.error_after_mm, 4),
                      "max_before_mm": round(rep.max_before_mm, 4),
                      "max_after_mm": round(rep.max_after_mm, 4),
                      "partial": rep.partial,
                      "unexplained": rep.unexplained is not None, "warnings": rep.warnings,
                      "out": str(args.out), **extra}))
    return 0
