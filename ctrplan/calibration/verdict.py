"""Stage 5 of the calibration pipeline: the conclusion, before the report is written.

What is named and with what status (:func:`conclude`): the honest remainder (named effects that
leave more than ``max_remainder`` of the initial validation error above the noise floor are not
named), parameters at a bound, the unexplained remainder and what it correlates with, the
held-out (test-row) errors and their quantiles, rows far from the model.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ctrplan.calibration.evidence import CHI3_MEAN
from ctrplan.calibration.fit import FinalFit
from ctrplan.calibration.nuisance import NUISANCES, Nuisances
from ctrplan.calibration.result import DiagnoseStatus
from ctrplan.calibration.select import TAIL_PERCENTILE, Selection, at_bounds, labels
from ctrplan.robot import Robot

#: Mean tip error (mm) above the noise floor that is no evidence of a remainder on its own: the
#: tolerance of the noise-floor check, and the least initial excess for which "the calibrated
#: model left too much of it" means anything (a nominal model that already fits the data leaves
#: all of a zero excess).
TOLERANCE_MM = 0.05


@dataclass(frozen=True)
class Errors:
    """Validation and test (held-out) tip errors (mm) of the base and the calibrated model, the
    noise floor's mean tip error and the remainder (fraction of the initial validation excess
    over the noise floor left by the calibrated model)."""

    val_before: float
    val_after: float
    test_before: float
    test_after: float
    max_before: float
    max_after: float
    e_noise: float
    excess0: float
    remainder: float
    #: (T,) the base model's and the reported (cross-fitted) tip error on the test rows (mm)
    base_test: np.ndarray = field(default_factory=lambda: np.zeros(0))
    after_test: np.ndarray = field(default_factory=lambda: np.zeros(0))


@dataclass(frozen=True)
class Verdict:
    """The conclusion: status and its sentence, the named effects (with forms, fitted values
    and sigma), the partial ones, the unexplained remainder, the errors, quantiles of the
    test-row tip error, outliers, and the warnings / experiments this stage adds."""

    status: DiagnoseStatus
    conclusion: str
    effects: list[str]
    forms: dict[str, str]
    parameters: dict[str, dict[str, float]]
    sigma: dict[str, dict[str, float]]
    partial: list[str]
    partial_values: dict
    unexplained: dict | None
    errors: Errors
    quantiles: dict[str, float] | None
    outliers: dict
    insufficient: bool
    warnings: tuple[str, ...] = ()
    experiment: tuple[str, ...] = ()
    #: quantiles of the base model's test-row tip error (as ``quantiles``)
    quantiles_before: dict[str, float] | None = None


@dataclass(frozen=True)
class HeldoutChoice:
    """Whether the fitted model or the base model is the default output, decided on the test
    rows (:func:`heldout_choice`): ``output`` ``"fit"`` or ``"base"``, ``err`` (B,) the
    output's tip error (the reported held-out error), ``info`` report.json
    ``heldout_comparison``."""

    output: str
    err: np.ndarray
    info: dict


def _no_worse(fit_e: np.ndarray, base_e: np.ndarray) -> bool:
    """The fitted model is no worse than the base on these rows: mean AND p99."""
    if not len(fit_e):
        return True
    return bool(fit_e.mean() <= base_e.mean() and np.percentile(fit_e, TAIL_PERCENTILE)
                <= np.percentile(base_e, TAIL_PERCENTILE))


def heldout_choice(base_err: np.ndarray, fit_err: np.ndarray, test: np.ndarray,
                   units: np.ndarray, glitch: np.ndarray | None = None) -> HeldoutChoice:
    """Never worse than the base on the held-out rows: the fitted model is the default output
    when its test-row mean AND p99 tip error are no worse than the base model's, otherwise the
    base model is (a choice between two fixed models, the fit's parameters and effects having
    been chosen without these rows; the report gives both models' numbers). The same rule on
    each of two folds of the test units (sweeps or blocks, alternating; one unit: its halves)
    says whether the choice holds across them (``stable``); where it does not, the warnings
    say so. ``glitch`` (B,) bool: rows whose measurement jumped, left out of the comparison
    (not of the reported errors): a tracker glitch of several mm sets the p99 of either model,
    at random."""
    full = np.flatnonzero(test)
    if glitch is not None:
        test = test & ~glitch
    idx = np.flatnonzero(test)
    u = np.asarray(units)[idx]
    names = list(dict.fromkeys(u.tolist()))
    if len(names) >= 2:
        fold = np.array([names.index(x) % 2 for x in u.tolist()])
    else:
        fold = (np.arange(len(idx)) >= len(idx) // 2).astype(int)
    fe, be = fit_err[idx], base_err[idx]
    per_fold = ["fit" if _no_worse(fe[fold == f], be[fold == f]) else "base" for f in (0, 1)]
    output = "fit" if _no_worse(fe, be) else "base"
    err = np.array(fit_err if output == "fit" else base_err, dtype=float)
    info = {"rule": f"the fitted model is the default output when its test-row mean and "
                    f"p{TAIL_PERCENTILE:g} tip error are no worse than the base model's",
            "output": output, "per_fold": per_fold, "stable": per_fold[0] == per_fold[1],
            "folds": [idx[fold == f].tolist() for f in (0, 1)],
            "glitch_rows_left_out": [int(i) + 1 for i in sorted(set(full) - set(idx))],
            "base": _summary(be), "fit": _summary(fe)}
    return HeldoutChoice(output, err, info)


def _summary(e: np.ndarray) -> dict:
    if not len(e):
        return {"mean_mm": None, "p99_mm": None, "max_mm": None}
    return {"mean_mm": float(e.mean()), "p99_mm": float(np.percentile(e, TAIL_PERCENTILE)),
            "max_mm": float(e.max())}


def errors(base_err: np.ndarray, fit: FinalFit, val: np.ndarray, test: np.ndarray,
           noise_sd: float | None, test_err: np.ndarray | None = None) -> Errors:
    """The :class:`Errors` of the base model (``base_err``, (B,) mm) and the final fit
    (``test_err``: the test rows' errors to report, default the fit's own)."""
    e_noise = CHI3_MEAN * noise_sd if noise_sd else 0.0
    val_before = float(base_err[val].mean())
    val_after = float(fit.err[val].mean())
    excess0 = max(val_before - e_noise, 0.0)
    excess1 = max(val_after - e_noise, 0.0)
    remainder = excess1 / excess0 if excess0 > 0 else 0.0
    te = (fit.err if test_err is None else test_err)[test]
    return Errors(val_before, val_after, float(base_err[test].mean()), float(te.mean()),
                  float(base_err[test].max()), float(te.max()), e_noise, excess0,
                  remainder, base_err[test], te)


def conclude(robot: Robot, base: str, sel: Selection, nuis: Nuisances, fit: FinalFit,
             err: Errors, ev_after: dict, insufficient, max_remainder: float, train: np.ndarray,
             test: np.ndarray) -> Verdict:
    """Name (or not) the effects the selection kept (module docstring). ``insufficient``:
    (reasons, experiments) from the data check, or None."""
    warnings: list[str] = []
    experiment: list[str] = []
    effects = list(nuis.named)
    if effects and err.remainder > max_remainder:
        warnings.append(f"the best fits ({', '.join(labels(sel.steps, sel.in_model))}) leave "
                        f"{100 * err.remainder:.0f} % of the validation error above the noise "
                        "floor: no effect of the vocabulary explains these data, so none is "
                        "named (the fits stay in the calibrated model)")
        effects = []
    data_insufficient = insufficient
    bounds = at_bounds(fit.effects, robot, base) if fit.effects else []
    if bounds:
        warnings.append("parameters at a bound that is not their off value (the effect may be "
                        "larger than its form allows, or another effect is being absorbed): "
                        + ", ".join(bounds))
        # only a named effect at a bound makes the diagnosis unsupported (unnamed effects at a
        # bound left the model before the final fit: select.drop_partials_at_bounds)
        if at_bounds({e: fit.effects[e] for e in effects if e in fit.effects}, robot, base):
            effects = []
            insufficient = ([f"fitted parameters at their bounds ({', '.join(bounds)})"],
                            ["check the set-up for an effect beyond its physical range (e.g. a "
                             "tracker origin far from the robot base, wrong units or tube "
                             "parameters) and measure over the whole joint range"])
            experiment += insufficient[1]
    partial = labels(sel.steps, [e for e in sel.in_model if e not in effects])
    partial_values = {e: dict(fit.effects[e]) for e in sel.in_model
                      if e not in effects and e in fit.effects}
    unexplained = _remainder(ev_after, err, nuis, max_remainder, data_insufficient)
    forms = {s.effect: s.form for s in sel.steps if s.accepted and s.effect in effects and s.form}
    status, conclusion = _status(sel, effects, forms, unexplained, insufficient)
    if partial and not insufficient:
        warnings.append("kept in the calibrated model without being named (they lower the "
                        "validation error, but the evidence does not single them out): "
                        + ", ".join(partial))
    outliers = _outliers(fit.err, train, err.e_noise)
    if outliers["rows"]:
        warnings.append(f"{len(outliers['rows'])} row(s) far from the model (more than "
                        f"{outliers['threshold_mm']:.2f} mm) were down-weighted by the robust "
                        f"loss: {', '.join(str(r) for r in outliers['rows'][:10])}"
                        + (" ..." if len(outliers["rows"]) > 10 else ""))
    quant, quant_before = quantiles(err.after_test), quantiles(err.base_test)
    warnings += tail_warnings(quant_before, quant)
    params = {e: {k: fit.effects[e][k] for k in sel.free.get(e, [])} for e in effects}
    sig = {e: {k: fit.sigma.get(e, {}).get(k, np.nan) for k in sel.free.get(e, [])}
           for e in effects}
    return Verdict(status, conclusion, effects, forms, params, sig, partial, partial_values,
                   unexplained, err, quant, outliers, bool(insufficient), tuple(warnings),
                   tuple(experiment), quant_before)


def quantiles(e: np.ndarray) -> dict[str, float] | None:
    """p50 / p95 / p99 / max of tip errors (mm), or None for no rows."""
    if not len(e):
        return None
    return {"p50": float(np.percentile(e, 50)), "p95": float(np.percentile(e, 95)),
            "p99": float(np.percentile(e, 99)), "max": float(e.max())}


def tail_warnings(before: dict | None, after: dict | None) -> list[str]:
    """A warning when the default output's test-row maximum tip error is above the base
    model's (the tail rule judges the mean and the p99; one row sets the maximum)."""
    if not before or not after or not after["max"] > before["max"] + 1e-9:
        return []
    return [f"the largest test-row tip error is worse than the base model's ({before['max']:.3f} "
            f"-> {after['max']:.3f} mm) while the mean and p99 are not: one row sets it; check "
            "that row (a tracker glitch?) before planning with a margin below it"]


def _remainder(ev_after: dict, err: Errors, nuis: Nuisances, max_remainder: float,
               data_insufficient) -> dict | None:
    """The unexplained remainder (None when the residual is at the noise floor), with the
    claimed nuisances as what it follows outside the vocabulary."""
    unexplained = None
    excess = max(err.test_after - err.e_noise, 0.0)
    if not data_insufficient and (err.val_after > 1.5 * err.e_noise + TOLERANCE_MM
                                  or (err.remainder > max_remainder
                                      and err.excess0 > TOLERANCE_MM)) and err.excess0 > 0:
        unexplained = _unexplained(ev_after, err.test_after, err.e_noise, excess, err.remainder)
    if not nuis.claimed:
        return unexplained
    if unexplained is None:
        unexplained = _unexplained(ev_after, err.test_after, err.e_noise, excess, err.remainder)
    unexplained["outside_vocabulary"] = [
        {"kind": o["kind"].lstrip("~"), "description": NUISANCES[o["kind"]],
         "heldout_mean_mm_once_removed": o["test_mean_with_mm"],
         "heldout_max_mm_once_removed": o["test_max_with_mm"],
         "robot_model_heldout_mean_mm": err.test_after,
         "distinguishable": o["why"]} for o in nuis.tests if o["claimed"]]
    for k in reversed(nuis.claimed):
        w = {"~drift": "time", "~field": "position"}[k]
        if not any(c["with"] == w for c in unexplained["correlates_with"]):
            unexplained["correlates_with"].insert(0, {
                "with": w, "description": NUISANCES[k], "r2": None, "p_value": None})
    return unexplained


def _status(sel: Selection, effects: list[str], forms: dict[str, str], unexplained: dict | None,
            insufficient) -> tuple[DiagnoseStatus, str]:
    """Status and conclusion sentence."""
    amb = [s for s in sel.steps if s.accepted and s.ambiguous and s.runner_up not in effects
           and s.effect in effects]
    if insufficient:
        return (DiagnoseStatus.INSUFFICIENT,
                "the data cannot support a diagnosis: " + "; ".join(insufficient[0]))
    if amb:
        return (DiagnoseStatus.AMBIGUOUS,
                "; ".join(f"ambiguous: {s.effect} or {s.runner_up}" for s in amb))
    if effects:
        conclusion = "missing effects: " + ", ".join(
            f"{e} ({forms[e]})" if e in forms else e for e in effects)
        if unexplained:
            conclusion += "; unexplained remainder" + _corr_text(unexplained)
        return DiagnoseStatus.FOUND, conclusion
    if unexplained is not None:
        return (DiagnoseStatus.UNEXPLAINED,
                "unexplained: no effect of the vocabulary explains the data"
                + _corr_text(unexplained))
    return DiagnoseStatus.NO_MISSING_EFFECT, "no missing effect"


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
