"""Points sampled on the anatomy's surface with the normal that points into the lumen.

The reachability map (:mod:`ctrplan.planning.reach`) asks, per surface point, whether the robot
can put its tip there. :func:`sample_surface` draws the points: triangles of the scene's wall
and obstacle meshes with probability proportional to their area, a point uniform on each (barycentric
coordinates ``(1 - sqrt(u), sqrt(u) (1 - v), sqrt(u) v)``), all from one seeded generator, so
the same seed gives the same points on any machine. The surface is that of every mesh
the robot must not touch (walls and obstacles); landmarks are not sampled. Optionally only the
surface within ``radius_mm`` of given points (``near``: a region around named targets) is
sampled: triangles that come that near, and of their points only those that lie that near
(rejection), so the points are uniform on the part of the surface inside the balls.

Each point's normal points into the lumen, the side the robot is on: of the triangle's two
sides, the one whose point ``side_mm`` away lies inside the walls (:func:`inside_walls`) and
outside every obstacle. Where both sides qualify (a double-layered wall, such as the airway's
trachea: the tissue between its two surfaces counts as inside by ray parity), the lumen is the
side along which a ray runs farther before it meets a surface (a lumen is wider than its wall);
where neither does (an open place, a hair-thin sliver) the point is dropped and another drawn.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ctrplan.errors import ArgumentError

#: How far from the surface each side is tested (mm): well above float round-off, well below
#: any lumen or wall thickness of the shipped scenes.
SIDE_MM = 0.25


@dataclass(frozen=True)
class SurfaceSamples:
    """Points on the wall surface.

    points : (P, 3) mm, scene frame, on the mesh's triangles.
    normals : (P, 3) unit, scene frame, pointing into the lumen.
    mesh : (P,) names of the meshes the points lie on.
    face : (P,) triangle index in that mesh.
    """

    points: np.ndarray
    normals: np.ndarray
    mesh: np.ndarray
    face: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


def triangle_areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    """(F,) areas (mm^2) of the triangles ``f`` (F, 3) of vertices ``v`` (V, 3)."""
    t = v[f]
    return 0.5 * np.linalg.norm(np.cross(t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]), axis=1)


def sample_surface(scene, count: int, seed: int = 0, near: np.ndarray | None = None,
                   radius_mm: float = 20.0, side_mm: float = SIDE_MM,
                   max_rounds: int = 50) -> SurfaceSamples:
    """``count`` points on the scene's wall and obstacle meshes (the collision meshes),
    area-weighted, with normals into the lumen.

    near : (K, 3) mm, scene frame: only the surface within ``radius_mm`` of one of these
        points (None: the whole surface).
    Raises ArgumentError when the region holds no wall triangle or too few points have a
    lumen side after ``max_rounds`` draws.
    """
    if count < 1:
        raise ArgumentError("count", f"must be >= 1, got {count}")
    walls = list(scene.collision_meshes)
    if not walls:
        raise ArgumentError("scene", f"scene {scene.name!r} has no wall or obstacle mesh to sample")
    names, verts, faces, owner = [], [], [], []
    for k, m in enumerate(walls):
        v = np.asarray(m.mesh.vertices, dtype=float)
        f = np.asarray(m.mesh.faces, dtype=np.int64)
        names.append(m.name)
        verts.append(v)
        faces.append(f)
        owner.append(np.full(len(f), k))
    areas = np.concatenate([triangle_areas(v, f) for v, f in zip(verts, faces)])
    if near is not None:
        near = np.asarray(near, dtype=float).reshape(-1, 3)
        keep = np.concatenate([_near_faces(v, f, near, radius_mm) for v, f in zip(verts, faces)])
        areas = np.where(keep, areas, 0.0)
    if not areas.sum() > 0:
        raise ArgumentError("region", f"no wall or obstacle triangle within {radius_mm:g} mm of the region's points")
    owner = np.concatenate(owner)
    local = np.concatenate([np.arange(len(f)) for f in faces])
    rng = np.random.default_rng(seed)
    p_face = areas / areas.sum()
    got: list[tuple[np.ndarray, ...]] = []
    have = 0
    for _ in range(max_rounds):
        need = count - have
        if need <= 0:
            break
        draw = max(need + need // 4 + 4, 8)
        tri = rng.choice(len(areas), size=draw, p=p_face)
        u, w = rng.random(draw), rng.random(draw)
        pts, nrm = _points_on(verts, faces, owner[tri], local[tri], u, w)
        if near is not None:      # the region: points within the radius only
            inside = _within(pts, near, radius_mm)
            tri, pts, nrm = tri[inside], pts[inside], nrm[inside]
        side = lumen_side(scene, pts, nrm, side_mm) if len(pts) else np.zeros(0, dtype=int)
        ok = side != 0
        got.append((pts[ok], nrm[ok] * side[ok, None], owner[tri][ok], local[tri][ok]))
        have += int(ok.sum())
    if have < count:
        raise ArgumentError("region", f"only {have} of {count} sampled points have a lumen side "
                                      f"(is the wall mesh closed?)")
    pts, nrm, own, loc = (np.concatenate(x)[:count] for x in zip(*got))
    return SurfaceSamples(points=pts, normals=nrm, mesh=np.array(names, dtype=object)[own], face=loc)


def _near_faces(v: np.ndarray, f: np.ndarray, near: np.ndarray, radius_mm: float) -> np.ndarray:
    """(F,) whether some point of each triangle lies within ``radius_mm`` of a ``near`` point."""
    from trimesh.triangles import closest_point

    tri = v[f]
    keep = np.zeros(len(f), dtype=bool)
    for c in near:
        # triangles whose bounding sphere reaches the ball, then their exact closest points
        cand = np.flatnonzero(~keep & (np.linalg.norm(tri.mean(axis=1) - c, axis=1)
                                       <= radius_mm + np.max(np.linalg.norm(tri - tri.mean(axis=1, keepdims=True), axis=2), axis=1)))
        if len(cand):
            cp = closest_point(tri[cand], np.repeat(c[None], len(cand), axis=0))
            keep[cand[np.linalg.norm(cp - c, axis=1) <= radius_mm]] = True
    return keep


def _within(points: np.ndarray, near: np.ndarray, radius_mm: float) -> np.ndarray:
    """(P,) whether each point lies within ``radius_mm`` of one of ``near`` (K, 3)."""
    d = np.linalg.norm(points[:, None, :] - near[None, :, :], axis=2)
    return d.min(axis=1) <= radius_mm


def _points_on(verts, faces, mesh_idx, face_idx, u, w) -> tuple[np.ndarray, np.ndarray]:
    """Uniform points on the chosen triangles and their unit face normals (mesh winding)."""
    tri = np.stack([verts[m][faces[m][t]] for m, t in zip(mesh_idx, face_idx)])   # (P, 3, 3)
    su = np.sqrt(u)
    bary = np.stack([1.0 - su, su * (1.0 - w), su * w], axis=1)                  # (P, 3)
    pts = np.einsum("pk,pkj->pj", bary, tri)
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-300)
    return pts, n


def free_space(scene, points: np.ndarray) -> np.ndarray:
    """(P,) whether points (P, 3) mm lie inside the walls and outside every closed obstacle."""
    from ctrplan.collision.scene import inside_mesh, inside_walls

    points = np.atleast_2d(np.asarray(points, dtype=float))
    free = inside_walls(scene, points)
    for m in scene.meshes:
        if m.role == "obstacle" and free.any():
            free &= ~inside_mesh(m, points)
    return free


def lumen_side(scene, points: np.ndarray, normals: np.ndarray, side_mm: float = SIDE_MM) -> np.ndarray:
    """(P,) +1 where the lumen lies along ``normals`` from ``points``, -1 against, 0 neither
    (module docstring)."""
    plus = free_space(scene, points + side_mm * normals)
    minus = free_space(scene, points - side_mm * normals)
    side = np.where(plus & ~minus, 1, np.where(minus & ~plus, -1, 0))
    both = np.flatnonzero(plus & minus)
    if len(both):
        far_plus = _free_run(scene, points[both], normals[both])
        far_minus = _free_run(scene, points[both], -normals[both])
        side[both] = np.where(far_plus > far_minus, 1, np.where(far_minus > far_plus, -1, 0))
    return side


def _free_run(scene, points: np.ndarray, dirs: np.ndarray) -> np.ndarray:
    """(P,) distance (mm) a ray from each point runs before meeting a collision mesh (inf
    where it meets none); the ray starts ``SIDE_MM`` off the surface it leaves."""
    import trimesh

    meshes = [m.mesh for m in scene.collision_meshes]
    merged = trimesh.util.concatenate(meshes) if len(meshes) > 1 else meshes[0]
    origins = points + SIDE_MM * dirs
    out = np.full(len(points), np.inf)
    loc, ray, _ = merged.ray.intersects_location(origins, dirs, multiple_hits=False)
    if len(ray):
        d = np.linalg.norm(loc - origins[ray], axis=1)
        np.minimum.at(out, ray, d)
    return out
