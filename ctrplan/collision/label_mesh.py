"""Surfaces from voxel masks: marching cubes, Taubin smoothing and decimation, each bounded by a
stated, measured limit on how far the surface may move.

The reference surface of a mask is its marching-cubes surface at level 0.5 (vertices at the
midpoints of voxel edges that cross the boundary) in the scanner frame of the image affine.
Smoothing (Taubin's lambda/mu filter, which does not shrink the way plain Laplacian smoothing
does) removes the voxel staircase; every vertex's move is then clamped to ``smooth_share`` of the
bound. Decimation (quadric, fast-simplification) is tried at decreasing strength until the
measured distance between the result and the marching-cubes surface, both ways, stays within
the bound; if no decimation does, the smoothed surface is kept undecimated.

How the distance is measured (:func:`surface_distance`): each surface is sampled (the
marching-cubes surface, whose triangles are smaller than a voxel, at its vertices and face
centroids; the decimated one at its vertices and points at most a third of the smallest voxel
size apart on every triangle), and from every sample of one surface the exact distance to the
other is taken over the triangles that own the 8 samples of the other surface nearest to it. Leaving out triangles can only make a distance larger, so the measure
never understates it; between samples it is interpolated, not bounded.

Thin structures are kept: the volume is padded by one empty voxel so that a label touching the
border still closes, and a single-voxel-thick label gives a closed surface of its own; because
every vertex moves less than the bound and the decimated surface must come within the bound of
every vertex of the marching-cubes surface, no part of a label can vanish.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numba
import numpy as np

log = logging.getLogger("ctrplan")

#: Candidate triangles per query point in :func:`surface_distance`.
CANDIDATES = 8


@dataclass(frozen=True)
class SurfaceStats:
    """How a label's surface was made: triangle counts before and after decimation, the
    largest measured distance (mm) between the final and the marching-cubes surface and the
    bound it had to meet, Taubin iterations, and the decimation kept (1.0 = none)."""

    faces_marching_cubes: int
    faces: int
    max_shift_mm: float
    bound_mm: float
    smoothing_iterations: int
    decimation_kept: float


def marching_cubes(mask: np.ndarray, affine: np.ndarray, offset: np.ndarray):
    """Closed triangle mesh (trimesh, mm, scanner frame) of a boolean mask ``(I, J, K)``.

    offset : (3,) int — voxel index of ``mask[0, 0, 0]`` in the full volume (masks are crops).
    affine : (4, 4) — voxel index (i, j, k, 1) -> scanner coordinates (mm).
    Normals point out of the mask whatever the handedness of the affine.
    """
    import trimesh
    from skimage import measure

    vol = np.pad(mask.astype(np.float32), 1)
    verts, faces, _, _ = measure.marching_cubes(vol, level=0.5, gradient_direction="descent",
                                                allow_degenerate=False)
    ijk = verts - 1.0 + np.asarray(offset, dtype=float)
    xyz = ijk @ affine[:3, :3].T + affine[:3, 3]
    if np.linalg.det(affine[:3, :3]) < 0:     # a left-handed voxel grid flips the winding
        faces = faces[:, ::-1]
    mesh = trimesh.Trimesh(xyz, faces, process=True)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    return mesh


def taubin(vertices: np.ndarray, faces: np.ndarray, iterations: int, lamb: float = 0.5,
           mu: float = -0.53) -> np.ndarray:
    """Taubin lambda/mu smoothing with the umbrella operator: ``iterations`` pairs of steps.
    vertices : (V, 3) mm; returns the smoothed (V, 3)."""
    import scipy.sparse as sp

    n = len(vertices)
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    e = np.unique(np.sort(e, axis=1), axis=0)
    rows = np.concatenate([e[:, 0], e[:, 1]])
    cols = np.concatenate([e[:, 1], e[:, 0]])
    adj = sp.csr_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    deg = np.asarray(adj.sum(axis=1)).ravel()
    deg[deg == 0] = 1.0
    lap = sp.diags(1.0 / deg) @ adj
    v = np.array(vertices, dtype=float)
    for _ in range(iterations):
        v += lamb * (lap @ v - v)
        v += mu * (lap @ v - v)
    return v


def clamp_moves(before: np.ndarray, after: np.ndarray, limit: float) -> np.ndarray:
    """``after`` with every vertex's move from ``before`` shortened to at most ``limit`` mm."""
    d = after - before
    n = np.linalg.norm(d, axis=1)
    scale = np.minimum(1.0, limit / np.maximum(n, 1e-300))
    return before + d * scale[:, None]


@numba.njit(cache=True, nogil=True)
def _pt_tri(px, py, pz, t):
    """Squared distance from a point to triangle ``t`` (3, 3): the closest-point regions of
    Ericson, Real-Time Collision Detection, 5.1.5, in scalar arithmetic."""
    ax, ay, az = t[0, 0], t[0, 1], t[0, 2]
    abx, aby, abz = t[1, 0] - ax, t[1, 1] - ay, t[1, 2] - az
    acx, acy, acz = t[2, 0] - ax, t[2, 1] - ay, t[2, 2] - az
    apx, apy, apz = px - ax, py - ay, pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return apx * apx + apy * apy + apz * apz
    bpx, bpy, bpz = px - t[1, 0], py - t[1, 1], pz - t[1, 2]
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return bpx * bpx + bpy * bpy + bpz * bpz
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        qx, qy, qz = apx - v * abx, apy - v * aby, apz - v * abz
        return qx * qx + qy * qy + qz * qz
    cpx, cpy, cpz = px - t[2, 0], py - t[2, 1], pz - t[2, 2]
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return cpx * cpx + cpy * cpy + cpz * cpz
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        qx, qy, qz = apx - w * acx, apy - w * acy, apz - w * acz
        return qx * qx + qy * qy + qz * qz
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and (d4 - d3) >= 0.0 and (d5 - d6) >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        qx = bpx - w * (t[2, 0] - t[1, 0])
        qy = bpy - w * (t[2, 1] - t[1, 1])
        qz = bpz - w * (t[2, 2] - t[1, 2])
        return qx * qx + qy * qy + qz * qz
    den = va + vb + vc
    if den <= 0.0:      # degenerate triangle: the nearest vertex
        da = apx * apx + apy * apy + apz * apz
        db = bpx * bpx + bpy * bpy + bpz * bpz
        dc = cpx * cpx + cpy * cpy + cpz * cpz
        return min(da, min(db, dc))
    v, w = vb / den, vc / den
    qx = apx - v * abx - w * acx
    qy = apy - v * aby - w * acy
    qz = apz - v * abz - w * acz
    return qx * qx + qy * qy + qz * qz


@numba.njit(cache=True, nogil=True, parallel=True)
def _nearest(points, cand, tri):
    out = np.empty(len(points))
    for i in numba.prange(len(points)):
        best = np.inf
        for j in range(cand.shape[1]):
            t = cand[i, j]
            if t < 0 or t >= len(tri):
                continue
            d = _pt_tri(points[i, 0], points[i, 1], points[i, 2], tri[t])
            if d < best:
                best = d
        out[i] = np.sqrt(best)
    return out


def surface_samples(vertices: np.ndarray, faces: np.ndarray, spacing: float,
                    with_faces: bool = False):
    """(S, 3) vertices plus points on every triangle, no point of a triangle farther than about
    ``spacing`` from a sample (a barycentric grid of n divisions per triangle); with
    ``with_faces`` also (S,) the index of a triangle each sample lies on."""
    tri = vertices[faces]
    edge = np.max(np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2), axis=1)
    n_div = np.clip(np.ceil(edge / spacing).astype(int), 1, 64)
    owner = np.zeros(len(vertices), dtype=np.int64)
    owner[faces.ravel()] = np.repeat(np.arange(len(faces)), 3)
    out, fid = [vertices], [owner]
    for n in np.unique(n_div):
        which = np.flatnonzero(n_div == n)
        ii, jj = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = ii + jj <= n
        u, w = ii[keep] / n, jj[keep] / n
        bary = np.stack([1 - u - w, u, w], axis=1)                 # (S, 3)
        out.append(np.einsum("sk,fkd->fsd", bary, tri[which]).reshape(-1, 3))
        fid.append(np.repeat(which, len(bary)))
    pts = np.concatenate(out)
    return (pts, np.concatenate(fid)) if with_faces else pts


class SurfaceIndex:
    """Nearest-triangle look-ups on one surface: a k-d tree over points sampled every
    ``spacing`` on it, each remembering its triangle."""

    def __init__(self, vertices: np.ndarray, faces: np.ndarray, spacing: float | None):
        from scipy.spatial import cKDTree

        if spacing is None:     # small triangles: their vertices and centroids
            owner = np.zeros(len(vertices), dtype=np.int64)
            owner[faces.ravel()] = np.repeat(np.arange(len(faces)), 3)
            self.samples = np.concatenate([vertices, vertices[faces].mean(axis=1)])
            self.owner = np.concatenate([owner, np.arange(len(faces))])
        else:
            self.samples, self.owner = surface_samples(vertices, faces, spacing, with_faces=True)
        self.tri = np.ascontiguousarray(vertices[faces], dtype=float)
        self.tree = cKDTree(self.samples)

    def distance(self, points: np.ndarray) -> np.ndarray:
        """(P,) upper bound (mm) on the distance from each point (P, 3) to the surface: the
        exact distance to the nearest of the triangles that own the ``CANDIDATES`` samples
        nearest the point (the true distance unless the nearest triangle owns none of them)."""
        k = min(CANDIDATES, len(self.samples))
        _, idx = self.tree.query(points, k=k, workers=-1)
        cand = self.owner[np.asarray(idx, dtype=np.int64).reshape(len(points), k)]
        return _nearest(np.ascontiguousarray(points, dtype=float), cand, self.tri)


def surface_distance(ref: SurfaceIndex, mesh_v: np.ndarray, mesh_f: np.ndarray,
                     spacing: float, stop_above: float = np.inf) -> float:
    """Largest distance (mm) between two surfaces, both ways (Hausdorff-like; see the module
    docstring for exactly what is sampled): points every ``spacing`` on ``mesh`` against
    ``ref``, and ``ref``'s samples against ``mesh``. Returns early (with a value above
    ``stop_above``) as soon as one direction exceeds it."""
    mesh = SurfaceIndex(mesh_v, mesh_f, spacing)
    worst = 0.0
    for index, points in ((mesh, ref.samples), (ref, mesh.samples)):
        for i in range(0, len(points), 100_000):
            worst = max(worst, float(index.distance(points[i:i + 100_000]).max(initial=0.0)))
            if worst > stop_above:
                return worst
    return worst


def _decimate(vertices: np.ndarray, faces: np.ndarray, keep: float):
    import fast_simplification
    import trimesh

    v, f = fast_simplification.simplify(np.asarray(vertices, dtype=np.float32),
                                        np.asarray(faces, dtype=np.int32),
                                        target_reduction=1.0 - keep)
    mesh = trimesh.Trimesh(np.asarray(v, dtype=float), f, process=True)
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    return mesh


def _manifold_closed(mesh) -> bool:
    f = np.asarray(mesh.faces)
    if len(f) == 0:
        return False
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    return bool(np.all(counts == 2))


def label_surface(mask: np.ndarray, affine: np.ndarray, offset: np.ndarray, bound_mm: float,
                  smoothing_iterations: int = 20, smooth_share: float = 0.7,
                  keep_fractions: tuple[float, ...] = (0.05, 0.1, 0.2, 0.4)):
    """The collision surface of one mask: (trimesh.Trimesh, :class:`SurfaceStats`).

    bound_mm : how far (mm) the result may lie from the marching-cubes surface, both ways.
    smooth_share : fraction of the bound that smoothing may use (each vertex's move clamped).
    keep_fractions : decimation strengths tried in order (fraction of triangles kept); the first
        whose measured distance stays within the bound and that stays closed and manifold wins.
    """
    import trimesh
    mc = marching_cubes(mask, affine, offset)
    ref_v, ref_f = np.asarray(mc.vertices), np.asarray(mc.faces)
    smooth = clamp_moves(ref_v, taubin(ref_v, ref_f, smoothing_iterations), smooth_share * bound_mm)
    shift = float(np.max(np.linalg.norm(smooth - ref_v, axis=1), initial=0.0))
    spacing = float(np.min(np.linalg.norm(affine[:3, :3], axis=0)))
    best = trimesh.Trimesh(smooth, ref_f, process=False)
    kept, measured = 1.0, shift       # same triangles, each vertex moved <= shift: exact bound
    ref = SurfaceIndex(ref_v, ref_f, None)
    for keep in keep_fractions:
        if len(ref_f) * keep < 200:
            continue
        dec = _decimate(smooth, ref_f, keep)
        if not _manifold_closed(dec):
            continue
        d = surface_distance(ref, np.asarray(dec.vertices), np.asarray(dec.faces),
                             spacing / 3.0, stop_above=bound_mm)
        log.debug("decimation keep %.2f: %d faces, %.3f mm (bound %.3f)", keep, len(dec.faces), d, bound_mm)
        if d <= bound_mm:
            best, kept, measured = dec, keep, d
            break
    best.fix_normals()
    return best, SurfaceStats(faces_marching_cubes=len(ref_f), faces=len(best.faces),
                              max_shift_mm=measured, bound_mm=float(bound_mm),
                              smoothing_iterations=int(smoothing_iterations), decimation_kept=kept)
