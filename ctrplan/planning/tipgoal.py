"""Tip pose goals: a point, an approach direction with a cone, and a standoff from the tissue.

:class:`TipGoal` is what :meth:`Planner.plan <ctrplan.planning.planner.Planner.plan>` (and
``plan_to_target``) accepts wherever a target point is; a plain point stays a point goal with
exactly the behaviour it always had. A TipGoal says where the tissue is (``position``, scene
frame), from which side the tip stands off it (``normal``: the surface normal pointing into the
lumen, e.g. from :func:`snap_to_surface`), how far (``standoff_mm``), and the tip's direction
(``direction``: the axis the tip tangent must lie within ``cone_deg`` of).

The tip's tangent is the backbone's direction at the tip: :func:`tip_tangents` differentiates
the backbone's last three points (second-order one-sided differences, evenly spaced in arc
length); :func:`tip_frames` evaluates the model with :data:`TANGENT_POINTS` points, where that
difference is within ``h^2 kappa^2 / 3`` rad of the tangent (0.02 deg at kappa = 0.02 /mm,
h = 2 mm). Frames: scene frame for everything a TipGoal holds; :func:`to_base_vectors` turns
directions into the robot base frame.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ctrplan.errors import ArgumentError

#: the cone (deg) around ``direction`` when a TipGoal gives a direction but no cone
DEFAULT_CONE_DEG = 10.0
#: how far (mm) beyond the tip's radius + margin the tip's centre stays from the surface when
#: the standoff asked for is smaller (the tip's capsule touches the surface at exactly radius +
#: margin, which the collision check must call a contact)
CONTACT_PAD_MM = 0.05
#: backbone points used to measure the tip tangent (evenly spaced from the base to the tip)
TANGENT_POINTS = 161
#: the largest standoff (mm) accepted (a scene is at most 2 m across)
MAX_STANDOFF_MM = 1000.0


def _vector(value, name: str) -> tuple[float, float, float]:
    try:
        v = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ArgumentError(name, f"must be three numbers X,Y,Z, got {value!r}") from None
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise ArgumentError(name, f"must be three finite numbers X,Y,Z, got {value!r}")
    return float(v[0]), float(v[1]), float(v[2])


def _unit(value, name: str) -> tuple[float, float, float]:
    v = np.asarray(_vector(value, name))
    norm = float(np.linalg.norm(v))
    if not norm > 1e-12 or not math.isfinite(norm):
        raise ArgumentError(name, f"must be a non-zero direction X,Y,Z, got {value!r}")
    u = v / norm
    return float(u[0]), float(u[1]), float(u[2])


@dataclass(frozen=True)
class TipGoal:
    """Where the tip goes and how it arrives (all in the scene frame, mm and degrees).

    position : (3,) mm — the target point; on the tissue surface when ``normal`` is given (a
        wall point from :func:`snap_to_surface`).
    direction : (3,) or None — the axis the tip's tangent must lie within ``cone_deg`` of (the
        direction the tip points, from the robot toward the tissue; normalised here). None: any
        direction.
    cone_deg : half-angle (deg, in (0, 90]) of the cone around ``direction``; None with a
        direction: :data:`DEFAULT_CONE_DEG`. Not allowed without a direction.
    standoff_mm : how far (mm, >= 0) the tip stops from ``position``: along ``normal`` when
        given, else back along ``direction`` (the tip stops short of the point it points at).
        A standoff > 0 needs one of them. The tip's centre never comes nearer the surface than
        its radius + margin: a smaller standoff (0: touching) is planned at radius + margin +
        :data:`CONTACT_PAD_MM` and reported as ``goal_shift_mm``; tolerances apply to the
        standoff point asked for.
    normal : (3,) or None — the surface normal at ``position``, pointing out of the tissue
        into the lumen (normalised here).

    Raises ArgumentError naming the field for a bad value.
    """

    position: tuple
    direction: tuple | None = None
    cone_deg: float | None = None
    standoff_mm: float = 0.0
    normal: tuple | None = None

    def __post_init__(self) -> None:
        from ctrplan.planning.arguments import check_target

        try:
            p = check_target(self.position)
        except ArgumentError as exc:
            raise ArgumentError("position", exc.message) from None
        object.__setattr__(self, "position", tuple(float(v) for v in p))
        if self.direction is not None:
            object.__setattr__(self, "direction", _unit(self.direction, "direction"))
        if self.normal is not None:
            object.__setattr__(self, "normal", _unit(self.normal, "normal"))
        cone = self.cone_deg
        if cone is not None:
            if self.direction is None:
                raise ArgumentError("cone_deg", "needs a `direction` (the cone's axis)")
            if isinstance(cone, bool) or not isinstance(cone, (int, float, np.floating, np.integer)) \
                    or not (math.isfinite(cone) and 0 < cone <= 90):
                raise ArgumentError("cone_deg", f"must be a half-angle in (0, 90] degrees, got {cone!r}")
            object.__setattr__(self, "cone_deg", float(cone))
        elif self.direction is not None:
            object.__setattr__(self, "cone_deg", DEFAULT_CONE_DEG)
        s = self.standoff_mm
        if isinstance(s, bool) or not isinstance(s, (int, float, np.floating, np.integer)) \
                or not (math.isfinite(s) and 0 <= s <= MAX_STANDOFF_MM):
            raise ArgumentError("standoff_mm", f"must be a distance in [0, {MAX_STANDOFF_MM:g}] mm, "
                                               f"got {s!r}")
        object.__setattr__(self, "standoff_mm", float(s))
        if s > 0 and self.normal is None and self.direction is None:
            raise ArgumentError("standoff_mm", "needs a surface `normal` or a `direction` to "
                                               "stand off along")

    # ---------------------------------------------------------------- derived
    @property
    def back(self) -> np.ndarray | None:
        """(3,) unit vector from the surface toward where the tip stands off: ``normal``, else
        minus ``direction``; None for neither."""
        if self.normal is not None:
            return np.asarray(self.normal, dtype=float)
        if self.direction is not None:
            return -np.asarray(self.direction, dtype=float)
        return None

    def point(self, standoff_mm: float | None = None) -> np.ndarray:
        """(3,) mm scene frame: the tip point at ``standoff_mm`` (default the goal's own) from
        ``position``."""
        s = self.standoff_mm if standoff_mm is None else float(standoff_mm)
        back = self.back
        p = np.asarray(self.position, dtype=float)
        return p if back is None or s == 0 else p + s * back

    @property
    def cone_rad(self) -> float | None:
        return None if self.cone_deg is None else math.radians(self.cone_deg)

    def record(self) -> dict:
        """plan.json's ``tip_goal``: the goal as given (normalised)."""
        return {"position": list(self.position),
                "direction": None if self.direction is None else list(self.direction),
                "cone_deg": self.cone_deg, "standoff_mm": self.standoff_mm,
                "normal": None if self.normal is None else list(self.normal)}


# ---------------------------------------------------------------------- tangents
def tip_tangents(points: np.ndarray) -> np.ndarray:
    """(B, 3) unit tip tangents of backbones ``points`` (B, m, 3), m >= 3, evenly spaced in arc
    length: the second-order one-sided difference ``3 p_m - 4 p_(m-1) + p_(m-2)``, normalised
    (NaN where the backbone is degenerate)."""
    p = np.asarray(points, dtype=float)
    if p.ndim != 3 or p.shape[1] < 3:
        raise ValueError(f"points must be (B, m >= 3, 3), got {p.shape}")
    d = 3.0 * p[:, -1] - 4.0 * p[:, -2] + p[:, -3]
    norm = np.linalg.norm(d, axis=1, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(norm > 1e-12, d / norm, np.nan)


def tip_frames(model, q: np.ndarray, points: int = TANGENT_POINTS,
               direction: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Tips (B, 3) mm, unit tip tangents (B, 3) and ok (B,) of configurations q (B, 2n), robot
    base frame, in one batched model call with ``points`` backbone points."""
    q = np.atleast_2d(np.asarray(q, dtype=float))
    shape = model.shape(q, points=points) if direction is None else \
        model.shape(q, points=points, direction=direction)
    t = tip_tangents(shape.points)
    ok = np.asarray(shape.ok, dtype=bool) & np.all(np.isfinite(t), axis=1)
    return shape.tip, t, ok


def angle_deg(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(B,) angle (deg) between unit vectors u (B, 3) and v (3,) or (B, 3) (atan2: accurate
    near 0 and 180)."""
    u = np.atleast_2d(np.asarray(u, dtype=float))
    v = np.broadcast_to(np.asarray(v, dtype=float), u.shape)
    cross = np.linalg.norm(np.cross(u, v), axis=1)
    dot = np.sum(u * v, axis=1)
    return np.degrees(np.arctan2(cross, dot))


def to_base_vectors(scene, vectors: np.ndarray) -> np.ndarray:
    """Directions (..., 3) from the scene frame to the robot base frame (rotation only)."""
    return np.asarray(vectors, dtype=float) @ scene.base_pose[:3, :3]


def to_scene_vectors(scene, vectors: np.ndarray) -> np.ndarray:
    """Directions (..., 3) from the robot base frame to the scene frame (rotation only)."""
    return np.asarray(vectors, dtype=float) @ scene.base_pose[:3, :3].T


# ---------------------------------------------------------------------- surfaces
@dataclass(frozen=True)
class SurfacePoint:
    """The nearest surface point of a scene to a query point.

    point : (3,) mm scene frame, on the mesh; normal : (3,) unit, pointing out of the tissue
    into the lumen (a wall mesh's inward normal, an obstacle's outward one); distance_mm : from
    the query point; mesh : the mesh's name; role : ``wall`` or ``obstacle``.
    """

    point: np.ndarray
    normal: np.ndarray
    distance_mm: float
    mesh: str
    role: str


def snap_to_surface(scene, point) -> SurfacePoint:
    """The nearest point (trimesh's exact closest point on the triangles) of the scene's
    collision meshes (walls and obstacles) to ``point`` (3,) mm, scene frame, with the normal of
    its triangle turned to point into the lumen (:func:`lumen_orientation`).

    Raises ArgumentError (``position``) for a scene without collision meshes."""
    import trimesh

    p = np.asarray(_vector(point, "position"), dtype=float)
    meshes = scene.collision_meshes
    if not meshes:
        raise ArgumentError("position", "the scene has no wall or obstacle mesh to snap to")
    signs = lumen_orientation(scene)
    best: SurfacePoint | None = None
    for k, m in enumerate(meshes):
        closest, dist, tri = trimesh.proximity.closest_point(m.mesh, p[None])
        d = float(dist[0])
        if best is not None and d >= best.distance_mm:
            continue
        n = np.asarray(m.mesh.face_normals[int(tri[0])], dtype=float) * signs[k]
        best = SurfacePoint(point=np.asarray(closest[0], dtype=float), normal=n / np.linalg.norm(n),
                            distance_mm=d, mesh=m.name, role=m.role)
    return best


def lumen_orientation(scene, rays: int = 256) -> np.ndarray:
    """(M,) +1 / -1 per collision mesh: the factor that turns its face normals into the lumen.

    The robot's base lies in the lumen (the scene loader checks it): rays from it meet the
    surfaces that bound the lumen first, and there the normal into the lumen faces back toward
    the base, so each mesh hit gets the majority vote of ``sign(-n . ray)`` over its hits (its
    winding is consistent: the loader's meshes are closed surfaces). A mesh no ray meets first
    keeps its own outward orientation (its signed volume): an obstacle's outward normals point
    into the lumen, a wall's inward ones do."""
    from ctrplan.collision._raycast import fibonacci_directions

    meshes = list(scene.collision_meshes)
    dirs = fibonacci_directions(rays)
    origin = np.repeat(scene.base_pose[:3, 3][None], len(dirs), axis=0)
    first = np.full(len(dirs), np.inf)           # the nearest hit along each ray, over meshes
    owner = np.full(len(dirs), -1)
    facing = np.zeros(len(dirs))
    for k, m in enumerate(meshes):               # (each mesh keeps its own ray tree: trimesh)
        tri, ray, loc = m.mesh.ray.intersects_id(origin, dirs, multiple_hits=False,
                                                 return_locations=True)
        if not len(tri):
            continue
        dist = np.linalg.norm(loc - origin[ray], axis=1)
        near = dist < first[ray]
        ray, tri, dist = ray[near], tri[near], dist[near]
        first[ray], owner[ray] = dist, k
        facing[ray] = -np.sum(m.mesh.face_normals[tri] * dirs[ray], axis=1)
    votes = np.zeros(len(meshes))
    hit = owner >= 0
    np.add.at(votes, owner[hit], np.sign(facing[hit]))
    out = np.empty(len(meshes))
    for k, m in enumerate(meshes):
        if votes[k] != 0:
            out[k] = np.sign(votes[k])
        else:
            outward = 1.0 if float(m.mesh.volume) >= 0 else -1.0
            out[k] = outward * (-1.0 if m.role == "wall" else 1.0)
    return out


def split_goal(target) -> tuple[np.ndarray, TipGoal | None]:
    """A plan's ``target``: a point (3,) mm (returned as it is checked, with None) or a
    :class:`TipGoal` (its standoff point and the goal). ArgumentError (``target``) otherwise."""
    from ctrplan.planning.arguments import check_target

    if isinstance(target, TipGoal):
        return check_target(target.point()), target
    return check_target(target), None


# ---------------------------------------------------------------------- goals from text
#: the farthest (mm) a target is snapped onto the anatomy for a standoff / ``approach normal``
MAX_SNAP_MM = 5.0
#: how the three tip pose values are named in messages: ``plan``'s flags (the targets CSV of
#: ``plan-batch`` names its columns instead: :data:`CSV_NAMES`)
FLAG_NAMES = ("--standoff", "--approach", "--cone")
#: the targets CSV columns of ``plan-batch`` holding the same three values
CSV_NAMES = ("standoff_mm", "approach", "cone_deg")


def _approach_value(text, name: str, error) -> str | list[float]:
    """``normal`` or a non-zero direction X,Y,Z (commas and/or spaces)."""
    import re

    from ctrplan.io import excerpt, strict_float

    if str(text).strip().lower() == "normal":
        return "normal"
    parts = [s for s in re.split(r"[,\s]+", str(text).strip()) if s]
    try:
        vals = [strict_float(s) for s in parts]
    except ValueError:
        vals = []
    if len(vals) == 3 and not all(math.isfinite(v) for v in vals):
        raise error(name, f"must be finite numbers, got {excerpt(str(text))}")
    if len(vals) != 3 or not math.hypot(*vals) > 1e-12:
        raise error(name, f"must be a non-zero direction X,Y,Z or 'normal', got {excerpt(text)}")
    return vals


def parse_goal_values(standoff, approach, cone, names=FLAG_NAMES, error=None) -> tuple:
    """A tip pose goal's values as given in text (None: not given), each checked: standoff
    (mm in [0, :data:`MAX_STANDOFF_MM`] or None), approach (``"normal"``, [3] floats or None)
    and cone (deg in (0, 90] or None; only with an approach). ``names`` name the three values
    in messages (``plan``'s flags, or the CSV columns); ``error(name, message)`` makes the
    exception raised (default: ``InputError(name, "", message)``)."""
    from ctrplan.errors import InputError

    error = error or (lambda name, message: InputError(name, "", message))
    n_standoff, n_approach, n_cone = names
    s = None if standoff is None else _number_value(
        standoff, lambda v: 0 <= v <= MAX_STANDOFF_MM, n_standoff,
        f"a distance in [0, {MAX_STANDOFF_MM:g}] mm", error)
    a = None if approach is None else _approach_value(approach, n_approach, error)
    c = None
    if cone is not None:
        c = _number_value(cone, lambda v: 0 < v <= 90, n_cone, "a half-angle in (0, 90] degrees",
                          error)
        if a is None:
            raise error(n_cone, f"needs {n_approach} (the cone's axis)")
    return s, a, c


def _number_value(text, ok, name: str, what: str, error) -> float:
    """``text`` as a finite number for which ``ok`` holds, else ``error(name, "must be
    <what>, got ...")``."""
    from ctrplan.io import excerpt, strict_float

    try:
        v = strict_float(text)
    except ValueError:
        v = math.nan
    if not (math.isfinite(v) and ok(v)):
        raise error(name, f"must be {what}, got {excerpt(text)}")
    return v


def goal_for_target(target, scene, standoff, approach, cone, field: str = "--target",
                    names=FLAG_NAMES) -> tuple:
    """A plan's goal from a target point (3,) mm, scene frame, and checked tip pose values
    (:func:`parse_goal_values`): the point itself when none is given (a point goal,
    unchanged), else a :class:`TipGoal`. With a standoff or ``approach "normal"`` the target
    is snapped to the nearest wall or obstacle point (with its normal into the lumen), at most
    :data:`MAX_SNAP_MM` away unless an explicit direction lets a free target stand off along
    it (InputError naming ``field`` otherwise). Returns (goal, plan.json's
    ``snap_distance_mm``, ``snap_mesh`` and ``target_given``, or {} without a snap)."""
    from ctrplan.errors import InputError

    if standoff is None and approach is None:
        return target, {}
    direction = None if approach in (None, "normal") else approach
    snap = None
    if standoff is not None or approach == "normal":
        snap = snap_to_surface(scene, target)
        if snap.distance_mm > MAX_SNAP_MM:
            if approach == "normal" or direction is None:
                raise InputError(field, "", f"is {snap.distance_mm:.2f} mm from the nearest "
                                 f"surface ({snap.mesh!r}), more than {MAX_SNAP_MM:g} mm: give a "
                                 f"point on the tissue for {names[0]} / {names[1]} normal, or "
                                 f"{names[1]} X,Y,Z to stand off a free target along it")
            snap = None
    if snap is None:
        return TipGoal(target, direction=direction, cone_deg=cone,
                       standoff_mm=standoff or 0.0), {}
    if approach == "normal":
        direction = -snap.normal
    goal = TipGoal(snap.point, direction=direction, cone_deg=cone, standoff_mm=standoff or 0.0,
                   normal=snap.normal)
    return goal, {"snap_distance_mm": float(snap.distance_mm), "snap_mesh": snap.mesh,
                  "target_given": [float(v) for v in target]}
