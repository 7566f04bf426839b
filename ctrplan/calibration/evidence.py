"""Evidence from the data alone, before (and after) fitting any effect.

Stage 2 of the calibration pipeline (:mod:`ctrplan.calibration.diagnose`): data-only
statistical tests whose results feed the data check, the screening and the conclusion (the
descriptive binned statistics of the report are :mod:`ctrplan.calibration.binned`). They run on
the fit and validation rows only (:func:`gather`, ``collect(rows=...)``): the test rows stay
untouched; directions of motion come from all rows in order (the commanded history).

Every test works on the tip residual ``r = predicted - measured`` (B, 3) of a model and on the
configurations, directions of motion and times of the rows:

``noise``        noise floor: the pooled spread of repeat visits (rows with the same
                 configuration approached the same way) when there are enough, else the local
                 smoothness of the residual along each sweep (second differences of consecutive
                 rows; a robust MAD estimate, an upper bound when the motion is coarse). sd per
                 axis, mm.
``hysteresis``   the same configuration approached from opposite directions: squared residual
                 differences of nearest-neighbour pairs whose joints last moved in opposite
                 directions, against pairs at similar distance that moved the same way
                 (one-sided Mann-Whitney test; ratio of medians).
``harmonics``    per adjacent tube pair, least squares of the residual on
                 1, cos phi, sin phi, cos 2phi, sin 2phi of the relative rotation phi: amplitude
                 (mm) and phase (deg) of each harmonic along its dominant direction, fraction of
                 the residual variance explained, F-test p-value.
``insertion``    linear trend of the residual with insertion (tip arc length): slope (mm per
                 mm), variance explained, p-value.
``procrustes``   the best rigid transform (Kabsch) of the predicted tips onto the measured ones:
                 rotation (deg), translation (mm), fraction of the residual variance it removes.
``time``         trend of the residual with time (quadratic): variance explained, p-value.
``position``     a smooth (quadratic) field of the measured tip position, fitted after the rigid
                 transform: variance explained, p-value (a nonlinear tracker distortion).

A test is ``significant`` when its p-value is below ``P_SIGNIFICANT`` and the variance it
explains is above the noise floor's share. All numbers are JSON-ready.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from scipy import stats

from ctrplan.calibration.data import Split, data_check
from ctrplan.measured import MeasuredData
from ctrplan.robot import Robot
from ctrplan.shape.base import direction_from_rows

P_SIGNIFICANT = 1e-3
#: mean norm of a 3-d Gaussian vector with unit sd per axis: sqrt(8 / pi)
CHI3_MEAN = math.sqrt(8.0 / math.pi)


@dataclass(frozen=True)
class Evidence:
    """Result of the evidence stage: the data-only tests on the base model's residual
    (``before``, see :func:`collect`), the noise floor (sd per axis, mm; None when not
    measurable), ``insufficient`` = (reasons, experiments) when the data cannot support a
    diagnosis (:func:`ctrplan.calibration.data.data_check`), the candidates left to screen, the
    robust loss's scale (mm) and what this stage warns about."""

    before: dict
    noise_sd: float | None
    insufficient: tuple[list[str], list[str]] | None
    candidates: tuple[str, ...]
    robust_scale: float | None
    warnings: tuple[str, ...] = ()
    experiment: tuple[str, ...] = ()

    @property
    def e_noise(self) -> float:
        """The noise floor's mean tip error (mm; 0 when not measured)."""
        return CHI3_MEAN * self.noise_sd if self.noise_sd else 0.0


def gather(robot: Robot, data: MeasuredData, split: Split, base_pred: np.ndarray,
           candidates: Sequence[str], min_configurations: int) -> Evidence:
    """The evidence stage on the fit and validation rows only (the test rows stay untouched):
    tests on the base model's predictions ``base_pred`` (B, m, 3), the data check, and
    friction dropped from the candidates when the rows show no reversals."""
    before = collect(robot, data.q, base_pred[:, -1], data.tip, split.sweeps, data.time,
                     split.ordered, rows=split.train)
    noise_sd = before["noise"].get("sd_mm")
    insufficient = data_check(robot, data, before, base_pred[:, -1], min_configurations)
    hyst = before["hysteresis"]
    cands = list(candidates)
    warnings, experiment = [], []
    if not insufficient and "friction" in cands and not hyst.get("tested"):
        if "no motion" in hyst.get("why", "") or "one way" in hyst.get("why", "") \
                or "not in order" in hyst.get("why", ""):
            cands = [c for c in cands if c != "friction"]
            warnings.append(f"friction not screened: {hyst['why']}")
            experiment.append("move each joint back and forth over the same range (reversals "
                              "reveal friction)")
    return Evidence(before, noise_sd, insufficient, tuple(cands), robust_scale(noise_sd),
                    tuple(warnings), tuple(experiment))


def robust_scale(noise_sd: float | None) -> float | None:
    """The robust loss's smallest scale (mm per coordinate): 3 noise sd (see Problem.fit)."""
    if noise_sd is None or not math.isfinite(noise_sd):
        return None
    return max(3.0 * float(noise_sd), 0.05)


def _sweep_starts(sweep: np.ndarray) -> np.ndarray:
    start = np.zeros(len(sweep), dtype=bool)
    if len(sweep):
        start[0] = True
        start[1:] = sweep[1:] != sweep[:-1]
    return start


def distinct_configurations(q: np.ndarray, tol: float = 1e-6) -> int:
    """Number of distinct rows of q (rounded to ``tol``)."""
    if len(q) == 0:
        return 0
    return int(len(np.unique(np.round(np.asarray(q) / tol).astype(np.int64), axis=0)))


def noise_floor(q: np.ndarray, res: np.ndarray, sweep: np.ndarray, direction: np.ndarray,
                ordered: bool = True) -> dict:
    """Noise sd per axis (mm) from repeat visits or local smoothness (module docstring)."""
    key = np.round(np.asarray(q) / 1e-6).astype(np.int64)
    key = np.hstack([key, np.asarray(direction, dtype=np.int64)])
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    inv = inv.ravel()
    rep = counts[inv] >= 2
    groups = int((counts >= 2).sum())
    if rep.sum() >= 20 and groups >= 5:
        r = res[rep]
        g = inv[rep]
        means = np.zeros((counts.size, 3))
        np.add.at(means, g, r)
        means /= counts[:, None]
        dev = r - means[g]
        dof = int(rep.sum() - groups)
        sd = float(np.sqrt((dev ** 2).sum() / max(dof, 1) / 3.0))
        return {"sd_mm": sd, "method": "repeat visits", "groups": groups, "rows": int(rep.sum())}
    if ordered and len(res) >= 5:
        start = _sweep_starts(sweep)
        ok = np.ones(len(res), dtype=bool)
        ok[:1] = ok[-1:] = False
        ok[1:-1] &= ~start[1:-1] & ~start[2:]
        idx = np.nonzero(ok)[0]
        if len(idx) >= 10:
            d2 = res[idx - 1] - 2 * res[idx] + res[idx + 1]
            mad = np.median(np.abs(d2 - np.median(d2, axis=0)), axis=0) / 0.6745
            sd = float(np.sqrt(np.mean(mad ** 2) / 6.0))
            return {"sd_mm": sd, "method": "local smoothness (second differences along sweeps)",
                    "rows": int(len(idx))}
    # unordered data: nearest neighbours in configuration space (an upper bound)
    from scipy.spatial import cKDTree

    f = _features(q)
    if len(f) >= 10:
        tree = cKDTree(f)
        _, nn = tree.query(f, k=2)
        d = res - res[nn[:, 1]]
        mad = np.median(np.abs(d - np.median(d, axis=0)), axis=0) / 0.6745
        sd = float(np.sqrt(np.mean(mad ** 2) / 2.0))
        return {"sd_mm": sd, "method": "nearest neighbours in configuration (upper bound)",
                "rows": int(len(f))}
    return {"sd_mm": None, "method": "too few rows", "rows": int(len(res))}


def _features(q: np.ndarray, scale: float = 20.0) -> np.ndarray:
    """Configuration features for neighbour search: angles on the circle (scaled to mm)."""
    n = q.shape[1] // 2
    a = q[:, :n]
    return np.hstack([scale * np.cos(a), scale * np.sin(a), q[:, n:]])


def hysteresis(q: np.ndarray, res: np.ndarray, direction: np.ndarray, noise_sd: float | None) -> dict:
    """Opposite-direction vs same-direction neighbour pairs (module docstring)."""
    from scipy.spatial import cKDTree

    n = q.shape[1] // 2
    d = np.asarray(direction)[:, :n]
    moving = np.any(d != 0, axis=1)
    out: dict = {"tested": False}
    if moving.sum() < 20:
        out["why"] = "no motion to reveal direction effects (too few rows with a known direction)"
        return out
    signs = d[moving]
    if not (np.any(signs > 0) and np.any(signs < 0)):
        out["why"] = "every joint moved one way only: no reversal to compare"
        return out
    f = _features(q[moving])
    r = res[moving]
    tree = cKDTree(f)
    k = min(16, len(f))
    dist, nn = tree.query(f, k=k)
    opp_d, same_d, opp_dist, same_dist = [], [], [], []
    for i in range(len(f)):
        for dd, j in zip(dist[i, 1:], nn[i, 1:]):
            if j <= i:
                continue
            diff = signs[i] != signs[j]
            opposite = np.any((signs[i] * signs[j]) < 0)
            v = float(((r[i] - r[j]) ** 2).sum())
            if opposite:
                opp_d.append(v)
                opp_dist.append(dd)
            elif not diff.any():
                same_d.append(v)
                same_dist.append(dd)
    if len(opp_d) < 10 or len(same_d) < 10:
        out["why"] = "too few pairs of nearby configurations approached from opposite directions"
        return out
    opp_d, same_d = np.array(opp_d), np.array(same_d)
    opp_dist, same_dist = np.array(opp_dist), np.array(same_dist)
    # compare at matched distances: keep pairs no farther than the closer group's 75th percentile
    lim = min(np.percentile(opp_dist, 75), np.percentile(same_dist, 75))
    a = opp_d[opp_dist <= lim]
    b = same_d[same_dist <= lim]
    if len(a) < 10 or len(b) < 10:
        a, b = opp_d, same_d
    p = float(stats.mannwhitneyu(a, b, alternative="greater").pvalue)
    gap = math.sqrt(max(float(np.median(a)) - float(np.median(b)), 0.0))
    ratio = float(np.median(a) / max(np.median(b), 1e-12))
    floor = (noise_sd or 0.0) * math.sqrt(6.0)
    out.update({"tested": True, "pairs_opposite": int(len(a)), "pairs_same": int(len(b)),
                "median_gap_mm": gap, "ratio": ratio, "p_value": p,
                "significant": bool(p < P_SIGNIFICANT and ratio > 1.5 and gap > 0.5 * floor)})
    return out


def _ftest(X: np.ndarray, Y: np.ndarray) -> tuple[np.ndarray, float, float]:
    """Least squares of Y (B, 3) on X (B, k) with an intercept column first; returns the
    coefficients, the fraction of variance explained beyond the mean and the F-test p-value."""
    B, k = X.shape
    coef, *_ = np.linalg.lstsq(X, Y, rcond=None)
    fit = X @ coef
    mean = Y.mean(0)
    ss_tot = float(((Y - mean) ** 2).sum())
    ss_res = float(((Y - fit) ** 2).sum())
    r2 = 1.0 - ss_res / ss_tot if ss_tot > 0 else 0.0
    df1 = 3 * (k - 1)
    df2 = 3 * (B - k)
    if df1 <= 0 or df2 <= 0 or ss_res <= 0:
        return coef, r2, 1.0 if ss_res > 0 or ss_tot == 0 else 0.0
    F = ((ss_tot - ss_res) / df1) / (ss_res / df2)
    return coef, max(r2, 0.0), float(stats.f.sf(F, df1, df2))


def harmonics(robot: Robot, q: np.ndarray, res: np.ndarray, noise_sd: float | None) -> list[dict]:
    """Residual harmonics in each adjacent pair's relative rotation (module docstring)."""
    n = robot.n
    out = []
    for i in range(n - 1):
        phi = q[:, i] - q[:, i + 1]
        X = np.stack([np.ones_like(phi), np.cos(phi), np.sin(phi), np.cos(2 * phi),
                      np.sin(2 * phi)], axis=1)
        spread = float(np.ptp(np.mod(phi, 2 * math.pi))) if len(phi) else 0.0
        item: dict = {"pair": [i + 1, i + 2], "relative_rotation_range_deg": math.degrees(spread)}
        if len(phi) < 12 or spread < math.pi / 2:
            item.update({"tested": False, "why": "the relative rotation covers less than 90 deg"})
            out.append(item)
            continue
        orders = (1, 2) if spread >= 1.5 * math.pi else (1,)
        X = X[:, : 1 + 2 * len(orders)]
        Xs = X / np.maximum(np.linalg.norm(X, axis=0), 1e-12)
        if np.linalg.cond(Xs) > 30.0:
            item.update({"tested": False, "why": "the relative rotation does not vary enough "
                         "independently of its harmonics (ill-conditioned)"})
            out.append(item)
            continue
        coef, r2, p = _ftest(X, res)
        harm = []
        for h in orders:
            C = coef[2 * h - 1: 2 * h + 1]                     # (2, 3): cos, sin rows
            u, s, vt = np.linalg.svd(C)
            axis = vt[0]
            a, b = C @ axis                                    # along the dominant direction
            amp = float(math.hypot(a, b))
            phase = float(math.degrees(math.atan2(b, a)) % 360.0)   # peak at phi = phase
            harm.append({"order": h, "amplitude_mm": amp, "phase_deg": phase,
                         "direction": axis.tolist()})
        floor = (noise_sd or 0.0)
        item.update({"tested": True, "harmonics": harm, "r2": r2, "p_value": p,
                     "significant": bool(p < P_SIGNIFICANT and sum(x["amplitude_mm"] for x in harm)
                                         > 2 * floor)})
        out.append(item)
    return out


def insertion_trend(robot: Robot, q: np.ndarray, res: np.ndarray) -> dict:
    ins = robot.tip_length(q)
    if np.ptp(ins) < 1e-6 or len(ins) < 8:
        return {"tested": False, "why": "insertion does not vary"}
    x = (ins - ins.mean()) / max(np.ptp(ins), 1e-9)
    X = np.stack([np.ones_like(x), x], axis=1)
    coef, r2, p = _ftest(X, res)
    slope = coef[1] / max(np.ptp(ins), 1e-9)
    return {"tested": True, "slope_mm_per_mm": slope.tolist(),
            "slope_norm": float(np.linalg.norm(slope)), "insertion_range_mm": float(np.ptp(ins)),
            "r2": r2, "p_value": p, "significant": bool(p < P_SIGNIFICANT and r2 > 0.05)}


def kabsch(P: np.ndarray, Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotation R and translation t minimising |R P + t - Q| (rows are points)."""
    pc, qc = P.mean(0), Q.mean(0)
    H = (P - pc).T @ (Q - qc)
    U, _, Vt = np.linalg.svd(H)
    d = np.sign(np.linalg.det(Vt.T @ U.T)) or 1.0
    D = np.diag([1.0, 1.0, d])
    R = Vt.T @ D @ U.T
    return R, qc - R @ pc


def procrustes(pred: np.ndarray, meas: np.ndarray, noise_sd: float | None) -> dict:
    if len(pred) < 4:
        return {"tested": False, "why": "too few rows"}
    R, t = kabsch(pred, meas)
    after = pred @ R.T + t - meas
    before = pred - meas
    ss0 = float((before ** 2).sum())
    ss1 = float((after ** 2).sum())
    frac = 1.0 - ss1 / ss0 if ss0 > 0 else 0.0
    ang = float(math.degrees(math.acos(max(-1.0, min(1.0, (np.trace(R) - 1) / 2)))))
    floor = 3 * len(pred) * (noise_sd or 0.0) ** 2
    excess = max(ss0 - floor, 0.0)
    frac_excess = (ss0 - ss1) / excess if excess > 0 else 0.0
    return {"tested": True, "rotation_deg": ang, "translation_mm": t.tolist(),
            "rms_before_mm": math.sqrt(ss0 / len(pred)), "rms_after_mm": math.sqrt(ss1 / len(pred)),
            "fraction_explained": frac, "fraction_of_excess_explained": float(min(frac_excess, 1.0)),
            "significant": bool(frac_excess > 0.5 and frac > 0.1)}


def time_trend(time: np.ndarray | None, res: np.ndarray) -> dict:
    if time is None or len(time) < 8 or np.ptp(time) <= 0:
        return {"tested": False, "why": "no time column"}
    x = (time - time.mean()) / np.ptp(time)
    X = np.stack([np.ones_like(x), x, x ** 2], axis=1)
    _, r2, p = _ftest(X, res)
    return {"tested": True, "r2": r2, "p_value": p, "significant": bool(p < P_SIGNIFICANT and r2 > 0.1)}


def position_field(pred: np.ndarray, meas: np.ndarray, res: np.ndarray) -> dict:
    """A quadratic field of the measured tip position, after the best rigid transform."""
    if len(meas) < 30:
        return {"tested": False, "why": "too few rows"}
    R, t = kabsch(pred, meas)
    r = pred @ R.T + t - meas
    c = meas - meas.mean(0)
    s = max(float(np.abs(c).max()), 1e-9)
    c = c / s
    X = np.hstack([np.ones((len(c), 1)), c, c ** 2, c[:, [0]] * c[:, [1]], c[:, [0]] * c[:, [2]],
                   c[:, [1]] * c[:, [2]]])
    _, r2, p = _ftest(X, r)
    return {"tested": True, "r2": r2, "p_value": p, "significant": bool(p < P_SIGNIFICANT and r2 > 0.1)}


def relative_rotation_field(robot: Robot, q: np.ndarray, res: np.ndarray) -> dict:
    """Variance of the residual explained by harmonics of every pair's relative rotation."""
    n = robot.n
    if n < 2 or len(q) < 20:
        return {"tested": False}
    cols = [np.ones(len(q))]
    for i in range(n - 1):
        phi = q[:, i] - q[:, i + 1]
        cols += [np.cos(phi), np.sin(phi), np.cos(2 * phi), np.sin(2 * phi)]
    _, r2, p = _ftest(np.stack(cols, 1), res)
    return {"tested": True, "r2": r2, "p_value": p, "significant": bool(p < P_SIGNIFICANT and r2 > 0.1)}


def direction_field(q: np.ndarray, res: np.ndarray, direction: np.ndarray) -> dict:
    n = q.shape[1] // 2
    d = np.asarray(direction, dtype=float)[:, :n]
    if not np.any(d != 0) or len(q) < 20:
        return {"tested": False}
    _, r2, p = _ftest(np.hstack([np.ones((len(q), 1)), d]), res)
    return {"tested": True, "r2": r2, "p_value": p, "significant": bool(p < P_SIGNIFICANT and r2 > 0.05)}


def collect(robot: Robot, q: np.ndarray, pred_tip: np.ndarray, meas_tip: np.ndarray,
            sweep: np.ndarray, time: np.ndarray | None, ordered: bool = True,
            noise: dict | None = None, rows: np.ndarray | None = None) -> dict:
    """All evidence for one model's residual (JSON-ready), on the rows ``rows`` ((B,) bool;
    default all). The direction of motion comes from the order of all rows (the commanded
    history); the noise floor's second differences run along contiguous runs of ``rows``
    within a sweep (never across a held-out block)."""
    direction = direction_from_rows(q, sweep) if ordered else np.zeros(q.shape, dtype=np.int8)
    res = pred_tip - meas_tip
    keep = np.all(np.isfinite(res), axis=1)
    seg = np.asarray(sweep)
    if rows is not None:
        seg = contiguous_runs(np.asarray(rows, dtype=bool), seg)
        keep &= np.asarray(rows, dtype=bool)
    q, res, pred_tip, meas_tip = q[keep], res[keep], pred_tip[keep], meas_tip[keep]
    direction, seg = direction[keep], seg[keep]
    time = None if time is None else time[keep]
    nf = noise or noise_floor(q, res, seg, direction, ordered)
    sd = nf.get("sd_mm")
    rms = float(np.sqrt((res ** 2).sum(1).mean())) if len(res) else math.nan
    return {
        "rows": int(len(q)), "distinct_configurations": distinct_configurations(q),
        "residual_rms_mm": rms, "noise": nf,
        "excess_rms_mm": float(math.sqrt(max(rms ** 2 - 3 * (sd or 0.0) ** 2, 0.0))),
        "hysteresis": hysteresis(q, res, direction, sd) if ordered else
        {"tested": False, "why": "rows are not in order of motion (no direction known)"},
        "harmonics": harmonics(robot, q, res, sd),
        "insertion": insertion_trend(robot, q, res),
        "procrustes": procrustes(pred_tip, meas_tip, sd),
        "time": time_trend(time, res),
        "position": position_field(pred_tip, meas_tip, res),
        "relative_rotation": relative_rotation_field(robot, q, res),
        "direction": direction_field(q, res, direction) if ordered else {"tested": False},
    }


#: a row is a measurement glitch when its residual jumps from the mean of its two neighbours'
#: by more than this many robust sd of such jumps (and by more than its neighbours do)
GLITCH_SD = 8.0


def glitches(res: np.ndarray, sweep: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """(B,) bool: rows of ``rows`` whose measurement jumped (a tracker glitch), from the
    residual ``res`` (B, 3) of any smooth model (the base model's): the second difference
    ``r_k - (r_(k-1) + r_(k+1)) / 2`` along contiguous runs of ``rows`` within a sweep exceeds
    :data:`GLITCH_SD` robust sd (the MAD of those differences, per axis) and is the largest of
    its neighbours'. A smooth model error barely changes from one row to the next of a slow
    motion; a glitch of a few mm stands out by orders of magnitude. Rows at the ends of a run,
    and unordered data (pass ``rows`` all False), are never flagged."""
    res = np.asarray(res, dtype=float)
    out = np.zeros(len(res), dtype=bool)
    runs = contiguous_runs(np.asarray(rows, dtype=bool), sweep)
    inner = np.zeros(len(res), dtype=bool)
    inner[1:-1] = (runs[1:-1] >= 0) & (runs[:-2] == runs[1:-1]) & (runs[2:] == runs[1:-1])
    idx = np.flatnonzero(inner & np.all(np.isfinite(res), axis=1))
    if len(idx) < 10:
        return out
    d = res[idx] - 0.5 * (res[idx - 1] + res[idx + 1])
    d = np.where(np.isfinite(d), d, 0.0)
    scale = np.median(np.abs(d - np.median(d, axis=0)), axis=0) * 1.4826
    size = np.linalg.norm(d / np.maximum(scale, 1e-9), axis=1)
    big = np.zeros(len(res))
    big[idx] = size
    peak = (big[idx] >= big[idx - 1]) & (big[idx] >= big[idx + 1])
    out[idx[(size > GLITCH_SD) & peak]] = True
    return out


def contiguous_runs(rows: np.ndarray, sweep: np.ndarray) -> np.ndarray:
    """(B,) int label of the contiguous run of selected ``rows`` within a sweep each row is in
    (a new run after every unselected row and at every sweep change; unselected rows: -1)."""
    sw = np.asarray(sweep)
    out = np.full(len(rows), -1, dtype=np.int64)
    idx = np.flatnonzero(rows)
    if len(idx):
        brk = np.ones(len(idx), dtype=bool)
        brk[1:] = (np.diff(idx) != 1) | (sw[idx[1:]] != sw[idx[:-1]])
        out[idx] = np.cumsum(brk)
    return out


#: which evidence supports which effect (shown in the report for each named effect)
SUPPORT = {
    "clearance": ("harmonics",),
    "friction": ("hysteresis", "direction"),
    "torsion": ("harmonics", "insertion"),
    "precurvature": ("insertion", "harmonics"),
    "stiffness": ("harmonics", "insertion"),
    "registration": ("procrustes",),
    "joint_offset": ("harmonics", "insertion"),
    "load": ("insertion", "procrustes"),
}


def supporting(effect: str, ev: dict) -> list[str]:
    """Human-readable lines: the evidence (significant tests) that supports ``effect``."""
    out = []
    for key in SUPPORT.get(effect, ()):
        item = ev.get(key)
        if key == "harmonics":
            for h in item or []:
                if h.get("significant"):
                    a = h["harmonics"][0]
                    out.append(f"residual harmonic in the relative rotation of tubes "
                               f"{h['pair'][0]}-{h['pair'][1]}: {a['amplitude_mm']:.2f} mm at "
                               f"{a['phase_deg']:.0f} deg (p = {h['p_value']:.1e})")
        elif item and item.get("significant"):
            if key == "hysteresis":
                out.append(f"hysteresis: opposite-direction neighbours differ by "
                           f"{item['median_gap_mm']:.2f} mm more (ratio {item['ratio']:.1f}, "
                           f"p = {item['p_value']:.1e})")
            elif key == "procrustes":
                out.append(f"rigid transform removes {100 * item['fraction_explained']:.0f} % of "
                           f"the residual (rotation {item['rotation_deg']:.2f} deg)")
            elif key == "insertion":
                out.append(f"trend with insertion: {item['slope_norm']:.3f} mm/mm "
                           f"(r2 {item['r2']:.2f}, p = {item['p_value']:.1e})")
            elif key == "direction":
                out.append(f"residual depends on the direction of motion (r2 {item['r2']:.2f})")
    return out
