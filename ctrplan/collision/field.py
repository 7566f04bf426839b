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

``d`` is 1-Lipschitz, so at any point ``x`` in a grid cell with corners ``c``:
``max_c (lb_c - |x - c|) <= d(x) <= min_c (ub_c + |x - c|)``. No interpolation error is hidden:
the bounds are exact consequences of the stored numbers. Outside the grid (which covers the
mesh's bounding box plus the band) the distance to the bounding box is a lower bound.

A capsule (segment, radius r) is provably free of a mesh when, at samples along its axis spaced
``delta`` apart, ``lb(sample) > r + delta / 2`` (every axis point is within ``delta / 2`` of a
sample); it provably touches it when ``ub(p) < r`` at some axis point. Anything else goes to FCL.

Fields are cached on disk (``$CTRPLAN_CACHE`` or ``~/.cache/ctrplan``), keyed by a hash of the
mesh and the field parameters.
"""

from __future__ import annotations

import hashlib
import logging
import math
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numba as nb
import numpy as np

log = logging.getLogger("ctrplan")

FIELD_VERSION = 1
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
    """

    h_mm: float = 0.5
    band_mm: float = 6.0
    max_nodes: int = 3_000_000
    sample_mm: float = 1.0


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
    build_s: float = 0.0    # seconds it took to build (0 when read from the cache)


def cache_dir() -> Path:
    """Folder for cached fields: ``$CTRPLAN_CACHE`` or ``~/.cache/ctrplan``."""
    env = os.environ.get("CTRPLAN_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "ctrplan"


def mesh_key(vertices: np.ndarray, faces: np.ndarray, config: FieldConfig) -> str:
    """Hash of a mesh and the field parameters (the cache key)."""
    h = hashlib.sha256()
    h.update(f"v{FIELD_VERSION}:{config}".encode())
    h.update(np.ascontiguousarray(vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(faces, dtype=np.int64).tobytes())
    return h.hexdigest()[:32]


def field_for(mesh, config: FieldConfig = FieldConfig(), cache: bool | Path = True) -> DistanceField:
    """The distance field of a trimesh mesh, from the disk cache when present."""
    v = np.asarray(mesh.vertices, dtype=float)
    f = np.asarray(mesh.faces, dtype=np.int64)
    folder = None
    if cache:
        folder = cache_dir() if cache is True else Path(cache)
        path = folder / f"field-{mesh_key(v, f, config)}.npz"
        if path.is_file():
            try:
                with np.load(path) as z:
                    return DistanceField(origin=z["origin"], h=float(z["h"]), lb=z["lb"], ub=z["ub"],
                                         box_lo=z["box_lo"], box_hi=z["box_hi"], rho=float(z["rho"]))
            except (OSError, ValueError, KeyError) as exc:  # a corrupt cache entry is rebuilt
                log.warning("ignoring unreadable field cache %s (%s)", path, exc)
    field = build_field(v, f, config)
    if folder is not None:
        try:
            folder.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(f".{os.getpid()}.tmp.npz")
            np.savez(tmp, origin=field.origin, h=field.h, lb=field.lb, ub=field.ub,
                     box_lo=field.box_lo, box_hi=field.box_hi, rho=field.rho)
            os.replace(tmp, path)
        except OSError as exc:  # a read-only cache only costs time
            log.warning("could not write field cache in %s (%s)", folder, exc)
    return field


def build_field(vertices: np.ndarray, faces: np.ndarray, config: FieldConfig = FieldConfig()) -> DistanceField:
    """Build the bounds grid of one mesh (see the module docstring)."""
    import trimesh
    from scipy import ndimage

    t0 = time.perf_counter()
    v = np.asarray(vertices, dtype=float)
    f = np.asarray(faces, dtype=np.int64)
    box_lo, box_hi = v.min(axis=0), v.max(axis=0)
    pad = config.band_mm + 1.0
    lo, hi = box_lo - pad, box_hi + pad
    ext = hi - lo
    h = max(config.h_mm, float(np.prod(ext) / config.max_nodes) ** (1 / 3))
    shape = tuple(int(math.ceil(e / h)) + 1 for e in ext)
    # surface samples: the vertices after subdividing every edge to at most h / 2
    sv, sf = trimesh.remesh.subdivide_to_size(v, f, max_edge=h / 2.0, max_iter=20)
    tri = sv[sf]
    e_max = max(float(np.linalg.norm(tri[:, i] - tri[:, (i + 1) % 3], axis=1).max()) for i in range(3))
    rho = e_max / math.sqrt(3.0)
    # mark the grid node nearest to each sample; keep one sample per marked node
    node = np.clip(np.rint((sv - lo) / h).astype(np.int64), 0, np.array(shape) - 1)
    flat = np.ravel_multi_index(node.T, shape)
    marked, first = np.unique(flat, return_index=True)
    rep = sv[first]
    grid = np.ones(shape, dtype=bool)
    grid.flat[marked] = False
    # exact Euclidean distance transform: for every node, the nearest marked node
    dist, idx = ndimage.distance_transform_edt(grid, sampling=h, return_indices=True)
    near = np.ravel_multi_index(idx.reshape(3, -1), shape)
    del idx
    rep_near = rep[np.searchsorted(marked, near)]
    nodes = np.stack(np.unravel_index(np.arange(len(near)), shape), axis=1) * h + lo
    # upper bound: distance to a true surface point (the sample held by the nearest marked node)
    ub = np.linalg.norm(nodes - rep_near, axis=1).reshape(shape).astype(np.float32)
    del nodes, rep_near
    # lower bound: the nearest surface point x has a sample within rho, whose node is within
    # h*sqrt(3)/2 of it, so dist <= d + rho + h*sqrt(3)/2
    lb = np.maximum(dist - rho - h * math.sqrt(3.0) / 2.0, 0.0).astype(np.float32)
    field = DistanceField(origin=lo, h=float(h), lb=lb, ub=ub, box_lo=box_lo, box_hi=box_hi,
                          rho=rho, build_s=time.perf_counter() - t0)
    log.debug("distance field: %s nodes, h %.3f mm, %d samples, rho %.3f mm, %.2f s",
              shape, h, len(sv), rho, field.build_s)
    return field


@nb.njit(cache=True, fastmath=False)
def _bounds_at(lb, ub, origin, h, box_lo, box_hi, x, y, z):
    """(lower, upper) bound of the distance at one point."""
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
        return math.sqrt(dx * dx + dy * dy + dz * dz), np.inf
    lo_b = -np.inf
    up_b = np.inf
    for di in range(2):
        cx = origin[0] + (i + di) * h - x
        for dj in range(2):
            cy = origin[1] + (j + dj) * h - y
            for dk in range(2):
                cz = origin[2] + (k + dk) * h - z
                dist = math.sqrt(cx * cx + cy * cy + cz * cz)
                lv = lb[i + di, j + dj, k + dk] - dist
                uv = ub[i + di, j + dj, k + dk] + dist
                if lv > lo_b:
                    lo_b = lv
                if uv < up_b:
                    up_b = uv
    return lo_b, up_b


@nb.njit(cache=True)
def _capsule_bounds(a, b, r, active, lb, ub, origin, h, box_lo, box_hi, sample_mm, eps,
                    clear_out, depth_out):
    """For each active configuration: clear_out = lower bound of the clearance (min over the
    capsules of axis distance minus radius minus half the sample spacing), depth_out = lower
    bound of the penetration depth (max of r - ub over axis samples). Stops a configuration at
    the first sample that proves a collision (depth > eps)."""
    B, K = r.shape
    for bi in range(B):
        if not active[bi]:
            continue
        clear = clear_out[bi]
        depth = depth_out[bi]
        done = False
        for kk in range(K):
            ax = a[bi, kk, 0]
            ay = a[bi, kk, 1]
            az = a[bi, kk, 2]
            vx = b[bi, kk, 0] - ax
            vy = b[bi, kk, 1] - ay
            vz = b[bi, kk, 2] - az
            seg = math.sqrt(vx * vx + vy * vy + vz * vz)
            n = int(math.ceil(seg / sample_mm)) + 1
            half = 0.5 * seg / (n - 1)
            rk = r[bi, kk]
            for s in range(n):
                t = s / (n - 1)
                lo_b, up_b = _bounds_at(lb, ub, origin, h, box_lo, box_hi,
                                        ax + t * vx, ay + t * vy, az + t * vz)
                c = lo_b - rk - half
                if c < clear:
                    clear = c
                d = rk - up_b
                if d > depth:
                    depth = d
                if depth > eps:
                    done = True
                    break
            if done:
                break
        clear_out[bi] = clear
        depth_out[bi] = depth


def capsule_bounds(field: DistanceField, a: np.ndarray, b: np.ndarray, r: np.ndarray,
                   active: np.ndarray, clear: np.ndarray, depth: np.ndarray, sample_mm: float) -> None:
    """Update ``clear`` (B,) and ``depth`` (B,) in place for the ``active`` configurations.

    a, b : (B, K, 3) capsule axis ends, mm, scene frame; r : (B, K) radii, mm.
    """
    _capsule_bounds(a, b, r, active, field.lb, field.ub, field.origin, field.h, field.box_lo,
                    field.box_hi, float(sample_mm), EPS_MM, clear, depth)


@nb.njit(cache=True)
def _point_bounds(p, lb, ub, origin, h, box_lo, box_hi, lo_out, up_out):
    for i in range(p.shape[0]):
        lo_out[i], up_out[i] = _bounds_at(lb, ub, origin, h, box_lo, box_hi, p[i, 0], p[i, 1], p[i, 2])


def point_bounds(field: DistanceField, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(lower, upper) bounds of the distance from points (P, 3) mm to the mesh."""
    p = np.ascontiguousarray(np.asarray(points, dtype=float).reshape(-1, 3))
    lo = np.empty(len(p))
    up = np.empty(len(p))
    _point_bounds(p, field.lb, field.ub, field.origin, field.h, field.box_lo, field.box_hi, lo, up)
    return lo, up
