"""``ctrplan train``: model files, fine-tuning on a measured CSV, the sweep, and bad input."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from ctrplan.cli import main
from ctrplan.measured import MeasuredData, write_measured
from ctrplan.robot import load_robot
from ctrplan.shape import training as T
from ctrplan.shape.learned import LearnedModel

torch.set_num_threads(1)
SMALL = ["--width", "8", "--depth", "2", "--terms", "4", "--epochs", "3", "--fine-epochs", "3",
         "--workers", "1"]


@pytest.fixture(scope="module")
def measured_csv(tmp_path_factory):
    r = load_robot("seed1")
    data = T.real_data(r, 120, seed=4)
    path = tmp_path_factory.mktemp("meas") / "measured.csv"
    write_measured(path, r, MeasuredData(q=data.q, tip=data.points[:, -1], points=data.points))
    return path


def test_train_writes_a_loadable_model_with_metadata(tmp_path):
    out = tmp_path / "m.pt"
    assert main(["-q", "train", "--robot", "seed1", "--sim", "300", *SMALL, "--out", str(out)]) == 0
    m = LearnedModel.load(out, robot="seed1")
    assert (m.width, m.depth, m.terms) == (8, 2, 4)
    assert m.meta["data"]["sim"]["rows"] == 300
    assert len(m.meta["data"]["sim"]["sha256_16"]) == 16
    assert m.meta["metrics"]["sim_test"]["n"] == 30
    assert "pretrain" in m.meta["training"]
    assert m.backbone(m.robot.sample(3, seed=0)).shape == (3, 20, 3)


def test_train_fine_tunes_on_measured_csv(tmp_path, measured_csv):
    out = tmp_path / "ft.pt"
    assert main(["-q", "train", "--robot", "seed1", "--sim", "200", "--real", str(measured_csv),
                 *SMALL, "--out", str(out)]) == 0
    m = LearnedModel.load(out)
    assert m.meta["data"]["real"]["source"] == str(measured_csv)
    assert {"pretrain", "finetune"} <= set(m.meta["training"])
    assert "real_test" in m.meta["metrics"]
    out2 = tmp_path / "real_only.pt"
    assert main(["-q", "train", "--robot", "seed1", "--sim", "0", "--real", str(measured_csv),
                 *SMALL, "--out", str(out2)]) == 0
    assert "real" in LearnedModel.load(out2).meta["training"]


def test_train_fine_tunes_the_shipped_model(tmp_path, measured_csv):
    out = tmp_path / "init.pt"
    assert main(["-q", "train", "--robot", "seed1", "--init", "learned", "--real", str(measured_csv),
                 "--fine-epochs", "2", "--out", str(out)]) == 0
    m = LearnedModel.load(out)
    assert (m.width, m.depth, m.terms) == (30, 3, 7)          # the shipped architecture
    assert "sim" not in m.meta["data"] and "finetune" in m.meta["training"]
    assert m.meta["data"]["init"]["sim"]["rows"] == 100_000
    assert main(["-q", "train", "--robot", "seed1", "--init", str(tmp_path / "nope.pt"),
                 "--real", str(measured_csv), "--out", str(out)]) == 2


def test_quick_sweep_writes_tables_and_plots(tmp_path):
    out = tmp_path / "sweep"
    assert main(["-q", "train", "--robot", "seed1", "--sweep", "--sim", "300", "--real-sim", "150",
                 "--archs", "2x8,3x8", *SMALL, "--out", str(out)]) == 0
    res = json.loads((out / "results.json").read_text())
    regimes = {(r["regime"], r["variant"], r["arch"]) for r in res["runs"]}
    assert regimes == {(g, v, a) for g in T.REGIMES for v in T.VARIANTS for a in ("2x8", "3x8")
                       if g != "Sim-only" or v == "pure"}
    for r in res["runs"]:
        assert len(r["per_position"]) == 20 and len(r["per_config_max"]) == r["n"]
        assert r["max_dev_mean"] > 0 and r["mse_mean"] > 0 and r["sum_dev_mean"] > 0
    assert res["physics"]["n"] == 15
    assert "hidden_effects" in res["data"]
    md = (out / "results.md").read_text()
    assert "Sim+Real" in md and "physics" in md and "±" in md
    for png in ("hist_max_error.png", "error_vs_position.png"):
        assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


@pytest.mark.parametrize("args, needle", [
    (["--sim", "50", "--out", "m.txt"], "--out"),
    (["--sim", "0", "--out", "m.pt"], "nothing to train on"),
    (["--sim", "5", "--out", "m.pt"], "at least 10"),
    (["--width", "0", "--out", "m.pt"], "--width"),
    (["--terms", "40", "--out", "m.pt"], "--terms"),
    (["--lr", "-1", "--out", "m.pt"], "--lr"),
    (["--sweep", "--archs", "3by30", "--out", "d"], "--archs"),
    (["--real", "missing.csv", "--sim", "0", "--out", "m.pt"], "missing.csv"),
])
def test_bad_arguments_exit_2(tmp_path, monkeypatch, capsys, args, needle):
    monkeypatch.chdir(tmp_path)
    assert main(["-q", "train", "--robot", "seed1", *args]) == 2
    assert needle in capsys.readouterr().err


def test_measured_csv_without_points_is_rejected(tmp_path, capsys):
    r = load_robot("seed1")
    q = r.sample(10, seed=0)
    path = tmp_path / "tips.csv"
    write_measured(path, r, MeasuredData(q=q, tip=np.zeros((10, 3))))
    assert main(["-q", "train", "--robot", "seed1", "--sim", "0", "--real", str(path),
                 "--out", str(tmp_path / "m.pt")]) == 2
    assert "p1_x" in capsys.readouterr().err


def test_train_direction_and_residual_variants(tmp_path, measured_csv):
    from ctrplan.shape.physics import PhysicsModel

    out = tmp_path / "rd.pt"
    assert main(["-q", "train", "--robot", "seed1", "--sim", "0", "--real", str(measured_csv),
                 "--direction", "--residual", "physics", "--refit", *SMALL, "--out", str(out)]) == 0
    m = LearnedModel.load(out)
    assert m.needs_direction and isinstance(m.base, PhysicsModel)
    assert m.meta["variant"] == "residual+direction"
    eq = m.error_quantiles
    assert eq is not None and 0 < eq["p50"] <= eq["p95"] <= eq["p99"] <= eq["max"]
    assert m.domain is not None
    out2 = tmp_path / "rs.pt"
    assert main(["-q", "train", "--robot", "seed1", "--sim", "200", "--real", str(measured_csv),
                 "--residual", "sim", *SMALL, "--out", str(out2)]) == 0
    m2 = LearnedModel.load(out2)
    assert m2.base_spec["kind"] == "learned" and not m2.needs_direction
    q = m2.robot.sample(5, seed=1)
    assert np.all(np.isfinite(m2.backbone(q)))


@pytest.mark.parametrize("args, needle", [
    (["--sim", "0", "--residual", "sim"], "--residual"),
    (["--sim", "0", "--residual", "nonexistent.pt"], "nonexistent.pt"),
])
def test_bad_variant_arguments_exit_2(tmp_path, measured_csv, capsys, args, needle):
    assert main(["-q", "train", "--robot", "seed1", "--real", str(measured_csv), *args,
                 "--out", str(tmp_path / "m.pt")]) == 2
    assert needle in capsys.readouterr().err


def test_direction_without_measured_data_exits_2(tmp_path, capsys):
    assert main(["-q", "train", "--robot", "seed1", "--sim", "50", "--direction",
                 "--out", str(tmp_path / "m.pt")]) == 2
    assert "--real" in capsys.readouterr().err
