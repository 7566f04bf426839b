"""Learned-model variants: direction-aware inputs, residual mode, error quantiles, training
domain (ok=False outside), whole-sweep splits, and the CLI supplying directions."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from ctrplan.cli import main
from ctrplan.measured import MeasuredData, write_measured
from ctrplan.robot import load_robot, write_configs
from ctrplan.shape import training as T
from ctrplan.shape.base import direction_from_rows, model_error_bound, needs_direction
from ctrplan.shape.learned import LearnedModel, default_model_for
from ctrplan.shape.physics import PhysicsModel

torch.set_num_threads(1)


@pytest.fixture(scope="module")
def shipped():
    return default_model_for("seed1")


def _perturb(model: LearnedModel, seed: int = 0, scale: float = 0.3) -> LearnedModel:
    """Random non-zero weights on every parameter (a stand-in for a trained network)."""
    m = copy.deepcopy(model)
    g = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in m.net.parameters():
            p.add_(scale * torch.randn(p.shape, generator=g))
    m.invalidate()
    return m


def _directions(robot, B, seed):
    return np.random.default_rng(seed).choice([-1, 0, 1], size=(B, robot.dof)).astype(np.int8)


# ----------------------------------------------------------------------------- direction inputs
def test_adding_direction_inputs_keeps_the_outputs_until_trained(shipped):
    m = T.with_direction_inputs(shipped)
    assert needs_direction(m) and not needs_direction(shipped)
    q = shipped.robot.sample(200, seed=1)
    d = _directions(shipped.robot, 200, 2)
    for B in (10, 200):                                    # compiled kernel and torch chunks
        np.testing.assert_allclose(m.shape(q[:B], direction=d[:B]).points, shipped.backbone(q[:B]),
                                   atol=1e-4)


@pytest.mark.parametrize("frame", ["outer", "base"])
def test_direction_inputs_change_the_shape_and_all_paths_agree(shipped, frame):
    r = shipped.robot
    m = _perturb(T.new_model(r, 20, 2, 5, seed=3, frame=frame, direction=True), seed=4)
    q = r.sample(150, seed=5)
    d = _directions(r, 150, 6)
    small = m.backbone(q[:40], direction=d[:40])            # numba float64
    big = m.backbone(q, direction=d)                         # torch float32 chunks
    ref = m.points_t(torch.as_tensor(q, dtype=torch.float32), 20,
                     torch.as_tensor(d, dtype=torch.float32)).detach().numpy()   # autograd path
    np.testing.assert_allclose(small, ref[:40], atol=2e-3)
    np.testing.assert_allclose(big, ref, atol=2e-3)
    flipped = m.backbone(q, direction=-d)
    assert np.abs(flipped - big).max() > 0.5                  # the inputs matter
    np.testing.assert_allclose(m.backbone(q), m.backbone(q, direction=np.zeros_like(d)), atol=1e-9)
    with pytest.raises(ValueError):
        m.backbone(q, direction=d[:, :2])


def test_direction_jacobian_matches_finite_differences(shipped):
    r = shipped.robot
    m = _perturb(T.with_direction_inputs(shipped), seed=7, scale=0.05)
    q = r.sample(6, seed=8)
    d = _directions(r, 6, 9)
    tip, J = m.tip_and_jacobian(q, direction=d)
    h = 1e-6
    for j in range(r.dof):
        e = np.zeros(r.dof)
        e[j] = h
        fd = (m.backbone(q + e, direction=d)[:, -1] - m.backbone(q - e, direction=d)[:, -1]) / (2 * h)
        np.testing.assert_allclose(J[:, :, j], fd, atol=1e-4 * max(1.0, np.abs(fd).max()))
    np.testing.assert_allclose(tip, m.backbone(q, direction=d)[:, -1], atol=1e-9)


# ----------------------------------------------------------------------------- residual mode
def test_residual_over_a_learned_base_is_base_plus_own_output(shipped, tmp_path):
    r = shipped.robot
    m = T.new_model(r, 15, 2, shipped.terms, seed=1, base=shipped, direction=True)
    m = _perturb(m, seed=2, scale=0.1)
    q = r.sample(300, seed=3)
    d = _directions(r, 300, 4)
    own = m.points_t(torch.as_tensor(q, dtype=torch.float32), 20,
                     torch.as_tensor(d, dtype=torch.float32)).detach().numpy()
    want = shipped.backbone(q) + own
    for B in (30, 300):
        np.testing.assert_allclose(m.backbone(q[:B], direction=d[:B]), want[:B], atol=2e-3)
    path = tmp_path / "res.pt"
    m.error_quantiles = {"p50": 1.0, "p95": 2.0, "p99": 3.0, "max": 4.0}
    m.save(path)
    back = LearnedModel.load(path)
    assert back.base_spec["kind"] == "learned" and back.direction_inputs
    np.testing.assert_array_equal(back.backbone(q, direction=d), m.backbone(q, direction=d))
    assert back.error_quantiles == m.error_quantiles and model_error_bound(back) == 3.0
    tip, J = back.tip_and_jacobian(q[:5], direction=d[:5])
    h = 1e-6
    e = np.zeros(r.dof)
    e[r.n] = h                                               # d tip / d beta_1
    fd = (back.backbone(q[:5] + e, direction=d[:5])[:, -1] - back.backbone(q[:5] - e, direction=d[:5])[:, -1]) / (2 * h)
    np.testing.assert_allclose(J[:, :, r.n], fd, atol=1e-3)


def test_residual_over_physics_adds_the_physics_shape(tmp_path):
    r = load_robot("seed1")
    phys = PhysicsModel(r)
    m = _perturb(T.new_model(r, 10, 2, 5, seed=1, base=phys), seed=3, scale=0.1)
    q = r.sample(80, seed=4)
    own = m.points_t(torch.as_tensor(q, dtype=torch.float32), 20).detach().numpy()
    sh = m.shape(q)
    np.testing.assert_allclose(sh.points, phys.backbone(q) + own, atol=2e-3)
    np.testing.assert_array_equal(sh.ok, phys.shape(q).ok & m.in_domain(q))
    m.save(tmp_path / "p.pt")
    back = LearnedModel.load(tmp_path / "p.pt")
    assert isinstance(back.base, PhysicsModel) and back.base.torsion
    np.testing.assert_allclose(back.backbone(q), sh.points, atol=1e-9)


# ----------------------------------------------------------------------------- domain and bound
def test_ok_is_false_outside_the_training_domain():
    r = load_robot("seed1")
    n = r.n
    q = r.sample(2000, seed=1)
    lo, hi = r.beta_bounds()
    # training data: rotations of tube 1 within +-1 rad of 0.5, translations in a middle band
    q[:, 0] = 0.5 + np.random.default_rng(2).uniform(-1.0, 1.0, len(q))
    mid = (lo + hi) / 2
    keep = np.all(np.abs(q[:, n:] - mid) <= 0.25 * (hi - lo), axis=1) & r.is_valid(q)
    seen = q[keep]
    m = T.new_model(r, 8, 1, 4, seed=0)
    m.set_domain(seen)
    assert m.domain["alpha_arcs_rad"][0] == pytest.approx([0.5, 1.0], abs=0.01)
    assert all(a is None for a in m.domain["alpha_arcs_rad"][1:])   # uniform: the whole circle
    inside = seen[:50]
    assert m.shape(inside).ok.all()
    out = inside.copy()
    out[:, 0] = 0.5 + np.pi                                   # rotation never seen
    assert not m.shape(out).ok.any()
    out = inside.copy()
    out[:, n] = seen[:, n].max() + 1.0                        # translation beyond the range seen
    assert not m.in_domain(out).any()
    bad = inside.copy()
    bad[:, n:] = hi + 50.0                                   # outside the robot's limits
    assert not m.shape(bad).ok.any()
    # persisted
    m.error_quantiles = {"p50": 0.1, "p95": 0.2, "p99": 0.3, "max": 0.4}
    import tempfile
    with tempfile.TemporaryDirectory() as td:
        m.save(f"{td}/m.pt")
        back = LearnedModel.load(f"{td}/m.pt")
    np.testing.assert_array_equal(back.in_domain(out), m.in_domain(out))
    np.testing.assert_array_equal(back.shape(inside).ok, m.shape(inside).ok)


def test_trained_models_carry_held_out_error_quantiles():
    r = load_robot("seed1")
    real = T.real_data(r, 400, seed=5)
    sweep = np.repeat([f"s{k}" for k in range(8)], 50)[:len(real)]
    real = T.ShapeData(real.q, real.points, "test", sweep=sweep).with_direction_from_rows()
    model, rep = T.pretrain_finetune(r, None, real, width=10, depth=2, terms=5, seed=0,
                                     fine=T.TrainConfig(epochs=3, progress=False), variant="direction")
    assert isinstance(rep, T.TrainReport) and isinstance(rep.stages["real"], T.TrainResult)
    # independent recomputation on the held-out sweeps
    _, _, te = T.split(real, seed=1)
    assert len(set(te.sweep)) >= 1 and not set(te.sweep) & set(T.split(real, seed=1)[0].sweep)
    pred = model.shape(te.q, 20, direction=te.direction).points
    mx = np.sqrt(((pred - te.points) ** 2).sum(axis=2)).max(axis=1)
    for k, p in (("p50", 50), ("p95", 95), ("p99", 99), ("max", 100)):
        assert model.error_quantiles[k] == pytest.approx(np.percentile(mx, p), rel=1e-6)
    assert model_error_bound(model) == model.error_quantiles["p99"]
    assert model.domain is not None and model.meta["error_quantiles_source"]["rows"] == len(te)


def test_shipped_model_carries_error_quantiles_consistent_with_fresh_physics(shipped):
    eq = shipped.error_quantiles
    assert eq is not None and eq["p50"] <= eq["p95"] <= eq["p99"] <= eq["max"]
    data = T.simulated_data("seed1", 1000, seed=777, workers=1, progress=False)
    pred = shipped.backbone(data.q)
    mx = np.linalg.norm(pred - data.points, axis=2).max(axis=1)
    assert np.percentile(mx, 50) == pytest.approx(eq["p50"], rel=0.2)
    assert np.percentile(mx, 95) == pytest.approx(eq["p95"], rel=0.25)
    assert shipped.shape(data.q).ok.all()                     # the whole robot range was seen


def test_split_by_whole_sweeps():
    r = load_robot("seed1")
    q = r.sample(300, seed=0)
    sweep = np.repeat([f"s{k}" for k in range(10)], 30)
    data = T.ShapeData(q, np.zeros((300, 5, 3)), sweep=sweep)
    tr, va, te = T.split(data, seed=3)
    parts = [set(p.sweep) for p in (tr, va, te)]
    assert not (parts[0] & parts[1]) and not (parts[0] & parts[2]) and not (parts[1] & parts[2])
    assert len(tr) + len(va) + len(te) == 300 and len(te) >= 30 and len(va) >= 30


# ----------------------------------------------------------------------------- callers
def test_shape_and_check_commands_supply_directions_from_row_order(shipped, tmp_path):
    r = shipped.robot
    m = _perturb(T.with_direction_inputs(shipped), seed=5, scale=0.2)
    mpath = tmp_path / "dir.pt"
    m.save(mpath)
    # a back-and-forth sweep: rows in order of motion
    t = np.linspace(0, 1, 40)
    q = np.tile(r.sample(1, seed=2), (40, 1))
    q[:, 0] += 0.8 * np.sin(2 * np.pi * t)
    q[:, r.n] = np.clip(q[:, r.n] + 5 * np.sin(4 * np.pi * t), *[b[0] for b in r.beta_bounds()])
    assert r.is_valid(q).all()
    cfg = tmp_path / "q.csv"
    write_configs(cfg, r, q)
    out = tmp_path / "s.npz"
    assert main(["-q", "shape", "--robot", "seed1", "--configs", str(cfg), "--model", str(mpath),
                 "--out", str(out)]) == 0
    got = np.load(out)["points"]
    d = direction_from_rows(q)
    np.testing.assert_allclose(got, m.shape(q, 20, direction=d).points, atol=1e-9)
    assert np.abs(got - m.backbone(q)).max() > 0.1            # not the direction-free answer
    # measured CSV with sweep ids: directions restart in each sweep
    meas = tmp_path / "m.csv"
    sweep = np.array(["a"] * 20 + ["b"] * 20, dtype=object)
    write_measured(meas, r, MeasuredData(q=q, tip=np.zeros((40, 3)), sweep=sweep))
    out2 = tmp_path / "s2.npz"
    assert main(["-q", "shape", "--robot", "seed1", "--configs", str(meas), "--model", str(mpath),
                 "--out", str(out2)]) == 0
    np.testing.assert_allclose(np.load(out2)["points"],
                               m.shape(q, 20, direction=direction_from_rows(q, sweep)).points, atol=1e-9)


def test_residual_over_a_calibrated_model_is_stored_in_the_file(tmp_path):
    from ctrplan.shape.effects import EffectModel

    r = load_robot("seed1")
    cal = EffectModel(r, "compliant", {"precurvature": {"scale1": 1.1, "scale2": 0.95, "scale3": 1.0}})
    m = _perturb(T.new_model(r, 10, 2, 5, seed=1, base=cal), seed=2, scale=0.1)
    q = r.sample(40, seed=3)
    own = m.points_t(torch.as_tensor(q, dtype=torch.float32), 20).detach().numpy()
    np.testing.assert_allclose(m.backbone(q), cal.backbone(q) + own, atol=2e-3)
    m.save(tmp_path / "c.pt")
    back = LearnedModel.load(tmp_path / "c.pt")
    assert isinstance(back.base, EffectModel) and back.base.effects == cal.effects
    np.testing.assert_allclose(back.backbone(q), m.backbone(q), atol=1e-9)


def test_device_path_agrees_for_direction_and_residual_models(shipped):
    """The torch path used on GPUs (``_fast_points`` per network, summed), run on the CPU."""
    r = shipped.robot
    m = _perturb(T.new_model(r, 15, 2, shipped.terms, seed=1, base=shipped, direction=True,
                             pairs=shipped.pair_inputs), seed=5, scale=0.1)
    q = r.sample(100, seed=6)
    d = _directions(r, 100, 7)
    nets, rest = m._chain()
    assert len(nets) == 2 and type(rest) is type(shipped.base)   # the shipped one's (rigid) base
    qt = torch.as_tensor(q, dtype=torch.float32)
    dt = torch.as_tensor(d, dtype=torch.float32)
    with torch.inference_mode():
        dev = sum(net._fast_points(qt, 20, dt) for net in nets).numpy()
    if rest is not None:
        dev = dev + rest.backbone(q, 20)
    np.testing.assert_allclose(dev, m.backbone(q, direction=d), atol=2e-3)


def test_split_of_one_ordered_trajectory_is_by_contiguous_blocks():
    """Rows in order of motion without sweeps: held-out rows come in contiguous blocks (not
    random rows, which would be neighbours of training rows), and the rows next to the test
    block are in no part (a gap: here the whole motion is one slow ramp, so the gap is as long
    as the splitter allows, half a block)."""
    r = load_robot("seed1")
    N = 500
    q = np.tile(r.sample(1, seed=0), (N, 1))
    q[:, 0] += np.linspace(0, 3, N)                        # one continuous motion
    data = T.ShapeData(q, np.zeros((N, 5, 3)), "traj", direction=direction_from_rows(q))
    tr, va, te = T.split(data, seed=2)
    assert 30 <= len(te) <= 80 and 30 <= len(va) <= 80
    rows = {round(float(a), 9): k for k, a in enumerate(q[:, 0])}
    idx = {}
    for name, part in (("tr", tr), ("va", va), ("te", te)):
        idx[name] = np.sort([rows[round(float(a), 9)] for a in part.q[:, 0]])
    for name in ("va", "te"):
        assert np.all(np.diff(idx[name]) == 1)             # one block each
        assert T.split_kind({"va": va, "te": te}[name]) == "contiguous blocks"
    assert not set(idx["te"]) & set(idx["tr"])
    left_out = sorted(set(range(N)) - set(idx["tr"]) - set(idx["va"]) - set(idx["te"]))
    assert len(tr) + len(va) + len(te) + len(left_out) == N and len(left_out) >= 10
    nearest = min(abs(int(t) - int(k)) for t in idx["te"] for k in idx["tr"])
    assert nearest > len(left_out) // 2                    # the gap separates test and training
    sim = T.ShapeData(q, np.zeros((N, 5, 3)), "sim")       # no order known: random rows
    _, _, te2 = T.split(sim, seed=2)
    idx = np.sort([rows[round(float(a), 9)] for a in te2.q[:, 0]])
    assert np.any(np.diff(idx) > 1) and T.split_kind(te2) == "rows"
