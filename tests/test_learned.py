"""Learned full-shape model: data generation, network, save/load, accuracy bounds."""

from __future__ import annotations

import numpy as np
import pytest

from ctrplan.shape.dataset import simulate_shapes
from ctrplan.shape.physics import PhysicsModel


@pytest.fixture(scope="module")
def physics():
    return PhysicsModel("seed1")


def test_simulate_shapes_matches_in_process_and_keeps_order(physics):
    q = physics.robot.sample(300, seed=3)
    ref = physics.shape(q, points=12)
    par = simulate_shapes(physics, q, points=12, workers=2, chunk=70, progress=False)
    one = simulate_shapes(physics, q, points=12, workers=1, chunk=70, progress=False)
    for got in (par, one):
        assert got.points.shape == (300, 12, 3)
        np.testing.assert_array_equal(got.points, ref.points)
        np.testing.assert_array_equal(got.s, ref.s)
        np.testing.assert_array_equal(got.radius, ref.radius)
        np.testing.assert_array_equal(got.ok, ref.ok)


def test_simulate_shapes_rejects_bad_arguments(physics):
    q = physics.robot.sample(4, seed=0)
    with pytest.raises(ValueError):
        simulate_shapes(physics, q, workers=0, progress=False)
    with pytest.raises(ValueError):
        simulate_shapes(physics, q, chunk=0, progress=False)
    with pytest.raises(ValueError):
        simulate_shapes(physics, q, points=1, progress=False)
