"""A learned residual on top of the calibrated physics model, offered only when it helps.

Kernel ridge regression (Gaussian kernel) of the calibrated model's tip residual on the
configuration and the direction of motion: features cos/sin of every tube angle and of every
adjacent relative rotation, insertions scaled by the robot's largest stroke, and the sign of each
joint's last motion. Its width and ridge are chosen by cross-validation over the TRAINING sweeps
only (each fold holds out whole training sweeps, or the held-out units of a continuous
recording: its blocks); it is offered only when it lowers the cross-validated mean tip error by
at least ``min_gain`` (naive learned corrections overfit small real data sets; see issue 12).
The test rows choose nothing: they only report its error.
"""

from __future__ import annotations

import math

import numpy as np

from ctrplan.robot import Robot
from ctrplan.shape.base import direction_from_rows


def features(robot: Robot, q: np.ndarray, direction: np.ndarray) -> np.ndarray:
    n = robot.n
    a = q[:, :n]
    rel = a[:, :-1] - a[:, 1:]
    lo, hi = robot.beta_bounds()
    span = float(np.max(hi - lo)) or 1.0
    return np.hstack([np.cos(a), np.sin(a), np.cos(rel), np.sin(rel), q[:, n:] / span,
                      0.5 * np.asarray(direction, dtype=float)[:, :n]])


def _kernel(X: np.ndarray, Y: np.ndarray, width: float) -> np.ndarray:
    d2 = (X * X).sum(1)[:, None] + (Y * Y).sum(1)[None, :] - 2.0 * X @ Y.T
    return np.exp(-np.maximum(d2, 0.0) / (2.0 * width * width))


def _fit(X, R, width, lam):
    K = _kernel(X, X, width)
    K[np.diag_indices_from(K)] += lam
    return np.linalg.solve(K, R)


def learned_residual(robot: Robot, q: np.ndarray, sweep: np.ndarray, tip: np.ndarray,
                     pred_tip: np.ndarray, train: np.ndarray, test: np.ndarray,
                     ordered: bool = True, min_gain: float = 0.05,
                     groups: np.ndarray | None = None) -> dict:
    """Fit on the training rows, choose width, ridge and whether it is offered by
    cross-validation over them (folds: ``groups`` (B,) units, default the sweeps), report the
    error on the held-out rows; JSON-ready summary."""
    direction = direction_from_rows(q, sweep) if ordered else np.zeros(q.shape, dtype=np.int8)
    X = features(robot, q, direction)
    R = tip - pred_tip
    ok = np.all(np.isfinite(R), axis=1)
    tr = np.nonzero(train & ok)[0]
    te = np.nonzero(test & ok)[0]
    out: dict = {"method": "kernel ridge (Gaussian) on configuration and direction of motion; "
                           "width and ridge by cross-validation over training sweeps",
                 "offered": False}
    if len(tr) < 30 or len(te) < 5:
        out["why"] = "too few rows"
        return out
    if len(tr) > 1500:                                  # keep the kernel matrix small
        tr = tr[np.linspace(0, len(tr) - 1, 1500).astype(int)]
    names = np.asarray(sweep if groups is None else groups)[tr]
    groups = list(dict.fromkeys(names.tolist()))
    if len(groups) >= 3:
        folds = [names == g for g in groups[: min(len(groups), 5)]]
    else:                                               # one sweep: contiguous blocks
        blk = (np.arange(len(tr)) * 4) // len(tr)
        folds = [blk == b for b in range(4)]
    best = (math.inf, 1.0, 1e-2)
    cv_none = float(np.mean([np.linalg.norm(R[tr][f], axis=1).mean() for f in folds
                             if f.any() and not f.all()] or [math.nan]))
    for width in (0.5, 1.0, 2.0):
        for lam in (1e-3, 1e-2, 1e-1, 1.0):
            err = []
            for f in folds:
                if f.all() or not f.any():
                    continue
                c = _fit(X[tr][~f], R[tr][~f], width, lam)
                p = _kernel(X[tr][f], X[tr][~f], width) @ c
                err.append(np.linalg.norm(R[tr][f] - p, axis=1).mean())
            if err and np.mean(err) < best[0]:
                best = (float(np.mean(err)), width, lam)
    _, width, lam = best
    coef = _fit(X[tr], R[tr], width, lam)
    corr = _kernel(X[te], X[tr], width) @ coef
    before = np.linalg.norm(R[te], axis=1)
    after = np.linalg.norm(R[te] - corr, axis=1)
    gain = 1.0 - after.mean() / before.mean() if before.mean() > 0 else 0.0
    cv_gain = 1.0 - best[0] / cv_none if cv_none > 0 else 0.0
    out.update({"width": width, "ridge": lam, "cv_mean_mm": best[0],
                "cv_mean_before_mm": cv_none, "cv_gain": float(cv_gain),
                "heldout_mean_before_mm": float(before.mean()),
                "heldout_mean_after_mm": float(after.mean()),
                "heldout_max_before_mm": float(before.max()),
                "heldout_max_after_mm": float(after.max()), "gain": float(gain),
                "offered": bool(cv_gain >= min_gain)})
    if not out["offered"]:
        out["why"] = (f"it does not lower the cross-validated mean tip error by "
                      f"{100 * min_gain:.0f} % ({cv_none:.3f} -> {best[0]:.3f} mm)")
    return out
