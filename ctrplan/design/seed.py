"""Where the search starts: one pre-curved tube fitted to the corridors.

A single tube of curvature ``kappa`` and curved length ``C``, its curved section starting
``d_j`` mm in front of the base and bending toward ``phi_j``, has a closed-form backbone (a
straight segment, then a circular arc). :func:`fit_arc` fits one ``(kappa, C)`` to every
corridor at once (each target with its own ``d_j``, ``phi_j``; scipy's ``least_squares``) so
that the tip reaches the target, the arc stays inside the corridor (each point of it no farther
from the centreline than the clearance there less the thinnest tube's radius) and the arc fits
the room at the entry (the retracted robot protrudes ``C``). The fit is the search's first
guess for the innermost tube (the others start straight and short); CMA-ES does the rest. It
ignores how tubes bend each other, so it only ever seeds the search: every design is still
screened and planned.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Curvatures (1/mm) the fit starts from (the best result is kept).
STARTS = (0.005, 0.02, 0.05)


@dataclass(frozen=True)
class ArcFit:
    """The fitted tube: curvature (1/mm), curved length and the straight length in front of
    the base per target (mm), the tip error per target (mm) and the worst excursion out of a
    corridor (mm)."""

    kappa: float
    curved: float
    depth: tuple[float, ...]
    tip_error: tuple[float, ...]
    excursion: float


def _arc(d: float, k: float, C: float, phi: float, s: np.ndarray) -> np.ndarray:
    """Backbone points (len(s), 3) base frame at arc lengths s along the curved part (0..C),
    after d mm of straight insertion."""
    k = max(k, 1e-6)
    th = k * s
    r = (1 - np.cos(th)) / k
    return np.column_stack([math.cos(phi) * r, math.sin(phi) * r, d + np.sin(th) / k])


def fit_arc(anatomy, pose: np.ndarray, radius: float, curvature: tuple[float, float],
            curved: tuple[float, float]) -> ArcFit | None:
    """Fit one arc to the open corridors (module docstring). ``pose``: base pose (4, 4);
    ``radius``: the thinnest tube's radius (mm); ``curvature``, ``curved``: the ranges."""
    from scipy.optimize import least_squares

    routes = [r for r in anatomy.routes if r.connected and len(r.s) > 1]
    if not routes:
        return None
    R, t = pose[:3, :3], pose[:3, 3]
    tips = [R.T @ (r.target - t) for r in routes]
    cls = [(r.centreline - t) @ R for r in routes]
    slack = [np.maximum(r.clearance - radius, 0.0) for r in routes]
    u = np.linspace(0.0, 1.0, 12)
    n = len(routes)

    def unpack(x):
        return x[0], x[1], x[2:2 + n], x[2 + n:]

    def residuals(x):
        k, C, d, phi = unpack(x)
        out = []
        for j in range(n):
            p = _arc(d[j], k, C, phi[j], u * C)
            out.extend(p[-1] - tips[j])
            # straight part and arc inside the corridor (distance to the centreline beyond the slack)
            pts = np.vstack([np.column_stack([np.zeros(4), np.zeros(4), np.linspace(0, d[j], 4)]), p])
            dist = np.linalg.norm(pts[:, None, :] - cls[j][None], axis=2)
            i = np.argmin(dist, axis=1)
            out.extend(2.0 * np.maximum(dist[np.arange(len(pts)), i] - slack[j][i], 0.0))
        room = anatomy.entry.longest(radius, k)
        out.append(2.0 * max(C - room, 0.0))
        return np.asarray(out)

    lo = [curvature[0], curved[0]] + [0.0] * n + [-4 * math.pi] * n
    hi = [max(curvature[1], curvature[0] + 1e-6), max(curved[1], curved[0] + 1e-6)] \
        + [max(np.linalg.norm(p) for p in tips) + 10.0] * n + [4 * math.pi] * n
    best = None
    for k0 in STARTS:
        k0 = float(np.clip(k0, lo[0], hi[0]))
        C0 = float(np.clip(min(curved[1], 0.5 * math.pi / max(k0, 1e-3)), lo[1], hi[1]))
        d0 = [float(np.clip(p[2] - math.sin(k0 * C0) / max(k0, 1e-6), 0.0, hi[2])) for p in tips]
        phi0 = [math.atan2(p[1], p[0]) for p in tips]
        x0 = np.clip(np.array([k0, C0] + d0 + phi0), lo, hi)
        res = least_squares(residuals, x0, bounds=(lo, hi), max_nfev=200, x_scale="jac")
        if best is None or res.cost < best.cost:
            best = res
    k, C, d, phi = unpack(best.x)
    errs = []
    exc = 0.0
    for j in range(n):
        p = _arc(d[j], k, C, phi[j], u * C)
        errs.append(float(np.linalg.norm(p[-1] - tips[j])))
    r = residuals(best.x)
    exc = float(np.max(np.abs(r[3:]), initial=0.0)) / 2.0
    return ArcFit(float(k), float(C), tuple(float(v) for v in d), tuple(errs), exc)


def start_point(space, k: int, fit: ArcFit | None) -> np.ndarray:
    """The search's start (dim,) in the unit cube for designs of k tubes: the fitted arc for the
    innermost tube (its straight length reaching the deepest target), the others straight and
    short, the middle of the allowed stock sizes; the centre of the cube without a fit."""
    from ctrplan.design.space import PER_TUBE

    x = np.full(space.dim, 0.5)
    if fit is None or space.derived is None:
        return x
    r = space.derived.ranges(0)
    x[0] = _unit(fit.kappa, r.curvature)
    od = space.stock[r.sizes[len(r.sizes) // 2]][0]            # the size x[3] = 0.5 picks
    cap = max(r.curved_length[0], min(r.curved_length[1], space.derived.curved_cap(od / 2, fit.kappa)))
    x[1] = _unit(fit.curved, (r.curved_length[0], cap))
    x[2] = _unit(max(fit.depth) + 5.0, r.straight_length)
    for i in range(1, k):
        x[PER_TUBE * i: PER_TUBE * i + 3] = (0.05, 0.1, 0.3)
    return x


def _unit(v: float, rng: tuple[float, float]) -> float:
    lo, hi = rng
    return float(np.clip((v - lo) / (hi - lo), 0.0, 1.0)) if hi > lo else 0.5
