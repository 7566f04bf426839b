"""``ctrplan check`` and ``ctrplan scene`` on the command line."""

from __future__ import annotations

import csv

import numpy as np
import pytest

from ctrplan.cli import main
from ctrplan.collision.build_scenes import sample_reach
from ctrplan.collision.scene import load_scene
from ctrplan.collision.world import CollisionWorld
from ctrplan.robot import write_configs
from ctrplan.shape.physics import PhysicsModel


@pytest.fixture(scope="module")
def configs(tmp_path_factory, seed1):
    scene = load_scene("skull_base")
    q = np.vstack([sample_reach(seed1, 40, 140.0, seed=3), [t.config for t in scene.targets[:3]]])
    path = tmp_path_factory.mktemp("cfg") / "c.csv"
    write_configs(path, seed1, q)
    return path, q


def _read(path):
    with open(path) as fh:
        return list(csv.DictReader(fh))


def test_check_writes_verdicts(tmp_path, configs, seed1):
    path, q = configs
    out = tmp_path / "v.csv"
    assert main(["-q", "check", "--scene", "skull_base", "--robot", "seed1", "--configs", str(path),
                 "--out", str(out)]) == 0
    rows = _read(out)
    assert list(rows[0]) == ["collides", "clearance_mm", "contact"] and len(rows) == len(q)
    # physics: margin auto = 0; capsules padded by the sagitta bound of seed1's largest curvature
    expect = CollisionWorld("skull_base", curvature_per_mm=0.0093354).check_exact(
        PhysicsModel(seed1).shape(q, points=21))
    got = np.array([int(r["collides"]) for r in rows], dtype=bool)
    np.testing.assert_array_equal(got, expect.collides)
    assert not got[-3:].any()                     # the targets' configurations are free
    assert all((r["contact"] != "") == (r["collides"] == "1") for r in rows)
    clear = np.array([float(r["clearance_mm"]) for r in rows])
    assert np.all(clear[got] <= 0) and np.all(clear[~got] >= 0)
    out2 = tmp_path / "v2.csv"
    assert main(["-q", "check", "--scene", "skull_base", "--robot", "seed1", "--configs", str(path),
                 "--exact", "--margin", "0.5", "--model", "rigid", "--out", str(out2)]) == 0
    assert len(_read(out2)) == len(q)


@pytest.mark.parametrize("args,match", [
    (["--scene", "nowhere"], "not a shipped scene"),
    (["--out", "v.txt"], "must end in"),
    (["--margin", "-1"], "--margin"),
])
def test_check_bad_input_exits_2(tmp_path, configs, capsys, args, match):
    path, _ = configs
    base = {"--scene": "airway", "--robot": "seed1", "--configs": str(path), "--out": str(tmp_path / "v.csv")}
    for k, v in zip(args[::2], args[1::2]):
        base[k] = v if k != "--out" else str(tmp_path / v)
    argv = ["check"] + [x for kv in base.items() for x in kv]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert match in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "v.csv").exists()


def test_scene_list_and_show(tmp_path, configs, capsys):
    assert main(["scene", "list"]) == 0
    out = capsys.readouterr().out
    for name in ("airway", "neuro", "skull_base", "bronchial_tree"):
        assert name in out
    png = tmp_path / "s.png"
    assert main(["-q", "scene", "show", "airway", "--out", str(png)]) == 0
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    html = tmp_path / "s.html"
    path, _ = configs
    assert main(["-q", "scene", "show", "skull_base", "--configs", str(path), "--out", str(html)]) == 0
    text = html.read_text()
    assert "plotly" in text.lower() and "<script src=\"http" not in text
    assert main(["scene", "show", "airway", "--out", str(tmp_path / "s.gif")]) == 2


def test_check_counts_configurations_beyond_the_measured_insertions(tmp_path, configs, seed1,
                                                                     capsys):
    """With a calibrated model that records its measured insertions, check warns how many
    configurations insert a tube beyond them (oracle: a count here)."""
    from ctrplan.shape.effects import EffectModel

    path, q = configs
    b = q[:, seed1.n:]
    rng = {"min": np.median(b, axis=0).tolist(), "max": b.max(axis=0).tolist()}
    eq = {"p50": 0.05, "p95": 0.1, "p99": 0.1, "max": 0.15}
    model = tmp_path / "calibrated.yaml"
    EffectModel(seed1, "rigid", {}, error_quantiles=eq, measured_insertion=rng).save(model)
    expect = int(np.sum(np.any(b < np.asarray(rng["min"]) - 1.0, axis=1)))
    assert 0 < expect < len(q)
    capsys.readouterr()
    assert main(["-q", "check", "--scene", "skull_base", "--robot", "seed1", "--configs", str(path),
                 "--model", str(model), "--out", str(tmp_path / "v.csv")]) == 0
    err = capsys.readouterr().err
    assert f"{expect} of {len(q)} configurations insert a tube beyond" in err, err
    # physics carries no measured insertions: no count
    assert main(["-q", "check", "--scene", "skull_base", "--robot", "seed1", "--configs", str(path),
                 "--out", str(tmp_path / "w.csv")]) == 0
    assert "beyond" not in capsys.readouterr().err
