"""The motion cover between checked states is derived from the model, and it holds.

Oracle: dense continuation along random straight edges (each dense state solved with its
``uz_init`` from the previous one; at least 50 states per edge, 8 per 0.5 mm segment) with 116
backbone points per shape; distances computed here. No backbone point (at a fixed arc-length
fraction) of a dense state is farther from the same point of either end state of its segment
than the cover the validator certifies for it (``point_mm``), and the dense continuous backbone
lies inside the end states' capsules (their chords grown by ``Shape.pad + capsule_mm``). Models:
physics and rigid, every effect family with representative parameters (torsion, friction,
clearance in both forms, precurvature, stiffness, registration, joint offsets, and loads:
gravity, 0.5 N and 2 N tip forces), on seed1 and two_tube_nylon, and the shipped learned model.
At a fold (a motion the robot really snaps on, replayed by continuation) the cover refuses.
"""

from __future__ import annotations

from dataclasses import fields

import numpy as np
import pytest
import trimesh

from ctrplan.collision.field import FieldConfig
from ctrplan.collision.scene import Scene, SceneMesh
from ctrplan.collision.world import CollisionWorld
from ctrplan.planning.motion import evaluate_chains, path_chains
from ctrplan.planning.validator import (
    BatchValidator,
    ValidatorConfig,
    edge_direction,
    interpolate,
    joint_delta,
    project_joints,
)
from ctrplan.robot import load_robot
from ctrplan.shape.bounds import MotionCover, motion_cover
from ctrplan.shape.effects import EffectModel, prepare, to_sensor
from ctrplan.shape.models import load_model
from ctrplan.shape.physics import Loads, PhysicsModel

G = 9.80665
PER = 8            # dense states per checked segment
SUB = 5            # dense backbone points per capsule
POINTS = 24
DENSE_POINTS = (POINTS - 1) * SUB + 1
TOL = 1e-6         # mm, round-off


def _effects(name: str) -> dict:
    """One effect family with representative parameters (fit-bound scale)."""
    return {
        "torsion": {"torsion": {"compliance": 1.5}},
        "friction": {"friction": {"lost1": 0.05, "lost2": 0.03, "form": 1.0}},
        "clearance": {"clearance": {"c0": 0.1, "c1": 0.1}},
        "gap": {"clearance": {"length": 20.0, "limit": 0.3}},
        "precurvature": {"precurvature": {"scale1": 1.2, "scale2": 0.8}},
        "stiffness": {"stiffness": {"ratio1": 1.3}},
        "registration": {"registration": {"tx": 5.0, "rx": 0.1}},
        "joint_offset": {"joint_offset": {"dalpha1": 0.1, "dbeta1": 2.0}},
        "load": {"load": {"gy": -G, "fx": 0.5}},
        "all": {"torsion": {"compliance": 1.2}, "friction": {"lost1": 0.05, "form": 1.0},
                "clearance": {"c0": 0.05, "c1": 0.05, "length": 10.0, "limit": 0.3},
                "precurvature": {"scale1": 1.1}, "stiffness": {"ratio1": 1.2},
                "registration": {"tx": 3.0, "rz": 0.2}, "joint_offset": {"dalpha2": 0.05},
                "load": {"gx": G, "fy": 0.5}},
    }[name]


def _model(robot, name):
    if name in ("physics", "rigid", "learned"):
        return load_model(name, robot)
    if name == "gravity":
        return PhysicsModel(robot, loads=Loads(gravity=(0.0, -G, 0.0)))
    if name == "force0.5":
        return PhysicsModel(robot, loads=Loads(tip_force=(0.5, 0.0, 0.0)))
    if name == "force2":
        return PhysicsModel(robot, loads=Loads(tip_force=(0.0, 2.0, 0.0)))
    return EffectModel(robot, "compliant", _effects(name), pure=True)


def _slice(params, i):
    return type(params)(**{f.name: (None if getattr(params, f.name) is None
                                    else getattr(params, f.name)[i:i + 1])
                           for f in fields(params)})


def continuation(model, qs, points, direction=None, uz=None):
    """Dense states along a motion: (points (T, m, 3), pads (T, m - 1), ok (T,), last uz0).
    Mechanics models: one state at a time, each Newton started from the previous state's
    uz(0) (the robot follows its branch); the learned model has no state."""
    if isinstance(model, (PhysicsModel, EffectModel)):
        if isinstance(model, PhysicsModel):
            phys, q, params, eff = model, qs, model.base_params(len(qs)), {}
        else:
            d = None if direction is None else np.broadcast_to(direction, qs.shape)
            prep = prepare(model.robot, model.base, model.effects, qs, direction=d, pure=True)
            phys = model._compliant if prep.torsion else model._rigid
            q, params, eff = prep.q, prep.params, model.effects
        P, pads, oks = [], [], []
        for i in range(len(qs)):
            sh = phys.solve(q[i:i + 1], points, _slice(params, i), uz_init=uz)
            uz = phys.last_info.uz0
            P.append(to_sensor(eff, sh.points)[0] if "registration" in eff else sh.points[0])
            pads.append(sh.pad[0])
            oks.append(bool(sh.ok[0]))
        return np.array(P), np.array(pads), np.array(oks), uz
    # small batches: the learned model's float64 path (larger ones run in float32)
    parts = [model.shape(qs[i:i + 64], points=points) for i in range(0, len(qs), 64)]
    return (np.concatenate([p.points for p in parts]), np.concatenate([p.pad for p in parts]),
            np.concatenate([np.asarray(p.ok) for p in parts]), None)


def seg_dist(p, a, b):
    """Distance of points p (..., J, 3) to segments a-b (..., 3)."""
    v = b - a
    vv = np.maximum(np.einsum("...c,...c->...", v, v), 1e-30)
    t = np.clip(np.einsum("...jc,...c->...j", p - a[..., None, :], v) / vv[..., None], 0.0, 1.0)
    return np.linalg.norm(p - (a[..., None, :] + t[..., None] * v[..., None, :]), axis=-1)


def _edge_oracle(robot, model, q0, q1, res=0.5):
    """(worst point ratio, worst capsule ratio, certified) of one edge, or None where the dense
    continuation is not ok or is on another branch than the validator's states."""
    n = robot.n
    val = BatchValidator(robot, model, None)
    states = interpolate(q0, q1, n, val.config.alpha_weight_mm, res)
    ev = evaluate_chains(val, path_chains(val, states), POINTS)
    cov = ev.cover
    K = len(states) - 1
    per = max(PER, -(-50 // K))
    t = np.linspace(0.0, 1.0, K * per + 1)
    qs = q0[None] + t[:, None] * joint_delta(q0, states[-1], n)[None]
    d = edge_direction(q0, q1, n) if val.directional else None
    P, _, ok, _ = continuation(model, qs, DENSE_POINTS, None if d is None else np.where(d == 0, 1, d))
    grid = P[:, ::SUB]
    # another branch than the validator's states (or, for the learned model, more than its
    # float32 path's round-off: the validator evaluates batches over 64 rows in float32)
    if not ok.all() or np.max(np.linalg.norm(grid[::per] - ev.shapes[0].points, axis=-1)) > 1e-3:
        return None
    worst_pt = worst_cap = 0.0
    pads = ev.shapes[0].pad
    for i in range(K):
        dense = P[i * per:(i + 1) * per + 1]                            # (per + 1, M, 3)
        caps = np.stack([dense[:, SUB * k:SUB * k + SUB + 1] for k in range(POINTS - 1)], 1)
        for end, idx in ((i * per, i), ((i + 1) * per, i + 1)):
            move = np.linalg.norm(dense[:, ::SUB] - grid[end][None], axis=-1)
            worst_pt = max(worst_pt, float(np.max((move - TOL) / cov.point_mm[i])))
            dist = seg_dist(caps, grid[end, :-1][None], grid[end, 1:][None]).max(-1)
            allow = pads[idx] + cov.capsule_mm[i]
            worst_cap = max(worst_cap, float(np.max((dist - TOL) / allow)))
    return worst_pt, worst_cap, bool(cov.certified.all())


def _oracle(robot_name, model_name, edges, seed):
    robot = load_robot(robot_name)
    model = _model(robot, model_name)
    rng = np.random.default_rng([seed, len(model_name)])
    n = robot.n
    done = certified = 0
    for _ in range(edges):
        q0 = robot.sample(1, seed=rng)[0]
        step = np.concatenate([rng.normal(0, 0.15, n), rng.normal(0, 3.0, n)])
        q1 = project_joints(robot, (q0 + step)[None])[0]
        out = _edge_oracle(robot, model, q0, q1)
        if out is None:
            continue
        pt, cap, cert = out
        assert pt <= 1.0, (robot_name, model_name, pt)
        assert cap <= 1.0, (robot_name, model_name, cap)
        done += 1
        certified += cert
    assert done >= edges * 2 // 3
    # not vacuous: smooth motions of these models are resolved (certified) where they are valid
    assert certified >= done * 2 // 3


@pytest.mark.parametrize("robot_name,model_name", [
    ("seed1", "physics"), ("two_tube_nylon", "all"), ("seed1", "force2"), ("seed1", "learned")])
def test_dense_continuation_never_exceeds_the_motion_cover(robot_name, model_name):
    _oracle(robot_name, model_name, edges=2, seed=1)


FAMILIES = ["physics", "rigid", "torsion", "friction", "clearance", "gap", "precurvature",
            "stiffness", "registration", "joint_offset", "load", "gravity", "force0.5", "force2",
            "all"]


@pytest.mark.statistical
@pytest.mark.parametrize("robot_name", ["seed1", "two_tube_nylon"])
@pytest.mark.parametrize("model_name", FAMILIES)
def test_dense_continuation_motion_cover_every_family(robot_name, model_name):
    """The oracle on 6 random edges per robot and model (every effect family alone)."""
    _oracle(robot_name, model_name, edges=6, seed=20)


@pytest.mark.statistical
def test_dense_motion_cover_learned_many_edges():
    _oracle("seed1", "learned", edges=30, seed=21)


# ----------------------------------------------------------------------------- jumps and folds
class Continued:
    """A physics model replayed as the robot moves: each row's Newton starts from the uz(0) of
    the nearest configuration solved before (in the joint metric), so a motion evaluated in
    order follows its branch, and snaps only where that branch ends (a fold)."""

    def __init__(self, robot, q_start, uz_start):
        self.robot = robot
        self.name = "continued"
        self.inner = PhysicsModel(robot)
        self.known_q = [np.asarray(q_start, dtype=float)]
        self.known_uz = [np.asarray(uz_start, dtype=float)]

    def shape(self, q, points=20):
        q = np.atleast_2d(np.asarray(q, dtype=float))
        out = []
        for row in q:
            d = joint_delta(np.array(self.known_q), row[None], self.robot.n)
            near = int(np.argmin(30.0 * np.abs(d[:, :self.robot.n]).sum(1)
                                 + np.linalg.norm(d[:, self.robot.n:], axis=1)))
            sh = self.inner.solve(row[None], points, self.inner.base_params(1),
                                  uz_init=self.known_uz[near][None])
            self.known_q.append(row)
            self.known_uz.append(self.inner.last_info.uz0[0].copy())
            out.append(sh)
        cat = lambda name: np.concatenate([getattr(s, name) for s in out])   # noqa: E731
        return type(out[0])(cat("points"), cat("s"), cat("radius"), cat("ok"), cat("pad"))


def _far_world():
    """A small obstacle half a metre away: every state is free and the clearances alone
    certify small motions (a motion that is not resolved is never certified by them)."""
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=5.0)
    mesh.apply_translation([500.0, 0.0, 0.0])
    scene = Scene(name="far", path="<memory>", meshes=(SceneMesh("far", "obstacle", mesh),),
                  base_pose=np.eye(4), targets=())
    return CollisionWorld(scene, cache=False, field_config=FieldConfig(h_mm=8.0, band_mm=2.0,
                                                                        max_nodes=20_000))


def _nylon_branch(a_start):
    """two_tube_nylon with both curved sections overlapping (bistable for relative rotations of
    about 2.54-3.74 rad): the uz(0) at relative rotation ``a_start`` reached by continuation
    from 2.4 rad (the branch the robot is on when it turns that way)."""
    robot = load_robot("two_tube_nylon")
    q = np.array([[a, 0.0, -160.0, -100.0] for a in np.linspace(2.4, a_start, 80)])
    _, _, ok, uz = continuation(PhysicsModel(robot), q, POINTS)
    assert ok.all()
    return robot, q[-1], uz[0]


def test_a_fold_on_the_motion_is_refused():
    """Turning two_tube_nylon's inner tube from 3.5 to 3.9 rad on the continued branch: the
    robot snaps at about 3.74 rad (the branch ends); the dense continuation jumps there, the
    cover refuses that segment and check_path fails it, while a motion from 3.5 to 3.7 rad
    (near the fold, not across it) is certified and its cover holds."""
    robot, q0, uz0 = _nylon_branch(3.5)
    world = _far_world()
    across = np.array([3.9, 0.0, -160.0, -100.0])
    qs = q0[None] + np.linspace(0, 1, 81)[:, None] * (across - q0)[None]
    P, _, ok, _ = continuation(PhysicsModel(robot), qs, POINTS, uz=uz0[None])
    assert np.max(np.linalg.norm(np.diff(P[:, -1], axis=0), axis=-1)) > 20.0   # the snap
    model = Continued(robot, q0, uz0)
    check = BatchValidator(robot, model, world).check_path(np.stack([q0, across]), 0.5, fcl_all=False)
    assert not check.ok and "motion" in set(check.contact[check.collides])
    # the states alone (no motion bound) miss the snap
    model = Continued(robot, q0, uz0)
    loose = BatchValidator(robot, model, world, ValidatorConfig(motion_bound=False))
    assert loose.check_path(np.stack([q0, across]), 0.5, fcl_all=False).ok
    # near the fold, not across it: certified, and the cover holds on the continued motion
    near = np.array([3.7, 0.0, -160.0, -100.0])
    model = Continued(robot, q0, uz0)
    assert BatchValidator(robot, model, world).check_path(np.stack([q0, near]), 0.5, fcl_all=False).ok
    val = BatchValidator(robot, Continued(robot, q0, uz0), None)
    states = interpolate(q0, near, robot.n, 30.0, 0.5)
    cov = evaluate_chains(val, path_chains(val, states), POINTS).cover
    K = len(states) - 1
    qs = q0[None] + np.linspace(0, 1, K * PER + 1)[:, None] * (near - q0)[None]
    P, _, ok, _ = continuation(PhysicsModel(robot), qs, POINTS, uz=uz0[None])
    assert ok.all()
    for i in range(K):
        seg = P[i * PER:(i + 1) * PER + 1]
        for end in (seg[0], seg[-1]):
            assert np.all(np.linalg.norm(seg - end[None], axis=-1) <= cov.point_mm[i] + TOL)


def test_a_jump_between_states_is_never_certified():
    """The model without history picks its branch per state and jumps 53 mm at relative
    rotation pi (issue 35): that segment is not resolved at any level, and check_path fails
    (with branch tracking the continuation sees the branch end first: contact "branch")."""
    robot = load_robot("two_tube_nylon")
    model = load_model("physics", robot)
    q0, q1 = np.array([3.0, 0.0, -160.0, -100.0]), np.array([3.3, 0.0, -160.0, -100.0])
    val = BatchValidator(robot, model, _far_world())
    states = interpolate(q0, q1, robot.n, 30.0, 0.5)
    cov = evaluate_chains(val, path_chains(val, states), POINTS).cover
    jump = np.max(np.linalg.norm(np.diff(val.shapes(states).points, axis=0), axis=-1), axis=1)
    assert jump.max() > 40.0
    assert not cov.certified[np.argmax(jump)]
    assert cov.certified[jump < 1.0].all()
    check = val.check_path(np.stack([q0, q1]), 0.5, fcl_all=False)
    assert not check.ok and check.contact[check.first_bad] in ("branch", "motion")


# ----------------------------------------------------------------------------- the bound itself
def _synthetic(f, h, eps):
    """motion_cover of a curve f(t) (t (T,) -> (T, m, 3)) on [0, h] with one-sided velocities
    over eps, and the true largest distance of each point from either end."""
    p0, p1 = f(np.array([0.0]))[0], f(np.array([h]))[0]
    v0 = (f(np.array([eps]))[0] - p0) / eps
    v1 = (p1 - f(np.array([h - eps]))[0]) / eps
    cov = motion_cover(p0[None], p1[None], v0[None], v1[None], np.array([h]), np.array([eps]))
    tt = np.linspace(0.0, h, 2001)
    P = f(tt)
    true = np.maximum(np.linalg.norm(P - p0, axis=-1), np.linalg.norm(P - p1, axis=-1)).max(0)
    return cov, true


def test_bound_covers_closed_form_motions():
    """Rotations about an axis (a point at radius r turning by omega t: exact circle), a
    quadratic and a cubic: the bound is at least the true largest distance, and resolved."""
    r = np.array([5.0, 50.0, 200.0])

    def circle(t, w=0.8):
        ang = w * t[:, None]
        return np.stack([r * np.cos(ang), r * np.sin(ang), 0.0 * r * ang], -1)

    def poly(t):
        return np.stack([t[:, None] ** 2 * r / 10, t[:, None] ** 3 * r / 30, t[:, None] * r / 50], -1)

    for f in (circle, poly):
        for h in (0.5, 0.06, 0.008):
            cov, true = _synthetic(f, h, h / 16)
            assert cov.resolved.all()
            assert np.all(true <= cov.point_mm[0])
            assert np.all(cov.point_mm[0] <= 3 * true + 2e-3)       # not absurdly loose


def test_a_step_is_not_resolved_at_any_segment_length():
    """A backbone point that steps by 1 mm inside the segment (a jump, smooth on either side):
    never resolved, however short the segment."""
    for h in (0.5, 0.06, 0.008):
        def f(t, h=h):
            x = 0.3 * t + (t > 0.4 * h)
            return np.stack([x, 0 * x, 0 * x], -1)[:, None, :]
        cov, _ = _synthetic(f, h, h / 16)
        assert isinstance(cov, MotionCover) and not cov.resolved.any()
