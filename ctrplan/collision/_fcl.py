"""Exact capsule-vs-mesh queries with python-fcl. FCL objects never leave this module."""

from __future__ import annotations

import fcl
import numpy as np


class FclMeshes:
    """FCL BVH models of a list of meshes (mm, scene frame). Not thread-safe (a pool of capsule
    objects is reused between queries)."""

    def __init__(self, meshes):
        self.objects = []
        for mesh in meshes:
            bvh = fcl.BVHModel()
            v = np.ascontiguousarray(mesh.vertices, dtype=np.float64)
            f = np.ascontiguousarray(mesh.faces, dtype=np.int32)
            bvh.beginModel(len(v), len(f))
            bvh.addSubModel(v, f)
            bvh.endModel()
            self.objects.append(fcl.CollisionObject(bvh, fcl.Transform()))
        self._request = fcl.CollisionRequest()
        self._pool: list = []
        self._dist_request = fcl.DistanceRequest()

    def _capsules(self, a: np.ndarray, b: np.ndarray, r: np.ndarray) -> list:
        """FCL capsules (K of them) for segments a -> b (K, 3) with radii r (K,)."""
        v = b - a
        h = np.linalg.norm(v, axis=1)
        d = v / np.where(h > 0, h, 1.0)[:, None]
        # quaternion [w, x, y, z] turning +z onto d: half-way form [1 + z.d, z x d], normalised
        q = np.column_stack([1.0 + d[:, 2], -d[:, 1], d[:, 0], np.zeros(len(d))])
        flip = q[:, 0] < 1e-9            # d = -z: half a turn about x
        q[flip] = [0.0, 1.0, 0.0, 0.0]
        q /= np.linalg.norm(q, axis=1, keepdims=True)
        c = (a + b) / 2.0
        # Reuse a pool of capsule objects: creating FCL objects costs ~15 us each from Python.
        while len(self._pool) < len(r):
            geom = fcl.Capsule(1.0, 1.0)
            self._pool.append((geom, fcl.CollisionObject(geom, fcl.Transform())))
        objs = []
        for k in range(len(r)):
            # fcl.Capsule(radius, lz) is centred at the origin along its local z axis
            geom, obj = self._pool[k]
            geom.radius = float(r[k])
            geom.lz = float(h[k])
            geom.computeLocalAABB()
            obj.setTransform(fcl.Transform(q[k], c[k]))  # also refreshes the world AABB
            objs.append(obj)
        return objs

    def first_hit(self, a: np.ndarray, b: np.ndarray, r: np.ndarray,
                  pairs: np.ndarray | None = None) -> int:
        """Index of the first mesh any capsule (K, ...) touches, or -1 if none. pairs : (K,)
        bit masks: only capsule k vs mesh j with bit j of pairs[k] set are checked."""
        if pairs is not None:
            keep = pairs != 0
            a, b, r, pairs = a[keep], b[keep], r[keep], pairs[keep]
        caps = self._capsules(a, b, r)
        for j, mo in enumerate(self.objects):
            for k, co in enumerate(caps):
                if pairs is not None and not (int(pairs[k]) >> j) & 1:
                    continue
                res = fcl.CollisionResult()
                if fcl.collide(co, mo, self._request, res):
                    return j
        return -1

    def distance(self, a: np.ndarray, b: np.ndarray, r: np.ndarray) -> tuple[float, int]:
        """(smallest capsule-surface distance to any mesh, that mesh's index). Negative means
        the shapes overlap (FCL then reports -1 without a depth)."""
        caps = self._capsules(a, b, r)
        best, which = np.inf, -1
        for j, mo in enumerate(self.objects):
            for co in caps:
                res = fcl.DistanceResult()
                d = fcl.distance(co, mo, self._dist_request, res)
                if d < best:
                    best, which = d, j
        return float(best), which

    def pair_distance(self, a: np.ndarray, b: np.ndarray, r: float, j: int) -> float:
        """FCL distance from one capsule (axis a -> b (3,), radius r) to mesh j; -1 on overlap."""
        co = self._capsules(a[None], b[None], np.array([r]))[0]
        return float(fcl.distance(co, self.objects[j], self._dist_request, fcl.DistanceResult()))

