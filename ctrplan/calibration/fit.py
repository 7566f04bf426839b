"""Stage 4 of the calibration pipeline: the final fit of the chosen model.

The effects the selection chose are refitted on fit + validation rows (:func:`final_fit`) with
the least-squares engine of :mod:`ctrplan.calibration.lsq` (re-exported here: ``Problem``,
``FitResult``); the test rows still choose nothing.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ctrplan.calibration.lsq import NONFINITE_MM, FitResult, Problem
from ctrplan.shape.effects import EffectModel

__all__ = ["FinalFit", "final_fit", "Problem", "FitResult", "NONFINITE_MM"]


@dataclass(frozen=True)
class FinalFit:
    """The chosen model refitted on fit + validation rows: complete effects, the fitted
    parameters' sigma (NaN when the refit did not improve on the selected values), predicted
    points (B, m, 3) and tip errors (B,) mm of every row; bistable (B,) the rows where the
    model has two stable equilibria, other_branch (B,) those predicted on the one the solve
    does not pick first (nearer the measurement: :class:`Problem`)."""

    effects: dict[str, dict[str, float]]
    sigma: dict[str, dict[str, float]]
    pred: np.ndarray
    err: np.ndarray
    bistable: np.ndarray
    other_branch: np.ndarray


def final_fit(prob: Problem, train: np.ndarray, test: np.ndarray,
              effects: dict[str, dict[str, float]], free: Mapping[str, Sequence[str]],
              fit_iter: int, base_pred: np.ndarray) -> FinalFit:
    """Refit ``free`` parameters of ``effects`` on the ``train`` rows (same robust loss as
    ``prob``), kept only when it lowers the training residual; predictions use ``prob``."""
    sigma: dict[str, dict[str, float]] = {}
    if effects and free:
        # scored on the training rows only: the refit's test errors are computed below
        prob_all = Problem(EffectModel(prob.robot, prob.model.base), prob.data, train, train)
        prob_all.robust = prob.robust
        sel = prob_all.score(effects)
        k_all = sum(len(v) for v in free.values())
        refit = prob_all.fit(effects, free, max_iter=fit_iter, k_total=k_all)
        if refit.rss <= sel.rss * (1 + 1e-9):
            effects = refit.effects
            sigma = refit.sigma
        else:
            sigma = {e: {k: math.nan for k in names} for e, names in free.items()}
        prob.evals += prob_all.evals
    none = np.zeros(len(base_pred), dtype=bool)
    if not effects:
        return FinalFit(effects, sigma, base_pred, prob.errors(base_pred), none, none)
    pred = prob.predict_many([effects])[0]
    return FinalFit(effects, sigma, pred, prob.errors(pred), prob.last_bistable.copy(),
                    prob.last_other_branch.copy())
