"""The learned model over the closed-form rigid base with pair inputs (issue 38's recipe):
every evaluation path gives the same backbones, the compiled Jacobian is the derivative, the
pair inputs are what they say, files round-trip, and the device plumbing refuses what torch
cannot use."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from ctrplan.cli import main
from ctrplan.robot import load_robot
from ctrplan.shape import training as T
from ctrplan.shape.learned import (
    SMALL_BATCH,
    LearnedModel,
    pair_features,
    polynomial_pad,
    polynomial_pad_torch,
    resolve_device,
    using_device,
)
from ctrplan.shape.rigid import RigidModel

torch.set_num_threads(1)


@pytest.fixture(scope="module", params=["seed1", "two_tube_wide"])
def model(request):
    r = load_robot(request.param)
    m = T.new_model(r, 16, 2, 7, seed=3, base=RigidModel(r), pairs=True)
    with torch.no_grad():                       # non-trivial outputs (the last layer starts at 0)
        for p in m.net.parameters():
            p.normal_(0.0, 0.2, generator=torch.Generator().manual_seed(4))
    m.coef_std = torch.full((21,), 0.01)
    m.invalidate()
    return m


def test_every_path_gives_the_same_backbones(model):
    r = model.robot
    q = r.sample(300, seed=5)
    qt = torch.as_tensor(q, dtype=torch.float32)
    ref = model.points_t(qt, 20).detach().double().numpy() + RigidModel(r).backbone(q, 20)
    small = np.concatenate([model.backbone(q[i:i + SMALL_BATCH]) for i in range(0, 300, SMALL_BATCH)])
    big = model.backbone(q)                                  # chunked float32 CPU path
    np.testing.assert_allclose(small, ref, atol=2e-3)
    np.testing.assert_allclose(big, ref, atol=2e-3)
    nets, rest = model._chain()
    assert isinstance(rest, RigidModel)
    dev_pts, dev_pad, left = model._device_points(q, 20, None, nets, rest, True)   # torch path
    assert left is None
    sh = model.shape(q, 20)
    np.testing.assert_allclose(dev_pts, sh.points, atol=2e-3)
    np.testing.assert_allclose(dev_pad, sh.pad, rtol=1e-3, atol=1e-4)
    assert sh.ok.all()


def test_compiled_jacobian_is_the_derivative(model):
    q = model.robot.sample(8, seed=6)
    D = model.robot.dof
    tip, J = model._own_tip_jacobian(q, None, "compiled")
    np.testing.assert_allclose(tip, model._numpy_points(q, 2)[:, -1], atol=1e-9)
    h = 1e-6
    for j in range(D):
        dq = np.zeros(D)
        dq[j] = h
        fd = (model._numpy_points(q + dq, 2)[:, -1] - model._numpy_points(q - dq, 2)[:, -1]) / (2 * h)
        np.testing.assert_allclose(J[:, :, j], fd, atol=1e-5 * max(1.0, np.abs(fd).max()))
    # with the rigid base (central differences of the closed form) against the whole model
    tip_all, J_all = model.tip_and_jacobian(q)
    np.testing.assert_allclose(tip_all, model.backbone(q, 2)[:, -1], atol=1e-9)
    fd = np.stack([(model.backbone(q + h * np.eye(D)[j], 2)[:, -1]
                    - model.backbone(q - h * np.eye(D)[j], 2)[:, -1]) / (2 * h) for j in range(D)], axis=2)
    np.testing.assert_allclose(J_all, fd, atol=1e-4 * max(1.0, np.abs(fd).max()))


def test_pair_inputs_by_brute_force(model):
    """Relative rotations and curved-section overlaps, the latter by counting arc-length
    samples where both tubes are in their curved sections beyond the constraint plane."""
    r = model.robot
    n = r.n
    q = r.sample(40, seed=7)
    got = pair_features(model, q)
    S, L, C = r.array("straight_length"), r.lengths, r.array("curved_length")
    s = np.linspace(0.0, 600.0, 600_001)                    # 1 um steps
    ds = s[1] - s[0]
    cols = []
    for i, j in model._pairs:
        cols += [np.cos(q[:, i] - q[:, j]), np.sin(q[:, i] - q[:, j])]
    for i, j in model._opairs:
        ov = np.array([ds * np.count_nonzero((s >= b[i] + S[i]) & (s < b[i] + L[i])
                                             & (s >= b[j] + S[j]) & (s < b[j] + L[j]))
                       for b in q[:, n:]]) / min(C[i], C[j])
        cols += [ov, ov * np.cos(q[:, i] - q[:, j]), ov * np.sin(q[:, i] - q[:, j])]
    np.testing.assert_allclose(got, np.stack(cols, axis=1), atol=2e-4)
    assert np.any(got[:, 2 * len(model._pairs)::3] > 0.2)           # overlaps do occur


def test_file_round_trip_keeps_inputs_and_base(model, tmp_path):
    p = tmp_path / "m.pt"
    model.save(p)
    back = LearnedModel.load(p)
    assert back.pair_inputs and isinstance(back.base, RigidModel)
    q = model.robot.sample(100, seed=8)
    np.testing.assert_array_equal(back.backbone(q), model.backbone(q))
    meta = back.metadata()
    assert meta["residual"]["kind"] == "rigid" and meta["architecture"]["pair_inputs"] is True


def test_a_residual_over_it_and_direction_inputs_keep_one_pass(model):
    """Sim+Real residual / direction variants over a model with pair inputs share its inputs
    (evaluated in the same pass as it)."""
    r = model.robot
    res = T.new_model(r, 8, 2, model.terms, seed=1, base=model, pairs=model.pair_inputs)
    nets, rest = res._chain()
    assert len(nets) == 2 and isinstance(rest, RigidModel)
    q = r.sample(80, seed=9)
    np.testing.assert_allclose(res.backbone(q), model.backbone(q), atol=2e-3)   # zero last layer
    d = T.with_direction_inputs(model)
    np.testing.assert_allclose(d.backbone(q, direction=np.ones_like(q)), model.backbone(q), atol=2e-3)
    assert d.pair_inputs


def test_torch_pad_equals_the_numpy_pad(model):
    q = model.robot.sample(50, seed=10)
    fit = model._net_points(q, 9, None, [model])
    np.testing.assert_allclose(polynomial_pad_torch(torch.as_tensor(fit), 12, 7).numpy(),
                               polynomial_pad(fit, 12, 7), rtol=1e-12)


def test_devices_are_resolved_and_refused():
    assert resolve_device("cpu").type == "cpu"
    assert resolve_device(None).type == "cpu"
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    with pytest.raises(ValueError, match="not a device"):
        resolve_device("gpu please")
    with using_device("cpu") as dev:
        assert dev == "cpu"
    m = copy.deepcopy(LearnedModel("seed1", width=4, depth=1, terms=3)).to("auto")
    assert m.device.type == resolve_device("auto").type


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")
def test_cuda_without_a_gpu_is_one_line_exit_2(tmp_path, capsys):
    with pytest.raises(ValueError, match="not available"):
        resolve_device("cuda")
    cfg = tmp_path / "q.csv"
    cfg.write_text("alpha1,alpha2,alpha3,beta1,beta2,beta3\n0,0,0,-100,-80,-40\n")
    for cmd in (["shape", "--robot", "seed1", "--configs", str(cfg), "--model", "learned"],
                ["train", "--robot", "seed1", "--sim", "50"]):
        out = tmp_path / ("x.csv" if cmd[0] == "shape" else "x.pt")
        assert main(["-q", *cmd, "--device", "cuda", "--out", str(out)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and "--device" in err[0]
        assert not out.exists()
