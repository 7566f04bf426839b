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
from ctrplan.shape.learned import LearnedModel, default_model_for

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
                 "--variant", "pure", *SMALL, "--out", str(out)]) == 0
    m = LearnedModel.load(out)
    assert m.meta["data"]["real"]["source"] == str(measured_csv)
    assert {"pretrain", "finetune"} <= set(m.meta["training"])
    assert "real_test" in m.meta["metrics"]
    assert m.meta["selection"]["mode"] == "explicit" and m.meta["variant"] == "pure"
    assert not out.with_suffix(".variants.json").exists()
    out2 = tmp_path / "real_only.pt"
    assert main(["-q", "train", "--robot", "seed1", "--sim", "0", "--real", str(measured_csv),
                 "--variant", "pure", *SMALL, "--out", str(out2)]) == 0
    assert "real" in LearnedModel.load(out2).meta["training"]


def test_train_fine_tunes_the_shipped_model(tmp_path, measured_csv):
    out = tmp_path / "init.pt"
    assert main(["-q", "train", "--robot", "seed1", "--init", "learned", "--real", str(measured_csv),
                 "--variant", "pure", "--fine-epochs", "2", "--out", str(out)]) == 0
    m = LearnedModel.load(out)
    shipped = default_model_for("seed1")                       # the shipped architecture
    assert (m.width, m.depth, m.terms, m.pair_inputs) == (shipped.width, shipped.depth,
                                                          shipped.terms, shipped.pair_inputs)
    assert "sim" not in m.meta["data"] and "finetune" in m.meta["training"]
    assert m.meta["data"]["init"]["sim"]["rows"] == shipped.meta["data"]["sim"]["rows"]
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
    # about 10 % of the 150 "real" rows are test rows (held out in blocks, the rows next to
    # them in no part), the same rows for physics and every learned model
    assert 10 <= res["physics"]["n"] <= 20
    assert all(r["n"] == res["physics"]["n"] for r in res["runs"])
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


@pytest.fixture(scope="module")
def sweeps_csv(tmp_path_factory):
    """Foreign-generator shapes (clearance + end-moment friction, back-and-forth sweeps):
    10 sweeps of 40 rows with backbone points, in order of motion."""
    from tests.foreign import generate

    r = load_robot("seed1")
    d = generate(robot="seed1", design="sweeps", n=400, effects={"clearance": {}, "friction": {}},
                 noise_mm=0.2, seed=5, points=20, sweeps=10)
    path = tmp_path_factory.mktemp("sweeps") / "sweeps.csv"
    write_measured(path, r, MeasuredData(q=np.asarray(d.q, float), tip=np.asarray(d.tip, float),
                                         sweep=np.asarray(d.sweep).astype(str).astype(object),
                                         points=np.asarray(d.points, float)))
    return path


def _rows_of(csv, sweeps):
    from ctrplan.measured import read_measured

    md = read_measured(csv, load_robot("seed1"))
    sw = np.asarray(md.sweep).astype(str)
    keep = np.isin(sw, list(sweeps))
    # directions from the row order, computed here independently of ctrplan
    q = md.q
    n = q.shape[1] // 2
    d = np.zeros(q.shape, dtype=float)
    for k in range(1, len(q)):
        if sw[k] != sw[k - 1]:
            continue
        step = q[k] - q[k - 1]
        step[:n] = (step[:n] + np.pi) % (2 * np.pi) - np.pi
        d[k] = np.where(np.abs(step) > 1e-9, np.sign(step), d[k - 1])
    return q[keep], md.points[keep], d[keep]


def test_train_without_variant_flags_chooses_by_validation_error(tmp_path, sweeps_csv):
    out = tmp_path / "auto.pt"
    assert main(["-q", "train", "--robot", "seed1", "--sim", "0", "--real", str(sweeps_csv),
                 "--width", "10", "--depth", "2", "--terms", "5", "--fine-epochs", "24",
                 "--out", str(out)]) == 0
    m = LearnedModel.load(out)
    sel = json.loads(out.with_suffix(".variants.json").read_text())
    assert m.meta["selection"] == sel and sel["mode"] == "auto"
    rows = {r["variant"]: r for r in sel["candidates"]}
    assert set(rows) == set(T.VARIANTS)                          # the rows show reversals
    val = {v: r["val_max_dev_mean_mm"] for v, r in rows.items()}
    assert sel["chosen"] == min(val, key=val.get) == m.meta["variant"]
    assert [v for v, r in rows.items() if r["chosen"]] == [sel["chosen"]]
    assert m.needs_direction == sel["chosen"].endswith("direction")
    assert sel["chosen"] in out.with_suffix(".variants.md").read_text()
    # validation and test sweeps: disjoint, and the final validation error recomputed here
    vs, ts = set(sel["validation"]["sweeps"]), set(sel["test"]["sweeps"])
    assert vs and ts and not vs & ts
    q, pts, d = _rows_of(sweeps_csv, vs)
    pred = m.shape(q, 20, direction=d).points if m.needs_direction else m.backbone(q, 20)
    dev = np.sqrt(((pred - pts) ** 2).sum(axis=2))
    assert dev.max(axis=1).mean() == pytest.approx(sel["final_val_max_dev_mean_mm"], rel=1e-4)
    assert sel["final_val_max_dev_mean_mm"] <= val[sel["chosen"]] + 1e-9
    # error quantiles and the error profile on the test sweeps, recomputed with numpy
    assert set(m.meta["error_profile_source"]["sweeps"]) == ts
    q, pts, d = _rows_of(sweeps_csv, ts)
    pred = m.shape(q, 20, direction=d).points if m.needs_direction else m.backbone(q, 20)
    dev = np.sqrt(((pred - pts) ** 2).sum(axis=2))
    prof = m.error_profile
    np.testing.assert_allclose(prof["fractions"], np.arange(20) / 19)
    for k, p in (("p50", 50), ("p95", 95), ("p99", 99), ("max", 100)):
        np.testing.assert_allclose(prof[k], np.percentile(dev, p, axis=0), rtol=1e-4, atol=1e-5)
        assert m.error_quantiles[k] == pytest.approx(np.percentile(dev.max(axis=1), p), rel=1e-4)
    assert prof["p99"][0] < prof["p99"][-1]                      # the base barely moves


def test_explicit_variant_flag_overrides_and_conflicts_exit_2(tmp_path, sweeps_csv, capsys):
    out = tmp_path / "res.pt"
    assert main(["-q", "train", "--robot", "seed1", "--real", str(sweeps_csv), "--variant", "residual",
                 *SMALL, "--out", str(out)]) == 0
    m = LearnedModel.load(out)
    from ctrplan.shape.physics import PhysicsModel

    assert isinstance(m.base, PhysicsModel) and not m.needs_direction
    assert m.meta["selection"]["mode"] == "explicit" and m.meta["variant"] == "residual"
    assert "sim" not in m.meta["data"]                            # residual over physics: no pre-training
    for extra, needle in ((["--variant", "pure", "--direction"], "--direction"),
                          (["--variant", "direction", "--residual", "physics"], "--residual")):
        assert main(["-q", "train", "--robot", "seed1", "--real", str(sweeps_csv), *extra,
                     "--out", str(tmp_path / "x.pt")]) == 2
        assert needle in capsys.readouterr().err
