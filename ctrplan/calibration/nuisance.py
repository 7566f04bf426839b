"""Nuisances outside the effect vocabulary, screened after the fit (calibration pipeline,
between the final fit and the conclusion; never part of the calibrated model).

A drift of the sensor in time and a distortion of the tracker field are claimed only where the
data tell them apart from the robot (see ``NUISANCES``); a named effect that is itself mostly
such a function of a claimed nuisance is un-named (:func:`screen`).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from ctrplan.calibration.data import Split
from ctrplan.calibration.lsq import Problem
from ctrplan.calibration.select import gain as _gain
from ctrplan.measured import MeasuredData
from ctrplan.robot import Robot


@dataclass(frozen=True)
class Nuisances:
    """Result of the nuisance screen: every test (report.json ``nuisance_tests``, with its
    ``features``), the claimed kinds, the effects still named, and warnings for un-named ones."""

    tests: list[dict]
    claimed: list[str]
    named: list[str]
    warnings: tuple[str, ...] = ()


def screen(robot: Robot, prob: Problem, data: MeasuredData, split: Split, final_pred: np.ndarray,
           base_pred: np.ndarray, current: dict, named: Sequence[str], min_gain: float
           ) -> Nuisances:
    """Test the nuisances on the calibrated and the base model's residuals; un-name the
    effects (``named``) that a claimed nuisance mimics."""
    outside = _nuisances(robot, prob, data, final_pred, split.fit, split.val, split.train,
                         split.test, min_gain, split.sweeps, split.ordered, base_pred)
    claimed = [o["kind"] for o in outside if o["claimed"]]
    named = list(named)
    warnings = []
    for o in outside:
        if not o["claimed"]:
            continue
        for e in list(named):
            frac, change = _explained_by(robot, prob, data, current, e, o["features"],
                                         split.train)
            if not frac > FIELD_LIKE:
                continue
            level = o.get("anchored_level_mm")
            if level is not None and _level_share(change, np.asarray(level)) < LEVEL_SHARE:
                continue       # a constant offset far larger than the drift ever moved
            named.remove(e)
            warnings.append(f"{e} is not named: {100 * frac:.0f} % of what it changes is "
                            f"also {NUISANCES[o['kind']]}, which the data show is at work")
    return Nuisances(outside, claimed, named, tuple(warnings))


def _level_share(change: np.ndarray, level: np.ndarray) -> float:
    """The share of an effect's mean change at the tips (3,) mm that a drift's anchored level
    (3,) accounts for: its projection on the change over the change's square norm."""
    cc = float(change @ change)
    return float(change @ level) / cc if cc > 0 else 1.0


#: Nuisances outside the effect vocabulary, tested only AFTER the robot model is fitted (so they
#: never absorb the robot's own effects): a sensor drift in time (a penalised linear spline) and
#: a smooth tracker-field distortion (a quadratic function of the measured tip position, ridge
#: penalised). One is claimed only where the data tell it apart from the robot: on the
#: validation rows (a drift: alternate spans of time, ``DRIFT_BLOCKS``), the nuisance's
#: features must explain the robot model's residual clearly
#: better (by ``DISTINGUISH``) than smooth features of the configuration
#: (harmonics of the relative and absolute rotations, insertions, direction of motion) - a field
#: gives the same correction wherever the tip is, however it got there; a robot effect does
#: not. On the base model's residual it must also beat the calibrated robot model. The
#: calibrated model never contains a nuisance; a named effect whose change to the tips is itself
#: mostly (``FIELD_LIKE``) such a function of the claimed nuisance (a drift's level and trend,
#: a field's nonlinear terms) is no longer named.
NUISANCES = {"~drift": "a drift of the sensor in time", "~field": "a distortion of the tracker "
             "field (a smooth function of the measured position)"}
DISTINGUISH = 0.9
FIELD_LIKE = 0.8
#: A drift's level is told from a constant offset by where the drift starts: a sensor drift is
#: a change since the tracker was registered, taken as the start of the recording, so a
#: claimed drift's *anchored level* is the mean of its fitted curve less its value at the first
#: row (a drift that settles by 4 mm within the recording: about 4 mm; the per-sweep jitter of
#: a joint's homing switch: about its own 0.2 mm). A named effect that is mostly a level and a
#: trend is un-named only when the anchored level accounts for at least this share of its mean
#: change at the tips (more than it leaves: the midpoint); a constant offset far larger than
#: the drift ever moved (a joint offset of 1.5 mm beside a 0.2 mm homing jitter) stays named.
#: Where the first row is held out (a test block) the start is not observed and the level
#: cannot be anchored: an effect that is mostly a level and a trend is then un-named.
LEVEL_SHARE = 0.5
#: A nuisance must lower the mean tip error by at least this much (mm; 1 um, below any
#: tracker's resolution) to be claimed: relative gains on a numerically zero residual (noiseless
#: data the model already fits) are no evidence.
RESOLUTION_MM = 1e-3
RIDGE = 1e-2
#: The drift: a linear spline in the fraction of the recording time with ``DRIFT_KNOTS`` evenly
#: spaced knots (about one per sweep of a typical recording: it follows a fast settling or a
#: bump of the tracker, which a polynomial in time does not), its second differences penalised
#: by ``DRIFT_SMOOTH`` x rows (across a gap in the data it interpolates linearly).
DRIFT_KNOTS = 10
DRIFT_SMOOTH = 1e-2
#: A drift is tested where a function of time can be: interpolated. The fit + validation rows
#: are cut, in time order, into ``DRIFT_BLOCKS`` spans of equal row count; the drift and the
#: configuration features are both fitted on the even spans and compared on the odd ones
#: between the first and the last even-span row (the validation sweeps, drawn at random, may
#: lie at either end of the recording, where a drift would have to be extrapolated; see
#: :func:`_time_spans`). Spans are long enough (half a sweep of a typical recording)
#: that the configuration moves within one: where spans were a few rows long, a function of
#: time followed the robot's own slowly varying error along the trajectory as well as a
#: configuration model did.
DRIFT_BLOCKS = 16


def _standardise(F: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """Columns scaled to unit rms on ``rows`` (a constant column stays 1)."""
    s = np.sqrt(np.mean(F[rows] ** 2, axis=0))
    return F / np.where(s > 0, s, 1.0)


def _nuisance_features(kind: str, data: MeasuredData, rows: np.ndarray) -> np.ndarray | None:
    """(B, k) features of nuisance ``kind`` for every row, or None when it cannot be tested."""
    if kind == "~drift":
        t = data.time
        if t is None or len(t) < 8 or not np.ptp(t) > 0:
            return None
        x = _time_fraction(data)
        knots = np.linspace(0.0, 1.0, DRIFT_KNOTS)
        h = knots[1] - knots[0]
        return np.clip(1.0 - np.abs(x[:, None] - knots[None, :]) / h, 0.0, None)
    p = np.asarray(data.tip, dtype=float)
    c = p - p[rows].mean(0)
    sc = float(np.max(np.abs(c[rows])))
    if not sc > 0:
        return None
    x, y, z = (c / sc).T
    return _standardise(np.stack([np.ones_like(x), x, y, z, x * x, y * y, z * z, x * y, x * z,
                                  y * z], axis=1), rows)


def _config_features(robot: Robot, data: MeasuredData, sw: np.ndarray, ordered: bool,
                     rows: np.ndarray) -> np.ndarray:
    """(B, k) configuration features of the same kind of flexibility as a nuisance's."""
    from ctrplan.shape.base import direction_from_rows

    n = robot.n
    q = data.q
    cols = [np.ones(len(q))]
    for i in range(n - 1):
        phi = q[:, i] - q[:, i + 1]
        cols += [np.cos(phi), np.sin(phi), np.cos(2 * phi), np.sin(2 * phi)]
    for i in range(n):
        # absolute rotations: what acts in the base frame (gravity, a tip load) turns with them
        cols += [np.cos(q[:, i]), np.sin(q[:, i])]
    b = q[:, n:]
    b = (b - b[rows].mean(0)) / np.maximum(np.ptp(b[rows], axis=0), 1e-9)
    cols += list(b.T)
    if ordered:
        d = direction_from_rows(q, sw).astype(float)[:, :n]
        cols += list(d.T)
    return _standardise(np.stack(cols, axis=1), rows)


def _ridge(F: np.ndarray, R: np.ndarray, rows: np.ndarray, smooth: bool = False) -> np.ndarray:
    A = F[rows]
    ok = np.all(np.isfinite(A), axis=1) & np.all(np.isfinite(R[rows]), axis=1)
    A = A[ok]
    k = A.shape[1]
    if smooth:
        D = np.diff(np.eye(k), 2, axis=0)
        P = DRIFT_SMOOTH * len(A) * (D.T @ D) + 1e-9 * len(A) * np.eye(k)
    else:
        P = RIDGE * len(A) * np.eye(k)
    coef = np.linalg.solve(A.T @ A + P, A.T @ R[rows][ok])
    return np.nan_to_num(F) @ coef


def _distinguish(F: np.ndarray, G: np.ndarray, r: np.ndarray, fit_rows: np.ndarray,
                 val: np.ndarray, smooth: bool = False) -> tuple[float, float, float]:
    """Validation mean |r| as is, after a ridge fit on nuisance features F, after one on
    configuration features G (both fitted on ``fit_rows``)."""
    def mean(x):
        return float(np.linalg.norm(x[val], axis=1).mean())

    return mean(r), mean(r - _ridge(F, r, fit_rows, smooth)), mean(r - _ridge(G, r, fit_rows))


def _time_fraction(data: MeasuredData) -> np.ndarray:
    t = np.asarray(data.time, dtype=float)
    return (t - np.min(t)) / np.ptp(t)


def _level_trend(data: MeasuredData) -> np.ndarray:
    """What a named effect must not mostly be once a drift is claimed: a constant offset and a
    steady trend over the recording (a drift's level cannot be told from a constant offset).
    Not the drift's faster variation: along a slow trajectory the robot's own effects vary
    slowly in time too (torsion's change at the tips was 89 % a spline in time on one seed)."""
    x = _time_fraction(data)
    return np.stack([np.ones_like(x), x], axis=1)


def _time_spans(data: MeasuredData, train: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fit + validation rows in even / odd spans of the recording time (``DRIFT_BLOCKS``),
    compared only where the drift is interpolated.

    The spans cut the fit + validation rows in time order into equal counts: the held-out
    test blocks leave gaps in time, and spans of equal *time* put whole stretches between two
    test blocks in one parity (one seed: every fit row before 45 % of the recording, the
    comparison rows after it, a drift extrapolated over half the recording and 2 mm worse
    than none). Odd-span rows before the first or after the last even-span row (the last span
    is odd) are not compared: there a function of time would be extrapolated."""
    x = _time_fraction(data)
    rows = np.flatnonzero(train)
    fit, cmp_ = np.zeros(len(x), dtype=bool), np.zeros(len(x), dtype=bool)
    if not len(rows):
        return fit, cmp_
    rows = rows[np.argsort(x[rows], kind="stable")]
    span = (np.arange(len(rows)) * DRIFT_BLOCKS) // len(rows)
    fit[rows[span % 2 == 0]] = True
    odd = rows[span % 2 == 1]
    lo, hi = x[fit].min(), x[fit].max()
    cmp_[odd[(x[odd] > lo) & (x[odd] < hi)]] = True
    return fit, cmp_


def _where(kind: str, data: MeasuredData, fit_rows: np.ndarray, val: np.ndarray,
           train: np.ndarray) -> tuple[np.ndarray, np.ndarray, str]:
    """Rows a nuisance is fitted on and compared on, and their name in the report: a drift on
    spans of time (interpolated; the validation sweeps when too few rows), a field on the
    validation sweeps (positions reached on other sweeps)."""
    if kind == "~drift":
        fr, vr = _time_spans(data, train)
        if min(fr.sum(), vr.sum()) >= 8:
            return fr, vr, "alternate spans of time"
    return fit_rows, val, "validation"


def _nuisances(robot, prob, data, final_pred, fit_rows, val, train, test, min_gain, sw,
               ordered, base_pred) -> list[dict]:
    """Test every nuisance (see NUISANCES) on two residuals: the calibrated robot model's, and
    the base model's after the best affine map (before any robot effect could absorb a
    field). Claimed when either shows it, distinguishably from the configuration."""
    r = data.tip - final_pred[:, -1]
    r = np.where(np.isfinite(r), r, 0.0)
    pb = base_pred[:, -1]
    okb = np.all(np.isfinite(pb), axis=1) & train
    # an affine map (rigid transform, scale, shear) is registration / tracker calibration, not
    # a field: the field must explain what the best affine map of the base model leaves
    X = np.hstack([pb, np.ones((len(pb), 1))])
    A, *_ = np.linalg.lstsq(X[okb], data.tip[okb], rcond=None)
    r0 = data.tip - X @ A
    r0 = np.where(np.isfinite(r0), r0, 0.0)
    G = _config_features(robot, data, sw, ordered, fit_rows)
    feats = {k: F for k in NUISANCES
             if (F := _nuisance_features(k, data, fit_rows)) is not None}

    def mean(x, rows):
        return float(np.linalg.norm(x[rows], axis=1).mean())

    rows = {k: _where(k, data, fit_rows, val, train) for k in feats}
    out = []
    # the nuisance that explains most is tested first, the next on what it leaves
    order = sorted(feats, key=lambda k: mean(r - _ridge(feats[k], r, rows[k][0], k == "~drift"),
                                             rows[k][1]))
    for kind in order:
        F = feats[kind]
        sm = kind == "~drift"
        fr, vr, where = rows[kind]
        rm = r
        if kind == "~field":
            # its affine part (in the measured position) is registration / tracker scale: the
            # field must explain what an affine map leaves
            rm = r - _ridge(F[:, :4], r, fit_rows)
        rb = r0
        if sm:
            # a constant offset is registration: the drift must explain what one leaves
            rm, rb = rm - rm[fr].mean(0), r0 - r0[fr].mean(0)
        e_model, e_nuis, e_conf = _distinguish(F, G, rm, fr, vr, sm)
        b_model, b_nuis, b_conf = _distinguish(F, G, rb, fr, vr, sm)
        gain = _gain(e_model, e_nuis)
        on_model = bool(gain >= 2 * min_gain and e_nuis <= DISTINGUISH * e_conf
                        and e_model - e_nuis >= RESOLUTION_MM)
        # on the base model's residual the nuisance must also beat the calibrated robot model
        # (its residual e_model): the robot's effects are a configuration-dependent
        # explanation too, and where they explain the base model's error better than the
        # nuisance does, a nuisance that explains part of it is only correlated with them
        on_base = bool(_gain(b_model, b_nuis) >= 2 * min_gain
                       and b_nuis <= DISTINGUISH * min(b_conf, e_model)
                       and b_model - b_nuis >= RESOLUTION_MM)
        claimed = on_model or on_base
        corr = _ridge(F, r, train, sm)               # fitted on fit + validation rows
        left = r - corr
        anchored = None
        first = int(np.argmin(np.asarray(data.time, dtype=float)))
        if sm and train[first]:
            # the drift's level if it started at zero at the first row (LEVEL_SHARE); only
            # where that row is a fit or validation row (a held-out first sweep leaves the
            # start extrapolated: a settling drift's level is then underestimated)
            anchored = [float(v) for v in corr[train].mean(0) - corr[first]]
        why = (f"calibrated model's residual: {where} mean {e_model:.3f} mm -> {e_nuis:.3f} "
               f"mm with it, {e_conf:.3f} mm with configuration features instead; base model "
               f"after an affine map: {b_model:.3f} -> {b_nuis:.3f} mm, {b_conf:.3f} mm")
        out.append({"kind": kind, "claimed": claimed, "why": why, "compared_on": where,
                    "validation_gain": gain,
                    "validation_mean_with_mm": e_nuis, "validation_mean_config_mm": e_conf,
                    "base_validation_mean_with_mm": b_nuis,
                    "base_validation_mean_config_mm": b_conf,
                    "test_mean_with_mm": mean(left, test),
                    "test_max_with_mm": float(np.linalg.norm(left[test], axis=1).max()),
                    "anchored_level_mm": anchored,
                    # what a named effect must not mostly be: a drift's level and trend, the
                    # nonlinear terms of a field
                    "features": _level_trend(data) if kind == "~drift" else F[:, 4:]})
        if claimed:
            r = left
            r0 = r0 - _ridge(F, r0, train, sm)
    return out


def _explained_by(robot, prob, data, current, effect, F, rows) -> tuple[float, np.ndarray]:
    """(fraction of what ``effect`` changes at the tips (sum of squares over ``rows``) that a
    least-squares function of the nuisance features F reproduces, its mean change (3,) mm)."""
    without = {k: v for k, v in current.items() if k != effect}
    a, b = prob.predict_many([current, without])
    d = a[:, -1] - b[:, -1]
    d = np.where(np.isfinite(d), d, 0.0)
    mean = d[rows].mean(0) if rows.any() else np.zeros(3)
    ss = float((d[rows] ** 2).sum())
    if ss <= 0:
        return 0.0, mean
    coef, *_ = np.linalg.lstsq(F[rows], d[rows], rcond=None)
    left = d[rows] - F[rows] @ coef
    return float(1.0 - (left ** 2).sum() / ss), mean
