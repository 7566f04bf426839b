"""Ray casting over a triangle mesh (numba, no acceleration structure: memory is the mesh).

Inside/outside of a closed surface by ray parity: a point is inside when a ray from it crosses
the surface an odd number of times. A closed surface (every edge shared by an even number of
triangles) separates space this way whatever its orientation or how many layers it has: any
path between points of different parity crosses it. A ray that grazes an edge or a vertex can
be counted twice; each point is tested along three fixed, generic directions and the majority
decides (a graze on all three at once would need the point on three special planes).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

#: three generic unit directions (no symmetry of a grid or a procedural mesh lines up with them)
DIRECTIONS = np.array([[0.5773502691896258, 0.5773502691896258, 0.5773502691896258],
                       [-0.3826834323650898, 0.8660254037844387, 0.3218603185458476],
                       [0.2672612419124244, -0.5345224838248488, 0.8017837257372732]])
DIRECTIONS /= np.linalg.norm(DIRECTIONS, axis=1, keepdims=True)


@nb.njit(cache=True, inline="always")
def _hit(v, f, t, px, py, pz, dx, dy, dz):
    """Ray parameter (> 0) where the ray p + s d crosses triangle t, or -1.0."""
    a = f[t, 0]
    b = f[t, 1]
    c = f[t, 2]
    ax = v[a, 0]
    ay = v[a, 1]
    az = v[a, 2]
    e1x = v[b, 0] - ax
    e1y = v[b, 1] - ay
    e1z = v[b, 2] - az
    e2x = v[c, 0] - ax
    e2y = v[c, 1] - ay
    e2z = v[c, 2] - az
    qx = dy * e2z - dz * e2y
    qy = dz * e2x - dx * e2z
    qz = dx * e2y - dy * e2x
    det = e1x * qx + e1y * qy + e1z * qz
    if det == 0.0:
        return -1.0
    inv = 1.0 / det
    tx = px - ax
    ty = py - ay
    tz = pz - az
    u = (tx * qx + ty * qy + tz * qz) * inv
    if u < 0.0 or u > 1.0:
        return -1.0
    rx = ty * e1z - tz * e1y
    ry = tz * e1x - tx * e1z
    rz = tx * e1y - ty * e1x
    w = (dx * rx + dy * ry + dz * rz) * inv
    if w < 0.0 or u + w > 1.0:
        return -1.0
    s = (e2x * rx + e2y * ry + e2z * rz) * inv
    return s if s > 0.0 else -1.0


@nb.njit(cache=True)
def _parity(v, f, points, dirs, out):
    for i in range(points.shape[0]):
        odd = 0
        for k in range(dirs.shape[0]):
            n = 0
            for t in range(f.shape[0]):
                if _hit(v, f, t, points[i, 0], points[i, 1], points[i, 2],
                        dirs[k, 0], dirs[k, 1], dirs[k, 2]) > 0.0:
                    n += 1
            odd += n & 1
        out[i] = 2 * odd > dirs.shape[0]


@nb.njit(cache=True)
def _all_hit(v, f, p, dirs):
    """Whether every ray from p along dirs meets some triangle."""
    for k in range(dirs.shape[0]):
        found = False
        for t in range(f.shape[0]):
            if _hit(v, f, t, p[0], p[1], p[2], dirs[k, 0], dirs[k, 1], dirs[k, 2]) > 0.0:
                found = True
                break
        if not found:
            return False
    return True


def odd_parity(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """(P,) bool: whether each point (P, 3) lies inside the closed surface (vertices (V, 3),
    faces (F, 3)) by ray parity, majority of three directions. Cost P x F (about 10 ns per
    triangle and direction)."""
    p = np.ascontiguousarray(np.asarray(points, dtype=np.float64).reshape(-1, 3))
    out = np.zeros(len(p), dtype=np.bool_)
    if len(p) and len(faces):
        _parity(np.ascontiguousarray(vertices, dtype=np.float64),
                np.ascontiguousarray(faces, dtype=np.int64), p, DIRECTIONS, out)
    return out


def fibonacci_directions(n: int = 96) -> np.ndarray:
    """``n`` unit directions spread evenly over the sphere (n, 3)."""
    k = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * k / n)
    theta = math.pi * (1 + 5 ** 0.5) * k
    return np.stack([np.cos(theta) * np.sin(phi), np.sin(theta) * np.sin(phi), np.cos(phi)], axis=1)


def enclosed(vertices: np.ndarray, faces: np.ndarray, point: np.ndarray, n: int = 96) -> bool:
    """Whether every one of ``n`` rays from ``point`` (3,) meets the surface. A ray that escapes
    proves the point lies in the unbounded region (nothing stops a path along it)."""
    return bool(_all_hit(np.ascontiguousarray(vertices, dtype=np.float64),
                         np.ascontiguousarray(faces, dtype=np.int64),
                         np.asarray(point, dtype=np.float64).reshape(3), fibonacci_directions(n)))
