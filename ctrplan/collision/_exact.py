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
non-finite end or radius, or one beyond ``FAR_MM``, is never decided here. Collision
checking never reports free when unsure: the stage only removes work from FCL, never a
verdict from it. Not thread-safe (per-mesh stamps of the triangles measured), as the FCL
models beside it.
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from ctrplan.collision._grid import _point_tri_d2, _seg_seg_d2, cell_of

#: Half-width (mm) of the band around contact (|d - r| <= TIE_MM) left to FCL: 100x the
#: largest disagreement of FCL with the exact distance measured on random near-contact
#: capsules (1e-6 mm), and far above the rounding of the closed form (~1e-12 mm).
TIE_MM = 1e-4
#: Capsules with a coordinate or radius this large (mm) or not finite are left to FCL (their
#: products would lose the precision TIE_MM needs, or overflow).
FAR_MM = 1e6
#: verdicts of :meth:`ExactStage.decide` (HIT: of one mesh, in the kernels)
FREE, UNSURE, HIT = -1, -2, 0


@nb.njit(cache=True, _nrt=False)
def seg_tri_d2(px, py, pz, qx, qy, qz, ax, ay, az, bx, by, bz, cx, cy, cz, above):
    """Squared distance between segment p-q and triangle abc (scalars, mm) where it is at
    most ``above``; where it is larger, some value larger than ``above`` (a lower bound when
    one is found first: the squared distance to the triangle's plane, or to the half-space
    beyond one of its edges, when that already is farther)."""
    e1x, e1y, e1z = bx - ax, by - ay, bz - az
    e2x, e2y, e2z = cx - ax, cy - ay, cz - az
    nx = e1y * e2z - e1z * e2y
    ny = e1z * e2x - e1x * e2z
    nz = e1x * e2y - e1y * e2x
    sp = nx * (px - ax) + ny * (py - ay) + nz * (pz - az)
    sq = nx * (qx - ax) + ny * (qy - ay) + nz * (qz - az)
    # separations by more than ``above`` count only in a triangle whose angles are not within
    # 1e-6 of flat, with 1e-7 mm spare (the normal's rounding cannot move them that much)
    n2 = nx * nx + ny * ny + nz * nz
    e12 = (e1x * e1x + e1y * e1y + e1z * e1z) * (e2x * e2x + e2y * e2y + e2z * e2z)
    sharp = n2 > 1e-12 * e12 and above < np.inf
    lim = math.sqrt(above) + 1e-7 if sharp else 0.0
    if (sp > 0.0 and sq > 0.0) or (sp < 0.0 and sq < 0.0):
        s2 = min(sp * sp, sq * sq)
        if sharp and s2 > lim * lim * n2:
            return s2 / n2                  # the plane is farther
    elif sp != sq:
        t = sp / (sp - sq)
        xx, xy, xz = px + t * (qx - px), py + t * (qy - py), pz + t * (qz - pz)
        if (_side(ax, ay, az, bx, by, bz, xx, xy, xz, nx, ny, nz) >= 0.0
                and _side(bx, by, bz, cx, cy, cz, xx, xy, xz, nx, ny, nz) >= 0.0
                and _side(cx, cy, cz, ax, ay, az, xx, xy, xz, nx, ny, nz) >= 0.0):
            return 0.0
    if sharp:
        # the segment beyond an edge's outer half-space boundary (in-plane normal n x edge)
        lb = max(_beyond(ax, ay, az, bx, by, bz, px, py, pz, qx, qy, qz, nx, ny, nz, n2, lim),
                 _beyond(bx, by, bz, cx, cy, cz, px, py, pz, qx, qy, qz, nx, ny, nz, n2, lim),
                 _beyond(cx, cy, cz, ax, ay, az, px, py, pz, qx, qy, qz, nx, ny, nz, n2, lim))
        if lb > 0.0:
            return lb
    d = _point_tri_d2(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz)
    d = min(d, _point_tri_d2(qx, qy, qz, ax, ay, az, bx, by, bz, cx, cy, cz))
    d = min(d, _seg_seg_d2(px, py, pz, qx, qy, qz, ax, ay, az, bx, by, bz))
    d = min(d, _seg_seg_d2(px, py, pz, qx, qy, qz, bx, by, bz, cx, cy, cz))
    return min(d, _seg_seg_d2(px, py, pz, qx, qy, qz, cx, cy, cz, ax, ay, az))


@nb.njit(cache=True, _nrt=False, inline="always")
def _beyond(ux, uy, uz, vx, vy, vz, px, py, pz, qx, qy, qz, nx, ny, nz, n2, lim):
    """Squared distance from segment p-q to the half-space on the triangle's side of edge
    u -> v (normal n, |n|^2 = n2) when it is farther than ``lim``, else 0."""
    w = max(_side(ux, uy, uz, vx, vy, vz, px, py, pz, nx, ny, nz),
            _side(ux, uy, uz, vx, vy, vz, qx, qy, qz, nx, ny, nz))
    if w >= 0.0:
        return 0.0
    scale = n2 * ((vx - ux) ** 2 + (vy - uy) ** 2 + (vz - uz) ** 2)
    return w * w / scale if w * w > lim * lim * scale else 0.0


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
def _pair_d2(px, py, pz, qx, qy, qz, reach, stop, V, F, S, start, tris, lox, loy, loz, c,
             nx, ny, nz, seen, tick):
    """Least squared distance from segment p-q to the triangles of one mesh where it is at
    most ``reach`` squared (else a value above that: inf if no triangle can lie within
    ``reach``); returns early once below ``stop``. The mesh's grid: origin (lox, loy, loz),
    cell c, (nx, ny, nz) cells in ``start``. S (T, 4): each triangle's ball (centre, radius)
    or (0, 4) (then the balls are computed here). ``seen`` (T,) holds the ``tick`` of the
    last call that measured each triangle (one listed in several cells is measured once)."""
    xlo, xhi = min(px, qx) - reach, max(px, qx) + reach
    ylo, yhi = min(py, qy) - reach, max(py, qy) + reach
    zlo, zhi = min(pz, qz) - reach, max(pz, qz) + reach
    i0, i1 = max(cell_of(xlo, lox, c, nx), 0), min(cell_of(xhi, lox, c, nx), nx - 1)
    j0, j1 = max(cell_of(ylo, loy, c, ny), 0), min(cell_of(yhi, loy, c, ny), ny - 1)
    k0, k1 = max(cell_of(zlo, loz, c, nz), 0), min(cell_of(zhi, loz, c, nz), nz - 1)
    half = 0.5 * c * math.sqrt(3.0)
    lim = (reach + half) * (reach + half)
    best = np.inf
    above = reach * reach
    balls = S.shape[0] > 0
    for i in range(i0, i1 + 1):
        ccx = lox + (i + 0.5) * c
        for j in range(j0, j1 + 1):
            ccy = loy + (j + 0.5) * c
            for k in range(k0, k1 + 1):
                cell = (i * ny + j) * nz + k
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
                    if balls:
                        e = reach + S[t, 3]
                        if _seg_seg_d2(S[t, 0], S[t, 1], S[t, 2], S[t, 0], S[t, 1], S[t, 2],
                                       px, py, pz, qx, qy, qz) > e * e:
                            continue
                    a, b, cc = F[t, 0], F[t, 1], F[t, 2]
                    if not balls and _far(px, py, pz, qx, qy, qz, V[a, 0], V[a, 1], V[a, 2],
                                          V[b, 0], V[b, 1], V[b, 2], V[cc, 0], V[cc, 1],
                                          V[cc, 2], reach):
                        continue
                    d = seg_tri_d2(px, py, pz, qx, qy, qz, V[a, 0], V[a, 1], V[a, 2],
                                   V[b, 0], V[b, 1], V[b, 2], V[cc, 0], V[cc, 1], V[cc, 2],
                                   min(best, above))
                    if d < best:
                        best = d
                        if best < stop:
                            return best
    return best


@nb.njit(cache=True, _nrt=False, inline="always")
def _within_far(px, py, pz, qx, qy, qz, r):
    """Whether every coordinate and the radius is finite and below FAR_MM in magnitude (each
    compared on its own: a max() over them may pass a NaN by, as NaN compares false)."""
    return (abs(px) < FAR_MM and abs(py) < FAR_MM and abs(pz) < FAR_MM and abs(qx) < FAR_MM
            and abs(qy) < FAR_MM and abs(qz) < FAR_MM and abs(r) < FAR_MM)


@nb.njit(cache=True, _nrt=False)
def _decide_mesh(a, b, r, rows, unsure, bit, V, F, S, start, tris, lo, c, dims, tie, seen,
                 ticks, out):
    """out[n] for configuration rows[n] against one mesh: HIT if one of its pairs marked by
    ``bit`` in unsure[i, k] touches the mesh, FREE if every such pair is free, UNSURE if
    none touches and one is a tie, not finite or beyond FAR_MM. ``seen`` and ``ticks[0]``
    (the last tick used): see :func:`_pair_d2`."""
    K = r.shape[1]
    for n in range(rows.shape[0]):
        i = rows[n]
        res = FREE
        for k2 in range(K):
            k = K - 1 - k2          # tip first, where the walls are met first
            if unsure[i, k] & bit == 0:
                continue
            rk = r[i, k]
            px, py, pz = a[i, k, 0], a[i, k, 1], a[i, k, 2]
            qx, qy, qz = b[i, k, 0], b[i, k, 1], b[i, k, 2]
            if not _within_far(px, py, pz, qx, qy, qz, rk):
                res = UNSURE        # not finite, or beyond what the closed form resolves
                continue
            reach = rk + tie
            stop = (rk - tie) * (rk - tie) if rk > tie else -1.0
            ticks[0] += 1
            d2 = _pair_d2(px, py, pz, qx, qy, qz, reach, stop, V, F, S, start, tris, lo[0],
                          lo[1], lo[2], c, dims[0], dims[1], dims[2], seen, ticks[0])
            if d2 < stop:
                res = HIT
                break
            if d2 <= reach * reach:
                res = UNSURE
        out[n] = res


#: Meshes up to this many triangles keep each triangle's ball (32 bytes a triangle); larger
#: ones (the grid backend's) compute them as they go.
BALLS_UP_TO = 1_000_000


class _Mesh:
    """One mesh's arrays for the stage: its grid of triangle lists (shared, not copied), the
    triangles' balls and the measured-triangle stamps."""

    def __init__(self, grid):
        self.g = grid
        v, f = grid.v, grid.f
        if len(f) <= BALLS_UP_TO:
            tri = v[f]                                              # (T, 3, 3)
            centre = tri.mean(axis=1)
            rad = np.sqrt(((tri - centre[:, None]) ** 2).sum(axis=2).max(axis=1))
            # rounding of the centre and radius: a micrometre's spare (the ball only skips)
            self.S = np.ascontiguousarray(np.column_stack([centre, rad * (1 + 1e-9) + 1e-6]))
        else:
            self.S = np.zeros((0, 4))
        self.seen = np.zeros(len(f), dtype=np.int64)
        self.lo = np.asarray(grid.lo, dtype=np.float64)
        self.dims = np.asarray(grid.dims, dtype=np.int64)


class ExactStage:
    """The second stage over a list of meshes (mm, scene frame).

    grids : the meshes' :class:`ctrplan.collision._grid._MeshGrid` objects (reused from the
    grid backend where the world has one)."""

    def __init__(self, grids):
        self.meshes = [_Mesh(g) for g in grids]
        if len(self.meshes) > 64:
            raise ValueError("at most 64 meshes (one bit each in the prefilter's masks)")
        self._ticks = np.zeros(1, dtype=np.int64)

    @classmethod
    def from_meshes(cls, meshes) -> ExactStage:
        from ctrplan.collision._grid import _MeshGrid

        return cls([_MeshGrid(m) for m in meshes])

    def decide(self, a: np.ndarray, b: np.ndarray, r: np.ndarray, rows: np.ndarray,
               unsure: np.ndarray) -> np.ndarray:
        """(len(rows),) int: per configuration ``rows`` of the batch (a, b (B, K, 3) mm,
        r (B, K) mm), the first mesh (in mesh order, as FCL's first hit) touched by a pair
        marked in ``unsure`` (B, K) uint64 (bit j: mesh j), FREE (-1) if none is, or UNSURE
        (-2, for FCL) where a pair of the first mesh not proven free is a tie."""
        a = np.ascontiguousarray(a, dtype=np.float64)
        b = np.ascontiguousarray(b, dtype=np.float64)
        r = np.ascontiguousarray(r, dtype=np.float64)
        unsure = np.ascontiguousarray(unsure, dtype=np.uint64)
        res = np.full(len(rows), FREE, dtype=np.int64)
        for j, m in enumerate(self.meshes):
            pending = np.flatnonzero(res == FREE)
            if len(pending) == 0:
                break
            out = np.empty(len(pending), dtype=np.int64)
            _decide_mesh(a, b, r, np.ascontiguousarray(rows[pending], dtype=np.int64), unsure,
                         np.uint64(1 << j), m.g.v, m.g.f, m.S, m.g.start, m.g.tris, m.lo,
                         float(m.g.c), m.dims, TIE_MM, m.seen, self._ticks, out)
            res[pending[out == HIT]] = j
            res[pending[out == UNSURE]] = UNSURE
        return res

    def pair_distance(self, a: np.ndarray, b: np.ndarray, r: float, j: int,
                      lower: float = 0.0, limit: float = np.inf) -> float:
        """Distance (mm) from the capsule (axis a -> b (3,), radius r) to mesh j's triangles,
        -1 where they overlap (FCL's convention), NaN where this cannot say (a non-finite end
        or radius, or one beyond FAR_MM: ask FCL). Where the distance is at least ``limit``, it
        may return a lower bound that is itself at least ``limit``. ``lower``: a known lower
        bound of the distance (the field's), where the search for triangles starts.

        The triangles within a reach of the axis are searched (:func:`_pair_d2`), the reach
        doubled until one is found or it passes ``limit``: the least segment-triangle distance
        found within the reach is the exact one (every nearer triangle lies within it too)."""
        px, py, pz = (float(v) for v in a)
        qx, qy, qz = (float(v) for v in b)
        r = float(r)
        if not _within_far(px, py, pz, qx, qy, qz, r):
            return math.nan
        m = self.meshes[j]
        c = float(m.g.c)
        extra = max(float(lower), 0.0) + 2.0 * c
        # beyond this reach every triangle of the mesh is within it (the search cannot go on)
        whole = math.dist((px, py, pz), m.g.centre) + m.g.diag
        while True:
            last = extra >= limit or extra >= whole
            span = min(extra, limit)
            reach = r + span
            self._ticks[0] += 1
            d2 = _pair_d2(px, py, pz, qx, qy, qz, reach, -1.0, m.g.v, m.g.f, m.S, m.g.start,
                          m.g.tris, m.lo[0], m.lo[1], m.lo[2], c, m.dims[0], m.dims[1], m.dims[2],
                          m.seen, self._ticks[0])
            if d2 <= reach * reach:
                d = math.sqrt(d2) - r
                return d if d >= 0.0 else -1.0
            if last:
                # farther than limit: a lower bound at least limit; else the whole mesh was
                # searched and has no triangle
                return span if span >= limit else math.inf
            extra *= 2.0

