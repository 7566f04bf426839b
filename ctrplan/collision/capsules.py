"""Backbone -> capsule chain, the robot's collision geometry.

A backbone of ``m`` points gives ``m - 1`` capsules (segments swept by a sphere). The radius of
capsule ``k`` is the outer radius of the outermost tube present anywhere on the segment from
point ``k`` to point ``k + 1`` (the larger of the two end radii: radii only shrink toward the
tip), plus an optional safety margin, plus the segment's **sagitta bound**. Because a tube's
distal end may fall strictly inside a segment, taking the larger end radius over-covers the
robot, never under-covers it.

Sagitta bound. The backbone between two samples is an arc, not the chord the capsule follows. For
a curve ``c(s)`` parameterised by arc length whose curvature is at most ``kappa`` on a segment of
arc length ``h``, the error ``e(s) = c(s) - chord(s)`` vanishes at both ends and
``|e''| <= kappa``, so ``|e(s)| <= kappa s (h - s) / 2 <= kappa h^2 / 8`` (the linear
interpolation bound, applied to ``u . e`` for every unit vector ``u``). Padding each capsule by
``kappa h^2 / 8`` therefore makes the capsule chain cover the continuous tube, not only its
samples. The physics models' backbone curvature is an EI-weighted mean of the precurvature
vectors of the tubes present, so its magnitude never exceeds the largest precurvature
(:func:`curvature_bound`); external loads add a per-segment share that the mechanics models
carry in ``Shape.pad`` (:mod:`ctrplan.shape.bounds`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ctrplan.shape.base import Shape

# chord bounds live with the shape models (re-exported here for callers of this module)
from ctrplan.shape.bounds import curvature_bound, kink_pad, sagitta_pad  # noqa: F401


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


def sagitta_bound(arc_mm: np.ndarray, curvature_per_mm: float) -> np.ndarray:
    """Largest distance (mm) of a curve of arc length ``arc_mm`` and curvature at most
    ``curvature_per_mm`` from its chord: ``kappa h^2 / 8`` (see the module docstring)."""
    return float(curvature_per_mm) * np.square(np.asarray(arc_mm, dtype=float)) / 8.0


def arc_from_chord(chord_mm: np.ndarray, curvature_per_mm: float) -> np.ndarray:
    """An upper bound of the arc length of a curve with curvature at most ``kappa`` whose chord
    is ``chord_mm`` (Schur's comparison: the chord is at least the circle's, ``2/k sin(k h/2)``).
    Where the chord is too long for a bound (``kappa c >= 2`` ... never for a tube backbone
    sampled at >= 2 points) the half circumference ``pi / kappa`` is used."""
    c = np.asarray(chord_mm, dtype=float)
    k = float(curvature_per_mm)
    if k <= 0:
        return c
    x = np.clip(k * c / 2.0, 0.0, 1.0)
    return 2.0 / k * np.arcsin(x)


def capsules_from_points(points: np.ndarray, radius: np.ndarray, margin_mm=0.0,
                         curvature_per_mm: float = 0.0, s: np.ndarray | None = None,
                         pad: np.ndarray | None = None) -> Capsules:
    """Capsules from backbones.

    points : (B, m, 3) mm; radius : (B, m) mm outer radius at each point (the outermost tube
    present); margin_mm : added to every radius: a number, a (B, m - 1) / (m - 1,) array of
    per-capsule margins, or an :class:`~ctrplan.shape.error_bounds.ErrorProfile` (its p99 at
    each capsule's arc-length fractions, from ``s``); curvature_per_mm : a bound of the
    backbone's curvature: every capsule grows by its sagitta bound ``kappa h^2 / 8`` with ``h``
    the arc length of its segment, from ``s`` (B, m) mm when given, else bounded from the chord;
    pad : (B, m - 1) mm, the model's own bound of the curve-to-chord distance of each segment
    (``Shape.pad``): capsules grow by the larger of it and the sagitta bound (both are bounds).
    Returns ``m - 1`` capsules per configuration.
    """
    points = np.asarray(points, dtype=float)
    radius = np.asarray(radius, dtype=float)
    if points.ndim != 3 or points.shape[-1] != 3 or points.shape[1] < 2:
        raise ValueError(f"points must have shape (B, m>=2, 3), got {points.shape}")
    if radius.shape != points.shape[:2]:
        raise ValueError(f"radius must have shape {points.shape[:2]}, got {radius.shape}")
    K = points.shape[1] - 1
    margin = _capsule_margin(margin_mm, points, s)
    if not (np.isfinite(curvature_per_mm) and curvature_per_mm >= 0):
        raise ValueError(f"curvature_per_mm must be a finite number >= 0, got {curvature_per_mm}")
    r = np.maximum(radius[:, :-1], radius[:, 1:]) + margin
    cont = np.zeros_like(r)
    if curvature_per_mm > 0:
        if s is not None:
            s = np.asarray(s, dtype=float)
            arc = np.abs(np.diff(np.broadcast_to(s, points.shape[:2]), axis=1))
            # never less than the chord (an arc is at least as long as its chord)
            arc = np.maximum(arc, np.linalg.norm(np.diff(points, axis=1), axis=-1))
        else:
            arc = arc_from_chord(np.linalg.norm(np.diff(points, axis=1), axis=-1), curvature_per_mm)
        cont = sagitta_bound(arc, curvature_per_mm)
    if pad is not None:
        pad = np.asarray(pad, dtype=float)
        if pad.shape != (points.shape[0], K):
            raise ValueError(f"pad must have shape {(points.shape[0], K)}, got {pad.shape}")
        # a NaN pad (a model that could not bound a shape) must never shrink the capsule
        cont = np.maximum(cont, np.where(np.isfinite(pad), pad, np.inf))
    return Capsules(a=points[:, :-1, :], b=points[:, 1:, :], radius=r + cont)


def _capsule_margin(margin, points: np.ndarray, s: np.ndarray | None):
    """Per-capsule margins (B, K) or a number from a number, an array or an ErrorProfile."""
    from ctrplan.shape.error_bounds import ErrorProfile

    B, K = points.shape[0], points.shape[1] - 1
    if isinstance(margin, ErrorProfile):
        if s is None:
            s = np.concatenate([np.zeros((B, 1)), np.cumsum(
                np.linalg.norm(np.diff(points, axis=1), axis=-1), axis=1)], axis=1)
        return margin.capsule_margins(np.broadcast_to(np.asarray(s, dtype=float), (B, K + 1)))
    m = np.asarray(margin, dtype=float)
    if m.ndim == 0:
        if not m >= 0:
            raise ValueError(f"margin_mm must be >= 0, got {margin}")
        return float(m)
    m = np.broadcast_to(m, (B, K)) if m.shape in ((K,), (B, K)) else None
    if m is None:
        raise ValueError(f"per-capsule margins must have shape ({K},) or ({B}, {K})")
    if not np.all(m >= 0):
        raise ValueError("margins must be >= 0")
    return m


#: what :class:`~ctrplan.collision.world.CollisionWorld` pads capsules with
PADDINGS = ("auto", "none")


def capsules_from_shape(shape: Shape, margin_mm=0.0, curvature_per_mm: float = 0.0,
                        padding: str = "auto") -> Capsules:
    """Capsules of a :class:`~ctrplan.shape.base.Shape` (robot base frame, mm).

    padding "auto": each capsule grows by the larger of the model's own curve-to-chord bound
    (``shape.pad``: sagitta, tangent jumps, polynomial bound) and the sagitta bound of
    ``curvature_per_mm`` over the segment's arc length ``diff(shape.s)``; "none": the chords
    only (plus the margin), for geometry that really is the polyline (a probe)."""
    if padding not in PADDINGS:
        raise ValueError(f"padding must be one of {PADDINGS}, got {padding!r}")
    if padding == "none":
        return capsules_from_points(shape.points, shape.radius, margin_mm, 0.0, shape.s)
    return capsules_from_points(shape.points, shape.radius, margin_mm, curvature_per_mm, shape.s,
                                getattr(shape, "pad", None))


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
