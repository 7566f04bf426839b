"""Batched inverse kinematics: Jacobians against analytic and exact references, convergence,
joint-constraint projection."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from ctrplan.planning import ik
from ctrplan.planning.validator import project_joints
from ctrplan.robot import Robot, Tube, load_robot
from ctrplan.shape.models import load_model


def one_tube() -> Robot:
    """A single curved tube: its tip is an exact circular arc (analytic Jacobian)."""
    return Robot(name="one", tubes=(Tube(od=1.0, id=0.6, straight_length=100.0, curved_length=60.0,
                                         curvature=0.01, youngs_modulus=60000.0, poisson_ratio=0.33),))


def arc_tip(q: np.ndarray, t: Tube) -> tuple[np.ndarray, np.ndarray]:
    """Tip (B, 3) and Jacobian (B, 3, 2) of one tube at q = (alpha, beta)."""
    a, b = q[:, 0], q[:, 1]
    k, c = t.curvature, t.curved_length
    r = (1 - math.cos(k * c)) / k
    tip = np.stack([r * np.cos(a), r * np.sin(a), b + t.straight_length + math.sin(k * c) / k], axis=1)
    J = np.zeros((len(q), 3, 2))
    J[:, 0, 0] = -r * np.sin(a)
    J[:, 1, 0] = r * np.cos(a)
    J[:, 2, 1] = 1.0
    return tip, J


def test_finite_difference_jacobian_matches_the_arc():
    robot = one_tube()
    model = load_model("physics", robot)
    q = np.column_stack([np.linspace(-3, 3, 7), np.linspace(-90, -5, 7)])
    tip, J, ok = ik.tip_and_jacobian(model, q, ik.IKConfig(jacobian="fd"))
    tip_ref, J_ref = arc_tip(q, robot.tubes[0])
    assert ok.all()
    assert np.allclose(tip, tip_ref, atol=1e-6)
    assert np.allclose(J, J_ref, rtol=0, atol=2e-3 * np.abs(J_ref).max())


def test_finite_differences_match_the_learned_models_autograd_jacobian():
    robot = load_robot("seed1")
    model = load_model("learned", robot)
    q = robot.sample(4, seed=3)      # 4 x 7 rows: the learned model's float64 path
    fine = ik.IKConfig(jacobian="fd", fd_alpha=1e-6, fd_beta=1e-6)
    tip_fd, J_fd, _ = ik.tip_and_jacobian(model, q, fine)
    tip_ad, J_ad, ok = ik.tip_and_jacobian(model, q, ik.IKConfig(jacobian="model"))
    assert ok.all()
    assert np.allclose(tip_fd, tip_ad, atol=1e-3)
    scale = np.abs(J_ad).max(axis=(1, 2), keepdims=True)
    assert np.max(np.abs(J_fd - J_ad) / scale) < 1e-3


def test_fd_jacobian_is_one_batched_shape_call():
    robot = load_robot("seed1")
    model = load_model("physics", robot)
    calls = []

    class Counting:
        def __init__(self, m):
            self.m, self.robot, self.name = m, m.robot, "counting"

        def shape(self, q, points=20):
            calls.append(len(q))
            return self.m.shape(q, points)

    ik.tip_and_jacobian(Counting(model), robot.sample(5, seed=0))
    assert calls == [5 * (robot.dof + 1)]


@pytest.mark.parametrize("name", ["physics", "learned"])
def test_batched_ik_reaches_reachable_targets(name):
    robot = load_robot("seed1")
    model = load_model(name, robot)
    table = ik.workspace_table(model, 2048)
    q_true = robot.sample(6, seed=11)
    targets = model.shape(q_true, points=2).tip
    rng = np.random.default_rng(0)
    for target in targets:
        seeds = ik.seeds_for(table, robot, target, 16, rng)
        res = ik.solve_ik(model, robot, target, seeds, ik.IKConfig(stop_mm=0.05))
        assert robot.is_valid(res.q).all()
        assert np.sum(res.error_mm < 0.1) >= 4, res.error_mm
        tips = model.shape(res.q, points=2).tip
        # batch-size dependent float32/float64 paths of the learned model: ~1e-4 mm
        assert np.allclose(np.linalg.norm(tips - target, axis=1), res.error_mm, atol=1e-3)


def test_ik_reports_failure_for_an_unreachable_target():
    robot = load_robot("seed1")
    model = load_model("physics", robot)
    table = ik.workspace_table(model, 2048)
    target = np.array([0.0, 0.0, -50.0])     # behind the constraint plane
    res = ik.solve_ik(model, robot, target, ik.seeds_for(table, robot, target, 8, np.random.default_rng(0)))
    assert np.all(res.error_mm > 10.0)


def test_max_reach_bounds_every_tip():
    robot = load_robot("seed1")
    tips = load_model("physics", robot).shape(robot.sample(500, seed=2), points=2).tip
    assert np.all(np.linalg.norm(tips, axis=1) <= ik.max_reach_mm(robot) + 1e-9)


@given(st.integers(0, 2**31 - 1))
def test_projection_lands_inside_the_joint_constraints(seed):
    robot = load_robot("seed1")
    rng = np.random.default_rng(seed)
    q = robot.sample(32, seed=rng)
    q += np.concatenate([rng.normal(0, 5, (32, robot.n)), rng.normal(0, 80, (32, robot.n))], axis=1)
    p = project_joints(robot, q)
    assert robot.is_valid(p).all()
    assert np.all(np.abs(p[:, :robot.n]) <= math.pi + 1e-12)
    inside = robot.sample(16, seed=rng)
    assert np.allclose(project_joints(robot, inside), inside)
