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

from ctrplan.collision.field import FieldConfig
from ctrplan.collision.scene import Scene, SceneMesh
from ctrplan.collision.world import CollisionWorld
from ctrplan.planning.validator import (
    BatchValidator,
    ValidatorConfig,
    interpolate_path,
    project_joints,
)
from ctrplan.shape.effects import EffectModel
from ctrplan.shape.models import load_model

DENSE = 500
POINTS = 24
#: a coarse distance field (its clearances are looser lower bounds: more subdivision, still safe)
COARSE = FieldConfig(h_mm=8.0, band_mm=2.0, max_nodes=20_000, refine_mm=2.0)


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


def _step(a: np.ndarray, b: np.ndarray, n: int) -> np.ndarray:
    """b - a with rotations along the shorter arc (the motion between two states)."""
    d = np.asarray(b, dtype=float) - np.asarray(a, dtype=float)
    d[:n] = (d[:n] + np.pi) % (2 * np.pi) - np.pi
    return d


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


_MODELS: dict = {}


def _model(seed1, name):
    """The model under test (loaded once per session)."""
    if name not in _MODELS:
        _MODELS[name] = (
            load_model("physics", seed1) if name == "physics" else
            EffectModel(seed1, "compliant", {"clearance": {"c0": 0.1, "c1": 0.1}})
            if name == "kinks" else load_model("learned", seed1))
    return _MODELS[name]


@pytest.mark.parametrize("name", ["physics", "kinks", "learned"])
def test_padded_check_never_calls_a_penetrating_configuration_free(seed1, name):
    _states_oracle(seed1, name, configs=12, directions=4, seed=4)


@pytest.mark.statistical
@pytest.mark.parametrize("name", ["physics", "kinks", "learned"])
def test_padded_check_oracle_many_configurations(seed1, name):
    """The same oracle on 150 configurations x 8 wall directions per model."""
    _states_oracle(seed1, name, configs=150, directions=8, seed=40)


def _states_oracle(seed1, name, configs, directions, seed):
    model = _model(seed1, name)
    rng = np.random.default_rng([seed, 11])
    q = seed1.sample(configs, seed=seed)
    dense = model.shape(q, points=DENSE)
    coarse = model.shape(q, points=POINTS)
    rad = _radius(seed1, q, dense.s)
    missed_by_chords = free_reported = 0
    for i in np.flatnonzero(dense.ok & coarse.ok):
        for _ in range(directions):
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
                hit = bool(CollisionWorld(scene, prefilter=False, cache=False).collides(sub)[0])
                if truth:
                    assert hit, (name, i, u, eps)
                    chords = CollisionWorld(scene, prefilter=False, cache=False, padding="none")
                    missed_by_chords += int(not chords.collides(sub)[0])
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
    _path_oracle(seed1, name, trials=3, seed=5)


@pytest.mark.statistical
@pytest.mark.parametrize("name", ["physics", "kinks", "learned"])
def test_verified_path_oracle_many_edges(seed1, name):
    """The same oracle on 12 random edges per model."""
    _path_oracle(seed1, name, trials=12, seed=50)


def _path_oracle(seed1, name, trials, seed):
    model = _model(seed1, name)
    rng = np.random.default_rng(seed)
    n = seed1.n
    val_cfg = ValidatorConfig()
    res = 0.5
    checked = 0
    for trial in range(trials):
        q0 = seed1.sample(1, seed=100 * seed + trial)[0]
        step = np.concatenate([rng.normal(0, 0.08, n), rng.normal(0, 2.0, n)])
        q1 = q0 + step
        q1 = project_joints(seed1, q1[None])[0]
        path = np.stack([q0, q1])
        states, _ = interpolate_path(path, n, val_cfg.alpha_weight_mm, res)
        t = np.linspace(0.0, 1.0, 11)[:, None]
        fine = np.concatenate([a[None] + t[:-1] * _step(a, b, n)[None] for a, b in
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
            world = CollisionWorld(scene, prefilter=False, cache=False, field_config=COARSE)
            check = BatchValidator(seed1, model, world, val_cfg).check_path(path, res, points=POINTS)
            if truth:
                assert not check.ok, (name, trial)
            checked += 1
    assert checked >= 2 * trials // 3


def _sphere(centre: np.ndarray, radius: float) -> Scene:
    mesh = trimesh.creation.icosphere(subdivisions=2, radius=radius)
    mesh.apply_translation(centre)
    return Scene(name="post", path="<memory>", meshes=(SceneMesh("post", "obstacle", mesh),),
                 base_pose=np.eye(4), targets=())


@pytest.mark.parametrize("name", ["physics", "learned"])
def test_motion_between_checked_states_is_covered(seed1, name):
    """A small obstacle beside the tip's path, touched only between two checked states (4 mm
    of metric apart): the motion bound makes check_path fail; the states alone
    (motion_bound=False) miss it at least once (the bug this fixes)."""
    model = _model(seed1, name)
    rng = np.random.default_rng(8)
    n, res, rho = seed1.n, 4.0, 0.1
    missed_by_states = caught = 0
    for trial in range(4):
        q0 = seed1.sample(1, seed=200 + trial)[0]
        # rotations only: the tip sweeps sideways, past the obstacle
        q1 = project_joints(seed1, (q0 + np.concatenate([rng.normal(0, 0.3, n),
                                                         np.zeros(n)]))[None])[0]
        path = np.stack([q0, q1])
        states, _ = interpolate_path(path, n, 30.0, res)
        if len(states) < 3:
            continue
        t = np.linspace(0.0, 1.0, 11)[:, None]
        k = len(states) // 2
        fine = states[k - 1][None] + t * _step(states[k - 1], states[k], n)[None]
        dense = model.shape(fine, points=DENSE)
        if not (dense.ok.all() and model.shape(states, points=POINTS).ok.all()):
            continue
        rad = _radius(seed1, fine, dense.s)
        tip = dense.points[:, -1]
        v = tip[6] - tip[4]
        tan = dense.points[5, -1] - dense.points[5, -2]
        tan /= np.linalg.norm(tan)
        w = v - tan * (v @ tan)               # the sideways part of the tip's motion ...
        w = np.cross(tan, w)                   # ... and the obstacle beside it
        if np.linalg.norm(w) < 1e-6 or np.linalg.norm(tip[10] - tip[0]) < 0.5:
            continue
        w /= np.linalg.norm(w)
        for eps in (-0.01,):
            scene = _sphere(tip[5] + w * (rad[5, -1] + rho + eps), rho)
            truth = any(_oracle_penetrates(scene, p, r) for p, r in zip(dense.points, rad))
            assert truth
            world = CollisionWorld(scene, cache=False, field_config=COARSE)
            ok = BatchValidator(seed1, model, world).check_path(path, res, points=POINTS).ok
            assert not ok, (name, trial)
            caught += 1
            loose = BatchValidator(seed1, model, world, ValidatorConfig(motion_bound=False))
            missed_by_states += int(loose.check_path(path, res, points=POINTS).ok)
    assert caught >= 2
    assert missed_by_states > 0


def test_learned_backbone_needs_and_keeps_its_polynomial_bound(seed1):
    """Dense (50 per segment) learned backbones against their 24-point chords, distances
    computed here: some exceed the precurvature sagitta (no curvature bound holds for the
    network), none exceeds the model's own polynomial bound (Shape.pad)."""
    model = load_model("learned", seed1)
    q = seed1.sample(1500, seed=1)
    sh = model.shape(q, points=POINTS)
    dense = model.backbone(q, points=(POINTS - 1) * 50 + 1)
    worst = np.zeros((len(q), POINTS - 1))
    for k in range(POINTS - 1):
        a, b = sh.points[:, k], sh.points[:, k + 1]
        seg = dense[:, k * 50:(k + 1) * 50 + 1]
        v = b - a
        tt = np.clip(np.einsum("bjc,bc->bj", seg - a[:, None], v)
                     / np.einsum("bc,bc->b", v, v)[:, None], 0.0, 1.0)
        worst[:, k] = np.linalg.norm(seg - (a[:, None] + tt[..., None] * v[:, None]), axis=-1).max(1)
    kappa = max(t.curvature for t in seed1.tubes)
    sagitta = kappa * np.diff(sh.s, axis=1) ** 2 / 8
    assert np.any(worst > sagitta + 1e-3)
    assert np.all(worst <= sh.pad)
