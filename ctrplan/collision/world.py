"""CollisionWorld: batched whole-shape collision checks of robot backbones against a scene.

Verdicts are exact (capsule chains vs the wall and obstacle meshes): FCL's, or for meshes of
millions of triangles those of a lean grid of triangle lists (:mod:`ctrplan.collision._grid`,
``exact=``). The prefilter (:mod:`ctrplan.collision.field`) only skips FCL where a distance bound proves the
answer; the capsule-mesh pairs it cannot prove go to the exact second stage
(:mod:`ctrplan.collision._exact`: segment-triangle distances to the triangles near each
capsule), and only the ties that stage leaves (within ``TIE_MM`` of contact) go to FCL, so the
verdicts with and without them are equal.

Clearances (``clearance_mm``) are conservative: for a free configuration a lower bound of the
distance from the capsule surfaces to the nearest mesh (within about ``h`` + ``sample_mm`` of
the truth near the surface; far from every mesh it saturates near the field's band), 0.0 where
no positive bound is known; for a colliding one minus a lower bound of the penetration depth
(0.0 where the depth is not known). :meth:`CollisionWorld.clearance_exact` gives exact distances
(closed-form segment-triangle distances of the second stage; FCL's where the stage is off or a
capsule is not finite).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ctrplan.collision.capsules import Capsules, capsules_from_shape
from ctrplan.collision.field import EPS_MM, FieldConfig, capsule_bounds, rows_finite
from ctrplan.collision.field_cache import field_for
from ctrplan.collision.scene import Scene, load_scene
from ctrplan.errors import InputError
from ctrplan.objcache import Bounded, owned
from ctrplan.shape.base import Shape

#: contact value of a configuration whose shape model failed (ok=False)
MODEL_FAILED = "model"
#: Largest margin (mm): the plausible range of a length (a margin beyond any scene is a typo,
#: and FCL's geometry fails numerically long before 1e300).
MAX_MARGIN_MM = 5000.0


@dataclass(frozen=True)
class CollisionReport:
    """Per-configuration verdicts.

    collides : (B,) bool. clearance_mm : (B,) float, signed (see module docstring).
    contact : (B,) object array of str — the mesh hit, "model" for a failed shape, "" if free.
    fcl_calls : configurations that went to exact FCL. stage_calls : configurations the
    prefilter's bounds left undecided that went to the exact second stage
    (:mod:`ctrplan.collision._exact`; only its ties go on to FCL).
    """

    collides: np.ndarray
    clearance_mm: np.ndarray
    contact: np.ndarray
    fcl_calls: int = 0
    stage_calls: int = 0

    def __len__(self) -> int:
        return int(self.collides.shape[0])


#: Above this many triangles (all collision meshes together) exact verdicts come from the
#: grid backend (:mod:`ctrplan.collision._grid`: about 10 bytes per triangle) instead of FCL
#: (about 600 bytes and 9 us to build per triangle).
GRID_ABOVE_TRIANGLES = 250_000
EXACT_BACKENDS = ("auto", "fcl", "grid")


def exact_backend(exact: str, triangles: int) -> str:
    """The exact-geometry backend for ``exact`` ("auto", "fcl" or "grid") and a triangle count."""
    if exact not in EXACT_BACKENDS:
        raise InputError("exact", "", f"must be one of {', '.join(EXACT_BACKENDS)}, got {exact!r}")
    if exact == "auto":
        return "grid" if triangles > GRID_ABOVE_TRIANGLES else "fcl"
    return exact


class WorldGeometry:
    """What a :class:`CollisionWorld` builds from a scene's collision meshes: the exact-geometry
    models (FCL), the distance fields (built or read from the cache on first use) and ``memo``,
    a dict for results that depend on them (e.g. the planner's start). It holds the meshes, not
    the scene, so a scene can cache it (and worlds over it) without a reference cycle: it is
    freed with the scene."""

    def __init__(self, meshes, field_config: FieldConfig, cache=True, exact: str = "auto"):
        self.meshes = tuple(meshes)
        self.field_config = field_config
        self.cache = cache
        self.backend = exact_backend(exact, sum(len(m.mesh.faces) for m in self.meshes))
        if self.backend == "fcl":
            from ctrplan.collision._fcl import FclMeshes

            self.exact = FclMeshes([m.mesh for m in self.meshes])
        else:
            from ctrplan.collision._grid import GridMeshes

            self.exact = GridMeshes([m.mesh for m in self.meshes])
        self._fields = None
        self._second = None
        self.memo: dict = Bounded(256)

    def bad_sides(self, base: np.ndarray) -> list[int]:
        """Per mesh, the side whose points prove a collision of a chain starting at ``base``
        (field module): for a mesh closed on its own, the other ray parity than the base's
        (+1: outside a closed wall that contains the base; -1: inside a closed obstacle); 0
        for a mesh that is not closed. Cached per base."""
        from ctrplan.collision.scene import inside_mesh

        key = ("bad_sides", tuple(np.asarray(base, dtype=float).tolist()))
        if key not in self.memo:
            b = np.asarray(base, dtype=float)[None]
            self.memo[key] = [(1 if inside_mesh(m, b)[0] else -1) if m.is_closed else 0
                              for m in self.meshes]
        return self.memo[key]

    @property
    def second_stage(self):
        """The exact second stage (:class:`ctrplan.collision._exact.ExactStage`) over the
        meshes: the grid backend's triangle lists where the world has them, else built once
        (on first use)."""
        if self._second is None:
            from ctrplan.collision._exact import ExactStage

            if self.backend == "grid":
                self._second = ExactStage(self.exact.objects)
            else:
                self._second = ExactStage.from_meshes([m.mesh for m in self.meshes])
        return self._second

    @property
    def fields(self):
        if self._fields is None:
            self._fields = [field_for(m.mesh, self.field_config, self.cache, m.is_closed)
                            for m in self.meshes]
        return self._fields


class CollisionWorld:
    """Collision checks against the wall and obstacle meshes of a scene.

    Parameters
    ----------
    scene : Scene or str
        The scene (or a shipped name / folder).
    margin_mm : float or ErrorProfile
        Safety margin added to every capsule radius: a number (mm), or a model's
        :class:`~ctrplan.shape.error_bounds.ErrorProfile` (each capsule grows by the profile's
        p99 over its arc-length fractions). ``margin_mm`` reads back the largest margin.
    curvature_per_mm : float
        Bound of the backbone curvature (1/mm, :func:`~ctrplan.collision.capsules.curvature_bound`
        of the shape model), for shapes that carry no padding of their own: each capsule is
        padded by the larger of its segment's sagitta bound and the shape's ``pad``.
    padding : "auto" (default) or "none"
        "auto" pads every capsule so that the capsule chain covers the continuous backbone
        between samples: by the model's own bound (``Shape.pad``: sagitta of its curvature
        bound, tangent jumps where tubes end, the learned model's polynomial bound) or the
        sagitta bound of ``curvature_per_mm``. "none" checks the chords only (points that
        really are the whole geometry, e.g. a probe); it must be asked for by name.
    motion_mm : float
        Extra padding (mm) for the motion between two checked states: the largest distance a
        backbone point can be from the nearest checked state's (the path check grows each
        capsule by its own bound instead: :mod:`ctrplan.planning.motion`). 0 = states only.
    prefilter : bool
        Use the conservative distance-field prefilter (same verdicts, faster).
    second_stage : bool
        With the prefilter, measure the capsule-mesh pairs its bounds cannot decide against
        the triangles near them (:mod:`ctrplan.collision._exact`: exact segment-triangle
        distances) and send only the ties within ``TIE_MM`` of contact to FCL (same
        verdicts, faster near walls). False: everything undecided goes to FCL.
    field_config : FieldConfig
        Distance-field parameters. cache : bool or folder for the field cache.
    geometry : WorldGeometry, optional
        Reuse the exact models and fields of another world of the same scene meshes.
    exact : "auto" (default), "fcl" or "grid"
        Where exact verdicts come from: FCL, or the lean grid of triangle lists
        (:mod:`ctrplan.collision._grid`) that "auto" picks above
        :data:`GRID_ABOVE_TRIANGLES` triangles. Both are exact; they differ in memory.
    """

    def __init__(self, scene: Scene | str, margin_mm=0.0, prefilter: bool = True,
                 field_config: FieldConfig | None = None, cache=True,
                 curvature_per_mm: float = 0.0, padding: str = "auto", motion_mm: float = 0.0,
                 geometry: WorldGeometry | None = None, exact: str = "auto",
                 second_stage: bool = True):
        from ctrplan.collision.capsules import PADDINGS
        from ctrplan.shape.error_bounds import ErrorProfile

        self.scene = load_scene(scene)
        meshes = self.scene.collision_meshes
        if not meshes:
            raise InputError(self.scene.path, "meshes", "empty world: no wall or obstacle mesh")
        if isinstance(margin_mm, ErrorProfile):
            self.margin_profile: ErrorProfile | None = margin_mm
            self.margin_mm = margin_mm.peak_mm
        else:
            if not (np.isfinite(margin_mm) and 0 <= margin_mm <= MAX_MARGIN_MM):
                raise InputError("margin_mm", "", f"must be a number of mm in [0, {MAX_MARGIN_MM:g}], "
                                 f"got {margin_mm:.4g}")
            self.margin_profile = None
            self.margin_mm = float(margin_mm)
        if not (np.isfinite(curvature_per_mm) and curvature_per_mm >= 0):
            raise InputError("curvature_per_mm", "", f"must be a finite number >= 0, got {curvature_per_mm}")
        self.curvature_per_mm = float(curvature_per_mm)
        if padding not in PADDINGS:
            raise InputError("padding", "", f"must be one of {', '.join(PADDINGS)}, got {padding!r}")
        self.padding = padding
        if not (np.isfinite(motion_mm) and motion_mm >= 0):
            raise InputError("motion_mm", "", f"must be a finite number >= 0, got {motion_mm}")
        self.motion_mm = float(motion_mm)
        self.names = np.array([m.name for m in meshes] + [""], dtype=object)
        self.prefilter = bool(prefilter)
        self.second_stage = bool(second_stage)
        self.field_config = field_config or FieldConfig()
        if geometry is None or geometry.field_config != self.field_config or tuple(
                m.mesh for m in geometry.meshes) != tuple(m.mesh for m in meshes) or (
                exact != "auto" and geometry.backend != exact):
            geometry = WorldGeometry(meshes, self.field_config, cache, exact)
        #: what is built from the meshes (exact-geometry models, distance fields), shareable
        #: between the worlds of one scene (:func:`world_for`)
        self.geometry = geometry
        self._fcl = geometry.exact
        #: configurations sent to FCL by the last check/collides call (for benchmarks)
        self.last_fcl_calls = 0
        #: configurations sent to the exact second stage by the last check/collides call
        self.last_stage_calls = 0
        self.pose = np.asarray(self.scene.base_pose, dtype=float)
        self._bad_side = geometry.bad_sides(self.pose[:3, 3])

    # ------------------------------------------------------------------ geometry
    def capsules(self, shape: Shape) -> Capsules:
        """Capsules of a shape (robot base frame) in the scene frame, margin, continuity padding
        and motion padding included."""
        margin = self.margin_profile if self.margin_profile is not None else self.margin_mm
        caps = capsules_from_shape(shape, margin, self.curvature_per_mm, self.padding)
        if self.motion_mm > 0:
            caps = Capsules(caps.a, caps.b, caps.radius + self.motion_mm)
        return caps.transformed(self.pose)

    def with_motion(self, motion_mm: float) -> CollisionWorld:
        """The same world (meshes, fields and FCL objects shared) with every capsule grown by
        ``motion_mm`` more (the motion between two checked states)."""
        import copy

        if not (np.isfinite(motion_mm) and motion_mm >= 0):
            raise InputError("motion_mm", "", f"must be a finite number >= 0, got {motion_mm}")
        other = copy.copy(self)
        other.motion_mm = self.motion_mm + float(motion_mm)
        return other

    @property
    def fields(self):
        """Distance fields of the meshes (built or read from the cache on first use)."""
        return self.geometry.fields

    def params_key(self) -> tuple:
        """What a verdict depends on besides the geometry: margin, curvature bound, padding,
        motion padding, prefilter (hashable)."""
        from ctrplan.shape.error_bounds import margin_key

        margin = self.margin_profile if self.margin_profile is not None else self.margin_mm
        return (margin_key(margin), self.curvature_per_mm, self.padding, self.motion_mm,
                self.prefilter)

    # ------------------------------------------------------------------ queries
    def check(self, shape: Shape) -> CollisionReport:
        """Verdict, conservative clearance and contact of each configuration of ``shape``."""
        return self._check(shape, use_field=self.prefilter)

    def check_exact(self, shape: Shape) -> CollisionReport:
        """Like :meth:`check` with every verdict from FCL (the prefilter only supplies
        clearance bounds)."""
        return self._check(shape, use_field=False)

    def collides(self, shape: Shape) -> np.ndarray:
        """(B,) bool verdicts (the fast path: no clearances, the field walk jumps ahead)."""
        return self._check(shape, use_field=self.prefilter, trace=True).collides

    def first_collision(self, shape: Shape) -> int:
        """Index of the first colliding configuration in batch order, -1 if none.

        FCL runs in batch order only on configurations neither the prefilter nor the second
        stage can decide, and stops at the first collision (edge validation).
        """
        from ctrplan.collision._exact import FREE, UNSURE

        B = len(shape)
        caps = self.capsules(shape)
        ok = np.asarray(shape.ok, dtype=bool)
        staged = np.full(B, UNSURE)
        if self.prefilter:
            _, depth, unsure = self._bounds(caps, ok, trace=True)
            proven = np.flatnonzero(~ok | (depth > EPS_MM))
            rows = np.flatnonzero(ok & ~(depth > EPS_MM) & unsure.any(axis=1))
            if len(proven):     # nothing after the first proven collision is needed
                rows = rows[rows < proven[0]]
            if self.second_stage and len(rows):
                staged[rows] = self.geometry.second_stage.decide(caps.a, caps.b, caps.radius,
                                                                 rows, unsure)
        else:
            depth, unsure = np.full(B, -np.inf), None
        for i in range(B):
            if not ok[i] or depth[i] > EPS_MM or staged[i] >= 0:
                return i
            pairs = None if unsure is None else unsure[i]
            if pairs is not None and (not pairs.any() or staged[i] == FREE):
                continue
            if self._fcl.first_hit(caps.a[i], caps.b[i], caps.radius[i], pairs) >= 0:
                return i
        return -1

    def clearance_exact(self, shape: Shape, below: float = np.inf) -> np.ndarray:
        """(B,) exact distance from the capsule surfaces to the nearest mesh, mm. Overlapping
        configurations give -1 (FCL's convention: no depth).

        Branch and bound over capsule-mesh pairs: with the prefilter on, each pair gets the
        field's lower bound first and pairs are measured in order of that bound until the
        smallest distance found is no larger than the next bound (the exact minimum, usually
        after a few pairs instead of K x meshes). Where a configuration's distance is at least ``below``, it may return a lower bound that is
        itself at least ``below`` (callers taking a minimum over many configurations pass the
        best value found so far)."""
        return self.clearance_bounded(shape, below)[0]

    def clearance_bounded(self, shape: Shape, below: float = np.inf,
                          max_pairs: int | None = None) -> tuple[np.ndarray, int]:
        """:meth:`clearance_exact` with a budget of ``max_pairs`` pair distances. A pair is
        measured by the second stage's closed-form segment-triangle distances
        (:meth:`~ctrplan.collision._exact.ExactStage.pair_distance`, equal to FCL's distance
        query within FCL's tolerance, and cheaper: no FCL object per query, the search starts
        at the field's bound), by FCL where the stage is off
        (``second_stage=False``) or the capsule is not finite or far out. Returns
        (values (B,), pairs measured). Once the budget is spent, the remaining configurations
        get lower bounds (the field's) instead of exact values; every value is exact or a lower
        bound, never more than the truth."""
        caps = self.capsules(shape)
        out = np.empty(len(shape))
        if not self.prefilter:
            for i in range(len(shape)):
                out[i] = self._fcl.distance(caps.a[i], caps.b[i], caps.radius[i])[0]
            return out, len(shape) * caps.radius.shape[1] * len(self._fcl.objects)
        left = np.inf if max_pairs is None else int(max_pairs)
        used = 0
        K = caps.radius.shape[1]
        bounds, hits = self._pair_bounds(caps)
        stage = self.geometry.second_stage if self.second_stage else None
        for i in range(len(shape)):
            flat = bounds[i]
            if hits[i]:
                out[i] = -1.0
                continue
            order = np.argsort(flat, kind="stable")
            best, measured = np.inf, 0
            for o in order:
                limit = min(best, below)
                if (flat[o] >= limit and limit < np.inf) or used >= left:
                    break
                j, k = divmod(int(o), K)
                d = math.nan
                if stage is not None:     # exact segment-triangle distances (numba)
                    d = stage.pair_distance(caps.a[i, k], caps.b[i, k], caps.radius[i, k], j,
                                            lower=flat[o], limit=limit)
                if math.isnan(d):         # not finite or far out: FCL
                    d = self._fcl.pair_distance(caps.a[i, k], caps.b[i, k],
                                                float(caps.radius[i, k]), j)
                best = min(best, d)
                measured += 1
                used += 1
                if best < 0:
                    break
            # Unmeasured pairs have bounds >= min(best, below) (or the budget ran out): the
            # value is exact when below ``below`` and settled, otherwise a lower bound.
            rest = flat[order[measured]] if measured < len(order) and best >= 0 else np.inf
            out[i] = min(best, rest)
        return out, used

    def _pair_bounds(self, caps: Capsules) -> tuple[np.ndarray, np.ndarray]:
        """Field lower bounds of the distance of every (mesh j, capsule k) pair of each
        configuration, (B, meshes * K) flattened j-major per row, and (B,) whether the field
        proves the configuration in collision. Each capsule is walked as a configuration of
        its own (one kernel call per mesh for the whole batch)."""
        B, K = caps.radius.shape
        a = np.ascontiguousarray(caps.a.reshape(B * K, 1, 3))
        b = np.ascontiguousarray(caps.b.reshape(B * K, 1, 3))
        r = np.ascontiguousarray(caps.radius.reshape(B * K, 1))
        finite = rows_finite(a, b, r)
        lows = np.empty((B, len(self.fields), K))
        hits = np.zeros(B, dtype=bool)
        for j, field in enumerate(self.fields):
            clear, depth = np.full(B * K, np.inf), np.full(B * K, -np.inf)
            capsule_bounds(field, a, b, r, np.ones(B * K, dtype=bool), clear, depth,
                           self.field_config.sample_mm, self._bad_side[j], finite=finite)
            lows[:, j, :] = clear.reshape(B, K)
            hits |= np.any(depth.reshape(B, K) > EPS_MM, axis=1)
        return lows.reshape(B, -1), hits

    # ------------------------------------------------------------------ internals
    def _bounds(self, caps: Capsules, active: np.ndarray, trace: bool = False):
        """Field bounds: clearance lower bound (B,), depth lower bound (B,), and (B, K) uint64
        masks of the capsule-mesh pairs the field could not prove free (bit j: mesh j)."""
        B = len(caps)
        a = np.ascontiguousarray(caps.a)
        b = np.ascontiguousarray(caps.b)
        r = np.ascontiguousarray(caps.radius)
        clear = np.full(B, np.inf)
        depth = np.full(B, -np.inf)
        unsure = np.zeros(r.shape, dtype=np.uint64)
        self._contact_idx = np.full(B, -1)
        act = np.array(active, dtype=bool)
        finite = rows_finite(a, b, r)       # once for every mesh
        for j, field in enumerate(self.fields):
            before = depth.copy()
            capsule_bounds(field, a, b, r, act, clear, depth, self.field_config.sample_mm,
                           self._bad_side[j], trace=trace, unsure=unsure, bit=1 << j,
                           finite=finite)
            hit = (depth > EPS_MM) & (before <= EPS_MM)
            self._contact_idx[hit] = j
            act &= ~hit
        return clear, depth, unsure

    def _check(self, shape: Shape, use_field: bool, trace: bool = False) -> CollisionReport:
        B = len(shape)
        caps = self.capsules(shape)
        ok = np.asarray(shape.ok, dtype=bool)
        if use_field or not trace:
            clear, depth, unsure = self._bounds(caps, ok, trace=trace)
            contact_idx = self._contact_idx
        else:  # FCL verdicts only: no field needed
            clear, depth, contact_idx = np.zeros(B), np.zeros(B), np.full(B, -1)
        collides = np.zeros(B, dtype=bool)
        staged = 0
        if use_field:
            decided_hit = depth > EPS_MM
            collides |= decided_hit
            todo = np.flatnonzero(ok & ~decided_hit & unsure.any(axis=1))
            if self.second_stage and len(todo):
                staged = len(todo)
                todo = self._second_stage(caps, todo, unsure, collides, contact_idx)
        else:
            contact_idx = np.full(B, -1)
            todo = np.flatnonzero(ok)
            unsure = None
        for i in todo:
            j = self._fcl.first_hit(caps.a[i], caps.b[i], caps.radius[i],
                                    None if unsure is None else unsure[i])
            collides[i] = j >= 0
            contact_idx[i] = j
        contact = self.names[contact_idx]
        contact[~collides] = ""
        collides |= ~ok
        contact[~ok] = MODEL_FAILED
        clearance = np.where(collides, np.minimum(-np.maximum(depth, 0.0), 0.0),
                             np.maximum(clear, 0.0))
        clearance[~ok] = np.nan
        self.last_fcl_calls = len(todo)
        self.last_stage_calls = staged
        return CollisionReport(collides=collides, clearance_mm=clearance, contact=contact,
                               fcl_calls=len(todo), stage_calls=staged)

    def _second_stage(self, caps: Capsules, rows: np.ndarray, unsure: np.ndarray,
                      collides: np.ndarray, contact_idx: np.ndarray) -> np.ndarray:
        """Decide the configurations ``rows`` with the exact second stage: sets ``collides``
        and ``contact_idx`` (B,) of those it proves to touch; returns the rows it leaves to
        FCL (ties within TIE_MM of contact)."""
        from ctrplan.collision._exact import UNSURE

        verdict = self.geometry.second_stage.decide(caps.a, caps.b, caps.radius, rows, unsure)
        hit = verdict >= 0
        collides[rows[hit]] = True
        contact_idx[rows[hit]] = verdict[hit]
        return rows[verdict == UNSURE]


def world_for(scene: Scene, margin_mm=0.0, curvature_per_mm: float = 0.0) -> CollisionWorld:
    """A CollisionWorld of a scene with this margin and curvature bound, over the scene's exact
    models and distance fields (built once per scene object and kept on it, freed with it).
    margin_mm : a number or an ErrorProfile (:func:`ctrplan.shape.error_bounds.auto_margin`)."""
    # The scene keeps the geometry (exact models, fields), not the world: a world refers to its
    # scene, and a scene -> world -> scene cycle would keep both (and their memory) alive until
    # a full garbage collection. Worlds themselves are cheap.
    cache = owned(scene)
    geometry = cache.get("world_geometry") if cache is not None else None
    world = CollisionWorld(scene, margin_mm=margin_mm, curvature_per_mm=curvature_per_mm,
                           geometry=geometry)
    if cache is not None:
        cache["world_geometry"] = world.geometry
    return world
