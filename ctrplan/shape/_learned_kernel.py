"""Numba forward pass of the learned shape network for small batches (low call overhead).

Same arithmetic as the torch path in float64: features per tube (cos, sin of alpha, relative
to the outermost tube's when ``outer``; beta scaled to [-1, 1]), per pair (i, j) of ``pairs``
cos, sin of alpha_i - alpha_j, per pair of ``opairs`` the overlap of the two curved sections
(scaled by ``oinv``) and its products with cos, sin of alpha_i - alpha_j
(:func:`ctrplan.shape.learned.pair_features`), ``depth`` Linear + PReLU layers,
the last layer (de-normalisation folded in) to (K, 3) coefficients times the tip length, the
turn by the outermost tube's angle (``outer``), and the basis expansion to points.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, inline="always")
def _overlap(q, bi, n, i, j, straight, L):
    """Overlap (mm) of the curved sections of tubes i and j beyond the constraint plane, and
    the tubes whose end / curve start bound it (ie, is: -1 for the plane)."""
    ei = q[bi, n + i] + L[i]
    ej = q[bi, n + j] + L[j]
    si = q[bi, n + i] + straight[i]
    sj = q[bi, n + j] + straight[j]
    ie = i if ei <= ej else j
    e = min(ei, ej)
    if si >= sj:
        st, is_ = si, i
    else:
        st, is_ = sj, j
    if st < 0.0:
        st, is_ = 0.0, -1
    return e - st, ie, is_


@njit(cache=True, inline="always")
def _features(q, bi, dirs, pairs, opairs, straight, oinv, n, outer, lo, inv, L, x):
    """The network inputs of configuration ``bi`` written into x (nx,): per tube cos, sin of
    alpha (relative to ``ref``) and the scaled beta, per pair cos, sin of the angle difference,
    per overlap pair the scaled overlap and its products with them, then ``dirs[bi]``.
    Returns (ref, length): the outermost tube's angle when ``outer`` (else 0) and the tip arc
    length max(beta + L) mm."""
    nd = dirs.shape[1]
    npair = pairs.shape[0]
    nov = opairs.shape[0]
    nq = 3 * n + 2 * npair + 3 * nov
    ref = q[bi, n - 1] if outer else 0.0
    length = -1e300
    for i in range(n):
        a = q[bi, i] - ref
        x[3 * i] = math.cos(a)
        x[3 * i + 1] = math.sin(a)
        x[3 * i + 2] = (q[bi, n + i] - lo[i]) * inv[i] - 1.0
        e = q[bi, n + i] + L[i]
        if e > length:
            length = e
    for p in range(npair):
        a = q[bi, pairs[p, 0]] - q[bi, pairs[p, 1]]
        x[3 * n + 2 * p] = math.cos(a)
        x[3 * n + 2 * p + 1] = math.sin(a)
    for p in range(nov):
        i0 = opairs[p, 0]
        i1 = opairs[p, 1]
        ov, _, _ = _overlap(q, bi, n, i0, i1, straight, L)
        ov = max(ov, 0.0) * oinv[p]
        a = q[bi, i0] - q[bi, i1]
        k0 = 3 * n + 2 * npair + 3 * p
        x[k0] = ov
        x[k0 + 1] = ov * math.cos(a)
        x[k0 + 2] = ov * math.sin(a)
    for k in range(nd):
        x[nq + k] = dirs[bi, k]
    return ref, length


@njit(cache=True, inline="always")
def _hidden(x, W0, Wh, bh, slopes, h, h2):
    """The hidden layers (Linear + PReLU, ``depth`` of them) of inputs x (nx,): the last
    one's activations in h (w,) (h2 (w,) is scratch). Row updates h += x_k W[k, :]
    (contiguous inner loops: SIMD)."""
    nx = x.shape[0]
    w = W0.shape[1]
    depth = bh.shape[0]
    for j in range(w):
        h[j] = bh[0, j]
    for k in range(nx):
        xk = x[k]
        for j in range(w):
            h[j] += xk * W0[k, j]
    sl = slopes[0]
    for j in range(w):
        if h[j] < 0.0:
            h[j] *= sl
    for d in range(1, depth):
        for j in range(w):
            h2[j] = bh[d, j]
        for k in range(w):
            hk = h[k]
            for j in range(w):
                h2[j] += hk * Wh[d - 1, k, j]
        sl = slopes[d]
        for j in range(w):
            v = h2[j]
            h[j] = v if v > 0.0 else sl * v


@njit(cache=True, inline="always")
def _coefficients(h, Wl, bl, length, outer, ref, c):
    """The basis coefficients c (3K,) mm of the last activations h (w,): the last layer
    (de-normalisation folded in) times the tip length, turned by ``ref`` about z when
    ``outer``."""
    w = h.shape[0]
    K3 = Wl.shape[1]
    for j in range(K3):
        c[j] = bl[j]
    for k in range(w):
        hk = h[k]
        for j in range(K3):
            c[j] += hk * Wl[k, j]
    for j in range(K3):
        c[j] *= length
    if outer:
        co = math.cos(ref)
        si = math.sin(ref)
        for k in range(K3 // 3):
            cx = c[3 * k]
            cy = c[3 * k + 1]
            c[3 * k] = co * cx - si * cy
            c[3 * k + 1] = si * cx + co * cy


@njit(cache=True)
def forward(q, dirs, pairs, opairs, straight, oinv, n, outer, lo, inv, L, W0, Wh, bh, slopes, Wl,
            bl, phi, out):
    """q (B, 2n); dirs (B, nd) extra inputs appended to the features (direction of the last
    motion, nd = 0 or 3n - 1); pairs (P, 2) int tube pairs (P may be 0); opairs (O, 2) int
    tube pairs of the overlap inputs, straight (n,) mm, oinv (O,) 1/mm; W0 (3n + 2P + 3O + nd, w);
    Wh (depth-1, w, w); bh (depth, w); slopes (depth,); Wl (w, 3K); bl (3K,); phi (m, K);
    out (B, m, 3) written in place."""
    B = q.shape[0]
    w = W0.shape[1]
    K3 = Wl.shape[1]
    K = K3 // 3
    m = phi.shape[0]
    x = np.empty(3 * n + 2 * pairs.shape[0] + 3 * opairs.shape[0] + dirs.shape[1])
    h = np.empty(w)
    h2 = np.empty(w)
    c = np.empty(K3)
    for bi in range(B):
        ref, length = _features(q, bi, dirs, pairs, opairs, straight, oinv, n, outer, lo, inv, L, x)
        _hidden(x, W0, Wh, bh, slopes, h, h2)
        _coefficients(h, Wl, bl, length, outer, ref, c)
        for p in range(m):
            for xyz in range(3):
                s = 0.0
                for k in range(K):
                    s += phi[p, k] * c[3 * k + xyz]
                out[bi, p, xyz] = s


@njit(cache=True, inline="always")
def _features_dual(q, bi, dirs, pairs, opairs, straight, oinv, n, outer, lo, inv, L, x, dx):
    """The network inputs x (nx,) of configuration ``bi`` (as :func:`_features`) and their
    derivatives dx (nx, 2n) with respect to q (the direction inputs are constants).
    Returns (ref, length, imax): the turn angle, the tip arc length and the tube that ends
    at the tip (d length / d beta_imax = 1)."""
    D = 2 * n
    nd = dirs.shape[1]
    npair = pairs.shape[0]
    nov = opairs.shape[0]
    nq = 3 * n + 2 * npair + 3 * nov
    ref = q[bi, n - 1] if outer else 0.0
    length = -1e300
    imax = 0
    for k in range(nq + nd):
        for j in range(D):
            dx[k, j] = 0.0
    for k in range(nd):
        x[nq + k] = dirs[bi, k]
    for p in range(npair):
        i0 = pairs[p, 0]
        i1 = pairs[p, 1]
        a = q[bi, i0] - q[bi, i1]
        ca = math.cos(a)
        sa = math.sin(a)
        x[3 * n + 2 * p] = ca
        x[3 * n + 2 * p + 1] = sa
        dx[3 * n + 2 * p, i0] = -sa
        dx[3 * n + 2 * p, i1] = sa
        dx[3 * n + 2 * p + 1, i0] = ca
        dx[3 * n + 2 * p + 1, i1] = -ca
    for p in range(nov):
        _overlap_dual(q, bi, n, p, opairs, straight, oinv, L, 3 * n + 2 * npair + 3 * p, x, dx)
    for i in range(n):
        a = q[bi, i] - ref
        ca = math.cos(a)
        sa = math.sin(a)
        x[3 * i] = ca
        x[3 * i + 1] = sa
        x[3 * i + 2] = (q[bi, n + i] - lo[i]) * inv[i] - 1.0
        dx[3 * i, i] += -sa
        dx[3 * i + 1, i] += ca
        if outer:
            dx[3 * i, n - 1] -= -sa
            dx[3 * i + 1, n - 1] -= ca
        dx[3 * i + 2, n + i] = inv[i]
        e = q[bi, n + i] + L[i]
        if e > length:
            length = e
            imax = i
    return ref, length, imax


@njit(cache=True, inline="always")
def _overlap_dual(q, bi, n, p, opairs, straight, oinv, L, k0, x, dx):
    """The three inputs of overlap pair p at x[k0:k0 + 3] (scaled overlap, times cos and sin
    of the angle difference) and their derivatives dx[k0:k0 + 3] (rows zero on entry)."""
    D = 2 * n
    i0 = opairs[p, 0]
    i1 = opairs[p, 1]
    ov, ie, is_ = _overlap(q, bi, n, i0, i1, straight, L)
    a = q[bi, i0] - q[bi, i1]
    ca = math.cos(a)
    sa = math.sin(a)
    if ov > 0.0:
        ov *= oinv[p]
        dx[k0, n + ie] += oinv[p]                  # d ov / d beta: the nearer end ...
        if is_ >= 0:
            dx[k0, n + is_] -= oinv[p]             # ... minus the later curve start
    else:
        ov = 0.0
    x[k0] = ov
    x[k0 + 1] = ov * ca
    x[k0 + 2] = ov * sa
    for t in range(D):
        dx[k0 + 1, t] = dx[k0, t] * ca
        dx[k0 + 2, t] = dx[k0, t] * sa
    dx[k0 + 1, i0] += -ov * sa
    dx[k0 + 1, i1] += ov * sa
    dx[k0 + 2, i0] += ov * ca
    dx[k0 + 2, i1] += -ov * ca


@njit(cache=True, inline="always")
def _hidden_dual(x, dx, nq, W0, Wh, bh, slopes, h, dh, h2, dh2):
    """The hidden layers of :func:`_hidden` with their derivatives: activations h (w,) and
    dh (w, D) from inputs x (nx,) and dx (nx, D), of which only the first nq rows depend on
    q (h2, dh2: scratch)."""
    nx = x.shape[0]
    w = W0.shape[1]
    depth = bh.shape[0]
    D = dx.shape[1]
    for j in range(w):
        s = bh[0, j]
        for k in range(nx):
            s += x[k] * W0[k, j]
        g = 1.0 if s > 0.0 else slopes[0]
        h[j] = g * s
        for t in range(D):
            ds = 0.0
            for k in range(nq):
                ds += dx[k, t] * W0[k, j]
            dh[j, t] = g * ds
    for d in range(1, depth):
        for j in range(w):
            s = bh[d, j]
            for k in range(w):
                s += h[k] * Wh[d - 1, k, j]
            g = 1.0 if s > 0.0 else slopes[d]
            h2[j] = g * s
            for t in range(D):
                ds = 0.0
                for k in range(w):
                    ds += dh[k, t] * Wh[d - 1, k, j]
                dh2[j, t] = g * ds
        for j in range(w):
            h[j] = h2[j]
            for t in range(D):
                dh[j, t] = dh2[j, t]


@njit(cache=True, inline="always")
def _coefficients_dual(h, dh, Wl, bl, length, dlen, outer, ref, n, c, dc):
    """The coefficients of :func:`_coefficients` and their derivatives dc (3K, 2n), from
    h (w,), dh (w, 2n) and d length / d q dlen (2n,)."""
    w = h.shape[0]
    K3 = Wl.shape[1]
    D = dh.shape[1]
    for j in range(K3):
        s = bl[j]
        for k in range(w):
            s += h[k] * Wl[k, j]
        for t in range(D):
            ds = 0.0
            for k in range(w):
                ds += dh[k, t] * Wl[k, j]
            dc[j, t] = ds * length + s * dlen[t]
        c[j] = s * length
    if outer:
        co = math.cos(ref)
        si = math.sin(ref)
        for k in range(K3 // 3):
            cx = c[3 * k]
            cy = c[3 * k + 1]
            c[3 * k] = co * cx - si * cy
            c[3 * k + 1] = si * cx + co * cy
            for t in range(D):
                dcx = dc[3 * k, t]
                dcy = dc[3 * k + 1, t]
                dc[3 * k, t] = co * dcx - si * dcy
                dc[3 * k + 1, t] = si * dcx + co * dcy
            dc[3 * k, n - 1] += -si * cx - co * cy
            dc[3 * k + 1, n - 1] += co * cx - si * cy


@njit(cache=True)
def tip_jacobian(q, dirs, pairs, opairs, straight, oinv, n, outer, lo, inv, L, W0, Wh, bh, slopes,
                 Wl, bl, ptip, tip, J):
    """Tip (B, 3) and d tip / d q (B, 3, 2n) by forward-mode differentiation of the same
    network (the direction inputs ``dirs`` (B, nd) are constants); ``ptip`` (K,) are the
    basis values at s = 1. tip and J are written in place."""
    B = q.shape[0]
    w = W0.shape[1]
    K3 = Wl.shape[1]
    K = K3 // 3
    D = 2 * n
    nq = 3 * n + 2 * pairs.shape[0] + 3 * opairs.shape[0]
    nx = nq + dirs.shape[1]
    x = np.empty(nx)
    dx = np.zeros((nx, D))
    h = np.empty(w)
    dh = np.empty((w, D))
    h2 = np.empty(w)
    dh2 = np.empty((w, D))
    c = np.empty(K3)
    dc = np.empty((K3, D))
    dlen = np.zeros(D)
    for bi in range(B):
        ref, length, imax = _features_dual(q, bi, dirs, pairs, opairs, straight, oinv, n, outer,
                                           lo, inv, L, x, dx)
        for j in range(D):
            dlen[j] = 0.0
        dlen[n + imax] = 1.0
        _hidden_dual(x, dx, nq, W0, Wh, bh, slopes, h, dh, h2, dh2)
        _coefficients_dual(h, dh, Wl, bl, length, dlen, outer, ref, n, c, dc)
        for xyz in range(3):
            s = 0.0
            for k in range(K):
                s += ptip[k] * c[3 * k + xyz]
            tip[bi, xyz] = s
            for t in range(D):
                ds = 0.0
                for k in range(K):
                    ds += ptip[k] * dc[3 * k + xyz, t]
                J[bi, xyz, t] = ds
