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
from collections import namedtuple

import numpy as np
from numba import njit

from ctrplan.shape._ode import (
    emit,
    frame_rates,
    kink_matrix,
    register_model,
    rk4,
    runtime,
    turn_frame,
)

# Every kernel uses numba's ``error_model="numpy"``: a division by zero gives inf/nan instead
# of a per-division check that raises (all divisions here are guarded; non-finite results end
# up as ok=False).

# Below this rotation angle the exponential's coefficients use their Taylor series
# (1 - cos t) / t^2 and (t - sin t) / t^3 cancel catastrophically for small t.
_SERIES_BELOW = 1e-2

#: One interval's constants of the state equations (:func:`_deriv`), the ``model`` of
#: :func:`ctrplan.shape._ode.rk4`: n tubes, a (n,) torsional coupling, w (n,) EI kappa of the
#: curved sections present (N mm^2 / mm), 1 / sum EI of the tubes present, and whether R, p are
#: integrated.
UnloadedRhs = namedtuple("UnloadedRhs", ("n", "a", "w", "eisum_inv", "frame"))

#: One configuration (the ``problem`` of :func:`ctrplan.shape._ode.newton`): alpha, beta (n,)
#: rad, mm; L, straight (n,) mm; kappa, EI, ratio (n,) 1/mm, N mm^2, EI/GJ; kink (n, 2) rad;
#: torsion (False: the rigid model); step (mm); tpos, ttyp, tidx its tube events; work
#: (:func:`unloaded_work`).
UnloadedProblem = namedtuple("UnloadedProblem", (
    "alpha", "beta", "L", "straight", "kappa", "EI", "ratio", "kink", "torsion", "step", "tpos",
    "ttyp", "tidx", "work"))


@njit(cache=True, error_model="numpy", _nrt=False)
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
        frame_rates(y, b, ux, uy, dy)
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


@njit(cache=True, error_model="numpy", _nrt=False)
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


@njit(cache=True, error_model="numpy", _nrt=False)
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


@njit(cache=True, error_model="numpy", _nrt=False)
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


@njit(cache=True, error_model="numpy", _nrt=False)
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


@njit(cache=True, error_model="numpy", inline="always")
def _start(alpha, beta, x, torsion, frame, sens, y, Y, pend):
    """The states at s = 0: psi_i = alpha_i - beta_i uz_i(0) (the straight part behind the
    constraint plane twists uniformly), uz = x (0 for the rigid model), R = I, p = 0; dpsi/dx
    = -beta, duz/dx = I."""
    n = alpha.shape[0]
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


@njit(cache=True, error_model="numpy", inline="always")
def _regime(mid, beta, L, straight, kappa, EI, ratio, torsion, y, a, w):
    """The regime at arc length ``mid`` (constant between break points): fills w (and a where
    two or more curved sections overlap in the compliant model). Returns (1 / sum EI, number of
    curved sections, the last curved tube, whether the torsions vary: RK4 is needed)."""
    n = beta.shape[0]
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
        # constant: the rigid model's exact arc, not RK4
    return eisum_inv, ncurved, jc, twisting


@njit(cache=True, error_model="numpy", inline="always")
def _interval(y, Y, n, nst, w, a, eisum_inv, ncurved, jc, twisting, torsion, frame, sens,
              s_now, s_next, step, out_s, m_out, ko, out_p, pend, ws, WS, G):
    """Advance from s_now to s_next (one regime): RK4 where the torsions vary, else exactly,
    split at the output points inside. Returns the next output index."""
    b = 3 * n
    if twisting:
        for i in range(n):
            _catch_up(y, n, i, pend)
        return rk4(UnloadedRhs(n, a, w, eisum_inv, frame), y, Y, nst, frame, sens, s_now,
                   s_next - s_now, step, out_s, m_out, runtime(ko), out_p, ws, WS)
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
        _exact(y, Y, n, b, w, eisum_inv, runtime(ncurved), runtime(jc), torsion, frame, sens, d,
               pend, G)
    return ko


@njit(cache=True, error_model="numpy", inline="always")
def _tube_end(i, y, Y, n, frame, sens, kink, resid, jac, G):
    """Tube i ends: its boundary residual uz_i (and the Jacobian row); then its torsion (and so
    its angle) is frozen, and the clearance kink turns the frame."""
    resid[i] = y[2 * n + i]
    if sens:
        for c in range(n):
            jac[i, c] = Y[n + i, c]
    y[2 * n + i] = 0.0
    if sens:
        for c in range(n):
            Y[n + i, c] = 0.0
    if frame and (kink[i, 0] != 0.0 or kink[i, 1] != 0.0):
        kink_matrix(kink[i, 0], kink[i, 1], G)
        turn_frame(y.reshape((y.shape[0], 1)), 0, 3 * n, G)


@njit(cache=True, error_model="numpy", _nrt=False)
def _integrate(alpha, beta, x, L, straight, kappa, EI, ratio, kink, torsion,
               tpos, ttyp, tidx, out_s, m_out, step, frame, sens, out_p, resid, jac,
               y, Y, a, w, pend, ws, WS, G):
    """Integrate one configuration from s = 0 to its last tube event.

    tpos/ttyp/tidx : the sorted tube events (:func:`ctrplan.shape._ode._tube_events`);
    out_s[:m_out] : sorted output arc lengths in [0, last event]. Fills ``out_p`` (m_out, 3)
    when ``frame``; ``resid`` (n,) = uz_i at tube i's end (always) and ``jac`` (n, n) =
    d resid / d x when ``sens``. y, Y, a, w, pend, ws, WS, G are workspace.
    """
    n = alpha.shape[0]
    nst = 3 * n + 12 if frame else 3 * n
    _start(alpha, beta, x, torsion, frame, sens, y, Y, pend)
    ko = 0
    if not frame:
        m_out = 0
    s_now = 0.0
    for it in range(2 * n):
        s_next = tpos[it]
        seg = s_next - s_now
        if seg > 0.0:
            eisum_inv, ncurved, jc, twisting = _regime(s_now + 0.5 * seg, beta, L, straight,
                                                       kappa, EI, ratio, torsion, y, a, w)
            ko = _interval(y, Y, n, nst, w, a, eisum_inv, ncurved, jc, twisting, torsion, frame,
                           sens, s_now, s_next, step, out_s, m_out, runtime(ko), out_p, pend,
                           ws, WS, G)
            s_now = s_next
        if ttyp[it] == 1:
            _tube_end(tidx[it], y, Y, n, frame, sens, kink, resid, jac, G)
        ko = emit(out_s, out_p, ko, m_out, s_now, it == 2 * n - 1, y, 3 * n)


# ----------------------------------------------------------------------------- the model's records
@njit(cache=True, error_model="numpy", inline="always")
def unloaded_work(n):
    """Workspace of one unloaded problem: y, Y, a, w, pend, ws, WS, G and the scaled EI/GJ."""
    nst = 3 * n + 12
    return (np.zeros(nst), np.zeros((2 * n, n)), np.zeros(n), np.zeros(n), np.zeros(n),
            np.zeros((5, nst)), np.zeros((5, 2 * n, n)), np.zeros((3, 3)), np.zeros(n))


def _derivative(model, y, Y, s, sens, dy, dY):
    _deriv(y, Y, model.n, model.a, model.w, model.eisum_inv, model.frame, sens, dy, dY)


def _shoot(problem, x, sens, out_s, m_out, out_p, resid, jac):
    p = problem
    y, Y, a, w, pend, ws, WS, G, _rs = p.work
    # R and p are integrated only for output points
    _integrate(p.alpha, p.beta, x, p.L, p.straight, p.kappa, p.EI, p.ratio, p.kink, p.torsion,
               p.tpos, p.ttyp, p.tidx, out_s, m_out, p.step, m_out > 0, sens, out_p, resid, jac,
               y, Y, a, w, pend, ws, WS, G)


def _scaled(problem, lam, what):
    p = problem                 # what: COMPLIANCE, the only parameter scaled here
    rs = p.work[8]
    for i in range(rs.shape[0]):
        rs[i] = p.ratio[i] * lam
    return UnloadedProblem(p.alpha, p.beta, p.L, p.straight, p.kappa, p.EI, rs, p.kink,
                           p.torsion, p.step, p.tpos, p.ttyp, p.tidx, p.work)


register_model(UnloadedRhs, UnloadedProblem, _derivative, _shoot, _scaled, chords=False)

# numba cache stamp: d8f966079f52654bec9904c45b481f0c7a18363c5bbb5d76c49e39122e994b7c
