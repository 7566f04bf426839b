"""Error bounds along the shaft: profiles from held-out backbones, the tip-to-shaft extension
rule checked on the foreign generator, margins per capsule, model metadata."""

from __future__ import annotations

import numpy as np
import pytest

from ctrplan.collision.capsules import capsules_from_points
from ctrplan.shape.effects import EffectModel
from ctrplan.shape.error_bounds import (
    auto_margin,
    error_bound_kind,
    extend_tip_bound,
    is_calibrated,
    profile_from_backbones,
    profile_from_dict,
)
from ctrplan.shape.physics import PhysicsModel


def test_profile_quantiles_per_point_against_numpy():
    rng = np.random.default_rng(0)
    meas = rng.normal(size=(400, 5, 3)) * 10
    # deviation of point j: a random direction scaled by j (known distribution per point)
    d = rng.normal(size=(400, 5, 3))
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    mag = rng.uniform(0, 1, (400, 5)) * np.arange(5)
    prof = profile_from_backbones(meas + d * mag[..., None], meas)
    np.testing.assert_allclose(prof.fractions, [0, 0.25, 0.5, 0.75, 1.0])
    for k, qn in (("p50", 50), ("p99", 99), ("max", 100)):
        np.testing.assert_allclose(prof.values[k], [np.percentile(mag[:, j], qn) for j in range(5)])
    # uniform deviations on [0, j]: p99 ~ 0.99 j
    np.testing.assert_allclose(prof.values["p99"], 0.99 * np.arange(5), atol=0.05)


def test_capsule_margins_follow_the_profile():
    prof = profile_from_dict({"fractions": [0.0, 0.5, 1.0], "p50": [0, 0, 0], "p95": [0, 0, 0],
                              "p99": [0.0, 1.0, 3.0], "max": [0, 1, 3]})
    pts = np.zeros((1, 5, 3))
    pts[0, :, 2] = [0, 25, 50, 75, 100]
    s = pts[..., 2]
    caps = capsules_from_points(pts, np.ones((1, 5)), prof, s=s)
    # largest p99 over [0, .25], [.25, .5], [.5, .75], [.75, 1]
    np.testing.assert_allclose(caps.radius[0], 1.0 + np.array([0.5, 1.0, 2.0, 3.0]))
    # a knot inside a capsule's interval counts
    pts3 = pts[:, [0, 2, 4]]
    caps3 = capsules_from_points(pts3, np.ones((1, 3)), prof, s=s[:, [0, 2, 4]])
    np.testing.assert_allclose(caps3.radius[0], 1.0 + np.array([1.0, 3.0]))
    with pytest.raises(ValueError):
        profile_from_dict({"fractions": [0.5, 0.2], "p50": [0, 0], "p95": [0, 0], "p99": [0, 0],
                           "max": [0, 0]})


def test_largest_margin_over_an_interval_against_dense_sampling():
    """ErrorProfile.over (range-maximum table of the knots) against brute force: the
    piecewise-linear profile sampled at 4,001 points of each interval (a lower bound of the
    true maximum, short of it by at most the largest slope x the sampling step)."""
    rng = np.random.default_rng(38)
    fr = np.r_[0.0, np.sort(rng.uniform(0.0, 1.0, 18)), 1.0]
    v = rng.uniform(0.0, 2.0, len(fr))
    prof = profile_from_dict({"fractions": fr, "p50": v / 4, "p95": v / 2, "p99": v, "max": 2 * v})
    slope = np.max(np.abs(np.diff(v)) / np.maximum(np.diff(fr), 1e-12))
    a = rng.uniform(-0.1, 1.1, 400)
    b = np.where(rng.random(400) < 0.3, a + rng.uniform(0, 0.05, 400), rng.uniform(-0.1, 1.1, 400))
    a[:40] = fr[rng.integers(0, len(fr), 40)]                 # ends on knots
    got = prof.over(a, b)
    for i in range(len(a)):
        lo, hi = sorted((a[i], b[i]))
        grid = np.linspace(lo, hi, 4001)
        dense = np.interp(np.clip(grid, 0, 1), fr, v).max()
        assert dense - 1e-12 <= got[i] <= dense + slope * (hi - lo) / 4000 + 1e-12


def test_models_read_their_bound_and_report_calibration(seed1, tmp_path):
    phys = PhysicsModel(seed1)
    assert not is_calibrated(phys) and auto_margin(phys) == 0.0
    eq = {"p50": 0.5, "p95": 1.0, "p99": 1.5, "max": 2.0}
    m = EffectModel(seed1, "compliant", {}, error_quantiles=eq)
    assert is_calibrated(m) and auto_margin(m) == 1.5          # uniform p99 fallback
    prof = extend_tip_bound(eq)
    m2 = EffectModel(seed1, "compliant", {}, error_quantiles=eq, error_profile=prof.to_dict())
    m2.save(tmp_path / "cal.yaml")
    back = EffectModel.load(tmp_path / "cal.yaml")
    got = auto_margin(back.planning_model())
    np.testing.assert_allclose(got.at([0.0, 0.5, 1.0]), [0.0, 0.75, 1.5])
    assert is_calibrated(back)


def test_learned_model_keeps_its_profile(seed1, tmp_path):
    from ctrplan.shape.learned import LearnedModel

    m = LearnedModel(seed1, width=4, depth=1)
    assert not is_calibrated(m)
    rng = np.random.default_rng(1)
    meas = rng.normal(size=(50, 6, 3))
    m.set_error_profile(meas + 0.1 * np.linspace(0, 1, 6)[None, :, None], meas)
    # a bound whose origin the model does not state is a surrogate's, never "calibrated"
    assert not is_calibrated(m) and error_bound_kind(m) == "surrogate"
    m.error_bound = "measured"            # rows measured on a robot: calibrated
    m.save(tmp_path / "m.pt")
    back = LearnedModel.load(tmp_path / "m.pt")
    np.testing.assert_allclose(auto_margin(back).at(1.0), 0.1 * np.sqrt(3), rtol=1e-6)
    assert is_calibrated(back) and back.error_bound == "measured"


def test_tip_extension_covers_a_foreign_robot_along_the_shaft(seed1):
    """The rule g(f) = f: quantiles of the tip deviation, extended along the shaft, cover the
    quantiles of the true deviation at every fraction. Truth: the foreign generator's robot with
    the "real robot" differences (middle tube 10 % less curved, outer tube 25 % stiffer,
    clearance tilt, torsional compliance, rotation lag of the inner tube); model: nominal
    physics. The rule relates the quantiles of the same configurations' deviations at the tip and
    along the shaft (estimating a tip quantile from a sample is a separate matter: that is the
    held-out data's job), so both come from the same 240 configurations."""
    from tests.foreign import backbones

    q = seed1.sample(240, seed=3)
    m = 21
    eff = {"precurvature": {"scale": [1.0, 0.9, 1.0]}, "stiffness": {"scale": [1.0, 1.0, 1.25]},
           "clearance": {}, "torsion": {}, "friction": {"form": "coulomb_lag", "lag": [0.05, 0, 0]}}
    truth = backbones("seed1", q, eff, points=m, direction=np.ones(q.shape))
    model = PhysicsModel(seed1, torsion=False).shape(q, points=m).points
    dev = np.linalg.norm(truth - model, axis=-1)
    dev = dev[np.all(np.isfinite(dev), axis=1)]
    fit = held = dev
    tipq = {k: float(np.percentile(fit[:, -1], v)) for k, v in
            (("p50", 50), ("p95", 95), ("p99", 99), ("max", 100))}
    assert 1.5 < tipq["p50"] < 6.0               # a robot a few mm from nominal
    prof = extend_tip_bound(tipq)
    f = np.linspace(0, 1, m)
    for k, v in (("p50", 50), ("p95", 95)):
        true_q = np.percentile(held, v, axis=0)
        bound = prof.at(f, k)
        assert np.all(true_q <= bound + 1e-9), (k, np.max(true_q - bound))


def test_calibrated_model_without_a_bound_gets_the_physics_recheck(seed1, tmp_path):
    """A calibrated model planned at margin 0 (no error bound in its file) is re-checked with
    physics; with a bound it plans at its margin and is re-checked with itself at margin 0."""
    from ctrplan.planning.plan import plan_to_target

    far = [0.0, 0.0, 5000.0]       # unreachable: the plan stops after setup, meta is filled in
    bare = EffectModel(seed1, "compliant", {"clearance": {"c0": 0.05}})
    r = plan_to_target(seed1, "airway", far, model=bare)
    assert r.reference_model == "physics" and r.margin_mm == 0.0
    eq = {"p50": 0.2, "p95": 0.4, "p99": 0.6, "max": 0.9}
    prof = extend_tip_bound(eq).to_dict()
    cal = EffectModel(seed1, "compliant", {"clearance": {"c0": 0.05}}, error_quantiles=eq,
                      error_profile=prof)
    r = plan_to_target(seed1, "airway", far, model=cal)
    assert r.reference_model != "physics" and r.margin_mm == pytest.approx(0.6) and r.margin_auto


def test_plan_counts_states_beyond_the_measured_insertions(seed1, tmp_path):
    """A calibrated model's error bound holds where it was measured: plan.json counts the path
    states that insert a tube beyond the measured insertions (oracle: a brute-force count over
    the path's rows), the file round-trips ``measured_insertion``, and bad ranges are refused
    naming the field."""
    import json

    import yaml

    from ctrplan.cli import main
    from ctrplan.errors import InputError
    from ctrplan.planning.plan import plan_to_target, scene_by_name

    sc = scene_by_name("airway")
    eq = {"p50": 0.05, "p95": 0.1, "p99": 0.1, "max": 0.15}
    n = seed1.n
    narrow = {"min": [-200.0, -150.0, -80.0], "max": [-190.0, -140.0, -70.0]}
    cal = EffectModel(seed1, "rigid", {}, error_quantiles=eq, measured_insertion=narrow)
    r = plan_to_target(seed1, sc, sc.targets[0].position, model=cal, seed=0, time_limit=30)
    assert r.success, r.message

    def beyond(path) -> int:
        """Brute force: path states with a tube inserted more than 1 mm outside ``narrow``."""
        return sum(any(not (lo - 1.0 <= x <= hi + 1.0) for x, lo, hi in
                       zip(row, narrow["min"], narrow["max"]))
                   for row in np.asarray(path)[:, n:].tolist())

    brute = beyond(r.path)
    assert r.outside_measured_states == brute > 0
    assert r.to_json()["outside_measured_states"] == brute
    wide = {"min": [-400.0] * n, "max": [0.0] * n}
    r2 = plan_to_target(seed1, sc, sc.targets[0].position,
                        model=EffectModel(seed1, "rigid", {}, error_quantiles=eq,
                                          measured_insertion=wide), seed=0, time_limit=30)
    assert r2.success and r2.outside_measured_states == 0
    r3 = plan_to_target(seed1, sc, sc.targets[0].position, seed=0, time_limit=30)   # physics
    assert r3.outside_measured_states is None
    # the file: round trip, then hostile values refused with the field named
    path = tmp_path / "calibrated.yaml"
    cal.save(path)
    assert EffectModel.load(path).measured_insertion == narrow
    good = yaml.safe_load(path.read_text())
    for bad, field in (({"min": [0.0] * n, "max": [-1.0] * n}, "measured_insertion"),
                       ({"min": [0.0] * (n - 1), "max": [0.0] * n}, "measured_insertion.min"),
                       ({"min": [0.0] * n, "max": ["x"] * n}, "measured_insertion.max"),
                       ([1, 2], "measured_insertion")):
        with pytest.raises(InputError) as ei:
            EffectModel.from_dict({**good, "measured_insertion": bad}, source="c.yaml")
        assert ei.value.field == field, (bad, ei.value)
    # the command line says it in its summary
    out = tmp_path / "plan.json"
    rc = main(["--quiet", "plan", "--robot", "seed1", "--scene", "airway", "--target", "t01",
               "--model", str(path), "--margin", "auto", "--out", str(out)])
    assert rc == 0 and json.loads(out.read_text())["outside_measured_states"] == brute
    # plan-batch: each job's count (brute force over the job's own path) in jobs.csv, their sum
    # in summary.csv; a physics job has none (empty cells, not 0)
    import csv

    from ctrplan.planning.batch import make_jobs, run_batch

    t = sc.targets[0]
    jobs = make_jobs([("airway", t.name, tuple(t.position))], seeds=[0, 1], model=str(path),
                     time_limit=10.0)
    jobs += make_jobs([("airway", t.name, tuple(t.position))], seeds=[0], time_limit=10.0)
    run_batch(jobs, tmp_path / "batch")
    counts = {}
    for f in (tmp_path / "batch" / "jobs").glob("*.json"):
        d = json.loads(f.read_text())
        counts[d["job_id"]] = None if d["model"] == "physics" else beyond(d["path"])
    with open(tmp_path / "batch" / "jobs.csv") as fh:
        rows = list(csv.DictReader(fh))
    assert {r["job_id"]: r["outside_measured_states"] for r in rows} == {
        k: "" if v is None else str(v) for k, v in counts.items()}
    with open(tmp_path / "batch" / "summary.csv") as fh:
        summary = list(csv.DictReader(fh))
    want = sum(v for v in counts.values() if v is not None)
    assert want > 0 and summary[0]["outside_measured_states"] == str(want)
