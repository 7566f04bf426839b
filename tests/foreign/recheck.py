"""An independent re-check of planned paths: shares no code with ctrplan.

What a plan's "collision-free" is checked against here, built from nothing ctrplan wrote:

* **backbone**: the foreign generator's own mechanics (:func:`tests.foreign.core.truth`:
  torsionally compliant Cosserat rods written from the equations, or any truth robot given as
  foreign effects), evaluated at ``points`` (default 600, at least 500) arc lengths evenly spaced
  from the constraint plane to the tip, plus each tube's distal end (a radius step), placed on
  the chord between its two neighbours;
* **geometry**: an exact cylinder per backbone segment with the outer radius of the outermost
  tube present there (``od / 2`` from the robot YAML, read with ``yaml.safe_load``), and a sphere
  at every interior joint with the smaller radius of its two segments (it fills the wedge
  between two cylinders on the outside of a bend); the tip end is flat. Chords stand in for the
  arc: with ``h`` the segment length (<= 0.53 mm on seed1 at 600 points) the chord is within
  ``kappa h^2 / 8`` (3e-4 mm at kappa 0.0093 / mm) of the backbone, and a tangent jump ``delta``
  where an outer tube ends (a clearance effect) within ``h delta / 4``;
* **anatomy**: the scene's meshes read from ``scene.yaml`` (``yaml.safe_load``) and the PLY
  files (``trimesh``), base pose applied here; FCL (``python-fcl``) is asked directly:
  ``collide`` for contact, ``distance`` for the clearance of a free state, and for a state in
  contact the penetration depth by bisection on the radius (the depth exceeds ``d`` exactly
  when the tube with every radius shrunk by ``d`` still touches a surface; 0.002 mm
  resolution); where even the centreline touches a surface the centreline crosses it
  (``crosses``) and the depth is at least that segment's radius;
* **clearance of a path**: the smallest distance over its states is exact; the work is cut by
  bounds that are proven, not estimated: every STRIDE-th free state asks FCL for each group of
  GROUP segments it must (coarse capsule, then the fine cylinders), and any other state starts
  from its neighbouring anchors' group distances less how far that group's geometry can have
  moved (vertex displacement, segment tilt, radius growth: :func:`_shift_bounds`), asking FCL
  only for groups that could still go below the smallest distance found. Every state's verdict
  is FCL's ``collide``;
* **states**: a dense linear interpolation of the path in the plan.json convention (rotations
  unwrapped: the straight line between consecutive configurations is the motion), at least
  ``per_edge`` (default 10) interpolated states per edge and at most ``step_mm`` (default
  0.25 mm: alpha weighted by ``alpha_weight_mm`` = 30 mm/rad, beta in mm) between two of them.

Direction-dependent effects (friction lags) get each state's direction of motion: the sign of
the joint change along the edge it lies on (the first state keeps the first edge's direction).

    from tests.foreign.recheck import recheck_path, load_scene
    rep = recheck_path("seed1", "airway", plan["path"])            # nominal compliant robot
    rep = recheck_path("seed1", "airway", path, effects=truth_fx)   # a foreign "real" robot
    rep.free, rep.min_clearance_mm, rep.penetrating(0.05), rep.depth_mm.max()
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import fcl
import numpy as np
import yaml

from .core import truth
from .effects import resolve
from .robot import Spec, load_spec, valid

_ANATOMY = Path(__file__).resolve().parents[2] / "anatomy"

#: nominal model of the re-check: torsionally compliant rods with the tubes' physical GJ
NOMINAL = {"torsion": {"gj_scale": 1.0, "coupling": 0.0, "play": 0.0}}
#: bisection resolution of the penetration depth (mm)
DEPTH_TOL_MM = 0.002
#: backbone segments per coarse capsule
GROUP = 24
#: free states between two anchors of the clearance pass (check_states)
STRIDE = 12


# ----------------------------------------------------------------------------- scene
@dataclass
class ForeignScene:
    """Meshes (FCL objects, scene frame, mm), their names and roles, the robot base pose
    (4x4, scene <- base) and the example targets (name -> (3,) mm)."""

    name: str
    names: list
    roles: list
    objects: list
    pose: np.ndarray
    targets: dict

    def to_scene(self, p: np.ndarray) -> np.ndarray:
        return p @ self.pose[:3, :3].T + self.pose[:3, 3]


def _quat_matrix(q) -> np.ndarray:
    w, x, y, z = np.asarray(q, float) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


_SCENES: dict = {}


def load_scene(scene) -> ForeignScene:
    """A shipped scene name or a scene folder (with ``scene.yaml``), read here from the files."""
    key = str(scene)
    if key in _SCENES:
        return _SCENES[key]
    import trimesh

    d = Path(key)
    if not (d / "scene.yaml").exists():
        d = _ANATOMY / key
    with open(d / "scene.yaml", encoding="utf-8") as f:
        data = yaml.safe_load(f)
    names, roles, objects = [], [], []
    for m in data["meshes"]:
        if m.get("role", "wall") not in ("wall", "obstacle"):
            continue
        mesh = trimesh.load(d / m["file"], force="mesh", process=False)
        bvh = fcl.BVHModel()
        v = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
        fc = np.ascontiguousarray(mesh.faces, dtype=np.int32)
        bvh.beginModel(len(v), len(fc))
        bvh.addSubModel(v, fc)
        bvh.endModel()
        names.append(str(m["name"]))
        roles.append(str(m.get("role", "wall")))
        objects.append(fcl.CollisionObject(bvh, fcl.Transform()))
    bp = data.get("base_pose") or {}
    pose = np.eye(4)
    pose[:3, :3] = _quat_matrix(bp.get("quaternion", [1.0, 0.0, 0.0, 0.0]))
    pose[:3, 3] = np.asarray(bp.get("position", [0.0, 0.0, 0.0]), float)
    targets = {str(t["name"]): np.asarray(t["position"], float) for t in data.get("targets") or []}
    sc = ForeignScene(str(data.get("name", d.name)), names, roles, objects, pose, targets)
    _SCENES[key] = sc
    return sc


# ----------------------------------------------------------------------------- states
def densify(path, n: int, per_edge: int = 10, step_mm: float = 0.25,
            alpha_weight_mm: float = 30.0) -> tuple[np.ndarray, np.ndarray]:
    """Linear interpolation of a waypoint path (K, 2n), rotations as given (unwrapped).
    Returns states (N, 2n) including every waypoint, and the edge index of each state (the
    first waypoint: edge 0)."""
    path = np.atleast_2d(np.asarray(path, float))
    states, edge = [path[0]], [0]
    for e, (a, b) in enumerate(zip(path[:-1], path[1:])):
        d = b - a
        dist = alpha_weight_mm * np.abs(d[:n]).sum() + np.abs(d[n:]).sum()
        k = max(int(per_edge), int(np.ceil(dist / step_mm)))
        t = np.linspace(0.0, 1.0, k + 1)[1:]
        states.extend(a + ti * d for ti in t)
        edge.extend([e] * len(t))
    return np.array(states), np.array(edge)


def directions(states: np.ndarray, edge: np.ndarray, path: np.ndarray) -> np.ndarray:
    """Direction of motion (-1, 0, +1) of each joint at each state: the sign of its change
    along the state's edge."""
    path = np.atleast_2d(path)
    if len(path) < 2:
        return np.zeros_like(states, dtype=np.int8)
    d = np.sign(np.diff(path, axis=0)).astype(np.int8)
    return d[np.minimum(edge, len(d) - 1)]


# ----------------------------------------------------------------------------- backbone
def backbone(spec: Spec, q: np.ndarray, effects=None, direction=None, points: int = 600,
             sweep=None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Backbone of each state with its tube ends inserted: points (B, P, 3) in the robot base
    frame, segment radii (B, P-1) (outer radius of the outermost tube on each segment), ok (B,).
    ``points`` evenly spaced samples (>= 500) plus one point per tube end."""
    if points < 500:
        raise ValueError("the re-check samples at least 500 points per shape")
    q = np.atleast_2d(np.asarray(q, float))
    B, n = q.shape[0], spec.n
    eff = resolve(NOMINAL if effects is None else effects, n, spec)
    _, pts, ok = truth(spec, q, eff, direction=direction, sweep=sweep, points=points)
    ends = np.maximum(q[:, n:] + spec.L, 0.0)                 # (B, n) distal ends (arc length)
    L = ends[:, :1]                                           # innermost reaches farthest
    s = np.linspace(0.0, 1.0, points)[None, :] * L            # (B, points)
    # tube ends strictly inside the backbone, placed on their chord
    s_all = np.concatenate([s, np.clip(ends[:, 1:], 0.0, L)], axis=1)
    order = np.argsort(s_all, axis=1, kind="stable")
    s_all = np.take_along_axis(s_all, order, axis=1)
    h = np.where(L > 0, L / (points - 1), 1.0)
    j = np.clip(np.floor(np.clip(s_all, 0.0, None) / h).astype(int), 0, points - 2)
    t = (s_all - j * h) / h
    rows = np.arange(B)[:, None]
    P = pts[rows, j] * (1 - t[..., None]) + pts[rows, j + 1] * t[..., None]
    mid = 0.5 * (s_all[:, 1:] + s_all[:, :-1])                # (B, P-1)
    present = mid[:, :, None] < ends[:, None, :]              # (B, P-1, n)
    outer = np.where(present.any(axis=2), n - 1 - np.argmax(present[:, :, ::-1], axis=2), 0)
    radius = (spec.od / 2.0)[outer]
    ok = ok & valid(spec, q) & np.all(np.isfinite(P), axis=(1, 2))
    return P, radius, ok


# ----------------------------------------------------------------------------- FCL
def _rot_z_to(d: np.ndarray) -> np.ndarray:
    """(K,3) unit vectors -> (K,3,3) rotations taking +z onto them."""
    z = np.array([0.0, 0.0, 1.0])
    v = np.cross(z, d)
    c = d[:, 2]
    K = np.zeros((len(d), 3, 3))
    K[:, 0, 1], K[:, 0, 2] = -v[:, 2], v[:, 1]
    K[:, 1, 0], K[:, 1, 2] = v[:, 2], -v[:, 0]
    K[:, 2, 0], K[:, 2, 1] = -v[:, 1], v[:, 0]
    f = 1.0 / np.maximum(1.0 + c, 1e-12)
    R = np.eye(3)[None] + K + (K @ K) * f[:, None, None]
    flip = c < -1 + 1e-12
    R[flip] = np.diag([1.0, -1.0, -1.0])
    return R


def _tube_objects(P: np.ndarray, radius: np.ndarray, shrink: float = 0.0,
                  segs: np.ndarray | None = None) -> list:
    """FCL cylinders of the segments ``segs`` (default all) and spheres at their interior end
    joints (joint k+1 belongs to segment k); radii shrunk by ``shrink`` (parts whose radius
    would vanish are dropped)."""
    M = len(P) - 1
    segs = np.arange(M) if segs is None else np.asarray(segs)
    a, b = P[segs], P[segs + 1]
    v = b - a
    h = np.linalg.norm(v, axis=1)
    r = radius[segs] - shrink
    keep = (h > 1e-9) & (r > 0)
    R = _rot_z_to(v[keep] / h[keep, None])
    c = 0.5 * (a + b)[keep]
    objs = [fcl.CollisionObject(fcl.Cylinder(float(rk), float(hk)), fcl.Transform(Rk, ck))
            for rk, hk, Rk, ck in zip(r[keep], h[keep], R, c)]
    inner = segs[segs < M - 1]
    rj = np.minimum(radius[inner], radius[inner + 1]) - shrink
    objs += [fcl.CollisionObject(fcl.Sphere(float(rk)), fcl.Transform(P[k + 1]))
             for rk, k in zip(rj, inner) if rk > 0]
    return objs


def _coarse(P: np.ndarray, radius: np.ndarray, shrink: float = 0.0, group: int = GROUP):
    """Capsules that contain the fine geometry of ``group`` consecutive segments each: the
    chord of the group, radius = its largest fine radius + the largest distance of its
    backbone points from the chord (the distance to a segment is convex, so every fine
    cylinder and joint sphere lies inside). Returns (objects, segment index arrays)."""
    M = len(P) - 1
    starts = np.arange(0, M, group)
    stops = np.minimum(starts + group, M)                   # group g: segments starts..stops-1
    A, Bp = P[starts], P[stops]
    AB = Bp - A
    L = np.linalg.norm(AB, axis=1)
    D = np.where(L[:, None] > 0, AB / np.where(L > 0, L, 1.0)[:, None], [0.0, 0.0, 1.0])
    Rs = _rot_z_to(D)
    out, parts = [], []
    for g, (g0, g1) in enumerate(zip(starts, stops)):
        segs = np.arange(g0, g1)
        pts = P[g0:g1 + 1] - A[g]
        t = np.clip(pts @ D[g], 0.0, L[g])
        dev = float(np.max(np.linalg.norm(pts - t[:, None] * D[g], axis=1)))
        r = float(np.max(radius[segs])) - shrink + dev + 1e-9
        parts.append(segs)
        if r <= 0:
            out.append(None)
            continue
        out.append(fcl.CollisionObject(fcl.Capsule(r, float(L[g])),
                                       fcl.Transform(Rs[g], 0.5 * (A[g] + Bp[g]))))
    return out, parts


class _Scene:
    """The scene's meshes and the queries of the re-check (coarse capsules first, the fine
    cylinders only of the groups the coarse ones cannot settle)."""

    def __init__(self, sc: ForeignScene):
        self.sc = sc

    @staticmethod
    def _manager(objs):
        m = fcl.DynamicAABBTreeCollisionManager()
        m.registerObjects(objs)
        m.setup()
        return m

    def _hit_objs(self, objs) -> str | None:
        if not objs:
            return None
        m = self._manager(objs)
        for o, nm in zip(self.sc.objects, self.sc.names):
            data = fcl.CollisionData(request=fcl.CollisionRequest())
            m.collide(o, data, fcl.defaultCollisionCallback)
            if data.result.is_collision:
                return nm
        return None

    def _dist_objs(self, objs) -> float:
        if not objs:
            return np.inf
        m = self._manager(objs)
        best = np.inf
        for o in self.sc.objects:
            data = fcl.DistanceData()
            m.distance(o, data, fcl.defaultDistanceCallback)
            best = min(best, float(data.result.min_distance))
        return best

    def hit(self, P, radius, shrink: float = 0.0) -> str | None:
        """Name of a mesh the tube (radii shrunk by ``shrink``) touches, None if none."""
        caps, parts = _coarse(P, radius, shrink)
        for c, segs in zip(caps, parts):
            if c is None or self._hit_objs([c]) is None:
                continue
            nm = self._hit_objs(_tube_objects(P, radius, shrink, segs))
            if nm is not None:
                return nm
        return None

    def distance(self, P, radius, lower=None, best: float = np.inf):
        """FCL distance from a free tube to the nearest mesh, asked group by group in order of
        the group's lower bound: ``lower`` (G,) known lower bounds per coarse group (default 0:
        the tube is free), then the group's coarse capsule, then its fine cylinders, until no
        group's bound is below the smallest distance found (or ``best``, a clearance already
        found elsewhere on the path). Returns (the state's distance: exact where below ``best``,
        else a lower bound >= ``best``; per-group lower bounds, exact where the fine geometry
        was asked)."""
        caps, parts = _coarse(P, radius)
        val = np.zeros(len(caps)) if lower is None else np.maximum(lower, 0.0)
        stage = np.zeros(len(caps), int)                  # 0: bound, 1: coarse, 2: fine (exact)
        own = np.inf
        while True:
            g = int(np.argmin(np.where(stage < 2, val, np.inf)))
            if stage[g] == 2 or val[g] >= min(best, own):
                break
            if stage[g] == 0:
                c = np.inf if caps[g] is None else self._dist_objs([caps[g]])
                val[g] = max(val[g], c)
            else:
                val[g] = self._dist_objs(_tube_objects(P, radius, 0.0, parts[g]))
                own = min(own, val[g])
            stage[g] += 1
        return float(min(own, val.min())), val


def _shift_bounds(Pj: np.ndarray, rj: np.ndarray, Pi: np.ndarray, ri: np.ndarray,
                  group: int = GROUP) -> np.ndarray:
    """Per coarse group: how much closer to any surface state j's geometry of that group can be
    than state i's (same number of backbone points); every point of it lies within the bound
    of a point of i's same group, so its distance_j >= distance_i - bound. A point c_j(t) + u
    of segment s (u normal to it, |u| <= r_j) maps to c_i(t) + R u (R: the smallest rotation
    between the two segment directions, u cut to r_i), moved by at most
    max(|dP_s|, |dP_s+1|) + r_j 2 sin(theta / 2) + max(r_j - r_i, 0); a joint sphere (joint s+1
    belongs to segment s) by |dP| + the radius growth. inf where i lacks a segment j has."""
    dv = np.linalg.norm(Pj - Pi, axis=1)
    vj, vi = np.diff(Pj, axis=0), np.diff(Pi, axis=0)
    hj, hi = np.linalg.norm(vj, axis=1), np.linalg.norm(vi, axis=1)
    has = (hj > 1e-9) & (rj > 0)                              # j's cylinders (_tube_objects)
    cos = np.einsum("ij,ij->i", vj, vi) / np.maximum(hj * hi, 1e-300)
    tilt = np.sqrt(np.clip(2.0 - 2.0 * cos, 0.0, 4.0))         # 2 sin(theta / 2)
    grow = np.maximum(rj - ri, 0.0)
    seg = np.where(has, np.maximum(dv[:-1], dv[1:]) + rj * tilt + grow, 0.0)
    seg[has & ((hi <= 1e-9) | (ri <= 0))] = np.inf
    seg[:-1] = np.maximum(seg[:-1], dv[1:-1] + np.maximum(grow[:-1], grow[1:]))
    return np.maximum.reduceat(seg, np.arange(0, len(seg), group))


# ----------------------------------------------------------------------------- report
@dataclass
class RecheckReport:
    """Per state: ``states`` (N, 2n), ``edge`` (N,), ``clearance_mm`` (N,) signed: the FCL
    distance from the tube to the nearest mesh where free (where a state cannot be the smallest
    over the states, a proven lower bound of it: the minimum over the states is exact), minus
    the penetration depth where in contact; ``depth_mm`` (N,) penetration depth (0 where free;
    a lower bound where ``crosses``); ``contact`` (N,) mesh name or "" ("model" where the
    mechanics failed or the state breaks the joint constraints); ``crosses`` (N,) the
    centreline itself touches a surface; ``tip`` (N, 3) scene frame."""

    states: np.ndarray
    edge: np.ndarray
    clearance_mm: np.ndarray
    depth_mm: np.ndarray
    contact: np.ndarray
    crosses: np.ndarray
    tip: np.ndarray

    @property
    def free(self) -> bool:
        return bool(np.all(self.contact == ""))

    @property
    def min_clearance_mm(self) -> float:
        return float(np.min(self.clearance_mm)) if len(self.clearance_mm) else float("nan")

    def penetrating(self, depth_mm: float = 0.0) -> int:
        """States in contact whose penetration is deeper than ``depth_mm`` (mechanics failures
        count as penetrating: nothing is known about them)."""
        bad = (self.contact != "") & ~(self.depth_mm <= depth_mm)    # NaN depth: unknown
        return int(np.sum(bad))

    def summary(self) -> dict:
        return {"states": int(len(self.edge)), "free": self.free,
                "min_clearance_mm": self.min_clearance_mm,
                "contact_states": int(np.sum(self.contact != "")),
                "penetrating_states_0.05mm": self.penetrating(0.05),
                "max_depth_mm": float(np.max(self.depth_mm)) if len(self.depth_mm) else 0.0,
                "centreline_crossings": int(np.sum(self.crosses))}


def check_states(robot, scene, q, effects=None, direction=None, points: int = 600,
                 distances: bool = True, sweep=None, depths: bool = True,
                 stop_at_first: bool = False) -> RecheckReport:
    """Re-check configurations (N, 2n) (one state each, no interpolation). ``direction``
    (N, 2n) and ``sweep`` (N,) as for the foreign generator (rows in order of motion).
    ``distances=False``: no clearance of free states (NaN); ``depths=False``: no penetration
    depth (NaN); ``stop_at_first``: states after the first in contact are not checked (their
    contact is "unchecked")."""
    spec = load_spec(robot)
    sc = scene if isinstance(scene, ForeignScene) else load_scene(scene)
    q = np.atleast_2d(np.asarray(q, float))
    N = len(q)
    clear = np.full(N, np.nan)
    depth = np.zeros(N)
    contact = np.array([""] * N, dtype=object)
    crosses = np.zeros(N, bool)
    tip = np.full((N, 3), np.nan)
    world = _Scene(sc)

    def full(i, Ps, rad, dist):
        """Contact (and depth) or clearance of one state, FCL asked directly."""
        hit = world.hit(Ps, rad)
        if hit is None:
            clear[i] = world.distance(Ps, rad)[0] if dist else np.nan
            return
        contact[i] = hit
        if not depths:
            depth[i] = clear[i] = np.nan
            return
        if world.hit(Ps, np.full(len(rad), 1e-5)) is not None:
            crosses[i] = True
        lo_d, hi_d = 0.0, float(rad.max())
        while hi_d - lo_d > DEPTH_TOL_MM:
            mid = 0.5 * (lo_d + hi_d)
            if world.hit(Ps, rad, shrink=mid) is not None:
                lo_d = mid
            else:
                hi_d = mid
        depth[i] = hi_d
        clear[i] = -hi_d

    # friction history runs along the rows: then one batch
    step = N if sweep is not None else 256
    for lo in range(0, N, max(step, 1)):
        idx = np.arange(lo, min(lo + step, N))
        dirs = None if direction is None else np.asarray(direction)[idx]
        sw = None if sweep is None else np.asarray(sweep)[idx]
        P, rad, ok = backbone(spec, q[idx], effects, dirs, points, sweep=sw)
        Ps = np.full_like(P, np.nan)
        for k, i in enumerate(idx):
            if ok[k]:
                Ps[k] = sc.to_scene(P[k])
                tip[i] = Ps[k, -1]
            else:
                contact[i], clear[i], depth[i] = "model", -np.inf, np.inf
        if not distances or stop_at_first:
            for k, i in enumerate(idx):
                if stop_at_first and np.any(contact[:i] != ""):
                    contact[i] = "unchecked"
                elif ok[k]:
                    full(i, Ps[k], rad[k], distances)
            continue
        # every state's verdict (FCL collide), and the exact smallest clearance over the states:
        # every STRIDE-th free state (an anchor) asks FCL for every group it must; any other free
        # state starts from its nearest anchors' per-group distances less how far the group can
        # have moved (_shift_bounds) and asks FCL only for groups that could still go below the
        # smallest clearance found
        for k, i in enumerate(idx):
            if ok[k]:
                full(i, Ps[k], rad[k], False)
        free = [k for k in range(len(idx)) if ok[k] and contact[idx[k]] == ""]
        anchors = sorted(set(free[::STRIDE] + free[-1:]))        # the last one asked once
        vals = {}
        for k in anchors:
            clear[idx[k]], vals[k] = world.distance(Ps[k], rad[k])
        best = float(np.nanmin(clear[idx], initial=np.inf))
        pos = np.array(anchors)
        for k in free:
            if k in vals:
                continue
            j = np.searchsorted(pos, k)
            lower = np.zeros(len(vals[anchors[0]]))
            for a in pos[max(j - 1, 0):j + 1]:
                lower = np.maximum(lower, vals[a] - _shift_bounds(Ps[k], rad[k], Ps[a], rad[a]))
            clear[idx[k]], _ = world.distance(Ps[k], rad[k], lower, best)
            best = min(best, clear[idx[k]])
    return RecheckReport(q, np.zeros(N, int), clear, depth, contact, crosses, tip)


def recheck_path(robot, scene, path, effects=None, per_edge: int = 10, step_mm: float = 0.25,
                 points: int = 600, distances: bool = True, sweep_history: bool = True,
                 depths: bool = True, stop_at_first: bool = False) -> RecheckReport:
    """Re-check a planned path (K, 2n) on the robot with ``effects`` (foreign effect dict;
    None: the nominal compliant robot) in ``scene`` (name, folder or :class:`ForeignScene`):
    densified (:func:`densify`), backbone, cylinders and FCL as in the module docstring."""
    spec = load_spec(robot)
    path = np.atleast_2d(np.asarray(path, float))
    states, edge = densify(path, spec.n, per_edge, step_mm)
    dirs = directions(states, edge, path)
    sweep = np.zeros(len(states), dtype=int) if sweep_history else None
    rep = check_states(spec, scene, states, effects, dirs, points, distances, sweep, depths,
                       stop_at_first)
    rep.edge = edge
    return rep
