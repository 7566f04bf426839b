"""Numerics shared by the mechanics kernels: tube events, the RK4 stepper with sensitivities, the
n x n linear algebra and the Newton shooting driver (numba).

Every mechanics model (the unloaded one of :mod:`ctrplan.shape._kernel`, the loaded one of
:mod:`ctrplan.shape._loaded`) integrates a state that starts with ``(cos psi (n), sin psi (n),
torsion (n), R (9, row-major), p (3))`` from s = 0 to the tip, between the tube events, and
solves for its unknowns at s = 0 by shooting. The stepper and the driver here are written once
for all models; what differs per model is reached through four generic functions, each
implemented by the model's module for its own record types (:func:`implement`: numba's
``@overload``, chosen at compile time by the argument's type, like ``functools.singledispatch``):

- :func:`derivative` ``(model, y, Y, s, sens, dy, dY)``: the right-hand side of the state
  equations at arc length s (and of the variational equations when ``sens``); ``model`` is the
  record of one interval's constants;
- :func:`shoot` ``(problem, x, sens, out_s, m_out, out_p, resid, jac)``: one integration pass
  at the unknowns x; fills the boundary residual ``resid``, its Jacobian ``jac`` when ``sens``
  and the backbone points ``out_p[:m_out]``; ``problem`` is the record of one configuration;
- :func:`scaled` ``(problem, lam, what)``: the problem with a parameter scaled by ``lam``
  (:data:`COMPLIANCE`: EI/GJ; :data:`LOADS`: every load), the homotopy of :func:`ramp`;
- :func:`keeps_jacobian` ``(problem)``: the Newton strategy of :func:`newton` (a constant).

numba caches a kernel with every kernel it calls compiled in, but decides whether a cache is
fresh from the source file of the cached function alone. So every kernel module ends with the
same ``# numba cache stamp:`` line, a digest of all kernel modules' sources
(:mod:`ctrplan.shape._cache_stamp`): edit a kernel, run ``python -m ctrplan.shape._cache_stamp``
(tests/test_kernel_cache.py fails until then), and the changed stamp makes numba recompile every
caller.
"""

from __future__ import annotations

import inspect
import math

import numpy as np
from numba import njit, types
from numba.extending import intrinsic, overload

# Every kernel uses numba's ``error_model="numpy"``: a division by zero gives inf/nan instead
# of a per-division check that raises (all divisions here are guarded; non-finite results end
# up as ok=False).
#
# Every kernel that allocates nothing and returns no array is compiled without numba's
# reference counting (``_nrt=False``); the batch entry points (which allocate
# the workspace and the results) and :func:`scaled` (returns a record of arrays) keep it.
# With it, every array argument of every call, every view (``ws[0]``) and every field read
# from a record of arrays costs an atomic increment and decrement of the array's count, and
# numba's pruning removes few of them across the small functions shared here: the shared
# stepper and driver (issue 37) ran at half main's speed (bench_shape batch 10,000 on one
# thread: compliant 28.1 vs 12.7 us/shape, loaded 92 vs 55), without it they run faster than
# main's copies. A kernel compiled so must not return an array, nor a record or tuple holding
# one, to a caller with reference counting (the caller would release a reference never taken),
# and cannot allocate (numba refuses to compile it). The arrays passed in are owned by the
# caller for the duration of the call.

#: :func:`scaled` targets: the torsional compliance EI/GJ, or every external load
COMPLIANCE = 0
LOADS = 1


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


# ----------------------------------------------------------------------------- generic functions
def derivative(model, y, Y, s, sens, dy, dY):
    """dy = y' and, when ``sens``, dY = Y' at arc length s (per model: ``@overload``)."""
    raise NotImplementedError


def shoot(problem, x, sens, out_s, m_out, out_p, resid, jac):
    """One integration pass at the unknowns x (per model: ``@overload``)."""
    raise NotImplementedError


def scaled(problem, lam, what):
    """``problem`` with the parameter ``what`` scaled by lam (per model: ``@overload``)."""
    raise NotImplementedError


def keeps_jacobian(problem):
    """True: :func:`newton` keeps its Jacobian while the steps contract (chord steps) and every
    pass writes the output points (per model: ``@overload``)."""
    raise NotImplementedError


def implement(generic, cls, impl, inline: bool = False, nrt: bool = False) -> None:
    """Register ``impl`` (a plain function with the parameters of ``generic``, compiled by
    numba) as ``generic`` where the first argument is a ``cls`` record (a namedtuple);
    ``inline``: compiled into each caller (numba IR inlining) instead of called; ``nrt``: with
    numba's reference counting, needed where ``impl`` returns arrays (the note above ``COMPLIANCE``)."""
    def typer(*args):
        t = args[0]
        if isinstance(t, types.BaseNamedTuple) and t.instance_class is cls:
            return impl
        return None

    typer.__signature__ = inspect.signature(generic)    # numba checks impl against it
    overload(generic, jit_options={"error_model": "numpy", "_nrt": nrt},
             inline="always" if inline else "never")(typer)


def register_model(rhs, problem, derivative_impl, shoot_impl, scaled_impl, chords: bool) -> None:
    """A mechanics model: its interval records (class ``rhs``) and configuration records
    (class ``problem``), the implementations of :func:`derivative`, :func:`shoot` and
    :func:`scaled` for them, and its :func:`keeps_jacobian` constant ``chords``."""
    # compile time: the small ones are compiled into their callers, the pass is called (one
    # compiled pass per model, not one per call site)
    implement(derivative, rhs, derivative_impl, inline=True)
    implement(shoot, problem, shoot_impl)
    implement(scaled, problem, scaled_impl, nrt=True)        # returns a record of arrays
    implement(keeps_jacobian, problem, (lambda problem: True) if chords else (lambda problem: False),
              inline=True)


# ----------------------------------------------------------------------------- events and output
@njit(cache=True, error_model="numpy", _nrt=False)
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


@njit(cache=True, error_model="numpy", inline="always")
def events(n):
    """Workspace of :func:`_tube_events` for n tubes: tpos, ttyp, tidx."""
    return np.zeros(2 * n), np.zeros(2 * n, dtype=np.int64), np.zeros(2 * n, dtype=np.int64)


@njit(cache=True, error_model="numpy", inline="always")
def row_grid(beta, L, straight, m, tpos, ttyp, tidx, out_s):
    """The tube events of one configuration and its m output arc lengths, evenly spaced from
    0 to the tip (mm)."""
    n = beta.shape[0]
    _tube_events(beta, L, straight, tpos, ttyp, tidx)
    tip = tpos[2 * n - 1]
    for k in range(m):
        out_s[k] = tip * k / (m - 1) if m > 1 else tip
    out_s[m - 1] = tip


@njit(cache=True, error_model="numpy", inline="always")
def emit(out_s, out_p, ko, m_out, s_now, last, y, b):
    """Output points at (or, by round-off, just past) arc length s_now, every remaining one
    when ``last``: the position y[b+9:b+12]. Returns the next output index."""
    while ko < m_out and (out_s[ko] <= s_now or last):
        out_p[ko, 0] = y[b + 9]
        out_p[ko, 1] = y[b + 10]
        out_p[ko, 2] = y[b + 11]
        ko += 1
    return ko


@njit(cache=True, error_model="numpy", inline="always")
def _point(y, b):
    """The position p = y[b+9:b+12] and the tangent R e_z = (y[b+2], y[b+5], y[b+8])."""
    return y[b + 9], y[b + 10], y[b + 11], y[b + 2], y[b + 5], y[b + 8]


@njit(cache=True, error_model="numpy", _nrt=False)
def _hermite_out(out_s, out_p, ko, m_out, s_end, sa, sb, h, pax, pay, paz, tax, tay, taz, y, b):
    """Backbone points at the output arc lengths in (sa, sb] of one RK4 step, by cubic Hermite
    interpolation between the step's end points (position y[b+9:b+12], tangent = third column
    of R, y[b+2], y[b+5], y[b+8]) and the start values ``pa``, ``ta``. Returns the next ``ko``."""
    pbx, pby, pbz, tbx, tby, tbz = _point(y, b)
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


# ----------------------------------------------------------------------------- kinks
@njit(cache=True, error_model="numpy", inline="always")
def kink_matrix(kx, ky, K):
    """K = Exp([kx, ky, 0]x), the rotation by |k| about the axis (kx, ky, 0) / |k| (Rodrigues)."""
    th = math.sqrt(kx * kx + ky * ky)
    ex = kx / th
    ey = ky / th
    ct = math.cos(th)
    st = math.sin(th)
    vt = 1.0 - ct
    K[0, 0] = ct + ex * ex * vt
    K[0, 1] = ex * ey * vt
    K[0, 2] = ey * st
    K[1, 0] = ex * ey * vt
    K[1, 1] = ct + ey * ey * vt
    K[1, 2] = -ex * st
    K[2, 0] = -ey * st
    K[2, 1] = ex * st
    K[2, 2] = ct


@njit(cache=True, error_model="numpy", inline="always")
def frame_rates(y, b, ux, uy, dy):
    """R' = R [u]x with u = (ux, uy, 0) and p' = R e_z for the frame R (row-major) and the
    position p in y[b:b+12]: columns d0 = -uy r2, d1 = ux r2, d2 = uy r0 - ux r1."""
    for r in range(3):
        r0 = y[b + 3 * r]
        r1 = y[b + 3 * r + 1]
        r2 = y[b + 3 * r + 2]
        dy[b + 3 * r] = -uy * r2
        dy[b + 3 * r + 1] = ux * r2
        dy[b + 3 * r + 2] = uy * r0 - ux * r1
        dy[b + 9 + r] = r2


@njit(cache=True, error_model="numpy", inline="always")
def turn_frame(Z, col, b, K):
    """R <- R K for the frame R stored row-major in Z[b:b+9, col]."""
    for r in range(3):
        r0 = Z[b + 3 * r, col]
        r1 = Z[b + 3 * r + 1, col]
        r2 = Z[b + 3 * r + 2, col]
        Z[b + 3 * r, col] = r0 * K[0, 0] + r1 * K[1, 0] + r2 * K[2, 0]
        Z[b + 3 * r + 1, col] = r0 * K[0, 1] + r1 * K[1, 1] + r2 * K[2, 1]
        Z[b + 3 * r + 2, col] = r0 * K[0, 2] + r1 * K[1, 2] + r2 * K[2, 2]


# ----------------------------------------------------------------------------- RK4
@njit(cache=True, error_model="numpy", inline="always")
def _stage(y, Y, k, K, c, yt, Yt, nst, sens):
    """yt = y + c k (first nst states) and, when ``sens``, Yt = Y + c K."""
    for j in range(nst):
        yt[j] = y[j] + c * k[j]
    if sens:
        for r in range(Y.shape[0]):
            for q in range(Y.shape[1]):
                Yt[r, q] = Y[r, q] + c * K[r, q]


@njit(cache=True, error_model="numpy", inline="always")
def _combine(y, Y, ws, WS, h6, nst, sens):
    """y += h/6 (k1 + 2 k2 + 2 k3 + k4) (first nst states), likewise Y when ``sens``."""
    k1, k2, k3, k4 = ws[0], ws[1], ws[2], ws[3]
    for j in range(nst):
        y[j] += h6 * (k1[j] + 2.0 * k2[j] + 2.0 * k3[j] + k4[j])
    if sens:
        K1, K2, K3, K4 = WS[0], WS[1], WS[2], WS[3]
        for r in range(Y.shape[0]):
            for c in range(Y.shape[1]):
                Y[r, c] += h6 * (K1[r, c] + 2.0 * K2[r, c] + 2.0 * K3[r, c] + K4[r, c])


@njit(cache=True, error_model="numpy", _nrt=False)
def rk4(model, y, Y, nst, frame, sens, s0, seg, step, out_s, m_out, ko, out_p, ws, WS):
    """Fixed-step RK4 of :func:`derivative` over [s0, s0 + seg] (``ceil(seg / step)`` equal steps).

    y : the first ``nst`` states are integrated; Y (r, c) : their sensitivities, integrated when
    ``sens`` (RK4 applied to the variational equations is the exact derivative of the RK4 map,
    so Newton converges quadratically on the discretised problem). The step grid depends on the
    break points only, so a pass with output reproduces a pass without it exactly. Output points
    ``out_s[ko:]`` strictly inside the interval (when ``frame``: R and p are integrated) are
    read off by cubic Hermite interpolation of p between steps (p' = R e_z at both ends;
    O(h^4) like RK4 itself). ws (5, >= nst) and WS (5, r, c) are workspace. Returns the next
    output index.
    """
    nsub = int(math.ceil(seg / step - 1e-9))
    if nsub < 1:
        nsub = 1
    h = seg / nsub
    b = 3 * model.n
    s_end = s0 + seg
    yt = ws[4]
    Yt = WS[4]
    for q in range(nsub):
        sa = s0 + q * h
        sb = s_end if q == nsub - 1 else sa + h
        want = frame and ko < m_out and out_s[ko] < s_end and out_s[ko] <= sb
        pax = pay = paz = tax = tay = taz = 0.0
        if want:
            pax, pay, paz, tax, tay, taz = _point(y, b)
        derivative(model, y, Y, sa, sens, ws[0], WS[0])
        _stage(y, Y, ws[0], WS[0], 0.5 * h, yt, Yt, nst, sens)
        derivative(model, yt, Yt, sa + 0.5 * h, sens, ws[1], WS[1])
        _stage(y, Y, ws[1], WS[1], 0.5 * h, yt, Yt, nst, sens)
        derivative(model, yt, Yt, sa + 0.5 * h, sens, ws[2], WS[2])
        _stage(y, Y, ws[2], WS[2], h, yt, Yt, nst, sens)
        derivative(model, yt, Yt, sa + h, sens, ws[3], WS[3])
        _combine(y, Y, ws, WS, h / 6.0, nst, sens)
        if want:
            ko = _hermite_out(out_s, out_p, ko, m_out, s_end, sa, sb, h, pax, pay, paz, tax, tay,
                              taz, y, b)
    return ko


# ----------------------------------------------------------------------------- linear algebra
@njit(cache=True, error_model="numpy", _nrt=False)
def max_abs(v):
    """max_i |v_i|, NaN when some v_i is NaN."""
    m = 0.0
    for i in range(v.shape[0]):
        if not abs(v[i]) <= m:       # NaN propagates
            m = abs(v[i])
    return m


@njit(cache=True, error_model="numpy", inline="always")
def _eliminate(jac, v, A, solve):
    """Gaussian elimination with partial pivoting of the n x n matrix ``jac`` (copied into the
    workspace ``A``), applied to v as well when ``solve`` (n is tiny). Returns (ok, det): ok is
    False at a zero or non-finite pivot column, where det is 0.0 or NaN."""
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
            return False, math.nan
        if big == 0.0:
            return False, 0.0
        if p != k:
            det = -det
            for j in range(n):
                t = A[k, j]
                A[k, j] = A[p, j]
                A[p, j] = t
            if solve:
                t = v[k]
                v[k] = v[p]
                v[p] = t
        det *= A[k, k]
        inv = 1.0 / A[k, k]
        for i in range(k + 1, n):
            f = A[i, k] * inv
            if f != 0.0:
                for j in range(k + 1, n):
                    A[i, j] -= f * A[k, j]
                if solve:
                    v[i] -= f * v[k]
    return True, det


@njit(cache=True, error_model="numpy", _nrt=False)
def newton_step(jac, resid, dx, A):
    """dx = -jac^{-1} resid (``A`` is workspace). Returns False when the Jacobian is singular
    or not finite."""
    n = resid.shape[0]
    for i in range(n):
        dx[i] = -resid[i]
    ok, _det = _eliminate(jac, dx, A, True)
    if not ok:
        return False
    for k in range(n - 1, -1, -1):
        t = dx[k]
        for j in range(k + 1, n):
            t -= A[k, j] * dx[j]
        dx[k] = t / A[k, k]
    for i in range(n):
        if not math.isfinite(dx[i]):
            return False
    return True


@njit(cache=True, error_model="numpy", _nrt=False)
def det(jac, A):
    """Determinant of the n x n matrix ``jac`` (``A`` is workspace); NaN when it is not finite."""
    return _eliminate(jac, jac[0], A, False)[1]


# ----------------------------------------------------------------------------- Newton
@njit(cache=True, error_model="numpy", inline="always")
def newton_work(nx):
    """Workspace of :func:`newton` for nx unknowns: resid, jac, resid_t, jac_t, dx, xt, A."""
    return (np.zeros(nx), np.zeros((nx, nx)), np.zeros(nx), np.zeros((nx, nx)), np.zeros(nx),
            np.zeros(nx), np.zeros((nx, nx)))


@njit(cache=True, error_model="numpy", inline="always")
def _step_to(x, dx, t, xt):
    for i in range(x.shape[0]):
        xt[i] = x[i] + t * dx[i]


@njit(cache=True, error_model="numpy", inline="always")
def _take(x, xt, resid, resid_t, jac, jac_t, with_jac):
    """x, resid (and jac when ``with_jac``) <- the trial's."""
    n = x.shape[0]
    for i in range(n):
        x[i] = xt[i]
        resid[i] = resid_t[i]
        if with_jac:
            for c in range(n):
                jac[i, c] = jac_t[i, c]


@njit(cache=True, error_model="numpy", inline="always")
def _line_search(problem, x, dx, r, tol, tries, out_s, m_out, pts, nw):
    """Backtracking from the full step x + dx, halving up to ``tries`` times, until the residual
    falls below r (or tol). Passes with sensitivities into the trial workspace. Returns
    (accepted, t, residual)."""
    resid_t, jac_t, xt = nw[2], nw[3], nw[5]
    t = 1.0
    rt = r
    for _ls in range(tries):
        _step_to(x, dx, t, xt)
        shoot(problem, xt, runtime(True), out_s, m_out, pts, resid_t, jac_t)
        rt = max_abs(resid_t)
        if rt < r or rt < tol:
            return True, t, rt
        t *= 0.5
    return False, t, rt


@njit(cache=True, error_model="numpy", _nrt=False)
def newton(problem, x, tol, max_iter, may_shape, out_s, m_out, pts, nw):
    """Shooting on the unknowns x (updated in place) by Newton with a backtracking line search.

    nw : :func:`newton_work`; on return nw[0], nw[1] hold the residual and the Jacobian of the
    last accepted full pass (where the predicted or chord step ended it, of one step earlier).
    Two strategies, by :func:`keeps_jacobian` of the problem:

    - False (unloaded): the passes with sensitivities write no output; once Newton is in its
      quadratic regime and predicts convergence (C |dx|^2 < tol / 10 with C from the last full
      step), the final pass with output points is run at the full step instead (``may_shape``),
      and its residual confirms convergence (same step grid, same residual): one sensitivity
      pass saved. Line search: 8 halvings.
    - True (loaded): the Jacobian is kept while the full steps contract by 10 (chord steps
      without the variational equations: about a sixth of the cost of a pass with them), and
      every pass writes the output points (cheap: Hermite interpolation). Line search: 10.

    Returns (residual, iterations, shaped): ``shaped`` is True when ``pts[:m_out]`` hold the
    backbone at the returned x.
    """
    resid, jac, resid_t, jac_t, dx, xt, A = nw
    keep = keeps_jacobian(problem)
    m_sens = m_out if keep else 0           # output of the passes with sensitivities
    on, off = runtime(True), runtime(False)
    shoot(problem, x, on, out_s, m_sens, pts, resid, jac)
    r = max_abs(resid)
    it = 0
    shaped = keep
    chord = keep             # try the full step with the kept Jacobian first
    fresh = True             # jac was evaluated at x
    quad = -1.0              # estimate of C in |resid after a full step| ~ C |dx|^2
    while r >= tol and it < max_iter and math.isfinite(r):
        it += 1
        if not newton_step(jac, resid, dx, A):
            break
        dxn = max_abs(dx)
        if chord or (may_shape and quad > 0.0 and quad * dxn * dxn < 0.1 * tol):
            # the full step without the variational equations, writing the output points
            _step_to(x, dx, 1.0, xt)
            shoot(problem, xt, off, out_s, m_out, pts, resid_t, jac_t)
            rt = max_abs(resid_t)
            if rt < tol or (chord and rt < 0.1 * r):
                _take(x, xt, resid, resid_t, jac, jac_t, False)
                r = rt
                shaped = True
                fresh = False
                continue
            chord = False   # not contracting: Newton steps until they contract strongly again
            shaped = False
        if not fresh:
            shoot(problem, x, on, out_s, m_sens, pts, resid, jac)
            r = max_abs(resid)
            shaped = keep
            fresh = True
            if not newton_step(jac, resid, dx, A):
                break
        accepted, t, rt = _line_search(problem, x, dx, r, tol, 10 if keep else 8, out_s, m_sens,
                                       pts, nw)
        if not accepted:
            shaped = False
            break
        if keep:
            chord = t == 1.0 and rt < 0.1 * r
        else:
            quad = rt / (dxn * dxn) if (t == 1.0 and dxn > 0.0) else -1.0
        _take(x, xt, resid, resid_t, jac, jac_t, True)
        r = rt
        shaped = keep
    return r, it, shaped


@njit(cache=True, error_model="numpy", inline="always")
def ramp(problem, x, k0, K, what, tol, max_iter, may_shape, out_s, m_out, pts, nw):
    """Continuation in a parameter: Newton on :func:`scaled` ``(problem, k / K, what)`` for
    k = k0..K, each stage from the previous one's solution (x, in place), until a stage fails.
    ``may_shape`` is passed on the last stage only. Returns (residual, iterations, shaped):
    ``shaped`` only if the last Newton ran at k = K (the problem itself)."""
    r = math.inf
    it = 0
    shaped = False
    for k in range(k0, K + 1):
        r, itk, shaped = newton(scaled(problem, k / K, what), x, tol, max_iter,
                                may_shape and k == K, out_s, m_out, pts, nw)
        it += itk
        if not r < tol:
            shaped = shaped and k == K
            break
    return r, it, shaped


# ----------------------------------------------------------------------------- batch rows
@njit(cache=True, error_model="numpy", inline="always")
def outputs(B, m, nx):
    """Per-batch results: points (B, m, 3), s (B, m), x (B, nx), iterations (B,),
    residual (B,), ok (B,)."""
    return (np.zeros((B, m, 3)), np.zeros((B, m)), np.zeros((B, nx)), np.zeros(B, dtype=np.int64),
            np.zeros(B), np.zeros(B, dtype=np.bool_))


@njit(cache=True, error_model="numpy", inline="always")
def finish_row(problem, x, shaped, out_s, m, pts, nw):
    """The backbone at x unless ``pts[:m]`` already hold it (final pass without
    sensitivities); returns True when every point is finite."""
    if not shaped:
        shoot(problem, x, runtime(False), out_s, m, pts, nw[2], nw[3])
    finite = True
    for k in range(m):
        for c in range(3):
            if not math.isfinite(pts[k, c]):
                finite = False
    return finite


@njit(cache=True, error_model="numpy", inline="always")
def store_row(out, bi, out_s, x, it, r, ok):
    """Row bi of :func:`outputs` (points are written in place by the passes)."""
    svals, xout, iters, rnorm, okv = out[1], out[2], out[3], out[4], out[5]
    for k in range(out_s.shape[0]):
        svals[bi, k] = out_s[k]
    for i in range(x.shape[0]):
        xout[bi, i] = x[i]
    iters[bi] = it
    rnorm[bi] = r
    okv[bi] = ok

# numba cache stamp: d8f966079f52654bec9904c45b481f0c7a18363c5bbb5d76c49e39122e994b7c
