"""Continuation of the compliant model's equilibrium along a motion (numba kernel).

A motion is a sequence of configurations (rows of a batch). The physical robot does not pick
an equilibrium per configuration: it stays on the equilibrium it is on, deformed continuously,
until that equilibrium stops existing (a fold of the equilibrium branch, where a stable and an
unstable branch meet and det J passes zero; the robot then snaps). :func:`solve_chain` follows
that branch: each row of a chain is solved by Newton started from the previous row's solution
(extrapolated along the branch), with no search for other equilibria.

Acceptance of a step (row a -> row b, or a part of it). Newton from the predicted uz(0) at b
must converge to a stable equilibrium (det of the shooting Jacobian > 0) from which Newton at
a converges back to a's equilibrium (max norm within ``1e-4 x max |kappa|``). The second
condition is what catches a jump: when the branch ends between a and b, Newton lands on another
equilibrium at b, and from there Newton at a finds that other branch's equilibrium at a (in a
bistable range both exist), not the one the robot is on. A step that fails is halved, down to
``2**-levels`` of the row step; a part that still fails ends the branch: that row and the rest
of its chain are not continued (``cont`` False). Between rows the configuration (rotations
along the shorter arc) and the per-row mechanics (curvatures, stiffnesses, kinks) are
interpolated linearly: the homotopy the continuation follows.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ctrplan.shape._kernel import _integrate, _tube_events, runtime
from ctrplan.shape._shooting import _det, _newton

#: a step is accepted without the backward check when the corrector moved the solution by at
#: most this fraction of the predictor's extrapolation (a smooth branch: O(h) smaller)
SMOOTH = 0.25


@njit(cache=True, error_model="numpy")
def _wrap(d):
    return d - 2.0 * math.pi * math.floor((d + math.pi) / (2.0 * math.pi))


@njit(cache=True, error_model="numpy")
def _blend(t, ra, rb, alpha, beta, kappa, EI, ratio, kink, al, be, ka, ei, rt, kk):
    """Row ra's configuration and mechanics moved a fraction t toward row rb's (rotations along
    the shorter arc), written into al, be, ka, ei, rt, kk."""
    n = alpha.shape[1]
    for i in range(n):
        al[i] = alpha[ra, i] + t * _wrap(alpha[rb, i] - alpha[ra, i])
        be[i] = beta[ra, i] + t * (beta[rb, i] - beta[ra, i])
        ka[i] = kappa[ra, i] + t * (kappa[rb, i] - kappa[ra, i])
        ei[i] = EI[ra, i] + t * (EI[rb, i] - EI[ra, i])
        rt[i] = ratio[ra, i] + t * (ratio[rb, i] - ratio[ra, i])
        for c in range(2):
            kk[i, c] = kink[ra, i, c] + t * (kink[rb, i, c] - kink[ra, i, c])


@njit(cache=True, error_model="numpy")
def solve_chain(alpha, beta, L, straight, kappa, EI, ratio, kink, m, step, tol, max_iter,
                x_init, start, dist, levels):
    """Solve a batch whose rows are chains of consecutive states of motions.

    alpha, beta : (B, n) rad, mm; L, straight : (n,) mm; kappa, EI, ratio : (B, n);
    kink : (B, n, 2) rad; x_init : (B, n) 1/mm, the uz(0) a chain starts from (read on rows
    with ``start``; Newton from it, no search for other equilibria); start : (B,) bool, the
    row starts a chain (row 0 always does); dist : (B,) mm, the metric distance from the
    previous row (scales the predictor); levels : halvings of a row step allowed.

    Returns points (B, m, 3), s (B, m), uz0 (B, n), iters (B,), residual (B,), ok (B,),
    detj (B,), cont (B,) bool: the row's equilibrium is the continuation of its chain start's
    (stable, reached without a jump); False from the first row where the branch ended, or
    where the start itself is not a stable equilibrium. ``ok`` is the solve's own verdict
    (converged, finite), False where not ``cont``.
    """
    B, n = alpha.shape
    points = np.zeros((B, m, 3))
    svals = np.zeros((B, m))
    uz0 = np.zeros((B, n))
    iters = np.zeros(B, dtype=np.int64)
    rnorm = np.full(B, np.inf)
    ok = np.zeros(B, dtype=np.bool_)
    detj = np.full(B, np.nan)
    cont = np.zeros(B, dtype=np.bool_)
    nst = 3 * n + 12
    y = np.zeros(nst)
    Y = np.zeros((2 * n, n))
    a = np.zeros(n)
    w = np.zeros(n)
    pend = np.zeros(n)
    ws = np.zeros((5, nst))
    WS = np.zeros((5, 2 * n, n))
    G = np.zeros((3, 3))
    tpos = np.zeros(2 * n)
    ttyp = np.zeros(2 * n, dtype=np.int64)
    tidx = np.zeros(2 * n, dtype=np.int64)
    resid = np.zeros(n)
    jac = np.zeros((n, n))
    resid_t = np.zeros(n)
    jac_t = np.zeros((n, n))
    A = np.zeros((n, n))
    dx = np.zeros(n)
    xt = np.zeros(n)
    out_s = np.zeros(m)
    no_p = np.zeros((0, 3))
    x = np.zeros(n)          # the branch's solution at the last accepted point
    xp = np.zeros(n)         # ... and at the one before (predictor)
    xn = np.zeros(n)         # trial solution
    xb = np.zeros(n)         # backward check
    al = np.zeros(n)
    be = np.zeros(n)
    ka = np.zeros(n)
    ei = np.zeros(n)
    rt = np.zeros(n)
    kk = np.zeros((n, 2))
    u_x = 0.0                # metric position of x and of xp along the chain
    u_xp = 0.0
    have_xp = False
    for bi in range(B):
        pts = points[bi]
        _tube_events(beta[bi], L, straight, tpos, ttyp, tidx)
        tip = tpos[2 * n - 1]
        for k in range(m):
            out_s[k] = tip * k / (m - 1) if m > 1 else tip
        out_s[m - 1] = tip
        if start[bi] or bi == 0:
            for i in range(n):
                x[i] = x_init[bi, i]
            r, it, shaped = _newton(alpha[bi], beta[bi], x, L, straight, kappa[bi], EI[bi],
                                    ratio[bi], kink[bi], tpos, ttyp, tidx, out_s, m, step, tol,
                                    max_iter, runtime(True), pts, resid, jac, resid_t, jac_t,
                                    dx, xt, A, y, Y, a, w, pend, ws, WS, G)
            dj = _det(jac, A)
            iters[bi] = it
            rnorm[bi] = r
            detj[bi] = dj
            cont[bi] = r < tol and dj > 0.0
            u_x = 0.0
            have_xp = False
        elif not cont[bi - 1]:
            shaped = False            # the branch ended earlier in this chain
        else:
            amp = 0.0
            for i in range(n):
                amp = max(amp, abs(kappa[bi - 1, i]), abs(kappa[bi, i]))
            same = max(1e-4 * amp, 1e-12)
            t = 0.0
            h = 1.0
            hmin = 0.5 ** levels
            u0 = u_x
            total = 0
            done = False
            shaped = False
            r = math.inf
            dj = math.nan
            while not done:
                t1 = min(1.0, t + h)
                last = t1 >= 1.0
                # predictor: extrapolate the last two accepted points along the metric
                u1 = u0 + t1 * dist[bi]
                for i in range(n):
                    xn[i] = x[i]
                    if have_xp and u_x - u_xp > 0.0:
                        xn[i] += (x[i] - xp[i]) * (u1 - u_x) / (u_x - u_xp)
                if last:
                    _tube_events(beta[bi], L, straight, tpos, ttyp, tidx)
                    r, it, shaped = _newton(alpha[bi], beta[bi], xn, L, straight, kappa[bi],
                                            EI[bi], ratio[bi], kink[bi], tpos, ttyp, tidx,
                                            out_s, m, step, tol, max_iter, runtime(True), pts,
                                            resid, jac, resid_t, jac_t, dx, xt, A, y, Y, a, w,
                                            pend, ws, WS, G)
                else:
                    _blend(t1, bi - 1, bi, alpha, beta, kappa, EI, ratio, kink, al, be, ka, ei,
                           rt, kk)
                    _tube_events(be, L, straight, tpos, ttyp, tidx)
                    r, it, shaped = _newton(al, be, xn, L, straight, ka, ei, rt, kk, tpos, ttyp,
                                            tidx, out_s, 0, step, tol, max_iter, runtime(False),
                                            no_p, resid, jac, resid_t, jac_t, dx, xt, A, y, Y,
                                            a, w, pend, ws, WS, G)
                total += it
                dj = _det(jac, A)
                good = r < tol and dj > 0.0
                smooth = False
                if good and have_xp:
                    # the corrector moved the solution by much less than the step moved the
                    # predictor: the branch extrapolated smoothly (no other stable equilibrium
                    # lies that close to the continuation; a jump moves by the branches' gap)
                    corr = 0.0
                    pred = 0.0
                    for i in range(n):
                        p_i = x[i] + (x[i] - xp[i]) * (u1 - u_x) / (u_x - u_xp) if u_x - u_xp > 0.0 else x[i]
                        corr = max(corr, abs(xn[i] - p_i))
                        pred = max(pred, abs(p_i - x[i]))
                    smooth = corr <= SMOOTH * pred + 1e-3 * same
                if good and not smooth:
                    # backward: Newton at the previous accepted point from the new solution
                    for i in range(n):
                        xb[i] = xn[i]
                    _blend(t, bi - 1, bi, alpha, beta, kappa, EI, ratio, kink, al, be, ka, ei,
                           rt, kk)
                    _tube_events(be, L, straight, tpos, ttyp, tidx)
                    rb, itb, _s = _newton(al, be, xb, L, straight, ka, ei, rt, kk, tpos, ttyp,
                                          tidx, out_s, 0, step, tol, max_iter, runtime(False),
                                          no_p, resid_t, jac_t, resid, jac, dx, xt, A, y, Y, a,
                                          w, pend, ws, WS, G)
                    total += itb
                    back = 0.0
                    for i in range(n):
                        back = max(back, abs(xb[i] - x[i]))
                    good = rb < tol and back <= same
                if good:
                    for i in range(n):
                        xp[i] = x[i]
                        x[i] = xn[i]
                    u_xp = u_x
                    u_x = u0 + t1 * dist[bi]
                    have_xp = True
                    t = t1
                    done = last
                    h = min(2.0 * h, 1.0)
                else:
                    h *= 0.5
                    if h < hmin:
                        break
                if not done:
                    shaped = False
            # events and output arc lengths of this row again (substeps overwrote them)
            _tube_events(beta[bi], L, straight, tpos, ttyp, tidx)
            iters[bi] = total
            if done:
                rnorm[bi] = r
                detj[bi] = dj
                cont[bi] = True
        if not shaped:
            _integrate(alpha[bi], beta[bi], x, L, straight, kappa[bi], EI[bi], ratio[bi],
                       kink[bi], True, tpos, ttyp, tidx, out_s, m, step, runtime(True),
                       runtime(False), pts, resid_t, jac_t, y, Y, a, w, pend, ws, WS, G)
        finite = True
        for k in range(m):
            svals[bi, k] = out_s[k]
            for c in range(3):
                if not math.isfinite(pts[k, c]):
                    finite = False
        for i in range(n):
            uz0[bi, i] = x[i]
        ok[bi] = cont[bi] and finite and rnorm[bi] < tol
    return points, svals, uz0, iters, rnorm, ok, detj, cont
