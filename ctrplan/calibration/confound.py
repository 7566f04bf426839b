"""Which effects of a calibrated model the rows cannot tell apart (report.json ``confounded``).

A helper of the conclusion (not a stage): for every pair of effects in the calibrated model,
on the rows the parameters were fitted on,

* ``tip_change_correlation``: the cosine between the two effects' changes of the tips (the
  model's tips minus the tips with the effect switched off, stacked over rows and axes);
* ``share_a_by_b`` / ``share_b_by_a``: the share of one effect's tip change that a linear
  combination of the other's Jacobian columns reproduces (least squares of the change on the
  finite-difference derivatives of the tips in the other effect's fitted parameters).

A pair is *confounded* when either share reaches :data:`CONFOUND_SHARE`: what one effect does to
the tips, the other's parameters can do as well (to first order), so the data do not say which
of the two is at work; the report lists the pair instead of crediting one of them alone.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence

import numpy as np

from ctrplan.calibration.lsq import Problem, param_scale
from ctrplan.shape.effects import effect_params

#: a pair of effects is confounded when a linear combination of one effect's Jacobian columns
#: reproduces at least this share of the other's tip change (sum of squares)
CONFOUND_SHARE = 0.9
#: finite-difference step, in units of each parameter's typical magnitude (as the fit's)
STEP = 1e-3


def confounded(prob: Problem, effects: Mapping[str, Mapping[str, float]],
               free: Mapping[str, Sequence[str]], rows: np.ndarray) -> list[dict]:
    """Confounded pairs among the fitted effects (module docstring), JSON-ready; one kernel
    call. prob : the problem the effects were fitted in; rows : (B,) bool, the rows compared."""
    names = [e for e in free if e in effects and free[e]]
    if len(names) < 2:
        return []
    sets: list[dict] = [dict(effects)]
    sets += [{k: v for k, v in effects.items() if k != e} for e in names]
    cols: dict[str, list[tuple[int, float]]] = {e: [] for e in names}
    for e in names:
        params = {p.name: p for p in effect_params(e, prob.robot, prob.model.base)}
        for nm in free[e]:
            p = params[nm]
            h = STEP * param_scale(p)
            v = float(effects[e][nm])
            step = h if v + h <= p.hi else -h
            sets.append({**effects, e: {**effects[e], nm: v + step}})
            cols[e].append((len(sets) - 1, step))
    tips = [p[:, -1][rows] for p in prob.predict_many(sets, rows)]
    ok = np.all([np.all(np.isfinite(t), axis=1) for t in tips], axis=0)
    if ok.sum() < 3:
        return []
    vec = [t[ok].ravel() for t in tips]
    change = {e: vec[0] - vec[1 + i] for i, e in enumerate(names)}
    jac = {e: np.stack([(vec[k] - vec[0]) / s for k, s in cols[e]], axis=1) for e in names}
    out = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            ab, ba = _share(change[a], jac[b]), _share(change[b], jac[a])
            na, nb = np.linalg.norm(change[a]), np.linalg.norm(change[b])
            corr = float(change[a] @ change[b] / (na * nb)) if na > 0 and nb > 0 else 0.0
            if max(ab, ba) >= CONFOUND_SHARE:
                out.append({"effects": [a, b], "tip_change_correlation": corr,
                            "share_a_by_b": ab, "share_b_by_a": ba,
                            "rows": int(ok.sum())})
    return out


def _share(d: np.ndarray, J: np.ndarray) -> float:
    """Share of ``d``'s sum of squares that least squares on the columns of ``J`` reproduces."""
    ss = float(d @ d)
    if ss <= 0 or not np.all(np.isfinite(J)):
        return 0.0
    c, *_ = np.linalg.lstsq(J, d, rcond=None)
    r = d - J @ c
    return float(max(0.0, 1.0 - (r @ r) / ss))


def describe(pairs: Sequence[dict]) -> list[str]:
    """One line per confounded pair (report.md and the warnings)."""
    return [f"{p['effects'][0]} and {p['effects'][1]} change the tips alike on these rows "
            f"(correlation {p['tip_change_correlation']:.2f}; {p['effects'][1]}'s parameters "
            f"reproduce {100 * p['share_a_by_b']:.0f} % of {p['effects'][0]}'s change, "
            f"{p['effects'][0]}'s {100 * p['share_b_by_a']:.0f} % of {p['effects'][1]}'s): the "
            "data cannot tell which of the two is at work" for p in pairs]
