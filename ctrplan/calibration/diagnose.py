"""The sim-vs-measured workflow: find where the model and the data disagree, name the missing
effect, add it, and show the gap shrink — and say so when the data cannot tell.

The pipeline (:func:`diagnose`), one module per stage, each returning a frozen dataclass:

=====================  ============================================  =========================
stage                  module                                        result
=====================  ============================================  =========================
1. data checks, split  :mod:`ctrplan.calibration.data`               ``Inputs``, ``Split``
2. evidence            :mod:`ctrplan.calibration.evidence`           ``Evidence``
3. screening/selection :mod:`ctrplan.calibration.select`             ``Selection``
4. fit                 :mod:`ctrplan.calibration.fit`                ``FinalFit``
   nuisances           :mod:`ctrplan.calibration.nuisance`           ``Nuisances``
5. conclusion          :mod:`ctrplan.calibration.verdict`            ``Verdict``
6. report              :mod:`ctrplan.calibration.report`             files (written as a set)
=====================  ============================================  =========================

No stage imports a later one (``tests/test_calibration_structure.py``). The public result
:class:`DiagnoseReport` is in :mod:`ctrplan.calibration.result` (it imports no stage); the
least-squares engine used by stages 3 and 4 is :mod:`ctrplan.calibration.lsq`;
:mod:`ctrplan.calibration.binned` holds the report's descriptive binned statistics,
:mod:`ctrplan.calibration.residual` the optional learned residual.

Procedure (:func:`diagnose`). Calibrating (the most accurate physically parameterised model
on data not used to choose it) and naming (which effects the evidence singles out) are two
decisions:

1. Data check: enough distinct configurations, a measurable noise floor below what any effect
   can change, an error the vocabulary can reach at all. Otherwise the report says that the data
   cannot support a diagnosis and what experiment would (status ``insufficient data``).
2. Split (the one held-out splitter, :func:`ctrplan.split.split`): fit / validation / test
   rows. With ``MIN_SWEEPS_WHOLE`` sweeps or more, whole sweeps; with fewer, contiguous blocks
   of every sweep, the rows within the motion's autocorrelation length of a test block left out
   (the report says how many independent test blocks the numbers rest on). Parameters are
   fitted on the fit rows, effects and forms chosen on the validation rows; the test rows make
   one choice only (step 9) and give the reported errors. Friction's history comes from all
   rows in order (the commanded motion).
3. Evidence from the data alone (:mod:`ctrplan.calibration.evidence`), on the fit and
   validation rows only.
4. Forward selection (:func:`ctrplan.calibration.select.forward`): every form of every
   candidate effect is fitted alone on top of the current model (robust soft-L1 loss, see :meth:`Problem.fit`); the leading ones are
   refitted jointly with the effects already in. A candidate enters the model when it lowers the
   BIC and the validation error by ``keep_gain``; it is *named* only when ``dBIC <
   -bic_threshold``, the validation error drops by ``min_gain``, by ``MIN_SHARE`` of the base
   model's validation error and, after a first named effect, by ``FOLLOWER_SHARE`` of the
   largest drop a named effect made (a smaller drop may be the first effect's form misfit).
5. Joint model (:func:`ctrplan.calibration.select.joint`): when step 4 leaves more than ``JOINT_TRIGGER`` times the noise,
   every effect that lowered the BIC in the first screen is fitted jointly (registration,
   precurvature, stiffness, friction and clearance are often uncertain all at once on a real
   robot; one at a time none of them helps), then each is dropped in turn: the drop decides
   whether it stays and whether it is named (the same three shares, the last of the largest
   drop). The joint model replaces step 4's when it is
   better on validation. Friction kept below the shares is named by its signature
   (:func:`ctrplan.calibration.select.name_by_signature`: the hysteresis it removes).
6. The chosen model is refitted on fit + validation rows and written as ``calibrated.yaml``
   whether or not its effects are named (unnamed ones are listed as ``partial``).
7. Nuisances (:mod:`ctrplan.calibration.nuisance`), only after the robot: a drift in time and a tracker-field
   distortion, claimed only where the data tell them apart from the robot; never in the model.
8. Honest remainder: when the named effects leave more than ``max_remainder`` of the initial
   validation error above the noise floor, nothing is named and ``unexplained`` says what the
   residual still correlates with and how much is left; ``unexplained`` is also reported
   (without un-naming) whenever the residual stays clearly above the noise floor.
9. Never worse than the base: before the final fit, a selected model worse than the base on
   the validation mean or p99 falls back to the largest smaller model (or the base) that is not
   (:func:`ctrplan.calibration.select.no_worse_than_base`); after it, the fitted model is the
   default output only when its test-row mean and p99 are no worse than the base's
   (:func:`ctrplan.calibration.verdict.heldout_choice`; otherwise the base model, with the fit
   in ``calibrated_fit.yaml``). Effects the rows cannot tell apart are reported as
   ``confounded`` (:mod:`ctrplan.calibration.confound`).

Long recordings: the selection fits every k-th fit and validation row (at most about
:data:`SELECT_FIT_ROWS` fit rows); the final fit uses them all. Progress and an estimate of
the time left are logged (stderr, INFO).

Out-of-sample rule. The selection constants of this pipeline (``FOLLOWER_SHARE``,
``MIN_SHARE``, ``JOINT_TRIGGER``, ``SIGNATURE_CUT``, ``DRIFT_BLOCKS``, the screen's iteration
counts, ...) were set by measuring the development seeds of ``tests/test_diagnose_foreign.py``,
which that suite then asserts. One changes only with a physical reason written beside it, or
with a fresh-seed run of ``benchmarks/bench_fresh.py`` (seeds never used in development)
before and after the change, both recorded; the rates the documents quote are the fresh-seed
ones (docs/validation.md, "Out-of-sample protocol").
"""

from __future__ import annotations

import logging
import os
import time
from collections.abc import Sequence

import numpy as np

from ctrplan.calibration import evidence as ev
from ctrplan.calibration.binned import residual_diagnostics
from ctrplan.calibration.confound import confounded
from ctrplan.calibration.confound import describe as describe_confounded
from ctrplan.calibration.data import (
    MIN_SWEEPS_WHOLE,
    Inputs,
    Split,
    check_inputs,
    row_ranges,
    split_rows,
    split_sweeps,
    split_three,
)
from ctrplan.calibration.evidence import CHI3_MEAN
from ctrplan.calibration.fit import FinalFit, final_fit
from ctrplan.calibration.lsq import Problem
from ctrplan.calibration.nuisance import NUISANCES, Nuisances
from ctrplan.calibration.nuisance import screen as screen_nuisances
from ctrplan.calibration.result import Candidate, DiagnoseReport, DiagnoseStatus, Step, headline
from ctrplan.calibration.select import (
    FOLLOWER_SHARE,
    JOINT_TRIGGER,
    MIN_SHARE,
    SelectConfig,
    Selection,
    drop_partials_at_bounds,
    name_by_signature,
    no_worse_than_base,
    select,
)
from ctrplan.calibration.verdict import HeldoutChoice, Verdict, conclude, errors, heldout_choice
from ctrplan.measured import MeasuredData
from ctrplan.robot import Robot
from ctrplan.shape.base import direction_from_rows
from ctrplan.shape.effects import EffectModel
from ctrplan.split import HeldOut

log = logging.getLogger("ctrplan")

__all__ = ["diagnose", "DiagnoseReport", "DiagnoseStatus", "Step", "Candidate", "split_sweeps",
           "split_three", "row_ranges", "headline", "NUISANCES", "CHI3_MEAN", "MIN_SWEEPS_WHOLE",
           "JOINT_TRIGGER", "MIN_SHARE", "FOLLOWER_SHARE"]


def diagnose(robot: Robot | str, data: MeasuredData | str | os.PathLike, base: str = "rigid",
             candidates: Sequence[str] | None = None, holdout: float = 0.25, seed: int = 0,
             bic_threshold: float = 10.0, min_gain: float = 0.05, ambiguity_bic: float = 10.0,
             screen_iter: int = 8, fit_iter: int = 25, refit_top: int = 3, max_effects: int = 6,
             max_remainder: float = 0.5, keep_gain: float = 0.02, min_configurations: int = 20,
             nuisances: bool = True, learned_residual: bool = True,
             out: str | os.PathLike | None = None,
             heldout: HeldOut | None = None) -> DiagnoseReport:
    """Run the workflow (module docstring) and return a :class:`DiagnoseReport`.

    robot : Robot or shipped name / YAML path. data : MeasuredData or measured CSV path.
    base : ``"rigid"`` or ``"compliant"``. candidates : effect names to consider (default all).
    max_remainder : effects are named only when they leave at most this fraction of the
    initial held-out error above the noise floor. nuisances : screen the nuisances outside the
    vocabulary (drift in time, tracker-field distortion). learned_residual : also fit a learned
    residual on top of the calibrated model (reported separately; offered only when it lowers
    the held-out error, see :mod:`ctrplan.calibration.residual`).
    out : when given, write report.json, report.md, plots and calibrated model files there
    (as a set: see :func:`ctrplan.calibration.report.write_report`).
    heldout : the rows' split made beforehand by :func:`ctrplan.split.split` (``diagnose
    --best`` passes the one it compares its candidates on); default: split here with
    ``holdout`` and ``seed``.
    """
    t0 = time.perf_counter()
    cfg = SelectConfig(bic_threshold, min_gain, keep_gain, ambiguity_bic, screen_iter, fit_iter,
                       refit_top, max_effects)
    inp = check_inputs(robot, data, base, candidates)
    robot, data = inp.robot, inp.data
    split = split_rows(data, holdout, seed, heldout)
    # selection problem: parameters fitted on the fit rows, effects chosen on validation rows
    # (of a long recording, every k-th: see selection_rows)
    prob = Problem(EffectModel(robot, inp.base), data, *selection_rows(split))
    base_score = prob.score({}, k=0)
    base_pred = prob.predict_many([{}])[0]
    evd = ev.gather(robot, data, split, base_pred, inp.candidates, min_configurations)
    prob.robust = evd.robust_scale
    glitch = _glitches(data, split, base_pred)
    sel, fit = _select_and_fit(prob, inp, split, evd, cfg, base_score, base_pred, glitch)
    log.info("diagnose: final fit done (%.0f s); nuisances, conclusion and report",
             time.perf_counter() - t0)
    ev_after = ev.collect(robot, data.q, fit.pred[:, -1], data.tip, split.sweeps, data.time,
                          split.ordered, noise=evd.before["noise"],
                          rows=split.train) if fit.effects else evd.before
    if nuisances and not evd.insufficient:
        nuis = screen_nuisances(robot, prob, data, split, fit.pred, base_pred, fit.effects,
                                sel.named, min_gain)
    else:
        nuis = Nuisances([], [], sel.named)
    base_err = prob.errors(base_pred)
    choice = heldout_choice(base_err, fit.err, split.test, split.units, glitch)
    err = errors(base_err, fit, split.val, split.test, evd.noise_sd, choice.err)
    conf = confounded(prob, fit.effects, sel.free, prob.train) if not evd.insufficient else []
    verdict = conclude(robot, inp.base, sel, nuis, fit, err, ev_after, evd.insufficient,
                       max_remainder, split.train, split.test)
    learned = None
    if learned_residual and not verdict.insufficient:
        from ctrplan.calibration.residual import learned_residual as _lr

        learned = _lr(robot, data.q, split.sweeps, data.tip, fit.pred[:, -1], split.train,
                      split.test, split.ordered, groups=split.units)
    settings = _settings(holdout, seed, max_remainder, cfg, inp, split, evd, sel, prob.evals,
                         fit)
    rep = _report(inp, split, evd, sel, fit, nuis, verdict, base_pred, ev_after, settings,
                  learned)
    rep.confounded = conf
    rep.warnings += describe_confounded(conf) + _bistable_warnings(settings["bistable_rows"])
    named_conf = [c for c in conf if set(c["effects"]) & set(rep.effects)]
    if named_conf:
        # the evidence singled one effect out by its fit; the conclusion says what it is
        # confounded with (report.json ``confounded``)
        rep.conclusion += "; " + "; ".join(
            f"{a} confounded with {b}" for a, b in (c["effects"] for c in named_conf))
    _apply_choice(rep, choice, fit)
    rep.elapsed_s = time.perf_counter() - t0
    if out is not None:
        from ctrplan.calibration.report import write_report

        write_report(rep, data, out, base_pred=base_pred, final_pred=fit.pred, test=split.test)
    return rep


#: the selection (screens, forward and joint models) fits at most about this many fit rows: a
#: longer recording's fit and validation rows are thinned to every k-th row for it (its rows a
#: few apart are nearly copies of each other: the motion's autocorrelation length is tens of
#: rows, so thinning loses little of what the rows tell), and only the final fit uses them all.
#: 1,300-row recordings (650 fit rows) are not thinned; 5,000 rows are thinned by 2-3, which
#: keeps diagnose within its time budget (benchmarks/bench_diagnose.py, ``real_5000``)
SELECT_FIT_ROWS = 1200


def selection_rows(split: Split) -> tuple[np.ndarray, np.ndarray]:
    """(fit, validation) rows of the selection: every k-th fit and validation row, k the
    smallest step that leaves at most :data:`SELECT_FIT_ROWS` fit rows (k = 1 for shorter
    data)."""
    k = max(1, -(-int(split.fit.sum()) // SELECT_FIT_ROWS))
    if k == 1:
        return split.fit, split.val
    out = []
    for m in (split.fit, split.val):
        idx = np.flatnonzero(m)[::k]
        t = np.zeros_like(m)
        t[idx] = True
        out.append(t)
    return out[0], out[1]


def _glitches(data: MeasuredData, split: Split, base_pred: np.ndarray) -> np.ndarray:
    """(B,) rows of the validation and the test rows whose measurement jumped
    (:func:`ctrplan.calibration.evidence.glitches`, each role on its own runs of rows); none
    for rows that are independent samples."""
    if not split.ordered:
        return np.zeros(len(data), dtype=bool)
    res = base_pred[:, -1] - data.tip
    return ev.glitches(res, split.sweeps, split.val) | ev.glitches(res, split.sweeps, split.test)


def _select_and_fit(prob: Problem, inp: Inputs, split: Split, evd: ev.Evidence,
                    cfg: SelectConfig, base_score, base_pred: np.ndarray, glitch: np.ndarray
                    ) -> tuple[Selection, FinalFit]:
    """Stages 3 and 4: the selection (with friction's signature and the fallback to a model no
    worse than the base on the validation rows), the final fit on fit + validation rows, and
    the partial effects at a bound left out."""
    robot, data = inp.robot, inp.data
    if evd.insufficient:
        sel = Selection({}, base_score, {}, [], {})
    else:
        sel = select(prob, robot, inp.base, evd.candidates, cfg, evd.e_noise, base_score)
        if split.ordered:
            sel = name_by_signature(prob, sel, split.train,
                                    direction_from_rows(data.q, split.sweeps), evd.noise_sd, cfg)
    sel = no_worse_than_base(prob, sel, glitch)
    fit = final_fit(prob, split.train, split.test, sel.effects, sel.free, cfg.fit_iter,
                    base_pred)
    trimmed = drop_partials_at_bounds(prob, robot, inp.base, sel, fit.effects, cfg)
    if trimmed is not None:
        sel = trimmed
        fit = final_fit(prob, split.train, split.test, sel.effects, sel.free, cfg.fit_iter,
                        base_pred)
    return sel, fit


def _bistable_warnings(counts: dict) -> list[str]:
    """The report's word on rows where the calibrated model has two stable equilibria
    (``counts``: report.json ``settings.bistable_rows``)."""
    if not counts["rows"]:
        return []
    return [f"the calibrated model has two stable equilibria at {counts['rows']} measured "
            f"row(s) ({counts['test_rows']} of them test rows): the tubes can snap "
            "between them there. Each such row is compared on the equilibrium nearer its "
            f"measurement, the branch the robot was on ({counts['on_other_branch']} row(s) "
            "on the one the solve does not pick first); a plan starts on the robot's measured "
            "branch and follows it (branch tracking): plan from these configurations with the "
            "branch the robot is on (ctrplan.planning.stability.Start)"]


def _apply_choice(rep: DiagnoseReport, choice: HeldoutChoice, fit: FinalFit) -> None:
    """The held-out comparison in the report; the base model as the default output (the fit
    kept as ``fit_effects``, written as calibrated_fit.yaml) when the fit is worse than the
    base on the test rows' mean or p99 (the report's after-errors are then the base's)."""
    rep.heldout_comparison = choice.info
    rep.fit_effects = fit.effects
    if not choice.info["stable"] and fit.effects:
        rep.warnings.append(
            "the fitted model and the base model compare differently on the two halves of the "
            f"test units (no worse on the mean and p99: {choice.info['per_fold'][0]} on one, "
            f"{choice.info['per_fold'][1]} on the other): the choice of the default output "
            "rests on few units; record more sweeps")
    if choice.output == "fit" or not fit.effects:
        return
    rep.model_effects = {}
    b, f = choice.info["base"], choice.info["fit"]
    rep.warnings.append(
        f"the fitted model ({', '.join(fit.effects)}) is not the default output: on the test "
        f"rows its tip error is mean {f['mean_mm']:.3f} mm, p99 {f['p99_mm']:.3f} mm against "
        f"the base model's {b['mean_mm']:.3f} / {b['p99_mm']:.3f} mm (a model worse than the "
        "base on the mean or the tail is not the default); calibrated.yaml is the base model "
        "with the error bound measured, the fit is in calibrated_fit.yaml")


def _settings(holdout: float, seed: int, max_remainder: float, cfg: SelectConfig, inp: Inputs,
              split: Split, evd: ev.Evidence, sel: Selection, evals: int, fit: FinalFit) -> dict:
    """report.json ``settings`` (in the order the workflow has always written them)."""
    data = inp.data
    rs = evd.robust_scale
    return {"holdout": holdout, "seed": seed,
            "bic_threshold": cfg.bic_threshold, "min_heldout_gain": cfg.min_gain,
            "keep_gain": cfg.keep_gain, "ambiguity_bic": cfg.ambiguity_bic,
            "max_remainder": max_remainder, "candidates": list(evd.candidates),
            "rows": len(data), "fit_rows": int(split.fit.sum()),
            "selection_fit_rows": int(selection_rows(split)[0].sum()),
            "validation_rows": int(split.val.sum()), "test_rows": int(split.test.sum()),
            "train_rows": int(split.train.sum()), "shapes_measured": data.points is not None,
            "rows_in_order_of_motion": split.ordered,
            "robust_loss": {"loss": "soft_l1", "f_scale_mm": rs} if rs else None,
            **sel.settings, "kernel_calls": evals, "noise_sd_mm": evd.noise_sd,
            "bistable_rows": {"rows": int(fit.bistable.sum()),
                              "test_rows": int((fit.bistable & split.test).sum()),
                              "on_other_branch": int(fit.other_branch.sum())}}


def _report(inp: Inputs, split: Split, evd: ev.Evidence, sel: Selection, fit: FinalFit,
            nuis: Nuisances, verdict: Verdict, base_pred: np.ndarray, ev_after: dict,
            settings: dict, learned: dict | None) -> DiagnoseReport:
    """Assemble the :class:`DiagnoseReport` from the stages' results."""
    robot, data, err = inp.robot, inp.data, verdict.errors
    measured = measured_insertion(robot, data)
    ins = evd.insufficient
    warnings = (list(ins[0]) if ins else []) + [
        *split.warnings, *evd.warnings, *sel.warnings, *nuis.warnings, *verdict.warnings,
        *coverage_warnings(robot, measured)]
    experiment = (list(ins[1]) if ins else []) + [
        *split.experiment, *evd.experiment, *verdict.experiment]
    info = {**split.info, "validation_error_before_mm": err.val_before,
            "validation_error_after_mm": err.val_after}
    return DiagnoseReport(
        success=not verdict.insufficient, status=verdict.status, conclusion=verdict.conclusion,
        robot=robot, base=inp.base, effects=verdict.effects, parameters=verdict.parameters,
        sigma=verdict.sigma, steps=sel.steps, error_before_mm=err.test_before,
        error_after_mm=err.test_after, max_before_mm=err.max_before, max_after_mm=err.max_after,
        train_sweeps=split.train_sweeps, test_sweeps=split.test_sweeps,
        diagnostics_before=residual_diagnostics(robot, data, base_pred),
        diagnostics_after=residual_diagnostics(robot, data, fit.pred),
        settings=settings, elapsed_s=0.0, model_effects=fit.effects,
        forms=verdict.forms, evidence_before=evd.before, evidence_after=ev_after,
        unexplained=verdict.unexplained, warnings=warnings, experiment=experiment,
        partial=verdict.partial, error_quantiles=verdict.quantiles, split=info,
        learned_residual=learned, partial_values=verdict.partial_values,
        outliers=verdict.outliers,
        nuisance_tests=[{k: v for k, v in o.items() if k != "features"} for o in nuis.tests],
        measured_insertion=measured, error_quantiles_before=verdict.quantiles_before,
    )


#: a tube whose measured insertions span less than this fraction of its insertion range gets a
#: warning: the error bound is extrapolated over most of where plans may go
COVERAGE_MIN = 0.5


def coverage_warnings(robot: Robot, measured: dict | None) -> list[str]:
    """Warnings for tubes whose measured insertions span less than :data:`COVERAGE_MIN` of the
    robot's insertion range (:meth:`Robot.beta_bounds`)."""
    if not measured:
        return []
    lo, hi = robot.beta_bounds()
    out = []
    for i, (a, b) in enumerate(zip(measured["min"], measured["max"])):
        span = float(hi[i] - lo[i])
        if span > 0 and (b - a) < COVERAGE_MIN * span:
            out.append(f"the rows insert tube {i + 1} over {a:.1f} to {b:.1f} mm only, "
                       f"{100 * (b - a) / span:.0f} % of its range {lo[i]:.1f} to {hi[i]:.1f} mm: "
                       "the calibrated model and its error bound are extrapolated beyond; "
                       "measure over the insertions you will plan in")
    return out


def measured_insertion(robot: Robot, data: MeasuredData) -> dict | None:
    """The insertions (beta, mm per tube) the measured rows span: where the calibrated model's
    error bound was measured (rows whose tip is not finite left out)."""
    q = np.asarray(data.q, dtype=float)
    ok = np.all(np.isfinite(q), axis=1) & np.all(np.isfinite(np.asarray(data.tip, float)), axis=1)
    if not ok.any():
        return None
    b = q[ok, robot.n:]
    return {"min": [float(v) for v in b.min(axis=0)], "max": [float(v) for v in b.max(axis=0)]}
