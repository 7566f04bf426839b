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

from ctrplan.shape._kernel import UnloadedProblem, unloaded_work
from ctrplan.shape._ode import (
    _tube_events,
    det,
    events,
    finish_row,
    newton,
    newton_work,
    outputs,
    row_grid,
    runtime,
    store_row,
)

#: a step is accepted without the backward check when the corrector moved the solution by at
#: most this fraction of the predictor's extrapolation (a smooth branch: O(h) smaller)
SMOOTH = 0.25


@njit(cache=True, error_model="numpy", _nrt=False)
def _wrap(d):
    return d - 2.0 * math.pi * math.floor((d + math.pi) / (2.0 * math.pi))


@njit(cache=True, error_model="numpy", _nrt=False)
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


@njit(cache=True, error_model="numpy", inline="always")
def _predict(x, xp, xn, have_xp, u1, u_x, u_xp):
    """xn = the last two accepted points (x at u_x, xp at u_xp) extrapolated to u1."""
    for i in range(x.shape[0]):
        xn[i] = x[i]
        if have_xp and u_x - u_xp > 0.0:
            xn[i] += (x[i] - xp[i]) * (u1 - u_x) / (u_x - u_xp)


@njit(cache=True, error_model="numpy", inline="always")
def _smooth(x, xp, xn, u1, u_x, u_xp, same):
    """The corrector moved the solution by much less than the step moved the predictor: the
    branch extrapolated smoothly (no other stable equilibrium lies that close to the
    continuation; a jump moves by the branches' gap)."""
    corr = 0.0
    pred = 0.0
    for i in range(x.shape[0]):
        p_i = x[i] + (x[i] - xp[i]) * (u1 - u_x) / (u_x - u_xp) if u_x - u_xp > 0.0 else x[i]
        corr = max(corr, abs(xn[i] - p_i))
        pred = max(pred, abs(p_i - x[i]))
    return corr <= SMOOTH * pred + 1e-3 * same


@njit(cache=True, error_model="numpy", inline="always")
def _goes_back(bprob, t, bi, rows, x, xn, xb, same, tol, max_iter, out_s, no_p, nw):
    """Backward check: Newton at the previous accepted point (fraction t of the row step)
    from the new solution xn must come back to x. Returns (passed, iterations)."""
    alpha, beta, kappa, EI, ratio, kink = rows
    for i in range(x.shape[0]):
        xb[i] = xn[i]
    _blend(t, bi - 1, bi, alpha, beta, kappa, EI, ratio, kink, bprob.alpha, bprob.beta,
           bprob.kappa, bprob.EI, bprob.ratio, bprob.kink)
    _tube_events(bprob.beta, bprob.L, bprob.straight, bprob.tpos, bprob.ttyp, bprob.tidx)
    rb, itb, _s = newton(bprob, xb, tol, max_iter, runtime(False), out_s, 0, no_p, nw)
    back = 0.0
    for i in range(x.shape[0]):
        back = max(back, abs(xb[i] - x[i]))
    return rb < tol and back <= same, itb


@njit(cache=True, error_model="numpy", inline="always")
def _corrector(prob, bprob, t1, last, bi, rows, xn, tol, max_iter, out_s, m, pts, no_p, nw):
    """Newton from the prediction xn (in place) at fraction t1 of the row step: at the row
    itself (``last``: with its output points) or at the blended configuration."""
    if last:
        _tube_events(prob.beta, prob.L, prob.straight, prob.tpos, prob.ttyp, prob.tidx)
        return newton(prob, xn, tol, max_iter, runtime(True), out_s, m, pts, nw)
    alpha, beta, kappa, EI, ratio, kink = rows
    _blend(t1, bi - 1, bi, alpha, beta, kappa, EI, ratio, kink, bprob.alpha, bprob.beta,
           bprob.kappa, bprob.EI, bprob.ratio, bprob.kink)
    _tube_events(bprob.beta, bprob.L, bprob.straight, bprob.tpos, bprob.ttyp, bprob.tidx)
    return newton(bprob, xn, tol, max_iter, runtime(False), out_s, 0, no_p, nw)


@njit(cache=True, error_model="numpy", inline="always")
def _continue_row(prob, bprob, bi, rows, dist, levels, have_xp, tol, max_iter, out_s, m, pts,
                  no_p, nw, cw):
    """Row bi continues the branch of row bi - 1 (cw: x at u[0] and the point before, xp at
    u[1]; xn, xb workspace): steps from the last accepted point, doubled after an accepted
    one and halved after a rejected one (down to 2**-levels of the row step). Returns (reached
    the row, iterations, residual, det J, pts hold x's backbone, have_xp)."""
    x, xp, xn, xb, u = cw
    n = x.shape[0]
    kappa = rows[2]
    amp = 0.0
    for i in range(n):
        amp = max(amp, abs(kappa[bi - 1, i]), abs(kappa[bi, i]))
    same = max(1e-4 * amp, 1e-12)
    t = 0.0
    h = 1.0
    hmin = 0.5 ** levels
    u0 = u[0]
    total = 0
    done = False
    shaped = False
    r = math.inf
    dj = math.nan
    while not done:
        t1 = min(1.0, t + h)
        last = t1 >= 1.0
        u1 = u0 + t1 * dist[bi]
        _predict(x, xp, xn, have_xp, u1, u[0], u[1])
        r, it, shaped = _corrector(prob, bprob, t1, last, bi, rows, xn, tol, max_iter, out_s, m,
                                   pts, no_p, nw)
        total += it
        dj = det(nw[1], nw[6])
        good = r < tol and dj > 0.0
        smooth = good and have_xp and _smooth(x, xp, xn, u1, u[0], u[1], same)
        if good and not smooth:
            good, itb = _goes_back(bprob, t, bi, rows, x, xn, xb, same, tol, max_iter, out_s,
                                   no_p, nw)
            total += itb
        if good:
            for i in range(n):
                xp[i] = x[i]
                x[i] = xn[i]
            u[1] = u[0]
            u[0] = u0 + t1 * dist[bi]
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
    return done, total, r, dj, shaped, have_xp


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
    out = outputs(B, m, n)
    points, iters, rnorm = out[0], out[3], out[4]
    rnorm[:] = math.inf
    detj = np.full(B, np.nan)
    cont = np.zeros(B, dtype=np.bool_)
    work = unloaded_work(n)
    tpos, ttyp, tidx = events(n)
    nw = newton_work(n)
    out_s = np.zeros(m)
    no_p = np.zeros((0, 3))
    # the branch's solution at the last accepted point, at the one before (predictor), trial,
    # backward check; their metric positions along the chain
    cw = (np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(n), np.zeros(2))
    x, u = cw[0], cw[4]
    have_xp = False
    bprob = UnloadedProblem(np.zeros(n), np.zeros(n), L, straight, np.zeros(n), np.zeros(n),
                            np.zeros(n), np.zeros((n, 2)), True, step, tpos, ttyp, tidx, work)
    rows = (alpha, beta, kappa, EI, ratio, kink)
    for bi in range(B):
        prob = UnloadedProblem(alpha[bi], beta[bi], L, straight, kappa[bi], EI[bi], ratio[bi],
                               kink[bi], True, step, tpos, ttyp, tidx, work)
        pts = points[bi]
        row_grid(beta[bi], L, straight, m, tpos, ttyp, tidx, out_s)
        if start[bi] or bi == 0:
            for i in range(n):
                x[i] = x_init[bi, i]
            r, it, shaped = newton(prob, x, tol, max_iter, runtime(True), out_s, m, pts, nw)
            dj = det(nw[1], nw[6])
            iters[bi] = it
            rnorm[bi] = r
            detj[bi] = dj
            cont[bi] = r < tol and dj > 0.0
            u[0] = 0.0
            have_xp = False
        elif not cont[bi - 1]:
            shaped = False            # the branch ended earlier in this chain
        else:
            done, total, r, dj, shaped, have_xp = _continue_row(
                prob, bprob, bi, rows, dist, levels, have_xp, tol, max_iter, out_s, m, pts, no_p,
                nw, cw)
            # events of this row again (substeps overwrote them)
            _tube_events(beta[bi], L, straight, tpos, ttyp, tidx)
            iters[bi] = total
            if done:
                rnorm[bi] = r
                detj[bi] = dj
                cont[bi] = True
        finite = finish_row(prob, x, shaped, out_s, m, pts, nw)
        store_row(out, bi, out_s, x, iters[bi], rnorm[bi], cont[bi] and finite and rnorm[bi] < tol)
    return out + (detj, cont)

# numba cache stamp: d8f966079f52654bec9904c45b481f0c7a18363c5bbb5d76c49e39122e994b7c
