"""The exact second stage behind the distance-field prefilter (numba): capsule-mesh pairs the
field's bounds cannot decide are measured against the triangles near them, and only the pairs
this cannot decide either go to FCL.

Each mesh gets the uniform grid of triangle lists of :mod:`ctrplan.collision._grid` (cells
about two triangles wide; every triangle listed in each cell its bounding box overlaps). A
capsule (segment p-q, radius r) visits the cells its bounding box grown by ``r + TIE_MM``
overlaps, skips cells whose centre lies farther than that reach plus half the cell diagonal
from the segment, and every triangle whose bounding box misses the grown box, and takes the
exact segment-triangle distance ``d`` of the rest (double precision, closed form: zero where
the segment crosses the triangle, found by the signs of its ends' distances to the plane and
the crossing point's side of each edge; else the least of the distances from the segment's
ends to the triangle and from the segment to the three edges, the closest-point routines of
Ericson, Real-Time Collision Detection, 5.1.5 and 5.1.9).

Verdict of a pair: ``d < r - TIE_MM`` touches, ``d > r + TIE_MM`` is free, anything between
is a tie that FCL decides (FCL's own convention at contact: it reports a collision up to a
tolerance measured below 1e-6 mm, see tests/test_exact_stage.py). A capsule with a
non-finite end or radius is never decided here. Collision checking never reports free when
unsure: the stage only removes work from FCL, never a verdict from it.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ctrplan.collision._grid import _point_tri_d2, _seg_seg_d2

#: Half-width (mm) of the band around contact (|d - r| <= TIE_MM) left to FCL: 100x the
#: largest disagreement of FCL with the exact distance measured on random near-contact
#: capsules (1e-6 mm), and far above the rounding of the closed form (~1e-12 mm).
TIE_MM = 1e-4
#: verdicts of :meth:`ExactStage.decide`
FREE, UNSURE = -1, -2


@nb.njit(cache=True, _nrt=False)
def seg_tri_d2(px, py, pz, qx, qy, qz, ax, ay, az, bx, by, bz, cx, cy, cz, above):
    """Squared distance between segment p-q and triangle abc (scalars, mm) where it is at
    most ``above``; where it is larger, some value larger than ``above`` (the squared
    distance to the triangle's plane when that already is: a lower bound)."""
    e1x, e1y, e1z = bx - ax, by - ay, bz - az
    e2x, e2y, e2z = cx - ax, cy - ay, cz - az
    nx = e1y * e2z - e1z * e2y
    ny = e1z * e2x - e1x * e2z
    nz = e1x * e2y - e1y * e2x
    sp = nx * (px - ax) + ny * (py - ay) + nz * (pz - az)
    sq = nx * (qx - ax) + ny * (qy - ay) + nz * (qz - az)
    if (sp > 0.0 and sq > 0.0) or (sp < 0.0 and sq < 0.0):
        # the plane is farther than ``above`` (by more than the normal's rounding can move
        # it, in a triangle whose angles are not within 1e-6 of flat)
        n2 = nx * nx + ny * ny + nz * nz
        e12 = (e1x * e1x + e1y * e1y + e1z * e1z) * (e2x * e2x + e2y * e2y + e2z * e2z)
        if n2 > 1e-12 * e12:
            s2 = min(sp * sp, sq * sq) / n2
            lim = math.sqrt(above) + 1e-7
            if s2 > lim * lim:
                return s2
    elif sp != sq:
        t = sp / (sp - sq)
        xx, xy, xz = px + t * (qx - px), py + t * (qy - py), pz + t * (qz - pz)
        if (_side(ax, ay, az, bx, by, bz, xx, xy, xz, nx, ny, nz) >= 0.0
                and _side(bx, by, bz, cx, cy, cz, xx, xy, xz, nx, ny, nz) >= 0.0
                and _side(cx, cy, cz, ax, ay, az, xx, xy, xz, nx, ny, nz) >= 0.0):
            return 0.0
    d = _point_tri_d2(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz)
    d = min(d, _point_tri_d2(qx, qy, qz, ax, ay, az, bx, by, bz, cx, cy, cz))
    d = min(d, _seg_seg_d2(px, py, pz, qx, qy, qz, ax, ay, az, bx, by, bz))
    d = min(d, _seg_seg_d2(px, py, pz, qx, qy, qz, bx, by, bz, cx, cy, cz))
    return min(d, _seg_seg_d2(px, py, pz, qx, qy, qz, cx, cy, cz, ax, ay, az))


@nb.njit(cache=True, _nrt=False, inline="always")
def _side(ux, uy, uz, vx, vy, vz, xx, xy, xz, nx, ny, nz):
    """n . ((v - u) x (x - u)): >= 0 where x lies on the inner side of the edge u -> v."""
    ex, ey, ez = vx - ux, vy - uy, vz - uz
    wx, wy, wz = xx - ux, xy - uy, xz - uz
    return nx * (ey * wz - ez * wy) + ny * (ez * wx - ex * wz) + nz * (ex * wy - ey * wx)


@nb.njit(cache=True, _nrt=False, inline="always")
def _far(px, py, pz, qx, qy, qz, ax, ay, az, bx, by, bz, cx, cy, cz, reach):
    """Whether the triangle's ball about its centroid (radius: the farthest vertex) lies
    farther than ``reach`` from segment p-q (the triangle then does too), with 1e-7 mm spare."""
    mx, my, mz = (ax + bx + cx) / 3.0, (ay + by + cy) / 3.0, (az + bz + cz) / 3.0
    rad2 = max((ax - mx) ** 2 + (ay - my) ** 2 + (az - mz) ** 2,
               (bx - mx) ** 2 + (by - my) ** 2 + (bz - mz) ** 2,
               (cx - mx) ** 2 + (cy - my) ** 2 + (cz - mz) ** 2)
    lim = reach + math.sqrt(rad2) + 1e-7
    return _seg_seg_d2(mx, my, mz, mx, my, mz, px, py, pz, qx, qy, qz) > lim * lim


@nb.njit(cache=True, _nrt=False)
def _pair_d2(px, py, pz, qx, qy, qz, reach, stop, V, F, start, tris, lox, loy, loz, c,
             nx, ny, nz, base, seen, tick):
    """Least squared distance from segment p-q to the triangles of one mesh where it is at
    most ``reach`` squared (else a value above that: inf if no triangle can lie within
    ``reach``); returns early once below ``stop``. The mesh's grid: origin (lox, loy, loz),
    cell c, (nx, ny, nz) cells from ``base`` in ``start``. ``seen`` (triangles) holds the
    ``tick`` of the last call that measured each triangle (a triangle listed in several
    cells is measured once)."""
    xlo, xhi = min(px, qx) - reach, max(px, qx) + reach
    ylo, yhi = min(py, qy) - reach, max(py, qy) + reach
    zlo, zhi = min(pz, qz) - reach, max(pz, qz) + reach
    i0, i1 = max(int(math.floor((xlo - lox) / c)), 0), min(int(math.floor((xhi - lox) / c)), nx - 1)
    j0, j1 = max(int(math.floor((ylo - loy) / c)), 0), min(int(math.floor((yhi - loy) / c)), ny - 1)
    k0, k1 = max(int(math.floor((zlo - loz) / c)), 0), min(int(math.floor((zhi - loz) / c)), nz - 1)
    half = 0.5 * c * math.sqrt(3.0)
    lim = (reach + half) * (reach + half)
    best = np.inf
    above = reach * reach
    for i in range(i0, i1 + 1):
        ccx = lox + (i + 0.5) * c
        for j in range(j0, j1 + 1):
            ccy = loy + (j + 0.5) * c
            for k in range(k0, k1 + 1):
                cell = base + (i * ny + j) * nz + k
                if start[cell] == start[cell + 1]:
                    continue
                ccz = loz + (k + 0.5) * c
                if _seg_seg_d2(ccx, ccy, ccz, ccx, ccy, ccz, px, py, pz, qx, qy, qz) > lim:
                    continue
                for n in range(start[cell], start[cell + 1]):
                    t = tris[n]
                    if seen[t] == tick:
                        continue
                    seen[t] = tick
                    a, b, cc = F[t, 0], F[t, 1], F[t, 2]
                    if (max(V[a, 0], V[b, 0], V[cc, 0]) < xlo or min(V[a, 0], V[b, 0], V[cc, 0]) > xhi
                            or max(V[a, 1], V[b, 1], V[cc, 1]) < ylo
                            or min(V[a, 1], V[b, 1], V[cc, 1]) > yhi
                            or max(V[a, 2], V[b, 2], V[cc, 2]) < zlo
                            or min(V[a, 2], V[b, 2], V[cc, 2]) > zhi):
                        continue
                    if _far(px, py, pz, qx, qy, qz, V[a, 0], V[a, 1], V[a, 2], V[b, 0], V[b, 1],
                            V[b, 2], V[cc, 0], V[cc, 1], V[cc, 2], reach):
                        continue
                    d = seg_tri_d2(px, py, pz, qx, qy, qz, V[a, 0], V[a, 1], V[a, 2],
                                   V[b, 0], V[b, 1], V[b, 2], V[cc, 0], V[cc, 1], V[cc, 2],
                                   min(best, above))
                    if d < best:
                        best = d
                        if best < stop:
                            return best
    return best


@nb.njit(cache=True, _nrt=False)
def _decide(a, b, r, rows, unsure, bits, V, F, start, tris, lo, c, dims, base, tie, seen,
            ticks, out):
    """out[n] for configuration rows[n]: the first mesh j (in mesh order, as FCL's first hit)
    one of whose unsure pairs (bit j of unsure[i, k]) touches, FREE if every unsure pair is
    free, UNSURE where a pair of the first undecided mesh is a tie or not finite. ``seen``
    and ``ticks[0]`` (the last tick used): see :func:`_pair_d2`."""
    K = r.shape[1]
    for n in range(rows.shape[0]):
        i = rows[n]
        res = -1
        for j in range(lo.shape[0]):
            hit = False
            tied = False
            for k2 in range(K):
                k = K - 1 - k2          # tip first, where the walls are met first
                if unsure[i, k] & bits[j] == 0:
                    continue
                rk = r[i, k]
                px, py, pz = a[i, k, 0], a[i, k, 1], a[i, k, 2]
                qx, qy, qz = b[i, k, 0], b[i, k, 1], b[i, k, 2]
                if not (math.isfinite(px + py + pz + qx + qy + qz) and math.isfinite(rk)):
                    tied = True
                    continue
                reach = rk + tie
                stop = (rk - tie) * (rk - tie) if rk > tie else -1.0
                ticks[0] += 1
                d2 = _pair_d2(px, py, pz, qx, qy, qz, reach, stop, V, F, start, tris,
                              lo[j, 0], lo[j, 1], lo[j, 2], c[j], dims[j, 0], dims[j, 1],
                              dims[j, 2], base[j], seen, ticks[0])
                if d2 < stop:
                    hit = True
                    break
                if d2 <= reach * reach:
                    tied = True
            if hit:
                res = j
                break
            if tied:
                res = -2
                break
        out[n] = res


class ExactStage:
    """The second stage over a list of meshes (mm, scene frame): per-mesh grids of triangle
    lists, concatenated (a single mesh's arrays are used as they are, no copy).

    grids : the meshes' :class:`ctrplan.collision._grid._MeshGrid` objects (reused from the
    grid backend where the world has one)."""

    def __init__(self, grids):
        grids = list(grids)
        if len(grids) > 64:
            raise ValueError("at most 64 meshes (one bit each in the prefilter's masks)")
        self.M = len(grids)
        if self.M == 1:
            g = grids[0]
            self.V, self.F, self.start, self.tris = g.v, g.f, g.start, g.tris
            base = [0]
        else:
            nv = np.cumsum([0] + [len(g.v) for g in grids])
            nf = np.cumsum([0] + [len(g.f) for g in grids])
            nt = np.cumsum([0] + [len(g.tris) for g in grids])
            base = np.cumsum([0] + [len(g.start) for g in grids])[:-1]
            self.V = np.ascontiguousarray(np.concatenate([g.v for g in grids]))
            self.F = np.ascontiguousarray(np.concatenate([g.f + nv[j] for j, g in enumerate(grids)]))
            self.start = np.concatenate([g.start + nt[j] for j, g in enumerate(grids)])
            self.tris = np.concatenate([(g.tris.astype(np.int64) + nf[j]).astype(g.tris.dtype)
                                        for j, g in enumerate(grids)])
        self.lo = np.ascontiguousarray(np.array([g.lo for g in grids], dtype=np.float64))
        self.c = np.array([g.c for g in grids], dtype=np.float64)
        self.dims = np.ascontiguousarray(np.array([g.dims for g in grids], dtype=np.int64))
        self.base = np.asarray(base, dtype=np.int64)
        self.bits = np.array([1 << j for j in range(self.M)], dtype=np.uint64)
        self._seen = np.zeros(len(self.F), dtype=np.int64)
        self._ticks = np.zeros(1, dtype=np.int64)

    @classmethod
    def from_meshes(cls, meshes) -> ExactStage:
        from ctrplan.collision._grid import _MeshGrid

        return cls([_MeshGrid(m) for m in meshes])

    def decide(self, a: np.ndarray, b: np.ndarray, r: np.ndarray, rows: np.ndarray,
               unsure: np.ndarray) -> np.ndarray:
        """(len(rows),) int: per configuration ``rows`` of the batch (a, b (B, K, 3) mm,
        r (B, K) mm), the first mesh touched by a pair marked in ``unsure`` (B, K) uint64
        (bit j: mesh j), FREE (-1) or UNSURE (-2, for FCL)."""
        out = np.empty(len(rows), dtype=np.int64)
        if len(rows):
            _decide(np.ascontiguousarray(a, dtype=np.float64),
                    np.ascontiguousarray(b, dtype=np.float64),
                    np.ascontiguousarray(r, dtype=np.float64),
                    np.ascontiguousarray(rows, dtype=np.int64),
                    np.ascontiguousarray(unsure, dtype=np.uint64), self.bits, self.V, self.F,
                    self.start, self.tris, self.lo, self.c, self.dims, self.base, TIE_MM,
                    self._seen, self._ticks, out)
        return out
