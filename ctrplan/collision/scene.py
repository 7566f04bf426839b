"""Anatomy scenes: meshes with roles, the robot's entry pose and example targets.

A scene is a folder with ``scene.yaml`` (format in docs/conventions.md) and its mesh files. Everything is
in the scene frame, in mm. Roles:

- ``wall``: the lumen surface the robot must stay inside; touching it is a collision. The walls
  together must be closed (:mod:`ctrplan.collision.closure`): small holes are filled on load,
  larger ones refuse the scene, and where the lumen continues beyond the model (the distal
  ends of the bronchi) the scene declares the opening under ``open_ends``, which is capped.
- ``obstacle``: a structure the robot must not touch (vessel, nerve).
- ``landmark``: drawn and used to pick targets (e.g. the ventricles the robot enters), never
  collision-checked.

Shipped scenes live in the repository's ``anatomy/`` folder and are loaded by name; a built
wheel carries them inside the package (``ctrplan/anatomy/``, copied there by ``setup.py``).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from ctrplan.collision.closure import DEFAULT_MAX_HOLE_MM
from ctrplan.errors import InputError
from ctrplan.io import load_yaml

ROLES = ("wall", "obstacle", "landmark")
SHIPPED_SCENES = ("airway", "neuro", "skull_base", "bronchial_tree")

#: Meshes whose largest extent falls outside this range (mm) are taken as a units mistake.
MIN_EXTENT_MM = 0.5
MAX_EXTENT_MM = 2000.0

_SCENE_KEYS = {"name", "units", "frame", "description", "meshes", "base_pose", "targets",
               "source", "licence", "generator", "open_ends", "max_hole_mm"}
_MESH_KEYS = {"name", "file", "role", "description"}


@dataclass(frozen=True)
class SceneMesh:
    """A named mesh of a scene: role ``wall``, ``obstacle`` or ``landmark``; mesh in mm, scene frame."""

    name: str
    role: str
    mesh: object  # trimesh.Trimesh (kept untyped so importing this module stays light)
    file: str = ""
    #: closed on its own (after the fills and caps of :mod:`ctrplan.collision.closure`); None:
    #: not known (a mesh not loaded by :func:`load_scene`: trimesh's ``is_watertight`` decides)
    closed: bool | None = field(default=None, compare=False)
    #: the holes filled and open ends capped on load
    closures: tuple = field(default=(), compare=False)

    @property
    def is_closed(self) -> bool:
        """Whether the mesh alone is a closed surface (inside/outside defined by ray parity)."""
        return bool(self.mesh.is_watertight) if self.closed is None else self.closed


@dataclass(frozen=True)
class Target:
    """A named example target: position (3,) mm, scene frame. ``config`` (2n,) rad and mm,
    where given, is a collision-free configuration of the ``seed1`` robot (physics model)
    whose tip reaches the target (how the shipped targets were chosen)."""

    name: str
    position: np.ndarray
    config: np.ndarray | None = None
    #: the anatomical name of a shipped scene's target (``name`` stays its id, ``t01``..; both
    #: are accepted wherever a target name is: :meth:`Scene.find_target`)
    label: str = field(default="", compare=False)

    @property
    def display(self) -> str:
        """``label (id)`` where the target has an anatomical name, else its name."""
        return f"{self.label} ({self.name})" if self.label else self.name


@dataclass(frozen=True)
class Scene:
    """An anatomy scene.

    base_pose : (4, 4) float — the robot base frame expressed in the scene frame (points in the
        base frame map to the scene frame by ``base_pose @ [p, 1]``).
    """

    name: str
    path: str
    meshes: tuple[SceneMesh, ...]
    base_pose: np.ndarray
    targets: tuple[Target, ...]
    source: str = ""
    licence: str = ""
    frame: str = ""
    description: str = field(default="", compare=False)
    #: the declared open ends (:class:`ctrplan.collision.closure.OpenEnd`), capped on load
    open_ends: tuple = field(default=(), compare=False)
    #: whether the walls together are closed (True for every scene :func:`load_scene` returns)
    walls_closed: bool = field(default=False, compare=False)

    def to_scene(self, points: np.ndarray) -> np.ndarray:
        """Points (..., 3) mm from the robot base frame to the scene frame."""
        p = np.asarray(points, dtype=float)
        return p @ self.base_pose[:3, :3].T + self.base_pose[:3, 3]

    def to_base(self, points: np.ndarray) -> np.ndarray:
        """Points (..., 3) mm from the scene frame to the robot base frame."""
        p = np.asarray(points, dtype=float)
        return (p - self.base_pose[:3, 3]) @ self.base_pose[:3, :3]

    @property
    def collision_meshes(self) -> tuple[SceneMesh, ...]:
        """The meshes that are collision-checked (roles wall and obstacle)."""
        return tuple(m for m in self.meshes if m.role in ("wall", "obstacle"))

    def mesh(self, name: str) -> SceneMesh:
        for m in self.meshes:
            if m.name == name:
                return m
        raise KeyError(name)

    def find_target(self, key: str) -> Target | None:
        """The target whose anatomical name or id (``t01``..) is ``key``, else None."""
        key = str(key).strip()
        for t in self.targets:
            if key in (t.name, t.label):
                return t
        return None

    def target_names(self) -> str:
        """The targets for an error message: ``carina (t01), ...``."""
        return ", ".join(t.display for t in self.targets) or "none"

    def target_positions(self) -> np.ndarray:
        """(T, 3) target positions, mm, scene frame."""
        return np.array([t.position for t in self.targets], dtype=float).reshape(-1, 3)


def anatomy_dir() -> Path:
    """Where the shipped scenes are: ``$CTRPLAN_ANATOMY`` if set, else ``ctrplan/anatomy/``
    inside an installed wheel, else the checkout's top-level ``anatomy/`` (editable install)."""
    env = os.environ.get("CTRPLAN_ANATOMY")
    if env:
        return Path(env)
    here = Path(__file__).resolve().parents[1]
    packaged = here / "anatomy"
    if packaged.is_dir():
        return packaged
    return here.parent / "anatomy"


def list_scenes() -> list[str]:
    """Names of the shipped scenes that are present."""
    d = anatomy_dir()
    return sorted(p.name for p in d.iterdir() if (p / "scene.yaml").is_file()) if d.is_dir() else []


def load_scene(name_or_path: str | os.PathLike | Scene) -> Scene:
    """Load a shipped scene by name or a scene folder (or its ``scene.yaml``)."""
    if isinstance(name_or_path, Scene):
        return name_or_path
    s = str(name_or_path)
    p = Path(s)
    try:   # a name the file system cannot hold (too long, NUL) names no scene either
        kind = ("file" if p.is_file() and p.name.endswith((".yaml", ".yml")) else "dir" if p.is_dir()
                else "shipped" if os.sep not in s and "/" not in s
                and (anatomy_dir() / s / "scene.yaml").is_file() else "")
    except (OSError, ValueError):
        kind = ""
    if kind == "file":
        folder, yml = p.parent, p
    elif kind == "dir":
        folder, yml = p, p / "scene.yaml"
    elif kind == "shipped":
        folder = anatomy_dir() / s
        yml = folder / "scene.yaml"
    else:
        shipped = ", ".join(list_scenes()) or "none found"
        raise InputError(s, "", f"no such scene folder, and not a shipped scene ({shipped})")
    if not yml.is_file():
        raise InputError(str(yml), "", "file not found")
    return scene_from_dict(load_yaml(yml), yml)


def scene_from_dict(data: object, yml: Path) -> Scene:
    """Build and validate a :class:`Scene` from parsed ``scene.yaml`` contents."""
    src = str(yml)
    if not isinstance(data, dict):
        raise InputError(src, "", "expected a mapping at the top level")
    unknown = sorted(set(data) - _SCENE_KEYS, key=str)
    if unknown:
        raise InputError(src, unknown[0], f"unknown key (allowed: {', '.join(sorted(_SCENE_KEYS))})")
    name = str(data.get("name") or yml.parent.name)
    units = data.get("units", "mm")
    if units != "mm":
        raise InputError(src, "units", f"must be 'mm' (convert the meshes), got {units!r}")
    raw_meshes = data.get("meshes")
    if not isinstance(raw_meshes, list) or not raw_meshes:
        raise InputError(src, "meshes", "an empty scene: list at least one mesh")
    entries = _parse_mesh_entries(raw_meshes, yml, src)
    ends = _parse_open_ends(data.get("open_ends"), entries, src)
    max_hole = _parse_max_hole(data.get("max_hole_mm", DEFAULT_MAX_HOLE_MM), src)
    meshes = _load_meshes(entries, ends, max_hole, src)
    base_pose = _parse_pose(data.get("base_pose"), src)
    targets = _parse_targets(data.get("targets") or [], src)
    if yml.parent.resolve() == (anatomy_dir() / name).resolve():  # a shipped scene
        from ctrplan.collision.target_names import anatomical_name

        targets = tuple(replace(t, label=anatomical_name(name, t.name)) for t in targets)
    scene = Scene(name=name, path=str(yml.parent), meshes=tuple(meshes), base_pose=base_pose,
                  targets=targets, source=str(data.get("source", "")),
                  licence=str(data.get("licence", "")), frame=str(data.get("frame", "")),
                  description=str(data.get("description", "")), open_ends=tuple(ends),
                  walls_closed=True)
    if not scene.collision_meshes:
        raise InputError(src, "meshes", "no wall or obstacle mesh: nothing to check collisions against")
    check_base_inside(scene, src)
    return scene


def _parse_mesh_entries(raw_meshes: list, yml: Path, src: str) -> list[tuple[str, str, str, Path]]:
    """(name, role, file, path) of each ``meshes`` entry, checked."""
    out = []
    seen = set()
    for k, entry in enumerate(raw_meshes):
        where = f"meshes[{k}]"
        if not isinstance(entry, dict):
            raise InputError(src, where, "expected a mapping with name, file, role")
        bad = sorted(set(entry) - _MESH_KEYS, key=str)
        if bad:
            raise InputError(src, f"{where}.{bad[0]}", "unknown key")
        for key in ("name", "file", "role"):
            if not entry.get(key):
                raise InputError(src, f"{where}.{key}", "missing")
        mname = str(entry["name"])
        if mname in seen:
            raise InputError(src, f"{where}.name", f"duplicate mesh name {mname!r}")
        seen.add(mname)
        role = str(entry["role"])
        if role not in ROLES:
            raise InputError(src, f"{where}.role", f"unknown role {role!r} (choose from {', '.join(ROLES)})")
        path = _mesh_path(yml, str(entry["file"]), src, f"{where}.file")
        out.append((mname, role, str(entry["file"]), path))
    return out


def _parse_open_ends(raw: object, entries: list, src: str) -> list:
    """``open_ends``: a list of ``{mesh, position: [x, y, z], radius, shape: loop|ball}``
    naming wall or obstacle meshes."""
    from ctrplan.collision.closure import OpenEnd

    if raw is None:
        return []
    if not isinstance(raw, list):
        raise InputError(src, "open_ends", "expected a list of {mesh, position, radius}")
    names = {e[0] for e in entries if e[1] in ("wall", "obstacle")}
    out = []
    for k, e in enumerate(raw):
        where = f"open_ends[{k}]"
        if not isinstance(e, dict) or not {"mesh", "position", "radius"} <= set(e):
            raise InputError(src, where, "expected {mesh, position: [x, y, z], radius}")
        bad = sorted(set(e) - {"mesh", "position", "radius", "shape"}, key=str)
        if bad:
            raise InputError(src, f"{where}.{bad[0]}", "unknown key")
        if str(e["mesh"]) not in names:
            raise InputError(src, f"{where}.mesh", f"{str(e['mesh'])[:60]!r} is not a wall or "
                             "obstacle mesh of this scene")
        radius = _vector([e["radius"]], 1, src, f"{where}.radius")[0]
        if not 0 < radius <= MAX_EXTENT_MM:
            raise InputError(src, f"{where}.radius", f"must be in (0, {MAX_EXTENT_MM:g}] mm")
        shape = e.get("shape", "loop")
        if shape not in ("loop", "ball"):
            raise InputError(src, f"{where}.shape", "must be 'loop' (cap the boundary loops within "
                             "the radius) or 'ball' (also plug the opening with the ball)")
        out.append(OpenEnd(str(e["mesh"]), _vector(e["position"], 3, src, f"{where}.position"),
                           float(radius), shape))
    return out


def _parse_max_hole(raw: object, src: str) -> float:
    v = _vector([raw], 1, src, "max_hole_mm")[0] if not isinstance(raw, bool) else -1.0
    if not 0 <= v <= MAX_EXTENT_MM:
        raise InputError(src, "max_hole_mm", f"must be a number of mm in [0, {MAX_EXTENT_MM:g}]")
    return float(v)


def _load_meshes(entries: list, ends: list, max_hole: float, src: str) -> list[SceneMesh]:
    """Read every mesh (after the work estimate), close the walls together and each obstacle
    alone (:func:`ctrplan.collision.closure.close_group`)."""
    import trimesh

    from ctrplan.collision.budget import check_scene_budget
    from ctrplan.collision.closure import Part, close_group

    check_scene_budget([(e[3], e[1]) for e in entries], src)
    parts = {name: Part(name, str(path), *read_mesh_file(path, edges=role == "landmark"))
             for name, role, _, path in entries}
    groups = [[e[0] for e in entries if e[1] == "wall"]]
    groups += [[e[0]] for e in entries if e[1] == "obstacle"]
    closed = {}
    for group in groups:
        if group:
            for cp in close_group([parts[n] for n in group], ends, max_hole, src):
                closed[cp.name] = cp
    out = []
    for name, role, file, _ in entries:
        if name in closed:
            cp = closed[name]
            mesh = trimesh.Trimesh(cp.vertices, cp.faces, process=False)
            out.append(SceneMesh(name, role, mesh, file, closed=cp.closed, closures=cp.closures))
        else:
            p = parts[name]
            out.append(SceneMesh(name, role, trimesh.Trimesh(p.vertices, p.faces, process=False), file))
    return out


def _mesh_path(yml: Path, file: str, src: str, fieldname: str) -> Path:
    """A mesh file named in scene.yaml: a relative path that stays inside the scene folder."""
    rel = Path(file)
    if rel.is_absolute() or file.startswith(("/", "\\")) or (len(file) > 1 and file[1] == ":"):
        raise InputError(src, fieldname, f"{file!r} is an absolute path: name a file inside the scene folder")
    if ".." in rel.parts or ".." in Path(file.replace("\\", "/")).parts:
        raise InputError(src, fieldname, f"{file!r} leaves the scene folder ('..')")
    path = yml.parent / rel
    # Symlinks too: the file the name finally resolves to must lie inside the (resolved) scene
    # folder, so a scene cannot make ctrplan read files elsewhere on the machine.
    folder = os.path.realpath(yml.parent)
    real = os.path.realpath(path)
    if os.path.commonpath([folder, real]) != folder:
        raise InputError(src, fieldname, f"{file!r} is a symlink that leaves the scene folder "
                                          f"(resolves outside {folder!r})")
    return path


def read_mesh_file(path: str | os.PathLike, edges: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) mm, faces (F, 3)) of a mesh file, read by the rules of its format
    (:mod:`ctrplan.collision.meshio`) and validated (``edges``: the non-manifold check too,
    which :mod:`ctrplan.collision.closure` makes anyway on the welded mesh); errors name the
    file."""
    from ctrplan.collision.meshio import read_mesh
    from ctrplan.io import read_bytes

    path = Path(path)
    try:
        found = path.is_file()
    except OSError:     # a name too long for the file system
        found = False
    if not found:
        raise InputError(str(path), "", "mesh file not found")
    v, f = read_mesh(path, read_bytes(path, "mesh"))
    validate_arrays(v, f, str(path), edges=edges)
    return v, f


def load_mesh(path: str | os.PathLike):
    """Load a triangle mesh (mm) as a trimesh object and validate it; errors name the file.
    (Scenes close their meshes on top of this: :func:`load_scene`.)"""
    import trimesh

    return trimesh.Trimesh(*read_mesh_file(path), process=False)


def validate_mesh(mesh, source: str) -> None:
    """Raise :class:`InputError` for an empty, non-finite, non-manifold or absurd-scale mesh."""
    validate_arrays(np.asarray(mesh.vertices), np.asarray(mesh.faces), source)


def validate_arrays(v: np.ndarray, f: np.ndarray, source: str, chunk: int = 1 << 20,
                    edges: bool = True) -> None:
    """:func:`validate_mesh` on arrays (vertices (V, 3), faces (F, 3)); memory O(F).
    ``edges``: check for non-manifold edges too."""
    v = np.asarray(v, dtype=float)
    f = np.asarray(f)
    if len(v) == 0 or len(f) == 0 or f.ndim != 2 or f.shape[1] != 3:
        raise InputError(source, "faces", "empty mesh (no triangles)")
    if not np.all(np.isfinite(v)):
        raise InputError(source, "vertices", "non-finite vertex coordinates")
    if f.min() < 0 or f.max() >= len(v):
        raise InputError(source, "faces", "face indices out of range")
    extent = float(np.max(v.max(axis=0) - v.min(axis=0)))
    if not MIN_EXTENT_MM <= extent <= MAX_EXTENT_MM:
        raise InputError(source, "vertices", f"largest extent {extent:.4g} mm is outside "
                         f"[{MIN_EXTENT_MM}, {MAX_EXTENT_MM}] mm: is the mesh in mm?")
    if not any(np.any(_areas(v, f[s:s + chunk]) > 0) for s in range(0, len(f), chunk)):
        raise InputError(source, "faces", "all triangles are degenerate")
    if not edges:
        return
    from ctrplan.collision.closure import count_edges

    bad = count_edges(f, len(v)).non_manifold
    if bad:
        raise InputError(source, "faces", f"non-manifold: {bad} edges shared by more than two "
                         "triangles")


def _areas(v: np.ndarray, f: np.ndarray) -> np.ndarray:
    return np.linalg.norm(np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]]), axis=1)


def _parse_pose(raw: object, src: str) -> np.ndarray:
    if not isinstance(raw, dict) or "position" not in raw or "quaternion" not in raw:
        raise InputError(src, "base_pose", "needs position [x, y, z] and quaternion [w, x, y, z]")
    bad = sorted(set(raw) - {"position", "quaternion"}, key=str)
    if bad:
        raise InputError(src, f"base_pose.{bad[0]}", "unknown key")
    pos = _vector(raw["position"], 3, src, "base_pose.position")
    quat = _vector(raw["quaternion"], 4, src, "base_pose.quaternion")
    norm = float(np.linalg.norm(quat))
    if abs(norm - 1.0) > 1e-3:
        raise InputError(src, "base_pose.quaternion", f"not a unit quaternion (norm {norm:.6g})")
    T = np.eye(4)
    T[:3, :3] = quaternion_to_matrix(quat / norm)
    T[:3, 3] = pos
    return T


def _parse_targets(raw: object, src: str) -> tuple[Target, ...]:
    if not isinstance(raw, list):
        raise InputError(src, "targets", "expected a list of {name, position}")
    out = []
    for k, t in enumerate(raw):
        if not isinstance(t, dict) or "position" not in t:
            raise InputError(src, f"targets[{k}]", "expected {name, position: [x, y, z]}")
        bad = sorted(set(t) - {"name", "position", "config"}, key=str)
        if bad:
            raise InputError(src, f"targets[{k}].{bad[0]}", "unknown key")
        config = None
        if t.get("config") is not None:
            raw = t["config"]
            config = _vector(raw, len(raw) if isinstance(raw, list) else -1, src, f"targets[{k}].config")
        out.append(Target(name=str(t.get("name", f"target{k + 1}")),
                          position=_vector(t["position"], 3, src, f"targets[{k}].position"),
                          config=config))
    return tuple(out)


def _vector(raw: object, n: int, src: str, fieldname: str) -> np.ndarray:
    try:
        v = np.asarray(raw, dtype=float)
    except (TypeError, ValueError):
        raise InputError(src, fieldname, f"expected {n} numbers") from None
    if v.shape != (n,):
        raise InputError(src, fieldname, f"expected {n} numbers, got {np.size(v)}")
    if not np.all(np.isfinite(v)):
        raise InputError(src, fieldname, "not finite")
    return v


def quaternion_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit quaternion ``[w, x, y, z]``."""
    w, x, y, z = np.asarray(q, dtype=float)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def matrix_to_quaternion(R: np.ndarray) -> np.ndarray:
    """Unit quaternion ``[w, x, y, z]`` (w >= 0) of a rotation matrix."""
    from scipy.spatial.transform import Rotation

    x, y, z, w = Rotation.from_matrix(np.asarray(R, dtype=float)).as_quat()
    q = np.array([w, x, y, z])
    return q if w >= 0 else -q


def inside_walls(scene: Scene, points: np.ndarray, min_hit_fraction: float = 0.7) -> np.ndarray:
    """(P,) bool: whether each point (P, 3) mm, scene frame, lies inside the scene's walls.

    Walls closed together (every scene :func:`load_scene` returns): a point inside by ray
    parity (an odd number of crossings, :mod:`ctrplan.collision._raycast`) is inside; a point
    of even parity (the lumen of a double-layered wall, such as the airway's trachea, whose
    mesh has an inner and an outer surface) is inside when every one of 96 rays from it meets
    the walls (one that escapes proves the point outside).

    Open walls (meshes not closed by the loader, e.g. while :mod:`build_scenes` builds a
    scene): a watertight wall uses trimesh's containment; otherwise a point counts as inside
    when at least ``min_hit_fraction`` of 96 rays from it hit the walls.
    """
    walls = [m for m in scene.meshes if m.role == "wall"]
    points = np.atleast_2d(np.asarray(points, dtype=float))
    if not walls:
        return np.ones(len(points), dtype=bool)
    if scene.walls_closed:
        from ctrplan.collision._raycast import enclosed, odd_parity

        v, f = _union(walls)
        inside = odd_parity(v, f, points)
        for i in np.flatnonzero(~inside):
            inside[i] = enclosed(v, f, points[i])
        return inside
    return _inside_open_walls([m.mesh for m in walls], points, min_hit_fraction)


def _union(meshes) -> tuple[np.ndarray, np.ndarray]:
    """(vertices, faces) of several scene meshes together."""
    vs = [np.asarray(m.mesh.vertices, dtype=float) for m in meshes]
    offsets = np.cumsum([0] + [len(v) for v in vs])
    fs = [np.asarray(m.mesh.faces, dtype=np.int64) + o for m, o in zip(meshes, offsets[:-1])]
    return np.vstack(vs), np.vstack(fs)


def _inside_open_walls(walls: list, points: np.ndarray, min_hit_fraction: float) -> np.ndarray:
    import trimesh

    from ctrplan.collision._raycast import fibonacci_directions

    inside = np.zeros(len(points), dtype=bool)
    for w in walls:
        if w.is_watertight:
            inside |= w.contains(points)
    open_walls = [w for w in walls if not w.is_watertight]
    if open_walls:
        merged = trimesh.util.concatenate(open_walls)
        dirs = fibonacci_directions()
        for i, p in enumerate(points):
            if inside[i]:
                continue
            hit = merged.ray.intersects_any(np.repeat(p[None], len(dirs), axis=0), dirs)
            inside[i] = hit.mean() >= min_hit_fraction
    return inside


def inside_mesh(m: SceneMesh, points: np.ndarray) -> np.ndarray:
    """(P,) bool: whether points (P, 3) mm lie inside a closed scene mesh (ray parity; all
    False for a mesh that is not closed: it has no inside)."""
    points = np.atleast_2d(np.asarray(points, dtype=float))
    closed = getattr(m, "is_closed", None)
    if not (closed if closed is not None else getattr(m.mesh, "is_watertight", False)):
        return np.zeros(len(points), dtype=bool)
    from ctrplan.collision._raycast import odd_parity

    return odd_parity(np.asarray(m.mesh.vertices), np.asarray(m.mesh.faces), points)


def check_base_inside(scene: Scene, src: str) -> None:
    """Raise :class:`InputError` if the base pose lies outside the scene's walls or inside a
    closed obstacle."""
    base = scene.base_pose[:3, 3][None]
    for k, end in enumerate(scene.open_ends):
        if end.shape == "ball" and np.linalg.norm(base[0] - end.position) <= end.radius:
            raise InputError(src, "base_pose.position", f"lies inside the ball of open_ends[{k}] "
                             "(a plug the robot may not enter)")
    for m in scene.meshes:
        if m.role == "obstacle" and inside_mesh(m, base)[0]:
            raise InputError(src, "base_pose.position", f"lies inside the obstacle {m.name!r}")
    if any(m.role == "wall" for m in scene.meshes) and not inside_walls(scene, base)[0]:
        raise InputError(src, "base_pose.position", "lies outside the wall meshes: the robot "
                         "must enter inside the lumen")
