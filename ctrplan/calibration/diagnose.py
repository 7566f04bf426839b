"""The sim-vs-measured workflow: find where the model and the data disagree, name the missing
effect, add it, and show the gap shrink.

Procedure (:func:`diagnose`):

1. Split the data holding out whole sweeps (a data set with a single sweep is cut into 8
   contiguous blocks, every 4th held out). The model is always evaluated on all rows in order
   (friction depends on the history), and only the rows' roles differ.
2. Residual diagnostics of the base model (:mod:`ctrplan.calibration.diagnostics`).
3. Screen every candidate effect not yet in the model: fit its parameters alone on top of the
   current model (bounded least squares, a few iterations); the ``refit_top`` best (by BIC)
   are then refitted jointly with the effects already added (uncertainties from the Jacobian).
4. A candidate is justified only by BOTH
   - the information criterion: ``BIC_new - BIC_current < -bic_threshold`` (default 10, "very
     strong" evidence on the Kass-Raftery scale), residuals = training coordinates (mm);
   - held-out error: the held-out mean tip error drops by at least ``min_gain`` (default 5 %).
   The justified candidate with the lowest BIC is added.
5. Repeat until no candidate is justified. When the runner-up is within ``ambiguity_bic`` of the
   best and also justified, the step is marked ambiguous; if the runner-up is never added later,
   the conclusion is "ambiguous: A or B". No effect added: "no missing effect".
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

from ctrplan.calibration.diagnostics import residual_diagnostics
from ctrplan.calibration.fit import FitResult, Problem
from ctrplan.errors import InputError
from ctrplan.measured import MeasuredData, read_measured
from ctrplan.robot import Robot, load_robot
from ctrplan.shape.effects import EFFECT_NAMES, EffectModel, effect_params, off_values

log = logging.getLogger("ctrplan")

__all__ = ["diagnose", "DiagnoseReport", "DiagnoseStatus", "Step", "split_sweeps"]


class DiagnoseStatus(str, enum.Enum):
    FOUND = "found"
    NO_MISSING_EFFECT = "no missing effect"
    AMBIGUOUS = "ambiguous"


@dataclass
class Candidate:
    """One screened candidate: effect, its BIC change and held-out error (mm)."""

    effect: str
    delta_bic: float
    test_mean_mm: float
    justified: bool


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


@dataclass
class DiagnoseReport:
    """Result of :func:`diagnose`.

    effects : names added, in order ([] = no missing effect). parameters : effect -> param ->
    value (joint final fit); sigma : the same, standard uncertainties. error_before_mm /
    error_after_mm : held-out mean tip error of the base / calibrated model.
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

    def model(self) -> EffectModel:
        """The calibrated shape model."""
        return EffectModel(self.robot, self.base, self.model_effects)

    def to_dict(self) -> dict:
        """JSON-ready dict (the report.json fields of DESIGN.md and more)."""
        from dataclasses import asdict

        steps = []
        for s in self.steps:
            d = asdict(s)
            steps.append(d)
        return {
            "robot": self.robot.name, "base": self.base, "status": self.status.value,
            "conclusion": self.conclusion, "effects": list(self.effects),
            "parameters": _params_json(self.parameters, self.sigma, self.robot, self.base),
            "steps": steps, "error_before_mm": self.error_before_mm,
            "error_after_mm": self.error_after_mm, "max_before_mm": self.max_before_mm,
            "max_after_mm": self.max_after_mm,
            "split": {"train_sweeps": self.train_sweeps, "test_sweeps": self.test_sweeps},
            "diagnostics": {"before": self.diagnostics_before, "after": self.diagnostics_after},
            "settings": self.settings, "elapsed_s": self.elapsed_s,
        }


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


def fitted_names(effect: str, robot: Robot, base: str) -> list[str]:
    return [p.name for p in effect_params(effect, robot, base) if p.fit]


def diagnose(robot: Robot | str, data: MeasuredData | str | os.PathLike, base: str = "rigid",
             candidates: Sequence[str] | None = None, holdout: float = 0.25, seed: int = 0,
             bic_threshold: float = 10.0, min_gain: float = 0.05, ambiguity_bic: float = 10.0,
             screen_iter: int = 8, fit_iter: int = 25, refit_top: int = 3, max_effects: int = 4,
             out: str | os.PathLike | None = None) -> DiagnoseReport:
    """Run the workflow (module docstring) and return a :class:`DiagnoseReport`.

    robot : Robot or shipped name / YAML path. data : MeasuredData or measured CSV path.
    base : ``"rigid"`` or ``"compliant"``. candidates : effect names to consider (default all).
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
    cands = [c for c in cands if fitted_names(c, robot, base)]
    if base == "compliant":
        pass  # torsion stays a candidate: it fits a compliance scale around the nominal 1
    if len(data) < 8:
        raise InputError("--data", "rows", f"need at least 8 rows to hold data out, got {len(data)}")
    train, test = split_sweeps(data, holdout, seed)
    prob = Problem(EffectModel(robot, base), data, train, test)
    current: dict[str, dict[str, float]] = {}
    cur = prob.score(current, k=0)
    base_fit = cur
    base_pred = prob.predict_many([current])[0]
    steps: list[Step] = []
    k_cur = 0
    while True:
        remaining = [c for c in cands if c not in current]
        if not remaining or len(current) >= max_effects:
            break
        results: dict[str, FitResult] = {}
        for c in remaining:
            fixed = {**current, c: off_values(c, robot, base)}
            names = fitted_names(c, robot, base)
            results[c] = prob.fit(fixed, {c: names}, max_iter=screen_iter,
                                  k_total=k_cur + len(names))
            log.debug("screen %s: dBIC %.1f held-out %.3f mm", c, results[c].bic() - cur.bic(),
                      results[c].test_mean)
        ranked = sorted(results, key=lambda c: results[c].bic())
        # the screen holds the effects already added fixed; the leading candidates are refitted
        # jointly with them (their parameters may have absorbed part of the new effect)
        if current:
            for c in ranked[:refit_top]:
                free = {e: fitted_names(e, robot, base) for e in [*current, c]}
                joint = prob.fit(results[c].effects, free, max_iter=fit_iter,
                                 k_total=sum(len(v) for v in free.values()))
                if joint.rss <= results[c].rss * (1 + 1e-9):
                    results[c] = joint
                else:
                    results[c].values, results[c].sigma = _fill_values(results[c], free)
        screened = []
        for c, r in results.items():
            dbic = r.bic() - cur.bic()
            gain = _gain(cur.test_mean, r.test_mean)
            screened.append(Candidate(c, float(dbic), float(r.test_mean),
                                      bool(dbic < -bic_threshold and gain >= min_gain)))
        screened.sort(key=lambda s: s.delta_bic)
        # the best justified candidate (lowest BIC among those passing both tests)
        best = next((s for s in screened if s.justified), screened[0])
        runner = next((s for s in screened if s is not best), None)
        if not best.justified:
            steps.append(Step(None, False, {}, {}, cur.test_mean, cur.test_mean, cur.test_max,
                              cur.test_max, best.delta_bic, _gain(cur.test_mean, best.test_mean_mm),
                              best.effect, None, False, screened))
            break
        joint = results[best.effect]
        if not current:  # first effect: polish the screening fit
            names = {best.effect: fitted_names(best.effect, robot, base)}
            polished = prob.fit(joint.effects, names, max_iter=fit_iter,
                                k_total=len(names[best.effect]))
            if polished.rss <= joint.rss * (1 + 1e-9):
                joint = polished
        k_new = joint.k
        ambiguous = bool(runner is not None and runner.justified
                         and runner.delta_bic - best.delta_bic < ambiguity_bic)
        dbic = joint.bic() - cur.bic()
        steps.append(Step(best.effect, True, joint.values, joint.sigma, cur.test_mean,
                          joint.test_mean, cur.test_max, joint.test_max, float(dbic),
                          _gain(cur.test_mean, joint.test_mean),
                          runner.effect if runner else None,
                          runner.delta_bic if runner else None, ambiguous, screened))
        log.info("added %s: held-out mean tip error %.3f -> %.3f mm (dBIC %.1f)", best.effect,
                 cur.test_mean, joint.test_mean, dbic)
        current = joint.effects
        cur = joint
        k_cur = k_new
    effects = [s.effect for s in steps if s.accepted]
    amb = [s for s in steps if s.accepted and s.ambiguous and s.runner_up not in effects]
    if amb:
        status = DiagnoseStatus.AMBIGUOUS
        conclusion = "; ".join(f"ambiguous: {s.effect} or {s.runner_up}" for s in amb)
    elif effects:
        status = DiagnoseStatus.FOUND
        conclusion = "missing effects: " + ", ".join(effects)
    else:
        status = DiagnoseStatus.NO_MISSING_EFFECT
        conclusion = "no missing effect"
    final_pred = prob.predict_many([current])[0]
    last = next((s for s in reversed(steps) if s.accepted), None)
    rep = DiagnoseReport(
        success=True, status=status, conclusion=conclusion, robot=robot, base=base,
        effects=effects,
        parameters=last.parameters if last else {}, sigma=last.sigma if last else {},
        steps=steps, error_before_mm=base_fit.test_mean, error_after_mm=cur.test_mean,
        max_before_mm=base_fit.test_max, max_after_mm=cur.test_max,
        train_sweeps=sorted(set(data.sweeps()[train].tolist())),
        test_sweeps=sorted(set(data.sweeps()[test].tolist())),
        diagnostics_before=residual_diagnostics(robot, data, base_pred),
        diagnostics_after=residual_diagnostics(robot, data, final_pred),
        settings={"holdout": holdout, "seed": seed, "bic_threshold": bic_threshold,
                  "min_heldout_gain": min_gain, "ambiguity_bic": ambiguity_bic,
                  "candidates": cands, "rows": len(data), "train_rows": int(train.sum()),
                  "test_rows": int(test.sum()), "shapes_measured": data.points is not None,
                  "kernel_calls": prob.evals},
        elapsed_s=0.0, model_effects=current,
    )
    rep.elapsed_s = time.perf_counter() - t0
    if out is not None:
        from ctrplan.calibration.report import write_report

        write_report(rep, data, out, base_pred=base_pred, final_pred=final_pred, test=test)
    return rep


def _gain(before: float, after: float) -> float:
    if not math.isfinite(before) or before <= 0:
        return 0.0
    return float((before - after) / before)


def _fill_values(fit: FitResult, free: dict[str, list[str]]):
    vals = {e: {k: fit.effects[e][k] for k in names} for e, names in free.items()}
    sig = {e: {k: fit.sigma.get(e, {}).get(k, math.nan) for k in names} for e, names in free.items()}
    return vals, sig
