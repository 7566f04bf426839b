"""Procedural anatomy: implicit surfaces (tubes along paths, ellipsoids, branching trees)
meshed by marching cubes. Deterministic: every random choice takes a seed.

Used only to build the shipped scenes (``python -m ctrplan.collision.build_scenes``); needs the
optional package ``scikit-image`` (marching cubes). All lengths in mm.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def smooth_path(control: np.ndarray, n: int = 60) -> np.ndarray:
    """A smooth curve (n, 3) through the control points (C, 3) (Catmull-Rom, centripetal-free)."""
    c = np.asarray(control, dtype=float)
    if len(c) < 3:
        t = np.linspace(0, 1, n)[:, None]
        return c[0] * (1 - t) + c[-1] * t
    p = np.vstack([2 * c[0] - c[1], c, 2 * c[-1] - c[-2]])
    segs = len(c) - 1
    out = []
    for i in range(segs):
        p0, p1, p2, p3 = p[i], p[i + 1], p[i + 2], p[i + 3]
        m = max(2, n // segs)
        t = np.linspace(0, 1, m, endpoint=(i == segs - 1))[:, None]
        out.append(0.5 * ((2 * p1) + (-p0 + p2) * t + (2 * p0 - 5 * p1 + 4 * p2 - p3) * t**2
                          + (-p0 + 3 * p1 - 3 * p2 + p3) * t**3))
    return np.vstack(out)


def tube_field(points: np.ndarray, path: np.ndarray, radii: np.ndarray | float) -> np.ndarray:
    """Implicit value (negative inside) of a tube of radius ``radii`` (P,) along ``path`` (P, 3),
    at ``points`` (N, 3): min over segments of distance-to-segment minus the local radius."""
    path = np.asarray(path, dtype=float)
    radii = np.broadcast_to(np.asarray(radii, dtype=float), (len(path),))
    x = np.asarray(points, dtype=float)
    best = np.full(len(x), np.inf)
    for i in range(len(path) - 1):
        a, b = path[i], path[i + 1]
        v = b - a
        L2 = float(v @ v)
        t = np.clip(((x - a) @ v) / L2, 0.0, 1.0) if L2 > 0 else np.zeros(len(x))
        d = np.linalg.norm(x - (a + t[:, None] * v), axis=1) - (radii[i] + t * (radii[i + 1] - radii[i]))
        np.minimum(best, d, out=best)
    return best


def ellipsoid_field(points: np.ndarray, centre: np.ndarray, semi_axes: np.ndarray) -> np.ndarray:
    """Implicit value (negative inside) of an axis-aligned ellipsoid, scaled to mm near it."""
    q = (np.asarray(points, dtype=float) - centre) / semi_axes
    return (np.linalg.norm(q, axis=1) - 1.0) * float(np.min(semi_axes))


def smooth_union(a: np.ndarray, b: np.ndarray, k: float = 2.0) -> np.ndarray:
    """Smooth minimum of two implicit values (blends junctions over about ``k`` mm)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b * (1 - h) + a * h - k * h * (1 - h)


def implicit_mesh(fn: Callable[[np.ndarray], np.ndarray], lo: np.ndarray, hi: np.ndarray,
                  h: float):
    """Marching-cubes mesh (trimesh, mm) of the zero level of ``fn`` over the box [lo, hi]."""
    import trimesh
    from skimage import measure

    lo = np.asarray(lo, dtype=float)
    hi = np.asarray(hi, dtype=float)
    shape = tuple(int(np.ceil((hi[i] - lo[i]) / h)) + 1 for i in range(3))
    axes = [lo[i] + h * np.arange(shape[i]) for i in range(3)]
    vol = np.empty(shape, dtype=np.float32)
    gy, gz = np.meshgrid(axes[1], axes[2], indexing="ij")
    yz = np.stack([gy.ravel(), gz.ravel()], axis=1)
    for i, x in enumerate(axes[0]):
        vol[i] = fn(np.column_stack([np.full(len(yz), x), yz])).reshape(shape[1], shape[2])
    # close the surface at the box faces so the mesh is watertight
    vol[[0, -1], :, :] = np.maximum(vol[[0, -1], :, :], h)
    vol[:, [0, -1], :] = np.maximum(vol[:, [0, -1], :], h)
    vol[:, :, [0, -1]] = np.maximum(vol[:, :, [0, -1]], h)
    verts, faces, _, _ = measure.marching_cubes(vol, level=0.0, spacing=(h, h, h))
    return clean(trimesh.Trimesh(verts + lo, faces, process=True))


def tubes_mesh(tubes: list[tuple[np.ndarray, np.ndarray]], h: float, blend: float = 1.5,
               extra: Callable[[np.ndarray], np.ndarray] | None = None,
               extra_box: tuple[np.ndarray, np.ndarray] | None = None):
    """One closed surface around the smooth union of tubes [(path (P, 3), radii (P,)), ...]
    (plus an optional extra implicit shape inside ``extra_box``), evaluated per tube in its
    own bounding box so that large sparse trees stay cheap."""
    import trimesh
    from skimage import measure

    boxes = [(np.min(p, axis=0) - np.max(r) - 3 * h, np.max(p, axis=0) + np.max(r) + 3 * h)
             for p, r in tubes]
    if extra_box is not None:
        boxes.append((np.asarray(extra_box[0], float), np.asarray(extra_box[1], float)))
    lo = np.min([b[0] for b in boxes], axis=0) - 2 * h
    hi = np.max([b[1] for b in boxes], axis=0) + 2 * h
    shape = tuple(int(np.ceil((hi[i] - lo[i]) / h)) + 1 for i in range(3))
    vol = np.full(shape, 10.0 * h, dtype=np.float32)
    parts = [(b, (lambda pts, p=p, r=r: tube_field(pts, p, r))) for b, (p, r) in zip(boxes, tubes)]
    if extra is not None:
        parts.append((boxes[-1], extra))
    for (blo, bhi), fn in parts:
        i0 = np.maximum(np.floor((blo - lo) / h).astype(int), 0)
        i1 = np.minimum(np.ceil((bhi - lo) / h).astype(int) + 1, shape)
        ax = [lo[d] + h * np.arange(i0[d], i1[d]) for d in range(3)]
        g = np.stack(np.meshgrid(*ax, indexing="ij"), axis=-1).reshape(-1, 3)
        sub = vol[i0[0]:i1[0], i0[1]:i1[1], i0[2]:i1[2]]
        val = fn(g).reshape(sub.shape)
        sub[...] = smooth_union(sub.astype(float), val, blend)
    verts, faces, _, _ = measure.marching_cubes(vol, level=0.0, spacing=(h, h, h))
    return clean(trimesh.Trimesh(verts + lo, faces, process=True))


def clean(mesh):
    """Drop the zero-area and duplicate triangles that marching cubes and vertex merging leave
    (they make edges look non-manifold); fix the winding."""
    mesh.update_faces(mesh.nondegenerate_faces())
    mesh.update_faces(mesh.unique_faces())
    mesh.remove_unreferenced_vertices()
    mesh.fix_normals()
    return mesh


def tube_mesh(path: np.ndarray, radius: float | np.ndarray, h: float = 0.4):
    """Closed tube (capped ends) along ``path`` (P, 3) with radius (scalar or (P,))."""
    r = float(np.max(radius))
    lo = np.min(path, axis=0) - r - 2 * h
    hi = np.max(path, axis=0) + r + 2 * h
    return implicit_mesh(lambda p: tube_field(p, path, radius), lo, hi, h)


def branching_tree(seed: int, root: np.ndarray, direction: np.ndarray, length: float,
                   radius: float, generations: int, angle_deg: float = 35.0,
                   length_ratio: float = 0.78, radius_ratio: float = 0.8) -> list[tuple[np.ndarray, np.ndarray]]:
    """Branches of a dichotomous tree: a list of (path (P, 3), radii (P,)) tubes.

    Each branch splits into two children in a plane turned by a random angle about the parent
    axis; angles and lengths are jittered by +-20 % (numpy Generator seeded with ``seed``).
    """
    rng = np.random.default_rng(seed)
    out: list[tuple[np.ndarray, np.ndarray]] = []

    def grow(start, d, L, r, gen, normal):
        end = start + d * L
        out.append((np.vstack([start, end]), np.array([r, r * (0.5 + 0.5 * radius_ratio)])))
        if gen == 0:
            return
        twist = rng.uniform(-np.pi / 2, np.pi / 2)
        n = _rotate(normal, d, twist)
        for sign in (-1.0, 1.0):
            ang = np.radians(angle_deg) * rng.uniform(0.8, 1.2)
            child = _rotate(d, n, sign * ang)
            grow(end, child, L * length_ratio * rng.uniform(0.85, 1.15), r * radius_ratio,
                 gen - 1, np.cross(child, n))

    d0 = np.asarray(direction, dtype=float)
    d0 /= np.linalg.norm(d0)
    normal = np.cross(d0, [1.0, 0.0, 0.0])
    if np.linalg.norm(normal) < 1e-6:
        normal = np.cross(d0, [0.0, 1.0, 0.0])
    grow(np.asarray(root, dtype=float), d0, length, radius, generations, normal / np.linalg.norm(normal))
    return out


def _rotate(v: np.ndarray, axis: np.ndarray, angle: float) -> np.ndarray:
    """Rodrigues rotation of ``v`` about the unit ``axis``."""
    k = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    v = np.asarray(v, dtype=float)
    return v * np.cos(angle) + np.cross(k, v) * np.sin(angle) + k * (k @ v) * (1 - np.cos(angle))
