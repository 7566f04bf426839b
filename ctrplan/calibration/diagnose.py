"""The sim-vs-measured workflow: find where the model and the data disagree, name the missing
effect, add it, and show the gap shrink — and say so when the data cannot tell.

Procedure (:func:`diagnose`):

1. Data check: enough distinct configurations, a measurable noise floor below what any effect
   can change, an error the vocabulary can reach at all. Otherwise the report says that the data
   cannot support a diagnosis and what experiment would (status ``insufficient data``).
2. Split the data holding out whole sweeps. A data set with a single sweep is cut into 8
   contiguous blocks, every 4th held out; the report then names the held-out rows (never the
   sweep as if it were held out) and warns that they are neighbours of training rows. The model
   is always evaluated on all rows in order (friction depends on the history); only the rows'
   roles differ.
3. Evidence from the data alone (:mod:`ctrplan.calibration.evidence`): noise floor, hysteresis,
   residual harmonics per relative rotation, trend with insertion, rigid-transform test.
4. Screen every form of every candidate effect not yet in the model (friction: dead band,
   presliding, lag, relative lag, end moment; clearance: harmonic series in the relative
   rotation of first / second order, curvature-jump gap): fit its parameters alone on top of the
   current model (bounded least squares, a few iterations); the ``refit_top`` best (by BIC) are
   refitted jointly with the effects already added.
5. A candidate is justified only by BOTH ``BIC_new - BIC_current < -bic_threshold`` (training
   residuals) AND a held-out mean tip error cut of at least ``min_gain``. The justified candidate
   with the lowest BIC is added (in the form that won); repeat until nothing is justified.
6. Honest remainder: when the effects found leave more than ``max_remainder`` of the initial
   error above the noise floor, no vocabulary form explains the data: nothing is named (the
   partial fits are listed as such) and ``unexplained`` says what the residual still correlates
   with and how much is left. ``unexplained`` is also reported (without un-naming) whenever the
   final residual stays clearly above the noise floor.
"""

from __future__ import annotations

import enum
import logging
import math
import os
import time
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from ctrplan.calibration import evidence as ev
from ctrplan.calibration.diagnostics import residual_diagnostics
from ctrplan.calibration.fit import FitResult, Problem
from ctrplan.errors import InputError
from ctrplan.measured import MeasuredData, read_measured
from ctrplan.robot import Robot, load_robot
from ctrplan.shape.effects import (
    EFFECT_NAMES,
    EffectModel,
    effect_form,
    effect_params,
    effect_variants,
    off_values,
)

log = logging.getLogger("ctrplan")

__all__ = ["diagnose", "DiagnoseReport", "DiagnoseStatus", "Step", "split_sweeps"]

#: mean norm of a 3-d Gaussian vector with unit sd per axis: sqrt(8 / pi)
CHI3_MEAN = math.sqrt(8.0 / math.pi)


class DiagnoseStatus(str, enum.Enum):
    FOUND = "found"
    NO_MISSING_EFFECT = "no missing effect"
    AMBIGUOUS = "ambiguous"
    UNEXPLAINED = "unexplained"
    INSUFFICIENT = "insufficient data"


@dataclass
class Candidate:
    """One screened candidate: effect (and form), its BIC change and held-out error (mm)."""

    effect: str
    delta_bic: float
    test_mean_mm: float
    justified: bool
    form: str = ""


@dataclass
class Step:
    """One accepted effect (or the final, rejected screening when ``accepted`` is False)."""

    effect: str | None
    accepted: bool
    parameters: dict[str, dict[str, float]]
    sigma: dict[str, dict[str, float]]
    error_before_mm: float
    error_after_mm: float
    max_before_mm: float
    max_after_mm: float
    delta_bic: float
    heldout_gain: float
    runner_up: str | None
    runner_up_delta_bic: float | None
    ambiguous: bool
    screened: list[Candidate] = field(default_factory=list)
    form: str = ""


@dataclass
class DiagnoseReport:
    """Result of :func:`diagnose`.

    effects : names added, in order ([] = nothing named). parameters : effect -> param ->
    value (joint final fit); sigma : the same, standard uncertainties. error_before_mm /
    error_after_mm : held-out mean tip error of the base / calibrated model (max_*: maximum).
    evidence : the data-only tests before and after; unexplained : what the residual still
    correlates with and how much is left (None when it is at the noise floor); warnings : what
    limits the diagnosis; experiment : what data would support one (when insufficient).
    """

    success: bool
    status: DiagnoseStatus
    conclusion: str
    robot: Robot
    base: str
    effects: list[str]
    parameters: dict[str, dict[str, float]]
    sigma: dict[str, dict[str, float]]
    steps: list[Step]
    error_before_mm: float
    error_after_mm: float
    max_before_mm: float
    max_after_mm: float
    train_sweeps: list[str]
    test_sweeps: list[str]
    diagnostics_before: dict
    diagnostics_after: dict
    settings: dict
    elapsed_s: float
    model_effects: dict[str, dict[str, float]] = field(default_factory=dict)
    forms: dict[str, str] = field(default_factory=dict)
    evidence_before: dict = field(default_factory=dict)
    evidence_after: dict = field(default_factory=dict)
    unexplained: dict | None = None
    warnings: list[str] = field(default_factory=list)
    experiment: list[str] = field(default_factory=list)
    partial: list[str] = field(default_factory=list)
    error_quantiles: dict[str, float] | None = None
    split: dict = field(default_factory=dict)
    learned_residual: dict | None = None
    partial_values: dict = field(default_factory=dict)

    def model(self) -> EffectModel:
        """The calibrated shape model (with its held-out error quantiles)."""
        return EffectModel(self.robot, self.base, self.model_effects,
                           error_quantiles=self.error_quantiles)

    def headline(self) -> str:
        """One line: held-out mean AND max tip error before -> after, each judged honestly."""
        return headline(self.error_before_mm, self.error_after_mm, self.max_before_mm,
                        self.max_after_mm)

    def to_dict(self) -> dict:
        """JSON-ready dict (the report.json fields of docs/conventions.md and more)."""
        from dataclasses import asdict

        steps = [asdict(s) for s in self.steps]
        return {
            "headline": self.headline(),
            "robot": self.robot.name, "base": self.base, "status": self.status.value,
            "conclusion": self.conclusion, "effects": list(self.effects),
            "forms": dict(self.forms),
            "parameters": _params_json(self.parameters, self.sigma, self.robot, self.base),
            "steps": steps, "error_before_mm": self.error_before_mm,
            "error_after_mm": self.error_after_mm, "max_before_mm": self.max_before_mm,
            "max_after_mm": self.max_after_mm, "error_quantiles": self.error_quantiles,
            "unexplained": self.unexplained, "warnings": list(self.warnings),
            "experiment": list(self.experiment), "partial_fits": list(self.partial),
            "partial_values": self.partial_values,
            "learned_residual": self.learned_residual,
            "evidence": {"before": self.evidence_before, "after": self.evidence_after},
            "split": {"train_sweeps": self.train_sweeps, "test_sweeps": self.test_sweeps,
                      **self.split},
            "diagnostics": {"before": self.diagnostics_before, "after": self.diagnostics_after},
            "settings": self.settings, "elapsed_s": self.elapsed_s,
        }


def headline(mb: float, ma: float, xb: float, xa: float) -> str:
    """``Held-out tip error: mean B -> A mm (improved), max B -> A mm (worse)``."""
    def judge(b, a):
        if not (math.isfinite(b) and math.isfinite(a)):
            return "not measured"
        if a < b - 1e-9:
            return "improved"
        if a > b + 1e-9:
            return "worse"
        return "unchanged"

    return (f"Held-out tip error: mean {mb:.3f} -> {ma:.3f} mm ({judge(mb, ma)}), "
            f"max {xb:.3f} -> {xa:.3f} mm ({judge(xb, xa)})")


def _params_json(values, sigma, robot, base) -> dict:
    out: dict = {}
    for e, vals in values.items():
        units = {p.name: p.unit for p in effect_params(e, robot, base)}
        out[e] = {k: {"value": v, "sigma": sigma.get(e, {}).get(k), "unit": units.get(k, "")}
                  for k, v in vals.items()}
    return out


def split_sweeps(data: MeasuredData, holdout: float = 0.25, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Boolean train/test masks holding out whole sweeps (see module docstring)."""
    sw = data.sweeps()
    names = list(dict.fromkeys(sw.tolist()))
    if len(names) < 2:
        blocks = np.minimum((np.arange(len(data)) * 8) // max(len(data), 1), 7)
        test = blocks % 4 == 3
        return ~test, test
    rng = np.random.default_rng(seed)
    k = min(len(names) - 1, max(1, int(round(holdout * len(names)))))
    held = set(rng.choice(np.array(names, dtype=object), size=k, replace=False).tolist())
    test = np.array([s in held for s in sw.tolist()])
    return ~test, test


def _row_ranges(mask: np.ndarray) -> list[str]:
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


def _ordered(data: MeasuredData) -> bool:
    """Rows are in order of motion unless every row is its own sweep (independent samples)."""
    sw = data.sweeps()
    return len(set(sw.tolist())) < max(2, len(sw) // 2)


def diagnose(robot: Robot | str, data: MeasuredData | str | os.PathLike, base: str = "rigid",
             candidates: Sequence[str] | None = None, holdout: float = 0.25, seed: int = 0,
             bic_threshold: float = 10.0, min_gain: float = 0.05, ambiguity_bic: float = 10.0,
             screen_iter: int = 8, fit_iter: int = 25, refit_top: int = 3, max_effects: int = 4,
             max_remainder: float = 0.5, min_configurations: int = 20, nuisances: bool = True,
             learned_residual: bool = True,
             out: str | os.PathLike | None = None) -> DiagnoseReport:
    """Run the workflow (module docstring) and return a :class:`DiagnoseReport`.

    robot : Robot or shipped name / YAML path. data : MeasuredData or measured CSV path.
    base : ``"rigid"`` or ``"compliant"``. candidates : effect names to consider (default all).
    max_remainder : effects are named only when they leave at most this fraction of the
    initial held-out error above the noise floor. nuisances : screen the nuisances outside the
    vocabulary (drift in time, tracker-field distortion). learned_residual : also fit a learned
    residual on top of the calibrated model (reported separately; offered only when it lowers
    the held-out error, see :mod:`ctrplan.calibration.residual`).
    out : when given, write report.json, report.md, plots and calibrated model files there.
    """
    t0 = time.perf_counter()
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
    warnings: list[str] = []
    experiment: list[str] = []
    sw = data.sweeps()
    names = list(dict.fromkeys(sw.tolist()))
    ordered = _ordered(data)
    train, test = split_sweeps(data, holdout, seed)
    if len(names) < 2:
        split = {"method": "contiguous blocks of the single sweep (every 4th of 8 held out)",
                 "test_rows": _row_ranges(test)}
        train_sw = [f"{names[0]} ({', '.join(_row_ranges(train))})"]
        test_sw = [f"{names[0]} ({', '.join(_row_ranges(test))})"]
        warnings.append("one sweep only: the held-out rows are contiguous blocks of the same "
                        "motion, next to training rows, so the held-out error is optimistic; "
                        "record at least 4 separate sweeps")
        experiment.append("record at least 4 separate sweeps (whole sweeps are then held out)")
    else:
        split = {"method": "whole sweeps held out"}
        train_sw = sorted(set(sw[train].tolist()))
        test_sw = sorted(set(sw[test].tolist()))
    prob = Problem(EffectModel(robot, base), data, train, test)
    current: dict[str, dict[str, float]] = {}
    cur = prob.score(current, k=0)
    base_fit = cur
    base_pred = prob.predict_many([current])[0]
    settings = {"holdout": holdout, "seed": seed, "bic_threshold": bic_threshold,
                "min_heldout_gain": min_gain, "ambiguity_bic": ambiguity_bic,
                "max_remainder": max_remainder, "candidates": cands, "rows": len(data),
                "train_rows": int(train.sum()), "test_rows": int(test.sum()),
                "shapes_measured": data.points is not None, "rows_in_order_of_motion": ordered}
    # ---------------------------------------------------------------- evidence and data check
    ev_before = ev.collect(robot, data.q, base_pred[:, -1], data.tip, sw, data.time, ordered)
    noise_sd = ev_before["noise"].get("sd_mm")
    insufficient = _data_check(robot, data, ev_before, base_pred[:, -1], min_configurations)
    hyst = ev_before["hysteresis"]
    if not insufficient and "friction" in cands and not hyst.get("tested"):
        if "no motion" in hyst.get("why", "") or "one way" in hyst.get("why", "") \
                or "not in order" in hyst.get("why", ""):
            cands = [c for c in cands if c != "friction"]
            warnings.append(f"friction not screened: {hyst['why']}")
            experiment.append("move each joint back and forth over the same range (reversals "
                              "reveal friction)")
    settings["candidates"] = list(cands)
    steps: list[Step] = []
    partial: list[str] = []
    nuisance: list[str] = []
    if insufficient:
        reasons, todo = insufficient
        warnings += reasons
        experiment += todo
    else:
        current, cur, nuisance = _select(prob, robot, base, cands, current, cur, steps,
                                         bic_threshold, min_gain, ambiguity_bic, screen_iter,
                                         fit_iter, refit_top, max_effects,
                                         tuple(NUISANCES) if nuisances else ())
    final_pred = prob.predict_many([current])[0]
    ev_after = ev.collect(robot, data.q, final_pred[:, -1], data.tip, sw, data.time, ordered,
                          noise=ev_before["noise"]) if current else ev_before
    effects = [s.effect for s in steps if s.accepted and s.effect not in NUISANCES]
    # ---------------------------------------------------------------- honest remainder
    e_noise = CHI3_MEAN * noise_sd if noise_sd else 0.0
    excess0 = max(base_fit.test_mean - e_noise, 0.0)
    excess1 = max(cur.test_mean - e_noise, 0.0)
    remainder = excess1 / excess0 if excess0 > 0 else 0.0
    if effects and remainder > max_remainder:
        partial = [f"{s.effect} ({s.form})" if s.form else s.effect
                   for s in steps if s.accepted and s.effect not in NUISANCES]
        warnings.append(f"the best fits ({', '.join(partial)}) leave {100 * remainder:.0f} % of "
                        "the held-out error above the noise floor: no effect of the vocabulary "
                        "explains these data, so none is named")
        effects = []
    bounds = _at_bounds(current, robot, base) if current else []
    if bounds:
        warnings.append("parameters at a bound that is not their off value (the effect may be "
                        "larger than its form allows, or another effect is being absorbed): "
                        + ", ".join(bounds))
        if effects:
            partial = partial or [f"{s.effect} ({s.form})" if s.form else s.effect
                                  for s in steps if s.accepted and s.effect not in NUISANCES]
            effects = []
            insufficient = ([f"fitted parameters at their bounds ({', '.join(bounds)})"],
                            ["check the set-up for an effect beyond its physical range (e.g. a "
                             "tracker origin far from the robot base, wrong units or tube "
                             "parameters) and measure over the whole joint range"])
            experiment += insufficient[1]
    partial_values: dict = {}
    if not effects and current:
        # nothing named: the calibrated model is the base model; the fits are only reported
        partial_values = current
        current = {}
        cur = base_fit
        final_pred = base_pred
        ev_after = ev_before
        excess1 = max(cur.test_mean - e_noise, 0.0)
        remainder = excess1 / excess0 if excess0 > 0 else 0.0
    unexplained = None
    if not insufficient and (cur.test_mean > 1.5 * e_noise + 0.05 or remainder > max_remainder) \
            and excess0 > 0:
        unexplained = _unexplained(ev_after, cur.test_mean, e_noise, excess1, remainder)
    if nuisance:
        if unexplained is None:
            unexplained = _unexplained(ev_after, cur.test_mean, e_noise, excess1, remainder)
        unexplained["outside_vocabulary"] = [
            {"kind": k.lstrip("~"), "description": NUISANCES[k],
             "heldout_mean_mm_once_removed": next(s.error_after_mm for s in steps
                                                  if s.effect == k)} for k in nuisance]
        for k in reversed(nuisance):
            if not any(c["with"] == {"~drift": "time", "~field": "position"}[k]
                       for c in unexplained["correlates_with"]):
                unexplained["correlates_with"].insert(0, {
                    "with": {"~drift": "time", "~field": "position"}[k],
                    "description": NUISANCES[k], "r2": None, "p_value": None})
    forms = {s.effect: s.form for s in steps if s.accepted and s.effect in effects and s.form}
    amb = [s for s in steps if s.accepted and s.ambiguous and s.runner_up not in effects
           and s.effect in effects]
    if insufficient:
        status = DiagnoseStatus.INSUFFICIENT
        conclusion = "the data cannot support a diagnosis: " + "; ".join(insufficient[0])
    elif not effects and (partial or nuisance):
        status = DiagnoseStatus.UNEXPLAINED
        conclusion = ("unexplained: no effect of the vocabulary explains the data"
                      + _corr_text(unexplained))
    elif amb:
        status = DiagnoseStatus.AMBIGUOUS
        conclusion = "; ".join(f"ambiguous: {s.effect} or {s.runner_up}" for s in amb)
    elif effects:
        status = DiagnoseStatus.FOUND
        conclusion = "missing effects: " + ", ".join(
            f"{e} ({forms[e]})" if e in forms else e for e in effects)
        if unexplained:
            conclusion += "; unexplained remainder" + _corr_text(unexplained)
    elif unexplained and unexplained.get("correlates_with"):
        status = DiagnoseStatus.UNEXPLAINED
        conclusion = "unexplained: no effect of the vocabulary explains the data" + \
            _corr_text(unexplained)
    else:
        status = DiagnoseStatus.NO_MISSING_EFFECT
        conclusion = "no missing effect"
    last = next((s for s in reversed(steps) if s.accepted and s.effect not in NUISANCES), None)
    if not effects:
        last = None
    err = prob.errors(final_pred)[test]
    quant = {"p50": float(np.percentile(err, 50)), "p95": float(np.percentile(err, 95)),
             "p99": float(np.percentile(err, 99)), "max": float(err.max())} if len(err) else None
    learned = None
    if learned_residual and not insufficient:
        from ctrplan.calibration.residual import learned_residual as _lr

        learned = _lr(robot, data.q, sw, data.tip, final_pred[:, -1], train, test, ordered)
    settings["kernel_calls"] = prob.evals
    settings["noise_sd_mm"] = noise_sd
    rep = DiagnoseReport(
        success=not insufficient, status=status, conclusion=conclusion, robot=robot, base=base,
        effects=effects,
        parameters=last.parameters if last else {}, sigma=last.sigma if last else {},
        steps=steps, error_before_mm=base_fit.test_mean, error_after_mm=cur.test_mean,
        max_before_mm=base_fit.test_max, max_after_mm=cur.test_max,
        train_sweeps=train_sw, test_sweeps=test_sw,
        diagnostics_before=residual_diagnostics(robot, data, base_pred),
        diagnostics_after=residual_diagnostics(robot, data, final_pred),
        settings=settings, elapsed_s=0.0, model_effects=current, forms=forms,
        evidence_before=ev_before, evidence_after=ev_after, unexplained=unexplained,
        warnings=warnings, experiment=experiment, partial=partial, error_quantiles=quant,
        split=split, learned_residual=learned, partial_values=partial_values,
    )
    rep.elapsed_s = time.perf_counter() - t0
    if out is not None:
        from ctrplan.calibration.report import write_report

        write_report(rep, data, out, base_pred=base_pred, final_pred=final_pred, test=test)
    return rep


def _data_check(robot: Robot, data: MeasuredData, evb: dict, pred_tip: np.ndarray,
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


def _at_bounds(effects: dict, robot: Robot, base: str) -> list[str]:
    out = []
    for e, vals in effects.items():
        for p in effect_params(e, robot, base):
            if not p.fit or p.name not in vals:
                continue
            v = vals[p.name]
            tol = 1e-3 * (p.hi - p.lo)
            for b in (p.lo, p.hi):
                if abs(v - b) <= tol and abs(b - p.off) > tol:
                    out.append(f"{e}.{p.name} = {v:.4g} {p.unit} (bound {b:g})")
    return out


def _unexplained(evd: dict, after: float, e_noise: float, excess: float, remainder: float) -> dict:
    corr = []
    labels = {"time": "time (a drift)", "position": "the measured tip position (a field "
              "distortion)", "relative_rotation": "the relative rotation of the tubes",
              "insertion": "insertion", "direction": "the direction of motion"}
    for key, label in labels.items():
        item = evd.get(key) or {}
        if item.get("significant"):
            corr.append({"with": key, "description": label, "r2": item.get("r2"),
                         "p_value": item.get("p_value")})
    if (evd.get("hysteresis") or {}).get("significant") and not any(
            c["with"] == "direction" for c in corr):
        h = evd["hysteresis"]
        corr.append({"with": "direction", "description": labels["direction"],
                     "r2": None, "p_value": h.get("p_value")})
    corr.sort(key=lambda c: -(c["r2"] or 0.0))
    return {"heldout_mean_mm": after, "noise_mean_mm": e_noise, "excess_mean_mm": excess,
            "fraction_of_initial_excess": remainder,
            "residual_rms_mm": evd.get("residual_rms_mm"), "excess_rms_mm": evd.get("excess_rms_mm"),
            "correlates_with": corr}


def _corr_text(unexplained: dict | None) -> str:
    if not unexplained:
        return ""
    c = unexplained.get("correlates_with") or []
    left = f" ({unexplained['excess_mean_mm']:.2f} mm above the noise floor left"
    if c:
        return left + "; it correlates with " + ", ".join(x["with"] for x in c) + ")"
    return left + ")"


#: Nuisances outside the effect vocabulary, screened like effects so that they are never
#: absorbed by a wrong name: a sensor drift growing with time from the first row (quadratic,
#: no constant: a constant offset is registration), and a smooth tracker-field distortion
#: (a cubic polynomial of the measured position; it contains every small rigid transform, so
#: a true registration wins against it only through its far fewer parameters). Accepted nuisances are
#: removed from the data before further screening and reported under ``unexplained``; the
#: calibrated model never contains them.
NUISANCES = {"~drift": "a drift of the sensor in time", "~field": "a distortion of the tracker "
             "field (a smooth function of the measured position)"}


def _nuisance_features(kind: str, prob, data: MeasuredData) -> np.ndarray | None:
    """(B, m, k) features of nuisance ``kind`` at every target point, or None."""
    B, m, _ = prob.target_raw.shape
    if kind == "~drift":
        t = data.time
        if t is None or len(t) < 8 or not np.ptp(t) > 0:
            return None
        x = (np.asarray(t, dtype=float) - np.min(t)) / np.ptp(t)
        f = np.stack([x, x * x], axis=1)
        return np.broadcast_to(f[:, None, :], (B, m, 2)).copy()
    if kind == "~field":
        p = prob.target_raw
        c = p - np.nanmean(p[:, prob.use].reshape(-1, 3), axis=0)
        sc = float(np.nanmax(np.abs(c[:, prob.use])))
        if not sc > 0:
            return None
        c = c / sc
        x, y, z = c[..., 0], c[..., 1], c[..., 2]
        one = np.ones_like(x)
        return np.stack([one, x, y, z, x * x, y * y, z * z, x * y, x * z, y * z,
                         x ** 3, y ** 3, z ** 3, x * x * y, x * x * z, y * y * x, y * y * z,
                         z * z * x, z * z * y, x * y * z], axis=-1)
    return None


def _fit_nuisance(prob, F: np.ndarray, pts: np.ndarray, train: np.ndarray):
    """Least squares of the residual (target - prediction) on features F; returns the
    correction (B, m, 3) and the number of coefficients."""
    use = prob.use
    r = (prob.target - pts)[train][:, use].reshape(-1, 3)
    A = F[train][:, use].reshape(-1, F.shape[-1])
    ok = np.all(np.isfinite(r), axis=1) & np.all(np.isfinite(A), axis=1)
    coef, *_ = np.linalg.lstsq(A[ok], r[ok], rcond=None)
    corr = np.nan_to_num(F) @ coef
    return corr, coef.size


def _select(prob, robot, base, cands, current, cur, steps, bic_threshold, min_gain,
            ambiguity_bic, screen_iter, fit_iter, refit_top, max_effects, nuisances=()):
    """Forward selection over effect forms (module docstring, steps 4-5)."""
    k_cur = 0          # parameters in the model: effects' fitted parameters + nuisance terms
    k_nuis = 0
    free_cur: dict[str, list[str]] = {}
    accepted_nuisances: list[str] = []
    correction = np.zeros_like(prob.target_raw)
    while True:
        remaining = [c for c in cands if c not in current]
        if steps:
            # after the first step, re-screen only the effects that lowered the BIC before
            # (an effect that explained nothing then rarely explains something now; this keeps
            # the workflow's runtime within its budget)
            prev = {c.effect: c.delta_bic for c in steps[-1].screened}
            remaining = [c for c in remaining if prev.get(c, -1.0) < 0.0]
        if (not remaining and len(accepted_nuisances) == len(nuisances)) or \
                len(current) >= max_effects:
            break
        results: dict[tuple[str, str], FitResult] = {}
        frees: dict[tuple[str, str], list[str]] = {}
        for c in remaining:
            for label, fixed_form, names in effect_variants(c, robot, base):
                if not names:
                    continue
                start = {**off_values(c, robot, base), **fixed_form}
                fixed = {**current, c: start}
                key = (c, label)
                frees[key] = names
                # later steps: a short screen (the leading candidates are refitted in full
                # below), since every solve now carries the effects already found
                results[key] = prob.fit(fixed, {c: names},
                                        max_iter=screen_iter if not current else
                                        max(2, screen_iter // 3),
                                        k_total=k_cur + len(names))
        # nuisances outside the vocabulary, fitted on top of the current model
        nuis: dict[str, tuple[FitResult, np.ndarray]] = {}
        if nuisances:
            pts = prob.predict_many([current])[0]
            for kind in nuisances:
                if kind in accepted_nuisances:
                    continue
                F = _nuisance_features(kind, prob, prob.data)
                if F is None:
                    continue
                corr, kk = _fit_nuisance(prob, F, pts, prob.train)
                r = prob.residual(pts + corr, prob.train)
                e = prob.errors(pts + corr)
                nuis[kind] = (FitResult(effects=current, rss=float(r @ r), n_res=r.size,
                                        k=k_cur + kk, test_mean=float(e[prob.test].mean()),
                                        test_max=float(e[prob.test].max())), corr)
        ranked = sorted(results, key=lambda c: results[c].bic())
        # the screen holds the effects already added fixed; the leading candidates are refitted
        # jointly with them (their parameters may have absorbed part of the new effect)
        if current:
            lead = [k for k in ranked if results[k].bic() - cur.bic() < -bic_threshold]
            for key in lead[:refit_top]:
                free = {**free_cur, key[0]: frees[key]}
                joint = prob.fit(results[key].effects, free, max_iter=fit_iter,
                                 k_total=k_nuis + sum(len(v) for v in free.values()))
                if joint.rss <= results[key].rss * (1 + 1e-9):
                    results[key] = joint
                else:
                    results[key].values, results[key].sigma = _fill_values(results[key], free)
        # best form per effect (lowest BIC); forms of one effect never compete as "ambiguous"
        best_form: dict[str, tuple[str, str]] = {}
        for key in ranked:
            best_form.setdefault(key[0], key)
        screened = []
        for c, key in best_form.items():
            r = results[key]
            dbic = r.bic() - cur.bic()
            gain = _gain(cur.test_mean, r.test_mean)
            screened.append(Candidate(c, float(dbic), float(r.test_mean),
                                      bool(dbic < -bic_threshold and gain >= min_gain), key[1]))
        # a justified form of an effect beats an unjustified form with lower BIC
        for c in best_form:
            forms_c = [k for k in ranked if k[0] == c]
            for k in forms_c:
                r = results[k]
                if r.bic() - cur.bic() < -bic_threshold and _gain(cur.test_mean, r.test_mean) >= min_gain:
                    if k != best_form[c]:
                        best_form[c] = k
                        cand = next(s for s in screened if s.effect == c)
                        cand.delta_bic = float(r.bic() - cur.bic())
                        cand.test_mean_mm = float(r.test_mean)
                        cand.justified = True
                        cand.form = k[1]
                    break
        for kind, (r, _) in nuis.items():
            dbic = r.bic() - cur.bic()
            gain = _gain(cur.test_mean, r.test_mean)
            screened.append(Candidate(kind, float(dbic), float(r.test_mean),
                                      bool(dbic < -bic_threshold and gain >= min_gain),
                                      "outside the vocabulary"))
        if not screened:
            break
        screened.sort(key=lambda s: s.delta_bic)
        best = next((s for s in screened if s.justified), screened[0])
        if best.justified and best.effect in nuis:
            r, corr = nuis[best.effect]
            runner = next((s for s in screened if s is not best), None)
            steps.append(Step(best.effect, True, {}, {}, cur.test_mean, r.test_mean,
                              cur.test_max, r.test_max, best.delta_bic,
                              _gain(cur.test_mean, r.test_mean),
                              runner.effect if runner else None,
                              runner.delta_bic if runner else None, False, screened,
                              "outside the vocabulary"))
            log.info("residual follows %s: held-out mean tip error %.3f -> %.3f mm once it is "
                     "removed (not a vocabulary effect)", NUISANCES[best.effect], cur.test_mean,
                     r.test_mean)
            correction = correction + corr
            prob.set_correction(correction)
            accepted_nuisances.append(best.effect)
            k_nuis += r.k - k_cur
            k_cur = r.k
            cur = prob.score(current, k=k_cur)
            continue
        runner = next((s for s in screened if s is not best), None)
        if not best.justified:
            steps.append(Step(None, False, {}, {}, cur.test_mean, cur.test_mean, cur.test_max,
                              cur.test_max, best.delta_bic, _gain(cur.test_mean, best.test_mean_mm),
                              best.effect, None, False, screened))
            break
        key = best_form[best.effect]
        joint = results[key]
        free_new = {**free_cur, best.effect: frees[key]}
        polished = prob.fit(joint.effects, free_new, max_iter=fit_iter,
                            k_total=k_nuis + sum(len(v) for v in free_new.values()))
        if polished.rss <= joint.rss * (1 + 1e-9) and polished.test_mean <= joint.test_mean * 1.05:
            joint = polished
        if not joint.values or best.effect not in joint.values:
            joint.values, joint.sigma = _fill_values(joint, free_new)
        ambiguous = bool(runner is not None and runner.justified
                         and runner.delta_bic - best.delta_bic < ambiguity_bic)
        dbic = joint.bic() - cur.bic()
        form = effect_form(best.effect, joint.effects[best.effect])
        steps.append(Step(best.effect, True, joint.values, joint.sigma, cur.test_mean,
                          joint.test_mean, cur.test_max, joint.test_max, float(dbic),
                          _gain(cur.test_mean, joint.test_mean),
                          runner.effect if runner else None,
                          runner.delta_bic if runner else None, ambiguous, screened, form))
        log.info("added %s%s: held-out mean tip error %.3f -> %.3f mm (dBIC %.1f)", best.effect,
                 f" ({form})" if form else "", cur.test_mean, joint.test_mean, dbic)
        current = joint.effects
        cur = joint
        free_cur = free_new
        k_cur = k_nuis + sum(len(v) for v in free_cur.values())
    prob.set_correction(None)
    return current, prob.score(current, k=k_cur), accepted_nuisances


def _gain(before: float, after: float) -> float:
    if not math.isfinite(before) or before <= 0:
        return 0.0
    return float((before - after) / before)


def _fill_values(fit: FitResult, free: dict[str, list[str]]):
    vals = {e: {k: fit.effects[e][k] for k in names} for e, names in free.items()}
    sig = {e: {k: fit.sigma.get(e, {}).get(k, math.nan) for k in names} for e, names in free.items()}
    return vals, sig
