"""Points covering a triangle mesh within a known radius: the samples of the distance field
(:mod:`ctrplan.collision.field`)."""

from __future__ import annotations

import math

import numba as nb
import numpy as np

#: A triangle is sampled by a grid in its plane (cost ~ area) instead of the barycentric
#: lattice (cost ~ longest edge squared) when the lattice would need this many times more points.
LATTICE_EXCESS = 16.0


def surface_samples(v: np.ndarray, f: np.ndarray, max_edge: float) -> tuple[np.ndarray, float]:
    """Points covering a mesh so that every surface point lies within ``rho = e / sqrt(3)`` of
    one, returned as (points (S, 3), ``e``); ``e <= max_edge`` where every triangle is
    well-shaped, ``e = sqrt(2) max_edge`` where some are long and thin. Cost follows surface
    area, not triangle shape.

    A well-shaped triangle gets the lattice ``(i a + j b + k c) / n`` with ``n = ceil(longest
    edge / max_edge)``: its sub-triangles are copies of the triangle scaled by ``1 / n``. A long
    thin triangle (whose lattice would need more than ``LATTICE_EXCESS`` times the points its area
    needs) gets a square grid of spacing ``g = max_edge`` in its own plane instead (and then,
    as the covering radius is set by those, every triangle gets whichever of a lattice with
    sub-edges up to ``g sqrt(2)`` or the grid needs fewer points): the grid
    nodes inside it, the points where its edges cross grid lines, and its corners. Each grid
    cell cuts the triangle into a convex polygon whose corners are all samples and whose
    diameter is at most ``g sqrt(2)``; triangulated from its corners, every point lies within
    (longest edge) / sqrt(3) of a corner, so ``e = g sqrt(2)`` bounds the covering radius.
    """
    f = np.asarray(f, dtype=np.int64)
    if len(f) == 0:
        return np.empty((0, 3)), 0.0
    # in chunks of triangles (memory O(chunk), not O(F)): whether any triangle is thin decides
    # the covering radius of all of them, so that is settled first
    chunks = [(s, min(s + TRI_CHUNK, len(f))) for s in range(0, len(f), TRI_CHUNK)]
    for any_thin in (False, True):      # the second pass only when some triangle is thin
        outs, corner_sets, e, thin_seen = [], [], 0.0, False
        for s, e_ in chunks:
            pts, corners, e_c, thin = _chunk_samples(v, f[s:e_], max_edge, any_thin)
            if thin and not any_thin:
                thin_seen = True
                break
            outs.append(pts)
            corner_sets.append(corners)
            e = max(e, e_c)
        if not thin_seen:
            break
    # a triangle whose lattice is its three corners (n = 1) is covered by the mesh's vertices:
    # they are taken once each, not once per triangle (a fine mesh shares each about 6 times)
    used = np.zeros(len(v), dtype=bool)
    for c in corner_sets:
        used[c] = True
    return np.concatenate(outs + [v[used]]), e


#: Triangles per chunk of :func:`surface_samples`.
TRI_CHUNK = 1 << 19


def _sample_plan(v, f, max_edge: float, any_thin: bool):
    """(tri (T, 3, 3), longest (T,), n (T,), thin (T,)) of a chunk of triangles."""
    tri = np.ascontiguousarray(v[f], dtype=float)
    edges = np.stack([np.linalg.norm(tri[:, i] - tri[:, (i + 1) % 3], axis=1) for i in range(3)], axis=1)
    longest = edges.max(axis=1)
    n = np.maximum(np.ceil(longest / max_edge), 1).astype(np.int64)
    lattice = (n + 1) * (n + 2) // 2
    g = max_edge
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    by_area = area / g**2 + 2.0 * edges.sum(axis=1) / g + 3.0
    thin = lattice > LATTICE_EXCESS * by_area
    if any_thin:
        # the grid triangles set the covering radius (e = g sqrt(2)): sample the others with
        # lattice sub-edges up to that too, and each triangle by whichever needs fewer points
        n = np.maximum(np.ceil(longest / (g * math.sqrt(2.0))), 1).astype(np.int64)
        lattice = (n + 1) * (n + 2) // 2
        thin |= lattice > by_area
    return tri, longest, n, thin


def _chunk_samples(v, f, max_edge: float, any_thin: bool):
    """(samples, vertex indices of corner-only triangles, e, any thin) of a chunk of
    triangles (with ``any_thin`` False it stops at the plan when the chunk has a thin one)."""
    tri, longest, n, thin = _sample_plan(v, f, max_edge, any_thin)
    if not any_thin and thin.any():
        return None, None, 0.0, True
    g = max_edge
    corners = ~thin & (n == 1)
    counts = np.where(thin | corners, 0, (n + 1) * (n + 2) // 2)
    if thin.any():
        counts[thin] = _grid_samples(tri[thin], g, np.empty((0, 3)), np.zeros(1, np.int64), False)
    offsets = np.concatenate([[0], np.cumsum(counts)])
    out = np.empty((int(offsets[-1]), 3))
    fat = ~thin
    if (fat & ~corners).any():
        _lattice_at(tri, n, offsets, np.flatnonzero(fat & ~corners), out)
    if thin.any():
        _grid_samples(tri[thin], g, out, offsets[:-1][thin], True)
    e = float((longest[fat] / n[fat]).max()) if fat.any() else 0.0
    if thin.any():
        e = max(e, g * math.sqrt(2.0))
    return out, f[corners].ravel(), e, bool(thin.any())


@nb.njit(cache=True)
def _lattice_at(tri, n, offsets, sel, out):
    for s in range(sel.shape[0]):
        t = sel[s]
        m = n[t]
        o = offsets[t]
        for i in range(m + 1):
            for j in range(m + 1 - i):
                k = m - i - j
                for d in range(3):
                    out[o, d] = (i * tri[t, 0, d] + j * tri[t, 1, d] + k * tri[t, 2, d]) / m
                o += 1


@nb.njit(cache=True)
def _grid_samples(tri, g, out, offsets, write):
    """Grid samples of each triangle (see :func:`surface_samples`). With ``write`` False only
    counts them (returns (T,) counts); with ``write`` True fills ``out`` from ``offsets``."""
    T = tri.shape[0]
    counts = np.zeros(T, dtype=np.int64)
    for t in range(T):
        # in-plane frame: U along the longest edge a->b, W perpendicular toward c
        q0 = 0
        best = -1.0
        for q in range(3):
            dd = 0.0
            for d in range(3):
                dd += (tri[t, (q + 1) % 3, d] - tri[t, q, d]) ** 2
            if dd > best:
                best = dd
                q0 = q
        a = tri[t, q0]
        b = tri[t, (q0 + 1) % 3]
        c = tri[t, (q0 + 2) % 3]
        ab = b - a
        L = math.sqrt(ab[0] ** 2 + ab[1] ** 2 + ab[2] ** 2)
        U = ab / L if L > 0.0 else np.zeros(3)
        ac = c - a
        cu = ac[0] * U[0] + ac[1] * U[1] + ac[2] * U[2]
        wv = ac - cu * U
        cw = math.sqrt(wv[0] ** 2 + wv[1] ** 2 + wv[2] ** 2)
        W = wv / cw if cw > 0.0 else np.zeros(3)
        P = np.array([[0.0, 0.0], [L, 0.0], [cu, cw]])
        o = offsets[t] if write else 0
        k = 0
        # corners
        for q in range(3):
            if write:
                for d in range(3):
                    out[o + k, d] = tri[t, q, d]
            k += 1
        # edge crossings with the grid lines u = i g and w = j g (corners excluded)
        for q in range(3):
            p0u = P[q, 0]
            p0w = P[q, 1]
            p1u = P[(q + 1) % 3, 0]
            p1w = P[(q + 1) % 3, 1]
            for axis in range(2):
                x0 = p0u if axis == 0 else p0w
                x1 = p1u if axis == 0 else p1w
                if x0 == x1:
                    continue
                lo = min(x0, x1)
                hi = max(x0, x1)
                i0 = int(math.floor(lo / g)) + 1
                i1 = int(math.ceil(hi / g)) - 1
                for i in range(i0, i1 + 1):
                    s = (i * g - x0) / (x1 - x0)
                    if s <= 0.0 or s >= 1.0:
                        continue
                    if write:
                        pu = p0u + s * (p1u - p0u)
                        pw = p0w + s * (p1w - p0w)
                        for d in range(3):
                            out[o + k, d] = a[d] + pu * U[d] + pw * W[d]
                    k += 1
        # grid nodes strictly inside
        for i in range(1, int(math.ceil(L / g))):
            u = i * g
            for j in range(1, int(math.ceil(cw / g))):
                w = j * g
                # inside: w > 0, left of b->c and of c->a
                e1 = (cu - L) * (w - 0.0) - (cw - 0.0) * (u - L)
                e2 = (0.0 - cu) * (w - cw) - (0.0 - cw) * (u - cu)
                if e1 > 0.0 and e2 > 0.0:
                    if write:
                        for d in range(3):
                            out[o + k, d] = a[d] + u * U[d] + w * W[d]
                    k += 1
        counts[t] = k
    return counts
