"""Simulated measurements: experiment designs, hidden effects, noise, the CLI."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ctrplan.calibration.simulate import EXPERIMENTS, _shapes, design, experiment, simulate
from ctrplan.cli import main
from ctrplan.measured import read_measured
from ctrplan.robot import load_robot, write_configs
from ctrplan.shape.effects import EffectModel
from ctrplan.shape.physics import PhysicsModel


@pytest.mark.parametrize("robot", ["seed1", "two_tube_nylon"])
def test_experiment_designs(robot):
    r = load_robot(robot)
    n = r.n
    for name in EXPERIMENTS:
        q, sw = experiment(name, r, 60, sweeps=3, seed=1)
        assert q.shape == (60, 2 * n) and r.is_valid(q).all()
        assert len(set(sw.tolist())) == 3
        first = q[sw == sw[0]]
        moving = np.flatnonzero(np.ptp(first, axis=0) > 1e-9)
        if name == "feed":
            assert moving.tolist() == [n]                           # only beta1
            assert np.all(first[:, :n] == 0.0)                      # first sweep at alpha = 0
        elif name == "inner_rotation":
            assert moving.tolist() == [0]
            assert np.ptp(first[:, 0]) == pytest.approx(2 * math.pi)  # a full turn, and back
            assert first[0, 0] == pytest.approx(first[-1, 0])
        elif name == "outer_rotation":
            assert moving.tolist() == [n - 1]
            assert np.ptp(first[:, n - 1]) == pytest.approx(2 * math.pi)
        else:
            assert len(moving) == 2 * n
            d = np.sign(np.diff(first[:, 0]))
            assert (d > 0).any() and (d < 0).any()                  # back and forth


def test_simulate_hides_effects_and_seeds_noise():
    r = load_robot("two_tube_nylon")
    q, sw = design(r, ["inner_rotation"], 40, 2, seed=0)
    clean = simulate(r, q, {}, sweep=sw)
    np.testing.assert_allclose(clean.tip, PhysicsModel(r, torsion=False).shape(q, 2).tip)
    a = simulate(r, q, {"clearance": {"length": 8}}, sweep=sw, noise_mm=0.3, seed=4, points=5)
    b = simulate(r, q, {"clearance": {"length": 8}}, sweep=sw, noise_mm=0.3, seed=4, points=5)
    np.testing.assert_array_equal(a.tip, b.tip)
    assert a.points.shape == (40, 5, 3) and np.array_equal(a.points[:, -1], a.tip)
    assert np.diff(a.time).min() > 0 and list(a.sweep) == list(sw)
    noise = a.tip - simulate(r, q, {"clearance": {"length": 8}}, sweep=sw).tip
    assert 0.2 < noise.std() < 0.4


def test_big_batches_keep_the_friction_history():
    r = load_robot("two_tube_nylon")
    q, sw = design(r, ["random_walk"], 50, 2, seed=2)
    m = EffectModel(r, "rigid", {"friction": {"lost1": 0.2, "lost2": 0.1}, "joint_offset": {"dbeta1": -1}})
    direct = m.shape(q, 3, sweep=sw).points
    pooled = _shapes(m, q, 3, sw, big=1).points      # the multi-core path
    np.testing.assert_allclose(pooled, direct, atol=1e-12)


def test_cli_simulate(tmp_path, capsys):
    out = tmp_path / "m.csv"
    rc = main(["-q", "simulate", "--robot", "two_tube_nylon", "--experiment", "feed",
               "--experiment", "outer_rotation", "--n", "24", "--sweeps", "2",
               "--effect", "friction:lost1=0.1,lost2=0.05", "--effect", "clearance:length=6",
               "--noise", "0.1", "--points", "4", "--seed", "3", "--out", str(out)])
    assert rc == 0
    r = load_robot("two_tube_nylon")
    d = read_measured(out, r)
    assert len(d) == 48 and d.points.shape == (48, 4, 3) and d.time is not None
    assert {s[:4] for s in d.sweep} == {"feed", "oute"}
    cfg = tmp_path / "c.csv"
    write_configs(cfg, r, r.sample(7, 0))
    assert main(["-q", "simulate", "--robot", "two_tube_nylon", "--configs", str(cfg),
                 "--out", str(tmp_path / "c_meas.csv")]) == 0
    assert len(read_measured(tmp_path / "c_meas.csv", r)) == 7
    assert main(["-q", "simulate", "--robot", "seed1", "--n", "5", "--seed", "1",
                 "--out", str(tmp_path / "r.csv")]) == 0


@pytest.mark.parametrize("effect", ["gravity:g=1", "clearance:gap=1", "clearance:length=abc",
                                    "friction:lost1=-1"])
def test_cli_simulate_bad_effect_exit_2(tmp_path, capsys, effect):
    out = tmp_path / "m.csv"
    rc = main(["simulate", "--robot", "seed1", "--n", "5", "--effect", effect, "--out", str(out)])
    assert rc == 2 and not out.exists()
    err = capsys.readouterr().err
    assert "--effect" in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
