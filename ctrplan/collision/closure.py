"""Closed collision meshes: holes filled or refused, declared open ends capped, orientation.

Collision checking is surface distance (FCL, the distance field). That is safe for a robot that
starts inside a lumen only if the lumen's surface is **closed**: then any backbone that leaves
it must cross the surface, and crossing is a contact. Through a hole nothing is crossed, so a
backbone poking out through it would read as free. On load (:func:`close_group`):

1. Vertices at exactly the same coordinates are merged (an STL file stores every triangle on
   its own; meshes of one lumen, such as a trachea and its bronchi, share their seams).
2. Every edge is counted over the meshes of the group (all walls together; each obstacle on
   its own). An edge used by an odd number of triangles is a boundary edge; the boundary edges
   form loops. A triangle-mesh surface is closed when it has none: then every path between
   points of different ray parity crosses it (see :mod:`ctrplan.collision._raycast`).
3. Each loop is either a declared **open end** (``open_ends`` in scene.yaml: where the lumen
   leaves the model, e.g. an airway at the image border), capped (an end of shape ``ball``
   also adds its ball as a closed plug: for a lumen that opens without any boundary loop, as
   between the two layers of a double-walled mesh); or a **hole** no larger than
   ``max_hole_mm`` (default :data:`DEFAULT_MAX_HOLE_MM`), filled, with a warning saying where
   and how much; or anything else, refused with its location and size.
4. A loop is closed by a fan of triangles from its centre (the mean of its vertices) to each
   boundary edge (wound against the edge's own triangle, so a consistently oriented mesh stays
   so). The fan lies in the convex hull of the loop. The caps and fills are collision geometry
   like the rest: a backbone through them is a contact, never free.
5. A mesh closed on its own gets its winding made consistent and its normals pointing out of
   the volume it encloses (both reported when changed).

The size of a loop is twice the largest distance from its centre to its vertices (at least
its diameter, at most twice it).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass

import numpy as np

from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")

#: Holes up to this size (mm, see the module docstring) are filled on load; larger ones refuse
#: the scene unless declared as open ends (scene.yaml ``max_hole_mm`` changes it per scene).
DEFAULT_MAX_HOLE_MM = 5.0


@dataclass(frozen=True)
class OpenEnd:
    """A declared open end: where the lumen of mesh ``mesh`` leaves the model. Every boundary
    loop of that mesh whose vertices all lie within ``radius`` mm of ``position`` (scene
    frame, mm) is capped. ``shape`` "loop": there must be such a loop; "ball": the ball itself
    is added as a closed cap (a plug) too, for a lumen that opens without a mesh boundary (the
    mouth of a double-layered wall, whose inner and outer surfaces join at its rim)."""

    mesh: str
    position: np.ndarray
    radius: float
    shape: str = "loop"


@dataclass(frozen=True)
class Closure:
    """One boundary loop closed on load: ``kind`` "hole" (filled) or "open end" (capped)."""

    mesh: str
    kind: str
    centre: np.ndarray      # (3,) mm, scene frame
    size_mm: float
    edges: int
    area_mm2: float

    def describe(self) -> str:
        c = ", ".join(f"{x:.2f}" for x in self.centre)
        if self.kind == "plug":
            return (f"plugged the open end of {self.mesh!r} with a ball {self.size_mm:.2f} mm "
                    f"across at ({c}) mm")
        verb = "filled a hole" if self.kind == "hole" else "capped the open end"
        return (f"{verb} of {self.mesh!r} {self.size_mm:.2f} mm across at ({c}) mm: "
                f"{self.edges} boundary edges, {self.area_mm2:.3g} mm^2 of new surface")


@dataclass(frozen=True)
class Part:
    """A mesh of a group: name, file (for messages), vertices (V, 3) mm, faces (F, 3)."""

    name: str
    file: str
    vertices: np.ndarray
    faces: np.ndarray


@dataclass(frozen=True)
class ClosedPart:
    """A part after :func:`close_group`: welded, with its fills and caps; ``closed`` says
    whether it is closed on its own (not only together with the group's other meshes)."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    closed: bool
    closures: tuple[Closure, ...]


def weld(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(unique vertices (U, 3), inverse (V,)) merging vertices with equal coordinates.
    Lexicographic sort, memory O(V)."""
    v = np.asarray(vertices, dtype=np.float64)
    if len(v) == 0:
        return v.reshape(0, 3), np.zeros(0, dtype=np.int64)
    order = np.lexsort((v[:, 2], v[:, 1], v[:, 0]))
    sv = v[order]
    new = np.empty(len(v), dtype=bool)
    new[0] = True
    np.any(sv[1:] != sv[:-1], axis=1, out=new[1:])
    group = np.cumsum(new) - 1
    inverse = np.empty(len(v), dtype=np.int64)
    inverse[order] = group
    return sv[new], inverse


def edge_runs(faces: np.ndarray, n_vertices: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Edges of a triangle list, grouped: (order (3F,) edge occurrences sorted by undirected
    edge, starts (R,) of each run in ``order``, counts (R,)). Occurrence ``e`` is edge ``e % 3``
    of face ``e // 3``, directed ``f[k] -> f[(k + 1) % 3]``."""
    f = np.asarray(faces, dtype=np.int64)
    a = f.ravel()
    b = np.roll(f, -1, axis=1).ravel()
    key = np.minimum(a, b) * np.int64(n_vertices) + np.maximum(a, b)
    order = np.argsort(key, kind="stable")
    ks = key[order]
    del key
    head = np.empty(len(ks), dtype=bool)
    if len(ks):
        head[0] = True
        np.not_equal(ks[1:], ks[:-1], out=head[1:])
    starts = np.flatnonzero(head)
    counts = np.diff(np.append(starts, len(ks)))
    return order, starts, counts


def close_group(parts: list[Part], ends: list[OpenEnd], max_hole_mm: float,
                src: str) -> list[ClosedPart]:
    """Close a group of meshes (module docstring). ``src`` names scene.yaml in messages about
    ``open_ends``; holes are reported against the mesh file."""
    from ctrplan.progress import bar

    with bar(total=3, desc="closing meshes", disable=sum(len(p.faces) for p in parts) < 1_000_000) as pb:
        pool, faces, owner = _welded(parts)
        pb.update(1)
        order, starts, counts = edge_runs(faces, len(pool))
        _refuse_non_manifold(parts, owner, order, starts, counts)
        bnd = order[starts[counts % 2 == 1]]            # one occurrence per boundary edge
        pb.update(1)
        loops = _loops(faces, bnd)
        inconsistent = _inconsistent(faces, order, starts, counts)
        del order, starts, counts
        new_v, new_f, new_owner, closures = _close_loops(parts, ends, pool, faces, owner, bnd,
                                                         loops, max_hole_mm, src)
        pb.update(1)
    pool = np.vstack([pool] + new_v) if new_v else pool
    all_f = np.vstack([faces] + new_f) if new_f else faces
    all_owner = np.concatenate([owner] + new_owner) if new_owner else owner
    out = []
    for m, part in enumerate(parts):
        fm = all_f[all_owner == m]
        used, local = np.unique(fm, return_inverse=True)
        v, f = pool[used], local.reshape(-1, 3).astype(np.int64)
        mine = tuple(c for c in closures if c.mesh == part.name)
        closed = len(parts) == 1 or _odd_edges(f, len(v)) == 0
        if closed:
            f = _orient(part, v, f, inconsistent if len(parts) == 1 else None)
        out.append(ClosedPart(part.name, v, f, closed, mine))
    return out


def _welded(parts: list[Part]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertex pool, faces into it (F, 3), owner part of each face (F,))."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts])
    pool, inverse = weld(np.vstack([p.vertices for p in parts]))
    faces = np.vstack([inverse[np.asarray(p.faces, dtype=np.int64) + o]
                       for p, o in zip(parts, offsets[:-1])])
    owner = np.concatenate([np.full(len(p.faces), m, dtype=np.int32) for m, p in enumerate(parts)])
    return pool, faces, owner


def _refuse_non_manifold(parts, owner, order, starts, counts) -> None:
    """An edge shared by more than two triangles of one mesh has no consistent inside."""
    for r in np.flatnonzero(counts > 2):
        occ = order[starts[r]:starts[r] + counts[r]] // 3
        per = np.bincount(owner[occ], minlength=len(parts))
        if per.max() > 2:
            m = int(np.argmax(per))
            bad = int(np.sum(counts > 2))
            raise InputError(parts[m].file, "faces", f"non-manifold: {bad} edges shared by more "
                             "than two triangles")


def _loops(faces: np.ndarray, bnd: np.ndarray) -> tuple[np.ndarray, int]:
    """(loop label of each boundary occurrence (E_b,), number of loops): connected components
    of the boundary edges."""
    if len(bnd) == 0:
        return np.zeros(0, dtype=np.int64), 0
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    a = faces.ravel()[bnd]
    b = np.roll(faces, -1, axis=1).ravel()[bnd]
    ids, local = np.unique(np.concatenate([a, b]), return_inverse=True)
    la, lb = local[:len(a)], local[len(a):]
    g = coo_matrix((np.ones(len(a)), (la, lb)), shape=(len(ids), len(ids)))
    n, label = connected_components(g, directed=False)
    return label[la], int(n)


def _inconsistent(faces, order, starts, counts) -> int:
    """Edges shared by two triangles that traverse it in the same direction (inconsistent
    winding)."""
    two = starts[counts == 2]
    if len(two) == 0:
        return 0
    flat = faces.ravel()
    rolled = np.roll(faces, -1, axis=1).ravel()
    i, j = order[two], order[two + 1]
    return int(np.sum((flat[i] < rolled[i]) == (flat[j] < rolled[j])))


def _close_loops(parts, ends, pool, faces, owner, bnd, loops, max_hole_mm, src):
    """Fans for every loop (cap, fill) or the refusal of the largest unfillable one."""
    label, n = loops
    new_v, new_f, new_owner, closures = [], [], [], []
    a = faces.ravel()[bnd]
    b = np.roll(faces, -1, axis=1).ravel()[bnd]
    face_owner = owner[bnd // 3]
    order = np.argsort(label, kind="stable")
    cuts = np.searchsorted(label[order], np.arange(n + 1))
    used_ends: set[int] = set()
    refuse: list[tuple[float, int, np.ndarray, int]] = []
    apex = len(pool)
    for k in range(n):
        sel = order[cuts[k]:cuts[k + 1]]
        verts = np.unique(np.concatenate([a[sel], b[sel]]))
        centre = pool[verts].mean(axis=0)
        size = 2.0 * float(np.max(np.linalg.norm(pool[verts] - centre, axis=1)))
        m = int(np.argmax(np.bincount(face_owner[sel], minlength=len(parts))))
        hit = [e for e, end in enumerate(ends)
               if end.mesh in {parts[o].name for o in np.unique(face_owner[sel])}
               and np.all(np.linalg.norm(pool[verts] - end.position, axis=1) <= end.radius)]
        if not hit and size > max_hole_mm:
            refuse.append((size, m, centre, len(sel)))
            continue
        used_ends.update(hit)
        fan = np.stack([b[sel], a[sel], np.full(len(sel), apex)], axis=1)
        p0, p1 = pool[b[sel]], pool[a[sel]]
        area = 0.5 * float(np.linalg.norm(np.cross(p0 - centre, p1 - centre), axis=1).sum())
        new_v.append(centre[None])
        new_f.append(fan)
        new_owner.append(np.full(len(fan), m, dtype=np.int32))
        apex += 1
        c = Closure(parts[m].name, "open end" if hit else "hole", centre, size, len(sel), area)
        closures.append(c)
        # a declared end is expected (debug); a filled hole is news (a warning)
        (log.debug if hit else log.warning)("%s: %s", parts[m].file, c.describe())
    for e, end in enumerate(ends):
        names = [p.name for p in parts]
        if end.shape == "ball" and end.mesh in names:
            m = names.index(end.mesh)
            bv, bf = _ball(end.position, end.radius)
            new_v.append(bv)
            new_f.append(bf + apex)
            new_owner.append(np.full(len(bf), m, dtype=np.int32))
            apex += len(bv)
            used_ends.add(e)
            c = Closure(end.mesh, "plug", np.asarray(end.position, float), 2.0 * end.radius, 0,
                        4.0 * np.pi * end.radius ** 2)
            closures.append(c)
            log.debug("%s: %s", parts[m].file, c.describe())
    if refuse:
        size, m, centre, edges = max(refuse, key=lambda r: r[0])
        at = ", ".join(f"{x:.2f}" for x in centre)
        more = f" (and {len(refuse) - 1} more above {max_hole_mm:g} mm)" if len(refuse) > 1 else ""
        raise InputError(parts[m].file, "boundary", f"a hole {size:.2f} mm across at ({at}) mm "
                         f"({edges} boundary edges){more}: a tube through it would read as free; "
                         "repair the mesh, or declare it under open_ends in scene.yaml where the "
                         f"lumen leaves the model (holes up to {max_hole_mm:g} mm are filled: "
                         "max_hole_mm)")
    _check_ends_used(parts, ends, used_ends, src)
    return new_v, new_f, new_owner, closures


def _ball(centre: np.ndarray, radius: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed triangulated sphere (icosphere, 1280 triangles) around ``centre``; its vertices
    lie on the sphere of ``radius``."""
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=3)
    return (np.asarray(ico.vertices) * radius + np.asarray(centre, float),
            np.asarray(ico.faces, dtype=np.int64))


def _check_ends_used(parts, ends, used: set[int], src: str) -> None:
    names = {p.name for p in parts}
    for e, end in enumerate(ends):
        if e not in used and end.mesh in names:
            at = ", ".join(f"{x:.2f}" for x in end.position)
            raise InputError(src, "open_ends", f"no open boundary of {end.mesh!r} lies within "
                             f"{end.radius:g} mm of ({at}) (an end matches a loop whose every "
                             "vertex lies within its radius)")


def _odd_edges(faces: np.ndarray, n_vertices: int) -> int:
    _, _, counts = edge_runs(faces, n_vertices)
    return int(np.sum(counts % 2 == 1))


def signed_volume(vertices: np.ndarray, faces: np.ndarray, chunk: int = 1 << 20) -> float:
    """Signed volume (mm^3) enclosed by a closed triangle surface (positive: normals outward)."""
    total = 0.0
    for s in range(0, len(faces), chunk):
        t = vertices[faces[s:s + chunk]]
        total += float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum())
    return total / 6.0


def _orient(part: Part, v: np.ndarray, f: np.ndarray, inconsistent: int | None) -> np.ndarray:
    """Faces of a closed mesh with consistent winding and outward normals (changes logged)."""
    if inconsistent is None:
        order, starts, counts = edge_runs(f, len(v))
        inconsistent = _inconsistent(f, order, starts, counts)
    if inconsistent:
        import trimesh

        mesh = trimesh.Trimesh(v, f, process=False)
        trimesh.repair.fix_winding(mesh)
        f = np.asarray(mesh.faces, dtype=np.int64)
        log.warning("%s: %d edges had inconsistent winding; triangles re-oriented", part.file,
                    inconsistent)
    if signed_volume(v, f) < 0:
        log.info("%s: normals pointed inward; flipped", part.file)
        f = np.ascontiguousarray(f[:, ::-1])
    return f
