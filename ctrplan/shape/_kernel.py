"""Numba kernels of the mechanics model (torsionally rigid and compliant CTRs).

Formulation (docs/conventions.md for units and frames). A twist-free backbone frame ``R`` (``R' = R [u]x`` with
``u = (ux, uy, 0)``, ``p' = R e_z``) carries every tube; tube i's material frame is
``R Rz(psi_i)`` and its torsion is ``uz_i = psi_i'``. Unloaded moment balance gives

    u_xy   = sum_j EI_j Rz(psi_j) uhat_j / sum_j EI_j          (tubes present at s)
    uz_i'  = (EI_i / GJ_i) kappa_i / EIsum * sum_j EI_j kappa_j sin(psi_i - psi_j)

with precurvature ``uhat_i = (0, kappa_i, 0)`` on the curved section. Boundary values:
``psi_i(0) = alpha_i - beta_i uz_i(0)`` (the straight part behind the constraint plane twists
uniformly) and ``uz_i(beta_i + L_i) = 0``, solved by shooting on ``x = uz(0)`` with Newton and
the Jacobian from the variational equations. The rigid model is the same with ``uz = 0``.

Integration runs over the intervals between break points (curve starts, tube ends and, in the
final pass, the output points). Where fewer than two curved sections overlap, the torsions are
constant (every ``sin(psi_i - psi_j)`` term vanishes) and the interval is stepped *exactly*:
psi advances linearly, and the backbone is a circular arc or, when the one curved tube twists,
a helix (in the frame ``R Rz(psi_j)`` the curvature ``(0, k, uz_j)`` is constant, so the
rotation is one matrix exponential). The rigid model is piecewise constant curvature, so it is
exact everywhere. Only where two or more curved sections overlap in the compliant model is
fixed-step RK4 used: the interval is cut into ``ceil(length / step)`` equal steps, angles are
carried as cos/sin (no trig in the loop), and the variational equations ride along in the
shooting passes (RK4 applied to them is the exact derivative of the RK4 map, so Newton
converges quadratically on the discretised problem). The step grid depends on the break
points only; output points inside an RK4 interval are read off by cubic Hermite interpolation,
so the final (frame) pass reproduces the shooting passes' torsion exactly and its residual
can confirm convergence (saving a pass). Where Newton stalls (snapping configurations) the
solve is retried by continuation in the torsional compliance. ``kink`` adds a small rotation
``R <- R Exp([kx, ky, 0])`` where tube j ends (used by the clearance effect; zero gives the base
model exactly). No numpy allocation happens per configuration: one workspace per batch.
"""

from __future__ import annotations

import math

from numba import njit, types
from numba.extending import intrinsic

# Every kernel uses numba's ``error_model="numpy"``: a division by zero gives inf/nan instead
# of a per-division check that raises (all divisions here are guarded; non-finite results end
# up as ok=False).

# Below this rotation angle the exponential's coefficients use their Taylor series
# (1 - cos t) / t^2 and (t - sin t) / t^3 cancel catastrophically for small t.
_SERIES_BELOW = 1e-2


@intrinsic
def runtime(typingctx, v):
    """``v`` with its literal type dropped (a bool or int constant becomes a plain bool or
    int64). Numba compiles one specialisation of a jitted callee per distinct literal argument
    (``True``, ``0``, ...); passing such arguments through this keeps one compiled version of
    each kernel: the first (uncached) compile of the compliant model took 28 s before and 15 s
    after on the 2-core development machine, with bit-identical results and the same run time."""
    plain = types.unliteral(v)

    def codegen(context, builder, signature, args):
        return context.cast(builder, args[0], v, plain)

    return plain(v), codegen


@njit(cache=True, error_model="numpy")
def _tube_events(beta, L, straight, tpos, ttyp, tidx):
    """Sorted tube events (curve start = 0, tube end = 1) by insertion sort; ties keep
    curve starts before ends, curve starts of lower tube indices first and ends of higher
    (outer) tube indices first: the order of ends just apart, as the constraints allow them
    (an inner tube reaches at least as far), so that the clearance kinks of tubes ending
    together compose as in the limit and the shape is continuous there."""
    n = beta.shape[0]
    ne = 2 * n
    for i in range(n):
        tpos[i] = max(beta[i] + straight[i], 0.0)
        ttyp[i] = 0
        tidx[i] = i
        o = n - 1 - i
        tpos[n + i] = max(beta[o] + L[o], 0.0)
        ttyp[n + i] = 1
        tidx[n + i] = o
    for k in range(1, ne):
        p = tpos[k]
        t = ttyp[k]
        j = tidx[k]
        m = k - 1
        while m >= 0 and tpos[m] > p:
            tpos[m + 1] = tpos[m]
            ttyp[m + 1] = ttyp[m]
            tidx[m + 1] = tidx[m]
            m -= 1
        tpos[m + 1] = p
        ttyp[m + 1] = t
        tidx[m + 1] = j


@njit(cache=True, error_model="numpy")
def _deriv(y, Y, n, a, w, eisum_inv, frame, sens, dy, dY):
    """Derivative of y = [c(n), s(n), uz(n), R(9, row-major), p(3)] and of the sensitivities
    Y = [dpsi/dx (n x n); duz/dx (n x n)] (when ``sens``)."""
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
    if sens:
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


@njit(cache=True, error_model="numpy")
def _hermite_out(out_s, out_p, ko, m_out, s_end, sa, sb, h, pax, pay, paz, tax, tay, taz, y, b):
    """Backbone points at the output arc lengths in (sa, sb] of one RK4 step, by cubic Hermite
    interpolation between the step's end points (position y[b+9:b+12], tangent = third column
    of R, y[b+2], y[b+5], y[b+8]) and the start values ``pa``, ``ta``. Returns the next ``ko``."""
    pbx = y[b + 9]
    pby = y[b + 10]
    pbz = y[b + 11]
    tbx = y[b + 2]
    tby = y[b + 5]
    tbz = y[b + 8]
    while ko < m_out and out_s[ko] < s_end and out_s[ko] <= sb:
        th = (out_s[ko] - sa) / h
        if th < 0.0:
            th = 0.0
        th2 = th * th
        th3 = th2 * th
        h00 = 2.0 * th3 - 3.0 * th2 + 1.0
        h10 = (th3 - 2.0 * th2 + th) * h
        h01 = -2.0 * th3 + 3.0 * th2
        h11 = (th3 - th2) * h
        out_p[ko, 0] = h00 * pax + h10 * tax + h01 * pbx + h11 * tbx
        out_p[ko, 1] = h00 * pay + h10 * tay + h01 * pby + h11 * tby
        out_p[ko, 2] = h00 * paz + h10 * taz + h01 * pbz + h11 * tbz
        ko += 1
    return ko


@njit(cache=True, error_model="numpy")
def _rk4(y, Y, n, nst, a, w, eisum_inv, frame, sens, s0, seg, step, out_s, m_out, ko, out_p,
         k1, k2, k3, k4, yt, K1, K2, K3, K4, Yt):
    """Fixed-step RK4 over [s0, s0 + seg] (``ceil(seg / step)`` equal steps).

    The step grid depends on the break points only, so the frame pass reproduces the shooting
    passes' torsion exactly. Output points ``out_s[ko:]`` that fall strictly inside the
    interval are read off by cubic Hermite interpolation of p between steps (p' = R e_z at
    both ends; O(h^4) like RK4 itself). Returns the next output index. k*, yt (nst,) and
    K*, Yt (2n, n) are workspace.
    """
    nsub = int(math.ceil(seg / step - 1e-9))
    if nsub < 1:
        nsub = 1
    h = seg / nsub
    n2 = 2 * n
    b = 3 * n
    s_end = s0 + seg
    for q in range(nsub):
        sa = s0 + q * h
        sb = s_end if q == nsub - 1 else sa + h
        pax = 0.0
        pay = 0.0
        paz = 0.0
        tax = 0.0
        tay = 0.0
        taz = 0.0
        want = frame and ko < m_out and out_s[ko] < s_end and out_s[ko] <= sb
        if want:
            pax = y[b + 9]
            pay = y[b + 10]
            paz = y[b + 11]
            tax = y[b + 2]
            tay = y[b + 5]
            taz = y[b + 8]
        _deriv(y, Y, n, a, w, eisum_inv, frame, sens, k1, K1)
        for j in range(nst):
            yt[j] = y[j] + 0.5 * h * k1[j]
        if sens:
            for r in range(n2):
                for c in range(n):
                    Yt[r, c] = Y[r, c] + 0.5 * h * K1[r, c]
        _deriv(yt, Yt, n, a, w, eisum_inv, frame, sens, k2, K2)
        for j in range(nst):
            yt[j] = y[j] + 0.5 * h * k2[j]
        if sens:
            for r in range(n2):
                for c in range(n):
                    Yt[r, c] = Y[r, c] + 0.5 * h * K2[r, c]
        _deriv(yt, Yt, n, a, w, eisum_inv, frame, sens, k3, K3)
        for j in range(nst):
            yt[j] = y[j] + h * k3[j]
        if sens:
            for r in range(n2):
                for c in range(n):
                    Yt[r, c] = Y[r, c] + h * K3[r, c]
        _deriv(yt, Yt, n, a, w, eisum_inv, frame, sens, k4, K4)
        h6 = h / 6.0
        for j in range(nst):
            y[j] += h6 * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j])
        if sens:
            for r in range(n2):
                for c in range(n):
                    Y[r, c] += h6 * (K1[r, c] + 2.0 * K2[r, c] + 2.0 * K3[r, c] + K4[r, c])
        if want:
            ko = _hermite_out(out_s, out_p, ko, m_out, s_end, sa, sb, h, pax, pay, paz, tax, tay,
                              taz, y, b)
    return ko


@njit(cache=True, error_model="numpy")
def _exp_coeffs(th2, seg):
    """For Exp(seg [v]x) with th = |v| seg: returns (a1, a2, a3) with
    Exp = I + a1 [v] + a2 [v]^2 and int_0^seg Exp(t [v]) dt = seg I + a2 [v] + a3 [v]^2."""
    if th2 < _SERIES_BELOW * _SERIES_BELOW:
        s1 = 1.0 - th2 / 6.0 + th2 * th2 / 120.0             # sin t / t
        s2 = 0.5 - th2 / 24.0 + th2 * th2 / 720.0            # (1 - cos t) / t^2
        s3 = 1.0 / 6.0 - th2 / 120.0 + th2 * th2 / 5040.0    # (t - sin t) / t^3
    else:
        th = math.sqrt(th2)
        st = math.sin(th)
        ct = math.cos(th)
        s1 = st / th
        s2 = (1.0 - ct) / th2
        s3 = (th - st) / (th2 * th)
    return seg * s1, seg * seg * s2, seg * seg * seg * s3


@njit(cache=True, error_model="numpy")
def _exact_frame(y, b, seg, vx, vy, vz, c0, s0, c1, s1, G):
    """Advance R, p exactly over ``seg`` when the curvature is constant in a frame that spins
    at rate vz about the tangent: R(s) = R0 Rz(phi0) Exp(s [v]x) Rz(-phi(s)),
    p(s) = p0 + R0 Rz(phi0) int Exp. (c0, s0) = (cos, sin) phi0, (c1, s1) = at the end."""
    v2 = vx * vx + vy * vy + vz * vz
    a1, a2, a3 = _exp_coeffs(v2 * seg * seg, seg)
    # E = I + a1 [v] + a2 [v]^2 ; [v]^2 = v v^T - |v|^2 I
    e00 = 1.0 + a2 * (vx * vx - v2)
    e11 = 1.0 + a2 * (vy * vy - v2)
    e22 = 1.0 + a2 * (vz * vz - v2)
    e01 = -a1 * vz + a2 * vx * vy
    e10 = a1 * vz + a2 * vx * vy
    e02 = a1 * vy + a2 * vx * vz
    e20 = -a1 * vy + a2 * vx * vz
    e12 = -a1 * vx + a2 * vy * vz
    e21 = a1 * vx + a2 * vy * vz
    # local displacement d = seg e_z + a2 (v x e_z) + a3 v x (v x e_z)
    dx = a2 * vy + a3 * vx * vz
    dy_ = -a2 * vx + a3 * vy * vz
    dz = seg + a3 * (vz * vz - v2)
    # M = E Rz(-phi1): Rz(-phi1) = [[c1, s1, 0], [-s1, c1, 0], [0, 0, 1]]
    m00 = e00 * c1 - e01 * s1
    m01 = e00 * s1 + e01 * c1
    m10 = e10 * c1 - e11 * s1
    m11 = e10 * s1 + e11 * c1
    m20 = e20 * c1 - e21 * s1
    m21 = e20 * s1 + e21 * c1
    # G = Rz(phi0) M (3 x 3), g = Rz(phi0) d
    G[0, 0] = c0 * m00 - s0 * m10
    G[0, 1] = c0 * m01 - s0 * m11
    G[0, 2] = c0 * e02 - s0 * e12
    G[1, 0] = s0 * m00 + c0 * m10
    G[1, 1] = s0 * m01 + c0 * m11
    G[1, 2] = s0 * e02 + c0 * e12
    G[2, 0] = m20
    G[2, 1] = m21
    G[2, 2] = e22
    gx = c0 * dx - s0 * dy_
    gy = s0 * dx + c0 * dy_
    gz = dz
    for r in range(3):
        r0 = y[b + 3 * r]
        r1 = y[b + 3 * r + 1]
        r2 = y[b + 3 * r + 2]
        y[b + 9 + r] += r0 * gx + r1 * gy + r2 * gz
        y[b + 3 * r] = r0 * G[0, 0] + r1 * G[1, 0] + r2 * G[2, 0]
        y[b + 3 * r + 1] = r0 * G[0, 1] + r1 * G[1, 1] + r2 * G[2, 1]
        y[b + 3 * r + 2] = r0 * G[0, 2] + r1 * G[1, 2] + r2 * G[2, 2]


@njit(cache=True, error_model="numpy")
def _catch_up(y, n, i, pend):
    """Apply tube i's deferred rotation ``pend[i]`` to its (cos, sin) psi."""
    th = pend[i]
    if th != 0.0:
        ct = math.cos(th)
        st = math.sin(th)
        c = y[i]
        s = y[n + i]
        y[i] = c * ct - s * st
        y[n + i] = s * ct + c * st
        pend[i] = 0.0


@njit(cache=True, error_model="numpy")
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


@njit(cache=True, error_model="numpy")
def _exact(y, Y, n, b, w, eisum_inv, ncurved, jc, torsion, frame, sens, seg, pend, G):
    """Advance over ``seg`` where fewer than two curved sections overlap (or the model is
    rigid): the torsions are constant, so every psi advances linearly (its (cos, sin) rotation
    is deferred in ``pend`` until someone needs the angle) and R, p follow an arc or helix."""
    cj0 = 1.0
    sj0 = 0.0
    if frame and torsion and ncurved == 1:
        _catch_up(y, n, jc, pend)
        cj0 = y[jc]
        sj0 = y[n + jc]
        nrm = 1.0 / math.sqrt(cj0 * cj0 + sj0 * sj0)
        cj0 *= nrm
        sj0 *= nrm
    if torsion:
        for i in range(n):
            pend[i] += y[2 * n + i] * seg
        if sens:
            for i in range(n):
                for c in range(n):
                    Y[i, c] += seg * Y[n + i, c]
    if frame:
        if ncurved == 0:
            for r in range(3):
                y[b + 9 + r] += seg * y[b + 3 * r + 2]
        elif torsion and ncurved == 1 and y[2 * n + jc] != 0.0:
            # helix: in the frame R Rz(psi_j) the curvature (0, k, uz_j) is constant
            _catch_up(y, n, jc, pend)
            cj1 = y[jc]
            sj1 = y[n + jc]
            nrm = 1.0 / math.sqrt(cj1 * cj1 + sj1 * sj1)
            _exact_frame(y, b, seg, 0.0, w[jc] * eisum_inv, y[2 * n + jc],
                         cj0, sj0, cj1 * nrm, sj1 * nrm, G)
        else:
            # constant curvature (the rigid model, or no torsion in the curved sections):
            # a circular arc
            cw = 0.0
            sw = 0.0
            for j in range(n):
                if w[j] != 0.0:
                    wj = w[j]
                    if torsion:
                        # (cos, sin) psi drift off the unit circle in RK4 intervals
                        _catch_up(y, n, j, pend)
                        wj /= math.sqrt(y[j] * y[j] + y[n + j] * y[n + j])
                    cw += wj * y[j]
                    sw += wj * y[n + j]
            _exact_frame(y, b, seg, -sw * eisum_inv, cw * eisum_inv, 0.0,
                         1.0, 0.0, 1.0, 0.0, G)


@njit(cache=True, error_model="numpy")
def _integrate(alpha, beta, x, L, straight, kappa, EI, ratio, kink, torsion,
               tpos, ttyp, tidx, out_s, m_out, step, frame, sens, out_p, resid, jac,
               y, Y, a, w, pend, ws, WS, G):
    """Integrate one configuration from s = 0 to its last tube event.

    tpos/ttyp/tidx : the sorted tube events (:func:`_tube_events`); out_s[:m_out] : sorted
    output arc lengths in [0, last event]. Fills ``out_p`` (m_out, 3) when ``frame``;
    ``resid`` (n,) = uz_i at tube i's end (always) and ``jac`` (n, n) = d resid / d x when
    ``sens``. y, Y, a, w, pend, ws, WS, G are workspace.
    """
    n = alpha.shape[0]
    nst = 3 * n + 12 if frame else 3 * n
    b = 3 * n
    for i in range(n):
        xi = x[i] if torsion else 0.0
        psi0 = alpha[i] - beta[i] * xi
        y[i] = math.cos(psi0)
        y[n + i] = math.sin(psi0)
        y[2 * n + i] = xi
        pend[i] = 0.0
    if frame:
        for j in range(12):
            y[b + j] = 0.0
        y[b + 0] = 1.0
        y[b + 4] = 1.0
        y[b + 8] = 1.0
    if sens:
        for r in range(2 * n):
            for c in range(n):
                Y[r, c] = 0.0
        for i in range(n):
            Y[i, i] = -beta[i]
            Y[n + i, i] = 1.0
    ko = 0
    if not frame:
        m_out = 0
    s_now = 0.0
    for it in range(2 * n):
        s_next = tpos[it]
        seg = s_next - s_now
        if seg > 0.0:
            # the regime (tubes present, curved sections) is constant inside the interval
            mid = s_now + 0.5 * seg
            eisum = 0.0
            ncurved = 0
            jc = -1
            for i in range(n):
                present = mid < beta[i] + L[i]
                curved = mid >= beta[i] + straight[i]
                if present:
                    eisum += EI[i]
                if present and curved and kappa[i] != 0.0:
                    w[i] = EI[i] * kappa[i]
                    ncurved += 1
                    jc = i
                else:
                    w[i] = 0.0
            eisum_inv = 1.0 / eisum if eisum > 0.0 else 0.0
            twisting = False
            if torsion and ncurved >= 2:
                for i in range(n):
                    a[i] = ratio[i] * kappa[i] * eisum_inv if w[i] != 0.0 else 0.0
                    if a[i] != 0.0 or y[2 * n + i] != 0.0:
                        twisting = True
                # with no torsional coupling and no torsion (e.g. EI/GJ = 0) the curvature is
                # constant: the rigid model's exact arc below, not RK4
            if twisting:
                for i in range(n):
                    _catch_up(y, n, i, pend)
                ko = _rk4(y, Y, n, nst, a, w, eisum_inv, frame, sens, s_now, seg, step,
                          out_s, m_out, runtime(ko), out_p, ws[0], ws[1], ws[2], ws[3], ws[4],
                          WS[0], WS[1], WS[2], WS[3], WS[4])
            else:
                # exact: split at the output points inside the interval
                s_at = s_now
                while ko < m_out and out_s[ko] < s_next:
                    d = out_s[ko] - s_at
                    if d > 0.0:
                        _exact(y, Y, n, b, w, eisum_inv, runtime(ncurved), runtime(jc), torsion, frame,
                               sens, d, pend, G)
                        s_at = out_s[ko]
                    out_p[ko, 0] = y[b + 9]
                    out_p[ko, 1] = y[b + 10]
                    out_p[ko, 2] = y[b + 11]
                    ko += 1
                d = s_next - s_at
                if d > 0.0:
                    _exact(y, Y, n, b, w, eisum_inv, runtime(ncurved), runtime(jc), torsion, frame,
                           sens, d, pend, G)
            s_now = s_next
        i = tidx[it]
        if ttyp[it] == 1:
            resid[i] = y[2 * n + i]
            if sens:
                for c in range(n):
                    jac[i, c] = Y[n + i, c]
            # the tube is gone: its torsion (and so its angle) is frozen from here on
            y[2 * n + i] = 0.0
            if sens:
                for c in range(n):
                    Y[n + i, c] = 0.0
            if frame and (kink[i, 0] != 0.0 or kink[i, 1] != 0.0):
                _apply_kink(y, b, kink[i, 0], kink[i, 1])
        # output points at (or, by round-off, just past) this event
        while ko < m_out and (out_s[ko] <= s_now or it == 2 * n - 1):
            out_p[ko, 0] = y[b + 9]
            out_p[ko, 1] = y[b + 10]
            out_p[ko, 2] = y[b + 11]
            ko += 1
