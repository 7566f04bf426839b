"""``ctrplan simulate``: measured data with hidden effects (and noise) from the physics model."""

from __future__ import annotations

import argparse
import logging

import numpy as np

from ctrplan.commands._common import (
    MAX_MB,
    MEMORY_BUDGET_MB,
    NONNEGATIVE,
    POSITIVE,
    SEED,
    add_robot_arg,
    float_arg,
    int_arg,
    output_path,
    refuse_costly,
)
from ctrplan.commands._vocab import DEFAULT_OUT, add_mechanics_model_arg, base_of
from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")

#: Default ceiling of integrator states (rows x arc length / step) one request may need.
MAX_STATES = 1e10


def estimate_cost(robot, rows: int, points: int, step: float | None) -> tuple[float, float]:
    """Up-front cost of simulating ``rows`` rows: (memory in MB, integrator states). Memory
    counts what is held at once: configuration, tip, time, sweep label, and the backbones
    (points, arc lengths, radii, a noisy copy) of ``max(2, points)`` points per row."""
    m = max(2, points)
    per_row = 8 * (2 * robot.n + 3 + 1) + 64 + 8 * m * (3 + 1 + 1 + 3) + (8 * 3 * m if points else 0)
    length = float(sum(t.straight_length + t.curved_length for t in robot.tubes))
    states = rows * length / step if step else 0.0
    return rows * per_row / 2 ** 20, states


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser(
        "simulate", help="simulate measured data with hidden effects",
        description="Simulate measured data (measured CSV of docs/conventions.md: configuration, tip, time, "
                    "sweep, optional backbone points) from the mechanics model with hidden "
                    "effects and Gaussian noise. Rows are in order of motion.",
        epilog="Effects: torsion, friction, clearance, precurvature, stiffness, registration, "
               "joint_offset, load; e.g. --effect clearance:length=8 --effect friction:lost1=0.1,lost2=0.1. "
               "Experiments: feed, inner_rotation, outer_rotation, random_walk.")
    add_robot_arg(p)
    src = p.add_mutually_exclusive_group()
    src.add_argument("--configs", help="configuration CSV; rows are one motion in order")
    src.add_argument("--experiment", action="append", default=None,
                     choices=["feed", "inner_rotation", "outer_rotation", "random_walk"],
                     help="experiment design (repeatable; one after the other)")
    p.add_argument("--n", type=int_arg(1), default=200,
                   help="rows: random configurations (no --configs/--experiment) or rows per "
                        "experiment (default 200)")
    p.add_argument("--sweeps", type=int_arg(1, 1_000_000), default=4, help="sweeps per experiment (default 4)")
    p.add_argument("--effect", action="append", default=[], metavar="NAME[:PARAM=VALUE,...]",
                   help="hidden effect (repeatable); unnamed parameters stay off")
    add_mechanics_model_arg(p, "rigid", "mechanics model of the simulated robot")
    p.add_argument("--noise", type=NONNEGATIVE, default=0.0, help="noise std per coordinate, mm (default 0)")
    p.add_argument("--points", type=int_arg(0, 100_000), default=0,
                   help="also record M backbone points per row (default 0: tip only)")
    p.add_argument("--step", type=POSITIVE, default=None,
                   help="integrator step of the simulated truth, mm (default: the model's)")
    p.add_argument("--max-mb", type=MAX_MB, default=None, metavar="MB",
                   help=f"memory budget of the simulated data, and size cap of input files, MB "
                        f"(default {MEMORY_BUDGET_MB:.0f}); a larger request is refused up front")
    p.add_argument("--max-states", type=float_arg(1.0), default=MAX_STATES, metavar="N",
                   help=f"most integrator states (rows x arc length / --step) a request may need "
                        f"(default {MAX_STATES:.0e}); a larger request is refused up front")
    p.add_argument("--seed", type=SEED, default=0, help="random seed (configurations and noise)")
    p.add_argument("--out", default=DEFAULT_OUT["simulate"], help=f"output measured CSV (default {DEFAULT_OUT['simulate']})")
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    from ctrplan.calibration.simulate import design, simulate
    from ctrplan.measured import write_measured
    from ctrplan.robot import load_robot, read_configs
    from ctrplan.shape.effects import complete_effects, parse_effect_arg

    out = output_path(args.out, (".csv",))
    robot = load_robot(args.robot)
    effects: dict[str, dict[str, float]] = {}
    for text in args.effect:
        name, vals = parse_effect_arg(text)
        if name in effects:
            raise InputError("--effect", name, "given twice")
        effects[name] = vals
    complete_effects(effects, robot, base_of(args.model), source="--effect")
    if args.points == 1:
        raise InputError("--points", "", f"must be 0 or >= 2, got {args.points}")
    if not args.configs:   # the request's size is known up front: refuse what cannot be afforded
        rows = args.n * (len(args.experiment) if args.experiment else 1)
        mb, states = estimate_cost(robot, rows, args.points, args.step)
        budget = args.max_mb if args.max_mb is not None else MEMORY_BUDGET_MB
        refuse_costly("--n", f"{rows:,} rows", mb, budget, "MB of memory", "--max-mb")
        refuse_costly("--step", f"{rows:,} rows at --step {args.step:g} mm" if args.step else "",
                      states, args.max_states, "integrator states", "--max-states or a larger --step")
    if args.configs:
        q = read_configs(args.configs, robot)
        sweep = None
        mb, states = estimate_cost(robot, len(q), args.points, args.step)
        budget = args.max_mb if args.max_mb is not None else MEMORY_BUDGET_MB
        refuse_costly("--configs", f"{len(q):,} rows", mb, budget, "MB of memory", "--max-mb")
        refuse_costly("--step", f"{len(q):,} rows at --step {args.step:g} mm" if args.step else "",
                      states, args.max_states, "integrator states", "--max-states or a larger --step")
    elif args.experiment:
        q, sweep = design(robot, args.experiment, args.n, args.sweeps, args.seed)
    else:
        q = robot.sample(args.n, args.seed)
        sweep = np.array([f"random{k // 50 + 1}" for k in range(len(q))], dtype=object)
    data = simulate(robot, q, effects, base_of(args.model), sweep, args.noise, args.points, args.seed,
                    args.step)
    write_measured(out, robot, data)
    log.info("wrote %d measured rows (hidden: %s; noise %g mm) to %s", len(data),
             ", ".join(effects) or "none", args.noise, out)
    return 0
