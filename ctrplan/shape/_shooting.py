"""Shooting for the compliant model: Newton on the base torsions ``uz(0)`` over a batch.

The integration passes (and the equations) are in :mod:`ctrplan.shape._kernel`, the Newton
driver and the continuation in a parameter in :mod:`ctrplan.shape._ode`; this module holds
:func:`solve_batch`, the one entry point used by :class:`ctrplan.shape.physics.PhysicsModel`,
with the compliance continuation fallback and the search for stable equilibria.

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

from ctrplan.shape._kernel import UnloadedProblem, unloaded_work
from ctrplan.shape._ode import (
    COMPLIANCE,
    det,
    events,
    finish_row,
    max_abs,
    newton,
    newton_step,
    newton_work,
    outputs,
    ramp,
    row_grid,
    runtime,
    store_row,
)

#: how far (x max kappa) the unstable root is pushed along its unstable mode, in this order
#: (the first is usually beyond the residual's turning point)
_SCALES = (1.0, 0.3, 3.0, 0.1)


@njit(cache=True, error_model="numpy", _nrt=False)
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
        big = max_abs(d)
        if not big > 0.0:
            for i in range(n):
                d[i] = 1.0 if i == 0 else 0.0
            return
        for i in range(n):
            d[i] /= big
        if it == 3:
            return
        if not newton_step(jac, d, v, A):      # v = -jac^{-1} d
            return
        for i in range(n):
            d[i] = v[i]


@njit(cache=True, error_model="numpy", inline="always")
def _solve_compliant(prob, x, tol, max_iter, out_s, m, pts, nw):
    """Newton from x (in place); where it fails, continuation in the torsional compliance from
    the rigid solution uz = 0 (EI/GJ scaled by k/K, k = 1..K, K = 8 then 32). Returns
    (residual, iterations, shaped)."""
    r, it, shaped = newton(prob, x, tol, max_iter, runtime(True), out_s, m, pts, nw)
    for K in (8, 32):
        if r < tol:
            break
        for i in range(x.shape[0]):
            x[i] = 0.0
        r, itk, shaped = ramp(prob, x, 1, K, COMPLIANCE, tol, max_iter, runtime(True), out_s, m,
                              pts, nw)
        it += itk
    return r, it, shaped


@njit(cache=True, error_model="numpy", inline="always")
def _amp(kappa):
    amp = 0.0
    for i in range(kappa.shape[0]):
        amp = max(amp, abs(kappa[i]))
    return amp


@njit(cache=True, error_model="numpy", inline="always")
def search_work(n):
    """Workspace of the stable-root search: xu, d, v (n,), roots (2, n), their residuals and
    Jacobian determinants (2,)."""
    return np.zeros(n), np.zeros(n), np.zeros(n), np.zeros((2, n)), np.zeros(2), np.zeros(2)


@njit(cache=True, error_model="numpy", inline="always")
def _keep_root(x, r2, d2, nfound, amp, sw):
    """Store a stable root unless it is the one already found. Returns the number found."""
    roots, rres, rdet = sw[3], sw[4], sw[5]
    if nfound == 1:
        diff = 0.0
        for i in range(x.shape[0]):
            diff = max(diff, abs(x[i] - roots[0, i]))
        if diff <= 1e-6 * amp:
            return nfound
    for i in range(x.shape[0]):
        roots[nfound, i] = x[i]
    rres[nfound] = r2
    rdet[nfound] = d2
    return nfound + 1


@njit(cache=True, error_model="numpy", inline="always")
def _both_sides(prob, x, amp, tol, max_iter, out_s, m, pts, nw, sw):
    """Newton from the unstable root xu pushed along its unstable mode by t x amp, t in
    :data:`_SCALES`, to each side; the first stable root per side is kept. Returns (number of
    distinct stable roots, iterations)."""
    xu, dvec = sw[0], sw[1]
    jac, A = nw[1], nw[6]
    _unstable_direction(jac, prob.ratio, prob.EI, dvec, sw[2], A)
    nfound = 0
    it = 0
    for side in range(2):
        sgn = 1.0 if side == 0 else -1.0
        for t in _SCALES:
            for i in range(x.shape[0]):
                x[i] = xu[i] + sgn * t * amp * dvec[i]
            r2, it2, _sh = newton(prob, x, tol, max_iter, runtime(False), out_s, m, pts, nw)
            it += it2
            if r2 < tol:
                d2 = det(jac, A)
                if d2 > 0.0:
                    nfound = _keep_root(x, r2, d2, nfound, amp, sw)
                    break
    return nfound, it


@njit(cache=True, error_model="numpy", inline="always")
def _from_rigid(prob, x, tol, max_iter, out_s, m, pts, nw, sw):
    """Continuation in the compliance (K = 8) from the rigid solution; its root is kept if
    stable. Returns (number found, iterations)."""
    for i in range(x.shape[0]):
        x[i] = 0.0
    r2, it, _sh = ramp(prob, x, 1, 8, COMPLIANCE, tol, max_iter, runtime(False), out_s, m, pts,
                       nw)
    if r2 < tol:
        d2 = det(nw[1], nw[6])
        if d2 > 0.0:
            return _keep_root(x, r2, d2, 0, 1.0, sw), it
    return 0, it


@njit(cache=True, error_model="numpy", inline="always")
def _stabilise(prob, x, x0, tol, max_iter, out_s, m, pts, nw, sw, alt):
    """x (in place) is an unstable equilibrium: search stable ones to both sides of it
    (:func:`_both_sides`), else by :func:`_from_rigid`; with two, return the one nearer x0
    (max norm) and write the other into ``alt``. Returns (branch code, residual, det J,
    iterations); code -1 (none stable found) leaves x."""
    n = x.shape[0]
    xu, roots, rres, rdet = sw[0], sw[3], sw[4], sw[5]
    amp = _amp(prob.kappa)
    for i in range(n):
        xu[i] = x[i]
    nfound, it = _both_sides(prob, x, amp, tol, max_iter, out_s, m, pts, nw, sw)
    code = 1
    if nfound == 0:
        nfound, itk = _from_rigid(prob, x, tol, max_iter, out_s, m, pts, nw, sw)
        it += itk
        code = 3
    if nfound == 0:
        for i in range(n):
            x[i] = xu[i]
        return -1, math.nan, math.nan, it
    pick = 0
    if nfound == 2:
        code = 2
        # the one nearest the initial guess (max norm): with x_init = 0 the less twisted one;
        # with a warm start from the previous configuration of a motion, the branch the robot
        # is on
        d0 = 0.0
        d1 = 0.0
        for i in range(n):
            d0 = max(d0, abs(roots[0, i] - x0[i]))
            d1 = max(d1, abs(roots[1, i] - x0[i]))
        if d1 < d0:
            pick = 1
    for i in range(n):
        x[i] = roots[pick, i]
        if nfound == 2:
            alt[i] = roots[1 - pick, i]
    return code, rres[pick], rdet[pick], it


@njit(cache=True, error_model="numpy", inline="always")
def _probe(prob, x, tol, max_iter, out_s, m, pts, nw, sw, alt):
    """x is a stable equilibrium: where some pair of curved tubes is rotated apart by more than
    90 deg at the actuators, Newton from the mirrored root pushed to the other side (1 and
    0.5 x max kappa along the torque-balanced direction) looks for a second stable root,
    written into ``alt``. x is left as it was. Returns True when one was found."""
    n = x.shape[0]
    ka, al = prob.kappa, prob.alpha
    apart = False
    for i in range(n):
        for j in range(i + 1, n):
            if ka[i] != 0.0 and ka[j] != 0.0 and math.cos(al[i] - al[j]) < 0.0:
                apart = True
    if not apart:
        return False
    xu, dvec = sw[0], sw[1]
    jac, A = nw[1], nw[6]
    amp = _amp(ka)
    for i in range(n):
        xu[i] = x[i]
    _unstable_direction(jac, prob.ratio, prob.EI, dvec, sw[2], A)
    c0 = 0.0
    for i in range(n):
        c0 += dvec[i] * xu[i]
    sgn = -1.0 if c0 >= 0.0 else 1.0       # towards the other side
    found = False
    for t in (1.0, 0.5):
        for i in range(n):
            x[i] = -xu[i] + sgn * t * amp * dvec[i]
        r2, _it2, _sh = newton(prob, x, tol, max_iter, runtime(False), out_s, m, pts, nw)
        if r2 < tol and det(jac, A) > 0.0:
            diff = 0.0
            for i in range(n):
                diff = max(diff, abs(x[i] - xu[i]))
            if diff > 1e-6 * amp:
                for i in range(n):
                    alt[i] = x[i]
                found = True
                break
    for i in range(n):
        x[i] = xu[i]
    return found


@njit(cache=True, error_model="numpy", inline="always")
def _solve_row(prob, x, x0, stability, probe, tol, max_iter, out_s, m, pts, nw, sw, alt):
    """One row of the compliant model (:func:`solve_batch`): x from x0 (in place). Returns
    (residual, iterations, shaped, stable, det J, branch code)."""
    r, it, shaped = _solve_compliant(prob, x, tol, max_iter, out_s, m, pts, nw)
    dj = 1.0
    code = 0
    stable = True
    if r < tol and stability:
        dj = det(nw[1], nw[6])
        if not dj > 0.0:
            # an unstable equilibrium: search stable ones to both sides of it
            code, r2, d2, it2 = _stabilise(prob, x, x0, tol, max_iter, out_s, m, pts, nw, sw, alt)
            it += it2
            stable = code != -1
            if stable:
                r = r2
                dj = d2
            shaped = False
        elif probe and it > 0 and _probe(prob, x, tol, max_iter, out_s, m, pts, nw, sw, alt):
            code = 4
    return r, it, shaped, stable, dj, code


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
    out = outputs(B, m, n)
    detj = np.ones(B)
    branch = np.zeros(B, dtype=np.int8)
    uz0alt = np.full((B, n), np.nan)
    work = unloaded_work(n)
    tpos, ttyp, tidx = events(n)
    nw = newton_work(n)
    sw = search_work(n)
    out_s = np.zeros(m)
    x = np.zeros(n)
    for bi in range(B):
        prob = UnloadedProblem(alpha[bi], beta[bi], L, straight, kappa[bi], EI[bi], ratio[bi],
                               kink[bi], torsion, step, tpos, ttyp, tidx, work)
        row_grid(beta[bi], L, straight, m, tpos, ttyp, tidx, out_s)
        pts = out[0][bi]
        for i in range(n):
            x[i] = x_init[bi, i] if torsion else 0.0
        shaped = False          # the final (frame) pass has been run at x
        it = 0
        r = 0.0
        stable = True
        if torsion:
            r, it, shaped, stable, dj, code = _solve_row(prob, x, x_init[bi], stability, probe,
                                                         tol, max_iter, out_s, m, pts, nw, sw,
                                                         uz0alt[bi])
            detj[bi] = dj
            branch[bi] = code
        finite = finish_row(prob, x, shaped, out_s, m, pts, nw)
        store_row(out, bi, out_s, x, it, r, r < tol and finite and stable)
    return out + (detj, branch, uz0alt)

# numba cache stamp: d8f966079f52654bec9904c45b481f0c7a18363c5bbb5d76c49e39122e994b7c
