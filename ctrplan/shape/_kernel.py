"""Numba kernels of the mechanics model (torsionally rigid and compliant CTRs).

Formulation (DESIGN.md). A twist-free backbone frame ``R`` (``R' = R [u]x`` with
``u = (ux, uy, 0)``, ``p' = R e_z``) carries every tube; tube i's material frame is
``R Rz(psi_i)`` and its torsion is ``uz_i = psi_i'``. Unloaded moment balance gives

    u_xy   = sum_j EI_j Rz(psi_j) uhat_j / sum_j EI_j          (tubes present at s)
    uz_i'  = (EI_i / GJ_i) kappa_i / EIsum * sum_j EI_j kappa_j sin(psi_i - psi_j)

with precurvature ``uhat_i = (0, kappa_i, 0)`` on the curved section. Boundary values:
``psi_i(0) = alpha_i - beta_i uz_i(0)`` (the straight part behind the constraint plane twists
uniformly) and ``uz_i(beta_i + L_i) = 0``, solved by shooting on ``x = uz(0)`` with Newton and
the Jacobian from the variational equations. The rigid model is the same with ``uz = 0``.

Integration is fixed-step RK4 on intervals aligned to every break point of a configuration
(curve starts, tube ends, requested output points); each interval is cut into
``ceil(length / step)`` equal steps. Angles are carried as cos/sin (no trig in the loop).
``kink`` adds a small rotation ``R <- R Exp([kx, ky, 0])`` where tube j ends (used by the
clearance effect; zero gives the base model exactly).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# Event types in the per-configuration event list.
_EV_CURVE = 0
_EV_END = 1
_EV_OUT = 2


@njit(cache=True, fastmath=False)
def _events(beta, L, straight, out_s):
    n = beta.shape[0]
    m = out_s.shape[0]
    ne = 2 * n + m
    pos = np.empty(ne)
    typ = np.empty(ne, dtype=np.int64)
    idx = np.empty(ne, dtype=np.int64)
    for i in range(n):
        pos[i] = max(beta[i] + straight[i], 0.0)
        typ[i] = _EV_CURVE
        idx[i] = i
        pos[n + i] = max(beta[i] + L[i], 0.0)
        typ[n + i] = _EV_END
        idx[n + i] = i
    for k in range(m):
        pos[2 * n + k] = out_s[k]
        typ[2 * n + k] = _EV_OUT
        idx[2 * n + k] = k
    order = np.argsort(pos, kind="mergesort")
    return pos[order], typ[order], idx[order]


@njit(cache=True)
def _rhs(y, n, a, w, eisum_inv, frame, dy):
    """Derivative of the state y = [c(n), s(n), uz(n), R(9, row-major), p(3)]."""
    cw = 0.0
    sw = 0.0
    for j in range(n):
        cw += w[j] * y[j]
        sw += w[j] * y[n + j]
    for i in range(n):
        c = y[i]
        s = y[n + i]
        uz = y[2 * n + i]
        dy[i] = -s * uz
        dy[n + i] = c * uz
        dy[2 * n + i] = a[i] * (s * cw - c * sw)
    if frame:
        ux = -sw * eisum_inv
        uy = cw * eisum_inv
        b = 3 * n
        # R' = R [u]x with u = (ux, uy, 0): columns d0 = -uy r2, d1 = ux r2, d2 = uy r0 - ux r1
        for r in range(3):
            r0 = y[b + 3 * r]
            r1 = y[b + 3 * r + 1]
            r2 = y[b + 3 * r + 2]
            dy[b + 3 * r] = -uy * r2
            dy[b + 3 * r + 1] = ux * r2
            dy[b + 3 * r + 2] = uy * r0 - ux * r1
            dy[b + 9 + r] = r2


@njit(cache=True)
def _rhs_sens(y, Y, n, a, w, dY):
    """Variational equations: Y = [dpsi/dx (n x n); duz/dx (n x n)]."""
    cw = 0.0
    sw = 0.0
    for j in range(n):
        cw += w[j] * y[j]
        sw += w[j] * y[n + j]
    for col in range(n):
        cwy = 0.0
        swy = 0.0
        for k in range(n):
            cwy += w[k] * y[k] * Y[k, col]
            swy += w[k] * y[n + k] * Y[k, col]
        for i in range(n):
            c = y[i]
            s = y[n + i]
            dY[i, col] = Y[n + i, col]
            dY[n + i, col] = a[i] * ((c * cw + s * sw) * Y[i, col] - c * cwy - s * swy)


@njit(cache=True)
def _integrate(alpha, beta, x, L, straight, kappa, EI, ratio, kink, torsion, out_s, step,
               frame, sens, out_p, resid, jac):
    """Integrate one configuration from s = 0 to its last event.

    Fills ``out_p`` (m, 3) when ``frame``; ``resid`` (n,) = uz_i at tube i's end and
    ``jac`` (n, n) = d resid / d x when ``sens``.
    """
    n = alpha.shape[0]
    pos, typ, idx = _events(beta, L, straight, out_s)
    nst = 3 * n + 12
    y = np.zeros(nst)
    for i in range(n):
        psi0 = alpha[i] - beta[i] * x[i]
        y[i] = math.cos(psi0)
        y[n + i] = math.sin(psi0)
        y[2 * n + i] = x[i]
    b = 3 * n
    y[b + 0] = 1.0
    y[b + 4] = 1.0
    y[b + 8] = 1.0
    Y = np.zeros((2 * n, n))
    if sens:
        for i in range(n):
            Y[i, i] = -beta[i]
            Y[n + i, i] = 1.0
    k1 = np.empty(nst)
    k2 = np.empty(nst)
    k3 = np.empty(nst)
    k4 = np.empty(nst)
    yt = np.empty(nst)
    K1 = np.empty((2 * n, n))
    K2 = np.empty((2 * n, n))
    K3 = np.empty((2 * n, n))
    K4 = np.empty((2 * n, n))
    Yt = np.empty((2 * n, n))
    a = np.empty(n)
    w = np.empty(n)
    s_now = 0.0
    for e in range(pos.shape[0]):
        s_next = pos[e]
        seg = s_next - s_now
        if seg > 0.0:
            mid = s_now + 0.5 * seg
            eisum = 0.0
            for i in range(n):
                present = mid < beta[i] + L[i]
                curved = mid >= beta[i] + straight[i]
                if present:
                    eisum += EI[i]
                w[i] = EI[i] * kappa[i] if (present and curved) else 0.0
            eisum_inv = 1.0 / eisum if eisum > 0.0 else 0.0
            for i in range(n):
                if torsion and w[i] != 0.0:
                    a[i] = ratio[i] * kappa[i] * eisum_inv
                else:
                    a[i] = 0.0
            # tubes that have ended keep their state frozen: zero a and zero uz rate
            nsub = int(math.ceil(seg / step - 1e-9))
            if nsub < 1:
                nsub = 1
            h = seg / nsub
            for _ in range(nsub):
                _rhs(y, n, a, w, eisum_inv, frame, k1)
                for j in range(nst):
                    yt[j] = y[j] + 0.5 * h * k1[j]
                _rhs(yt, n, a, w, eisum_inv, frame, k2)
                for j in range(nst):
                    yt[j] = y[j] + 0.5 * h * k2[j]
                _rhs(yt, n, a, w, eisum_inv, frame, k3)
                for j in range(nst):
                    yt[j] = y[j] + h * k3[j]
                _rhs(yt, n, a, w, eisum_inv, frame, k4)
                if sens:
                    _rhs_sens(y, Y, n, a, w, K1)
                    for r in range(2 * n):
                        for c in range(n):
                            Yt[r, c] = Y[r, c] + 0.5 * h * K1[r, c]
                    for j in range(nst):
                        yt[j] = y[j] + 0.5 * h * k1[j]
                    _rhs_sens(yt, Yt, n, a, w, K2)
                    for r in range(2 * n):
                        for c in range(n):
                            Yt[r, c] = Y[r, c] + 0.5 * h * K2[r, c]
                    for j in range(nst):
                        yt[j] = y[j] + 0.5 * h * k2[j]
                    _rhs_sens(yt, Yt, n, a, w, K3)
                    for r in range(2 * n):
                        for c in range(n):
                            Yt[r, c] = Y[r, c] + h * K3[r, c]
                    for j in range(nst):
                        yt[j] = y[j] + h * k3[j]
                    _rhs_sens(yt, Yt, n, a, w, K4)
                    for r in range(2 * n):
                        for c in range(n):
                            Y[r, c] += h / 6.0 * (K1[r, c] + 2.0 * K2[r, c] + 2.0 * K3[r, c] + K4[r, c])
                for j in range(nst):
                    y[j] += h / 6.0 * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j])
                # ended tubes: their angle rate is uz (frozen at 0 after the end by the
                # boundary condition); keep c/s on the unit circle against round-off
            s_now = s_next
        t = typ[e]
        i = idx[e]
        if t == _EV_OUT:
            if frame:
                out_p[i, 0] = y[b + 9]
                out_p[i, 1] = y[b + 10]
                out_p[i, 2] = y[b + 11]
        elif t == _EV_END:
            if sens:
                resid[i] = y[2 * n + i]
                for c in range(n):
                    jac[i, c] = Y[n + i, c]
            # the tube is gone: freeze its torsion (and angle) from here on
            y[2 * n + i] = 0.0
            if sens:
                for c in range(n):
                    Y[n + i, c] = 0.0
            if frame and (kink[i, 0] != 0.0 or kink[i, 1] != 0.0):
                _apply_kink(y, b, kink[i, 0], kink[i, 1])


@njit(cache=True)
def _apply_kink(y, b, kx, ky):
    """R <- R Exp([kx, ky, 0]) (Rodrigues)."""
    th = math.sqrt(kx * kx + ky * ky)
    ex = kx / th
    ey = ky / th
    ct = math.cos(th)
    st = math.sin(th)
    vt = 1.0 - ct
    # rotation about axis (ex, ey, 0)
    m00 = ct + ex * ex * vt
    m01 = ex * ey * vt
    m02 = ey * st
    m10 = ex * ey * vt
    m11 = ct + ey * ey * vt
    m12 = -ex * st
    m20 = -ey * st
    m21 = ex * st
    m22 = ct
    for r in range(3):
        r0 = y[b + 3 * r]
        r1 = y[b + 3 * r + 1]
        r2 = y[b + 3 * r + 2]
        y[b + 3 * r] = r0 * m00 + r1 * m10 + r2 * m20
        y[b + 3 * r + 1] = r0 * m01 + r1 * m11 + r2 * m21
        y[b + 3 * r + 2] = r0 * m02 + r1 * m12 + r2 * m22


@njit(cache=True)
def _max_abs(v):
    m = 0.0
    for i in range(v.shape[0]):
        if abs(v[i]) > m:
            m = abs(v[i])
    return m


@njit(cache=True)
def solve_batch(alpha, beta, L, straight, kappa, EI, ratio, kink, torsion, m, step, tol,
                max_iter, x_init):
    """Solve and integrate a batch of configurations.

    alpha, beta : (B, n)  rad, mm
    L, straight : (n,)    mm
    kappa, EI, ratio : (B, n)  1/mm, N mm^2, EI/GJ
    kink : (B, n, 2) rad  (rotation where tube j ends)
    x_init : (B, n) initial guess of uz(0), 1/mm

    Returns points (B, m, 3), s (B, m), uz0 (B, n), iters (B,), residual (B,), ok (B,).
    """
    B, n = alpha.shape
    points = np.zeros((B, m, 3))
    svals = np.zeros((B, m))
    uz0 = np.zeros((B, n))
    iters = np.zeros(B, dtype=np.int64)
    rnorm = np.zeros(B)
    ok = np.zeros(B, dtype=np.bool_)
    empty = np.zeros(0)
    dummy_p = np.zeros((0, 3))
    resid = np.zeros(n)
    jac = np.zeros((n, n))
    resid_t = np.zeros(n)
    jac_t = np.zeros((n, n))
    out_s = np.zeros(m)
    for bi in range(B):
        al = alpha[bi]
        be = beta[bi]
        tip = 0.0
        for i in range(n):
            if be[i] + L[i] > tip:
                tip = be[i] + L[i]
        x = x_init[bi].copy()
        converged = True
        it = 0
        r = 0.0
        if torsion:
            converged = False
            _integrate(al, be, x, L, straight, kappa[bi], EI[bi], ratio[bi], kink[bi], True,
                       empty, step, False, True, dummy_p, resid, jac)
            r = _max_abs(resid)
            while it < max_iter:
                if r < tol:
                    converged = True
                    break
                it += 1
                dx = np.linalg.solve(jac, -resid) if np.isfinite(jac).all() else np.zeros(n)
                t = 1.0
                accepted = False
                for _ls in range(8):
                    xt = x + t * dx
                    _integrate(al, be, xt, L, straight, kappa[bi], EI[bi], ratio[bi], kink[bi],
                               True, empty, step, False, True, dummy_p, resid_t, jac_t)
                    rt = _max_abs(resid_t)
                    if rt < r or rt < tol:
                        accepted = True
                        break
                    t *= 0.5
                if not accepted or not math.isfinite(rt):
                    break
                x = xt
                r = rt
                resid[:] = resid_t
                jac[:, :] = jac_t
            if r < tol:
                converged = True
        for k in range(m):
            out_s[k] = tip * k / (m - 1) if m > 1 else tip
        _integrate(al, be, x, L, straight, kappa[bi], EI[bi], ratio[bi], kink[bi], torsion,
                   out_s, step, True, False, points[bi], resid_t, jac_t)
        for k in range(m):
            svals[bi, k] = out_s[k]
        uz0[bi] = x
        iters[bi] = it
        rnorm[bi] = r
        ok[bi] = converged
    return points, svals, uz0, iters, rnorm, ok
