"""Numba kernel of the externally loaded CTR (Rucker-style Cosserat-rod boundary value problem).

Used only when a configuration carries a load (tip force, tip moment or distributed weight);
unloaded configurations keep the exact/RK4 kernels of :mod:`ctrplan.shape._kernel`.

Formulation. As in the unloaded kernel a twist-free backbone frame ``R`` (``R' = R [u]x``,
``u = (ux, uy, 0)``, ``p' = R e_z``) carries every tube; tube i's material frame is
``R Rz(psi_i)``. The states are, per tube, (cos, sin) psi_i and the torsional moment
``tau_i = GJ_i uz_i`` (N mm; ``psi_i' = uz_i = (EI_i/GJ_i) tau_i / EI_i``), and for the backbone
R, p and the bending components ``mb = (mb_x, mb_y)`` of the total internal moment in the
backbone frame (N mm). The internal force is known in closed form because the loads do not
depend on the shape (base frame, N)::

    n(s) = F_tip + sum_i W_i max(0, l_i - s)          W_i: weight per length of tube i (N/mm)

Moment balance of the whole cross-section ``m' = -p' x n`` (no distributed moments) in the
backbone frame, with the twisting component ``mb_z = sum_i tau_i`` (tubes present)::

    mb_x' = -uy mb_z + nb_y,   mb_y' = ux mb_z - nb_x,          nb = R^T n
    u_xy  = (mb_xy + sum_j EI_j Rz(psi_j) uhat_j) / sum_j EI_j
    tau_i' = EI_i kappa_i (ux cos psi_i + uy sin psi_i)           (curved section of tube i)

(the torsion law is the unloaded one: a frictionless tube takes no axial moment from the
others). Boundary values: ``psi_i(0) = alpha_i - beta_i uz_i(0)`` (the straight part behind the
constraint plane twists uniformly); unknowns at s = 0: ``x = (tau_1..tau_n, mb_x, mb_y)`` (R(0)
is the identity, so the base-frame and backbone-frame moments agree there); residuals, divided
by a bending stiffness so that they read as curvatures (1/mm)::

    tau_i(l_i) = 0                          tube i's free end (i > 1)
    tau_1(l) = (R^T M_tip)_z                the innermost tube carries the tip moment's twist
    mb_xy(l) = (R^T M_tip)_xy               the tip

With every load zero the solution has ``mb = 0`` and is the unloaded model. The torsionally
rigid model is the limit ``EI/GJ -> 0`` (``ratio = 0``): psi stays alpha, and the tubes still
carry torsional moments ``tau`` (which enter the balance through ``mb_z``); it is solved by the
same shooting. Integration is fixed-step RK4 between break points (curve starts, tube ends),
each interval cut into ``ceil(length / step)`` equal steps, with the variational equations
riding along (exact derivative of the RK4 map: Newton converges quadratically). Output points
inside a step are read off by cubic Hermite interpolation (p and p' = R e_z at both ends).
``kink`` (clearance effect) rotates R where a tube ends: the bending moment turns with the frame
(mb_xy <- (K^T mb)_xy) and the twisting moment carries over (the tubes' torsional moments are
continuous; no axial moment acts at the kink). To first order in the kink angle the total
moment is continuous.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ctrplan.shape._kernel import _hermite_out, _tube_events, runtime

# numba caches this module's kernels with the _kernel functions they call compiled in, and
# checks only this file's time stamp: edit this file too when _kernel.py changes (last: the
# tie order of tube ends in _tube_events).
from ctrplan.shape._shooting import _newton_step


@njit(cache=True, error_model="numpy")
def _rhs(y, T, n, nx, s, k, w, eisum_inv, n0, wsum, sens, dy, dT):
    """Derivative of the state y (3n + 14) and, when ``sens``, of its tangent T (3n + 14, nx).

    Layout: c (n), s (n), tau (n), R (9, row-major), p (3), mb_x, mb_y.
    k_i = ratio_i / EI_i (uz = k tau); w_i = EI_i kappa_i where tube i is present and curved;
    n(s) = n0 - s wsum (base frame, N).
    """
    b = 3 * n
    mbz = 0.0
    cw = 0.0
    sw = 0.0
    for j in range(n):
        mbz += y[2 * n + j]
        cw += w[j] * y[j]
        sw += w[j] * y[n + j]
    mbx = y[b + 12]
    mby = y[b + 13]
    ux = (mbx - sw) * eisum_inv
    uy = (mby + cw) * eisum_inv
    for i in range(n):
        c = y[i]
        si = y[n + i]
        uz = k[i] * y[2 * n + i]
        dy[i] = -si * uz
        dy[n + i] = c * uz
        dy[2 * n + i] = w[i] * (ux * c + uy * si)
    n_x = n0[0] - s * wsum[0]
    n_y = n0[1] - s * wsum[1]
    n_z = n0[2] - s * wsum[2]
    nbx = 0.0
    nby = 0.0
    for r in range(3):
        r0 = y[b + 3 * r]
        r1 = y[b + 3 * r + 1]
        r2 = y[b + 3 * r + 2]
        dy[b + 3 * r] = -uy * r2
        dy[b + 3 * r + 1] = ux * r2
        dy[b + 3 * r + 2] = uy * r0 - ux * r1
        dy[b + 9 + r] = r2
    nbx = y[b + 0] * n_x + y[b + 3] * n_y + y[b + 6] * n_z
    nby = y[b + 1] * n_x + y[b + 4] * n_y + y[b + 7] * n_z
    dy[b + 12] = -uy * mbz + nby
    dy[b + 13] = ux * mbz - nbx
    if sens:
        for col in range(nx):
            dmbz = 0.0
            dcw = 0.0
            dsw = 0.0
            for j in range(n):
                dmbz += T[2 * n + j, col]
                dcw += w[j] * T[j, col]
                dsw += w[j] * T[n + j, col]
            dux = (T[b + 12, col] - dsw) * eisum_inv
            duy = (T[b + 13, col] + dcw) * eisum_inv
            for i in range(n):
                c = y[i]
                si = y[n + i]
                uz = k[i] * y[2 * n + i]
                dc = T[i, col]
                ds = T[n + i, col]
                duz = k[i] * T[2 * n + i, col]
                dT[i, col] = -ds * uz - si * duz
                dT[n + i, col] = dc * uz + c * duz
                dT[2 * n + i, col] = w[i] * (dux * c + ux * dc + duy * si + uy * ds)
            for r in range(3):
                r0 = y[b + 3 * r]
                r1 = y[b + 3 * r + 1]
                r2 = y[b + 3 * r + 2]
                e0 = T[b + 3 * r, col]
                e1 = T[b + 3 * r + 1, col]
                e2 = T[b + 3 * r + 2, col]
                dT[b + 3 * r, col] = -duy * r2 - uy * e2
                dT[b + 3 * r + 1, col] = dux * r2 + ux * e2
                dT[b + 3 * r + 2, col] = duy * r0 + uy * e0 - dux * r1 - ux * e1
                dT[b + 9 + r, col] = e2
            dnbx = T[b + 0, col] * n_x + T[b + 3, col] * n_y + T[b + 6, col] * n_z
            dnby = T[b + 1, col] * n_x + T[b + 4, col] * n_y + T[b + 7, col] * n_z
            dT[b + 12, col] = -duy * mbz - uy * dmbz + dnby
            dT[b + 13, col] = dux * mbz + ux * dmbz - dnbx


@njit(cache=True, error_model="numpy")
def _rk4(y, T, n, nx, k, w, eisum_inv, n0, wsum, sens, s0, seg, step, out_s, m_out, ko,
         out_p, k1, k2, k3, k4, yt, K1, K2, K3, K4, Tt):
    """Fixed-step RK4 over [s0, s0 + seg]; output points strictly inside by cubic Hermite
    interpolation. Returns the next output index."""
    nsub = int(math.ceil(seg / step - 1e-9))
    if nsub < 1:
        nsub = 1
    h = seg / nsub
    N = y.shape[0]
    b = 3 * n
    s_end = s0 + seg
    for q in range(nsub):
        sa = s0 + q * h
        sb = s_end if q == nsub - 1 else sa + h
        want = ko < m_out and out_s[ko] < s_end and out_s[ko] <= sb
        pax = y[b + 9]
        pay = y[b + 10]
        paz = y[b + 11]
        tax = y[b + 2]
        tay = y[b + 5]
        taz = y[b + 8]
        _rhs(y, T, n, nx, sa, k, w, eisum_inv, n0, wsum, sens, k1, K1)
        for j in range(N):
            yt[j] = y[j] + 0.5 * h * k1[j]
        if sens:
            for r in range(N):
                for c in range(nx):
                    Tt[r, c] = T[r, c] + 0.5 * h * K1[r, c]
        _rhs(yt, Tt, n, nx, sa + 0.5 * h, k, w, eisum_inv, n0, wsum, sens, k2, K2)
        for j in range(N):
            yt[j] = y[j] + 0.5 * h * k2[j]
        if sens:
            for r in range(N):
                for c in range(nx):
                    Tt[r, c] = T[r, c] + 0.5 * h * K2[r, c]
        _rhs(yt, Tt, n, nx, sa + 0.5 * h, k, w, eisum_inv, n0, wsum, sens, k3, K3)
        for j in range(N):
            yt[j] = y[j] + h * k3[j]
        if sens:
            for r in range(N):
                for c in range(nx):
                    Tt[r, c] = T[r, c] + h * K3[r, c]
        _rhs(yt, Tt, n, nx, sa + h, k, w, eisum_inv, n0, wsum, sens, k4, K4)
        h6 = h / 6.0
        for j in range(N):
            y[j] += h6 * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j])
        if sens:
            for r in range(N):
                for c in range(nx):
                    T[r, c] += h6 * (K1[r, c] + 2.0 * K2[r, c] + 2.0 * K3[r, c] + K4[r, c])
        if want:
            ko = _hermite_out(out_s, out_p, ko, m_out, s_end, sa, sb, h, pax, pay, paz, tax, tay,
                              taz, y, b)
    return ko


@njit(cache=True, error_model="numpy")
def _kink(y, T, n, nx, sens, kx, ky):
    """R <- R K with K = Exp([kx, ky, 0]); mb_xy <- (K^T (mb_x, mb_y, sum tau))_xy, the
    twisting moment sum tau carries over. The tangent follows (K is constant)."""
    b = 3 * n
    th = math.sqrt(kx * kx + ky * ky)
    ex = kx / th
    ey = ky / th
    ct = math.cos(th)
    st = math.sin(th)
    vt = 1.0 - ct
    K = np.empty((3, 3))
    K[0, 0] = ct + ex * ex * vt
    K[0, 1] = ex * ey * vt
    K[0, 2] = ey * st
    K[1, 0] = ex * ey * vt
    K[1, 1] = ct + ey * ey * vt
    K[1, 2] = -ex * st
    K[2, 0] = -ey * st
    K[2, 1] = ex * st
    K[2, 2] = ct
    ncol = nx if sens else 0
    for col in range(-1, ncol):
        for r in range(3):
            if col < 0:
                r0 = y[b + 3 * r]
                r1 = y[b + 3 * r + 1]
                r2 = y[b + 3 * r + 2]
            else:
                r0 = T[b + 3 * r, col]
                r1 = T[b + 3 * r + 1, col]
                r2 = T[b + 3 * r + 2, col]
            v0 = r0 * K[0, 0] + r1 * K[1, 0] + r2 * K[2, 0]
            v1 = r0 * K[0, 1] + r1 * K[1, 1] + r2 * K[2, 1]
            v2 = r0 * K[0, 2] + r1 * K[1, 2] + r2 * K[2, 2]
            if col < 0:
                y[b + 3 * r] = v0
                y[b + 3 * r + 1] = v1
                y[b + 3 * r + 2] = v2
            else:
                T[b + 3 * r, col] = v0
                T[b + 3 * r + 1, col] = v1
                T[b + 3 * r + 2, col] = v2
        if col < 0:
            mx = y[b + 12]
            my = y[b + 13]
            mz = 0.0
            for j in range(n):
                mz += y[2 * n + j]
        else:
            mx = T[b + 12, col]
            my = T[b + 13, col]
            mz = 0.0
            for j in range(n):
                mz += T[2 * n + j, col]
        nx_ = K[0, 0] * mx + K[1, 0] * my + K[2, 0] * mz
        ny_ = K[0, 1] * mx + K[1, 1] * my + K[2, 1] * mz
        if col < 0:
            y[b + 12] = nx_
            y[b + 13] = ny_
        else:
            T[b + 12, col] = nx_
            T[b + 13, col] = ny_


@njit(cache=True, error_model="numpy")
def _integrate(alpha, beta, x, L, straight, kappa, EI, ratio, kink, W, F, M, tpos, ttyp, tidx,
               out_s, m_out, step, sens, out_p, resid, jac, y, T, k, w, n0, wsum, ws, WS):
    """One pass from s = 0 to the tip at unknowns x (n + 2). Fills resid (n + 2), jac when
    ``sens`` and out_p[:m_out] (m_out may be 0)."""
    n = alpha.shape[0]
    nx = n + 2
    N = 3 * n + 14
    b = 3 * n
    for i in range(n):
        k[i] = ratio[i] / EI[i]
    for j in range(N):
        y[j] = 0.0
    for i in range(n):
        psi0 = alpha[i] - beta[i] * k[i] * x[i]
        y[i] = math.cos(psi0)
        y[n + i] = math.sin(psi0)
        y[2 * n + i] = x[i]
    y[b + 0] = 1.0
    y[b + 4] = 1.0
    y[b + 8] = 1.0
    y[b + 12] = x[n]
    y[b + 13] = x[n + 1]
    if sens:
        for r in range(N):
            for c in range(nx):
                T[r, c] = 0.0
        for i in range(n):
            f = -beta[i] * k[i]
            T[i, i] = -y[n + i] * f
            T[n + i, i] = y[i] * f
            T[2 * n + i, i] = 1.0
        T[b + 12, n] = 1.0
        T[b + 13, n + 1] = 1.0
    ko = 0
    s_now = 0.0
    ne = 2 * n
    for it in range(ne):
        s_next = tpos[it]
        seg = s_next - s_now
        if seg > 0.0:
            mid = s_now + 0.5 * seg
            eisum = 0.0
            for c in range(3):
                n0[c] = F[c]
                wsum[c] = 0.0
            for i in range(n):
                present = mid < beta[i] + L[i]
                curved = mid >= beta[i] + straight[i]
                if present:
                    eisum += EI[i]
                    for c in range(3):
                        n0[c] += W[i, c] * (beta[i] + L[i])
                        wsum[c] += W[i, c]
                w[i] = EI[i] * kappa[i] if (present and curved) else 0.0
            eisum_inv = 1.0 / eisum if eisum > 0.0 else 0.0
            ko = _rk4(y, T, n, nx, k, w, eisum_inv, n0, wsum, sens, s_now, seg, step, out_s,
                      m_out, runtime(ko), out_p, ws[0], ws[1], ws[2], ws[3], ws[4], WS[0], WS[1], WS[2],
                      WS[3], WS[4])
            s_now = s_next
        i = tidx[it]
        if ttyp[it] == 1:
            tz = 0.0
            if i == 0:
                # twisting component of the tip moment, in the backbone frame
                tz = y[b + 2] * M[0] + y[b + 5] * M[1] + y[b + 8] * M[2]
            resid[i] = (y[2 * n + i] - tz) / EI[i]
            if sens:
                for c in range(nx):
                    dtz = 0.0
                    if i == 0:
                        dtz = T[b + 2, c] * M[0] + T[b + 5, c] * M[1] + T[b + 8, c] * M[2]
                    jac[i, c] = (T[2 * n + i, c] - dtz) / EI[i]
            # the tube is gone: no torsion, its angle frozen
            y[2 * n + i] = 0.0
            if sens:
                for c in range(nx):
                    T[2 * n + i, c] = 0.0
            if kink[i, 0] != 0.0 or kink[i, 1] != 0.0:
                _kink(y, T, n, nx, sens, kink[i, 0], kink[i, 1])
        while ko < m_out and (out_s[ko] <= s_now or it == ne - 1):
            out_p[ko, 0] = y[b + 9]
            out_p[ko, 1] = y[b + 10]
            out_p[ko, 2] = y[b + 11]
            ko += 1
    # the tip: bending moment equals the applied moment (backbone frame)
    e0 = EI[0]
    mx = y[b + 0] * M[0] + y[b + 3] * M[1] + y[b + 6] * M[2]
    my = y[b + 1] * M[0] + y[b + 4] * M[1] + y[b + 7] * M[2]
    resid[n] = (y[b + 12] - mx) / e0
    resid[n + 1] = (y[b + 13] - my) / e0
    if sens:
        for c in range(nx):
            dmx = T[b + 0, c] * M[0] + T[b + 3, c] * M[1] + T[b + 6, c] * M[2]
            dmy = T[b + 1, c] * M[0] + T[b + 4, c] * M[1] + T[b + 7, c] * M[2]
            jac[n, c] = (T[b + 12, c] - dmx) / e0
            jac[n + 1, c] = (T[b + 13, c] - dmy) / e0


@njit(cache=True, error_model="numpy")
def _max_abs(v):
    m = 0.0
    for i in range(v.shape[0]):
        if not abs(v[i]) <= m:       # NaN propagates
            m = abs(v[i])
    return m


@njit(cache=True, error_model="numpy")
def _newton(al, be, x, L, straight, ka, ei, ra, kk, W, F, M, tpos, ttyp, tidx, out_s, m_out,
            step, tol, max_iter, pts, resid, jac, resid_t, jac_t, dx, xt, A, y, T, k, w, n0,
            wsum, ws, WS):
    """Newton on x (in place) with the Jacobian kept while it contracts well (chord steps
    without the variational equations: about a sixth of the cost of a pass with them) and a
    fresh Jacobian with a backtracking line search otherwise. Every pass also writes the
    output points ``pts[:m_out]`` (cheap: Hermite interpolation), so no final pass is needed
    when the last pass was at the returned x.
    Returns (residual, iterations, pts_at_x)."""
    nx = x.shape[0]
    on, off = runtime(True), runtime(False)     # one compiled _integrate (see runtime)
    _integrate(al, be, x, L, straight, ka, ei, ra, kk, W, F, M, tpos, ttyp, tidx, out_s, m_out,
               step, on, pts, resid, jac, y, T, k, w, n0, wsum, ws, WS)
    r = _max_abs(resid)
    it = 0
    at_x = True             # the last pass (and so pts) was at x
    fresh = True            # jac was evaluated at x
    chord = True            # try the full step with the kept Jacobian first
    while r >= tol and it < max_iter and math.isfinite(r):
        it += 1
        if not _newton_step(jac, resid, dx, A):
            break
        if chord:
            # the full step without the variational equations
            for i in range(nx):
                xt[i] = x[i] + dx[i]
            _integrate(al, be, xt, L, straight, ka, ei, ra, kk, W, F, M, tpos, ttyp, tidx,
                       out_s, m_out, step, off, pts, resid_t, jac_t, y, T, k, w, n0, wsum,
                       ws, WS)
            rt = _max_abs(resid_t)
            if rt < tol or rt < 0.1 * r:
                for i in range(nx):
                    x[i] = xt[i]
                    resid[i] = resid_t[i]
                r = rt
                at_x = True
                fresh = False
                continue
            # not contracting: Newton steps until they contract strongly again
            chord = False
            at_x = False
        if not fresh:
            _integrate(al, be, x, L, straight, ka, ei, ra, kk, W, F, M, tpos, ttyp, tidx,
                       out_s, m_out, step, on, pts, resid, jac, y, T, k, w, n0, wsum, ws, WS)
            r = _max_abs(resid)
            at_x = True
            fresh = True
            if not _newton_step(jac, resid, dx, A):
                break
        t = 1.0
        accepted = False
        for _ls in range(10):
            for i in range(nx):
                xt[i] = x[i] + t * dx[i]
            _integrate(al, be, xt, L, straight, ka, ei, ra, kk, W, F, M, tpos, ttyp, tidx,
                       out_s, m_out, step, on, pts, resid_t, jac_t, y, T, k, w, n0, wsum,
                       ws, WS)
            rt = _max_abs(resid_t)
            if rt < r or rt < tol:
                accepted = True
                break
            t *= 0.5
        if not accepted:
            at_x = False
            break
        chord = t == 1.0 and rt < 0.1 * r
        for i in range(nx):
            x[i] = xt[i]
            resid[i] = resid_t[i]
            for c in range(nx):
                jac[i, c] = jac_t[i, c]
        r = rt
        at_x = True
        fresh = True
    return r, it, at_x


@njit(cache=True, error_model="numpy")
def solve_loaded_batch(alpha, beta, L, straight, kappa, EI, ratio, kink, W, F, M, m, step, tol,
                       max_iter, x_init, x_start):
    """Solve and integrate a batch of loaded configurations.

    alpha, beta : (B, n) rad, mm; L, straight : (n,) mm; kappa, EI, ratio : (B, n) 1/mm,
    N mm^2, EI/GJ (0 = torsionally rigid); kink : (B, n, 2) rad; W : (B, n, 3) weight per unit
    length of each tube (N/mm, base frame); F : (B, 3) tip force N; M : (B, 3) tip moment N mm
    (base frame). x_init : (B, n + 2) first guess of (tau(0), mb_xy(0)) (N mm); x_start :
    (B, n + 2) the unloaded solution's unknowns, from which the load is ramped up (k/K of it,
    K = 8 then 32) where Newton from x_init fails; where that fails too, the torsional
    compliance is ramped up (EI/GJ scaled by k/K, K = 16 then 64) from the torsionally rigid
    loaded solution.

    Returns points (B, m, 3), s (B, m), x (B, n + 2), iterations (B,), residual (B,) (1/mm),
    ok (B,): converged (max residual < tol) and every point finite.
    """
    B, n = alpha.shape
    nx = n + 2
    N = 3 * n + 14
    points = np.zeros((B, m, 3))
    svals = np.zeros((B, m))
    xout = np.zeros((B, nx))
    iters = np.zeros(B, dtype=np.int64)
    rnorm = np.zeros(B)
    ok = np.zeros(B, dtype=np.bool_)
    y = np.zeros(N)
    T = np.zeros((N, nx))
    ws = np.zeros((5, N))
    WS = np.zeros((5, N, nx))
    k = np.zeros(n)
    w = np.zeros(n)
    n0 = np.zeros(3)
    wsum = np.zeros(3)
    tpos = np.zeros(2 * n)
    ttyp = np.zeros(2 * n, dtype=np.int64)
    tidx = np.zeros(2 * n, dtype=np.int64)
    resid = np.zeros(nx)
    jac = np.zeros((nx, nx))
    resid_t = np.zeros(nx)
    jac_t = np.zeros((nx, nx))
    A = np.zeros((nx, nx))
    dx = np.zeros(nx)
    x = np.zeros(nx)
    xt = np.zeros(nx)
    Wl = np.zeros((n, 3))
    Fl = np.zeros(3)
    Ml = np.zeros(3)
    rs = np.zeros(n)
    out_s = np.zeros(m)
    for bi in range(B):
        al = alpha[bi]
        be = beta[bi]
        _tube_events(be, L, straight, tpos, ttyp, tidx)
        tip = tpos[2 * n - 1]
        for q in range(m):
            out_s[q] = tip * q / (m - 1)
        out_s[m - 1] = tip
        for i in range(nx):
            x[i] = x_init[bi, i]
        r, it, at_x = _newton(al, be, x, L, straight, kappa[bi], EI[bi], ratio[bi], kink[bi],
                              W[bi], F[bi], M[bi], tpos, ttyp, tidx, out_s, m, step, tol,
                              max_iter, points[bi], resid, jac, resid_t, jac_t, dx, xt, A, y, T,
                              k, w, n0, wsum, ws, WS)
        for K in (8, 32):
            if r < tol:
                break
            for i in range(nx):
                x[i] = x_start[bi, i]
            for kk in range(1, K + 1):
                lam = kk / K
                for c in range(3):
                    Fl[c] = lam * F[bi, c]
                    Ml[c] = lam * M[bi, c]
                    for i in range(n):
                        Wl[i, c] = lam * W[bi, i, c]
                r, itk, at_x = _newton(al, be, x, L, straight, kappa[bi], EI[bi], ratio[bi],
                                       kink[bi], Wl, Fl, Ml, tpos, ttyp, tidx, out_s, m, step,
                                       tol, max_iter, points[bi], resid, jac, resid_t, jac_t, dx,
                                       xt, A, y, T, k, w, n0, wsum, ws, WS)
                it += itk
                if not r < tol:
                    at_x = at_x and kk == K
                    break
        for K in (16, 64):
            # near snapping the loaded branch through the unloaded solution may end (a fold):
            # continuation in the torsional compliance instead, from the torsionally rigid
            # loaded solution (EI/GJ = 0, well posed) to the nominal EI/GJ, at full load
            if r < tol:
                break
            for i in range(n):
                x[i] = 0.0
            x[n] = x_init[bi, n]
            x[n + 1] = x_init[bi, n + 1]
            if not (math.isfinite(x[n]) and math.isfinite(x[n + 1])):
                x[n] = 0.0
                x[n + 1] = 0.0
            for kk in range(0, K + 1):
                lam = kk / K
                for i in range(n):
                    rs[i] = lam * ratio[bi, i]
                r, itk, at_x = _newton(al, be, x, L, straight, kappa[bi], EI[bi], rs, kink[bi],
                                       W[bi], F[bi], M[bi], tpos, ttyp, tidx, out_s, m, step,
                                       tol, max_iter, points[bi], resid, jac, resid_t, jac_t, dx,
                                       xt, A, y, T, k, w, n0, wsum, ws, WS)
                it += itk
                if not r < tol:
                    at_x = at_x and kk == K
                    break
        if not at_x:
            _integrate(al, be, x, L, straight, kappa[bi], EI[bi], ratio[bi], kink[bi], W[bi],
                       F[bi], M[bi], tpos, ttyp, tidx, out_s, m, step, runtime(False),
                       points[bi], resid_t, jac_t, y, T, k, w, n0, wsum, ws, WS)
        finite = True
        for q in range(m):
            svals[bi, q] = out_s[q]
            for c in range(3):
                if not math.isfinite(points[bi, q, c]):
                    finite = False
        for i in range(nx):
            xout[bi, i] = x[i]
        iters[bi] = it
        rnorm[bi] = r
        ok[bi] = r < tol and finite
    return points, svals, xout, iters, rnorm, ok
