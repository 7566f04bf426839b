"""Experiment designs: configurations in motion order, times and sweep ids. Only valid
configurations (DESIGN.md constraints, checked)."""

from __future__ import annotations

import numpy as np

from .robot import Spec, beta_from_unit, valid

DESIGNS = ("sweeps", "feed", "inner_rotation", "outer_rotation", "uniform")
DT = 0.05          # s between rows
GAP = 5.0          # s between sweeps


def _split(n, k):
    base = np.full(k, n // k)
    base[: n % k] += 1
    return base


def _times(rng, counts):
    out, t0 = [], 0.0
    for c in counts:
        dt = DT * rng.uniform(0.8, 1.2, c)
        dt[0] = 0.0
        tt = t0 + np.cumsum(dt)
        out.append(tt)
        t0 = tt[-1] + GAP
    return np.concatenate(out) if out else np.zeros(0)


def _walk(rng, m, lo, hi, step_lo, step_hi, p_flip=0.05):
    """Back-and-forth random walk of m rows in [lo, hi] (reflecting), step sizes per joint drawn
    once per sweep, direction reversing at random (and at the ends). At least one reversal per
    joint (forced at the middle when chance gave none)."""
    k = lo.shape[0]
    x = np.empty((m, k))
    x[0] = lo + rng.uniform(0.2, 0.8, k) * (hi - lo)
    step = rng.uniform(step_lo, step_hi)
    d = rng.choice([-1.0, 1.0], k)
    flips = np.zeros(k, int)
    for i in range(1, m):
        f = rng.random(k) < p_flip
        if i == m // 2:
            f |= flips == 0
        d = np.where(f, -d, d)
        flips += f
        nxt = x[i - 1] + d * step * rng.uniform(0.5, 1.5, k)
        over, under = nxt > hi, nxt < lo
        nxt = np.where(over, 2 * hi - nxt, nxt)
        nxt = np.where(under, 2 * lo - nxt, nxt)
        d = np.where(over | under, -d, d)
        x[i] = np.clip(nxt, lo, hi)
    return x


def design(spec: Spec, name: str, n_rows: int, rng: np.random.Generator, sweeps: int | None = None):
    """-> q (N, 2n), time (N,), sweep (N,) str."""
    n = spec.n
    if name not in DESIGNS:
        raise ValueError(f"unknown design {name!r}; known: {DESIGNS}")
    if name == "uniform":
        lo = np.maximum(spec.beta_lo, -spec.L)
        out = np.zeros((0, n))
        while out.shape[0] < n_rows:
            b = rng.uniform(lo, 0.0, (max(4 * n_rows, 64), n))
            b = b[valid(spec, np.c_[np.zeros_like(b), b])]
            out = np.vstack([out, b])
        beta = out[:n_rows]
        alpha = rng.uniform(-np.pi, np.pi, (n_rows, n))
        q = np.c_[alpha, beta]
        t = np.arange(n_rows) * DT
        sw = np.array([f"u{i}" for i in range(n_rows)])
        return q, t, sw
    if sweeps is None:
        sweeps = int(np.clip(n_rows // 150, 2, 12)) if name == "sweeps" else int(np.clip(n_rows // 100, 2, 8))
    sweeps = max(1, min(sweeps, n_rows))
    counts = _split(n_rows, sweeps)
    qs, sws = [], []
    for k, m in enumerate(counts):
        if name == "sweeps":
            lo = np.r_[np.full(n, -np.pi), np.zeros(n)]
            hi = np.r_[np.full(n, np.pi), np.ones(n)]
            step_lo = np.r_[np.full(n, 0.02), np.full(n, 0.004)]
            step_hi = np.r_[np.full(n, 0.10), np.full(n, 0.02)]
            x = _walk(rng, m, lo, hi, step_lo, step_hi)
            q = np.c_[x[:, :n], beta_from_unit(spec, x[:, n:])]
        else:
            alpha0 = rng.uniform(-np.pi, np.pi, n)
            u0 = rng.uniform(0.3, 1.0, n)
            tri = np.abs(((np.arange(m) / max(m - 1, 1)) * 2.0) - 1.0)      # 1 -> 0 -> 1
            ramp = 1.0 - tri                                                 # 0 -> 1 -> 0
            if name == "feed":
                u = np.tile(u0, (m, 1))
                u[:, 0] = 0.02 + 0.96 * ramp
                q = np.c_[np.tile(alpha0, (m, 1)), beta_from_unit(spec, u)]
            else:
                j = 0 if name == "inner_rotation" else n - 1
                a = np.tile(alpha0, (m, 1))
                a[:, j] = alpha0[j] + 2 * np.pi * ramp
                q = np.c_[a, np.tile(beta_from_unit(spec, u0[None])[0], (m, 1))]
        qs.append(q)
        sws += [f"s{k}"] * m
    q = np.vstack(qs)
    ok = valid(spec, q)
    if not ok.all():
        raise AssertionError(f"design {name} produced {np.sum(~ok)} invalid rows")
    return q, _times(rng, counts), np.array(sws)


def directions(q: np.ndarray, sweep: np.ndarray) -> np.ndarray:
    """True sign of the last motion of each joint (0 = none yet in this sweep), (N, 2n) int8."""
    N, d = q.shape
    out = np.zeros((N, d), np.int8)
    last = np.zeros(d, np.int8)
    for i in range(N):
        if i == 0 or sweep[i] != sweep[i - 1]:
            last = np.zeros(d, np.int8)
        else:
            dq = q[i] - q[i - 1]
            s = np.sign(np.where(np.abs(dq) > 1e-12, dq, 0.0)).astype(np.int8)
            last = np.where(s != 0, s, last)
        out[i] = last
    return out
