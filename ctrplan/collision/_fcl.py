"""Exact capsule-vs-mesh queries with python-fcl. FCL objects never leave this module."""

from __future__ import annotations

import fcl
import numpy as np

from ctrplan.collision.capsules import rotation_z_to


class FclMeshes:
    """FCL BVH models of a list of meshes (mm, scene frame)."""

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
        self._dist_request = fcl.DistanceRequest()

    def _capsules(self, a: np.ndarray, b: np.ndarray, r: np.ndarray) -> list:
        objs = []
        for ak, bk, rk in zip(a, b, r):
            v = bk - ak
            h = float(np.linalg.norm(v))
            if h < 1e-9:
                geom = fcl.Sphere(float(rk))
                R = np.eye(3)
            else:
                # fcl.Capsule(radius, lz) is centred at the origin along its local z axis
                geom = fcl.Capsule(float(rk), h)
                R = rotation_z_to(v / h)
            objs.append(fcl.CollisionObject(geom, fcl.Transform(R, (ak + bk) / 2.0)))
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

