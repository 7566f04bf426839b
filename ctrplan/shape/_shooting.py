"""Shooting for the compliant model: Newton on the base torsions ``uz(0)`` over a batch.

The integration passes (and the equations) are in :mod:`ctrplan.shape._kernel`; this module
holds the n x n Newton step, the per-configuration Newton loop with its line search and the
continuation fallback, and :func:`solve_batch`, the one entry point used by
:class:`ctrplan.shape.physics.PhysicsModel`.

Elastic stability of an unloaded equilibrium
--------------------------------------------
(Literature: Dupont et al., "Design and control of concentric-tube robots", T-RO 2010;
Gilbert, Hendrick, Webster, "Elastic stability of concentric tube robots: a stability measure
and design test", T-RO 2016; Ha, Park, Dupont, "Elastic stability of concentric tube robots
subject to external loads", T-BME 2016.) With no load the backbone curvature is the
stiffness-weighted mean of the rotated precurvatures, so the bending energy can be minimised
out pointwise and the elastic energy becomes a functional of the tube angles psi(s) alone:

    E[psi] = sum_i int_{beta_i}^{e_i} GJ_i psi_i'^2 / 2 ds + int V(psi, s) ds,
    V = -1 / (2 EIsum) sum_ij w_i w_j cos(psi_i - psi_j),   w_j = EI_j kappa_j (curved, present)

with psi_i(beta_i) = alpha_i (Dirichlet, at the actuator) and nothing imposed at the tube end
e_i = beta_i + L_i. Its Euler-Lagrange equations are the kernel's (GJ_i psi_i'' = dV/dpsi_i)
with the natural condition uz_i(e_i) = 0. An equilibrium is stable iff the second variation

    Q[eta] = sum_i int GJ_i eta_i'^2 + int eta^T H eta,   H = d^2 V / dpsi^2,  eta_i(beta_i) = 0

is positive definite. Its Jacobi fields with the Dirichlet end conditions are exactly the
variational solutions Newton integrates: eta = U c with U_i(s) = (s - beta_i) e_i behind the
constraint plane (d psi / d x, ``Y`` in the kernel) and K U'' = H U beyond, K = diag(GJ).
Q has a zero eigenvalue iff some c != 0 also meets the natural ends, U_i'(e_i) c = 0 for all
i, i.e. iff the shooting Jacobian J = d uz(e) / d uz(0) (J_ij = U_ij'(e_i)) is singular. More:
by Forman's theorem for Sturm-Liouville operators (the Gel'fand-Yaglom identity with mixed
boundary conditions) det(Q) / det(Q_0) = det J / det J_0, where Q_0 is the same operator with
H = 0, which is positive definite with J_0 = I. So sign(det J) = (-1)^(number of negative
eigenvalues of Q): det J > 0 is necessary for stability, and sufficient while the Morse index
is at most 1 (index 2 needs two negative modes of the relative twist at once, a much longer
or more compliant overlap than where snapping begins; not checked here. On the shipped
robots tests/test_stability.py checks the positive definiteness of an independently
discretised energy Hessian on every returned two_tube_nylon solution). Note det J is the ratio of two determinants and passes zero exactly at the
folds where a stable and an unstable branch meet (snap-through).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ctrplan.shape._kernel import _integrate, _tube_events, runtime

# numba caches this module's kernels with the _kernel functions they call compiled in, and
# checks only this file's time stamp: edit this file too when _kernel.py changes (last: the
# tie order of tube ends in _tube_events).


@njit(cache=True, error_model="numpy")
def _max_abs(v):
    m = 0.0
    for i in range(v.shape[0]):
        if not abs(v[i]) <= m:       # NaN propagates
            m = abs(v[i])
    return m


@njit(cache=True, error_model="numpy")
def _newton_step(jac, resid, dx, A):
    """dx = -jac^{-1} resid by Gaussian elimination with partial pivoting (n is tiny).
    Returns False when the Jacobian is singular or not finite."""
    n = resid.shape[0]
    for i in range(n):
        for j in range(n):
            A[i, j] = jac[i, j]
        dx[i] = -resid[i]
    for k in range(n):
        p = k
        big = abs(A[k, k])
        for i in range(k + 1, n):
            if abs(A[i, k]) > big:
                big = abs(A[i, k])
                p = i
        if not (big > 0.0) or not math.isfinite(big):
            return False
        if p != k:
            for j in range(n):
                t = A[k, j]
                A[k, j] = A[p, j]
                A[p, j] = t
            t = dx[k]
            dx[k] = dx[p]
            dx[p] = t
        inv = 1.0 / A[k, k]
        for i in range(k + 1, n):
            f = A[i, k] * inv
            if f != 0.0:
                for j in range(k + 1, n):
                    A[i, j] -= f * A[k, j]
                dx[i] -= f * dx[k]
    for k in range(n - 1, -1, -1):
        t = dx[k]
        for j in range(k + 1, n):
            t -= A[k, j] * dx[j]
        dx[k] = t / A[k, k]
    for i in range(n):
        if not math.isfinite(dx[i]):
            return False
    return True


@njit(cache=True, error_model="numpy")
def _det(jac, A):
    """Determinant of the n x n matrix ``jac`` (Gaussian elimination with partial pivoting in
    the workspace ``A``); NaN when ``jac`` is not finite."""
    n = jac.shape[0]
    for i in range(n):
        for j in range(n):
            A[i, j] = jac[i, j]
    det = 1.0
    for k in range(n):
        p = k
        big = abs(A[k, k])
        for i in range(k + 1, n):
            if abs(A[i, k]) > big:
                big = abs(A[i, k])
                p = i
        if not math.isfinite(big):
            return math.nan
        if big == 0.0:
            return 0.0
        if p != k:
            det = -det
            for j in range(n):
                t = A[k, j]
                A[k, j] = A[p, j]
                A[p, j] = t
        det *= A[k, k]
        inv = 1.0 / A[k, k]
        for i in range(k + 1, n):
            f = A[i, k] * inv
            if f != 0.0:
                for j in range(k + 1, n):
                    A[i, j] -= f * A[k, j]
    return det


@njit(cache=True, error_model="numpy")
def _newton(al, be, x, L, straight, ka, ei, ra, kk, tpos, ttyp, tidx, out_s, m, step, tol,
            max_iter, may_shape, pts, resid, jac, resid_t, jac_t, dx, xt, A,
            y, Y, a, w, pend, ws, WS, G):
    """Shooting on uz(0) = x (updated in place) by Newton with a backtracking line search.

    Returns (residual, iterations, shaped): ``shaped`` is True when the final frame pass
    (points into ``pts``) has already been run at the returned x (only if ``may_shape``).
    """
    n = x.shape[0]
    no_out = out_s[:0]
    no_p = pts[:0]
    on, off, zero = runtime(True), runtime(False), runtime(0)   # one compiled _integrate
    _integrate(al, be, x, L, straight, ka, ei, ra, kk, on, tpos, ttyp, tidx,
               no_out, zero, step, off, on, no_p, resid, jac, y, Y, a, w, pend, ws, WS, G)
    r = _max_abs(resid)
    it = 0
    quad = -1.0         # estimate of C in |resid after a full step| ~ C |dx|^2
    while r >= tol and it < max_iter and math.isfinite(r):
        it += 1
        if not _newton_step(jac, resid, dx, A):
            break
        dxn = _max_abs(dx)
        if may_shape and quad > 0.0 and quad * dxn * dxn < 0.1 * tol:
            # Newton is in its quadratic regime and predicts convergence: run the final
            # frame pass at the full step and read the residual from it (same step grid, so
            # the same residual), saving a sensitivity pass that would only confirm it
            for i in range(n):
                xt[i] = x[i] + dx[i]
            _integrate(al, be, xt, L, straight, ka, ei, ra, kk, on, tpos, ttyp, tidx,
                       out_s, m, step, on, off, pts, resid_t, jac_t,
                       y, Y, a, w, pend, ws, WS, G)
            rt = _max_abs(resid_t)
            if rt < tol:
                for i in range(n):
                    x[i] = xt[i]
                return rt, it, True
        t = 1.0
        accepted = False
        rt = r
        for _ls in range(8):
            for i in range(n):
                xt[i] = x[i] + t * dx[i]
            _integrate(al, be, xt, L, straight, ka, ei, ra, kk, on, tpos, ttyp, tidx,
                       no_out, zero, step, off, on, no_p, resid_t, jac_t,
                       y, Y, a, w, pend, ws, WS, G)
            rt = _max_abs(resid_t)
            if rt < r or rt < tol:
                accepted = True
                break
            t *= 0.5
        if not accepted:
            break
        quad = rt / (dxn * dxn) if (t == 1.0 and dxn > 0.0) else -1.0
        for i in range(n):
            x[i] = xt[i]
            resid[i] = resid_t[i]
            for c in range(n):
                jac[i, c] = jac_t[i, c]
        r = rt
    return r, it, False


@njit(cache=True, error_model="numpy")
def _unstable_direction(jac, ra, ei, d, v, A):
    """Direction of the unstable mode of an unstable equilibrium, in the torque-balanced
    hyperplane sum_i GJ_i uz_i(0) = 0 that holds every unloaded equilibrium (the total
    torsional moment is conserved along s and vanishes at the tube ends): three inverse
    iterations on the shooting Jacobian (its eigenvalue nearest zero is the one that changed
    sign), each projected onto the hyperplane. Scaled to max |d_i| = 1; written into ``d``."""
    n = d.shape[0]
    gg = 0.0
    for i in range(n):
        g = ei[i] / ra[i] if ra[i] > 0.0 else 0.0
        gg += g * g
        d[i] = 1.0 if i % 2 == 0 else -1.0
    for it in range(4):
        # project: d <- d - (g.d / g.g) g
        gd = 0.0
        for i in range(n):
            g = ei[i] / ra[i] if ra[i] > 0.0 else 0.0
            gd += g * d[i]
        for i in range(n):
            g = ei[i] / ra[i] if ra[i] > 0.0 else 0.0
            d[i] = d[i] - (gd / gg) * g if gg > 0.0 else d[i]
        big = _max_abs(d)
        if not big > 0.0:
            for i in range(n):
                d[i] = 1.0 if i == 0 else 0.0
            return
        for i in range(n):
            d[i] /= big
        if it == 3:
            return
        if not _newton_step(jac, d, v, A):      # v = -jac^{-1} d
            return
        for i in range(n):
            d[i] = v[i]


@njit(cache=True, error_model="numpy")
def solve_batch(alpha, beta, L, straight, kappa, EI, ratio, kink, torsion, m, step, tol,
                max_iter, x_init, stability=True, probe=False):
    """Solve and integrate a batch of configurations.

    alpha, beta : (B, n)  rad, mm
    L, straight : (n,)    mm
    kappa, EI, ratio : (B, n)  1/mm, N mm^2, EI/GJ
    kink : (B, n, 2) rad  (rotation where tube j ends)
    x_init : (B, n) initial guess of uz(0), 1/mm (ignored by the rigid model)

    Returns points (B, m, 3), s (B, m), uz0 (B, n), iters (B,), residual (B,), ok (B,),
    detj (B,), branch (B,) int8 and uz0alt (B, n) (below).
    A configuration is ok when max |uz_i(end_i)| < tol was reached at a STABLE equilibrium and
    every point is finite. Newton (at most max_iter iterations, backtracking line search)
    starts from x_init; where it fails (near snapping configurations the residual has local
    minima) the solve is retried by continuation in the torsional compliance: EI/GJ scaled by
    k/K, k = 1..K (K = 8, then 32), each stage started from the previous one's solution (at 0
    the rigid solution uz = 0 is exact). iters counts every Newton iteration.

    Stability (compliant model; skipped when ``stability`` is False: detj 1, branch 0, the
    first equilibrium returned whatever its stability). ``detj`` = det(d uz(end) / d uz(0)), the shooting Jacobian at
    the solution (from the variational equations Newton already integrates; where Newton
    stopped on the predicted full step it is the Jacobian one step earlier, |dx| < 1e-5 of
    the solution). The equilibrium is a minimum of the elastic energy iff det > 0 (derivation
    and the index <= 1 proviso: the module docstring). Where det <= 0 the
    unstable equilibrium is rejected and a stable one searched: Newton from the unstable root
    pushed along its unstable mode (:func:`_unstable_direction`) by t = 1, 0.3, 3, 0.1 x
    max kappa (in that order: the first is usually beyond the residual's turning point) to
    each side, the first stable root per side kept; if neither side gives one,
    continuation in the compliance (K = 8) from the rigid solution, kept if stable. With two
    distinct stable roots the one nearest the initial guess x_init (max norm) is returned: with
    the default x_init = 0 the least twisted one (nearest the rigid solution uz = 0); with a
    warm start from the previous configuration of a motion, the branch the robot is on (it
    snaps only where that branch ends). ``branch``: 0 the first equilibrium was stable
    (or the rigid model), 1 unstable rejected and one stable found, 2 unstable rejected and
    two stable found (bistable: the returned one is the nearer x_init; the other one's uz(0) in
    ``uz0alt``, NaN elsewhere), 3 unstable rejected and
    the stable one found by continuation, -1 unstable rejected and no stable one found
    (ok = False); 4 (only with ``probe``) the first equilibrium was stable and a second stable
    one was found by probing (returned: the first; the other in ``uz0alt``). ``probe``: for
    rows with a stable first root where two curved tubes are rotated apart by more than 90 deg
    at the actuators (where snapping occurs), Newton from the mirrored root pushed to the other
    side (1 and 0.5 x max kappa along the torque-balanced direction) looks for a second stable
    root; the returned shape is unchanged.
    """
    B, n = alpha.shape
    points = np.zeros((B, m, 3))
    svals = np.zeros((B, m))
    uz0 = np.zeros((B, n))
    iters = np.zeros(B, dtype=np.int64)
    rnorm = np.zeros(B)
    ok = np.zeros(B, dtype=np.bool_)
    detj = np.ones(B)
    branch = np.zeros(B, dtype=np.int8)
    uz0alt = np.full((B, n), np.nan)
    # one workspace for the whole batch
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
    x = np.zeros(n)
    xt = np.zeros(n)
    rs = np.zeros(n)
    out_s = np.zeros(m)
    xu = np.zeros(n)
    dvec = np.zeros(n)
    vtmp = np.zeros(n)
    roots = np.zeros((2, n))
    rres = np.zeros(2)
    rdet = np.zeros(2)
    scales = np.array([1.0, 0.3, 3.0, 0.1])
    for bi in range(B):
        al = alpha[bi]
        be = beta[bi]
        ka = kappa[bi]
        ei = EI[bi]
        ra = ratio[bi]
        kk = kink[bi]
        pts = points[bi]
        _tube_events(be, L, straight, tpos, ttyp, tidx)
        tip = tpos[2 * n - 1]
        for k in range(m):
            out_s[k] = tip * k / (m - 1) if m > 1 else tip
        out_s[m - 1] = tip
        for i in range(n):
            x[i] = x_init[bi, i] if torsion else 0.0
        shaped = False          # the final (frame) pass has been run at x
        it = 0
        r = 0.0
        stable = True
        if torsion:
            r, it, shaped = _newton(al, be, x, L, straight, ka, ei, ra, kk, tpos, ttyp, tidx,
                                    out_s, m, step, tol, max_iter, runtime(True), pts, resid, jac,
                                    resid_t, jac_t, dx, xt, A, y, Y, a, w, pend, ws, WS, G)
            for K in (8, 32):
                if r < tol:
                    break
                for i in range(n):
                    x[i] = 0.0
                for k in range(1, K + 1):
                    lam = k / K
                    for i in range(n):
                        rs[i] = ra[i] * lam
                    r, itk, shaped = _newton(al, be, x, L, straight, ka, ei, rs, kk, tpos, ttyp,
                                             tidx, out_s, m, step, tol, max_iter, k == K, pts,
                                             resid, jac, resid_t, jac_t, dx, xt, A,
                                             y, Y, a, w, pend, ws, WS, G)
                    it += itk
                    if not r < tol:
                        break
            if r < tol and stability:
                dj = _det(jac, A)
                detj[bi] = dj
                if not dj > 0.0:
                    # an unstable equilibrium: search stable ones to both sides of it
                    amp = 0.0
                    for i in range(n):
                        amp = max(amp, abs(ka[i]))
                    for i in range(n):
                        xu[i] = x[i]
                    _unstable_direction(jac, ra, ei, dvec, vtmp, A)
                    nfound = 0
                    for side in range(2):
                        sgn = 1.0 if side == 0 else -1.0
                        for t in scales:
                            for i in range(n):
                                x[i] = xu[i] + sgn * t * amp * dvec[i]
                            r2, it2, _sh = _newton(al, be, x, L, straight, ka, ei, ra, kk, tpos,
                                                   ttyp, tidx, out_s, m, step, tol, max_iter,
                                                   runtime(False), pts, resid, jac, resid_t,
                                                   jac_t, dx, xt, A, y, Y, a, w, pend,
                                                   ws, WS, G)
                            it += it2
                            if r2 < tol:
                                d2 = _det(jac, A)
                                if d2 > 0.0:
                                    same = False
                                    if nfound == 1:
                                        diff = 0.0
                                        for i in range(n):
                                            diff = max(diff, abs(x[i] - roots[0, i]))
                                        same = diff <= 1e-6 * amp
                                    if not same:
                                        for i in range(n):
                                            roots[nfound, i] = x[i]
                                        rres[nfound] = r2
                                        rdet[nfound] = d2
                                        nfound += 1
                                    break
                    code = 1
                    if nfound == 0:
                        # continuation in the compliance from the rigid solution
                        for i in range(n):
                            x[i] = 0.0
                        K = 8
                        r2 = math.inf
                        for k in range(1, K + 1):
                            for i in range(n):
                                rs[i] = ra[i] * (k / K)
                            r2, itk, _sh = _newton(al, be, x, L, straight, ka, ei, rs, kk, tpos,
                                                   ttyp, tidx, out_s, m, step, tol, max_iter,
                                                   runtime(False), pts, resid, jac, resid_t,
                                                   jac_t, dx, xt, A, y, Y, a, w, pend,
                                                   ws, WS, G)
                            it += itk
                            if not r2 < tol:
                                break
                        if r2 < tol:
                            d2 = _det(jac, A)
                            if d2 > 0.0:
                                for i in range(n):
                                    roots[0, i] = x[i]
                                rres[0] = r2
                                rdet[0] = d2
                                nfound = 1
                                code = 3
                    if nfound == 0:
                        stable = False
                        branch[bi] = -1
                        for i in range(n):
                            x[i] = xu[i]
                    else:
                        pick = 0
                        if nfound == 2:
                            code = 2
                            # the one nearest the initial guess (max norm): with x_init = 0
                            # the less twisted one; with a warm start from the previous
                            # configuration of a motion, the branch the robot is on
                            d0 = 0.0
                            d1 = 0.0
                            for i in range(n):
                                d0 = max(d0, abs(roots[0, i] - x_init[bi, i]))
                                d1 = max(d1, abs(roots[1, i] - x_init[bi, i]))
                            if d1 < d0:
                                pick = 1
                        branch[bi] = code
                        for i in range(n):
                            x[i] = roots[pick, i]
                            if nfound == 2:
                                uz0alt[bi, i] = roots[1 - pick, i]
                        r = rres[pick]
                        detj[bi] = rdet[pick]
                    shaped = False
                elif probe and it > 0:
                    # stable first root: probe for a second stable one where some pair of
                    # curved tubes is rotated apart by more than 90 deg at the actuators
                    apart = False
                    for i in range(n):
                        for j in range(i + 1, n):
                            if ka[i] != 0.0 and ka[j] != 0.0 and math.cos(al[i] - al[j]) < 0.0:
                                apart = True
                    if apart:
                        amp = 0.0
                        for i in range(n):
                            amp = max(amp, abs(ka[i]))
                        for i in range(n):
                            xu[i] = x[i]
                        _unstable_direction(jac, ra, ei, dvec, vtmp, A)
                        c0 = 0.0
                        for i in range(n):
                            c0 += dvec[i] * xu[i]
                        sgn = -1.0 if c0 >= 0.0 else 1.0       # towards the other side
                        for t in (1.0, 0.5):
                            for i in range(n):
                                x[i] = -xu[i] + sgn * t * amp * dvec[i]
                            r2, it2, _sh = _newton(al, be, x, L, straight, ka, ei, ra, kk, tpos,
                                                   ttyp, tidx, out_s, m, step, tol, max_iter,
                                                   runtime(False), pts, resid, jac, resid_t,
                                                   jac_t, dx, xt, A, y, Y, a, w, pend,
                                                   ws, WS, G)
                            if r2 < tol and _det(jac, A) > 0.0:
                                diff = 0.0
                                for i in range(n):
                                    diff = max(diff, abs(x[i] - xu[i]))
                                if diff > 1e-6 * amp:
                                    branch[bi] = 4
                                    for i in range(n):
                                        uz0alt[bi, i] = x[i]
                                    break
                        for i in range(n):
                            x[i] = xu[i]
        if not shaped:
            _integrate(al, be, x, L, straight, ka, ei, ra, kk, torsion, tpos, ttyp, tidx,
                       out_s, m, step, runtime(True), runtime(False), pts, resid_t, jac_t,
                       y, Y, a, w, pend, ws, WS, G)
        finite = True
        for k in range(m):
            svals[bi, k] = out_s[k]
            for c in range(3):
                if not math.isfinite(pts[k, c]):
                    finite = False
        for i in range(n):
            uz0[bi, i] = x[i]
        iters[bi] = it
        rnorm[bi] = r
        ok[bi] = r < tol and finite and stable
    return points, svals, uz0, iters, rnorm, ok, detj, branch, uz0alt
