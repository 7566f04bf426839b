"""The padded collision check covers the continuous tube and its motion, for every model.

Oracle (shares no code with ctrplan/collision): each model's own dense backbone (500 points per
shape; along a path 10 interpolated states per checked edge) and the tube radius at each point,
computed here; its distance to a wall mesh measured with trimesh's closest-point query. The wall
is a plane placed, for each configuration and direction, at ``eps`` beyond the dense tube's
farthest extent: the tube penetrates iff ``eps < 0`` (to the dense sampling's precision, far below
the eps used). The padded check (24 points, the planner's density) must never call a
penetrating configuration free. Models: physics, a calibrated model with clearance kinks
(c0 = c1 = 0.1 rad, the fit bounds' scale), the shipped learned model.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from ctrplan.collision.scene import Scene, SceneMesh
from ctrplan.collision.world import CollisionWorld
from ctrplan.planning.validator import BatchValidator, ValidatorConfig, interpolate_path
from ctrplan.shape.effects import EffectModel
from ctrplan.shape.models import load_model

DENSE = 500
POINTS = 24


def _radius(robot, q, s):
    """Outer radius at arc lengths s (B, m): the outermost tube whose end is at or beyond s
    (written here, not ctrplan's radius_along)."""
    n = robot.n
    ends = q[:, n:] + np.array([t.straight_length + t.curved_length for t in robot.tubes])
    od = np.array([t.od for t in robot.tubes])
    r = np.full(s.shape, od[0] / 2.0)
    for i in range(n):   # innermost first: later (outer) tubes overwrite where present
        r = np.where(s <= ends[:, i:i + 1] + 1e-9, od[i] / 2.0, r)
    return r


def _plane(u: np.ndarray, offset: float) -> Scene:
    """A 600 mm square wall with normal u at u.x = offset (mesh: two triangles)."""
    a = np.cross(u, [1.0, 0.0, 0.0] if abs(u[0]) < 0.9 else [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(u, a)
    c = u * offset
    v = np.array([c - 300 * a - 300 * b, c + 300 * a - 300 * b, c + 300 * a + 300 * b,
                  c - 300 * a + 300 * b])
    mesh = trimesh.Trimesh(v, np.array([[0, 1, 2], [0, 2, 3]]), process=False)
    return Scene(name="plane", path="<memory>", meshes=(SceneMesh("plane", "wall", mesh),),
                 base_pose=np.eye(4), targets=())


def _oracle_penetrates(scene: Scene, pts: np.ndarray, rad: np.ndarray) -> bool:
    """Dense points (P, 3) with radii (P,): does any ball reach the wall mesh?"""
    mesh = scene.meshes[0].mesh
    _, dist, _ = trimesh.proximity.closest_point(mesh, pts)
    return bool(np.any(dist < rad))


def _models(seed1):
    return {
        "physics": load_model("physics", seed1),
        "kinks": EffectModel(seed1, "compliant", {"clearance": {"c0": 0.1, "c1": 0.1}}),
        "learned": load_model("learned", seed1),
    }


@pytest.mark.parametrize("name", ["physics", "kinks", "learned"])
def test_padded_check_never_calls_a_penetrating_configuration_free(seed1, name):
    model = _models(seed1)[name]
    rng = np.random.default_rng(11)
    q = seed1.sample(12, seed=4)
    dense = model.shape(q, points=DENSE)
    coarse = model.shape(q, points=POINTS)
    rad = _radius(seed1, q, dense.s)
    missed_by_chords = free_reported = 0
    for i in np.flatnonzero(dense.ok & coarse.ok):
        for _ in range(4):
            u = rng.normal(size=3)
            u /= np.linalg.norm(u)
            extent = float(np.max(dense.points[i] @ u + rad[i]))
            for eps in (-0.004, 0.02, 0.3):
                scene = _plane(u, extent + eps)
                truth = _oracle_penetrates(scene, dense.points[i], rad[i])
                assert truth == (eps < 0)
                sub = type(coarse)(coarse.points[i:i + 1], coarse.s[i:i + 1],
                                   coarse.radius[i:i + 1], coarse.ok[i:i + 1],
                                   None if coarse.pad is None else coarse.pad[i:i + 1])
                hit = bool(CollisionWorld(scene, prefilter=False, cache=False).check(sub).collides[0])
                if truth:
                    assert hit, (name, i, u, eps)
                    chords = CollisionWorld(scene, prefilter=False, cache=False, padding="none")
                    missed_by_chords += int(not chords.check(sub).collides[0])
                else:
                    free_reported += int(not hit)
    # not vacuous: the padding is not so large that nothing near the wall is free, and the
    # chords alone miss penetrations that the padding catches
    assert free_reported > 0
    assert missed_by_chords > 0


@pytest.mark.parametrize("name", ["physics", "kinks", "learned"])
def test_verified_path_motion_never_penetrates(seed1, name):
    """A path verified by check_path (states 0.5 mm apart) stays out of the wall at 10
    interpolated states per checked edge and 500 points per shape; a wall the dense motion
    touches makes the verification fail."""
    model = _models(seed1)[name]
    rng = np.random.default_rng(5)
    n = seed1.n
    val_cfg = ValidatorConfig()
    res = 0.5
    checked = 0
    for trial in range(3):
        q0 = seed1.sample(1, seed=100 + trial)[0]
        step = np.concatenate([rng.normal(0, 0.08, n), rng.normal(0, 2.0, n)])
        q1 = q0 + step
        from ctrplan.planning.validator import project_joints

        q1 = project_joints(seed1, q1[None])[0]
        path = np.stack([q0, q1])
        states, _ = interpolate_path(path, n, val_cfg.alpha_weight_mm, res)
        t = np.linspace(0.0, 1.0, 11)[:, None]
        fine = np.concatenate([a[None] + t[:-1] * (b - a)[None] for a, b in
                               zip(states[:-1], states[1:])] + [states[-1:]])
        dense = model.shape(fine, points=DENSE)
        if not dense.ok.all():
            continue
        rad = _radius(seed1, fine, dense.s)
        u = rng.normal(size=3)
        u /= np.linalg.norm(u)
        extent = np.max(np.einsum("bpc,c->bp", dense.points, u) + rad)
        for eps in (-0.004, 0.3):
            scene = _plane(u, float(extent + eps))
            truth = any(_oracle_penetrates(scene, p, r) for p, r in zip(dense.points, rad))
            assert truth == (eps < 0)
            world = CollisionWorld(scene, prefilter=False, cache=False)
            check = BatchValidator(seed1, model, world, val_cfg).check_path(path, res, points=POINTS)
            if truth:
                assert not check.ok, (name, trial)
            checked += 1
    assert checked >= 2
