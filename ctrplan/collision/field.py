"""Conservative distance fields: the prefilter in front of exact FCL.

For each mesh, a regular grid (spacing ``h``) stores two bounds on the unsigned distance ``d``
from each grid node to the mesh surface. The surface is sampled by the vertices of the mesh
subdivided until no edge is longer than ``e`` (every point of a triangle with edges <= ``e`` lies
within ``rho = e / sqrt(3)`` of a corner: the circumradius of an acute triangle, half the longest
edge otherwise). Each sample marks its nearest grid node; scipy's exact Euclidean distance
transform (``ndimage.distance_transform_edt``, a second or two for millions of nodes) then gives
every node ``g`` its nearest marked node ``n`` at distance ``D``:

- ``ub = |g - s|`` for the sample ``s`` held by ``n``: a true surface point, so ``d <= ub``;
- ``lb = D - rho - h sqrt(3) / 2``: the surface point nearest to ``g`` has a sample within
  ``rho`` whose node is within ``h sqrt(3) / 2`` of it, so ``D <= d + rho + h sqrt(3) / 2``.

Within ``refine_mm`` of the surface (where verdicts are decided) both are tightened to the
exact distance ``ds`` to the nearest sample: ``ds - rho <= d <= ds``.

``d`` is 1-Lipschitz, so at any point ``x`` in a grid cell with corners ``c``:
``max_c (lb_c - |x - c|) <= d(x) <= min_c (ub_c + |x - c|)``. No interpolation error is hidden:
the bounds are exact consequences of the stored numbers. Outside the grid (which covers the
mesh's bounding box plus the band) the distance to the bounding box is a lower bound.

A capsule (segment, radius r) is provably free of a mesh when, at samples along its axis spaced
``delta`` apart, ``lb(sample) > r + delta / 2`` (every axis point is within ``delta / 2`` of a
sample); it provably touches it when ``ub(p) < r`` at some axis point. For a closed mesh the
grid also stores which side (inside/outside) nodes far from the surface lie on; a capsule chain
that starts inside a closed wall (or outside a closed obstacle) and has an axis point proven to
lie outside it (inside the obstacle) must cross the surface, so it provably collides.
Anything else goes to the exact second stage (:mod:`ctrplan.collision._exact`) and, for its
ties, to FCL.

Fields are cached on disk, verified on load (:mod:`ctrplan.collision.field_cache`).
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass

import numba as nb
import numpy as np

from ctrplan.collision.sampling import TRI_CHUNK, surface_samples  # noqa: F401 (re-exported)

log = logging.getLogger("ctrplan")

FIELD_VERSION = 5
#: Safety added to every decision threshold (mm): covers float32 storage and FCL's tolerance.
EPS_MM = 1e-3


@dataclass(frozen=True)
class FieldConfig:
    """Distance-field parameters.

    h_mm : grid spacing (mm), raised if the grid would exceed ``max_nodes``.
    band_mm : padding of the grid around the mesh's bounding box (mm); beyond it the distance
        to the bounding box is used.
    max_nodes : largest grid (nodes).
    sample_mm : largest spacing of the samples along capsule axes.
    refine_mm : nodes nearer the surface than this get exact distances to the samples.
    """

    h_mm: float = 0.5
    band_mm: float = 6.0
    max_nodes: int = 8_000_000
    sample_mm: float = 1.0
    refine_mm: float = 4.0


@dataclass(frozen=True)
class DistanceField:
    """Lower/upper bounds of the unsigned distance to one mesh on a grid (mm, scene frame)."""

    origin: np.ndarray      # (3,) position of node (0, 0, 0)
    h: float                # grid spacing
    lb: np.ndarray          # (nx, ny, nz) float32 lower bounds
    ub: np.ndarray          # (nx, ny, nz) float32 upper bounds (inf beyond the band)
    box_lo: np.ndarray      # (3,) mesh bounding box
    box_hi: np.ndarray
    rho: float              # covering radius of the subdivided vertices
    side: np.ndarray        # (nx, ny, nz) int8: +1 outside, -1 inside, 0 unknown (closed meshes)
    watertight: bool        # whether side holds any information
    build_s: float = 0.0    # seconds it took to build (0 when read from the cache)


def build_field(vertices: np.ndarray, faces: np.ndarray, config: FieldConfig = FieldConfig(),
                watertight: bool = False, progress: bool = False) -> DistanceField:
    """Build the bounds grid of one mesh (see the module docstring). ``progress``: a bar over
    the build's stages on a terminal."""
    from scipy import ndimage

    from ctrplan.progress import bar

    with bar(total=5, desc="distance field", disable=not progress) as pbar:
        return _build_field(vertices, faces, config, watertight, pbar, ndimage)


def _build_field(vertices, faces, config, watertight, pbar, ndimage) -> DistanceField:
    t0 = time.perf_counter()
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces, dtype=np.int64)
    box_lo, box_hi = v.min(axis=0), v.max(axis=0)
    pad = config.band_mm + 1.0
    lo, hi = box_lo - pad, box_hi + pad
    ext = hi - lo
    h = max(config.h_mm, float(np.prod(ext) / config.max_nodes) ** (1 / 3))
    shape = tuple(int(math.ceil(e / h)) + 1 for e in ext)
    # surface samples covering every triangle within rho (cost ~ area, see surface_samples)
    sv, e_max = surface_samples(v, f, h / 2.0)
    rho = e_max / math.sqrt(3.0)
    pbar.update(1)
    # mark the grid node nearest to each sample; keep one sample per marked node
    node = np.clip(np.rint((sv - lo) / h).astype(np.int64), 0, np.array(shape) - 1)
    flat = np.ravel_multi_index(node.T, shape)
    marked, first = np.unique(flat, return_index=True)
    rep = sv[first]
    grid = np.ones(shape, dtype=bool)
    grid.flat[marked] = False
    del node, flat
    # exact Euclidean distance transform: for every node, the nearest marked node
    dist, idx = ndimage.distance_transform_edt(grid, sampling=h, return_indices=True)
    del grid
    pbar.update(1)
    # upper bound: distance to a true surface point (the sample held by the nearest marked
    # node); computed in chunks of nodes so memory stays O(chunk)
    ub = _upper_bounds(idx.reshape(3, -1), shape, h, lo, marked, rep)
    del idx, marked, rep
    # lower bound: the nearest surface point x has a sample within rho, whose node is within
    # h*sqrt(3)/2 of it, so dist <= d + rho + h*sqrt(3)/2
    lb = np.maximum(dist - rho - h * math.sqrt(3.0) / 2.0, 0.0).astype(np.float32)
    pbar.update(1)
    # Near the surface, where verdicts are decided, replace both bounds by the exact distance
    # to the nearest sample (lb then loses only rho, not the snapping term). A node within
    # refine_mm of a sample has a marked node within refine_mm + h sqrt(3)/2 (the sample's),
    # so only those nodes are asked for their nearest sample (a k-d tree over the samples).
    refine = refine_radius(config.refine_mm, len(sv), len(f), h)
    cand = np.flatnonzero(dist.ravel() <= refine + h * math.sqrt(3.0) / 2.0)
    del dist
    near = _nearest_sample(sv, cand, shape, h, lo, refine)
    pbar.update(1)
    band = near <= refine
    cand, near = cand[band], near[band]
    lbf, ubf = lb.reshape(-1), ub.reshape(-1)
    lbf[cand] = np.maximum(lbf[cand], np.maximum(near - rho, 0.0))
    ubf[cand] = np.minimum(ubf[cand], near)
    del near, band, cand
    side = _sides(lb, h, lo, v, f) if watertight else np.zeros(shape, dtype=np.int8)
    pbar.update(1)
    field = DistanceField(origin=lo, h=float(h), lb=lb, ub=ub, box_lo=box_lo, box_hi=box_hi,
                          rho=rho, side=side, watertight=watertight,
                          build_s=time.perf_counter() - t0)
    log.debug("distance field: %s nodes, h %.3f mm, %d samples, rho %.3f mm, refined within "
              "%.2f mm, %.2f s", shape, h, len(sv), rho, refine, field.build_s)
    return field


#: Nodes per chunk of the bounds computation.
NODE_CHUNK = 1 << 20
#: Meshes above this many triangles (large: a fine segmentation; every shipped mesh has fewer
#: than 50,000) get a refinement radius capped by REFINE_WORK.
LARGE_TRIANGLES = 250_000
#: Largest refinement work, samples x (radius / h)^3 (about 25 s on one core of the reference
#: machine; the shipped brain surface needs 1.4e8 at 4 mm).
REFINE_WORK = 1.5e8


def refine_radius(refine_mm: float, samples: int, triangles: int, h: float) -> float:
    """The refinement radius: ``refine_mm``, except for a mesh of more than LARGE_TRIANGLES
    triangles, where it shrinks so that samples x (radius / h)^3 stays within REFINE_WORK (the
    nearest-sample search costs in proportion; 2.5 million samples at h 0.5 mm give 1.8 mm).
    Bounds stay valid either way: only nodes within the radius are tightened."""
    if triangles <= LARGE_TRIANGLES or samples == 0:
        return float(refine_mm)
    return float(min(refine_mm, h * (REFINE_WORK / samples) ** (1.0 / 3.0)))


def _upper_bounds(idx: np.ndarray, shape: tuple, h: float, lo: np.ndarray, marked: np.ndarray,
                  rep: np.ndarray) -> np.ndarray:
    """(shape) float32: distance from every node to the sample held by its nearest marked node
    (``idx`` (3, N): the distance transform's nearest-node indices)."""
    n = int(np.prod(shape))
    ub = np.empty(n, dtype=np.float32)
    for s in range(0, n, NODE_CHUNK):
        e = min(s + NODE_CHUNK, n)
        held = rep[np.searchsorted(marked, np.ravel_multi_index(idx[:, s:e], shape))]
        nodes = np.stack(np.unravel_index(np.arange(s, e), shape), axis=1) * h + lo
        ub[s:e] = np.linalg.norm(nodes - held, axis=1)
    return ub.reshape(shape)


def _nearest_sample(samples: np.ndarray, flat: np.ndarray, shape: tuple, h: float,
                    lo: np.ndarray, radius: float) -> np.ndarray:
    """(len(flat),) distance from each node (flat indices) to its nearest sample, inf where
    none lies within ``radius``."""
    from scipy.spatial import cKDTree

    out = np.full(len(flat), np.inf)
    if len(flat) == 0 or len(samples) == 0:
        return out
    tree = cKDTree(samples, leafsize=16, balanced_tree=False, compact_nodes=False)
    for s in range(0, len(flat), NODE_CHUNK):
        nodes = np.stack(np.unravel_index(flat[s:s + NODE_CHUNK], shape), axis=1) * h + lo
        d, _ = tree.query(nodes, k=1, distance_upper_bound=radius * (1.0 + 1e-12), workers=1)
        out[s:s + NODE_CHUNK] = d
    return out


def _sides(lb: np.ndarray, h: float, lo: np.ndarray, v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """Inside/outside of a closed mesh at the grid nodes far enough from it to be sure.

    Two face-adjacent nodes with ``lb > h / 2`` are joined by a segment that no surface point
    comes near (each half lies in a surface-free ball), so the connected components of such
    nodes (6-connectivity) each lie on one side. A component touching the grid's border is
    outside (the border is outside the mesh's bounding box); every other component takes the
    side of one of its nodes by ray parity (:func:`ctrplan.collision._raycast.odd_parity`: exact
    for a closed surface, memory only the mesh).
    """
    from scipy import ndimage

    from ctrplan.collision._raycast import odd_parity

    safe = lb > h / 2.0
    labels, n = ndimage.label(safe)
    side_of = np.zeros(n + 1, dtype=np.int8)
    border = np.unique(np.concatenate([labels[[0, -1], :, :].ravel(), labels[:, [0, -1], :].ravel(),
                                       labels[:, :, [0, -1]].ravel()]))
    side_of[border] = 1
    rest = np.setdiff1d(np.arange(1, n + 1), border)
    if len(rest):
        # one node per component: the first in raster order
        flat = labels.ravel()
        order = np.argsort(flat, kind="stable")
        starts = np.searchsorted(flat[order], rest)
        reps = np.stack(np.unravel_index(order[starts], labels.shape), axis=1) * h + lo
        side_of[rest] = np.where(odd_parity(v, f, reps), -1, 1)
    side_of[0] = 0
    return side_of[labels]


@nb.njit(cache=True, fastmath=False)
def _bounds_at(lb, ub, side, origin, h, box_lo, box_hi, x, y, z):
    """(lower bound, upper bound, side) of the distance at one point; side is +1 (outside),
    -1 (inside) or 0 (unknown): a corner c with a known side whose surface-free ball
    (radius lb_c) contains the point passes its side on."""
    nx, ny, nz = lb.shape
    fx = (x - origin[0]) / h
    fy = (y - origin[1]) / h
    fz = (z - origin[2]) / h
    i = int(math.floor(fx))
    j = int(math.floor(fy))
    k = int(math.floor(fz))
    if i < 0 or j < 0 or k < 0 or i >= nx - 1 or j >= ny - 1 or k >= nz - 1:
        dx = max(box_lo[0] - x, 0.0, x - box_hi[0])
        dy = max(box_lo[1] - y, 0.0, y - box_hi[1])
        dz = max(box_lo[2] - z, 0.0, z - box_hi[2])
        # outside the grid is outside the bounding box, hence outside the mesh
        return math.sqrt(dx * dx + dy * dy + dz * dz), np.inf, 1
    lo_b = -np.inf
    up_b = np.inf
    sd = 0
    for di in range(2):
        cx = origin[0] + (i + di) * h - x
        for dj in range(2):
            cy = origin[1] + (j + dj) * h - y
            for dk in range(2):
                cz = origin[2] + (k + dk) * h - z
                dist = math.sqrt(cx * cx + cy * cy + cz * cz)
                lc = lb[i + di, j + dj, k + dk]
                lv = lc - dist
                uv = ub[i + di, j + dj, k + dk] + dist
                if lv > lo_b:
                    lo_b = lv
                if uv < up_b:
                    up_b = uv
                if lv > 0.0 and side[i + di, j + dj, k + dk] != 0:
                    sd = side[i + di, j + dj, k + dk]
    return lo_b, up_b, sd


@nb.njit(cache=True)
def _nearest_bound(lb, side, origin, h, x, y, z):
    """(lower bound, side) of the distance at one point from its nearest grid node only
    (side 0 unless the node's surface-free ball contains the point). Outside the grid: (-inf, 0)
    (the caller then takes the full :func:`_bounds_at`)."""
    nx, ny, nz = lb.shape
    i = int(math.floor((x - origin[0]) / h + 0.5))
    j = int(math.floor((y - origin[1]) / h + 0.5))
    k = int(math.floor((z - origin[2]) / h + 0.5))
    if i < 0 or j < 0 or k < 0 or i >= nx or j >= ny or k >= nz:
        return -np.inf, 0
    cx = origin[0] + i * h - x
    cy = origin[1] + j * h - y
    cz = origin[2] + k * h - z
    lv = lb[i, j, k] - math.sqrt(cx * cx + cy * cy + cz * cz)
    return lv, side[i, j, k] if lv > 0.0 else 0


# Compiled without numba's reference counting (as the mechanics kernels' steppers, see
# ctrplan/shape/_ode.py): it allocates nothing and returns scalars only, and without it every
# sample's lookups would count references to the six grid arrays (measured on 2,000 x 19
# capsules against a sphere's field: inlined with counting, the split ran 1.1-1.4x slower than
# the walk written inside _capsule_bounds; compiled so, 1.5-2x faster).
@nb.njit(cache=True, _nrt=False)
def _walk_axis(ax, ay, az, vx, vy, vz, rk, lb, ub, side, bad_side, origin, h, box_lo, box_hi,
               sample_mm, min_step, eps, trace, clear, depth):
    """Walk one capsule axis from (ax, ay, az) along (vx, vy, vz) (mm), radius rk, updating
    the configuration's ``clear`` and ``depth`` bounds (see :func:`_capsule_bounds`).
    Returns (clear, depth, unsure: the axis was not proven free, done: depth > eps was
    proven, the configuration collides)."""
    seg = math.sqrt(vx * vx + vy * vy + vz * vz)
    inv = 1.0 / seg if seg > 0.0 else 0.0
    n = max(int(math.ceil(seg / sample_mm)) + 1, 2)     # a zero-length axis is one point
    delta = seg / (n - 1)
    half = 0.5 * delta
    unsure = False
    done = False
    pos = 0.0
    while True:
        t = pos * inv
        px = ax + t * vx
        py = ay + t * vy
        pz = az + t * vz
        if trace:
            # cheap first look: the nearest grid node alone (one lookup, not eight)
            q_lo, q_sd = _nearest_bound(lb, side, origin, h, px, py, pz)
            q_slack = q_lo - rk - eps
            if q_slack >= min_step and (bad_side == 0 or q_sd != bad_side):
                if q_slack < clear:
                    clear = q_slack
                if pos + q_slack >= seg:
                    break       # the sample's free ball reaches the end of the axis
                pos += q_slack
                continue
        lo_b, up_b, sd = _bounds_at(lb, ub, side, origin, h, box_lo, box_hi, px, py, pz)
        d = rk - up_b
        if bad_side != 0 and sd == bad_side:
            d = max(d, lo_b + rk)
        if d > depth:
            depth = d
        if depth > eps:
            done = True
            break
        if trace:
            slack = lo_b - rk - eps
            if slack < min_step:
                unsure = True
                step = delta
            else:
                step = slack
                if pos + slack >= seg:
                    if slack < clear:
                        clear = slack
                    break       # the sample's free ball reaches the end of the axis
            if slack < clear:
                clear = slack
        else:
            c = lo_b - rk - half
            if c < clear:
                clear = c
            if c <= eps:
                unsure = True
            step = delta
        if pos >= seg:
            break
        pos = min(pos + step, seg) if step > 0.0 else seg
    return clear, depth, unsure, done


@nb.njit(cache=True, _nrt=False)
def _box_gap(ax, ay, az, bx, by, bz, box_lo, box_hi):
    """Distance (mm) between the bounding box of segment a-b and the box box_lo..box_hi: a
    lower bound of the distance from any point of the segment to anything in the box."""
    dx = max(box_lo[0] - max(ax, bx), 0.0, min(ax, bx) - box_hi[0])
    dy = max(box_lo[1] - max(ay, by), 0.0, min(ay, by) - box_hi[1])
    dz = max(box_lo[2] - max(az, bz), 0.0, min(az, bz) - box_hi[2])
    return math.sqrt(dx * dx + dy * dy + dz * dz)


@nb.njit(cache=True)
def _capsule_bounds(a, b, r, active, lb, ub, side, bad_side, origin, h, box_lo, box_hi,
                    sample_mm, eps, trace, bit, clear_out, depth_out, unsure_out):
    """Bounds of every active configuration against one mesh.

    Walks each capsule axis (:func:`_walk_axis`). With ``trace`` False, samples are
    ``delta <= sample_mm`` apart and
    clear_out gets the lower bound of the clearance (min of lb - r - delta / 2). With ``trace``
    True (verdicts only) it sphere-traces: a sample with slack ``lb - r - eps`` proves the
    axis free for that distance on both sides, so the walk jumps ahead by the slack (clear_out
    is then only a verdict: > eps proven free). A capsule whose axis it cannot prove free gets
    ``bit`` set in unsure_out (B, K) (only those capsule-mesh pairs go to FCL).
    depth_out = lower bound of the penetration depth: max of r - ub over the samples, and
    lb + r at a sample proven to lie on ``bad_side`` (+1: outside a wall the robot starts
    inside; -1: inside an obstacle; 0: no side information). A configuration stops at its
    first proof of collision (depth > eps)."""
    B, K = r.shape
    min_step = 0.05 * sample_mm
    for bi in range(B):
        if not active[bi]:
            continue
        clear = clear_out[bi]
        depth = depth_out[bi]
        for k2 in range(K):
            # verdicts walk tip first: the distal capsules meet the walls first, and a proof
            # of collision ends the configuration's walk
            kk = K - 1 - k2 if trace else k2
            ax = a[bi, kk, 0]
            ay = a[bi, kk, 1]
            az = a[bi, kk, 2]
            if trace:
                # a capsule whose axis box is farther from the mesh's box than its radius
                # (with the walk's least step to spare) is free of the mesh: no walk
                gap = _box_gap(ax, ay, az, b[bi, kk, 0], b[bi, kk, 1], b[bi, kk, 2], box_lo,
                               box_hi) - r[bi, kk] - eps
                if gap >= min_step:
                    if gap < clear:
                        clear = gap
                    continue
            clear, depth, unsure, done = _walk_axis(
                ax, ay, az, b[bi, kk, 0] - ax, b[bi, kk, 1] - ay, b[bi, kk, 2] - az, r[bi, kk],
                lb, ub, side, bad_side, origin, h, box_lo, box_hi, sample_mm, min_step, eps, trace,
                clear, depth)
            if done:
                break
            if unsure:
                unsure_out[bi, kk] |= bit
        clear_out[bi] = clear
        depth_out[bi] = depth


def rows_finite(a: np.ndarray, b: np.ndarray, r: np.ndarray) -> np.ndarray:
    """(B,) bool: whether every end (a, b (B, K, 3)) and radius (r (B, K)) of a row is finite."""
    return (np.isfinite(a).all(axis=(1, 2)) & np.isfinite(b).all(axis=(1, 2))
            & np.isfinite(r).all(axis=1))


def capsule_bounds(field: DistanceField, a: np.ndarray, b: np.ndarray, r: np.ndarray,
                   active: np.ndarray, clear: np.ndarray, depth: np.ndarray, sample_mm: float,
                   bad_side: int = 0, trace: bool = False, unsure: np.ndarray | None = None,
                   bit: int = 1, finite: np.ndarray | None = None) -> None:
    """Update ``clear`` (B,), ``depth`` (B,) and ``unsure`` (B, K) uint64 bit masks in place
    for the ``active`` configurations (see :func:`_capsule_bounds`).

    a, b : (B, K, 3) capsule axis ends, mm, scene frame; r : (B, K) radii, mm. bad_side : the
    side of a closed mesh whose points prove a collision. finite : (B,) bool, whether each
    row's ends and radii are all finite, when the caller knows it (one check for many meshes).
    """
    if unsure is None:
        unsure = np.zeros(r.shape, dtype=np.uint64)
    # A capsule with a non-finite end or radius (a model that produced NaN) would walk its
    # segment for ever (no step reaches a NaN length): such a row is a proven collision
    # (depth +inf, clearance -inf), never free, and the walk skips it.
    if finite is None:
        finite = rows_finite(a, b, r)
    if not finite.all():
        bad = np.asarray(active, dtype=bool) & ~finite
        clear[bad] = -np.inf
        depth[bad] = np.inf
        active = np.ascontiguousarray(np.asarray(active, dtype=bool) & finite)
    _capsule_bounds(a, b, r, active, field.lb, field.ub, field.side,
                    int(bad_side) if field.watertight else 0, field.origin, field.h, field.box_lo,
                    field.box_hi, float(sample_mm), EPS_MM, bool(trace), np.uint64(bit), clear,
                    depth, unsure)


@nb.njit(cache=True)
def _point_bounds(p, lb, ub, side, origin, h, box_lo, box_hi, lo_out, up_out, side_out):
    for i in range(p.shape[0]):
        lo_out[i], up_out[i], side_out[i] = _bounds_at(lb, ub, side, origin, h, box_lo, box_hi,
                                                       p[i, 0], p[i, 1], p[i, 2])


def point_bounds(field: DistanceField, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(lower bound, upper bound, side) of the distance from points (P, 3) mm to the mesh."""
    p = np.ascontiguousarray(np.asarray(points, dtype=float).reshape(-1, 3))
    lo = np.empty(len(p))
    up = np.empty(len(p))
    sd = np.empty(len(p), dtype=np.int8)
    _point_bounds(p, field.lb, field.ub, field.side, field.origin, field.h, field.box_lo,
                  field.box_hi, lo, up, sd)
    return lo, up, sd

