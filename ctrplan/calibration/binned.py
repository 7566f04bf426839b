"""Binned residual statistics for the report (``diagnostics`` in report.json and the plots).

Stage: report. Descriptive only: nothing here tests a hypothesis or decides anything (the
data-only tests that feed the decisions are :mod:`ctrplan.calibration.evidence`).

Tip errors are binned against the relative rotation of each adjacent tube pair (split by the
direction in which that relative angle is moving), against insertion (tip arc length), and, when
backbones are measured, against arc length along the backbone.
"""

from __future__ import annotations

import math

import numpy as np

from ctrplan.measured import MeasuredData
from ctrplan.robot import Robot, wrap_angle
from ctrplan.shape.effects import sweep_starts


def motion_direction(values: np.ndarray, sweep: np.ndarray) -> np.ndarray:
    """(B, k) sign of each column's change from the previous row of the same sweep (0 at the
    start of a sweep or when still). Rows are in order of motion."""
    v = np.asarray(values, dtype=float)
    if v.ndim == 1:
        v = v[:, None]
    d = np.zeros_like(v)
    d[1:] = np.sign(v[1:] - v[:-1])
    d[sweep_starts(len(v), sweep)] = 0.0
    return d


def _binned(x: np.ndarray, y: np.ndarray, edges: np.ndarray) -> list[float | None]:
    idx = np.clip(np.digitize(x, edges) - 1, 0, len(edges) - 2)
    out: list[float | None] = []
    for b in range(len(edges) - 1):
        sel = idx == b
        out.append(float(y[sel].mean()) if sel.any() else None)
    return out


def residual_diagnostics(robot: Robot, data: MeasuredData, pred: np.ndarray, bins: int = 12) -> dict:
    """Binned tip-error statistics of predicted points ``pred`` (B, m, 3) against ``data``.

    Returns a JSON-ready dict: ``rotation`` (per adjacent tube pair: bin centres (rad), mean error
    (mm) per direction +/-/still and the mean gap between the two directions' residual vectors),
    ``insertion`` (tip arc length bins, mm) and ``arc_length`` (per measured point, when shapes
    are measured).
    """
    n = robot.n
    sweep = data.sweeps()
    res = pred[:, -1, :] - data.tip
    err = np.linalg.norm(res, axis=1)
    out: dict = {"mean_tip_error_mm": float(np.nanmean(err))}
    edges = np.linspace(-math.pi, math.pi, bins + 1)
    centres = 0.5 * (edges[1:] + edges[:-1])
    rot = []
    for i in range(n - 1):
        rel = data.q[:, i] - data.q[:, i + 1]
        d = motion_direction(rel, sweep)[:, 0]
        relw = wrap_angle(rel)
        item: dict = {"pair": [i + 1, i + 2], "angle_rad": centres.tolist()}
        for name, sel in (("up", d > 0), ("down", d < 0), ("still", d == 0)):
            item[f"error_{name}_mm"] = _binned(relw[sel], err[sel], edges)
            item[f"count_{name}"] = int(sel.sum())
        # hysteresis: mean residual vector moving up minus moving down, in matched angle bins
        gaps = []
        for b in range(bins):
            inb = (relw >= edges[b]) & (relw < edges[b + 1])
            up = inb & (d > 0)
            dn = inb & (d < 0)
            if up.sum() >= 2 and dn.sum() >= 2:
                gaps.append(np.linalg.norm(res[up].mean(0) - res[dn].mean(0)))
        item["direction_gap_mm"] = float(np.mean(gaps)) if gaps else None
        rot.append(item)
    out["rotation"] = rot
    ins = robot.tip_length(data.q)
    iedges = np.linspace(ins.min(), ins.max() + 1e-9, bins + 1)
    out["insertion"] = {"tip_arc_length_mm": (0.5 * (iedges[1:] + iedges[:-1])).tolist(),
                        "error_mm": _binned(ins, err, iedges)}
    if data.points is not None and pred.shape[1] == data.points.shape[1]:
        pe = np.linalg.norm(pred - data.points, axis=2)
        out["arc_length"] = {"fraction": np.linspace(0, 1, pe.shape[1]).tolist(),
                             "error_mm": np.nanmean(pe, axis=0).tolist()}
    return out
