"""Swept geometry covers the continuous backbone: capsules padded by the sagitta bound.

Oracle (closed form, shares nothing with the capsule code): a single circular tube of curvature
``kappa`` and radius ``r`` facing a flat wall placed at ``r + eps`` from the true arc at a chosen
arc length. The arc lies on a circle, so its distance to a plane tangent-parallel to the circle
at that point is exactly ``r + eps`` there and larger everywhere else: the tube penetrates iff
``eps < 0``. At every sampling density the world must report a collision for ``eps < 0``, and
must report free once ``eps`` exceeds the padding (``kappa h^2 / 8``).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import trimesh

from ctrplan.collision.capsules import capsules_from_points, curvature_bound, sagitta_bound
from ctrplan.collision.scene import Scene, SceneMesh
from ctrplan.collision.world import CollisionWorld
from ctrplan.shape.base import Shape

KAPPA = 0.02      # 1/mm: twice seed1's largest precurvature, so the sagitta is easy to see
LENGTH = 60.0     # mm of arc (kappa * L = 1.2 rad)
RADIUS = 1.25     # mm, seed1's outer tube


def _arc(s):
    """Points (m, 3), unit tangents and outward normals of the circular arc at arc lengths s."""
    k = KAPPA
    p = np.stack([(1 - np.cos(k * s)) / k, np.zeros_like(s), np.sin(k * s) / k], axis=-1)
    t = np.stack([np.sin(k * s), np.zeros_like(s), np.cos(k * s)], axis=-1)
    centre = np.array([1 / k, 0.0, 0.0])
    n = (p - centre) / np.linalg.norm(p - centre, axis=-1, keepdims=True)
    return p, t, n


def _wall():
    half = 15.0
    v = np.array([[-half, -half, 0], [half, -half, 0], [half, half, 0], [-half, half, 0]], float)
    mesh = trimesh.Trimesh(v, np.array([[0, 1, 2], [0, 2, 3]]), process=False)
    return Scene(name="plane", path="<memory>", meshes=(SceneMesh("plane", "wall", mesh),),
                 base_pose=np.eye(4), targets=())


@pytest.fixture(scope="module")
def scene():
    return _wall()


def _placed(m: int, s_star: float, eps: float) -> Shape:
    """The arc sampled at m points, moved rigidly so that its point at s_star is at distance
    RADIUS + eps below the plane z = 0, with the outward normal there pointing to +z."""
    s = np.linspace(0.0, LENGTH, m)
    pts, _, _ = _arc(s)
    p0, t0, n0 = (a[0] for a in _arc(np.array([s_star])))
    R = np.stack([t0, np.cross(n0, t0), n0])        # rows: new x, y, z axes
    local = (pts - p0) @ R.T
    local[:, 2] -= RADIUS + eps
    return Shape(points=local[None], s=s[None], radius=np.full((1, m), RADIUS), ok=np.array([True]))


@pytest.mark.parametrize("prefilter", [False, True])
def test_padded_capsules_never_call_a_penetrating_arc_free_at_any_density(scene, prefilter):
    world = CollisionWorld(scene, prefilter=prefilter, cache=False, curvature_per_mm=KAPPA)
    chords_only = CollisionWorld(scene, prefilter=prefilter, cache=False, padding="none")
    missed_by_chords = 0
    for m in range(2, 41):
        h = LENGTH / (m - 1)
        pad = float(sagitta_bound(h, KAPPA))
        # the true bulge of a circle's arc over its chord is (1 - cos(kappa h / 2)) / kappa
        assert pad >= (1 - math.cos(KAPPA * h / 2)) / KAPPA - 1e-12
        k = (m - 1) // 2
        for s_star in (k * h + h / 2, k * h + h / 3, k * h):   # mid-segment (worst), off-mid, sample
            for eps in (-0.01, -0.002):
                shp = _placed(m, s_star, eps)
                assert world.check(shp).collides[0], (m, s_star, eps)
                assert world.collides(shp)[0] and world.first_collision(shp) == 0
                missed_by_chords += int(not chords_only.check(shp).collides[0])
            free = _placed(m, s_star, pad + 0.01)
            rep = world.check(free)
            assert not rep.collides[0], (m, s_star, pad)
            # the padded capsules are at least eps - pad = 0.01 mm away (exactly that where a
            # sample sits at s_star); the conservative clearance never exceeds FCL's distance
            exact = world.clearance_exact(free)[0]
            assert exact >= 0.01 - 1e-6
            if s_star == k * h:
                assert exact == pytest.approx(0.01, abs=1e-5)
            assert 0.0 <= rep.clearance_mm[0] <= exact + 1e-9
    # without the padding, the chords miss the bulge at coarse densities (the bug this fixes)
    assert missed_by_chords > 0


def test_curvature_bound_of_the_physics_models_holds_on_dense_backbones(seed1):
    """The physics backbones' curvature (finite differences on 600 points) stays below the
    robot's largest precurvature, the bound the padding uses."""
    from ctrplan.shape.physics import PhysicsModel

    bound = curvature_bound(seed1)
    assert bound == pytest.approx(0.0093354)
    q = seed1.sample(40, seed=5)
    for torsion in (True, False):
        shp = PhysicsModel(seed1, torsion=torsion).shape(q, points=600)
        ok = shp.ok
        p = shp.points[ok]
        h = np.diff(shp.s[ok], axis=1)[:, :1, None]
        second = (p[:, 2:] - 2 * p[:, 1:-1] + p[:, :-2]) / h**2
        kappa = np.linalg.norm(second, axis=-1)
        assert kappa.max() <= bound * 1.02, kappa.max()
        assert kappa.max() >= 0.5 * bound      # the test sees real curvature


def test_padding_grows_with_the_square_of_the_spacing():
    pts = np.zeros((1, 3, 3))
    pts[0, :, 2] = [0.0, 10.0, 20.0]
    caps = capsules_from_points(pts, np.full((1, 3), 1.0), 0.5, curvature_per_mm=0.01,
                                s=np.array([[0.0, 10.0, 20.0]]))
    np.testing.assert_allclose(caps.radius, 1.0 + 0.5 + 0.01 * 100 / 8)
    with pytest.raises(ValueError):
        capsules_from_points(pts, np.ones((1, 3)), curvature_per_mm=-1.0)
