"""``ctrplan shape``: outputs match the Python API."""

from __future__ import annotations

import csv
import subprocess
import sys

import numpy as np
import pytest

from ctrplan import cli
from ctrplan.robot import write_configs
from ctrplan.shape.physics import PhysicsModel


@pytest.fixture
def configs(tmp_path, seed1):
    q = seed1.sample(9, seed=4)
    p = tmp_path / "configs.csv"
    write_configs(p, seed1, q)
    return p, q


@pytest.mark.parametrize("model,torsion", [("physics", True), ("rigid", False)])
def test_npz_matches_the_api(tmp_path, seed1, configs, model, torsion):
    path, q = configs
    out = tmp_path / "shapes.npz"
    rc = cli.main(["-q", "shape", "--robot", "seed1", "--configs", str(path), "--model", model,
                   "--points", "13", "--out", str(out)])
    assert rc == 0
    with np.load(out) as z:
        expect = PhysicsModel(seed1, torsion=torsion).shape(q, points=13)
        assert z["points"].shape == (9, 13, 3)
        np.testing.assert_array_equal(z["points"], expect.points)
        np.testing.assert_array_equal(z["s"], expect.s)
        np.testing.assert_array_equal(z["ok"], expect.ok)
        assert z["ok"].dtype == bool


def test_csv_matches_the_api(tmp_path, seed1, configs):
    path, q = configs
    out = tmp_path / "shapes.csv"
    assert cli.main(["-q", "shape", "--robot", "seed1", "--configs", str(path), "--points", "5",
                     "--out", str(out)]) == 0
    with open(out, newline="") as fh:
        rows = list(csv.reader(fh))
    header, body = rows[0], rows[1:]
    assert header[0] == "ok" and header[1:4] == ["p1_x", "p1_y", "p1_z"] and header[-1] == "p5_z"
    assert len(body) == 9
    got = np.array([[float(v) for v in r[1:]] for r in body]).reshape(9, 5, 3)
    expect = PhysicsModel(seed1).shape(q, points=5)
    np.testing.assert_array_equal(got, expect.points)       # repr() round-trips floats exactly
    np.testing.assert_array_equal([int(r[0]) for r in body], expect.ok.astype(int))


def test_robot_yaml_path_and_help(tmp_path, seed1, configs):
    path, q = configs
    rp = tmp_path / "mine.yaml"
    seed1.save(rp)
    out = tmp_path / "o.npz"
    assert cli.main(["-q", "shape", "--robot", str(rp), "--configs", str(path), "--out", str(out)]) == 0
    with np.load(out) as z:
        np.testing.assert_array_equal(z["points"], PhysicsModel(seed1).backbone(q))
    proc = subprocess.run([sys.executable, "-m", "ctrplan.cli", "shape", "--help"],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0
    for flag in ("--robot", "--configs", "--model", "--points", "--out"):
        assert flag in proc.stdout
