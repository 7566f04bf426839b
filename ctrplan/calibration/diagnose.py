"""The sim-vs-measured workflow: find where the model and the data disagree, name the missing
effect, add it, and show the gap shrink — and say so when the data cannot tell.

Procedure (:func:`diagnose`). Calibrating (the most accurate physically parameterised model
on data not used to choose it) and naming (which effects the evidence singles out) are two
decisions:

1. Data check: enough distinct configurations, a measurable noise floor below what any effect
   can change, an error the vocabulary can reach at all. Otherwise the report says that the data
   cannot support a diagnosis and what experiment would (status ``insufficient data``).
2. Split (:func:`split_three`): fit / validation / test rows. With ``MIN_SWEEPS_WHOLE`` sweeps
   or more, whole sweeps; with fewer, contiguous blocks of every sweep (named in the report,
   with a warning that they neighbour fit rows). Parameters are fitted on the fit rows, effects
   and forms chosen on the validation rows; the test rows choose nothing and give the reported
   errors. The model is always evaluated on all rows in order (friction depends on the history).
3. Evidence from the data alone (:mod:`ctrplan.calibration.evidence`).
4. Forward selection (:func:`_select`): every form of every candidate effect is fitted alone on
   top of the current model (robust soft-L1 loss, see :meth:`Problem.fit`); the leading ones are
   refitted jointly with the effects already in. A candidate enters the model when it lowers the
   BIC and the validation error by ``keep_gain``; it is *named* only when ``dBIC <
   -bic_threshold``, the validation error drops by ``min_gain`` and by ``MIN_SHARE`` of the base
   model's validation error.
5. Joint model (:func:`_joint`): when step 4 leaves more than ``JOINT_TRIGGER`` times the noise,
   every effect that lowered the BIC in the first screen is fitted jointly (registration,
   precurvature, stiffness, friction and clearance are often uncertain all at once on a real
   robot; one at a time none of them helps), then each is dropped in turn: the drop decides
   whether it stays and whether it is named. The joint model replaces step 4's when it is
   better on validation.
6. The chosen model is refitted on fit + validation rows and written as ``calibrated.yaml``
   whether or not its effects are named (unnamed ones are listed as ``partial``).
7. Nuisances (:func:`_nuisances`), only after the robot: a drift in time and a tracker-field
   distortion, claimed only where the data tell them apart from the robot; never in the model.
8. Honest remainder: when the named effects leave more than ``max_remainder`` of the initial
   validation error above the noise floor, nothing is named and ``unexplained`` says what the
   residual still correlates with and how much is left; ``unexplained`` is also reported
   (without un-naming) whenever the residual stays clearly above the noise floor.
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
    named: bool = True


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
    outliers: dict = field(default_factory=dict)
    nuisance_tests: list = field(default_factory=list)

    def model(self) -> EffectModel:
        """The calibrated shape model with its held-out error quantiles (tip error on the test
        rows) and the error profile along the shaft they imply
        (:func:`ctrplan.shape.error_bounds.extend_tip_bound`: tip bound x arc-length fraction),
        which ``--margin auto`` pads each capsule with."""
        from ctrplan.shape.error_bounds import extend_tip_bound

        prof = extend_tip_bound(self.error_quantiles).to_dict() if self.error_quantiles else None
        return EffectModel(self.robot, self.base, self.model_effects,
                           error_quantiles=self.error_quantiles, error_profile=prof)

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
            "experiment": list(self.experiment), "partial": list(self.partial),
            "partial_fits": list(self.partial),
            "partial_values": self.partial_values,
            "learned_residual": self.learned_residual,
            "evidence": {"before": self.evidence_before, "after": self.evidence_after},
            "split": {"train_sweeps": self.train_sweeps, "test_sweeps": self.test_sweeps,
                      **self.split},
            "diagnostics": {"before": self.diagnostics_before, "after": self.diagnostics_after},
            "test_rows": self.split.get("test_row_ranges", []),
            "max_error_before_mm": self.max_before_mm, "max_error_after_mm": self.max_after_mm,
            "outliers": self.outliers, "nuisance_tests": self.nuisance_tests,
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


def _ordered(data: MeasuredData) -> bool:
    """Rows are in order of motion unless every row is its own sweep (independent samples)."""
    sw = data.sweeps()
    return len(set(sw.tolist())) < max(2, len(sw) // 2)


def diagnose(robot: Robot | str, data: MeasuredData | str | os.PathLike, base: str = "rigid",
             candidates: Sequence[str] | None = None, holdout: float = 0.25, seed: int = 0,
             bic_threshold: float = 10.0, min_gain: float = 0.05, ambiguity_bic: float = 10.0,
             screen_iter: int = 8, fit_iter: int = 25, refit_top: int = 3, max_effects: int = 6,
             max_remainder: float = 0.5, keep_gain: float = 0.02, min_configurations: int = 20, nuisances: bool = True,
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
    fit_rows, val, test = split_three(data, holdout, seed)
    train = fit_rows | val
    if len(names) < MIN_SWEEPS_WHOLE:
        what = "the single sweep" if len(names) < 2 else f"each of the {len(names)} sweeps"
        split = {"method": f"contiguous blocks of {what} (of 8 blocks: 2 and 6 validation, "
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
        split = {"method": "whole sweeps: fit / validation (chooses effects and forms) / test "
                 "(touched by nothing else; reports the errors)"}
        train_sw = sorted(set(sw[train].tolist()))
        test_sw = sorted(set(sw[test].tolist()))
        val_sw = sorted(set(sw[val].tolist()))
    split.update({"test_row_ranges": row_ranges(test), "validation_sweeps": val_sw,
                  "fit_sweeps": sorted(set(sw[fit_rows].tolist()))})
    # selection problem: parameters fitted on the fit rows, effects chosen on validation rows
    prob = Problem(EffectModel(robot, base), data, fit_rows, val)
    current: dict[str, dict[str, float]] = {}
    cur = prob.score(current, k=0)
    base_pred = prob.predict_many([current])[0]
    base_err = prob.errors(base_pred)
    settings = {"holdout": holdout, "seed": seed, "bic_threshold": bic_threshold,
                "min_heldout_gain": min_gain, "keep_gain": keep_gain,
                "ambiguity_bic": ambiguity_bic, "max_remainder": max_remainder,
                "candidates": cands, "rows": len(data), "fit_rows": int(fit_rows.sum()),
                "validation_rows": int(val.sum()), "test_rows": int(test.sum()),
                "train_rows": int(train.sum()),
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
    robust_scale = _robust_scale(noise_sd)
    prob.robust = robust_scale
    settings["robust_loss"] = ({"loss": "soft_l1", "f_scale_mm": robust_scale}
                               if robust_scale else None)
    steps: list[Step] = []
    partial: list[str] = []
    nuisance: list[str] = []
    outside: list[dict] = []
    free: dict[str, list[str]] = {}
    if insufficient:
        reasons, todo = insufficient
        warnings[:0] = reasons
        experiment[:0] = todo          # what the data lack first, the split's advice after
    else:
        current, cur, free = _select(prob, robot, base, cands, current, cur, steps,
                                     bic_threshold, min_gain, keep_gain, ambiguity_bic,
                                     screen_iter, fit_iter, refit_top, max_effects)
    e_noise0 = CHI3_MEAN * noise_sd if noise_sd else 0.0
    if not insufficient and steps and cands and \
            cur.test_mean > JOINT_TRIGGER * e_noise0 + 0.05 and max_effects > 1:
        # the effects one at a time left much more than the noise: effects that are uncertain
        # all at once (registration, precurvature, stiffness, friction, clearance on a real
        # robot) only show jointly; the joint model wins when it lowers the validation error
        greedy_val = cur.test_mean
        joint = _joint(prob, robot, base, cands, steps, bic_threshold, min_gain, keep_gain,
                       fit_iter, max_effects)
        if joint is not None and joint[1].test_mean < greedy_val * (1.0 - keep_gain):
            settings["greedy_steps"] = [
                {"effect": st.effect, "form": st.form, "validation_mean_mm": st.error_after_mm}
                for st in steps if st.accepted]
            greedy_named = {st.effect for st in steps if st.accepted and st.named}
            current, cur, free, steps[:] = joint
            for st in steps:
                # evidence from either test names an effect: alone (one at a time) or
                # dropped from the joint model
                st.named = st.named or st.effect in greedy_named
            warnings.append(f"effects one at a time left {greedy_val:.3f} mm on the validation "
                            f"rows; fitted jointly {cur.test_mean:.3f} mm: the joint model is "
                            "used, each effect judged by dropping it from the joint model")
        settings["joint_model_tried"] = True
    in_model = [s.effect for s in steps if s.accepted]
    named = [s.effect for s in steps if s.accepted and s.named]
    # ---------------------------------------------------------------- final fit (fit + validation)
    final_sigma: dict[str, dict[str, float]] = {}
    if current and free:
        prob_all = Problem(EffectModel(robot, base), data, train, test)
        prob_all.robust = robust_scale
        sel = prob_all.score(current)
        k_all = sum(len(v) for v in free.values())
        refit = prob_all.fit(current, free, max_iter=fit_iter, k_total=k_all)
        if refit.rss <= sel.rss * (1 + 1e-9):
            current = refit.effects
            final_sigma = refit.sigma
        else:
            final_sigma = {e: {k: math.nan for k in names_} for e, names_ in free.items()}
        prob.evals += prob_all.evals
    final_pred = prob.predict_many([current])[0] if current else base_pred
    final_err = prob.errors(final_pred)
    val_before = float(base_err[val].mean())
    val_after = float(final_err[val].mean())
    ev_after = ev.collect(robot, data.q, final_pred[:, -1], data.tip, sw, data.time, ordered,
                          noise=ev_before["noise"]) if current else ev_before
    # ---------------------------------------------------------------- nuisances (robot first)
    if nuisances and not insufficient:
        outside = _nuisances(robot, prob, data, final_pred, fit_rows, val, train, test,
                             min_gain, sw, ordered, base_pred)
        nuisance = [o["kind"] for o in outside if o["claimed"]]
        for o in outside:
            if not o["claimed"]:
                continue
            for e in list(named):
                frac = _explained_by(robot, prob, data, current, e, o["features"], train)
                if frac > FIELD_LIKE:
                    named.remove(e)
                    warnings.append(f"{e} is not named: {100 * frac:.0f} % of what it changes is "
                                    f"also {NUISANCES[o['kind']]}, which the data show is at work")
    # ---------------------------------------------------------------- honest remainder
    e_noise = CHI3_MEAN * noise_sd if noise_sd else 0.0
    excess0 = max(val_before - e_noise, 0.0)
    excess1 = max(val_after - e_noise, 0.0)
    remainder = excess1 / excess0 if excess0 > 0 else 0.0
    effects = list(named)
    if effects and remainder > max_remainder:
        warnings.append(f"the best fits ({', '.join(_labels(steps, in_model))}) leave "
                        f"{100 * remainder:.0f} % of the validation error above the noise floor: "
                        "no effect of the vocabulary explains these data, so none is named "
                        "(the fits stay in the calibrated model)")
        effects = []
    data_insufficient = insufficient
    bounds = _at_bounds(current, robot, base) if current else []
    if bounds:
        warnings.append("parameters at a bound that is not their off value (the effect may be "
                        "larger than its form allows, or another effect is being absorbed): "
                        + ", ".join(bounds))
        if effects:
            effects = []
            insufficient = ([f"fitted parameters at their bounds ({', '.join(bounds)})"],
                            ["check the set-up for an effect beyond its physical range (e.g. a "
                             "tracker origin far from the robot base, wrong units or tube "
                             "parameters) and measure over the whole joint range"])
            experiment += insufficient[1]
    partial = _labels(steps, [e for e in in_model if e not in effects])
    partial_values = {e: dict(current[e]) for e in in_model if e not in effects and e in current}
    test_before = float(base_err[test].mean())
    test_after = float(final_err[test].mean())
    max_before = float(base_err[test].max())
    max_after = float(final_err[test].max())
    unexplained = None
    if not data_insufficient and (val_after > 1.5 * e_noise + 0.05 or remainder > max_remainder) \
            and excess0 > 0:
        unexplained = _unexplained(ev_after, test_after, e_noise,
                                   max(test_after - e_noise, 0.0), remainder)
    if nuisance:
        if unexplained is None:
            unexplained = _unexplained(ev_after, test_after, e_noise,
                                       max(test_after - e_noise, 0.0), remainder)
        unexplained["outside_vocabulary"] = [
            {"kind": o["kind"].lstrip("~"), "description": NUISANCES[o["kind"]],
             "heldout_mean_mm_once_removed": o["test_mean_with_mm"],
             "heldout_max_mm_once_removed": o["test_max_with_mm"],
             "robot_model_heldout_mean_mm": test_after,
             "distinguishable": o["why"]} for o in outside if o["claimed"]]
        for k in reversed(nuisance):
            w = {"~drift": "time", "~field": "position"}[k]
            if not any(c["with"] == w for c in unexplained["correlates_with"]):
                unexplained["correlates_with"].insert(0, {
                    "with": w, "description": NUISANCES[k], "r2": None, "p_value": None})
    forms = {s.effect: s.form for s in steps if s.accepted and s.effect in effects and s.form}
    amb = [s for s in steps if s.accepted and s.ambiguous and s.runner_up not in effects
           and s.effect in effects]
    if insufficient:
        status = DiagnoseStatus.INSUFFICIENT
        conclusion = "the data cannot support a diagnosis: " + "; ".join(insufficient[0])
    elif amb:
        status = DiagnoseStatus.AMBIGUOUS
        conclusion = "; ".join(f"ambiguous: {s.effect} or {s.runner_up}" for s in amb)
    elif effects:
        status = DiagnoseStatus.FOUND
        conclusion = "missing effects: " + ", ".join(
            f"{e} ({forms[e]})" if e in forms else e for e in effects)
        if unexplained:
            conclusion += "; unexplained remainder" + _corr_text(unexplained)
    elif unexplained is not None:
        status = DiagnoseStatus.UNEXPLAINED
        conclusion = ("unexplained: no effect of the vocabulary explains the data"
                      + _corr_text(unexplained))
    else:
        status = DiagnoseStatus.NO_MISSING_EFFECT
        conclusion = "no missing effect"
    if partial and not insufficient:
        warnings.append("kept in the calibrated model without being named (they lower the "
                        "validation error, but the evidence does not single them out): "
                        + ", ".join(partial))
    outliers = _outliers(final_err, train, e_noise)
    if outliers["rows"]:
        warnings.append(f"{len(outliers['rows'])} row(s) far from the model (more than "
                        f"{outliers['threshold_mm']:.2f} mm) were down-weighted by the robust "
                        f"loss: {', '.join(str(r) for r in outliers['rows'][:10])}"
                        + (" ..." if len(outliers["rows"]) > 10 else ""))
    err = final_err[test]
    quant = {"p50": float(np.percentile(err, 50)), "p95": float(np.percentile(err, 95)),
             "p99": float(np.percentile(err, 99)), "max": float(err.max())} if len(err) else None
    learned = None
    if learned_residual and not insufficient:
        from ctrplan.calibration.residual import learned_residual as _lr

        learned = _lr(robot, data.q, sw, data.tip, final_pred[:, -1], train, test, ordered)
    settings["kernel_calls"] = prob.evals
    settings["noise_sd_mm"] = noise_sd
    split["validation_error_before_mm"] = val_before
    split["validation_error_after_mm"] = val_after
    params = {e: {k: current[e][k] for k in free.get(e, [])} for e in effects}
    sig = {e: {k: final_sigma.get(e, {}).get(k, math.nan) for k in free.get(e, [])}
           for e in effects}
    rep = DiagnoseReport(
        success=not insufficient, status=status, conclusion=conclusion, robot=robot, base=base,
        effects=effects, parameters=params, sigma=sig,
        steps=steps, error_before_mm=test_before, error_after_mm=test_after,
        max_before_mm=max_before, max_after_mm=max_after,
        train_sweeps=train_sw, test_sweeps=test_sw,
        diagnostics_before=residual_diagnostics(robot, data, base_pred),
        diagnostics_after=residual_diagnostics(robot, data, final_pred),
        settings=settings, elapsed_s=0.0, model_effects=current,
        forms=forms, evidence_before=ev_before, evidence_after=ev_after,
        unexplained=unexplained, warnings=warnings, experiment=experiment, partial=partial,
        error_quantiles=quant, split=split, learned_residual=learned,
        partial_values=partial_values, outliers=outliers,
        nuisance_tests=[{k: v for k, v in o.items() if k != "features"} for o in outside],
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


#: Nuisances outside the effect vocabulary, tested only AFTER the robot model is fitted (so they
#: never absorb the robot's own effects): a sensor drift in time (quadratic) and a smooth
#: tracker-field distortion (a quadratic function of the measured tip position, ridge
#: penalised). One is claimed only where the data tell it apart from the robot: on the
#: validation rows, the nuisance's features must explain the robot model's residual clearly
#: better (by ``DISTINGUISH``) than smooth features of the configuration
#: (harmonics of the relative rotations, insertions, direction of motion) - a field gives the
#: same correction wherever the tip is, however it got there; a robot effect does not. The
#: calibrated model never contains a nuisance; a named effect whose change to the tips is itself
#: mostly (``FIELD_LIKE``) such a function of the claimed nuisance is no longer named.
NUISANCES = {"~drift": "a drift of the sensor in time", "~field": "a distortion of the tracker "
             "field (a smooth function of the measured position)"}
DISTINGUISH = 0.9
FIELD_LIKE = 0.8
RIDGE = 1e-2


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
        x = (np.asarray(t, dtype=float) - np.min(t)) / np.ptp(t)
        return np.stack([np.ones_like(x), x, x * x], axis=1)
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
    b = q[:, n:]
    b = (b - b[rows].mean(0)) / np.maximum(np.ptp(b[rows], axis=0), 1e-9)
    cols += list(b.T)
    if ordered:
        d = direction_from_rows(q, sw).astype(float)[:, :n]
        cols += list(d.T)
    return _standardise(np.stack(cols, axis=1), rows)


def _ridge(F: np.ndarray, R: np.ndarray, rows: np.ndarray) -> np.ndarray:
    A = F[rows]
    ok = np.all(np.isfinite(A), axis=1) & np.all(np.isfinite(R[rows]), axis=1)
    A = A[ok]
    lam = RIDGE * len(A)
    coef = np.linalg.solve(A.T @ A + lam * np.eye(A.shape[1]), A.T @ R[rows][ok])
    return np.nan_to_num(F) @ coef


def _distinguish(F: np.ndarray, G: np.ndarray, r: np.ndarray, fit_rows: np.ndarray,
                 val: np.ndarray) -> tuple[float, float, float]:
    """Validation mean |r| as is, after a ridge fit on nuisance features F, after one on
    configuration features G (both fitted on ``fit_rows``)."""
    def mean(x):
        return float(np.linalg.norm(x[val], axis=1).mean())

    return mean(r), mean(r - _ridge(F, r, fit_rows)), mean(r - _ridge(G, r, fit_rows))


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

    out = []
    # the nuisance that explains most is tested first, the next on what it leaves
    order = sorted(feats, key=lambda k: mean(r - _ridge(feats[k], r, fit_rows), val))
    for kind in order:
        F = feats[kind]
        rm = r
        if kind == "~field":
            # its affine part (in the measured position) is registration / tracker scale: the
            # field must explain what an affine map leaves
            rm = r - _ridge(F[:, :4], r, fit_rows)
        e_model, e_nuis, e_conf = _distinguish(F, G, rm, fit_rows, val)
        b_model, b_nuis, b_conf = _distinguish(F, G, r0, fit_rows, val)
        gain = _gain(e_model, e_nuis)
        on_model = bool(gain >= 2 * min_gain and e_nuis <= DISTINGUISH * e_conf)
        on_base = bool(_gain(b_model, b_nuis) >= 2 * min_gain and b_nuis <= DISTINGUISH * b_conf)
        claimed = on_model or on_base
        corr = _ridge(F, r, train)                 # fitted on fit + validation rows
        left = r - corr
        why = (f"calibrated model's residual: validation mean {e_model:.3f} mm -> {e_nuis:.3f} "
               f"mm with it, {e_conf:.3f} mm with configuration features instead; base model "
               f"after an affine map: {b_model:.3f} -> {b_nuis:.3f} mm, {b_conf:.3f} mm")
        out.append({"kind": kind, "claimed": claimed, "why": why, "validation_gain": gain,
                    "validation_mean_with_mm": e_nuis, "validation_mean_config_mm": e_conf,
                    "base_validation_mean_with_mm": b_nuis,
                    "base_validation_mean_config_mm": b_conf,
                    "test_mean_with_mm": mean(left, test),
                    "test_max_with_mm": float(np.linalg.norm(left[test], axis=1).max()),
                    # what a named effect must not mostly be: the nonconstant terms of a drift,
                    # the nonlinear terms of a field
                    "features": F[:, 1:] if kind == "~drift" else F[:, 4:]})
        if claimed:
            r = left
            r0 = r0 - _ridge(F, r0, train)
    return out


def _explained_by(robot, prob, data, current, effect, F, rows) -> float:
    """Fraction of what ``effect`` changes at the tips (sum of squares over ``rows``) that a
    least-squares function of the nuisance features F reproduces."""
    without = {k: v for k, v in current.items() if k != effect}
    a, b = prob.predict_many([current, without])
    d = a[:, -1] - b[:, -1]
    d = np.where(np.isfinite(d), d, 0.0)
    ss = float((d[rows] ** 2).sum())
    if ss <= 0:
        return 0.0
    coef, *_ = np.linalg.lstsq(F[rows], d[rows], rcond=None)
    left = d[rows] - F[rows] @ coef
    return float(1.0 - (left ** 2).sum() / ss)


def _select(prob, robot, base, cands, current, cur, steps, bic_threshold, min_gain, keep_gain,
            ambiguity_bic, screen_iter, fit_iter, refit_top, max_effects):
    """Forward selection over effect forms (module docstring, steps 4-6).

    Parameters are fitted on the fit rows (``prob.train``), effects and forms chosen on the
    validation rows (``prob.test``). A candidate enters the model when it lowers the BIC and the
    validation mean error by at least ``keep_gain``; it is marked ``named`` (evidence enough to
    name it) only with ``dBIC < -bic_threshold`` and a validation gain of at least ``min_gain``.
    Returns the effects, their score and the fitted parameter names per effect.
    """
    free_cur: dict[str, list[str]] = {}
    base_val = cur.test_mean
    while len(current) < max_effects:
        remaining = [c for c in cands if c not in current]
        if steps:
            # after the first step, re-screen only the effects that lowered the BIC before
            # (an effect that explained nothing then rarely explains something now; this keeps
            # the workflow's runtime within its budget)
            prev = {c.effect: c.delta_bic for c in steps[-1].screened}
            remaining = [c for c in remaining if prev.get(c, -1.0) < 0.0]
        if not remaining:
            break
        k_cur = sum(len(v) for v in free_cur.values())
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
        ranked = sorted(results, key=lambda c: results[c].bic())
        if not current and ("registration", "") in results:
            # registration is part of the base on a real set-up (the tracker frame is rarely
            # known): shares are of the error a registered base leaves
            base_val = min(base_val, results[("registration", "")].test_mean)
        # the screen holds the effects already added fixed; the leading candidates are refitted
        # jointly with them (their parameters may have absorbed part of the new effect)
        if current:
            lead = [k for k in ranked if results[k].bic() - cur.bic() < 0.0
                    and _gain(cur.test_mean, results[k].test_mean) > -0.5]
            for key in lead[:refit_top]:
                free = {**free_cur, key[0]: frees[key]}
                joint = prob.fit(results[key].effects, free, max_iter=fit_iter,
                                 k_total=sum(len(v) for v in free.values()))
                if joint.rss <= results[key].rss * (1 + 1e-9):
                    results[key] = joint
                else:
                    results[key].values, results[key].sigma = _fill_values(results[key], free)
            ranked = sorted(results, key=lambda c: results[c].bic())

        def named_grade(r: FitResult, cur: FitResult = cur, ref: float = base_val) -> bool:
            return bool(r.bic() - cur.bic() < -bic_threshold
                        and _gain(cur.test_mean, r.test_mean) >= min_gain
                        and cur.test_mean - r.test_mean >= MIN_SHARE * ref)

        def keep_grade(r: FitResult, cur: FitResult = cur) -> bool:
            return bool(r.bic() - cur.bic() < 0.0 and _gain(cur.test_mean, r.test_mean) >= keep_gain)

        # best form per effect: a named-grade form with the lowest BIC, else the kept form with
        # the lowest validation error, else the lowest BIC; forms never compete as "ambiguous"
        best_form: dict[str, tuple[str, str]] = {}
        for c in dict.fromkeys(k[0] for k in ranked):
            forms_c = [k for k in ranked if k[0] == c]
            good = [k for k in forms_c if named_grade(results[k])]
            kept = sorted((k for k in forms_c if keep_grade(results[k])),
                          key=lambda k: results[k].test_mean)
            best_form[c] = good[0] if good else (kept[0] if kept else forms_c[0])
        screened = []
        for c, key in best_form.items():
            r = results[key]
            screened.append(Candidate(c, float(r.bic() - cur.bic()), float(r.test_mean),
                                      named_grade(r), key[1]))
        if not screened:
            break
        screened.sort(key=lambda s: s.delta_bic)
        justified = [s for s in screened if s.justified]
        kept = sorted((s for s in screened if keep_grade(results[best_form[s.effect]])),
                      key=lambda s: s.test_mean_mm)
        best = justified[0] if justified else (kept[0] if kept else screened[0])
        runner = next((s for s in screened if s is not best), None)
        if not (best.justified or kept):
            steps.append(Step(None, False, {}, {}, cur.test_mean, cur.test_mean, cur.test_max,
                              cur.test_max, best.delta_bic, _gain(cur.test_mean, best.test_mean_mm),
                              best.effect, None, False, screened))
            break
        key = best_form[best.effect]
        joint = results[key]
        free_new = {**free_cur, best.effect: frees[key]}
        polished = prob.fit(joint.effects, free_new, max_iter=fit_iter,
                            k_total=sum(len(v) for v in free_new.values()))
        if polished.rss <= joint.rss * (1 + 1e-9) and polished.test_mean <= joint.test_mean * 1.05:
            joint = polished
        if not joint.values or best.effect not in joint.values:
            joint.values, joint.sigma = _fill_values(joint, free_new)
        ambiguous = bool(best.justified and runner is not None and runner.justified
                         and runner.delta_bic - best.delta_bic < ambiguity_bic)
        dbic = joint.bic() - cur.bic()
        form = effect_form(best.effect, joint.effects[best.effect])
        steps.append(Step(best.effect, True, joint.values, joint.sigma, cur.test_mean,
                          joint.test_mean, cur.test_max, joint.test_max, float(dbic),
                          _gain(cur.test_mean, joint.test_mean),
                          runner.effect if runner else None,
                          runner.delta_bic if runner else None, ambiguous, screened, form,
                          named=bool(best.justified)))
        log.info("added %s%s%s: validation mean tip error %.3f -> %.3f mm (dBIC %.1f)",
                 best.effect, f" ({form})" if form else "",
                 "" if best.justified else " (kept, not named)", cur.test_mean,
                 joint.test_mean, dbic)
        current = joint.effects
        cur = joint
        free_cur = free_new
    return current, cur, free_cur


#: the joint model is tried when the one-at-a-time effects leave more than this many times the
#: noise floor's mean tip error on the validation rows
JOINT_TRIGGER = 3.0
#: an effect is named only when it accounts for at least this share of the base model's
#: validation mean error (of the registered base's, when registration alone lowers it; smaller
#: refinements stay in the model, listed as partial)
MIN_SHARE = 0.15
#: effects that switch to a slower kernel (loaded / torsionally compliant): never in the joint
#: model (it is compared with the one-at-a-time model, which may hold them)
SLOW = ("load", "torsion")


def _joint(prob, robot, base, cands, steps, bic_threshold, min_gain, keep_gain, fit_iter,
           max_effects):
    """Every effect that lowered the BIC in the first screen, in its best screened form
    (clearance with both harmonics), fitted jointly; then each effect dropped in turn (the rest
    refitted briefly): effects whose removal does not raise the validation error by
    ``keep_gain`` leave the model; an effect is named when its removal raises the BIC by more
    than ``bic_threshold`` and its presence cuts the validation error by ``min_gain``.
    Returns (effects, score, fitted names, steps) or None."""
    first = {c.effect: c for c in steps[0].screened} if steps[0].screened else {}
    for st in steps:
        if st.accepted:
            first.setdefault(st.effect, Candidate(st.effect, st.delta_bic, st.error_after_mm,
                                                  st.named, st.form))
    chosen = sorted((c for c in first.values() if c.delta_bic < 0.0 and c.effect in cands
                     and c.effect not in SLOW),
                    key=lambda c: c.delta_bic)[:max_effects]
    if len(chosen) < 2:
        return None
    fixed: dict[str, dict[str, float]] = {}
    free: dict[str, list[str]] = {}
    forms: dict[str, str] = {}
    for c in chosen:
        variants = {lab: (fx, nm) for lab, fx, nm in effect_variants(c.effect, robot, base)}
        lab = "harmonic2" if c.effect == "clearance" and "harmonic2" in variants else c.form
        if lab not in variants:
            lab = next(iter(variants))
        fx, nm = variants[lab]
        fixed[c.effect] = {**off_values(c.effect, robot, base), **fx}
        free[c.effect] = list(nm)
        forms[c.effect] = lab
    k_all = sum(len(v) for v in free.values())
    base_val = prob.score({}).test_mean
    reg = first.get("registration")
    if reg is not None and steps[0].screened and reg.test_mean_mm > 0:
        base_val = min(base_val, reg.test_mean_mm)
    full = prob.fit(fixed, free, max_iter=2 * fit_iter, k_total=k_all)
    drops: dict[str, FitResult] = {}
    for e in free:
        fx = {k: v for k, v in full.effects.items() if k != e}
        fr = {k: v for k, v in free.items() if k != e}
        drops[e] = prob.fit(fx, fr, max_iter=max(4, fit_iter // 3),
                            k_total=k_all - len(free[e]))
    keep = [e for e in free if drops[e].test_mean > full.test_mean * (1.0 + keep_gain)]
    model, mfree = full, free
    if keep and len(keep) < len(free):
        kf = {e: free[e] for e in keep}
        reduced = prob.fit({e: full.effects[e] for e in keep}, kf, max_iter=fit_iter,
                           k_total=sum(len(v) for v in kf.values()))
        if reduced.test_mean <= full.test_mean:
            model, mfree = reduced, kf
    out_steps = []
    for e in mfree:
        d = drops[e]
        dbic = float(model.bic() - d.bic())
        gain = _gain(d.test_mean, model.test_mean)
        named = bool(dbic < -bic_threshold and gain >= min_gain
                     and d.test_mean - model.test_mean >= MIN_SHARE * base_val)
        vals = {e: {k: model.effects[e][k] for k in mfree[e]}}
        sig = {e: {k: model.sigma.get(e, {}).get(k, math.nan) for k in mfree[e]}}
        out_steps.append(Step(e, True, vals, sig, float(d.test_mean), float(model.test_mean),
                              float(d.test_max), float(model.test_max), dbic, gain, None, None,
                              False, [], effect_form(e, model.effects[e]) or "", named=named))
    out_steps.sort(key=lambda st: st.delta_bic)
    return model.effects, model, mfree, out_steps


def _labels(steps: list[Step], effects: Sequence[str]) -> list[str]:
    """``effect (form)`` labels of accepted steps, in the order they were added."""
    return [f"{s.effect} ({s.form})" if s.form else s.effect
            for s in steps if s.accepted and s.effect in effects]


def _robust_scale(noise_sd: float | None) -> float | None:
    """The robust loss's smallest scale (mm per coordinate): 3 noise sd (see Problem.fit)."""
    if noise_sd is None or not math.isfinite(noise_sd):
        return None
    return max(3.0 * float(noise_sd), 0.05)


def _outliers(err: np.ndarray, rows: np.ndarray, e_noise: float) -> dict:
    """Rows (1-based) of the fit/validation data far from the calibrated model: error above the
    median + 6 robust sd (and above 5x the noise mean); the robust loss down-weighted them."""
    e = err[rows]
    med = float(np.median(e))
    mad = float(np.median(np.abs(e - med))) * 1.4826
    thr = max(med + 6.0 * mad, 5.0 * e_noise, 1e-9)
    idx = np.nonzero(rows & (err > thr))[0]
    return {"threshold_mm": thr, "rows": [int(i) + 1 for i in idx],
            "method": "tip error above median + 6 robust sd of the fit/validation rows; "
                      "down-weighted by the soft-L1 loss, not removed"}


def _gain(before: float, after: float) -> float:
    if not math.isfinite(before) or before <= 0:
        return 0.0
    return float((before - after) / before)


def _fill_values(fit: FitResult, free: dict[str, list[str]]):
    vals = {e: {k: fit.effects[e][k] for k in names} for e, names in free.items()}
    sig = {e: {k: fit.sigma.get(e, {}).get(k, math.nan) for k in names} for e, names in free.items()}
    return vals, sig
