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

import numba as nb
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


@dataclass(frozen=True)
class Edges:
    """The edges of a triangle list, counted: the boundary edges (used by an odd number of
    triangles; one each, directed as in a triangle that uses it, with that triangle's part),
    edges shared by two triangles that traverse them the same way (inconsistent winding),
    and edges shared by more than two triangles of one part (non-manifold)."""

    a: np.ndarray
    b: np.ndarray
    owner: np.ndarray
    inconsistent: int
    non_manifold: int
    non_manifold_part: int


def count_edges(faces: np.ndarray, n_vertices: int, owner: np.ndarray | None = None,
                parts: int = 1) -> Edges:
    """:class:`Edges` of ``faces`` (F, 3) over ``n_vertices`` vertices (``owner`` (F,): the part
    of each face). One sort of 3F packed 64-bit keys (edge, part, direction) and a compiled
    scan: memory about 8 bytes per edge."""
    f = np.asarray(faces, dtype=np.int64)
    nv = np.int64(max(int(n_vertices), 1))
    if float(nv) ** 2 * parts * 2 >= 2.0 ** 62:
        raise InputError("mesh", "vertices", f"{int(nv):,} vertices: too many to count edges")
    own = (np.asarray(owner, dtype=np.int64) if owner is not None and parts > 1
           else np.zeros(1, dtype=np.int64))
    keys = _pack_keys(f, nv, np.int64(parts), own, owner is not None and parts > 1)
    keys.sort()
    n_bnd, inc, nm, nm_part = _scan_count(keys, parts)
    ea = np.empty(n_bnd, np.int64)
    eb = np.empty(n_bnd, np.int64)
    eo = np.empty(n_bnd, np.int32)
    _scan_fill(keys, parts, nv, ea, eb, eo)
    return Edges(ea, eb, eo, int(inc), int(nm), int(nm_part))


@nb.njit(cache=True)
def _pack_keys(f, nv, parts, owner, with_owner):
    """(3F,) keys ((edge * parts + part) * 2 + direction), edge = lo * nv + hi."""
    keys = np.empty(3 * f.shape[0], np.int64)
    for t in range(f.shape[0]):
        p = owner[t] if with_owner else 0
        for k in range(3):
            a = f[t, k]
            b = f[t, (k + 1) % 3]
            lo = min(a, b)
            hi = max(a, b)
            keys[3 * t + k] = ((lo * nv + hi) * parts + p) * 2 + (1 if a > b else 0)
    return keys


@nb.njit(cache=True)
def _scan_count(keys, parts):
    n = keys.shape[0]
    i = 0
    n_bnd = inc = nm = 0
    nm_part = -1
    while i < n:
        e = (keys[i] >> 1) // parts
        j = i + 1
        while j < n and (keys[j] >> 1) // parts == e:
            j += 1
        cnt = j - i
        if cnt % 2 == 1:
            n_bnd += 1
        elif cnt == 2 and (keys[i] & 1) == (keys[i + 1] & 1):
            inc += 1
        if cnt > 2:
            k = i
            while k < j:          # occurrences are sorted by part within the edge
                p = (keys[k] >> 1) % parts
                m = k + 1
                while m < j and (keys[m] >> 1) % parts == p:
                    m += 1
                if m - k > 2:
                    nm += 1
                    nm_part = p
                    break
                k = m
        i = j
    return n_bnd, inc, nm, nm_part


@nb.njit(cache=True)
def _scan_fill(keys, parts, nv, ea, eb, eo):
    n = keys.shape[0]
    i = 0
    out = 0
    while i < n:
        e = (keys[i] >> 1) // parts
        j = i + 1
        while j < n and (keys[j] >> 1) // parts == e:
            j += 1
        if (j - i) % 2 == 1:
            lo = e // nv
            hi = e % nv
            if keys[i] & 1:      # the triangle ran hi -> lo
                ea[out] = hi
                eb[out] = lo
            else:
                ea[out] = lo
                eb[out] = hi
            eo[out] = (keys[i] >> 1) % parts
            out += 1
        i = j


def close_group(parts: list[Part], ends: list[OpenEnd], max_hole_mm: float,
                src: str) -> list[ClosedPart]:
    """Close a group of meshes (module docstring). ``src`` names scene.yaml in messages about
    ``open_ends``; holes are reported against the mesh file."""
    from ctrplan.progress import bar

    with bar(total=3, desc="closing meshes", disable=sum(len(p.faces) for p in parts) < 1_000_000) as pb:
        pool, faces, owner = _welded(parts)
        pb.update(1)
        edges = count_edges(faces, len(pool), owner, len(parts))
        if edges.non_manifold:
            raise InputError(parts[edges.non_manifold_part].file, "faces", f"non-manifold: "
                             f"{edges.non_manifold} edges shared by more than two triangles")
        pb.update(1)
        loops = _loops(edges.a, edges.b)
        new_v, new_f, new_owner, closures = _close_loops(parts, ends, pool, edges, loops,
                                                         max_hole_mm, src)
        pb.update(1)
    if len(parts) == 1 and not new_f and len(pool) == len(parts[0].vertices):
        # nothing merged, nothing added: the mesh as read (no copies of a large mesh)
        part = parts[0]
        f = _orient(part, part.vertices, np.asarray(part.faces, dtype=np.int64), edges.inconsistent)
        return [ClosedPart(part.name, part.vertices, f, True, ())]
    pool = np.vstack([pool] + new_v) if new_v else pool
    all_f = np.vstack([faces] + new_f) if new_f else faces
    all_owner = np.concatenate([owner] + new_owner) if new_owner else owner
    out = []
    for m, part in enumerate(parts):
        fm = all_f[all_owner == m]
        used, local = np.unique(fm, return_inverse=True)
        v, f = pool[used], local.reshape(-1, 3).astype(np.int64)
        mine = tuple(c for c in closures if c.mesh == part.name)
        own = count_edges(f, len(v))
        closed = len(own.a) == 0
        if closed:
            f = _orient(part, v, f, own.inconsistent)
        out.append(ClosedPart(part.name, v, f, closed, mine))
    return out


def _welded(parts: list[Part]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertex pool, faces into it (F, 3), owner part of each face (F,))."""
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts])
    pool, inverse = weld(np.vstack([p.vertices for p in parts]))
    if len(parts) == 1 and len(pool) == len(parts[0].vertices):     # nothing to merge
        f = np.asarray(parts[0].faces, dtype=np.int64)
        return parts[0].vertices, f, np.zeros(len(f), dtype=np.int32)
    faces = np.vstack([inverse[np.asarray(p.faces, dtype=np.int64) + o]
                       for p, o in zip(parts, offsets[:-1])])
    owner = np.concatenate([np.full(len(p.faces), m, dtype=np.int32) for m, p in enumerate(parts)])
    return pool, faces, owner


def boundary_loops(parts: list[Part]) -> list[tuple[str, np.ndarray, float]]:
    """The boundary loops of meshes taken together (seams between them closed): (name of the
    part owning most of the loop, centre (mean of its vertices), largest distance from the
    centre to a vertex)."""
    pool, faces, owner = _welded(parts)
    edges = count_edges(faces, len(pool), owner, len(parts))
    label, n = _loops(edges.a, edges.b)
    out = []
    for k in range(n):
        sel = label == k
        verts = np.unique(np.concatenate([edges.a[sel], edges.b[sel]]))
        centre = pool[verts].mean(axis=0)
        m = int(np.argmax(np.bincount(edges.owner[sel], minlength=len(parts))))
        out.append((parts[m].name, centre, float(np.max(np.linalg.norm(pool[verts] - centre, axis=1)))))
    return out


def _loops(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, int]:
    """(loop label of each boundary edge a-b (E_b,), number of loops): connected components
    of the boundary edges."""
    if len(a) == 0:
        return np.zeros(0, dtype=np.int64), 0
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    ids, local = np.unique(np.concatenate([a, b]), return_inverse=True)
    la, lb = local[:len(a)], local[len(a):]
    g = coo_matrix((np.ones(len(a)), (la, lb)), shape=(len(ids), len(ids)))
    n, label = connected_components(g, directed=False)
    return label[la], int(n)


def _close_loops(parts, ends, pool, edges: Edges, loops, max_hole_mm, src):
    """Fans for every loop (cap, fill) or the refusal of the largest unfillable one."""
    label, n = loops
    new_v, new_f, new_owner, closures = [], [], [], []
    a, b, face_owner = edges.a, edges.b, edges.owner
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


def signed_volume(vertices: np.ndarray, faces: np.ndarray, chunk: int = 1 << 20) -> float:
    """Signed volume (mm^3) enclosed by a closed triangle surface (positive: normals outward)."""
    total = 0.0
    for s in range(0, len(faces), chunk):
        t = vertices[faces[s:s + chunk]]
        total += float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum())
    return total / 6.0


def _orient(part: Part, v: np.ndarray, f: np.ndarray, inconsistent: int) -> np.ndarray:
    """Faces of a closed mesh with consistent winding and outward normals (changes logged)."""
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
