"""Training and evaluation of the learned shape model.

* :func:`simulated_data` - uniform valid configurations and their physics backbones (all cores);
* :class:`HiddenEffects` / :func:`real_data` - "real" measurements: our own simulator with
  effects the learned model is never told about (miscalibrated precurvature, changed stiffness
  ratios, clearance tilts at the outer tubes' ends, rotational offsets and backlash, sensor noise);
* :func:`train` - Adam on the sum of squared point distances (or with the largest along the
  shaft weighted in, :data:`LOSSES`), early stopping on a validation set or one cycle of the
  learning rate (:data:`SCHEDULES`); :func:`pretrain_finetune` - pre-train on simulation
  (:data:`SIM_RECIPE`: the network learns the compliant model's difference to the closed-form
  rigid model, with pair inputs), fine-tune on measured shapes;
* :func:`bistable_fraction` - how much of a robot's joint space has two stable equilibria
  (where a surrogate of one shape per configuration cannot follow the robot);
* :func:`evaluate` - the literature's metrics (max deviation, MSE, sum of deviations along the
  shaft) with mean +- std over a test set;
* :func:`sweep` - Sim-only / Real-only / Sim+Real x variants (pure, direction-aware,
  residual, residual + direction) x architectures, tables and plots.

Variants: *direction-aware* models get the sign of the last motion of each joint as extra
inputs (from row order within each sweep of measured data, :func:`direction_from_rows`); a
Sim+Real direction-aware model starts from the Sim model with zero weights on those inputs.
*Residual* models learn the difference to a base model: physics for Real-only, the frozen
Sim model for Sim+Real (no physics call at evaluation), or a calibrated model.
Data is split by the one held-out splitter (:func:`split`, :mod:`ctrplan.split`): whole sweeps,
or blocks of a continuous recording with gaps, or random rows for independent samples.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import logging
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from ctrplan.robot import Robot, load_robot
from ctrplan.shape import basis
from ctrplan.shape.base import direction_from_rows, needs_direction
from ctrplan.shape.learned import (
    DEFAULT_DEPTH,
    DEFAULT_FRAME,
    DEFAULT_WIDTH,
    LearnedModel,
    base_model_spec,
)
from ctrplan.shape.physics import MechanicsParams, PhysicsModel
from ctrplan.split import BLOCK_TAG, is_ordered
from ctrplan.split import split as heldout_split

log = logging.getLogger("ctrplan")

DEFAULT_SIM = 100_000


@dataclass(frozen=True)
class SimRecipe:
    """Defaults of the network pre-trained on simulation (``ctrplan train --robot R``): rows of
    simulated data, the network (width, depth) and its base (:func:`sim_base_model`), epochs,
    loss and schedule (:class:`TrainConfig`). See ctrplan/data/models/README.md for what it
    reaches and costs."""

    rows: int
    width: int
    depth: int
    epochs: int
    loss: str
    schedule: str
    pairs: bool = False


#: the documented recipe (``ctrplan train --robot R``)
SIM_RECIPE = SimRecipe(rows=1_000_000, width=64, depth=4, epochs=30, loss="sum_sq+max",
                       schedule="onecycle", pairs=True)
#: ``ctrplan train --sweep``: the literature's settings (the architectures are swept)
SWEEP_RECIPE = SimRecipe(rows=DEFAULT_SIM, width=DEFAULT_WIDTH, depth=DEFAULT_DEPTH, epochs=150,
                         loss="sum_sq", schedule="plateau")
ARCH_DEPTHS = (3, 5, 7)
ARCH_WIDTHS = (15, 30, 60)


# ---------------------------------------------------------------------------------- data
@dataclass(frozen=True)
class ShapeData:
    """Configurations and measured/simulated backbones.

    q : (N, 2n) rad, mm. points : (N, m, 3) mm, evenly spaced in arc length base to tip.
    direction : (N, 2n) sign of the last motion of each joint (-1/0/+1) or None (unknown).
    sweep : (N,) sweep ids (one continuous experiment each) or None.
    """

    q: np.ndarray
    points: np.ndarray
    source: str = "<memory>"
    direction: np.ndarray | None = None
    sweep: np.ndarray | None = None
    #: measured on a robot (a measured CSV) rather than simulated: an error bound held out
    #: from these rows is ``measured`` (calibrated), else ``surrogate``
    measured: bool = False

    def __len__(self) -> int:
        return int(self.q.shape[0])

    def subset(self, idx: np.ndarray) -> ShapeData:
        def pick(a):
            return None if a is None else a[idx]
        return ShapeData(self.q[idx], self.points[idx], self.source, pick(self.direction), pick(self.sweep),
                         self.measured)

    def with_direction_from_rows(self) -> ShapeData:
        """Direction of the last motion from the row order within each sweep."""
        return dataclasses.replace(self, direction=direction_from_rows(self.q, self.sweep))

    def digest(self) -> str:
        """sha256 of the arrays (first 16 hex digits), recorded in model metadata."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.q, dtype=np.float64).tobytes())
        h.update(np.ascontiguousarray(self.points, dtype=np.float64).tobytes())
        return h.hexdigest()[:16]

    def describe(self) -> dict[str, Any]:
        return {"source": self.source, "rows": len(self), "points": int(self.points.shape[1]),
                "sha256_16": self.digest()}


def simulated_data(robot: Robot | str, n: int, seed: int = 0, points: int = 20,
                   workers: int | None = None, progress: bool = True) -> ShapeData:
    """``n`` uniform valid configurations of ``robot`` and their compliant-physics backbones
    (rows the solver did not converge on are dropped)."""
    from ctrplan.shape.dataset import simulate_shapes

    robot = load_robot(robot)
    q = robot.sample(int(n), seed=seed)
    sh = simulate_shapes(PhysicsModel(robot), q, points=points, workers=workers, progress=progress)
    ok = sh.ok
    if not ok.all():
        log.info("simulated data: dropped %d of %d configurations that did not converge", int((~ok).sum()), len(q))
    return ShapeData(q[ok], sh.points[ok], source=f"physics:{robot.name}:n={n}:seed={seed}")


#: configurations :func:`bistable_fraction` probes by default
BISTABLE_PROBE = 2000


def bistable_fraction(robot: Robot | str, n: int = BISTABLE_PROBE, seed: int = 0) -> dict[str, Any]:
    """How much of the joint space of ``robot`` is bistable (two stable equilibria of the
    compliant model): the fraction of ``n`` uniform valid configurations where the physics
    model, probing for a second stable equilibrium (``PhysicsConfig(probe_bistable=True)``),
    finds two. A surrogate trained on simulation follows the branch the physics model returns
    by default (the less twisted one) there and cannot represent a snap between branches; its
    held-out error includes those configurations. Returns {"fraction", "probed", "seed"}."""
    from ctrplan.shape.physics import PhysicsConfig

    robot = load_robot(robot)
    q = robot.sample(int(n), seed=seed)
    pm = PhysicsModel(robot, config=PhysicsConfig(probe_bistable=True))
    pm.shape(q, 2)
    bi = pm.last_info.bistable if pm.last_info is not None else None
    frac = float(np.mean(bi)) if bi is not None and len(bi) else 0.0
    return {"fraction": frac, "probed": int(len(q)), "seed": int(seed),
            "rule": "two stable equilibria found by the physics model's probe "
                    "(PhysicsConfig(probe_bistable=True)) at uniform valid configurations"}


@dataclass(frozen=True)
class HiddenEffects:
    """A "real" robot: the physics model plus effects a learned model is not told about.

    kappa_scale : (n,) precurvature scale per tube (miscalibrated curvature).
    ei_scale : (n,) bending-stiffness scale per tube (changes the EI ratios).
    clearance_rad : tilt (rad) of the backbone where an outer tube ends, growing with how much
        the curvature directions of that tube and the one inside it disagree:
        ``kink_j = g (Rz(alpha_{j-1}) e_y - Rz(alpha_j) e_y)`` for j >= 1.
    alpha_offset : (n,) rad, constant rotation offsets (zero calibration).
    backlash_rad : rad, rotational friction: each tube lags by this much against the (unknown)
        direction it was last turned in, drawn at random per configuration.
    noise_mm : standard deviation of Gaussian sensor noise per coordinate (mm).
    """

    kappa_scale: tuple[float, ...]
    ei_scale: tuple[float, ...]
    clearance_rad: float = 0.02
    alpha_offset: tuple[float, ...] = ()
    backlash_rad: float = 0.02
    noise_mm: float = 0.3

    @classmethod
    def default(cls, robot: Robot) -> HiddenEffects:
        n = robot.n
        return cls(
            kappa_scale=tuple(0.9 if i % 2 == 0 else 1.1 for i in range(n)),
            ei_scale=tuple(1.2 if i == 0 else (0.85 if i == n - 1 else 1.0) for i in range(n)),
            clearance_rad=0.02,
            alpha_offset=tuple(0.04 * (-1) ** i for i in range(n)),
            backlash_rad=0.02,
            noise_mm=0.3,
        )

    def to_dict(self) -> dict[str, Any]:
        return {"kappa_scale": list(self.kappa_scale), "ei_scale": list(self.ei_scale),
                "clearance_rad": self.clearance_rad, "alpha_offset_rad": list(self.alpha_offset),
                "backlash_rad": self.backlash_rad, "noise_mm": self.noise_mm}

    def shapes(self, physics: PhysicsModel, q: np.ndarray, points: int,
               rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(clean points (B, m, 3), noisy points, ok (B,)) for commanded configurations q."""
        robot = physics.robot
        n = robot.n
        q = np.asarray(q, dtype=float)
        B = len(q)
        qa = q.copy()
        direction = rng.choice([-1.0, 1.0], size=(B, n))
        off = np.asarray(self.alpha_offset if self.alpha_offset else [0.0] * n, dtype=float)
        qa[:, :n] = q[:, :n] + off - direction * self.backlash_rad
        base = physics.base_params(B)
        kink = np.zeros((B, n, 2))
        a = qa[:, :n]
        for j in range(1, n):
            kink[:, j, 0] = -self.clearance_rad * (np.sin(a[:, j - 1]) - np.sin(a[:, j]))
            kink[:, j, 1] = self.clearance_rad * (np.cos(a[:, j - 1]) - np.cos(a[:, j]))
        params = MechanicsParams(kappa=base.kappa * np.asarray(self.kappa_scale),
                                 EI=base.EI * np.asarray(self.ei_scale),
                                 ratio=base.ratio, kink=kink)
        sh = physics.solve(qa, points, params)
        noisy = sh.points + rng.normal(0.0, self.noise_mm, size=sh.points.shape)
        return sh.points, noisy, sh.ok


def real_data(robot: Robot | str, n: int, seed: int = 1, points: int = 20,
              effects: HiddenEffects | None = None) -> ShapeData:
    """Simulated "measured" shapes with hidden effects (noisy points), ``n`` rows."""
    robot = load_robot(robot)
    effects = effects or HiddenEffects.default(robot)
    rng = np.random.default_rng(seed + 7919)
    q = robot.sample(int(n), seed=seed)
    _, noisy, ok = effects.shapes(PhysicsModel(robot), q, points, rng)
    return ShapeData(q[ok], noisy[ok], source=f"hidden-effects:{robot.name}:n={n}:seed={seed}")


def from_measured(path: str, robot: Robot) -> ShapeData:
    """Measured shapes from a CSV with backbone columns p1_x..pM_z (docs/conventions.md)."""
    from ctrplan.errors import InputError
    from ctrplan.measured import read_measured

    md = read_measured(path, robot)
    if md.points is None:
        raise InputError(str(path), "p1_x", "training needs backbone point columns p1_x..pM_z")
    sweep = None if md.sweep is None else np.asarray(md.sweep)
    return ShapeData(md.q, md.points, source=str(path), sweep=sweep,
                     direction=direction_from_rows(md.q, sweep), measured=True)


def split(data: ShapeData, fractions: Sequence[float] = (0.8, 0.1, 0.1),
          seed: int = 0) -> tuple[ShapeData, ShapeData, ShapeData]:
    """Seeded train/validation/test split by the one held-out splitter of ctrplan
    (:func:`ctrplan.split.split`, the rule diagnose uses; ``fractions[2]`` of the units for
    test, ``fractions[1]`` for validation; each part gets at least one row).

    Measured rows in order of motion (sweep ids or directions given) are split by whole sweeps
    when there are at least :data:`ctrplan.split.MIN_SWEEPS_WHOLE` of them, else every sweep is
    cut into contiguous blocks (labelled ``"<sweep>#block<k>"``) and the rows within the
    motion's autocorrelation length of a test block are left out (in no part), so that
    held-out rows are not the neighbours of training rows; other data (simulated, independent
    rows) by random rows."""
    N = len(data)
    if N < 3:
        raise ValueError(f"need at least 3 rows to split, got {N}")
    ordered = data.sweep is not None or data.direction is not None
    if data.sweep is not None:
        ordered = is_ordered(data.sweep, N)
    h = heldout_split(data.sweep, N, test=fractions[2], val=fractions[1], seed=seed, q=data.q,
                      ordered=ordered)
    if not (h.fit.any() and h.val.any() and h.test.any()):
        raise ValueError(f"too few rows ({N}) for a train/validation/test split")
    if h.kind == "blocks":
        data = dataclasses.replace(data, sweep=np.asarray(h.labels, dtype=object))
    return (data.subset(np.flatnonzero(h.fit)), data.subset(np.flatnonzero(h.val)),
            data.subset(np.flatnonzero(h.test)))


def split_kind(part: ShapeData) -> str:
    """How a split part was held out: "whole sweeps", "contiguous blocks" or "rows"."""
    if part.sweep is None:
        return "rows"
    sw = np.asarray(part.sweep).astype(str)
    return "contiguous blocks" if len(sw) and all(BLOCK_TAG in x for x in sw[:1]) else "whole sweeps"


# ---------------------------------------------------------------------------------- training
#: Losses per configuration (mm^2): ``sum_sq`` the sum over the backbone points of the squared
#: distance (the literature's); ``sum_sq+max`` that sum divided by the number of points plus
#: :data:`MAX_WEIGHT` times the largest squared distance along the shaft: the held-out bound is
#: a quantile of the max deviation along the shaft, so the worst point of each configuration
#: is what the loss weighs most.
LOSSES = ("sum_sq", "sum_sq+max")
MAX_WEIGHT = 4.0
#: ``plateau``: the learning rate halves after ``patience // 3`` epochs without validation
#: improvement, training stops after ``patience``; ``onecycle``: warm-up over the first 5 % of
#: the steps to ``lr``, cosine annealing to ``lr / 1e4`` over all ``epochs`` (no early stop; the
#: weights with the best validation loss are kept either way).
SCHEDULES = ("plateau", "onecycle")


@dataclass(frozen=True)
class TrainConfig:
    """Optimiser settings. ``patience``: epochs without validation improvement before stopping;
    the learning rate halves after ``patience // 3`` such epochs."""

    epochs: int = 150
    lr: float = 2e-3
    batch_size: int = 512
    patience: int = 20
    seed: int = 0
    min_lr: float = 1e-5
    max_seconds: float | None = None
    progress: bool = True
    label: str = "train"
    #: decoupled weight decay (AdamW) per step, 0 = plain Adam
    weight_decay: float = 0.0
    #: the loss per configuration, averaged over the batch (:data:`LOSSES`)
    loss: str = "sum_sq"
    #: the learning-rate schedule (:data:`SCHEDULES`)
    schedule: str = "plateau"

    def __post_init__(self) -> None:
        if self.loss not in LOSSES:
            raise ValueError(f"loss must be one of {', '.join(LOSSES)}, got {self.loss!r}")
        if self.schedule not in SCHEDULES:
            raise ValueError(f"schedule must be one of {', '.join(SCHEDULES)}, got {self.schedule!r}")

    def replace(self, **changes: Any) -> TrainConfig:
        return dataclasses.replace(self, **changes)


@dataclass(frozen=True)
class TrainResult:
    """What one :func:`train` call did: epochs, the best validation loss (mean over
    configurations of the sum of squared point distances, mm^2), time, settings, and the
    per-epoch history (epoch, train_loss, val_loss, lr)."""

    epochs_run: int
    best_epoch: int
    best_val_loss_mm2: float
    seconds: float
    lr: float
    batch_size: int
    patience: int
    seed: int
    rows_train: int
    rows_val: int
    history: tuple[dict, ...] = ()

    def to_dict(self) -> dict[str, Any]:
        """JSON-able summary (without the history), as stored in model metadata."""
        d = dataclasses.asdict(self)
        d.pop("history")
        return d


@dataclass(frozen=True)
class TrainReport:
    """What :func:`pretrain_finetune` did: data descriptions, one :class:`TrainResult` per
    stage ("pretrain", "finetune" or "real"), held-out metrics per data set ("sim_test",
    "real_test"), and the error quantiles stored in the model."""

    data: dict[str, Any]
    stages: dict[str, TrainResult]
    metrics: dict[str, dict[str, Any]]
    error_quantiles: dict[str, float] | None = None
    variant: str = "pure"
    #: how the variant was chosen (``variant="auto"``: the candidates and their errors)
    selection: dict[str, Any] | None = None

    def to_meta(self) -> dict[str, Any]:
        return {"data": self.data, "training": {k: v.to_dict() for k, v in self.stages.items()},
                "metrics": self.metrics}


def _loss(model: LearnedModel, x: torch.Tensor, length: torch.Tensor, pts: torch.Tensor,
          kind: str = "sum_sq") -> torch.Tensor:
    """Mean over the batch of the loss ``kind`` per configuration (:data:`LOSSES`), mm^2."""
    pred = model.points_from_features(x, length, pts.shape[1])
    d2 = ((pred - pts) ** 2).sum(dim=2)                        # (B, m) squared distances
    if kind == "sum_sq":
        return d2.sum(dim=1).mean()
    return d2.mean(dim=1).mean() + MAX_WEIGHT * d2.amax(dim=1).mean()


def base_points(base: Any, data: ShapeData) -> np.ndarray:
    """A residual base model's backbones at the data's configurations (and directions)."""
    m = data.points.shape[1]
    if data.direction is not None and needs_direction(base):
        return base.shape(data.q, points=m, direction=data.direction).points
    return base.backbone(data.q, m)


def targets(model: LearnedModel, data: ShapeData) -> np.ndarray:
    """What the network itself must output (B, m, 3) mm, base frame: the measured points, or
    for a residual model their difference to the base model."""
    if model.base is None:
        return np.asarray(data.points, dtype=float)
    return np.asarray(data.points, dtype=float) - base_points(model.base, data)


def _tensors(model: LearnedModel, data: ShapeData) -> tuple[torch.Tensor, ...]:
    """Network inputs, tip lengths and target points of a data set, on the model's device."""
    dev = model.device
    with torch.no_grad():
        q = torch.as_tensor(data.q, dtype=torch.float32, device=dev)
        d = None if data.direction is None else torch.as_tensor(data.direction, dtype=torch.float32, device=dev)
        x = model.features(q, d)
        length = model.tip_length_t(q)
    pts = model.to_model_frame(data.q, targets(model, data))
    return x, length, torch.as_tensor(pts, dtype=torch.float32, device=dev)


def set_normalisation(model: LearnedModel, data: ShapeData) -> None:
    """Output normalisation from the least-squares basis coefficients of ``data`` (of the
    differences to the base model in residual mode)."""
    L = model.robot.tip_length(data.q)
    c = basis.fit(model.to_model_frame(data.q, targets(model, data)), L, model.terms).reshape(len(data), -1)
    mean = c.mean(axis=0)
    std = c.std(axis=0)
    std = np.maximum(std, 1e-3 * max(float(std.max()), 1e-12))
    model.coef_mean = torch.tensor(mean, dtype=torch.float32, device=model.device)
    model.coef_std = torch.tensor(std, dtype=torch.float32, device=model.device)
    model.invalidate()


def _optimiser(model: LearnedModel, cfg: TrainConfig, steps_per_epoch: int):
    """(optimiser, one-cycle scheduler stepped per batch or None, plateau scheduler stepped
    per epoch) for the trainable weights of ``model``: Adam, or AdamW with
    ``cfg.weight_decay`` > 0; the plateau scheduler is used when there is no one-cycle one."""
    params = [p for p in model.net.parameters() if p.requires_grad]
    Opt = torch.optim.AdamW if cfg.weight_decay > 0 else torch.optim.Adam
    kw = {"weight_decay": cfg.weight_decay} if cfg.weight_decay > 0 else {}
    try:
        opt = Opt(params, lr=cfg.lr, fused=True, **kw)
    except (RuntimeError, TypeError):  # pragma: no cover - older torch / unsupported device
        opt = Opt(params, lr=cfg.lr, **kw)
    cycle = None
    if cfg.schedule == "onecycle":
        cycle = torch.optim.lr_scheduler.OneCycleLR(
            opt, max_lr=cfg.lr, total_steps=cfg.epochs * steps_per_epoch, pct_start=0.05,
            div_factor=25.0, final_div_factor=400.0)
    sched = torch.optim.lr_scheduler.ReduceLROnPlateau(opt, factor=0.5, patience=max(1, cfg.patience // 3),
                                                       min_lr=cfg.min_lr)
    return opt, cycle, sched


def _train_epoch(model: LearnedModel, opt: torch.optim.Optimizer, cycle: Any,
                 data: tuple[torch.Tensor, ...], perm: torch.Tensor, bs: int, loss_kind: str) -> float:
    """One pass over the training rows ``data`` (features, tip lengths, targets) in the order
    ``perm``, batches of ``bs``; returns the summed loss (mean per batch times its rows). The
    network is left in eval mode."""
    x, length, pts = data
    model.net.train()
    tot = 0.0
    for a in range(0, len(perm), bs):
        idx = perm[a:a + bs]
        loss = _loss(model, x[idx], length[idx], pts[idx], loss_kind)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        if cycle is not None:
            cycle.step()
        tot += float(loss.detach()) * len(idx)
    model.net.eval()
    return tot


def train(model: LearnedModel, train_data: ShapeData, val_data: ShapeData,
          config: TrainConfig | None = None) -> TrainResult:
    """Fit ``model`` in place; returns a :class:`TrainResult` (epochs run, best validation
    loss, seconds, history).

    Adam on the mean per-configuration sum of squared point distances; the weights with the
    best validation loss are kept (early stopping)."""
    from ctrplan.progress import bar

    cfg = config or TrainConfig()
    torch.manual_seed(cfg.seed)
    gen = torch.Generator().manual_seed(cfg.seed)
    dev = model.device
    xtr, ltr, ptr = _tensors(model, train_data)
    xva, lva, pva = _tensors(model, val_data)
    N = len(train_data)
    bs = max(1, min(cfg.batch_size, N))
    opt, cycle, sched = _optimiser(model, cfg, math.ceil(N / bs))
    best = math.inf
    best_state = copy.deepcopy(model.net.state_dict())
    best_epoch = 0
    stale = 0
    history: list[dict] = []
    t0 = time.perf_counter()
    epoch = 0
    with bar(total=cfg.epochs, desc=cfg.label, unit="epoch") as pb:
        if not cfg.progress:
            pb.disable = True
        for epoch in range(1, cfg.epochs + 1):
            perm = torch.randperm(N, generator=gen).to(dev)
            tot = _train_epoch(model, opt, cycle, (xtr, ltr, ptr), perm, bs, cfg.loss)
            with torch.no_grad():
                val = float(_loss(model, xva, lva, pva, cfg.loss))
            if cycle is None:
                sched.step(val)
            history.append({"epoch": epoch, "train_loss": tot / N, "val_loss": val,
                                "lr": opt.param_groups[0]["lr"]})
            pb.set_postfix(val=f"{val:.3g}")
            pb.update(1)
            if val < best * (1 - 1e-4):
                best, best_epoch, stale = val, epoch, 0
                best_state = copy.deepcopy(model.net.state_dict())
            else:
                stale += 1
            if stale >= cfg.patience and cycle is None:
                break
            if cfg.max_seconds is not None and time.perf_counter() - t0 > cfg.max_seconds:
                log.info("%s: time limit reached after %d epochs", cfg.label, epoch)
                break
    model.net.load_state_dict(best_state)
    model.net.eval()
    model.invalidate()
    summary = TrainResult(epochs_run=epoch, best_epoch=best_epoch, best_val_loss_mm2=best,
                          seconds=time.perf_counter() - t0, lr=cfg.lr, batch_size=bs,
                          patience=cfg.patience, seed=cfg.seed, rows_train=N, rows_val=len(val_data),
                          history=tuple(history))
    log.info("%s: %d epochs (best %d), validation loss %.4g mm^2, %.1f s", cfg.label, epoch,
             best_epoch, best, summary.seconds)
    return summary


def new_model(robot: Robot, width: int = DEFAULT_WIDTH, depth: int = DEFAULT_DEPTH,
              terms: int = basis.DEFAULT_TERMS, seed: int = 0, device: str = "cpu",
              frame: str = DEFAULT_FRAME, direction: bool = False, base: Any = None,
              pairs: bool = False) -> LearnedModel:
    """A fresh network; with ``base`` a residual model whose last layer starts at zero (it
    starts as the base model plus the mean difference once normalised); ``pairs``: pair
    inputs (:func:`ctrplan.shape.learned.pair_list`)."""
    spec = None if base is None else base_model_spec(base)
    if isinstance(base, LearnedModel):
        base = copy.deepcopy(base)
        base.invalidate()
        base.net.requires_grad_(False)
    m = LearnedModel(robot, width=width, depth=depth, terms=terms, seed=seed, device=device,
                     frame=frame, direction=direction, base=base, base_spec=spec, pairs=pairs)
    if base is not None:
        with torch.no_grad():
            last = m.net.net[-1]
            last.weight.zero_()
            last.bias.zero_()
    return m


def with_direction_inputs(model: LearnedModel) -> LearnedModel:
    """A copy of a trained model with direction inputs added (zero weights on them: the
    same outputs until fine-tuned)."""
    if model.direction_inputs:
        return copy.deepcopy(model)
    new = LearnedModel(model.robot, width=model.width, depth=model.depth, terms=model.terms,
                       seed=None, frame=model.frame, direction=True, base=copy.deepcopy(model.base),
                       base_spec=model.base_spec, pairs=model.pair_inputs)
    state = {k: v.clone() for k, v in model.net.state_dict().items()}
    W0 = state["net.0.weight"]
    extra = new.net.net[0].weight.shape[1] - W0.shape[1]
    state["net.0.weight"] = torch.cat([W0, torch.zeros(W0.shape[0], extra, dtype=W0.dtype)], dim=1)
    new.net.load_state_dict(state)
    new.coef_mean, new.coef_std = model.coef_mean.clone(), model.coef_std.clone()
    new.meta = copy.deepcopy(model.meta)
    new.to(model.device)
    new.invalidate()
    return new


# ---------------------------------------------------------------------------------- evaluation
def shape_errors(pred: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Point distances (B, m), mm."""
    return np.linalg.norm(np.asarray(pred) - np.asarray(true), axis=2)


def evaluate(model: Any, data: ShapeData) -> dict[str, Any]:
    """Metrics over a test set, at the data's points (20 evenly spaced in the literature):

    max_dev (max distance along the shaft), mse (mean squared distance), sum_dev (sum of
    distances), each as mean and std over configurations (mm, mm^2, mm); per_position (mean
    distance at each point) and per_config_max (the max deviation of every configuration).
    Direction-aware models get the data's directions."""
    m = data.points.shape[1]
    if needs_direction(model) and data.direction is not None:
        pred = model.shape(data.q, m, direction=data.direction).points
    else:
        pred = model.backbone(data.q, m)
    d = shape_errors(pred, data.points)
    mx, mse, sm = d.max(axis=1), (d ** 2).mean(axis=1), d.sum(axis=1)
    good = np.isfinite(mx)
    return {
        "n": int(good.sum()),
        "max_dev_mean": float(mx[good].mean()), "max_dev_std": float(mx[good].std()),
        "mse_mean": float(mse[good].mean()), "mse_std": float(mse[good].std()),
        "sum_dev_mean": float(sm[good].mean()), "sum_dev_std": float(sm[good].std()),
        "tip_mean": float(d[good, -1].mean()),
        "per_position": d[good].mean(axis=0).tolist(),
        "per_config_max": mx.tolist(),
    }


def summary_metrics(m: dict[str, Any]) -> dict[str, Any]:
    """The scalar part of :func:`evaluate`'s result."""
    return {k: v for k, v in m.items() if k not in ("per_position", "per_config_max")}


def basis_fit_table(robot: Robot | str, n: int = 5000, seed: int = 11, points: int = 20,
                    terms: Sequence[int] = range(3, 9)) -> list[dict]:
    """Least-squares basis fit accuracy on simulated shapes (max deviation over ``points``)."""
    robot = load_robot(robot)
    q = robot.sample(n, seed=seed)
    sh = PhysicsModel(robot).shape(q, points)
    return basis.fit_report(sh.points[sh.ok], robot.tip_length(q[sh.ok]), terms)


# ---------------------------------------------------------------------------------- workflows
#: Model variants: pure (configuration in, shape out), direction-aware inputs, residual mode
#: (the network learns the difference to a base model) and both.
VARIANTS = ("pure", "direction", "residual", "residual+direction")


def fit_real(robot: Robot, r_tr: ShapeData, r_va: ShapeData, variant: str = "pure",
             sim_model: LearnedModel | None = None, residual_base: Any = None,
             width: int = DEFAULT_WIDTH, depth: int = DEFAULT_DEPTH, terms: int = basis.DEFAULT_TERMS,
             seed: int = 0, frame: str = DEFAULT_FRAME, device: str = "cpu",
             fine: TrainConfig | None = None, real_only: TrainConfig | None = None,
             refit: bool = False) -> tuple[LearnedModel, TrainResult]:
    """Train one variant on measured data (train / validation parts).

    ``refit``: after early stopping on the validation part has chosen the number of epochs,
    train the variant again from the same start on train + validation for that many epochs
    (all the measured data; the returned result is the refit's).

    * pure / direction with ``sim_model``: fine-tune a copy of it (Sim+Real; direction inputs
      added with zero weights), with ``fine``;
    * pure / direction without: a new network trained on the measured data (Real-only);
    * residual[+direction]: a new network for the difference to ``residual_base`` (default: the
      ``sim_model`` if given - Sim+Real residual, no physics call - else the physics model),
      with ``real_only`` (the network starts at the base plus the mean difference).
    """
    if variant not in VARIANTS:
        raise ValueError(f"variant must be one of {VARIANTS}, got {variant!r}")
    if refit:
        kw = dict(sim_model=sim_model, residual_base=residual_base, width=width, depth=depth,
                  terms=terms, seed=seed, frame=frame, device=device)
        _, first = fit_real(robot, r_tr, r_va, variant, fine=fine, real_only=real_only, **kw)
        both = _concat(r_tr, r_va)
        n_ep = max(1, first.best_epoch)

        def again(c: TrainConfig | None) -> TrainConfig | None:
            return None if c is None else c.replace(epochs=n_ep, patience=n_ep + 1, max_seconds=None)
        fine2 = again(fine or TrainConfig(seed=seed, lr=5e-4, batch_size=128, label="fine-tune (real)"))
        real2 = again(real_only or TrainConfig(seed=seed, batch_size=128, label="train (real)"))
        return fit_real(robot, both, both, variant, fine=fine2, real_only=real2, **kw)
    direction = variant.endswith("direction")
    fine = fine or TrainConfig(seed=seed, lr=5e-4, batch_size=128, label="fine-tune (real)")
    real_only = real_only or TrainConfig(seed=seed, batch_size=128, label="train (real)")
    if variant.startswith("residual"):
        if residual_base is None:
            from ctrplan.shape.physics import PhysicsModel

            residual_base = sim_model if sim_model is not None else PhysicsModel(robot)
        pairs = False
        if isinstance(residual_base, LearnedModel):      # same inputs: one pass for both
            terms, frame, pairs = residual_base.terms, residual_base.frame, residual_base.pair_inputs
        model = new_model(robot, width, depth, terms, seed, device, frame, direction=direction,
                          base=residual_base, pairs=pairs)
        set_normalisation(model, r_tr)
        return model, train(model, r_tr, r_va, real_only)
    if sim_model is not None:
        model = with_direction_inputs(sim_model) if direction else copy.deepcopy(sim_model)
        model.invalidate()
        return model, train(model, r_tr, r_va, fine)
    model = new_model(robot, width, depth, terms, seed, device, frame, direction=direction)
    set_normalisation(model, r_tr)
    return model, train(model, r_tr, r_va, real_only)


def predict(model: Any, data: ShapeData) -> np.ndarray:
    """A model's backbones (B, m, 3) at the data's configurations, at the data's m points
    (direction-aware models get the data's directions)."""
    m = data.points.shape[1]
    if needs_direction(model) and data.direction is not None:
        return model.shape(data.q, m, direction=data.direction).points
    return model.backbone(data.q, m)


def error_profile(deviation: np.ndarray) -> dict[str, list[float]]:
    """The ``error_profile`` of the model files (docs/conventions.md) from point deviations
    (B, m) mm at m points evenly spaced in arc length from base (fraction 0) to tip (1)."""
    from ctrplan.shape.error_bounds import profile_from_deviations

    return profile_from_deviations(deviation).to_dict()


def finish(model: LearnedModel, seen: ShapeData, test: ShapeData, label: str,
           profile: bool = True) -> dict[str, float]:
    """Store the training domain, the error quantiles of the max deviation along the shaft on
    the held-out ``test`` data and (``profile``: shapes measured) its ``error_profile`` per
    arc-length fraction in the model. Domain: the joint ranges of ``seen``; for simulated data
    (uniform over the robot's joint limits, ``label == "sim"``) the robot's limits themselves."""
    model.set_domain(seen.q, source=label)
    if label == "sim":
        lo, hi = model.robot.beta_bounds()
        model.domain.update(beta_min_mm=lo.tolist(), beta_max_mm=hi.tolist(), alpha_arcs_rad=[None] * model.robot.n,
                            source="sim: uniform over the robot's joint limits")
    dev = shape_errors(predict(model, test), test.points)
    # measured rows give a calibrated bound; simulated ones the surrogate's error
    eq = model.set_error_quantiles(dev.max(axis=1), kind="measured" if test.measured else "surrogate")
    part = f"held-out test split ({split_kind(test)})"
    model.meta["error_quantiles_source"] = {
        "data": test.source, "part": part, **_part(test),
        "metric": "max deviation along the shaft per configuration, mm"}
    model.error_profile = None
    model.meta.pop("error_profile_source", None)
    if profile and test.points.shape[1] >= 2:
        model.error_profile = error_profile(dev)
        model.meta["error_profile_source"] = {
            "data": test.source, "part": part, **_part(test),
            "metric": "distance of the backbone point at each arc-length fraction, mm"}
    return eq


def _concat(a: ShapeData, b: ShapeData) -> ShapeData:
    def cat(x, y):
        return None if x is None or y is None else np.concatenate([x, y])
    return ShapeData(np.concatenate([a.q, b.q]), np.concatenate([a.points, b.points]), a.source,
                     cat(a.direction, b.direction), cat(a.sweep, b.sweep), a.measured and b.measured)


#: ``variant="auto"``: train the candidate variants and keep the best on the validation sweeps
AUTO = "auto"
SELECTION_METRIC = ("mean over the validation rows (whole sweeps, or blocks of a continuous "
                    "recording, by the one held-out splitter; not used to fit the weights) of "
                    "the max deviation along the shaft, mm")


def has_motion(data: ShapeData) -> bool:
    """True when the data carry directions of motion with at least one reversal: some joint
    whose last motion changes sign between consecutive rows of the same sweep (back and
    forth motion, where friction / hysteresis can show)."""
    d = data.direction
    if d is None or len(d) < 2:
        return False
    d = np.asarray(d, dtype=float)
    flip = (d[1:] * d[:-1]) < 0
    if data.sweep is not None:
        sw = np.asarray(data.sweep)
        flip &= (sw[1:] == sw[:-1])[:, None]
    return bool(flip.any())


def candidate_variants(data: ShapeData) -> list[str]:
    """The variants ``variant="auto"`` compares: all four when the data has motion with
    reversals (:func:`has_motion`), else pure and residual."""
    return list(VARIANTS) if has_motion(data) else ["pure", "residual"]


def _base_name(variant: str, sim_model: Any, residual_base: Any) -> str:
    if not variant.startswith("residual"):
        return "-"
    base = residual_base if residual_base is not None else sim_model
    if base is None:
        return "physics"
    if isinstance(base, LearnedModel):
        return "learned (sim model)" if base is sim_model else "learned"
    return str(getattr(base, "name", type(base).__name__))


def _check_candidates(cands: list[str], r_tr: ShapeData) -> list[str]:
    """``cands`` after checking each is a variant the training data can train (ValueError)."""
    if not cands:
        raise ValueError("no candidate variants")
    for v in cands:
        if v not in VARIANTS:
            raise ValueError(f"variant must be one of {VARIANTS}, got {v!r}")
        if v.endswith("direction") and r_tr.direction is None:
            raise ValueError("a direction-aware variant needs measured data with directions")
    return cands


def _screen(robot: Robot, r_tr: ShapeData, r_va: ShapeData, cands: list[str],
            stage: Callable[[str], TrainConfig], fine: TrainConfig, real_only: TrainConfig,
            kw: dict[str, Any]) -> tuple[list[dict[str, Any]], dict[str, tuple[LearnedModel, TrainResult]]]:
    """Train each candidate variant with its stage's (``stage(v)``) epochs divided by the
    number of candidates (``kw``: the :func:`fit_real` arguments). Returns (one table row per
    candidate with its validation error, variant -> (model, TrainResult))."""
    rows: list[dict[str, Any]] = []
    models: dict[str, tuple[LearnedModel, TrainResult]] = {}
    for v in cands:
        budget = stage(v).epochs
        screen = max(1, budget // len(cands))
        model, res = fit_real(robot, r_tr, r_va, v,
                              fine=fine.replace(epochs=screen, label=f"{fine.label} [{v}]"),
                              real_only=real_only.replace(epochs=screen, label=f"{real_only.label} [{v}]"),
                              **kw)
        ev = evaluate(model, r_va)
        models[v] = (model, res)
        rows.append({"variant": v, "residual_base": _base_name(v, kw["sim_model"], kw["residual_base"]),
                     "screen_epochs": res.epochs_run, "val_max_dev_mean_mm": ev["max_dev_mean"],
                     "val_rows": ev["n"]})
        log.info("variant %-18s validation max deviation %.3f mm (%d epochs)", v, ev["max_dev_mean"],
                 res.epochs_run)
    return rows, models


def _selection_record(rows: list[dict[str, Any]], models: dict[str, tuple[LearnedModel, TrainResult]],
                      model: LearnedModel, chosen: str, r_va: ShapeData, r_te: ShapeData | None,
                      refit: bool) -> dict[str, Any]:
    """The selection record of :func:`select_variant` (metadata ``selection``): the rows
    marked with the choice and, with a test part ``r_te``, each candidate's test error (the
    chosen one's final ``model``)."""
    for r in rows:
        r["chosen"] = r["variant"] == chosen
        if r_te is not None:
            m = model if r["chosen"] else models[r["variant"]][0]
            r["test_max_dev_mean_mm"] = evaluate(m, r_te)["max_dev_mean"]
    return {"mode": AUTO, "chosen": chosen, "by": SELECTION_METRIC,
            "final_val_max_dev_mean_mm": evaluate(model, r_va)["max_dev_mean"],
            "validation": _part(r_va), "test": None if r_te is None else _part(r_te),
            "budget": "each candidate screened with 1/len(candidates) of its stage's epochs, "
                      "the winner trained on for the rest" + (" and refitted" if refit else ""),
            "candidates": rows,
            "test_note": "test errors (the held-out test part) are listed for information "
                         "only; they did not take part in the choice"}


def select_variant(robot: Robot, r_tr: ShapeData, r_va: ShapeData, r_te: ShapeData | None = None,
                   candidates: Sequence[str] | None = None, sim_model: LearnedModel | None = None,
                   residual_base: Any = None, width: int = DEFAULT_WIDTH, depth: int = DEFAULT_DEPTH,
                   terms: int = basis.DEFAULT_TERMS, seed: int = 0, frame: str = DEFAULT_FRAME,
                   device: str = "cpu", fine: TrainConfig | None = None,
                   real_only: TrainConfig | None = None,
                   refit: bool = False) -> tuple[LearnedModel, TrainResult, dict[str, Any]]:
    """Train the candidate variants on ``r_tr`` and keep the one with the lowest mean max
    deviation on the validation part ``r_va`` (:data:`SELECTION_METRIC`).

    Budget: each candidate is screened with its stage's epochs divided by the number of
    candidates (early stopping on ``r_va``), then the winner goes on training for the rest
    of its epochs (kept only where that lowers its validation error); with ``refit`` the
    winner is trained again by :func:`fit_real` with ``refit=True``. Residual candidates use
    ``residual_base`` (default: physics). ``r_te`` (optional) is only evaluated for the table,
    never used for the choice. Returns (model, the winner's last TrainResult, selection
    record: candidates with their validation (and test) errors, the choice and the rule)."""
    from ctrplan.shape.physics import PhysicsModel

    cands = _check_candidates(list(candidates) if candidates is not None else candidate_variants(r_tr),
                              r_tr)
    if residual_base is None and any(v.startswith("residual") for v in cands):
        residual_base = PhysicsModel(robot)
    fine = fine or TrainConfig(seed=seed, lr=5e-4, batch_size=128, label="fine-tune (real)")
    real_only = real_only or TrainConfig(seed=seed, batch_size=128, label="train (real)")

    def stage(v: str) -> TrainConfig:
        return fine if (sim_model is not None and not v.startswith("residual")) else real_only

    kw = dict(sim_model=sim_model, residual_base=residual_base, width=width, depth=depth,
              terms=terms, seed=seed, frame=frame, device=device)
    rows, models = _screen(robot, r_tr, r_va, cands, stage, fine, real_only, kw)
    best = min(rows, key=lambda r: r["val_max_dev_mean_mm"])
    chosen = best["variant"]
    model, res = models[chosen]
    cfg = stage(chosen)
    if refit:
        model, res = fit_real(robot, r_tr, r_va, chosen, fine=fine, real_only=real_only, refit=True, **kw)
    elif cfg.epochs > res.epochs_run:
        more = copy.deepcopy(model)
        res2 = train(more, r_tr, r_va, cfg.replace(epochs=cfg.epochs - res.epochs_run,
                                                   label=f"{cfg.label} [{chosen}, continued]"))
        if evaluate(more, r_va)["max_dev_mean"] < best["val_max_dev_mean_mm"]:
            model, res = more, res2
            models[chosen] = (model, res)
    selection = _selection_record(rows, models, model, chosen, r_va, r_te, refit)
    log.info("chose variant %s (validation max deviation %.3f mm; candidates: %s)", chosen,
             best["val_max_dev_mean_mm"],
             ", ".join(f"{r['variant']} {r['val_max_dev_mean_mm']:.3f}" for r in rows))
    return model, res, selection


def _part(data: ShapeData) -> dict[str, Any]:
    """Rows and (when known) the sweep ids of a split part, for the metadata."""
    out: dict[str, Any] = {"rows": len(data)}
    if data.sweep is not None:
        out["sweeps"] = sorted({str(x) for x in np.asarray(data.sweep).tolist()})
    return out


def selection_markdown(selection: dict[str, Any]) -> str:
    """The candidate table of an automatic variant choice as markdown."""
    rows = selection.get("candidates", [])
    has_test = any("test_max_dev_mean_mm" in r for r in rows)
    lines = [f"# Variant selection: `{selection.get('chosen')}`", "",
             f"Chosen by: {selection.get('by', '')}.", ""]
    head = "| variant | residual base | validation max deviation (mm) |"
    sep = "|---|---|---|"
    if has_test:
        head += " test max deviation (mm, not used for the choice) |"
        sep += "---|"
    lines += [head + " chosen |", sep + "---|"]
    for r in rows:
        line = f"| {r['variant']} | {r['residual_base']} | {r['val_max_dev_mean_mm']:.3f} |"
        if has_test:
            t = r.get("test_max_dev_mean_mm")
            line += f" {t:.3f} |" if t is not None else " - |"
        lines.append(line + (" yes |" if r.get("chosen") else " |"))
    return "\n".join(lines) + "\n"


def _pretrain(robot: Robot, sim: ShapeData, start: LearnedModel | None, pre: TrainConfig | None,
              arch: tuple[int, int], terms: int, seed: int, device: str, frame: str,
              sim_base: str | None, sim_pairs: bool) -> tuple[LearnedModel, TrainResult, tuple]:
    """Pre-train ``start`` (default: a new network of ``arch`` (width, depth) over
    ``sim_base``) on the simulated data's train / validation parts. Returns (the model, its
    TrainResult, (train + validation, test part, "sim")) - what its error quantiles come from."""
    s_tr, s_va, s_te = split(sim, seed=seed)
    if start is None:
        sw, sd = arch
        start = new_model(robot, sw, sd, terms, seed, device, frame,
                          base=sim_base_model(robot, sim_base), pairs=sim_pairs)
        if sim_base is not None:
            start.meta["sim_base"] = sim_base
        set_normalisation(start, s_tr)
    pre = pre or TrainConfig(seed=seed, label="pre-train (sim)")
    return start, train(start, s_tr, s_va, pre), (_concat(s_tr, s_va), s_te, "sim")


def _train_real(robot: Robot, real: ShapeData, start: LearnedModel | None, variant: str,
                candidates: Sequence[str] | None, residual_base: Any, fine: TrainConfig | None,
                real_only: TrainConfig | None, refit: bool, kw: dict[str, Any]):
    """Train ``variant`` (or choose one: :data:`AUTO`) on the measured data's train /
    validation parts, from the pre-trained ``start`` where the variant fine-tunes (``kw``:
    width, depth, terms, seed, frame, device). Returns (model, the variant trained, the
    selection record, the stage name, its TrainResult, (train + validation, test part,
    "real"))."""
    r_tr, r_va, r_te = split(real, seed=kw["seed"] + 1)
    if variant.endswith("direction") and real.direction is None:
        raise ValueError("a direction-aware variant needs measured data with directions")
    if variant == AUTO:
        model, res, selection = select_variant(
            robot, r_tr, r_va, r_te, candidates=candidates, sim_model=start,
            residual_base=residual_base, fine=fine, real_only=real_only, refit=refit, **kw)
        variant = selection["chosen"]
    else:
        selection = {"mode": "explicit", "chosen": variant,
                     "by": "given by the caller (no comparison)"}
        model, res = fit_real(robot, r_tr, r_va, variant, sim_model=start, residual_base=residual_base,
                              fine=fine, real_only=real_only, refit=refit, **kw)
    stage = "finetune" if (start is not None and not variant.startswith("residual")) else "real"
    return model, variant, selection, stage, res, (_concat(r_tr, r_va), r_te, "real")


def pretrain_finetune(robot: Robot | str, sim: ShapeData | None, real: ShapeData | None,
                      width: int = DEFAULT_WIDTH, depth: int = DEFAULT_DEPTH,
                      terms: int = basis.DEFAULT_TERMS, seed: int = 0,
                      pre: TrainConfig | None = None, fine: TrainConfig | None = None,
                      device: str = "cpu", base: LearnedModel | None = None,
                      frame: str = DEFAULT_FRAME, variant: str = "pure",
                      residual_base: Any = None, real_only: TrainConfig | None = None,
                      refit: bool = False,
                      candidates: Sequence[str] | None = None, sim_base: str | None = None,
                      sim_arch: tuple[int, int] | None = None,
                      sim_pairs: bool = False) -> tuple[LearnedModel, TrainReport]:
    """Pre-train on ``sim`` (if given), then train ``variant`` on ``real`` (if given).

    ``variant="auto"``: train the ``candidates`` (default :func:`candidate_variants`; residual
    ones over ``residual_base``, default physics) and keep the best on the validation part
    (:func:`select_variant`); the table is stored in the metadata under ``selection``.

    Each data set is split 80/10/10 (seeded; by :func:`split`: measured data by whole sweeps
    or blocks with gaps);
    validation drives early stopping, the test parts are evaluated and stored in the metadata,
    with the error quantiles and the training domain of the last data set trained on.
    ``base``: start from this trained model instead of pre-training (its normalisation is
    kept). ``residual_base``: the base of a residual variant (default: the pre-trained model,
    else physics). ``fine``: fine-tuning settings; ``real_only``: for new networks trained on
    ``real`` (default ``fine`` when nothing was pre-trained). ``refit``: see :func:`fit_real`.
    ``sim_base``: what the network pre-trained on ``sim`` adds to (:func:`sim_base_model`:
    ``"rigid"``, the closed-form rigid model, or None); ``sim_arch``: its (width, depth)
    (default ``width``, ``depth``, which also size the networks trained on ``real`` alone);
    ``sim_pairs``: its pair inputs (:func:`ctrplan.shape.learned.pair_list`).
    """
    robot = load_robot(robot)
    if variant not in VARIANTS and variant != AUTO:
        raise ValueError(f"variant must be one of {VARIANTS} or {AUTO!r}, got {variant!r}")
    if variant == AUTO and real is None:
        variant = "pure"                          # nothing to choose with: simulation only
    if sim is None and real is None:
        raise ValueError("need simulated and/or measured data")
    data: dict[str, Any] = {}
    stages: dict[str, TrainResult] = {}
    metrics: dict[str, dict[str, Any]] = {}
    selection: dict[str, Any] | None = None
    start: LearnedModel | None = None
    if base is not None:
        start = copy.deepcopy(base)
        start.invalidate()
        data["init"] = dict(getattr(base, "meta", {}).get("data", {}))
    model: LearnedModel | None = start
    if sim is not None:
        start, stages["pretrain"], eq_data = _pretrain(
            robot, sim, start, pre, sim_arch if sim_arch is not None else (width, depth), terms,
            seed, device, frame, sim_base, sim_pairs)
        data["sim"] = sim.describe()
        metrics["sim_test"] = summary_metrics(evaluate(start, eq_data[1]))
        model = start
    if real is not None:
        model, variant, selection, stage, res, eq_data = _train_real(
            robot, real, start, variant, candidates, residual_base, fine,
            real_only or (fine if start is None else None), refit,
            dict(width=width, depth=depth, terms=terms, seed=seed, frame=frame, device=device))
        stages[stage] = res
        data["real"] = real.describe()
        metrics["real_test"] = summary_metrics(evaluate(model, eq_data[1]))
    elif variant != "pure":
        raise ValueError(f"variant {variant!r} needs measured data")
    assert model is not None
    eq = finish(model, eq_data[0], eq_data[1], eq_data[2])
    report = TrainReport(data=data, stages=stages, metrics=metrics, error_quantiles=eq, variant=variant,
                         selection=selection)
    model.meta.update(report.to_meta())
    model.meta["variant"] = variant
    if selection is not None:
        model.meta["selection"] = selection
    return model, report


def sim_base_model(robot: Robot, kind: str | None) -> Any:
    """The base a network pre-trained on simulation adds to: ``"rigid"`` the closed-form
    torsionally rigid model (:class:`~ctrplan.shape.rigid.RigidModel`), None / ``"none"``
    nothing (the network predicts the whole backbone)."""
    if kind in (None, "none"):
        return None
    if kind == "rigid":
        from ctrplan.shape.rigid import RigidModel

        return RigidModel(robot)
    raise ValueError(f"sim_base must be 'rigid' or 'none', got {kind!r}")


# ---------------------------------------------------------------------------------- sweep
def parse_archs(text: str) -> list[tuple[int, int]]:
    """``"3x15,5x30"`` -> [(depth, width), ...] (depth hidden layers of width neurons)."""
    out = []
    for part in str(text).split(","):
        part = part.strip().lower()
        if not part:
            continue
        d, _, w = part.partition("x")
        if not (d.isdigit() and w.isdigit()) or int(d) < 1 or int(w) < 1:
            raise ValueError(f"architecture {part!r} is not DEPTHxWIDTH (e.g. 3x30)")
        out.append((int(d), int(w)))
    if not out:
        raise ValueError("no architectures given")
    return out


@dataclass(frozen=True)
class SweepResult:
    """What :func:`sweep` measured: settings, data descriptions and splits, the physics model's
    metrics on the held-out real data (``physics``) and on held-out simulation, and one entry
    per trained model in ``runs`` (regime, variant, residual_base, arch, seconds, epochs and the
    :func:`evaluate` metrics with per-configuration errors). ``to_dict()`` is results.json."""

    robot: str
    terms: int
    frame: str
    seed: int
    variants: list[str]
    refit: bool
    data: dict[str, Any]
    physics: dict[str, Any]
    physics_sim_test: dict[str, Any]
    runs: list[dict[str, Any]]
    seconds: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def _as_dict(res: SweepResult | dict[str, Any]) -> dict[str, Any]:
    return res.to_dict() if isinstance(res, SweepResult) else res


ALL_ARCHS = [(d, w) for d in ARCH_DEPTHS for w in ARCH_WIDTHS]
REGIMES = ("Sim-only", "Real-only", "Sim+Real")


def sweep(robot: Robot | str, sim: ShapeData, real: ShapeData,
          archs: Sequence[tuple[int, int]] = tuple(ALL_ARCHS), terms: int = basis.DEFAULT_TERMS,
          frame: str = DEFAULT_FRAME, seed: int = 0, pre: TrainConfig | None = None,
          fine: TrainConfig | None = None, real_only: TrainConfig | None = None,
          device: str = "cpu", progress: bool = True,
          variants: Sequence[str] = VARIANTS, refit: bool = False) -> SweepResult:
    """Sim-only, and Real-only and Sim+Real for each variant (pure, direction-aware, residual,
    residual + direction), for each architecture, all evaluated on the same held-out part of
    ``real`` (:func:`split`: whole sweeps, or blocks with gaps), next to the physics model. Residual
    variants: Real-only learns the difference to physics, Sim+Real the difference to the
    Sim-only model. Returns a :class:`SweepResult` (per-configuration errors for the plots)."""
    from ctrplan.shape.physics import PhysicsModel

    robot = load_robot(robot)
    for v in variants:
        if v not in VARIANTS:
            raise ValueError(f"unknown variant {v!r} (one of {', '.join(VARIANTS)})")
    if real.direction is None and any(v.endswith("direction") for v in variants):
        real = real.with_direction_from_rows()
    s_tr, s_va, s_te = split(sim, seed=seed)
    r_tr, r_va, r_te = split(real, seed=seed + 1)

    def cfg(base: TrainConfig | None, label: str, **kw) -> TrainConfig:
        c = base if base is not None else TrainConfig(**kw)
        return c.replace(label=label, progress=progress)

    phys = PhysicsModel(robot)
    res: dict[str, Any] = {
        "robot": robot.name, "terms": terms, "frame": frame, "seed": seed,
        "variants": list(variants), "refit": refit,
        "data": {"sim": sim.describe(), "real": real.describe(),
                 "splits": {"sim": [len(s_tr), len(s_va), len(s_te)],
                            "real": [len(r_tr), len(r_va), len(r_te)]},
                 "real_split_by": {"whole sweeps": "sweep", "contiguous blocks": "contiguous block",
                                   "rows": "row"}[split_kind(r_te)]},
        "physics": evaluate(phys, r_te), "physics_sim_test": summary_metrics(evaluate(phys, s_te)),
        "runs": [],
    }
    for depth, width in archs:
        tag = f"{depth}x{width}"
        sim_model = new_model(robot, width, depth, terms, seed, device, frame)
        set_normalisation(sim_model, s_tr)
        t_sim = train(sim_model, s_tr, s_va, cfg(pre, f"{tag} sim", seed=seed))
        runs = [("Sim-only", "pure", sim_model, [t_sim])]
        for variant in variants:
            for regime, start in (("Real-only", None), ("Sim+Real", sim_model)):
                model, t = fit_real(robot, r_tr, r_va, variant, sim_model=start, width=width,
                                    depth=depth, terms=terms, seed=seed, frame=frame, device=device,
                                    fine=cfg(fine, f"{tag} {regime} {variant}", seed=seed, lr=5e-4),
                                    real_only=cfg(real_only, f"{tag} {regime} {variant}", seed=seed),
                                    refit=refit)
                runs.append((regime, variant, model, [t_sim, t] if start is not None else [t]))
        for regime, variant, model, tinfo in runs:
            ev = evaluate(model, r_te)
            base = ("-" if not variant.startswith("residual")
                    else ("physics" if regime == "Real-only" else "Sim-only model"))
            run = {"regime": regime, "variant": variant, "residual_base": base,
                   "name": f"{regime} {variant}", "depth": depth, "width": width, "arch": tag,
                   "seconds": float(sum(t.seconds for t in tinfo)),
                   "epochs": [t.epochs_run for t in tinfo], **ev}
            if regime == "Sim-only":
                run["sim_test"] = summary_metrics(evaluate(model, s_te))
            res["runs"].append(run)
            log.info("sweep %s %-9s %-18s max dev %.3f +- %.3f mm", tag, regime, variant,
                     ev["max_dev_mean"], ev["max_dev_std"])
    return SweepResult(**res)


def _pm(m: dict, key: str, fmt: str = ".3f") -> str:
    return f"{m[key + '_mean']:{fmt}} ± {m[key + '_std']:{fmt}}"


def sweep_markdown(res: SweepResult | dict[str, Any]) -> str:
    """The sweep's tables as markdown."""
    res = _as_dict(res)
    ph = res["physics"]
    d = res["data"]
    lines = [
        f"# Learned shape model: evaluation on robot `{res['robot']}`",
        "",
        f"Test set: {ph['n']} held-out \"real\" configurations ({d['real']['source']}; "
        f"held out by {d.get('real_split_by', 'row')}); metrics at "
        f"{len(ph['per_position'])} points evenly spaced along the shaft, mean ± std over the test set. "
        f"Basis terms K = {res['terms']}, frame `{res['frame']}`. Simulation: {d['sim']['rows']} rows "
        f"(split {d['splits']['sim']}), real: {d['real']['rows']} rows (split {d['splits']['real']}).",
        "",
        "Variants: pure (configuration in); direction (+ sign of the last motion of each joint, "
        "from row order within a sweep); residual (the network learns the difference to a base "
        "model: physics for Real-only, the Sim-only model for Sim+Real).",
        "",
        "| model | training | variant | residual base | arch (depth x width) | max deviation (mm) | MSE (mm²) | sum of deviations (mm) | tip error (mm) |",
        "|---|---|---|---|---|---|---|---|---|",
        f"| physics (compliant) | - | - | - | - | {_pm(ph, 'max_dev')} | {_pm(ph, 'mse')} | {_pm(ph, 'sum_dev', '.2f')} | {ph['tip_mean']:.3f} |",
    ]
    for r in res["runs"]:
        lines.append(f"| learned | {r['regime']} | {r.get('variant', 'pure')} | {r.get('residual_base', '-')} | "
                     f"{r['arch']} | {_pm(r, 'max_dev')} | {_pm(r, 'mse')} | "
                     f"{_pm(r, 'sum_dev', '.2f')} | {r['tip_mean']:.3f} |")
    best = best_runs(res)
    lines += ["", "Best architecture per training regime and variant (by mean max deviation):", ""]
    for regime, r in best.items():
        gain = 100.0 * (1.0 - r["max_dev_mean"] / ph["max_dev_mean"])
        lines.append(f"- {regime}: {r['arch']}, {r['max_dev_mean']:.3f} ± {r['max_dev_std']:.3f} mm "
                     f"({gain:+.1f}% vs physics {ph['max_dev_mean']:.3f} mm)")
    sims = [r for r in res["runs"] if r["regime"] == "Sim-only" and "sim_test" in r]
    if sims:
        ps = res["physics_sim_test"]
        lines += ["", "Sim-only models on held-out *simulated* data (the physics model is exact there "
                      f"up to solver tolerance: {ps['max_dev_mean']:.2g} mm):", "",
                  "| arch | max deviation (mm) | MSE (mm²) | sum of deviations (mm) |", "|---|---|---|---|"]
        for r in sims:
            st = r["sim_test"]
            lines.append(f"| {r['arch']} | {_pm(st, 'max_dev')} | {_pm(st, 'mse', '.4f')} | {_pm(st, 'sum_dev', '.2f')} |")
    lines += ["", "Plots: `hist_max_error.png` (per-configuration max error, learned vs physics), "
                  "`error_vs_position.png` (mean error along the shaft).", ""]
    return "\n".join(lines)


def best_runs(res: SweepResult | dict[str, Any]) -> dict[str, dict]:
    """The best architecture per "regime variant" (e.g. "Sim+Real direction")."""
    res = _as_dict(res)
    best: dict[str, dict] = {}
    for r in res["runs"]:
        key = r.get("name", r["regime"])
        if key not in best or r["max_dev_mean"] < best[key]["max_dev_mean"]:
            best[key] = r
    return best


def sweep_plots(res: SweepResult | dict[str, Any], out_dir: str | Path) -> list[Path]:
    """hist_max_error.png and error_vs_position.png for the best architecture per regime."""
    res = _as_dict(res)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ctrplan.io import save_figure

    out_dir = Path(out_dir)
    best = best_runs(res)
    ph = res["physics"]
    series = [("physics", ph)] + [(f"{k} ({v['arch']})", v) for k, v in best.items()]
    paths = []
    fig, ax = plt.subplots(figsize=(7, 4.2))
    allv = np.concatenate([np.asarray(s["per_config_max"]) for _, s in series])
    bins = np.linspace(0, float(np.nanpercentile(allv, 99.5)) * 1.05 + 1e-9, 40)
    for name, s in series:
        ax.hist(np.clip(s["per_config_max"], 0, bins[-1]), bins=bins, histtype="step", linewidth=1.6,
                label=f"{name}: {s['max_dev_mean']:.2f} mm")
    ax.set_xlabel("max deviation along the shaft per configuration (mm)")
    ax.set_ylabel("configurations")
    ax.set_title(f"{res['robot']}: learned vs physics on held-out real data")
    ax.legend(fontsize=8)
    paths.append(out_dir / "hist_max_error.png")
    save_figure(fig, paths[-1], dpi=110)
    fig, ax = plt.subplots(figsize=(7, 4.2))
    for name, s in series:
        pp = np.asarray(s["per_position"])
        ax.plot(np.linspace(0, 1, len(pp)), pp, marker="o", markersize=3, label=name)
    ax.set_xlabel("position along the shaft (s / tip arc length)")
    ax.set_ylabel("mean distance to measured point (mm)")
    ax.set_title("error vs position along the shaft")
    ax.legend(fontsize=8)
    paths.append(out_dir / "error_vs_position.png")
    save_figure(fig, paths[-1], dpi=110)
    return paths


def write_sweep(res: SweepResult | dict[str, Any], out_dir: str | Path) -> list[Path]:
    """results.json, results.md and the PNG plots under ``out_dir``."""
    res = _as_dict(res)
    from ctrplan.io import jsonable, write_json_atomic, write_text_atomic

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json_atomic(out_dir / "results.json", jsonable(res))
    write_text_atomic(out_dir / "results.md", sweep_markdown(res))
    return [out_dir / "results.json", out_dir / "results.md"] + sweep_plots(res, out_dir)
