"""The closed-form torsionally rigid model (the learned model's analytic base).

Oracles: the foreign generator's rigid truth (tests/foreign, its own YAML parsing and its own
closed-form arcs, no ctrplan import), ctrplan's integrating kernel (a different
implementation of the same equations) and a single precurved tube written out by hand.
"""

from __future__ import annotations

import numpy as np
import pytest
import torch

from ctrplan.robot import load_robot, robot_from_dict
from ctrplan.shape.physics import PhysicsModel
from ctrplan.shape.rigid import RigidModel, rigid_points_torch

ROBOTS = ("seed1", "two_tube_nylon", "two_tube_wide")


def _configs(robot, n, seed):
    q = robot.sample(n, seed=seed)
    # and the corners: retracted, everything out, tube ends and curve starts coinciding
    lo, hi = robot.beta_bounds()
    extra = [robot.retracted(), np.concatenate([np.zeros(robot.n), hi])]
    return np.concatenate([q, np.array(extra)])


@pytest.mark.parametrize("name", ROBOTS)
def test_matches_the_foreign_rigid_truth_and_the_kernel(name):
    from tests.foreign import backbones

    robot = load_robot(name)
    q = _configs(robot, 400, seed=11)
    mine = RigidModel(robot).shape(q, 23)
    theirs = backbones(name, q, {}, points=23)          # no torsion effect: the rigid truth
    assert np.max(np.abs(mine.points - theirs)) < 1e-9
    kernel = PhysicsModel(robot, torsion=False).shape(q, 23)
    assert np.max(np.abs(mine.points - kernel.points)) < 1e-9
    np.testing.assert_allclose(mine.s, kernel.s, atol=1e-12)
    np.testing.assert_array_equal(mine.radius, kernel.radius)
    np.testing.assert_allclose(mine.pad, kernel.pad, rtol=1e-12)
    assert mine.ok.all()


@pytest.mark.parametrize("name", ROBOTS)
def test_torch_implementation_matches_the_foreign_truth(name):
    from tests.foreign import backbones

    robot = load_robot(name)
    q = _configs(robot, 300, seed=12)
    theirs = backbones(name, q, {}, points=17)
    got = RigidModel(robot).points_torch(torch.as_tensor(q, dtype=torch.float64), 17).numpy()
    assert np.max(np.abs(got - theirs)) < 1e-9


def test_one_precurved_tube_by_hand():
    """A single tube, straight then curved with curvature k: a line then a circular arc in
    the plane its precurvature points to (alpha = 0: +x; alpha = pi/2: +y)."""
    robot = robot_from_dict({"name": "one", "tubes": [
        {"od": 1.0, "id": 0.8, "straight_length": 60.0, "curved_length": 50.0,
         "curvature": 0.02, "youngs_modulus": 60000, "poisson_ratio": 0.33}]})
    k, Ls = 0.02, 60.0
    for alpha, beta in ((0.0, 0.0), (np.pi / 2, -20.0), (1.1, -45.0)):
        q = np.array([[alpha, beta]])
        m = 41
        s = np.linspace(0.0, beta + 110.0, m)
        start = beta + Ls                                   # curve start (arc length)
        th = k * np.clip(s - max(start, 0.0), 0.0, None)
        straight = np.minimum(s, max(start, 0.0))
        # in the bending plane: along z and sideways toward R_z(alpha) e_x
        side = (1 - np.cos(th)) / k
        z = straight + np.sin(th) / k
        want = np.stack([side * np.cos(alpha), side * np.sin(alpha), z], axis=1)
        got = RigidModel(robot).backbone(q, m)[0]
        np.testing.assert_allclose(got, want, atol=1e-10)


def test_pad_bounds_the_chords_of_the_dense_backbone():
    robot = load_robot("seed1")
    q = robot.sample(200, seed=13)
    m = 8                                                  # every 64th dense point is a coarse one
    rm = RigidModel(robot)
    coarse = rm.shape(q, m)
    dense = rm.backbone(q, (m - 1) * 64 + 1)
    a, b = coarse.points[:, :-1], coarse.points[:, 1:]
    worst = np.zeros((len(q), m - 1))
    for j in range(1, 64):
        p = dense[:, j::64][:, :m - 1]
        t = np.clip(np.einsum("bkc,bkc->bk", p - a, b - a) / np.einsum("bkc,bkc->bk", b - a, b - a), 0, 1)
        worst = np.maximum(worst, np.linalg.norm(p - (a + t[..., None] * (b - a)), axis=2))
    assert np.all(worst <= coarse.pad + 1e-9)
    assert worst.max() > 0.3 * coarse.pad.max()          # and the bound is not vacuous


def test_bad_arguments():
    rm = RigidModel("seed1")
    with pytest.raises(ValueError):
        rm.backbone(np.zeros((2, 5)))
    with pytest.raises(ValueError):
        rm.shape(rm.robot.sample(2, seed=0), points=1)
    with pytest.raises(ValueError):
        rm.backbone(np.full((1, 6), np.nan))


def test_torch_function_takes_any_device_tensors():
    robot = load_robot("two_tube_wide")
    rm = RigidModel(robot)
    q = robot.sample(5, seed=1)
    t = lambda a: torch.as_tensor(a, dtype=torch.float64)  # noqa: E731
    got = rigid_points_torch(t(q), t(rm._L), t(rm._straight), t(rm._kappa), t(rm._EI), 9)
    assert got.shape == (5, 9, 3) and got.dtype == torch.float64
    np.testing.assert_allclose(got.numpy(), rm.backbone(q, 9), atol=1e-10)
