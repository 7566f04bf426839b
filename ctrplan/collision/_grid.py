"""Exact capsule-vs-mesh queries over a uniform grid of triangle lists (numba): the lean
alternative to FCL for meshes of millions of triangles.

FCL's bounding-volume tree costs about 600 bytes and 9 us to build per triangle (measured:
3 GB and 45 s for 5 million), more than a check of a fine segmentation can afford. Here each
mesh gets a uniform grid over its bounding box; every triangle is listed in each cell its
bounding box overlaps (compressed: an offsets array and one int32 list, about 10 bytes per
triangle). A capsule (segment a-b, radius r) visits the cells its bounding box (grown by r)
overlaps, skips those whose centre lies farther than ``r + half the cell diagonal`` from the
segment, and tests the triangles listed there with the exact segment-triangle distance (in
double precision: zero when the segment crosses the triangle, else the least of the distances
from the segment's ends to the triangle and from the segment to the triangle's edges, the
closest-point routines of Ericson, Real-Time Collision Detection, 5.1.5 and 5.1.9). A capsule
touches the mesh when that distance is at most r, as for FCL. Same interface as
:class:`ctrplan.collision._fcl.FclMeshes`; the two agree on random capsules
(tests/test_large_meshes.py).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

#: most cells of one mesh's grid
MAX_CELLS = 4_000_000


@nb.njit(cache=True, inline="always")
def _clamp01(x):
    return 0.0 if x < 0.0 else (1.0 if x > 1.0 else x)


@nb.njit(cache=True)
def _point_tri_d2(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Squared distance from point p to triangle abc (Ericson 5.1.5, closest point by regions)."""
    abx, aby, abz = bx - ax, by - ay, bz - az
    acx, acy, acz = cx - ax, cy - ay, cz - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        qx, qy, qz = ax, ay, az
    else:
        bpx, bpy, bpz = px - bx, py - by, pz - bz
        d3 = abx * bpx + aby * bpy + abz * bpz
        d4 = acx * bpx + acy * bpy + acz * bpz
        vc = d1 * d4 - d3 * d2
        cpx, cpy, cpz = px - cx, py - cy, pz - cz
        d5 = abx * cpx + aby * cpy + abz * cpz
        d6 = acx * cpx + acy * cpy + acz * cpz
        vb = d5 * d2 - d1 * d6
        va = d3 * d6 - d5 * d4
        if d3 >= 0.0 and d4 <= d3:
            qx, qy, qz = bx, by, bz
        elif vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
            v = d1 / (d1 - d3) if d1 != d3 else 0.0
            qx, qy, qz = ax + v * abx, ay + v * aby, az + v * abz
        elif d6 >= 0.0 and d5 <= d6:
            qx, qy, qz = cx, cy, cz
        elif vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
            w = d2 / (d2 - d6) if d2 != d6 else 0.0
            qx, qy, qz = ax + w * acx, ay + w * acy, az + w * acz
        elif va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
            den = (d4 - d3) + (d5 - d6)
            w = (d4 - d3) / den if den > 0.0 else 0.0
            qx, qy, qz = bx + w * (cx - bx), by + w * (cy - by), bz + w * (cz - bz)
        else:
            den = va + vb + vc
            if den == 0.0:      # a degenerate triangle: its edges decide
                return min(_seg_seg_d2(px, py, pz, px, py, pz, ax, ay, az, bx, by, bz),
                           _seg_seg_d2(px, py, pz, px, py, pz, bx, by, bz, cx, cy, cz),
                           _seg_seg_d2(px, py, pz, px, py, pz, cx, cy, cz, ax, ay, az))
            v = vb / den
            w = vc / den
            qx = ax + abx * v + acx * w
            qy = ay + aby * v + acy * w
            qz = az + abz * v + acz * w
    dx, dy, dz = px - qx, py - qy, pz - qz
    return dx * dx + dy * dy + dz * dz


@nb.njit(cache=True)
def _seg_seg_d2(p1x, p1y, p1z, q1x, q1y, q1z, p2x, p2y, p2z, q2x, q2y, q2z):
    """Squared distance between segments p1-q1 and p2-q2 (Ericson 5.1.9)."""
    d1x, d1y, d1z = q1x - p1x, q1y - p1y, q1z - p1z
    d2x, d2y, d2z = q2x - p2x, q2y - p2y, q2z - p2z
    rx, ry, rz = p1x - p2x, p1y - p2y, p1z - p2z
    a = d1x * d1x + d1y * d1y + d1z * d1z
    e = d2x * d2x + d2y * d2y + d2z * d2z
    f = d2x * rx + d2y * ry + d2z * rz
    if a <= 1e-300 and e <= 1e-300:
        s = 0.0
        t = 0.0
    elif a <= 1e-300:
        s = 0.0
        t = _clamp01(f / e)
    else:
        c = d1x * rx + d1y * ry + d1z * rz
        if e <= 1e-300:
            t = 0.0
            s = _clamp01(-c / a)
        else:
            b = d1x * d2x + d1y * d2y + d1z * d2z
            den = a * e - b * b
            s = _clamp01((b * f - c * e) / den) if den > 0.0 else 0.0
            t = (b * s + f) / e
            if t < 0.0:
                t = 0.0
                s = _clamp01(-c / a)
            elif t > 1.0:
                t = 1.0
                s = _clamp01((b - c) / a)
    dx = p1x + d1x * s - (p2x + d2x * t)
    dy = p1y + d1y * s - (p2y + d2y * t)
    dz = p1z + d1z * s - (p2z + d2z * t)
    return dx * dx + dy * dy + dz * dz


@nb.njit(cache=True)
def _seg_crosses_tri(px, py, pz, qx, qy, qz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Whether segment p-q meets triangle abc (Moeller-Trumbore with t in [0, 1])."""
    dx, dy, dz = qx - px, qy - py, qz - pz
    e1x, e1y, e1z = bx - ax, by - ay, bz - az
    e2x, e2y, e2z = cx - ax, cy - ay, cz - az
    hx = dy * e2z - dz * e2y
    hy = dz * e2x - dx * e2z
    hz = dx * e2y - dy * e2x
    det = e1x * hx + e1y * hy + e1z * hz
    if det == 0.0:
        return False        # parallel: the edge distances decide
    inv = 1.0 / det
    sx, sy, sz = px - ax, py - ay, pz - az
    u = (sx * hx + sy * hy + sz * hz) * inv
    if u < 0.0 or u > 1.0:
        return False
    qqx = sy * e1z - sz * e1y
    qqy = sz * e1x - sx * e1z
    qqz = sx * e1y - sy * e1x
    v = (dx * qqx + dy * qqy + dz * qqz) * inv
    if v < 0.0 or u + v > 1.0:
        return False
    t = (e2x * qqx + e2y * qqy + e2z * qqz) * inv
    return 0.0 <= t <= 1.0


@nb.njit(cache=True)
def seg_tri_d2(p, q, a, b, c):
    """Squared distance between segment p-q and triangle abc ((3,) arrays)."""
    if _seg_crosses_tri(p[0], p[1], p[2], q[0], q[1], q[2], a[0], a[1], a[2], b[0], b[1], b[2],
                        c[0], c[1], c[2]):
        return 0.0
    d = _point_tri_d2(p[0], p[1], p[2], a[0], a[1], a[2], b[0], b[1], b[2], c[0], c[1], c[2])
    d = min(d, _point_tri_d2(q[0], q[1], q[2], a[0], a[1], a[2], b[0], b[1], b[2], c[0], c[1], c[2]))
    d = min(d, _seg_seg_d2(p[0], p[1], p[2], q[0], q[1], q[2], a[0], a[1], a[2], b[0], b[1], b[2]))
    d = min(d, _seg_seg_d2(p[0], p[1], p[2], q[0], q[1], q[2], b[0], b[1], b[2], c[0], c[1], c[2]))
    d = min(d, _seg_seg_d2(p[0], p[1], p[2], q[0], q[1], q[2], c[0], c[1], c[2], a[0], a[1], a[2]))
    return d


@nb.njit(cache=True)
def _cell_range(v, f, lo, c, dims, t):
    i0 = np.empty(3, np.int64)
    i1 = np.empty(3, np.int64)
    for d in range(3):
        m0 = min(v[f[t, 0], d], v[f[t, 1], d], v[f[t, 2], d])
        m1 = max(v[f[t, 0], d], v[f[t, 1], d], v[f[t, 2], d])
        i0[d] = min(max(int(math.floor((m0 - lo[d]) / c)), 0), dims[d] - 1)
        i1[d] = min(max(int(math.floor((m1 - lo[d]) / c)), 0), dims[d] - 1)
    return i0, i1


@nb.njit(cache=True)
def _build(v, f, lo, c, dims):
    """CSR lists: (start (cells + 1,) int64, tris (P,) int32)."""
    ncell = dims[0] * dims[1] * dims[2]
    count = np.zeros(ncell + 1, np.int64)
    for t in range(f.shape[0]):
        i0, i1 = _cell_range(v, f, lo, c, dims, t)
        for i in range(i0[0], i1[0] + 1):
            for j in range(i0[1], i1[1] + 1):
                for k in range(i0[2], i1[2] + 1):
                    count[(i * dims[1] + j) * dims[2] + k + 1] += 1
    for n in range(ncell):
        count[n + 1] += count[n]
    tris = np.empty(count[ncell], np.int32)
    fill = count[:-1].copy()
    for t in range(f.shape[0]):
        i0, i1 = _cell_range(v, f, lo, c, dims, t)
        for i in range(i0[0], i1[0] + 1):
            for j in range(i0[1], i1[1] + 1):
                for k in range(i0[2], i1[2] + 1):
                    cell = (i * dims[1] + j) * dims[2] + k
                    tris[fill[cell]] = t
                    fill[cell] += 1
    return count, tris


@nb.njit(cache=True, _nrt=False, inline="always")
def cell_of(x, lo, c, n):
    """floor((x - lo) / c), the cell of coordinate x on a grid of n cells from lo, clamped
    into [-1, n] in floating point first (a far coordinate never overflows the integer)."""
    return int(math.floor(min(max((x - lo) / c, -1.0), float(n))))


@nb.njit(cache=True)
def _min_d2(v, f, lo, c, dims, start, tris, p, q, reach, stop_below):
    """Least squared segment-triangle distance over the triangles in cells that can hold a
    point within ``reach`` of segment p-q (inf if none); returns early once below
    ``stop_below`` (squared)."""
    i0 = np.empty(3, np.int64)
    i1 = np.empty(3, np.int64)
    for d in range(3):
        m0 = min(p[d], q[d]) - reach
        m1 = max(p[d], q[d]) + reach
        if not (math.isfinite(m0) and math.isfinite(m1)):
            return 0.0          # unsure (a non-finite segment): touching, never "free"
        # clamped before the integer conversion (:func:`cell_of`): a huge coordinate's cell
        # overflowed int64 to a negative index and the capsule looked free
        i0[d] = max(cell_of(m0, lo[d], c, dims[d]), 0)
        i1[d] = min(cell_of(m1, lo[d], c, dims[d]), dims[d] - 1)
        if i0[d] > i1[d]:
            return np.inf
    half = 0.5 * c * math.sqrt(3.0)
    lim = (reach + half) * (reach + half)
    best = np.inf
    for i in range(i0[0], i1[0] + 1):
        cx = lo[0] + (i + 0.5) * c
        for j in range(i0[1], i1[1] + 1):
            cy = lo[1] + (j + 0.5) * c
            for k in range(i0[2], i1[2] + 1):
                cell = (i * dims[1] + j) * dims[2] + k
                if start[cell] == start[cell + 1]:
                    continue
                cz = lo[2] + (k + 0.5) * c
                if _seg_seg_d2(cx, cy, cz, cx, cy, cz, p[0], p[1], p[2], q[0], q[1], q[2]) > lim:
                    continue
                for n in range(start[cell], start[cell + 1]):
                    t = tris[n]
                    d = seg_tri_d2(p, q, v[f[t, 0]], v[f[t, 1]], v[f[t, 2]])
                    if d < best:
                        best = d
                        if best <= stop_below:
                            return best
    return best


class _MeshGrid:
    def __init__(self, mesh):
        self.v = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
        self.f = np.ascontiguousarray(mesh.faces, dtype=np.int64)
        lo, hi = self.v.min(axis=0), self.v.max(axis=0)
        ext = np.maximum(hi - lo, 1e-9)
        tri = self.v[self.f[: min(len(self.f), 100_000)]]
        size = float(np.median(tri.max(axis=1) - tri.min(axis=1)))
        # cells about two triangles wide, but no more than MAX_CELLS of them (a flat mesh has
        # one layer of cells: grow the cell until the count fits)
        c = max(2.0 * size, float(np.prod(ext) / MAX_CELLS) ** (1.0 / 3.0), 1e-6)
        while np.prod(np.maximum(np.ceil((ext + 2e-9) / c), 1.0)) > MAX_CELLS:
            c *= 1.25
        self.lo = lo - 1e-9
        self.c = c
        self.dims = np.maximum(np.ceil((ext + 2e-9) / c).astype(np.int64), 1)
        self.start, self.tris = _build(self.v, self.f, self.lo, self.c, self.dims)
        self.diag = float(np.linalg.norm(ext)) + c
        #: the centre of the vertices' bounding box: every point of the mesh lies within
        #: diag / 2 of it
        self.centre = 0.5 * (lo + hi)

    def min_d2(self, p, q, reach, stop_below=-1.0):
        return _min_d2(self.v, self.f, self.lo, self.c, self.dims, self.start, self.tris,
                       p, q, float(reach), float(stop_below))

    def distance(self, p, q) -> float:
        """Exact distance from segment p-q to the mesh (an expanding search)."""
        reach = self.c
        # once the reach passes this, every triangle lies within it (from p, the centre, then
        # half the diagonal): the search has seen them all
        whole = float(np.linalg.norm(p - self.centre)) + self.diag
        while True:
            d2 = self.min_d2(p, q, reach)
            if d2 <= reach * reach or reach > whole:
                return math.sqrt(d2)
            reach *= 2.0


class GridMeshes:
    """Exact capsule queries against a list of meshes (mm, scene frame); the interface of
    :class:`ctrplan.collision._fcl.FclMeshes`."""

    def __init__(self, meshes):
        self.objects = [_MeshGrid(m) for m in meshes]

    def first_hit(self, a: np.ndarray, b: np.ndarray, r: np.ndarray,
                  pairs: np.ndarray | None = None) -> int:
        """Index of the first mesh any capsule (K, ...) touches, or -1. pairs : (K,) bit masks
        (bit j of pairs[k]: check capsule k against mesh j)."""
        a = np.ascontiguousarray(a, dtype=np.float64)
        b = np.ascontiguousarray(b, dtype=np.float64)
        for j, g in enumerate(self.objects):
            for k in range(len(r)):
                if pairs is not None and not (int(pairs[k]) >> j) & 1:
                    continue
                rk = float(r[k])
                if g.min_d2(a[k], b[k], rk, rk * rk) <= rk * rk:
                    return j
        return -1

    def distance(self, a: np.ndarray, b: np.ndarray, r: np.ndarray) -> tuple[float, int]:
        """(smallest capsule-surface distance to any mesh, that mesh); -1 on overlap (as FCL)."""
        best, which = np.inf, -1
        for j in range(len(self.objects)):
            for k in range(len(r)):
                d = self.pair_distance(a[k], b[k], float(r[k]), j)
                if d < best:
                    best, which = d, j
        return float(best), which

    def pair_distance(self, a: np.ndarray, b: np.ndarray, r: float, j: int) -> float:
        """Distance from one capsule (axis a -> b (3,), radius r) to mesh j; -1 on overlap."""
        d = self.objects[j].distance(np.ascontiguousarray(a, dtype=np.float64),
                                     np.ascontiguousarray(b, dtype=np.float64)) - float(r)
        return -1.0 if d <= 0.0 else float(d)
