"""Capsules from backbones, and capsule-vs-mesh queries against a brute-force oracle."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from ctrplan.collision.capsules import capsules_from_points, capsules_from_shape, rotation_z_to
from ctrplan.shape.base import Shape
from ctrplan.shape.physics import PhysicsModel


def test_radius_is_outermost_tube_on_segment_plus_margin(seed1):
    q = seed1.sample(20, seed=3)
    shape = PhysicsModel(seed1).shape(q, points=21)
    caps = capsules_from_shape(shape, margin_mm=0.3, padding="none")
    assert caps.a.shape == (20, 20, 3) and caps.radius.shape == (20, 20)
    np.testing.assert_allclose(caps.a, shape.points[:, :-1])
    np.testing.assert_allclose(caps.b, shape.points[:, 1:])
    expect = np.maximum(shape.radius[:, :-1], shape.radius[:, 1:]) + 0.3
    np.testing.assert_allclose(caps.radius, expect)
    # the first capsule carries the outermost tube (OD 2.5 mm)
    assert np.all(caps.radius[:, 0] == pytest.approx(1.25 + 0.3))
    # by default the capsules also carry the model's sagitta bound: kappa_max h^2 / 8 with
    # seed1's largest precurvature and each segment's arc length
    padded = capsules_from_shape(shape, margin_mm=0.3)
    h = np.diff(shape.s, axis=1)
    np.testing.assert_allclose(padded.radius, expect + 0.0093354 * h**2 / 8, rtol=1e-4)
    with pytest.raises(ValueError):
        capsules_from_shape(shape, padding="chords")


def test_radius_covers_a_tube_ending_inside_a_segment():
    pts = np.zeros((1, 3, 3))
    pts[0, :, 2] = [0.0, 10.0, 20.0]
    radius = np.array([[1.25, 0.95, 0.65]])  # outer tube ends between points 0 and 1
    caps = capsules_from_points(pts, radius)
    np.testing.assert_allclose(caps.radius, [[1.25, 0.95]])


def test_bad_inputs():
    with pytest.raises(ValueError):
        capsules_from_points(np.zeros((2, 1, 3)), np.zeros((2, 1)))
    with pytest.raises(ValueError):
        capsules_from_points(np.zeros((2, 3, 3)), np.zeros((2, 2)))
    with pytest.raises(ValueError):
        capsules_from_points(np.zeros((2, 3, 3)), np.zeros((2, 3)), margin_mm=-1.0)


def test_transform_and_mesh_export():
    rng = np.random.default_rng(0)
    pts = np.cumsum(rng.normal(size=(1, 6, 3)) * 5, axis=1)
    caps = capsules_from_points(pts, np.full((1, 6), 1.0))
    T = np.eye(4)
    T[:3, :3] = rotation_z_to(np.array([1.0, 2.0, 2.0]) / 3.0)
    T[:3, 3] = [10.0, -5.0, 3.0]
    moved = caps.transformed(T)
    np.testing.assert_allclose(moved.length, caps.length)
    np.testing.assert_allclose(moved.a[0, 0], T[:3, :3] @ caps.a[0, 0] + T[:3, 3])
    mesh = caps.to_trimesh(0)
    assert isinstance(mesh, trimesh.Trimesh)
    # every vertex of the exported chain lies on the swept surface (within the radius of the
    # axis, and at the radius of at least one segment's axis up to the polygon's sag)
    d = _segment_distance(mesh.vertices, caps.a[0], caps.b[0])
    assert np.all(d.min(axis=1) <= 1.0 + 1e-6)
    assert np.all(np.abs(d - 1.0).min(axis=1) <= 1.0 - np.cos(np.pi / 12) + 1e-6)


@pytest.mark.parametrize("d", [np.array([0, 0, 1.0]), np.array([0, 0, -1.0]), np.array([0.6, 0, 0.8])])
def test_rotation_z_to(d):
    R = rotation_z_to(d)
    np.testing.assert_allclose(R @ [0, 0, 1.0], d, atol=1e-12)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)


def _segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(P, K) distances from points to segments."""
    v = b - a
    t = np.clip(np.einsum("pkj,kj->pk", p[:, None, :] - a[None], v) / np.einsum("kj,kj->k", v, v), 0, 1)
    return np.linalg.norm(p[:, None, :] - (a[None] + t[..., None] * v[None]), axis=2)


def shape_from_points(points: np.ndarray, radius: float | np.ndarray) -> Shape:
    """A Shape built directly from backbone points (B, m, 3) (for synthetic tests)."""
    B, m, _ = points.shape
    s = np.concatenate([np.zeros((B, 1)), np.cumsum(np.linalg.norm(np.diff(points, axis=1), axis=2), axis=1)], axis=1)
    return Shape(points=points, s=s, radius=np.broadcast_to(radius, (B, m)).astype(float).copy(),
                 ok=np.ones(B, dtype=bool))
