"""The one held-out splitter (ctrplan/split.py) and the calibration's tail and confounding rules.

Oracles: an AR(1) motion whose autocorrelation is rho^k in closed form (its 1/e length is
ceil(-1 / ln rho)); brute-force row distances between roles; hand-made error vectors for the
held-out choice; the physical identity that a sensor rotation about the insertion axis and a
common offset of every tube's rotation move a rigid robot's tip alike (confounded), while a
sensor translation and a precurvature scale do not.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from ctrplan.split import MIN_SWEEPS_WHOLE, autocorrelation_rows, blocks_per_sweep, split


def _ar1(n: int, rho: float, seed: int = 0, tubes: int = 3) -> np.ndarray:
    """q (n, 2 tubes): rotations fixed, insertions AR(1) with coefficient rho (unit variance)."""
    rng = np.random.default_rng(seed)
    x = np.zeros((n, tubes))
    e = rng.normal(size=(n, tubes)) * math.sqrt(1 - rho * rho)
    for k in range(1, n):
        x[k] = rho * x[k - 1] + e[k]
    return np.hstack([np.zeros((n, tubes)), x])


@pytest.mark.parametrize("rho", [0.9, 0.97])
def test_autocorrelation_length_of_an_ar1_motion(rho):
    q = _ar1(40000, rho)
    want = math.ceil(-1.0 / math.log(rho))            # rho^k < 1/e
    assert abs(autocorrelation_rows(q) - want) <= max(2, 0.15 * want)


def _nearest(a: np.ndarray, b: np.ndarray) -> int:
    ia, ib = np.flatnonzero(a), np.flatnonzero(b)
    return int(np.min(np.abs(ia[:, None] - ib[None, :])))


def test_blocks_of_a_continuous_recording_keep_a_gap_of_the_autocorrelation_length():
    q = _ar1(3000, 0.95, seed=1)
    h = split(None, len(q), 0.25, 0.25, seed=0, q=q)
    g = h.autocorrelation_rows
    assert h.kind == "blocks" and 15 <= g <= 25 and not h.capped
    roles = [h.fit, h.val, h.test, h.gap]
    assert np.all(np.sum(roles, axis=0) == 1)          # every row in exactly one role
    assert _nearest(h.test, h.fit | h.val) == g + 1     # the gap: g rows in no role
    L = blocks_per_sweep(3000, g)
    assert L == 4 * (3000 // (4 * 4 * g)) or L in (8, 32)
    assert h.test_units == round(0.25 * L) and h.gap_rows == g
    # test blocks are contiguous runs ending each quarter, the last one ends the recording
    runs = np.flatnonzero(np.diff(np.r_[0, h.test.astype(int), 0]) != 0).reshape(-1, 2)
    assert len(runs) == h.test_units and runs[-1][1] == len(q)


def test_whole_sweeps_from_eight_sweeps_and_random_rows_for_independent_samples():
    q = _ar1(400, 0.9)
    sweep = np.repeat([f"s{k}" for k in range(MIN_SWEEPS_WHOLE)], 50).astype(object)
    h = split(sweep, 400, 0.25, 0.25, seed=3, q=q)
    assert h.kind == "whole sweeps" and h.test_units == 2 and not h.gap.any()
    for role in (h.fit, h.val, h.test):
        for other in (h.fit, h.val, h.test):
            if role is not other:
                assert not set(sweep[role]) & set(sweep[other])
    rows = split(None, 400, 0.1, 0.1, seed=3, ordered=False)
    assert rows.kind == "rows" and rows.test.sum() == 40 and rows.val.sum() == 40
    # fewer sweeps: blocks of every sweep, each sweep in every role
    few = np.repeat(["a", "b", "c"], [100, 150, 150]).astype(object)
    hb = split(few, 400, 0.25, 0.25, seed=0, q=q)
    assert hb.kind == "blocks" and hb.test_units == 6
    for nm in "abc":
        assert all((r & (few == nm)).any() for r in (hb.fit, hb.val, hb.test))


def test_heldout_choice_keeps_the_base_when_the_fit_worsens_the_tail():
    from ctrplan.calibration.verdict import heldout_choice

    rng = np.random.default_rng(0)
    base = rng.uniform(1.0, 2.0, 400)
    test = np.zeros(400, dtype=bool)
    test[200:] = True
    units = np.repeat(["a", "b", "c", "d"], 100).astype(object)
    better = base * 0.5
    c = heldout_choice(base, better, test, units)
    assert c.output == "fit" and c.info["stable"] and np.array_equal(c.err, better)
    tail = better.copy()
    tail[210] = 5.0                                     # mean better, p99 worse than the base
    tail[260:265] = 5.0
    c = heldout_choice(base, tail, test, units)
    assert c.output == "base" and np.array_equal(c.err, base)
    assert c.info["fit"]["p99_mm"] > c.info["base"]["p99_mm"]
    assert c.info["folds"][0] == list(range(200, 300)) and c.info["folds"][1] == list(range(300, 400))


def test_registration_about_the_axis_and_a_common_rotation_offset_are_confounded():
    from ctrplan.calibration.confound import confounded
    from ctrplan.calibration.lsq import Problem
    from ctrplan.measured import MeasuredData
    from ctrplan.robot import load_robot
    from ctrplan.shape.effects import EffectModel, off_values

    r = load_robot("seed1")
    q = r.sample(120, seed=4)
    data = MeasuredData(q=q, tip=np.zeros((120, 3)), sweep=np.array([f"u{i}" for i in range(120)],
                                                                    dtype=object))
    rows = np.ones(120, dtype=bool)
    prob = Problem(EffectModel(r, "rigid"), data, rows, rows)
    reg = {**off_values("registration", r, "rigid"), "rz": 0.05}
    jo = {**off_values("joint_offset", r, "rigid"), "dalpha1": 0.05, "dalpha2": 0.05,
          "dalpha3": 0.05}
    out = confounded(prob, {"registration": reg, "joint_offset": jo},
                     {"registration": ["rz"], "joint_offset": ["dalpha1", "dalpha2", "dalpha3"]},
                     rows)
    assert len(out) == 1 and out[0]["share_a_by_b"] > 0.99 and out[0]["share_b_by_a"] > 0.99
    assert abs(out[0]["tip_change_correlation"]) > 0.99
    pc = {**off_values("precurvature", r, "rigid"), "scale1": 1.1}
    reg_t = {**off_values("registration", r, "rigid"), "tx": 2.0}
    assert confounded(prob, {"registration": reg_t, "precurvature": pc},
                      {"registration": ["tx"], "precurvature": ["scale1"]}, rows) == []


def test_selection_progress_says_the_time_so_far_and_an_estimate(caplog):
    import logging
    import time

    from ctrplan.calibration.select import _progress

    clock = [time.perf_counter() - 30.0]               # 30 s spent on 2 steps
    with caplog.at_level(logging.INFO, logger="ctrplan"):
        _progress(2, 5, 3, clock)
    msg = caplog.records[-1].getMessage()
    assert "step 3" in msg and "30 s so far" in msg and "about 45 s more" in msg


def test_glitches_are_the_rows_whose_measurement_jumped():
    """A smooth residual (a slowly varying model error along the motion) plus noise, and
    glitches of 3-15 mm on known rows: exactly those rows are flagged, in every role's own runs
    (rows of another role are never used as neighbours)."""
    from ctrplan.calibration.evidence import glitches

    rng = np.random.default_rng(2)
    n = 1200
    t = np.linspace(0, 6 * np.pi, n)
    res = np.stack([3 * np.sin(t), 2 * np.cos(0.7 * t), np.sin(0.3 * t)], axis=1)
    res += rng.normal(0, 0.08, res.shape)
    bad = np.sort(rng.choice(np.arange(5, n - 5), 24, replace=False))
    v = rng.normal(size=(24, 3))
    res[bad] += v / np.linalg.norm(v, axis=1, keepdims=True) * rng.uniform(3, 15, (24, 1))
    sweep = np.zeros(n, dtype=object)
    rows = np.ones(n, dtype=bool)
    got = np.flatnonzero(glitches(res, sweep, rows))
    edge = set(bad[np.isin(bad + 1, bad) | np.isin(bad - 1, bad)])   # adjacent pairs: ambiguous
    assert set(bad) - edge <= set(got) and set(got) <= set(bad)
    half = np.arange(n) < n // 2
    only = glitches(res, sweep, half)
    assert not only[~half].any() and set(np.flatnonzero(only)) <= set(bad)
    assert not glitches(res - 0.0, sweep, np.zeros(n, dtype=bool)).any()
