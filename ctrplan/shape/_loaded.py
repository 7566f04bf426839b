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
from collections import namedtuple

import numpy as np
from numba import njit

from ctrplan.shape._ode import (
    COMPLIANCE,
    LOADS,
    emit,
    events,
    finish_row,
    frame_rates,
    kink_matrix,
    newton,
    newton_work,
    outputs,
    ramp,
    register_model,
    rk4,
    row_grid,
    runtime,
    store_row,
    turn_frame,
)

#: One interval's constants of the state equations (:func:`_rhs`), the ``model`` of
#: :func:`ctrplan.shape._ode.rk4`: n tubes, nx = n + 2 unknowns, k (n,) EI/GJ / EI, w (n,)
#: EI kappa of the curved sections present, 1 / sum EI of the tubes present, and the internal
#: force n(s) = n0 - s wsum (base frame, N).
LoadedRhs = namedtuple("LoadedRhs", ("n", "nx", "k", "w", "eisum_inv", "n0", "wsum"))

#: One loaded configuration (the ``problem`` of :func:`ctrplan.shape._ode.newton`): as
#: :class:`ctrplan.shape._kernel.UnloadedProblem` with the loads W (n, 3) N/mm, F (3,) N,
#: M (3,) N mm instead of the torsion flag (ratio = 0 is the rigid model); work
#: (:func:`loaded_work`).
LoadedProblem = namedtuple("LoadedProblem", (
    "alpha", "beta", "L", "straight", "kappa", "EI", "ratio", "kink", "W", "F", "M", "step",
    "tpos", "ttyp", "tidx", "work"))


@njit(cache=True, error_model="numpy", _nrt=False)
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
    frame_rates(y, b, ux, uy, dy)
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


@njit(cache=True, error_model="numpy", inline="always")
def _turn_moment(Z, col, n, b, K):
    """mb_xy <- (K^T (mb_x, mb_y, sum tau))_xy for the state (or tangent) Z[:, col]: the
    bending moment turns with the frame, the twisting moment sum tau carries over."""
    mx = Z[b + 12, col]
    my = Z[b + 13, col]
    mz = 0.0
    for j in range(n):
        mz += Z[2 * n + j, col]
    Z[b + 12, col] = K[0, 0] * mx + K[1, 0] * my + K[2, 0] * mz
    Z[b + 13, col] = K[0, 1] * mx + K[1, 1] * my + K[2, 1] * mz


@njit(cache=True, error_model="numpy", _nrt=False)
def _kink(y, T, n, nx, sens, kx, ky, K):
    """R <- R K with K = Exp([kx, ky, 0]); mb_xy <- (K^T (mb_x, mb_y, sum tau))_xy, the
    twisting moment sum tau carries over. The tangent follows (K is constant). K (3, 3) is
    workspace."""
    b = 3 * n
    kink_matrix(kx, ky, K)
    Yv = y.reshape((y.shape[0], 1))
    turn_frame(Yv, 0, b, K)
    _turn_moment(Yv, 0, n, b, K)
    for col in range(nx if sens else 0):
        turn_frame(T, col, b, K)
        _turn_moment(T, col, n, b, K)


@njit(cache=True, error_model="numpy", inline="always")
def _start(alpha, beta, x, ratio, EI, sens, y, T, k):
    """The states at s = 0: psi_i = alpha_i - beta_i uz_i(0), tau = x[:n], R = I, p = 0,
    mb = x[n:]; and their derivatives by x."""
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


@njit(cache=True, error_model="numpy", inline="always")
def _regime(mid, beta, L, straight, kappa, EI, W, F, w, n0, wsum):
    """The regime at arc length ``mid`` (constant between break points): w, and the internal
    force n(s) = n0 - s wsum of the tip force and the weight of the tubes present (N).
    Returns 1 / sum EI."""
    n = beta.shape[0]
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
    return 1.0 / eisum if eisum > 0.0 else 0.0


@njit(cache=True, error_model="numpy", inline="always")
def _along(Z, col, b, M, j):
    """Component j of R^T M (the moment M in the backbone frame) from the frame in Z[:, col]."""
    return Z[b + j, col] * M[0] + Z[b + 3 + j, col] * M[1] + Z[b + 6 + j, col] * M[2]


@njit(cache=True, error_model="numpy", inline="always")
def _tube_end(i, y, T, n, sens, EI, M, kink, resid, jac, K):
    """Tube i ends: its residual tau_i (the innermost tube: minus the tip moment's twist) / EI_i
    and its Jacobian row; then no torsion, its angle frozen; the clearance kink."""
    nx = n + 2
    b = 3 * n
    Yv = y.reshape((y.shape[0], 1))
    tz = _along(Yv, 0, b, M, 2) if i == 0 else 0.0
    resid[i] = (y[2 * n + i] - tz) / EI[i]
    if sens:
        for c in range(nx):
            dtz = _along(T, c, b, M, 2) if i == 0 else 0.0
            jac[i, c] = (T[2 * n + i, c] - dtz) / EI[i]
    y[2 * n + i] = 0.0
    if sens:
        for c in range(nx):
            T[2 * n + i, c] = 0.0
    if kink[i, 0] != 0.0 or kink[i, 1] != 0.0:
        _kink(y, T, n, nx, sens, kink[i, 0], kink[i, 1], K)


@njit(cache=True, error_model="numpy", inline="always")
def _tip(y, T, n, sens, EI, M, resid, jac):
    """The tip: the bending moment equals the applied moment (backbone frame), / EI_1."""
    b = 3 * n
    e0 = EI[0]
    Yv = y.reshape((y.shape[0], 1))
    resid[n] = (y[b + 12] - _along(Yv, 0, b, M, 0)) / e0
    resid[n + 1] = (y[b + 13] - _along(Yv, 0, b, M, 1)) / e0
    if sens:
        for c in range(n + 2):
            jac[n, c] = (T[b + 12, c] - _along(T, c, b, M, 0)) / e0
            jac[n + 1, c] = (T[b + 13, c] - _along(T, c, b, M, 1)) / e0


@njit(cache=True, error_model="numpy", _nrt=False)
def _integrate(alpha, beta, x, L, straight, kappa, EI, ratio, kink, W, F, M, tpos, ttyp, tidx,
               out_s, m_out, step, sens, out_p, resid, jac, y, T, k, w, n0, wsum, ws, WS, K):
    """One pass from s = 0 to the tip at unknowns x (n + 2). Fills resid (n + 2), jac when
    ``sens`` and out_p[:m_out] (m_out may be 0)."""
    n = alpha.shape[0]
    _start(alpha, beta, x, ratio, EI, sens, y, T, k)
    ko = 0
    s_now = 0.0
    ne = 2 * n
    for it in range(ne):
        s_next = tpos[it]
        seg = s_next - s_now
        if seg > 0.0:
            eisum_inv = _regime(s_now + 0.5 * seg, beta, L, straight, kappa, EI, W, F, w, n0,
                                wsum)
            ko = rk4(LoadedRhs(n, n + 2, k, w, eisum_inv, n0, wsum), y, T, y.shape[0],
                     runtime(True), sens, s_now, seg, step, out_s, m_out, runtime(ko), out_p, ws,
                     WS)
            s_now = s_next
        if ttyp[it] == 1:
            _tube_end(tidx[it], y, T, n, sens, EI, M, kink, resid, jac, K)
        ko = emit(out_s, out_p, ko, m_out, s_now, it == ne - 1, y, 3 * n)
    _tip(y, T, n, sens, EI, M, resid, jac)


# ----------------------------------------------------------------------------- the model's records
@njit(cache=True, error_model="numpy", inline="always")
def loaded_work(n):
    """Workspace of one loaded problem: y, T, k, w, n0, wsum, ws, WS and the scaled EI/GJ,
    weights, tip force and tip moment; K (3, 3) the kink rotation."""
    N = 3 * n + 14
    nx = n + 2
    return (np.zeros(N), np.zeros((N, nx)), np.zeros(n), np.zeros(n), np.zeros(3), np.zeros(3),
            np.zeros((5, N)), np.zeros((5, N, nx)), np.zeros(n), np.zeros((n, 3)), np.zeros(3),
            np.zeros(3), np.zeros((3, 3)))


def _derivative(model, y, Y, s, sens, dy, dY):
    m = model
    _rhs(y, Y, m.n, m.nx, s, m.k, m.w, m.eisum_inv, m.n0, m.wsum, sens, dy, dY)


def _shoot(problem, x, sens, out_s, m_out, out_p, resid, jac):
    p = problem
    y, T, k, w, n0, wsum, ws, WS = p.work[:8]
    K = p.work[12]
    _integrate(p.alpha, p.beta, x, p.L, p.straight, p.kappa, p.EI, p.ratio, p.kink, p.W, p.F,
               p.M, p.tpos, p.ttyp, p.tidx, out_s, m_out, p.step, sens, out_p, resid, jac, y, T,
               k, w, n0, wsum, ws, WS, K)


def _scaled(problem, lam, what):
    p = problem
    rs, Wl, Fl, Ml = p.work[8:12]
    if what == LOADS:
        for c in range(3):
            Fl[c] = lam * p.F[c]
            Ml[c] = lam * p.M[c]
            for i in range(Wl.shape[0]):
                Wl[i, c] = lam * p.W[i, c]
        return LoadedProblem(p.alpha, p.beta, p.L, p.straight, p.kappa, p.EI, p.ratio, p.kink,
                             Wl, Fl, Ml, p.step, p.tpos, p.ttyp, p.tidx, p.work)
    for i in range(rs.shape[0]):
        rs[i] = lam * p.ratio[i]
    return LoadedProblem(p.alpha, p.beta, p.L, p.straight, p.kappa, p.EI, rs, p.kink, p.W, p.F,
                         p.M, p.step, p.tpos, p.ttyp, p.tidx, p.work)


register_model(LoadedRhs, LoadedProblem, _derivative, _shoot, _scaled, chords=True)


# ----------------------------------------------------------------------------- the batch
@njit(cache=True, error_model="numpy", inline="always")
def _solve_row(prob, x, x0, xs, tol, max_iter, out_s, m, pts, nw):
    """Newton from x0 (into x); where it fails, the load ramped up from the unloaded solution
    xs (K = 8, then 32 stages); where that fails too, the torsional compliance ramped up from
    the torsionally rigid loaded solution at full load (EI/GJ scaled by k/K, k = 0..K, K = 16
    then 64: near snapping the loaded branch through the unloaded solution may end at a fold;
    EI/GJ = 0 is well posed). Returns (residual, iterations, pts at x)."""
    nx = x.shape[0]
    n = nx - 2
    for i in range(nx):
        x[i] = x0[i]
    r, it, at_x = newton(prob, x, tol, max_iter, runtime(False), out_s, m, pts, nw)
    for K in (8, 32):
        if r < tol:
            break
        for i in range(nx):
            x[i] = xs[i]
        r, itk, at_x = ramp(prob, x, 1, K, LOADS, tol, max_iter, runtime(False), out_s, m, pts,
                            nw)
        it += itk
    for K in (16, 64):
        if r < tol:
            break
        for i in range(n):
            x[i] = 0.0
        x[n] = x0[n]
        x[n + 1] = x0[n + 1]
        if not (math.isfinite(x[n]) and math.isfinite(x[n + 1])):
            x[n] = 0.0
            x[n + 1] = 0.0
        r, itk, at_x = ramp(prob, x, 0, K, COMPLIANCE, tol, max_iter, runtime(False), out_s, m,
                            pts, nw)
        it += itk
    return r, it, at_x


@njit(cache=True, error_model="numpy")
def solve_loaded_batch(alpha, beta, L, straight, kappa, EI, ratio, kink, W, F, M, m, step, tol,
                       max_iter, x_init, x_start):
    """Solve and integrate a batch of loaded configurations.

    alpha, beta : (B, n) rad, mm; L, straight : (n,) mm; kappa, EI, ratio : (B, n) 1/mm,
    N mm^2, EI/GJ (0 = torsionally rigid); kink : (B, n, 2) rad; W : (B, n, 3) weight per unit
    length of each tube (N/mm, base frame); F : (B, 3) tip force N; M : (B, 3) tip moment N mm
    (base frame). x_init : (B, n + 2) first guess of (tau(0), mb_xy(0)) (N mm); x_start :
    (B, n + 2) the unloaded solution's unknowns, from which the load is ramped up where Newton
    from x_init fails (:func:`_solve_row`).

    Returns points (B, m, 3), s (B, m), x (B, n + 2), iterations (B,), residual (B,) (1/mm),
    ok (B,): converged (max residual < tol) and every point finite.
    """
    B, n = alpha.shape
    out = outputs(B, m, n + 2)
    work = loaded_work(n)
    tpos, ttyp, tidx = events(n)
    nw = newton_work(n + 2)
    out_s = np.zeros(m)
    x = np.zeros(n + 2)
    for bi in range(B):
        prob = LoadedProblem(alpha[bi], beta[bi], L, straight, kappa[bi], EI[bi], ratio[bi],
                             kink[bi], W[bi], F[bi], M[bi], step, tpos, ttyp, tidx, work)
        row_grid(beta[bi], L, straight, m, tpos, ttyp, tidx, out_s)
        pts = out[0][bi]
        r, it, at_x = _solve_row(prob, x, x_init[bi], x_start[bi], tol, max_iter, out_s, m, pts,
                                 nw)
        finite = finish_row(prob, x, at_x, out_s, m, pts, nw)
        store_row(out, bi, out_s, x, it, r, r < tol and finite)
    return out

# numba cache stamp: d8f966079f52654bec9904c45b481f0c7a18363c5bbb5d76c49e39122e994b7c
