"""``ctrplan diagnose --best``: the best model of the robot from its measurements.

Data from the independent generator (tests/foreign, no ctrplan code): seed1 shapes with a
precurvature error (inside the fitted family) and clearance at the outer tubes' ends, which
the diagnosis is not allowed to fit (``--effects precurvature``): an effect outside the fitted
families, which only a learned residual can take up. The winner and every candidate's test
error are recomputed here from the written model files (loaded as ``--model`` loads them) and
the CSV rows the comparison says it held out, with numpy - not read from the table.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch

from ctrplan.cli import main
from ctrplan.shape.models import load_model

torch.set_num_threads(1)


def _crossfit(devs, folds):
    """Independent recomputation of the winner's cross-fitted deviations: the rows of fold f
    take the deviations of the candidate with the lowest mean on the other fold (ties: the
    simpler, in the table's order)."""
    order = ["nominal", "calibrated", "calibrated+learned", "learned"]
    out = np.full_like(next(iter(devs.values())), np.nan)
    for f in (0, 1):
        other = folds != f
        pick = min(devs, key=lambda k: (devs[k][other].max(axis=1).mean(), order.index(k)))
        out[folds == f] = devs[pick][folds == f]
    return out


def _alternating_folds(units):
    """Fold of each test row: its unit's place among the test units (first seen first),
    alternating; one unit: its two halves."""
    names = list(dict.fromkeys(units))
    if len(names) < 2:
        return (np.arange(len(units)) >= len(units) // 2).astype(int)
    return np.array([names.index(u) % 2 for u in units])


def _deviations(model, q, direction, points):
    """(B, m) distances between a loaded model's backbone points and measured points."""
    m = points.shape[1]
    if getattr(model, "needs_direction", False):
        pred = model.shape(q, m, direction=direction).points
    else:
        pred = model.backbone(q, m)
    return np.sqrt(((pred - points) ** 2).sum(axis=2))


@pytest.fixture(scope="module")
def best_run(tmp_path_factory):
    from tests.foreign import generate

    d = generate(robot="seed1", design="uniform", n=500, effects={"clearance": {}, "precurvature": {}},
                 noise_mm=0.2, seed=3, points=20)
    tmp = tmp_path_factory.mktemp("best")
    csv = tmp / "measured.csv"
    d.write_csv(csv)
    out = tmp / "out"
    rc = main(["-q", "diagnose", "--robot", "seed1", "--data", str(csv), "--effects", "precurvature",
               "--best", "--out", str(out)])
    return rc, d, out


def test_best_model_is_the_candidate_with_the_lowest_recomputed_test_error(best_run, capsys):
    rc, d, out = best_run
    assert rc == 0
    table = json.loads((out / "best_model.json").read_text())
    test = np.asarray(table["split"]["test_row_indices"])
    assert 0.1 * len(d) <= len(test) <= 0.3 * len(d) and len(set(test.tolist())) == len(test)
    # the diagnosis fitted and chose on the other rows of the same split
    rep = json.loads((out / "report.json").read_text())
    assert rep["settings"]["rows"] == len(d) and rep["settings"]["test_rows"] == len(test)
    rep_test = np.concatenate([np.arange(int(a) - 1, int(b)) for a, b in
                               (r.split()[1].split("-") for r in rep["split"]["test_row_ranges"])])
    np.testing.assert_array_equal(np.sort(rep_test), np.sort(test))
    q, pts, dirs = d.q[test], np.asarray(d.points)[test], np.asarray(d.direction)[test]
    means, devs = {}, {}
    models = {}
    for name, rel in table["files"].items():
        if name == "best_model":
            continue
        models[name] = load_model(str(out / rel), "seed1")
        devs[name] = _deviations(models[name], q, dirs, pts)
        means[name] = devs[name].max(axis=1).mean()
        assert table["candidates"][name]["mean_mm"] == pytest.approx(means[name], rel=1e-6)
    assert set(means) == {"nominal", "calibrated", "calibrated+learned", "learned"}
    winner = min(means, key=means.get)
    assert table["winner"] == winner
    for name, model in models.items():          # each candidate file carries its own quantiles
        if name != winner:
            for k, p in (("p50", 50), ("p99", 99), ("max", 100)):
                assert model.error_quantiles[k] == pytest.approx(
                    np.percentile(devs[name].max(axis=1), p), rel=1e-6)
    # the written best model is the winner, with its error bound cross-fitted over two folds of
    # the test units (independent rows here: alternate test rows), each fold's deviations
    # those of the candidate the other fold chooses
    folds = _alternating_folds([f"row{i}" for i in test])
    assert table["split"]["crossfit"]["folds"] == [test[folds == f].tolist() for f in (0, 1)]
    best = load_model(str(out / table["files"]["best_model"]), "seed1")
    # every bound here was measured on the robot's test rows: calibrated, learned ones too
    from ctrplan.shape.error_bounds import is_calibrated

    assert is_calibrated(best) and all(is_calibrated(load_model(str(out / rel), "seed1"))
                                       for rel in table["files"].values())
    dev = _deviations(best, q, dirs, pts)
    np.testing.assert_allclose(dev, devs[winner], atol=1e-6)
    cf = _crossfit(devs, folds)
    mx = cf.max(axis=1)
    prof = best.error_profile
    np.testing.assert_allclose(prof["fractions"], np.linspace(0, 1, 20))
    for k, p in (("p50", 50), ("p95", 95), ("p99", 99), ("max", 100)):
        assert best.error_quantiles[k] == pytest.approx(np.percentile(mx, p), rel=1e-6)
        np.testing.assert_allclose(prof[k], np.percentile(cf, p, axis=0), rtol=1e-6, atol=1e-9)
    assert (out / "best_model.md").read_text().startswith(f"# Best model: {winner}")


def test_a_learned_residual_takes_up_an_effect_outside_the_fitted_families(best_run):
    """Clearance is outside the fitted family (only precurvature may be fitted): a learned
    candidate must win - the learned residual over the calibrated model, or the shipped network
    fine-tuned alone - and both must cut the calibrated model's test error by at least a
    quarter (measured: nominal 3.77, calibrated 2.17, calibrated + learned 1.07, learned alone
    1.50 mm; with branch gen's rewritten generator forms 4.16, 1.89, 1.13, 1.58; with issue 38's
    shipped network (4 x 64 over the rigid model) 4.15, 1.90, 1.11, 1.02: fine-tuned alone it
    now wins)."""
    rc, d, out = best_run
    table = json.loads((out / "best_model.json").read_text())
    c = table["candidates"]
    assert table["winner"] in ("calibrated+learned", "learned"), {k: v["mean_mm"] for k, v in c.items()}
    for name in ("calibrated+learned", "learned"):
        assert c[name]["mean_mm"] <= 0.75 * c["calibrated"]["mean_mm"], (name, c[name]["mean_mm"])
    assert c["calibrated"]["mean_mm"] < c["nominal"]["mean_mm"]      # precurvature was fitted
    model = load_model(str(out / table["files"]["calibrated+learned"]), "seed1")
    assert model.base_spec["kind"] == "effect" and "precurvature" in model.base.effects


def test_best_with_tip_only_data_extends_the_tip_bound(tmp_path):
    from ctrplan.calibration.best import best_model
    from ctrplan.measured import MeasuredData
    from tests.foreign import generate

    d = generate(robot="seed1", design="sweeps", n=240, effects={"clearance": {}}, noise_mm=0.2,
                 seed=4, sweeps=8)
    md = MeasuredData(q=np.asarray(d.q, float), tip=np.asarray(d.tip, float),
                      sweep=np.asarray(d.sweep).astype(str).astype(object))
    res = best_model("seed1", md, out=tmp_path, diagnose_kwargs={"candidates": ["precurvature"]},
                     epochs=30, width=10, depth=2)
    table = json.loads((tmp_path / "best_model.json").read_text())
    assert set(table["candidates"]) == {"nominal", "calibrated", "calibrated+learned"}
    assert all("error_profile" not in v for v in table["candidates"].values())
    best = load_model(str(tmp_path / table["files"]["best_model"]), "seed1")
    # no measured profile: the tip bound extended along the shaft (bound x arc-length fraction)
    prof = best.error_profile
    eq = best.error_quantiles
    assert prof["fractions"][0] == 0.0 and prof["fractions"][-1] == 1.0
    for k in ("p50", "p95", "p99", "max"):
        np.testing.assert_allclose(prof[k], np.asarray(prof["fractions"]) * eq[k], rtol=1e-9)
    test = np.asarray(table["split"]["test_row_indices"])
    assert set(np.asarray(d.sweep)[test]) == set(table["split"]["test_sweeps"])
    # tip deviations recomputed with the generator's own directions of motion (rows in order)
    target = np.stack([np.zeros((len(test), 3)), md.tip[test]], axis=1)
    dev = _deviations(best, md.q[test], np.asarray(d.direction)[test], target)
    assert np.all(dev[:, 0] < 1e-9)                                # the base point stays put
    assert table["candidates"][res.winner]["mean_mm"] == pytest.approx(dev[:, 1].mean(), rel=1e-6)
    # the bound: cross-fitted over the two test sweeps (each from the other's choice)
    devs = {}
    for name, rel in table["files"].items():
        if name != "best_model":
            devs[name] = _deviations(load_model(str(tmp_path / rel), "seed1"), md.q[test],
                                     np.asarray(d.direction)[test], target)
    folds = _alternating_folds(np.asarray(d.sweep)[test].tolist())
    assert best.error_quantiles["max"] == pytest.approx(_crossfit(devs, folds)[:, 1].max(), rel=1e-6)


def test_registration_is_inverted_into_the_robot_frame():
    from scipy.spatial.transform import Rotation

    from ctrplan.calibration.best import to_robot_frame

    rng = np.random.default_rng(0)
    p = rng.normal(0, 50, (7, 5, 3))
    rv, t = np.array([0.1, -0.2, 0.05]), np.array([3.0, -1.0, 2.0])
    sensor = Rotation.from_rotvec(rv).apply(p.reshape(-1, 3)).reshape(p.shape) + t
    eff = {"registration": {"tx": t[0], "ty": t[1], "tz": t[2], "rx": rv[0], "ry": rv[1], "rz": rv[2]}}
    np.testing.assert_allclose(to_robot_frame(eff, sensor), p, atol=1e-9)
    np.testing.assert_array_equal(to_robot_frame({}, sensor), sensor)


def test_test_split_holds_out_whole_sweeps_or_contiguous_blocks():
    from ctrplan.calibration.best import holdout_split
    from ctrplan.measured import MeasuredData

    N = 200
    q = np.zeros((N, 6))
    q[:, 3] = np.arange(N) * 0.01
    many = MeasuredData(q=q, tip=np.zeros((N, 3)), sweep=np.repeat([f"s{k}" for k in range(10)], 20).astype(object))
    test, lab, desc = holdout_split(many, 0.2, seed=1)
    held = set(desc["test_sweeps"])
    assert len(held) == 2 and set(np.asarray(many.sweep)[test]) == held
    assert not held & set(np.asarray(many.sweep)[~test])
    one = MeasuredData(q=q, tip=np.zeros((N, 3)))                  # one continuous trajectory
    test, lab, desc = holdout_split(one, 0.2, seed=1)
    assert 0.15 * N <= test.sum() <= 0.25 * N
    starts = np.flatnonzero(np.diff(test.astype(int)) == 1)        # contiguous blocks, not rows
    assert len(starts) <= 2
    dev_labels = set(lab[~test].tolist())
    assert len(dev_labels) >= 3 and not dev_labels & set(lab[test].tolist())
    for name in dev_labels:                                        # each dev label is contiguous
        idx = np.flatnonzero(lab == name)
        assert np.all(np.diff(idx) == 1)


@pytest.mark.parametrize("flag", ["--holdout", "--test-fraction"])
@pytest.mark.parametrize("frac", ["0", "1.5"])
def test_bad_holdout_exits_2_without_output(tmp_path, capsys, frac, flag):
    from tests.foreign import generate

    d = generate(robot="seed1", design="uniform", n=30, effects={}, noise_mm=0.2, seed=1)
    d.write_csv(tmp_path / "m.csv")
    out = tmp_path / "out"
    assert main(["-q", "diagnose", "--robot", "seed1", "--data", str(tmp_path / "m.csv"), "--best",
                 flag, frac, "--out", str(out)]) == 2
    assert flag in capsys.readouterr().err and not out.exists()


def test_test_fraction_is_a_deprecated_alias_of_holdout():
    import argparse

    from ctrplan.commands import diagnose as cmd

    p = argparse.ArgumentParser()
    cmd.register(p.add_subparsers())
    import contextlib
    import io

    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        args = p.parse_args(["diagnose", "--robot", "seed1", "--data", "x.csv",
                             "--test-fraction", "0.3"])
    assert args.holdout == 0.3
    assert err.getvalue().strip() == "ctrplan: --test-fraction is deprecated; use --holdout"


def test_error_profile_round_trips_through_the_calibrated_yaml_and_bad_ones_are_refused(tmp_path):
    from ctrplan.errors import InputError
    from ctrplan.shape.effects import EffectModel

    prof = {"fractions": [0.0, 0.5, 1.0], "p50": [0.1, 0.5, 1.0], "p95": [0.2, 0.9, 2.0],
            "p99": [0.3, 1.1, 2.5], "max": [0.4, 1.5, 3.0]}
    m = EffectModel("seed1", "rigid", {"precurvature": {"scale1": 1.05}},
                    error_quantiles={"p50": 1.0, "p95": 2.0, "p99": 2.5, "max": 3.0}, error_profile=prof)
    m.save(tmp_path / "c.yaml")
    back = load_model(str(tmp_path / "c.yaml"), "seed1")
    assert back.error_profile == prof and back.planning_model().error_profile == prof
    import yaml

    doc = yaml.safe_load((tmp_path / "c.yaml").read_text())
    for key, value in (("fractions", [0.0, 1.5, 1.0]), ("p99", [0.3, float("nan"), 2.5]),
                       ("max", [0.4, 1.5]), ("p96", [0.2, 0.9, 2.0])):
        bad = {**doc, "error_profile": {**prof, key: value}}
        (tmp_path / "bad.yaml").write_text(yaml.safe_dump(bad))
        with pytest.raises(InputError, match="error_profile"):
            load_model(str(tmp_path / "bad.yaml"), "seed1")


def test_winner_rule_lowest_mean_fewest_failures_simplest_on_ties():
    from ctrplan.calibration.best import choose_winner

    def t(**rows):
        return {k.replace("_", "+"): {"mean_mm": m, "failed_rows": f} for k, (m, f) in rows.items()}

    assert choose_winner(t(nominal=(3.0, 0), calibrated=(2.0, 0), calibrated_learned=(1.0, 0))) == "calibrated+learned"
    assert choose_winner(t(nominal=(3.0, 0), calibrated=(2.0, 0), calibrated_learned=(1.0, 4))) == "calibrated"
    assert choose_winner(t(nominal=(2.0, 0), calibrated=(2.0, 0), learned=(2.5, 0))) == "nominal"
