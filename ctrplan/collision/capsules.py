"""Backbone -> capsule chain, the robot's collision geometry.

A backbone of ``m`` points gives ``m - 1`` capsules (segments swept by a sphere). The radius of
capsule ``k`` is the outer radius of the outermost tube present anywhere on the segment from
point ``k`` to point ``k + 1`` (the larger of the two end radii: radii only shrink toward the
tip), plus an optional safety margin. Because a tube's distal end may fall strictly inside a
segment, taking the larger end radius over-covers the robot, never under-covers it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ctrplan.shape.base import Shape


@dataclass(frozen=True)
class Capsules:
    """Capsule chains of a batch of configurations (frame of the input points, mm).

    a, b : (B, K, 3) float, mm — segment end points (K = m - 1 capsules per configuration).
    radius : (B, K) float, mm — swept-sphere radius of each capsule (margin included).
    """

    a: np.ndarray
    b: np.ndarray
    radius: np.ndarray

    def __len__(self) -> int:
        return int(self.a.shape[0])

    @property
    def count(self) -> int:
        """Capsules per configuration (K)."""
        return int(self.a.shape[1])

    @property
    def length(self) -> np.ndarray:
        """(B, K) segment lengths, mm."""
        return np.linalg.norm(self.b - self.a, axis=-1)

    def transformed(self, pose: np.ndarray) -> Capsules:
        """The same capsules after the rigid transform ``pose`` (4, 4)."""
        R = np.asarray(pose, dtype=float)[:3, :3]
        t = np.asarray(pose, dtype=float)[:3, 3]
        return Capsules(a=self.a @ R.T + t, b=self.b @ R.T + t, radius=self.radius)

    def to_trimesh(self, index: int = 0, sections: int = 12):
        """One configuration's capsule chain as a single :class:`trimesh.Trimesh` (for viewing)."""
        import trimesh

        parts = []
        for a, b, r in zip(self.a[index], self.b[index], self.radius[index]):
            v = b - a
            h = float(np.linalg.norm(v))
            cap = trimesh.creation.capsule(height=max(h, 1e-9), radius=float(r), count=[sections, sections])
            # trimesh's capsule runs along +z from 0 to height with both caps beyond; centre it
            cap.apply_translation([0.0, 0.0, -cap.bounds[:, 2].mean()])
            T = np.eye(4)
            T[:3, :3] = rotation_z_to(v / h if h > 0 else np.array([0.0, 0.0, 1.0]))
            T[:3, 3] = (a + b) / 2.0
            cap.apply_transform(T)
            parts.append(cap)
        return trimesh.util.concatenate(parts)


def capsules_from_points(points: np.ndarray, radius: np.ndarray, margin_mm: float = 0.0) -> Capsules:
    """Capsules from backbones.

    points : (B, m, 3) mm; radius : (B, m) mm outer radius at each point (the outermost tube
    present); margin_mm : added to every radius. Returns ``m - 1`` capsules per configuration.
    """
    points = np.asarray(points, dtype=float)
    radius = np.asarray(radius, dtype=float)
    if points.ndim != 3 or points.shape[-1] != 3 or points.shape[1] < 2:
        raise ValueError(f"points must have shape (B, m>=2, 3), got {points.shape}")
    if radius.shape != points.shape[:2]:
        raise ValueError(f"radius must have shape {points.shape[:2]}, got {radius.shape}")
    if not margin_mm >= 0:
        raise ValueError(f"margin_mm must be >= 0, got {margin_mm}")
    r = np.maximum(radius[:, :-1], radius[:, 1:]) + float(margin_mm)
    return Capsules(a=points[:, :-1, :], b=points[:, 1:, :], radius=r)


def capsules_from_shape(shape: Shape, margin_mm: float = 0.0) -> Capsules:
    """Capsules of a :class:`~ctrplan.shape.base.Shape` (robot base frame, mm)."""
    return capsules_from_points(shape.points, shape.radius, margin_mm)


def rotation_z_to(d: np.ndarray) -> np.ndarray:
    """A rotation matrix taking +z to the unit vector ``d``."""
    z = np.array([0.0, 0.0, 1.0])
    c = float(np.dot(z, d))
    if c > 1.0 - 1e-12:
        return np.eye(3)
    if c < -1.0 + 1e-12:
        return np.diag([1.0, -1.0, -1.0])
    v = np.cross(z, d)
    s = np.linalg.norm(v)
    k = v / s
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + s * K + (1 - c) * (K @ K)
