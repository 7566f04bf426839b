"""Learned full-shape model: data generation, network, save/load, accuracy bounds."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from ctrplan.errors import InputError
from ctrplan.robot import load_robot
from ctrplan.shape import basis
from ctrplan.shape import training as T
from ctrplan.shape.base import ShapeModel, radius_along
from ctrplan.shape.dataset import simulate_shapes
from ctrplan.shape.learned import (
    SMALL_BATCH,
    LearnedModel,
    default_model_for,
    shipped_model_path,
)
from ctrplan.shape.physics import PhysicsModel

# one worker runs this file (`make test-stat` distributes by xdist group): its module fixtures
# are computed once
pytestmark = pytest.mark.xdist_group("learned")


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


# ----------------------------------------------------------------------------- the model
torch.set_num_threads(1)


@pytest.fixture(scope="module")
def shipped():
    return default_model_for("seed1")


@pytest.fixture(scope="module")
def random_model():
    m = LearnedModel("seed1", width=16, depth=2, terms=5, seed=3)
    m.coef_mean = torch.linspace(-0.5, 0.5, 15)    # non-trivial outputs
    m.invalidate()
    return m


def test_protocol_and_shape_fields(shipped):
    assert isinstance(shipped, ShapeModel)
    assert shipped.name == "learned"
    q = shipped.robot.sample(50, seed=4)
    sh = shipped.shape(q, points=11)
    assert sh.points.shape == (50, 11, 3) and sh.points.dtype == np.float64
    assert sh.ok.all()
    L = shipped.robot.tip_length(q)
    np.testing.assert_allclose(sh.s[:, -1], L)
    np.testing.assert_allclose(sh.s[:, 0], 0.0)
    np.testing.assert_allclose(sh.radius, radius_along(shipped.robot, q, sh.s))
    np.testing.assert_allclose(sh.points[:, 0], 0.0, atol=1e-9)   # the basis vanishes at s = 0
    np.testing.assert_allclose(shipped.backbone(q, 11), sh.points)


@pytest.mark.parametrize("frame", ["outer", "base"])
def test_inference_paths_agree(random_model, frame):
    m = copy.deepcopy(random_model)
    m.frame = frame
    m.invalidate()
    q = m.robot.sample(300, seed=5)
    ref = m.points_t(torch.as_tensor(q, dtype=torch.float32), 20).detach().numpy()
    small = np.concatenate([m.backbone(q[i:i + SMALL_BATCH]) for i in range(0, 300, SMALL_BATCH)])
    big = m.backbone(q)                                  # chunked CPU path
    np.testing.assert_allclose(small, ref, atol=2e-3)
    np.testing.assert_allclose(big, ref, atol=2e-3)
    c = m.coefficients_t(torch.as_tensor(q, dtype=torch.float32)).detach().numpy()
    np.testing.assert_allclose(basis.reconstruct(c, m.robot.tip_length(q), 20), ref, atol=2e-3)


def test_outer_frame_is_equivariant_to_a_common_rotation(random_model):
    q = random_model.robot.sample(40, seed=6)
    q2 = q.copy()
    q2[:, :3] += 0.9
    R = np.array([[np.cos(0.9), -np.sin(0.9), 0], [np.sin(0.9), np.cos(0.9), 0], [0, 0, 1]])
    np.testing.assert_allclose(random_model.backbone(q2), random_model.backbone(q) @ R.T, atol=2e-3)


@pytest.mark.parametrize("frame", ["outer", "base"])
def test_tip_and_jacobian_match_finite_differences(shipped, frame):
    m = copy.deepcopy(shipped)
    m.frame = frame
    m.invalidate()
    q = m.robot.sample(6, seed=7)
    tip, J = m.tip_and_jacobian(q)                         # compiled forward mode (float64)
    tip_a, J_a = m.tip_and_jacobian(q, method="autograd")   # torch autograd (float32)
    assert tip.shape == (6, 3) and J.shape == (6, 3, 6)
    np.testing.assert_allclose(tip, m.backbone(q)[:, -1], atol=1e-9)
    np.testing.assert_allclose(tip_a, tip, atol=2e-3)
    np.testing.assert_allclose(J_a, J, atol=2e-3 * max(1.0, np.abs(J).max()))
    h = 1e-6
    for j in range(6):
        dq = np.zeros(6)
        dq[j] = h
        fd = (m.backbone(q + dq, 2)[:, -1] - m.backbone(q - dq, 2)[:, -1]) / (2 * h)   # float64 paths
        np.testing.assert_allclose(J[:, :, j], fd, atol=1e-5 * max(1.0, np.abs(fd).max()))
    with pytest.raises(ValueError):
        m.tip_and_jacobian(q, method="nope")


def test_save_load_roundtrip(tmp_path, random_model):
    p = tmp_path / "m.pt"
    random_model.meta = {"metrics": {"x": 1.0}}
    random_model.save(p)
    m2 = LearnedModel.load(p)
    q = random_model.robot.sample(100, seed=8)
    np.testing.assert_array_equal(m2.backbone(q), random_model.backbone(q))
    assert (m2.width, m2.depth, m2.terms, m2.frame) == (16, 2, 5, "outer")
    assert m2.meta["metrics"] == {"x": 1.0}
    assert m2.robot == random_model.robot
    assert LearnedModel.load(p, robot="seed1").robot.name == "seed1"


def test_load_errors_name_the_file(tmp_path, random_model):
    good = tmp_path / "good.pt"
    random_model.save(good)
    with pytest.raises(InputError, match="trained for robot 'seed1'"):
        LearnedModel.load(good, robot="two_tube_nylon")
    bad = tmp_path / "garbage.pt"
    bad.write_bytes(b"not a torch file at all")
    with pytest.raises(InputError, match="garbage.pt"):
        LearnedModel.load(bad)
    trunc = tmp_path / "trunc.pt"
    trunc.write_bytes(good.read_bytes()[:200])
    with pytest.raises(InputError, match="trunc.pt"):
        LearnedModel.load(trunc)
    with pytest.raises(InputError, match="not found"):
        LearnedModel.load(tmp_path / "missing.pt")
    other = tmp_path / "other.pt"
    torch.save({"format": "something-else"}, other)
    with pytest.raises(InputError, match="other.pt: format"):
        LearnedModel.load(other)
    obj = torch.load(good, weights_only=True)
    obj["state"]["net.0.weight"] = torch.zeros(3, 3)
    wrong = tmp_path / "wrong.pt"
    torch.save(obj, wrong)
    with pytest.raises(InputError, match="wrong.pt: state"):
        LearnedModel.load(wrong)
    obj = torch.load(good, weights_only=True)
    obj["state"]["net.0.weight"][0, 0] = float("nan")
    nan = tmp_path / "nan.pt"
    torch.save(obj, nan)
    with pytest.raises(InputError, match="non-finite"):
        LearnedModel.load(nan)
    obj = torch.load(good, weights_only=True)
    obj["meta_json"] = "{not json"
    meta = tmp_path / "meta.pt"
    torch.save(obj, meta)
    with pytest.raises(InputError, match="meta.pt: meta_json"):
        LearnedModel.load(meta)


def test_default_model_lookup():
    from ctrplan.shape.models import load_model

    assert shipped_model_path("seed1") is not None
    assert load_model("learned", "seed1").name == "learned"
    with pytest.raises(InputError, match="no shipped learned model"):
        default_model_for("two_tube_nylon")


def test_shipped_model_file_is_small_and_documented(shipped):
    p = shipped_model_path("seed1")
    assert p.stat().st_size < 1_000_000
    meta = shipped.meta
    assert meta["data"]["sim"]["rows"] >= 99_000 and len(meta["data"]["sim"]["sha256_16"]) == 16
    assert meta["metrics"]["sim_test"]["max_dev_mean"] < SIM_BOUND_MM


# Mean max deviation along the shaft of the shipped seed1 model on held-out simulated shapes
# (configurations from a seed the training never saw). Measured 0.048 mm (issue 38's model; the
# previous one 0.77 mm): see ctrplan/data/models/README.md.
SIM_BOUND_MM = 0.1


def test_shipped_model_accuracy_on_held_out_simulation(shipped):
    data = T.simulated_data("seed1", 1000, seed=12345, workers=1, progress=False)
    ev = T.evaluate(shipped, data)
    assert ev["max_dev_mean"] < SIM_BOUND_MM
    assert ev["max_dev_mean"] + 3 * ev["max_dev_std"] < 4 * SIM_BOUND_MM


# ----------------------------------------------------------------------------- training
def test_training_is_seeded_reduces_loss_and_keeps_the_best_weights():
    data = T.simulated_data("seed1", 600, seed=3, workers=1, progress=False)
    tr, va, te = T.split(data, seed=0)
    assert (len(tr), len(va), len(te)) == (480, 60, 60)
    models = []
    for _ in range(2):
        m = T.new_model(load_robot("seed1"), 15, 2, 5, seed=1)
        T.set_normalisation(m, tr)
        cfg = T.TrainConfig(epochs=8, patience=3, seed=1, progress=False)
        info = T.train(m, tr, va, cfg)
        models.append(m)
        losses = [h["val_loss"] for h in info.history]
        assert info.best_val_loss_mm2 == pytest.approx(min(losses))
        assert min(losses) < losses[0]
    q = data.q[:20]
    np.testing.assert_array_equal(models[0].backbone(q), models[1].backbone(q))


def test_hidden_effects_change_the_shapes():
    r = load_robot("seed1")
    eff = T.HiddenEffects.default(r)
    q = r.sample(50, seed=2)
    clean, noisy, ok = eff.shapes(PhysicsModel(r), q, 20, np.random.default_rng(0))
    assert ok.all()
    phys = PhysicsModel(r).backbone(q)
    dev = np.linalg.norm(clean - phys, axis=2).max(axis=1)
    assert 1.0 < dev.mean() < 15.0
    noise = noisy - clean
    assert noise.std() == pytest.approx(eff.noise_mm, rel=0.15)


def test_sim_plus_real_beats_real_only_sim_only_and_physics(shipped):
    """Done-when of issue 3, small version: fine-tune the shipped (simulation-trained) model on
    a small "real" data set with hidden effects; compare on its held-out part."""
    r = shipped.robot
    real = T.real_data(r, 1000, seed=21)
    tr, va, te = T.split(real, seed=2)
    phys = T.evaluate(PhysicsModel(r), te)["max_dev_mean"]
    sim_only = T.evaluate(shipped, te)["max_dev_mean"]
    fine = copy.deepcopy(shipped)
    fine.invalidate()
    T.train(fine, tr, va, T.TrainConfig(epochs=60, lr=5e-4, batch_size=128, patience=15, progress=False))
    sim_real = T.evaluate(fine, te)["max_dev_mean"]
    real_only = T.new_model(r, shipped.width, shipped.depth, shipped.terms, seed=0)
    T.set_normalisation(real_only, tr)
    T.train(real_only, tr, va, T.TrainConfig(epochs=60, lr=2e-3, batch_size=128, patience=15, progress=False))
    real_only_err = T.evaluate(real_only, te)["max_dev_mean"]
    assert sim_real < real_only_err
    assert sim_real < sim_only
    assert sim_real <= 0.6 * phys, (sim_real, phys)


@pytest.mark.statistical   # backs the README's "learned beats physics on real data" (.ci/run)
def test_full_sweep_default_architecture_meets_the_done_when(tmp_path):
    """The sweep at a meaningful size (minutes): Sim+Real beats Real-only and Sim-only and is
    at least 40% better than the physics model on held-out "real" data (default 3 x 30)."""
    r = load_robot("seed1")
    sim = T.simulated_data(r, 20_000, seed=0, progress=False)
    real = T.real_data(r, 1500, seed=1)
    res = T.sweep(r, sim, real, archs=[(3, 30)],
                  pre=T.TrainConfig(epochs=80, progress=False),
                  fine=T.TrainConfig(epochs=200, lr=5e-4, batch_size=128, patience=20, progress=False),
                  real_only=T.TrainConfig(epochs=200, batch_size=128, patience=20, progress=False),
                  progress=False)
    T.write_sweep(res, tmp_path)
    best = T.best_runs(res)
    phys = res.physics["max_dev_mean"]
    assert best["Sim+Real pure"]["max_dev_mean"] < best["Real-only pure"]["max_dev_mean"]
    assert best["Sim+Real pure"]["max_dev_mean"] < best["Sim-only pure"]["max_dev_mean"]
    assert best["Sim+Real pure"]["max_dev_mean"] <= 0.6 * phys
