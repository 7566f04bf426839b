"""Stage 1 of the calibration pipeline: check the inputs and the data, split the rows.

:func:`check_inputs` loads the robot and the data and validates the options (one-line
:class:`~ctrplan.errors.InputError` naming the field); :func:`split_rows` cuts the rows into fit /
validation / test (:func:`split_three`); :func:`data_check` says when the data cannot support a
diagnosis (after the evidence stage has measured the noise floor) and what experiment would.
"""

from __future__ import annotations

import math
import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ctrplan.errors import InputError
from ctrplan.measured import MeasuredData, read_measured
from ctrplan.robot import Robot, load_robot
from ctrplan.shape.effects import EFFECT_NAMES, effect_params, effect_variants


@dataclass(frozen=True)
class Inputs:
    """Checked inputs: the robot, its data, the base model and the candidate effects (those
    with at least one fittable parameter for this robot and base)."""

    robot: Robot
    data: MeasuredData
    base: str
    candidates: tuple[str, ...]


@dataclass(frozen=True)
class Split:
    """Fit / validation / test rows (boolean (B,) masks; ``train`` = fit | validation) and how
    they were cut. ``info`` is report.json's ``split`` (without the errors added later);
    ``warnings`` / ``experiment`` say what the split limits (few sweeps)."""

    fit: np.ndarray
    val: np.ndarray
    test: np.ndarray
    train: np.ndarray
    sweeps: np.ndarray
    ordered: bool
    info: dict
    train_sweeps: list[str]
    test_sweeps: list[str]
    warnings: tuple[str, ...] = ()
    experiment: tuple[str, ...] = ()


def check_inputs(robot: Robot | str, data: MeasuredData | str | os.PathLike, base: str,
                 candidates: Sequence[str] | None) -> Inputs:
    """Load the robot (name / YAML) and the data (CSV path) and check base and candidates."""
    robot = load_robot(robot)
    if not isinstance(data, MeasuredData):
        data = read_measured(data, robot)
    if base not in ("rigid", "compliant"):
        raise InputError("--base", "", f"must be rigid or compliant, got {base!r}")
    cands = list(candidates) if candidates is not None else list(EFFECT_NAMES)
    for c in cands:
        if c not in EFFECT_NAMES:
            raise InputError("candidates", c, f"unknown effect; known: {', '.join(EFFECT_NAMES)}")
    cands = [c for c in cands if any(v[2] for v in effect_variants(c, robot, base))]
    if len(data) < 8:
        raise InputError("--data", "rows", f"need at least 8 rows to hold data out, got {len(data)}")
    return Inputs(robot, data, base, tuple(cands))


def split_rows(data: MeasuredData, holdout: float, seed: int) -> Split:
    """Fit / validation / test masks (:func:`split_three`) with the report's description."""
    sw = data.sweeps()
    names = list(dict.fromkeys(sw.tolist()))
    fit_rows, val, test = split_three(data, holdout, seed)
    train = fit_rows | val
    warnings, experiment = [], []
    if len(names) < MIN_SWEEPS_WHOLE:
        what = "the single sweep" if len(names) < 2 else f"each of the {len(names)} sweeps"
        info = {"method": f"contiguous blocks of {what} (of 8 blocks: 2 and 6 validation, "
                "4 and 8 test)", "test_rows": row_ranges(test),
                "validation_rows": row_ranges(val), "fit_rows": row_ranges(fit_rows)}
        train_sw = [f"{nm} ({', '.join(row_ranges(train & (sw == nm)))})" for nm in names]
        test_sw = [f"{nm} ({', '.join(row_ranges(test & (sw == nm)))})" for nm in names]
        val_sw = [f"{nm} ({', '.join(row_ranges(val & (sw == nm)))})" for nm in names]
        warnings.append(("one sweep only" if len(names) < 2 else f"only {len(names)} sweeps")
                        + ": the held-out rows are contiguous blocks of the same motion, next "
                        "to training rows, so the held-out error is optimistic; record at least "
                        f"{MIN_SWEEPS_WHOLE} separate sweeps")
        experiment.append(f"record at least {MIN_SWEEPS_WHOLE} separate sweeps (whole sweeps "
                          "are then held out)")
    else:
        info = {"method": "whole sweeps: fit / validation (chooses effects and forms) / test "
                "(touched by nothing else; reports the errors)"}
        train_sw = sorted(set(sw[train].tolist()))
        test_sw = sorted(set(sw[test].tolist()))
        val_sw = sorted(set(sw[val].tolist()))
    info.update({"test_row_ranges": row_ranges(test), "validation_sweeps": val_sw,
                 "fit_sweeps": sorted(set(sw[fit_rows].tolist()))})
    return Split(fit_rows, val, test, train, sw, ordered(data), info, train_sw, test_sw,
                 tuple(warnings), tuple(experiment))


def split_sweeps(data: MeasuredData, holdout: float = 0.25, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Boolean (fit + validation) / test masks holding out whole sweeps (see
    :func:`split_three`)."""
    fit, val, test = split_three(data, holdout, seed)
    return fit | val, test


#: fewer sweeps than this: every sweep is cut into blocks (each role sees every sweep)
MIN_SWEEPS_WHOLE = 8


def split_three(data: MeasuredData, holdout: float = 0.25,
                seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boolean fit / validation / test masks.

    At least ``MIN_SWEEPS_WHOLE`` sweeps: whole sweeps, ``round(holdout * sweeps)`` test sweeps
    and as many validation sweeps (drawn with ``seed``), the rest fit. Fewer sweeps (a few
    experiments of one kind each would otherwise leave the fit rows without, e.g., any
    rotation): every sweep is cut into 8 contiguous blocks; blocks 4 and 8 are test rows,
    blocks 2 and 6 validation rows (neighbours of fit rows: optimistic, and warned about).
    The test rows choose nothing: they only report the error of the model chosen on the others.
    """
    sw = data.sweeps()
    B = len(data)
    names = list(dict.fromkeys(sw.tolist()))
    if len(names) < MIN_SWEEPS_WHOLE:
        b = np.zeros(B, dtype=int)
        for nm in names:
            idx = np.nonzero(sw == nm)[0]
            b[idx] = np.minimum((np.arange(len(idx)) * 8) // max(len(idx), 1), 7)
        test = b % 4 == 3
        val = b % 4 == 1
        return ~test & ~val, val, test
    rng = np.random.default_rng(seed)
    order = [names[i] for i in rng.permutation(len(names))]
    k = max(1, min(int(round(holdout * len(names))), (len(names) - 1) // 2))
    held = set(order[:k])
    valn = set(order[k:2 * k])
    test = np.array([s in held for s in sw.tolist()])
    val = np.array([s in valn for s in sw.tolist()])
    return ~test & ~val, val, test


def row_ranges(mask: np.ndarray) -> list[str]:
    """1-based data-row ranges ("rows a-b") of the rows a boolean mask selects."""
    idx = np.nonzero(mask)[0]
    if not len(idx):
        return []
    out = []
    start = prev = int(idx[0])
    for i in idx[1:]:
        i = int(i)
        if i != prev + 1:
            out.append(f"rows {start + 1}-{prev + 1}")
            start = i
        prev = i
    out.append(f"rows {start + 1}-{prev + 1}")
    return out


def fitted_names(effect: str, robot: Robot, base: str) -> list[str]:
    return [p.name for p in effect_params(effect, robot, base) if p.fit]


def ordered(data: MeasuredData) -> bool:
    """Rows are in order of motion unless every row is its own sweep (independent samples)."""
    sw = data.sweeps()
    return len(set(sw.tolist())) < max(2, len(sw) // 2)


def data_check(robot: Robot, data: MeasuredData, evb: dict, pred_tip: np.ndarray,
                min_configurations: int):
    """(reasons, experiments) when the data cannot support a diagnosis, else None."""
    reasons, todo = [], []
    distinct = evb["distinct_configurations"]
    if distinct < min_configurations:
        reasons.append(f"only {distinct} distinct configuration(s) in {len(data)} rows "
                       f"(at least {min_configurations} needed)")
        todo.append("move every joint over its range: at least 20 (better 200+) distinct "
                    "configurations in several sweeps; repeats of a few of them give the noise "
                    "floor")
    span = float(np.median(robot.tip_length(data.q)))
    sd = evb["noise"].get("sd_mm")
    if sd is not None and sd * math.sqrt(3.0) > 0.1 * span:
        reasons.append(f"the measurement noise ({sd:.2f} mm per axis, {evb['noise']['method']}) "
                       f"is larger than what any effect changes at this robot's size "
                       f"({span:.0f} mm tip arc length)")
        todo.append("check the tracker and its synchronisation with the joints; record repeat "
                    "visits of the same configurations to measure the noise")
    pr = evb.get("procrustes", {})
    if pr.get("tested") and pr["rms_after_mm"] > 0.3 * span:
        reasons.append(f"even after the best rigid transform the tips are "
                       f"{pr['rms_after_mm']:.1f} mm (rms) from the model, far beyond any "
                       f"effect's reach at this robot's size ({span:.0f} mm)")
        todo.append("check the robot file, the units (mm, rad) and that the columns are in the "
                    "order of docs/conventions.md")
    return (reasons, todo) if reasons else None
