"""The learned model on a CUDA device: same answers as the CPU paths, training and save/load.

These run only where torch sees a GPU (they were run on an NVIDIA H100 during development; CI
machines have none, so there they are reported as skipped with the reason).
"""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from ctrplan.cli import main
from ctrplan.robot import load_robot
from ctrplan.shape import training as T
from ctrplan.shape.learned import GPU_MIN_BATCH, SMALL_BATCH, LearnedModel, default_model_for

pytestmark = pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device")

TOL_MM = 2e-3      # float32 network on either device; backbones are ~100-250 mm long


@pytest.fixture(scope="module")
def shipped_cpu():
    return default_model_for("seed1")


@pytest.fixture(scope="module")
def shipped_gpu():
    return default_model_for("seed1", device="cuda")


@pytest.mark.parametrize("batch", [1, SMALL_BATCH + 1, GPU_MIN_BATCH, 20_000])
def test_gpu_backbone_matches_cpu(shipped_cpu, shipped_gpu, batch):
    """Batches below GPU_MIN_BATCH run on the CPU paths, larger ones on the GPU (network,
    closed-form rigid base and the polynomial pad in torch)."""
    assert shipped_gpu.device.type == "cuda"
    assert shipped_gpu._on_device(batch) == (batch >= GPU_MIN_BATCH)
    q = shipped_cpu.robot.sample(batch, seed=batch)
    cpu = shipped_cpu.backbone(q, 20)
    gpu = shipped_gpu.backbone(q, 20)
    assert gpu.dtype == np.float64 and gpu.shape == (batch, 20, 3)
    np.testing.assert_allclose(gpu, cpu, atol=TOL_MM)
    sh = shipped_gpu.shape(q, 7)
    ref = shipped_cpu.shape(q, 7)
    np.testing.assert_allclose(sh.points, ref.points, atol=TOL_MM)
    np.testing.assert_allclose(sh.radius, ref.radius)
    np.testing.assert_allclose(sh.pad, ref.pad, rtol=1e-3, atol=1e-4)
    np.testing.assert_array_equal(sh.ok, ref.ok)


def test_rigid_base_on_the_gpu_matches_the_numba_kernel():
    from ctrplan.shape.rigid import RigidModel

    rm = RigidModel("seed1")
    q = rm.robot.sample(5000, seed=4)
    got = rm.points_torch(torch.as_tensor(q, dtype=torch.float64, device="cuda"), 20).cpu().numpy()
    np.testing.assert_allclose(got, rm.backbone(q, 20), atol=1e-9)


def test_gpu_jacobian_matches_compiled_cpu(shipped_cpu, shipped_gpu):
    q = shipped_cpu.robot.sample(GPU_MIN_BATCH, seed=2)
    tip, J = shipped_cpu.tip_and_jacobian(q)               # numba forward mode, float64
    tip_g, J_g = shipped_gpu.tip_and_jacobian(q)           # autograd on the GPU ("auto")
    np.testing.assert_allclose(tip_g, tip, atol=TOL_MM)
    np.testing.assert_allclose(J_g, J, atol=2e-3 * max(1.0, np.abs(J).max()))


def test_model_moves_between_devices(shipped_cpu):
    m = copy.deepcopy(shipped_cpu).to("cuda")
    q = m.robot.sample(500, seed=3)
    on_gpu = m.backbone(q)
    m.to("cpu")
    assert m.device.type == "cpu"
    np.testing.assert_allclose(m.backbone(q), on_gpu, atol=TOL_MM)


def test_training_on_gpu_is_seeded_and_loads_on_cpu(tmp_path):
    data = T.simulated_data("seed1", 600, seed=3, workers=1, progress=False)
    tr, va, te = T.split(data, seed=0)
    runs = []
    for _ in range(2):
        m = T.new_model(load_robot("seed1"), 15, 2, 5, seed=1, device="cuda")
        T.set_normalisation(m, tr)
        cfg = T.TrainConfig(epochs=8, patience=3, seed=1, progress=False)
        info = T.train(m, tr, va, cfg)
        losses = [h["val_loss"] for h in info.history]
        assert min(losses) < losses[0]
        runs.append(m)
    q = te.q[:50]
    # cuBLAS may reorder float32 sums between runs; the same seed gives the same model to
    # well under the network's own error
    np.testing.assert_allclose(runs[0].backbone(q), runs[1].backbone(q), atol=1e-2)
    path = tmp_path / "gpu.pt"
    runs[0].save(path)
    back = LearnedModel.load(path, robot="seed1")            # CPU by default
    assert back.device.type == "cpu"
    np.testing.assert_allclose(back.backbone(q), runs[0].backbone(q), atol=TOL_MM)
    assert T.evaluate(back, te)["max_dev_mean"] == pytest.approx(
        T.evaluate(runs[0], te)["max_dev_mean"], abs=1e-2)


def test_train_command_on_cuda(tmp_path):
    out = tmp_path / "m.pt"
    args = ["-q", "train", "--robot", "seed1", "--sim", "300", "--width", "8", "--depth", "2",
            "--terms", "4", "--epochs", "3", "--workers", "1", "--device", "cuda", "--out", str(out)]
    assert main(args) == 0
    m = LearnedModel.load(out, robot="seed1")
    assert (m.width, m.depth, m.terms) == (8, 2, 4)
    assert np.isfinite(m.backbone(m.robot.sample(5, seed=0))).all()
