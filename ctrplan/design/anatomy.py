"""The anatomy read before any design is sampled: corridors from the entry to each target.

From the scene's distance fields (:mod:`ctrplan.collision.field`, the fields collision checking
already builds and caches) this module estimates, on the field's grid (spacing ``h``, 0.5 mm by
default), the clearance ``d`` of every node: the distance to the nearest wall or obstacle
surface (the mean of the field's lower and upper bound; nodes outside a closed wall that holds
the base, or inside an obstacle, are not free). Then, per target:

- **bottleneck**: the largest clearance ``b`` (at most the base point's own) such that the base
  and the target are connected through nodes with ``d >= b`` (:mod:`ctrplan.design.corridor`)
  -- a tube of radius above ``b`` cannot reach the target (up to the grid's
  resolution), whatever its design; where the corridor may be too narrow for the smallest stock
  tube (narrower than its diameter + 2 h), the narrowest cross-section is measured again from the
  mesh itself (trimesh's closest points, refined to a 0.1 mm grid);
- **centreline**: the cheapest path (scikit-image's minimum-cost path, 26-connected) from the base
  to the target through nodes with ``d >= b``, each step costing its length times
  ``1 + (1 mm / d)^2`` (it keeps to the middle of the lumen), resampled every 1 mm and smoothed
  (Gaussian, 2 mm); along it the clearance profile, the depth (arc length), the **narrowest**
  place (width ``2 d``, arc length from the entry, position) and the **bends** (stretches where
  the centreline's curvature exceeds 1/80 mm and that turn by more than 10 degrees: where they
  start, their angle, length and radius);
- the **entry room**: how far the retracted robot can protrude from the base: for each stock
  radius, the straight distance along the base's +z before the clearance drops below it, and the
  longest circular arc of each curvature (best of 16 bending directions) that keeps it.

Everything is in the scene frame unless named ``base``. Results are estimates at the field's
resolution (stated in design.json as ``anatomy.resolution_mm``), used to derive the design space
(:mod:`ctrplan.design.derive`) and to explain what blocks a target
(:mod:`ctrplan.design.explain`); the screen and the plans still decide every design exactly.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass

import numpy as np

from ctrplan.design.corridor import bottlenecks, centrelines, crop

log = logging.getLogger("ctrplan")

#: Curvature (1/mm) above which the centreline counts as bending, and the smallest bend kept.
BEND_CURVATURE = 1.0 / 80.0
BEND_MIN_DEG = 10.0
#: Smoothing (mm) of the centreline and its resampling step.
SMOOTH_MM = 2.5
STEP_MM = 1.0
#: Curvatures (1/mm) of the entry-room table and the bending directions tried.
ENTRY_KAPPA = np.round(np.arange(0.0, 0.1201, 0.005), 4)
ENTRY_DIRECTIONS = 16
ENTRY_MAX_MM = 200.0


@dataclass(frozen=True)
class Bend:
    """A bend of a corridor: starts ``at_mm`` past the entry (arc length), turns by
    ``angle_deg`` over ``length_mm``."""

    at_mm: float
    angle_deg: float
    length_mm: float

    @property
    def curvature(self) -> float:
        """Mean curvature (1/mm) of the bend."""
        return math.radians(self.angle_deg) / max(self.length_mm, 1e-9)

    @property
    def radius_mm(self) -> float:
        return 1.0 / max(self.curvature, 1e-12)


@dataclass(frozen=True)
class Narrowest:
    """The narrowest place of a corridor: ``width_mm`` (twice the clearance), ``at_mm`` past the
    entry (arc length along the centreline), ``position`` (3,) scene frame; ``refined``: the
    width was measured from the mesh (else the field's estimate)."""

    width_mm: float
    at_mm: float
    position: np.ndarray
    refined: bool = False


@dataclass(frozen=True)
class Route:
    """The corridor from the entry to one target (see the module docstring).

    connected : a corridor with positive clearance reaches within ``target_gap_mm`` of it.
    target_gap_mm : distance from the target to the corridor's nearest free node (0 inside).
    bottleneck_mm : the largest tube radius that can pass (maximin clearance), mm.
    depth_mm : arc length of the centreline from the base to the target; straight_mm: the
        straight distance. centreline (K, 3) scene frame, s (K,) arc length, clearance (K,) mm.
    """

    name: str
    target: np.ndarray
    connected: bool
    target_gap_mm: float
    bottleneck_mm: float
    narrowest: Narrowest | None
    depth_mm: float
    straight_mm: float
    bends: tuple[Bend, ...]
    centreline: np.ndarray
    s: np.ndarray
    clearance: np.ndarray

    def place(self, s_mm: float) -> np.ndarray:
        """Scene position (3,) at arc length ``s_mm`` along the centreline."""
        if len(self.s) == 0:
            return np.asarray(self.target, dtype=float)
        return np.array([np.interp(s_mm, self.s, self.centreline[:, k]) for k in range(3)])

    def to_json(self) -> dict:
        n = self.narrowest
        return {"target": self.name, "position": [float(v) for v in self.target],
                "connected": self.connected,
                "target_gap_mm": round(self.target_gap_mm, 3) if math.isfinite(self.target_gap_mm) else None,
                "bottleneck_width_mm": round(2 * self.bottleneck_mm, 3),
                "narrowest": None if n is None else {
                    "width_mm": round(n.width_mm, 3), "at_mm": round(n.at_mm, 2),
                    "position": [round(float(v), 3) for v in n.position], "refined": n.refined},
                "depth_mm": round(self.depth_mm, 2) if math.isfinite(self.depth_mm) else None,
                "straight_mm": round(self.straight_mm, 2),
                "bends": [{"at_mm": round(b.at_mm, 1), "angle_deg": round(b.angle_deg, 1),
                           "length_mm": round(b.length_mm, 1), "radius_mm": round(b.radius_mm, 1)}
                          for b in self.bends]}


@dataclass(frozen=True)
class EntryRoom:
    """How far the retracted robot can protrude from the base.

    radii (R,) mm; straight_mm (R,): straight distance along the base's +z with clearance >=
    radius; exit (R, 3) scene position where the straight line runs out of room; kappa (M,)
    1/mm; curved_mm (R, M): the longest arc of that curvature from the base (tangent +z, best
    of the bending directions) that keeps the clearance.
    """

    radii: np.ndarray
    straight_mm: np.ndarray
    exit: np.ndarray
    kappa: np.ndarray
    curved_mm: np.ndarray

    def longest(self, radius: float, kappa: float) -> float:
        """Longest protrusion (mm) of an arc of curvature ``kappa`` for a tube of ``radius``
        (the nearest tabulated radius at or above it; interpolated in kappa)."""
        i = int(np.searchsorted(self.radii, radius - 1e-9))
        if i >= len(self.radii):
            return 0.0
        return float(np.interp(kappa, self.kappa, self.curved_mm[i]))

    def to_json(self) -> dict:
        return {"radii_mm": [round(float(r), 3) for r in self.radii],
                "straight_mm": [round(float(v), 2) for v in self.straight_mm],
                "exit": [[round(float(x), 3) for x in p] for p in self.exit],
                "kappa_per_mm": [float(k) for k in self.kappa],
                "curved_mm": [[round(float(v), 2) for v in row] for row in self.curved_mm]}


@dataclass(frozen=True)
class Anatomy:
    """Routes per target, the entry room, the grid's resolution (mm) and the clearance at the
    base (mm)."""

    routes: tuple[Route, ...]
    entry: EntryRoom
    resolution_mm: float
    base_clearance_mm: float

    def to_json(self) -> dict:
        return {"resolution_mm": round(self.resolution_mm, 3),
                "base_clearance_mm": round(self.base_clearance_mm, 3),
                "routes": [r.to_json() for r in self.routes], "entry": self.entry.to_json()}


# ----------------------------------------------------------------------------- the grid
@dataclass
class _Grid:
    """Node clearance estimates ``d`` (nx, ny, nz) float32 (-1 where not free) on the grid of
    one field, and the fields (with the side each must not be on) for point queries."""

    origin: np.ndarray
    h: float
    d: np.ndarray
    fields: list
    bad: list
    rho: float

    def node(self, p: np.ndarray) -> tuple[int, int, int]:
        i = np.rint((np.asarray(p, float) - self.origin) / self.h).astype(int)
        return tuple(int(v) for v in np.clip(i, 0, np.array(self.d.shape) - 1))

    def at(self, points: np.ndarray) -> np.ndarray:
        """Clearance estimate (N,) at scene points: the fields' upper bound less half their
        sampling error (the upper bound is a distance to a true surface point); -1 on a side
        that is not free."""
        from ctrplan.collision.field import point_bounds

        p = np.asarray(points, float).reshape(-1, 3)
        out = np.full(len(p), np.inf)
        for f, bad in zip(self.fields, self.bad):
            lo, up, sd = point_bounds(f, p)
            est = np.where(np.isfinite(up), up - 0.5 * f.rho, lo)
            if bad:
                est = np.where(sd == bad, -1.0, est)
            out = np.minimum(out, est)
        return out


def _estimate(f) -> np.ndarray:
    """Node estimates of one field: upper bound less half the sampling error (mm)."""
    return np.where(np.isfinite(f.ub), f.ub - 0.5 * f.rho, f.lb).astype(np.float32)


def clearance_grid(scene, world) -> _Grid:
    """Clearance estimate on the grid of the wall field that holds the base (the first field
    when none does); other meshes are evaluated at its nodes (:func:`point_bounds`)."""
    from ctrplan.collision.field import point_bounds

    meshes = scene.collision_meshes
    fields = list(world.fields)
    base = np.asarray(scene.base_pose, float)[:3, 3]
    bad = [_bad_side(m, base) if f.watertight else 0 for m, f in zip(meshes, fields)]
    ref = 0
    for k, (m, f) in enumerate(zip(meshes, fields)):
        if m.role == "wall" and point_bounds(f, base[None])[2][0] == -1:
            ref = k
            break
    f0 = fields[ref]
    d = _estimate(f0)
    if bad[ref]:
        d[f0.side == bad[ref]] = -1.0
    if len(fields) > 1:
        nodes = np.stack(np.indices(d.shape), axis=-1).reshape(-1, 3) * f0.h + f0.origin
        for k, f in enumerate(fields):
            if k == ref:
                continue
            lo, up, sd = point_bounds(f, nodes)
            est = np.where(np.isfinite(up), up - 0.5 * f.rho, lo)
            if bad[k]:
                est[sd == bad[k]] = -1.0
            d = np.minimum(d, est.reshape(d.shape).astype(np.float32))
    return _Grid(np.asarray(f0.origin, float), float(f0.h), d, fields, bad,
                 float(max(f.rho for f in fields)))


def _bad_side(mesh, base: np.ndarray) -> int:
    """+1: a closed wall holding the base (outside is not free); -1: a closed obstacle."""
    m = mesh.mesh
    if not m.is_watertight:
        return 0
    if mesh.role == "wall":
        return 1 if bool(m.contains(base[None])[0]) else 0
    return -1


# ----------------------------------------------------------------------------- routes
def _end_nodes(grid: _Grid, target: np.ndarray, tol: float) -> np.ndarray:
    """Flat indices of free nodes within ``tol`` of the target (the nearest free node when none)."""
    r = int(math.ceil(tol / grid.h)) + 1
    c = np.array(grid.node(target))
    lo = np.maximum(c - r, 0)
    hi = np.minimum(c + r + 1, grid.d.shape)
    idx = np.stack(np.meshgrid(*[np.arange(a, b) for a, b in zip(lo, hi)], indexing="ij"), -1).reshape(-1, 3)
    dist = np.linalg.norm(idx * grid.h + grid.origin - target, axis=1)
    ok = (dist <= tol) & (grid.d[tuple(idx.T)] > 0)
    return np.ravel_multi_index(idx[ok].T, grid.d.shape)


def _smooth(path: np.ndarray, base: np.ndarray, target: np.ndarray,
            pinned: bool = True) -> np.ndarray:
    """Base, the node path and the target, resampled every STEP_MM and smoothed (with
    ``pinned``, blended back to the raw points within 2 SMOOTH_MM of the ends, so the
    centreline starts at the base and ends at the target)."""
    from scipy.ndimage import gaussian_filter1d

    p = np.vstack([base, path, target])
    seg = np.linalg.norm(np.diff(p, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if s[-1] <= 0:
        return p[:1]
    n = max(2, int(math.ceil(s[-1] / STEP_MM)) + 1)
    u = np.linspace(0.0, s[-1], n)
    q = np.column_stack([np.interp(u, s, p[:, k]) for k in range(3)])
    sig = SMOOTH_MM / (u[1] - u[0])
    sm = np.column_stack([gaussian_filter1d(q[:, k], sig, mode="nearest") for k in range(3)])
    if not pinned:
        return sm
    w = np.clip(np.minimum(u, u[-1] - u) / (2 * SMOOTH_MM), 0.0, 1.0)[:, None]
    return q * (1 - w) + sm * w


def _bends(c: np.ndarray) -> tuple[np.ndarray, tuple[Bend, ...]]:
    """Arc length (K,) and the bends of a smoothed centreline (K, 3)."""
    seg = np.linalg.norm(np.diff(c, axis=0), axis=1)
    s = np.concatenate([[0.0], np.cumsum(seg)])
    if len(c) < 5:
        return s, ()
    t = np.gradient(c, s, axis=0)
    t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-12)
    k = np.linalg.norm(np.gradient(t, s, axis=0), axis=1)
    on = k > BEND_CURVATURE
    bends = []
    i = 0
    while i < len(on):
        if not on[i]:
            i += 1
            continue
        j = i
        while j + 1 < len(on) and on[j + 1]:
            j += 1
        a, b = max(i - 1, 0), min(j + 1, len(c) - 1)
        ang = math.degrees(math.acos(float(np.clip(t[a] @ t[b], -1.0, 1.0))))
        if ang >= BEND_MIN_DEG:
            bends.append(Bend(float(s[a]), ang, float(s[b] - s[a])))
        i = j + 1
    return s, tuple(bends)


def _free_distance(scene, pts: np.ndarray) -> np.ndarray:
    """Signed distance (N,) from points to the nearest collision mesh, measured on the meshes
    (trimesh's closest points): positive on the free side (inside a wall, outside an
    obstacle), the side taken from the closest triangle's outward normal."""
    import trimesh

    out = np.full(len(pts), np.inf)
    for m in scene.collision_meshes:
        c, d, tri = trimesh.proximity.ProximityQuery(m.mesh).on_surface(pts)
        outward = np.einsum("ij,ij->i", pts - c, m.mesh.face_normals[tri]) > 0
        inside = np.where(outward, -d, d)
        out = np.minimum(out, inside if m.role == "wall" else -inside)
    return out


def _refine_width(scene, centre: np.ndarray, tangent: np.ndarray, span: float = 1.5,
                  half: float = 1.6) -> float | None:
    """Width (mm) of the narrowest cross-section near ``centre`` measured on the mesh: for
    cross-sections perpendicular to ``tangent`` every 0.5 mm within +-span, twice the largest
    distance to the mesh on the free side (:func:`_free_distance`), found on a 0.4 mm grid
    over +-half mm and refined on a 0.1 mm grid around the best point; the smallest of them."""
    t = tangent / max(np.linalg.norm(tangent), 1e-12)
    a = np.cross(t, [1.0, 0.0, 0.0] if abs(t[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(t, a)

    def plane(cu: float, cv: float, h: float, step: float) -> tuple[np.ndarray, np.ndarray]:
        g = np.arange(-h, h + 1e-9, step)
        U, V = np.meshgrid(cu + g, cv + g, indexing="ij")
        uv = np.column_stack([U.ravel(), V.ravel()])
        return uv, uv[:, :1] * a + uv[:, 1:] * b

    widths = []
    for off in np.arange(-span, span + 1e-9, 0.5):
        o = centre + off * t
        uv, pl = plane(0.0, 0.0, half, 0.4)
        d = _free_distance(scene, o + pl)
        k = int(np.argmax(d))
        uv2, pl2 = plane(uv[k, 0], uv[k, 1], 0.4, 0.1)
        d2 = _free_distance(scene, o + pl2)
        widths.append(2.0 * max(float(max(d.max(), d2.max())), 0.0))
    return min(widths) if widths else None


def _route(grid: _Grid, scene, name: str, target: np.ndarray, start: tuple, base: np.ndarray,
           ends: np.ndarray, bottleneck: float, refine_below: float, tol: float,
           closures: dict, path: np.ndarray | None) -> Route:
    straight = float(np.linalg.norm(target - base))
    empty = np.zeros((0, 3)), np.zeros(0), np.zeros(0)
    if len(ends) == 0:           # the target lies outside the lumen: how far from it
        free = np.argwhere(grid.d > 0)
        gap = float(np.min(np.linalg.norm(free * grid.h + grid.origin - target, axis=1))) if len(free) else math.inf
        return Route(name, target, False, gap, 0.0, None, math.nan, straight, (), *empty)
    near = np.stack(np.unravel_index(ends, grid.d.shape), 1) * grid.h + grid.origin
    gap = 0.0 if grid.at(target[None])[0] > 0 else float(np.linalg.norm(near - target, axis=1).min())
    if path is None:
        closed = _closure(grid, scene, start, base, ends, closures)
        return Route(name, target, False, gap, 0.0, closed, math.nan, straight, (), *empty)
    c = _smooth(path, base, target)
    s, _ = _bends(c)
    # bends from the centreline smoothed to its ends (the pinned ends kink on the node grid)
    _, bends = _bends(_smooth(path, base, target, pinned=False))
    clr = np.maximum(grid.at(c), 0.0)
    # the narrowest place: along the smoothed centreline (a path too: its minimum is a lower
    # bound of the corridor's), or the node path's bottleneck where that is wider
    body = s <= s[-1] - tol
    k = int(np.argmin(np.where(body, clr, np.inf))) if body.any() else 0
    width, at, pos = 2.0 * float(clr[k]), float(s[k]), c[k]
    if 2.0 * bottleneck > width:
        node_clr = grid.at(path)
        j = int(np.argmin(node_clr))
        width, pos = 2.0 * bottleneck, path[j]
        at = float(s[int(np.argmin(np.linalg.norm(c - path[j], axis=1)))])
    refined = False
    if width < refine_below:
        kk = int(np.argmin(np.linalg.norm(c - pos, axis=1)))
        w = _refine_width(scene, pos, c[min(kk + 2, len(c) - 1)] - c[max(kk - 2, 0)])
        if w is not None:
            width, refined = w, True
    return Route(name, target, True, gap, 0.5 * width, Narrowest(width, at, pos, refined),
                 float(s[-1]), straight, bends, c, s, clr)


def _closure(grid: _Grid, scene, start: tuple, base: np.ndarray, ends: np.ndarray,
             cache: dict) -> Narrowest | None:
    """Where the corridor to a target closes: the closest pair of nodes between the base's free
    component and the target's; width measured on the mesh across the gap, arc length along
    the base side's centreline to it plus half the gap (``cache``: per target component)."""
    from scipy import ndimage
    from scipy.spatial import cKDTree

    free = grid.d > 0
    if "labels" not in cache:
        cache["labels"] = ndimage.label(free, structure=np.ones((3, 3, 3), bool))[0]
    lab = cache["labels"]
    e = tuple(int(v) for v in np.unravel_index(ends[0], grid.d.shape))
    key = int(lab[e])
    if key in cache:
        return cache[key]
    a = lab == lab[start]
    bmask = lab == key
    if not free[start] or key == 0:
        cache[key] = None
        return None
    pa = np.argwhere(a) * grid.h + grid.origin
    pb = np.argwhere(bmask) * grid.h + grid.origin
    dist, idx = cKDTree(pb).query(pa)
    i = int(np.argmin(dist))
    p, q = pa[i], pb[idx[i]]
    mid = 0.5 * (p + q)
    (path,) = centrelines(grid, crop(grid, start), start,
                           [np.array([np.ravel_multi_index(grid.node(p), grid.d.shape)])], np.array([1e-3]))
    s_mid = 0.0
    if path is not None:
        c = np.vstack([base, path, mid])
        s_mid = float(np.sum(np.linalg.norm(np.diff(c, axis=0), axis=1)))
    w = _refine_width(scene, mid, q - p)
    cache[key] = Narrowest(0.0 if w is None else w, s_mid, mid, w is not None)
    return cache[key]


# ----------------------------------------------------------------------------- entry room
def entry_room(grid: _Grid, scene, radii: np.ndarray) -> EntryRoom:
    """The straight and curved protrusion tables (see :class:`EntryRoom`)."""
    radii = np.sort(np.unique(np.round(np.asarray(radii, float), 4)))
    s = np.arange(0.0, ENTRY_MAX_MM + 1e-9, 0.25)
    pose = np.asarray(scene.base_pose, float)
    axis = np.column_stack([np.zeros_like(s), np.zeros_like(s), s])
    clr = grid.at(axis @ pose[:3, :3].T + pose[:3, 3])
    straight = np.array([_run(clr, r, s) for r in radii])
    exits = np.array([pose[:3, :3] @ [0.0, 0.0, v] + pose[:3, 3] for v in straight])
    phi = np.arange(ENTRY_DIRECTIONS) * 2 * math.pi / ENTRY_DIRECTIONS
    curved = np.zeros((len(radii), len(ENTRY_KAPPA)))
    for m, k in enumerate(ENTRY_KAPPA):
        if k == 0:
            curved[:, m] = straight
            continue
        th = np.minimum(k * s, math.pi)                   # arcs end at a half turn
        r_ = (1 - np.cos(th)) / k
        z = np.sin(th) / k
        pts = np.stack([np.stack([np.cos(f) * r_, np.sin(f) * r_, z], 1) for f in phi])   # (D, S, 3)
        c = grid.at(pts.reshape(-1, 3) @ pose[:3, :3].T + pose[:3, 3]).reshape(len(phi), len(s))
        for i, r in enumerate(radii):
            curved[i, m] = max(_run(c[f], r, s) for f in range(len(phi)))
    return EntryRoom(radii, straight, exits, ENTRY_KAPPA.copy(), curved)


def _run(clr: np.ndarray, r: float, s: np.ndarray) -> float:
    """Arc length before the clearance first drops below r."""
    bad = np.flatnonzero(clr < r)
    return float(s[bad[0]]) if len(bad) else float(s[-1])


# ----------------------------------------------------------------------------- main
def analyse(scene, world, names, targets: np.ndarray, radii, tolerance_mm: float = 1.0,
            refine_below_mm: float | None = None) -> Anatomy:
    """Read the anatomy (module docstring). ``targets`` (T, 3) scene frame; ``radii``: the
    tube radii (mm) the entry room is tabulated for (the stock sizes'); a bottleneck narrower
    than ``refine_below_mm`` (default: the largest stock diameter) is measured again from the
    mesh."""
    import time

    t0 = time.perf_counter()
    grid = clearance_grid(scene, world)
    base = np.asarray(scene.base_pose, float)[:3, 3]
    start = _start_node(grid, base)
    base_clear = float(max(grid.at(base[None])[0], 0.0))
    targets = np.atleast_2d(np.asarray(targets, float))
    ends = [_end_nodes(grid, t, tolerance_mm + grid.h) for t in targets]
    # the base point's own clearance (interpolated) caps every corridor: the robot leaves there
    crop_ = crop(grid, start)
    bott = bottlenecks(crop_, start, ends, grid.d.shape, cap=base_clear)
    paths = centrelines(grid, crop_, start, ends, bott)
    refine = (refine_below_mm if refine_below_mm is not None
              else 2.0 * float(np.min(radii)) + 2.0 * grid.h)
    closures: dict = {}
    routes = tuple(_route(grid, scene, str(n), t, start, base, e, b, refine, tolerance_mm, closures, p)
                   for n, t, e, b, p in zip(names, targets, ends, bott, paths))
    entry = entry_room(grid, scene, radii)
    log.debug("anatomy read in %.2f s (%d targets, grid %s at %.2f mm)", time.perf_counter() - t0,
             len(targets), grid.d.shape, grid.h)
    return Anatomy(routes, entry, grid.h, base_clear)


def _start_node(grid: _Grid, base: np.ndarray) -> tuple:
    """The node with the most clearance among the 8 around the base point (the nearest node
    can sit up to h sqrt(3) / 2 off the lumen's axis)."""
    f = np.floor((base - grid.origin) / grid.h).astype(int)
    best, arg = -np.inf, grid.node(base)
    for o in np.ndindex(2, 2, 2):
        i = tuple(int(v) for v in np.clip(f + o, 0, np.array(grid.d.shape) - 1))
        if grid.d[i] > best:
            best, arg = float(grid.d[i]), i
    return arg
