"""Stage 1 of the calibration pipeline: check the inputs and the data, split the rows.

:func:`check_inputs` loads the robot and the data and validates the options (one-line
:class:`~ctrplan.errors.InputError` naming the field); :func:`split_rows` cuts the rows into fit /
validation / test (the one
splitter of :mod:`ctrplan.split`); :func:`data_check` says when the data cannot support a
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
from ctrplan.split import MIN_SWEEPS_WHOLE, HeldOut, is_ordered, row_ranges, split


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
    """Fit / validation / test rows (boolean (B,) masks; ``train`` = fit | validation; ``gap``:
    rows left out between test blocks and the others) and how they were cut (``heldout``, the
    one splitter's result, :mod:`ctrplan.split`). ``info`` is report.json's ``split`` (without
    the errors added later); ``warnings`` / ``experiment`` say what the split limits."""

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
    gap: np.ndarray | None = None
    heldout: HeldOut | None = None

    @property
    def units(self) -> np.ndarray:
        """(B,) the held-out unit of each row (sweep, or ``<sweep>#block<k>``): contiguous
        runs of development rows never straddle a test block or a gap within one unit."""
        return self.heldout.labels if self.heldout is not None else self.sweeps


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


def split_rows(data: MeasuredData, holdout: float, seed: int,
               heldout: HeldOut | None = None) -> Split:
    """Fit / validation / test masks by the one splitter (:func:`ctrplan.split.split`:
    ``holdout`` of the sweeps or blocks for test and as many for validation) with the report's
    description; ``heldout``: a split made beforehand (``diagnose --best`` passes its own)."""
    sw = data.sweeps()
    names = list(dict.fromkeys(sw.tolist()))
    h = heldout if heldout is not None else split(
        data.sweep, len(data), holdout, holdout, seed, q=data.q, ordered=ordered(data))
    fit_rows, val, test = h.fit, h.val, h.test
    train = fit_rows | val
    warnings, experiment = [], []
    if h.kind == "blocks":
        what = "the single sweep" if len(names) < 2 else f"each of the {len(names)} sweeps"
        info = {"method": f"contiguous blocks of {what} (validation and test blocks evenly "
                f"spaced; {h.gap_rows} rows left out on each side of a test block, the "
                f"motion's autocorrelation length {h.autocorrelation_rows} rows)",
                "test_rows": row_ranges(test), "validation_rows": row_ranges(val),
                "fit_rows": row_ranges(fit_rows), "gap_rows_ranges": row_ranges(h.gap)}
        train_sw = [f"{nm} ({', '.join(row_ranges(train & (sw == nm)))})" for nm in names]
        test_sw = [f"{nm} ({', '.join(row_ranges(test & (sw == nm)))})" for nm in names]
        val_sw = [f"{nm} ({', '.join(row_ranges(val & (sw == nm)))})" for nm in names]
        warnings.append(("one sweep only" if len(names) < 2 else f"only {len(names)} sweeps")
                        + f": the held-out rows are {h.test_units} blocks of the same motion "
                        "as the training rows (separated from them by a gap of "
                        f"{h.gap_rows} rows), so the held-out error may be optimistic; record "
                        f"at least {MIN_SWEEPS_WHOLE} separate sweeps")
        if h.capped:
            warnings.append(f"the sweeps are too short for a gap of the motion's "
                            f"autocorrelation length ({h.autocorrelation_rows} rows): the "
                            f"gap is {h.gap_rows} rows, so test rows are correlated with fit "
                            "rows")
        experiment.append(f"record at least {MIN_SWEEPS_WHOLE} separate sweeps (whole sweeps "
                          "are then held out)")
    else:
        info = {"method": "whole sweeps: fit / validation (chooses effects and forms) / test "
                "(touched by nothing else; reports the errors)"}
        train_sw = sorted(set(sw[train].tolist()))
        test_sw = sorted(set(sw[test].tolist()))
        val_sw = sorted(set(sw[val].tolist()))
    info.update({"test_row_ranges": row_ranges(test), "validation_sweeps": val_sw,
                 "fit_sweeps": sorted(set(sw[fit_rows].tolist())), **h.describe()})
    return Split(fit_rows, val, test, train, sw, ordered(data), info, train_sw, test_sw,
                 tuple(warnings), tuple(experiment), h.gap, h)


def split_sweeps(data: MeasuredData, holdout: float = 0.25, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Boolean (fit + validation) / test masks (see :func:`split_three`)."""
    fit, val, test = split_three(data, holdout, seed)
    return fit | val, test


def split_three(data: MeasuredData, holdout: float = 0.25,
                seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Boolean fit / validation / test masks of the one splitter
    (:func:`ctrplan.split.split`, ``holdout`` for test and as many for validation): whole
    sweeps with at least ``MIN_SWEEPS_WHOLE`` sweeps, else blocks of every sweep with the rows
    next to a test block left out (in no mask). The test rows choose nothing: they only
    report the error of the model chosen on the others."""
    h = split(data.sweep, len(data), holdout, holdout, seed, q=data.q, ordered=ordered(data))
    return h.fit, h.val, h.test


def fitted_names(effect: str, robot: Robot, base: str) -> list[str]:
    return [p.name for p in effect_params(effect, robot, base) if p.fit]


def ordered(data: MeasuredData) -> bool:
    """Rows are in order of motion unless every row is its own sweep (independent samples)."""
    return is_ordered(data.sweeps(), len(data))


def data_check(robot: Robot, data: MeasuredData, evb: dict, pred_tip: np.ndarray,
                min_configurations: int):
    """(reasons, experiments) when the data cannot support a diagnosis, else None."""
    reasons, todo = [], []
    distinct = evb["distinct_configurations"]
    if distinct < min_configurations:
        reasons.append(f"only {distinct} distinct configuration(s) in the {evb['rows']} fit "
                       f"and validation rows of {len(data)} (at least {min_configurations} "
                       "needed)")
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
