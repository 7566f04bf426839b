"""``ctrplan train``: train a learned shape model, or run the evaluation sweep."""

from __future__ import annotations

import argparse
import dataclasses
import logging
import time

from ctrplan.commands._common import (
    POINTS,
    SEED,
    WORKERS,
    add_robot_arg,
    device_arg,
    float_arg,
    int_arg,
    output_path,
)
from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")


#: ``ctrplan train --help``: what the command does
DESCRIPTION = ("Pre-train the learned shape network on simulated shapes (by default "
               "1,000,000 uniform valid configurations of the compliant physics model; a "
               "4 x 64 network with pair inputs learns their difference to the closed-form "
               "rigid model, one cycle of the learning rate over 30 epochs, loss with the "
               "largest point distance along the shaft: the recipe of "
               "ctrplan/data/models/README.md, minutes of one CPU core), then fine-tune it on "
               "measured shapes (a measured CSV with backbone columns p1_x..pM_z). Each data set is "
               "split 80/10/10 into train/validation/test (measured rows by whole sweeps, or with "
               "fewer than 8 sweeps by contiguous blocks of the motion with the rows next to a "
               "test block left out, as diagnose splits); training on measured data minimises "
               "the sum of squared point distances with Adam and stops early on the validation "
               "loss. A robot with two stable equilibria somewhere (probed on 2,000 "
               "configurations) gets a warning: the network follows one branch. "
               "Writes a model file (.pt) with its metadata, the held-out error quantiles "
               "(p50/p95/p99/max of the max deviation along the shaft; error_bound says "
               "where they were measured: 'measured' with --real, a calibrated model; "
               "'surrogate' from simulation alone, the network's surrogate error against "
               "the physics model, uncalibrated) and the training "
               "domain (joint ranges seen; the model answers ok=False outside). "
               "With --real and no variant flags the variant is chosen by held-out error: "
               "the candidates (pure; direction-aware when the rows show motion with "
               "reversals; residual over physics; residual + direction) are each trained "
               "with a share of the epochs, the one with the lowest mean max deviation on "
               "the validation sweeps (not used for training) is trained on and kept; the "
               "table goes to MODEL.variants.json / .md beside the model and into its "
               "metadata ('selection'). --variant NAME, --direction or --residual choose "
               "the variant instead: --direction adds the direction of the last motion of "
               "each joint as inputs (from row order within each sweep of the CSV); "
               "--residual learns the difference to a base model. With shapes measured "
               "the model also stores error_profile (p50/p95/p99/max per arc-length "
               "fraction of the point deviation on the held-out test split). With --sweep: train Sim-only, and Real-only and "
               "Sim+Real for each variant (pure, direction-aware, residual, both) for several "
               "architectures, evaluated on held-out whole sweeps, and write tables "
               "(results.md, results.json) and plots (PNG) to the --out folder.")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "train", help="train a learned shape model (or run the evaluation sweep)",
        description=DESCRIPTION)
    add_robot_arg(p)
    _data_args(p)
    _training_args(p)
    _variant_args(p)
    p.add_argument("--out", required=True, help="model file (.pt), or a folder with --sweep")
    p.set_defaults(func=run)


def _data_args(p: argparse.ArgumentParser) -> None:
    """What to train on: simulated and measured data, a model to start from."""
    p.add_argument("--sim", type=int_arg(0, 100_000_000), default=None,
                   help="simulated configurations for pre-training (default 1000000, with --sweep "
                        "100000; 0 = none)")
    p.add_argument("--sim-base", choices=("rigid", "none"), default="rigid",
                   help="what the network pre-trained on simulation adds to: 'rigid' (default: the "
                        "closed-form torsionally rigid model; the network learns the tubes' twist, "
                        "a smooth correction) or 'none' (the network predicts the whole backbone)")
    p.add_argument("--real", default=None,
                   help="measured CSV with backbone points to fine-tune on (with --sweep: the "
                        "'real' data; default there: simulated with hidden effects)")
    p.add_argument("--init", default=None,
                   help="start from a trained model instead of pre-training: 'learned' (the "
                        "shipped default of the robot) or a model file; --sim then defaults to 0")
    p.add_argument("--real-sim", type=int_arg(1, 100_000_000), default=3000,
                   help="--sweep without --real: rows of simulated 'real' data with hidden "
                        "effects (default 3000)")


def _training_args(p: argparse.ArgumentParser) -> None:
    """The network, its optimiser and where it trains."""
    p.add_argument("--width", type=int_arg(1, 4096), default=None,
                   help="neurons per hidden layer (default 64 for the network pre-trained on "
                        "simulation, 30 for networks trained on measured data alone)")
    p.add_argument("--depth", type=int_arg(1, 64), default=None,
                   help="hidden layers (default 4 for the network pre-trained on simulation, 3 "
                        "for networks trained on measured data alone)")
    p.add_argument("--terms", type=int_arg(1, 1000), default=None, help="basis terms K per coordinate (default 7)")
    p.add_argument("--frame", choices=("outer", "base"), default="outer",
                   help="outer: angles relative to the outermost tube, output turned with it "
                        "(default); base: absolute angles as in the literature")
    p.add_argument("--epochs", type=int_arg(1, 1_000_000), default=None,
                   help="pre-training epochs (default 30 with --schedule onecycle; at most 150 "
                        "with plateau)")
    p.add_argument("--schedule", choices=("onecycle", "plateau"), default=None,
                   help="pre-training learning rate: 'onecycle' (default: warm-up, then cosine "
                        "annealing over all --epochs) or 'plateau' (halved when the validation "
                        "loss stalls, early stop after --patience; the default with --sweep)")
    p.add_argument("--loss", choices=("sum_sq+max", "sum_sq"), default=None,
                   help="pre-training loss per configuration: 'sum_sq+max' (default: mean squared "
                        "point distance + 4 x the largest along the shaft) or 'sum_sq' (sum of "
                        "squared point distances; the default with --sweep); training on measured "
                        "data uses sum_sq")
    p.add_argument("--fine-epochs", type=int_arg(0, 1_000_000), default=300, help="maximum fine-tuning epochs (default 300)")
    p.add_argument("--patience", type=int_arg(1, 1_000_000), default=20, help="early-stopping patience in epochs (default 20)")
    p.add_argument("--lr", type=float_arg(0.0, 10.0, lo_open=True), default=2e-3, help="Adam learning rate of pre-training (default 2e-3)")
    p.add_argument("--batch-size", type=int_arg(1, 10_000_000), default=512, help="mini-batch size (default 512)")
    p.add_argument("--points", type=POINTS, default=20, help="points per simulated backbone (default 20)")
    p.add_argument("--seed", type=SEED, default=0, help="random seed (data, splits, weights)")
    p.add_argument("--workers", type=WORKERS, default=None, help="processes for simulation (default: all cores)")
    p.add_argument("--threads", type=int_arg(1, 1024), default=1,
                   help="torch threads for training (default 1: the fastest for these small networks)")
    p.add_argument("--device", default="cpu",
                   help="torch device for training: cpu (default), cuda[:N] or auto (cuda when "
                        "torch sees a GPU)")


def _variant_args(p: argparse.ArgumentParser) -> None:
    """The model variant (direction inputs, residual base) and the evaluation sweep."""
    p.add_argument("--direction", action="store_true",
                   help="direction-aware inputs: the sign of the last motion of each joint, from "
                        "the row order within each sweep of the --real CSV")
    p.add_argument("--residual", default=None, metavar="BASE",
                   help="residual mode: the network learns the difference to BASE: 'physics', "
                        "'rigid', 'sim' (the pre-trained or --init model; no physics call at "
                        "evaluation), a calibrated model file from diagnose, or a learned model file; "
                        "with physics/rigid/FILE --sim defaults to 0")
    p.add_argument("--variant", default=None, choices=("auto", "pure", "direction", "residual", "residual+direction"),
                   help="the model variant (default with --real: auto, chosen by held-out error; "
                        "without --real: pure); residual variants use --residual BASE (default "
                        "physics)")
    p.add_argument("--refit", action="store_true",
                   help="after early stopping has chosen the epochs, train again on the measured "
                        "training + validation parts for that many epochs")
    p.add_argument("--variants", default=None,
                   help="--sweep variants, comma separated (default all: pure,direction,residual,"
                        "residual+direction)")
    p.add_argument("--sweep", action="store_true", help="run the evaluation sweep; --out is a folder")
    p.add_argument("--archs", default=None,
                   help="--sweep architectures DEPTHxWIDTH,... (default all of {3,5,7}x{15,30,60})")


def _check(args: argparse.Namespace) -> None:
    for name in ("width", "depth", "epochs", "batch_size", "threads", "points", "real_sim"):
        v = getattr(args, name)
        if v is not None and v < 1:
            raise InputError(f"--{name.replace('_', '-')}", "", f"must be >= 1, got {v}")
    if args.threads > 256:    # torch.set_num_threads overflows on huge values
        raise InputError("--threads", "", f"must be <= 256, got {args.threads}")
    if args.fine_epochs < 0 or args.patience < 1:
        raise InputError("--patience" if args.patience < 1 else "--fine-epochs", "", "out of range")
    if args.sim is not None and args.sim < 0:
        raise InputError("--sim", "", f"must be >= 0, got {args.sim}")
    if not args.lr > 0:
        raise InputError("--lr", "", f"must be > 0, got {args.lr}")
    if args.workers is not None and args.workers < 1:
        raise InputError("--workers", "", f"must be >= 1, got {args.workers}")
    if args.terms is not None and not 1 <= args.terms <= 12:
        raise InputError("--terms", "", f"must be in 1..12, got {args.terms}")
    args.device = device_arg(args.device)


def run(args: argparse.Namespace) -> int:
    import torch

    from ctrplan import progress
    from ctrplan.robot import load_robot
    from ctrplan.shape import basis
    from ctrplan.shape import training as T

    _check(args)
    torch.set_num_threads(args.threads)
    robot = load_robot(args.robot)
    terms = args.terms or basis.DEFAULT_TERMS
    if args.variant is not None and args.direction:
        raise InputError("--direction", "", "give either --variant or --direction")
    if args.variant in ("pure", "direction") and args.residual is not None:
        raise InputError("--residual", "", f"--variant {args.variant} does not take a residual base")
    explicit_base = args.residual is not None and args.residual != "sim"
    if args.variant is not None and args.variant.startswith("residual") and args.residual is None:
        explicit_base = True                      # residual over physics: nothing to pre-train
    recipe = T.SIM_RECIPE if not args.sweep else T.SWEEP_RECIPE
    n_sim = (0 if args.init or explicit_base else recipe.rows) if args.sim is None else args.sim
    show = progress._enabled
    pre, fine, real_only = _train_configs(args, recipe, show)
    t0 = time.perf_counter()
    if args.sweep:
        return _run_sweep(args, robot, n_sim, terms, (pre, fine, real_only), show, t0)

    out = output_path(args.out, (".pt",))
    real = T.from_measured(args.real, robot) if args.real else None
    if real is not None and len(real) < 3:
        raise InputError(args.real, "rows", "need at least 3 rows (train/validation/test)")
    if real is not None:
        for line in check_variety(real.q, real.points, args.real, robot.column_names):
            log.warning("%s", line)
    base = None
    if args.init:
        from ctrplan.shape.models import load_model

        base = load_model(args.init, robot)
        if getattr(base, "name", "") != "learned":
            raise InputError("--init", "", f"{args.init!r} is not a learned model")
        base.to(args.device)
    if n_sim == 0 and real is None:
        raise InputError("--sim", "", "nothing to train on: give --sim N > 0 and/or --real CSV")
    if n_sim and n_sim < 10:
        raise InputError("--sim", "", f"need at least 10 simulated configurations, got {n_sim}")
    variant = _variant(args, real is not None)
    residual_base = _residual_base(args, robot, variant, n_sim, base)
    sim = (T.simulated_data(robot, n_sim, seed=args.seed, points=args.points, workers=args.workers,
                            progress=show) if n_sim else None)
    try:
        model, report = T.pretrain_finetune(
            robot, sim, real, width=args.width or T.DEFAULT_WIDTH, depth=args.depth or T.DEFAULT_DEPTH,
            terms=terms, seed=args.seed,
            pre=pre, fine=fine if (sim is not None or base is not None) else real_only,
            real_only=real_only, device=args.device, frame=args.frame, base=base,
            variant=variant, residual_base=residual_base, refit=args.refit,
            sim_base=None if args.sim_base == "none" else args.sim_base,
            sim_arch=(args.width or recipe.width, args.depth or recipe.depth), sim_pairs=recipe.pairs)
    except ValueError as exc:
        raise InputError(args.real or "--sim", "", str(exc)) from None
    if sim is not None:
        _note_bistable(model, robot, args.seed)
    _write_model(out, model, report)
    _log_results(model, report)
    log.info("wrote %s (%.0f s)", out, time.perf_counter() - t0)
    return 0


def _train_configs(args: argparse.Namespace, recipe, show: bool):
    """(pre-training, fine-tuning, measured-only) TrainConfigs from the options."""
    from ctrplan.shape import training as T

    schedule = args.schedule or recipe.schedule
    pre = T.TrainConfig(epochs=args.epochs or (recipe.epochs if schedule == "onecycle" else 150),
                        lr=args.lr, batch_size=args.batch_size, patience=args.patience,
                        seed=args.seed, progress=show, label="pre-train (sim)",
                        loss=args.loss or recipe.loss, schedule=schedule)
    fine = T.TrainConfig(epochs=max(1, args.fine_epochs), lr=args.lr / 4, batch_size=min(args.batch_size, 128),
                         patience=args.patience, seed=args.seed, progress=show, label="fine-tune (real)")
    real_only = T.TrainConfig(epochs=max(1, args.fine_epochs), lr=args.lr, batch_size=min(args.batch_size, 128),
                              patience=args.patience, seed=args.seed, progress=show, label="train (real)")
    return pre, fine, real_only


def _run_sweep(args: argparse.Namespace, robot, n_sim: int, terms: int, configs: tuple,
               show: bool, t0: float) -> int:
    """``train --sweep``: the evaluation sweep into the --out folder (tables and plots)."""
    from pathlib import Path

    from ctrplan.shape import training as T

    pre, fine, real_only = configs
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError("--out", "", f"{args.out!r} exists and is not a folder (--sweep writes a folder)")
    try:
        archs = T.parse_archs(args.archs) if args.archs else list(T.ALL_ARCHS)
    except ValueError as exc:
        raise InputError("--archs", "", str(exc)) from None
    variants = [v.strip() for v in args.variants.split(",") if v.strip()] if args.variants else list(T.VARIANTS)
    bad = [v for v in variants if v not in T.VARIANTS]
    if bad or not variants:
        raise InputError("--variants", "", f"unknown variant {bad[0] if bad else ''!r} "
                                           f"(one of {', '.join(T.VARIANTS)})")
    if n_sim < 10:
        raise InputError("--sim", "", "--sweep needs at least 10 simulated configurations")
    sim = T.simulated_data(robot, n_sim, seed=args.seed, points=args.points, workers=args.workers,
                           progress=show)
    real = (T.from_measured(args.real, robot) if args.real
            else T.real_data(robot, args.real_sim, seed=args.seed + 1, points=args.points))
    if len(real) < 10:
        raise InputError(args.real or "--real-sim", "rows", "need at least 10 rows of real data")
    res = T.sweep(robot, sim, real, archs=archs, terms=terms, frame=args.frame, seed=args.seed,
                  pre=pre, fine=fine, real_only=real_only, device=args.device, progress=show,
                  variants=variants, refit=args.refit)
    if not args.real:
        res.data["hidden_effects"] = T.HiddenEffects.default(robot).to_dict()
    res = dataclasses.replace(res, seconds=time.perf_counter() - t0)
    paths = T.write_sweep(res, out)
    print(T.sweep_markdown(res))
    log.info("wrote %s", ", ".join(str(p) for p in paths))
    return 0


def _variant(args: argparse.Namespace, has_real: bool) -> str:
    """The variant the options ask for (``auto`` with --real and no variant option)."""
    if args.variant is not None:
        variant = args.variant
    elif args.residual or args.direction:
        variant = ("residual" if args.residual else "pure") + ("+direction" if args.residual and args.direction else "")
        if args.direction and not args.residual:
            variant = "direction"
    else:
        variant = "auto" if has_real else "pure"
    if variant not in ("pure", "auto") and not has_real:
        flag = "--variant" if args.variant else ("--residual" if args.residual else "--direction")
        raise InputError("--real", "", f"{flag} needs a measured CSV")
    return variant


def _residual_base(args: argparse.Namespace, robot, variant: str, n_sim: int, base):
    """The base model of a residual variant given by --residual (None: none, or 'sim': the
    pre-trained model, chosen later)."""
    if args.residual and args.residual != "sim":
        from ctrplan.shape.models import load_model

        return load_model(args.residual, robot)
    if args.residual is None and variant.startswith("residual"):
        from ctrplan.shape.physics import PhysicsModel

        return PhysicsModel(robot)
    if args.residual == "sim" and n_sim == 0 and base is None:
        raise InputError("--residual", "", "'sim' needs a pre-trained model (--sim N or --init)")
    return None


def _note_bistable(model, robot, seed: int) -> None:
    """A bistable robot: the surrogate follows the physics model's default branch and cannot
    represent snapping (docs/conventions.md); say so, and record it in the model's metadata."""
    from ctrplan.shape import training as T

    bist = T.bistable_fraction(robot, seed=seed)
    model.meta["bistable"] = bist
    if bist["fraction"] > 0:
        log.warning("%s is bistable at %.1f%% of %d probed configurations: the learned model "
                    "follows the physics model's default (least twisted) branch there and "
                    "cannot represent a snap; plan this robot with --model physics",
                    robot.name, 100 * bist["fraction"], bist["probed"])


def _write_model(out, model, report) -> None:
    """Stamp the model's metadata (command, time, version) and write it to ``out``, with the
    variant table beside it when the variant was chosen."""
    import contextlib
    import sys

    from ctrplan import __version__
    from ctrplan.io import atomic_path, jsonable, write_json_atomic, write_text_atomic
    from ctrplan.shape import training as T

    model.meta.update({
        "command": "ctrplan train " + " ".join(sys.argv[2:]) if sys.argv[1:2] == ["train"] else "ctrplan train",
        "created": time.strftime("%Y-%m-%dT%H:%M:%S"),
        "ctrplan_version": __version__,
    })
    sel = report.selection or {}
    # Every file goes to a temporary beside its target and all are renamed into place only
    # after all were written: a full disk leaves the previous model (and tables) as they were.
    with contextlib.ExitStack() as stack:
        if sel.get("mode") == "auto":
            side = out.with_suffix(".variants.json")
            write_json_atomic(stack.enter_context(atomic_path(side)), jsonable(sel))
            write_text_atomic(stack.enter_context(atomic_path(out.with_suffix(".variants.md"))),
                              T.selection_markdown(sel))
            log.info("variant %s chosen by validation error: %s (table: %s)", sel["chosen"],
                     ", ".join(f"{r['variant']} {r['val_max_dev_mean_mm']:.3f} mm"
                               for r in sel["candidates"]), side)
        model.save(stack.enter_context(atomic_path(out)))


def _log_results(model, report) -> None:
    """Log the held-out metrics, error quantiles and where the error bound comes from."""
    for name, m in report.metrics.items():
        log.info("%s: max deviation %.3f +- %.3f mm, MSE %.4f mm^2, sum of deviations %.2f mm (n=%d)",
                 name, m["max_dev_mean"], m["max_dev_std"], m["mse_mean"], m["sum_dev_mean"], m["n"])
    eq = report.error_quantiles or {}
    for line in quantile_summary(eq, model.meta.get("error_quantiles_source") or {}):
        log.info("%s", line)
    if eq:   # where the bound comes from (error_bound in the file): what `plan` will call it
        log.info("error_bound: %s", "measured (held-out measured rows: the model is calibrated)"
                 if model.error_bound == "measured" else
                 "surrogate (held-out simulated shapes: its surrogate error against the simulated "
                 "model, not a bound on the real robot; the model is uncalibrated)")


#: Fewest distinct configurations (and distinct measured shapes) ``train`` accepts in --real:
#: below it the train / validation / test parts cannot each hold different configurations, so
#: a held-out error would be measured on the training rows themselves.
MIN_DISTINCT = 10
#: Fewest held-out configurations for which a p99 is more than the largest value seen.
MIN_ROWS_P99 = 100


def check_variety(q, points, source: str, columns) -> list[str]:
    """Refuse measured data without variety; return warnings for data with little.

    q : (N, 2n) configurations; points : (N, M, 3) measured backbones, mm. Refused (InputError)
    when fewer than :data:`MIN_DISTINCT` distinct configurations or distinct shapes (rounded to
    1e-9) are present: 300 identical rows would otherwise train a model and report a held-out
    error measured on copies of its training rows. Warned: more than half the rows repeat
    another row (held-out errors optimistic), and joints that never move (the model knows them
    at one value only)."""
    import numpy as np

    q = np.asarray(q, dtype=float)
    n_rows = len(q)
    distinct = len(np.unique(np.round(q, 9), axis=0))
    shapes = len(np.unique(np.round(np.asarray(points, dtype=float).reshape(n_rows, -1), 9), axis=0))
    if min(distinct, shapes) < MIN_DISTINCT:
        what = "configurations" if distinct <= shapes else "measured shapes"
        raise InputError(source, "rows", f"only {min(distinct, shapes)} distinct {what} in {n_rows} "
                         f"rows (need >= {MIN_DISTINCT}): data without variety cannot train a model, "
                         f"and its held-out error would be measured on copies of training rows")
    out = []
    if distinct < n_rows / 2:
        out.append(f"{source}: only {distinct} distinct configurations in {n_rows} rows: held-out "
                   f"rows repeat training rows, so the reported errors are optimistic")
    still = [c for c, j in zip(columns, range(q.shape[1])) if np.ptp(q[:, j]) == 0]
    if still:
        out.append(f"{source}: {', '.join(still)} never move(s) in the data: the model is trained "
                   f"(and its domain set) at that one value only")
    return out


def quantile_summary(eq: dict, source: dict) -> list[str]:
    """The held-out error quantiles as printed by ``train``, with the number of configurations
    they rest on, and a note where that number cannot support a quantile (p99 of fewer than
    :data:`MIN_ROWS_P99` configurations is the max, or nearly)."""
    if not eq:
        return ["no held-out error quantiles (no test rows)"]
    rows = source.get("rows")
    head = (f"error quantiles (held-out max deviation over {rows} configurations, mm): "
            if rows is not None else "error quantiles (held-out max deviation, mm): ")
    lines = [head + ", ".join(f"{k} {v:.3f}" for k, v in eq.items())]
    if rows is not None and rows < MIN_ROWS_P99:
        lines.append(f"note: {rows} held-out configurations cannot support a p99 (needs >= "
                     f"{MIN_ROWS_P99}); the p99 here is interpolated among the largest few values, "
                     f"treat it as the max")
    return lines
