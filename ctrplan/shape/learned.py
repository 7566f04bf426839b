"""Learned full-shape model: configuration -> polynomial backbone coefficients (torch MLP).

Network (one per robot):

* input, per tube i: ``cos alpha_i, sin alpha_i, beta_i~`` with ``beta_i~`` the translation
  scaled to [-1, 1] over the robot's joint range (``2 (beta - lo) / (hi - lo) - 1``); with
  *pair inputs* (:func:`pair_list`) also the relative rotations of the tubes and the overlaps
  of their curved sections with their products (what the tubes' twist depends on);
* ``depth`` hidden layers of ``width`` neurons, each Linear + PReLU (``LearnedModel``'s default
  3 hidden layers of 30 neurons, "3 x 30", the literature's; ``ctrplan train``'s simulation
  recipe 4 x 64 with pair inputs over the rigid base, :data:`ctrplan.shape.training.SIM_RECIPE`);
* output: ``3 K`` numbers ``z``, de-normalised to coefficients ``c = mean + std * z`` (mean, std
  from the training set) and arranged as (K, 3);
* backbone ``x(q, s) = len(q) * sum_k c_k P_k(s / len(q))`` with :mod:`ctrplan.shape.basis`,
  ``len(q)`` the arc length to the tip (:meth:`Robot.tip_length`).

Frame ``outer`` (default): the angles enter relative to the outermost tube's and the backbone
is predicted in a frame turned with that tube, which is exact for an unloaded CTR (turning
every tube by the same angle turns the backbone about the insertion axis) and leaves one angle
less to learn; frame ``base`` uses the absolute angles as the literature does.

The whole batch goes through one forward pass (float32, CPU unless ``device=`` says otherwise;
batches up to :data:`SMALL_BATCH` use a compiled float64 kernel for low latency; on a GPU,
batches of at least :data:`GPU_MIN_BATCH` run there - network, rigid base and continuity pad -
smaller ones on the CPU paths, where a call costs less than a GPU round trip).
``tip_and_jacobian`` differentiates the torch path with autograd (for inverse kinematics).
Model files are written with :func:`torch.save` and read with ``torch.load(weights_only=True)``:
they hold only tensors and a JSON string of metadata (robot, basis, normalisation,
architecture, training-data hashes, metrics), never pickled code.

Options recorded in the model file:

* **Direction-aware inputs** (``direction=True``): ``3n - 1`` more inputs, the sign of the last
  motion of each joint (same layout as q, -1/0/+1, 0 = unknown) and the direction of relative
  rotation of each pair of neighbouring tubes (:func:`direction_features`), so friction /
  hysteresis that depends on the direction of the last motion can be learned. Such a model has
  ``needs_direction = True`` and takes ``shape(q, points, direction=D)``
  (:func:`ctrplan.shape.base.needs_direction`); without ``direction`` every input is 0.
* **Residual mode** (``base=``): the network predicts the basis coefficients of the difference
  to a base model - ``rigid`` (the closed-form torsionally rigid model,
  :class:`~ctrplan.shape.rigid.RigidModel`, about 0.3 us per shape: the shipped networks learn
  the compliant model's difference to it, the tubes' twist), ``physics`` (a physics call per
  evaluation), a calibrated
  EffectModel (``ctrplan diagnose``; also a physics call) or a learned model (stored inside the
  file; evaluated in the same pass, no physics call). A residual model answers in its base
  model's frame (a calibrated model with ``registration``: the sensor frame).
* **Error bound**: ``error_quantiles`` (p50/p95/p99/max, mm) of the max deviation along the
  shaft on the held-out test part of the data the model was last trained on, and
  ``error_bound``: ``measured`` (that data was measured on a robot: the model is calibrated)
  or ``surrogate`` (simulated: the bound is the network's surrogate error against the model it
  imitates); see :mod:`ctrplan.shape.error_bounds`.
* **Training domain**: ``ok`` is False outside the robot's joint limits and outside the joint
  ranges seen in that data (translations: min..max per tube; rotations: the smallest arc that
  holds every angle seen, or the whole circle when no gap between seen angles exceeds
  :data:`FULL_CIRCLE_GAP`).
"""

from __future__ import annotations

import io
import json
import os
from importlib import resources
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np
import torch
from torch import nn

from ctrplan.errors import ArgumentError, InputError
from ctrplan.io import jsonable
from ctrplan.robot import Robot, load_robot, robot_from_dict
from ctrplan.shape import basis
from ctrplan.shape.base import Shape, check_q, radius_along
from ctrplan.shape.base import needs_direction as _needs_direction
from ctrplan.shape.devices import GPU_MIN_BATCH, current_device, resolve_device
from ctrplan.shape.devices import using_device as using_device  # noqa: F401 (API)
from ctrplan.shape.pairs import pair_features, pair_list
from ctrplan.shape.rigid import RigidModel

FORMAT = "ctrplan-learned-model"
FORMAT_VERSION = 2
#: Versions :meth:`LearnedModel.load` reads (1: no direction inputs, residual, bound or domain).
READ_VERSIONS = (1, 2)
#: Rotations: the seen angles cover the whole circle when no gap between them exceeds this (rad).
FULL_CIRCLE_GAP = 0.5
QUANTILES = {"p50": 50.0, "p95": 95.0, "p99": 99.0, "max": 100.0}
#: Slack of the domain check (mm for translations and the joint constraints, rad for
#: rotations): finite-difference steps just across a limit (IK) still count as inside.
DOMAIN_TOL = 0.05
DEFAULT_WIDTH = 30
DEFAULT_DEPTH = 3
#: "outer": angles relative to the outermost tube, backbone predicted in a frame turned with
#: it (exact rotational symmetry about the insertion axis); "base": absolute angles (literature).
FRAMES = ("outer", "base")
DEFAULT_FRAME = "outer"
#: Batches up to this size are evaluated in numpy (lower per-call overhead than torch).
SMALL_BATCH = 64
#: Rows per chunk of the CPU inference path (intermediates stay in cache).
CHUNK = 4096


class ShapeNet(nn.Module):
    """MLP ``3n -> [Linear(width), PReLU] x depth -> Linear(3K)`` (normalised coefficients).

    PReLU has one learned slope per layer (the torch default)."""

    def __init__(self, n_in: int, n_out: int, width: int = DEFAULT_WIDTH, depth: int = DEFAULT_DEPTH):
        super().__init__()
        if width < 1 or depth < 1:
            raise ValueError("width and depth must be >= 1")
        layers: list[nn.Module] = []
        d = n_in
        for _ in range(depth):
            layers += [nn.Linear(d, width), nn.PReLU()]
            d = width
        layers.append(nn.Linear(d, n_out))
        self.net = nn.Sequential(*layers)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(x)


class LearnedModel:
    """A trained shape network for one robot (implements the ShapeModel protocol).

    Parameters
    ----------
    robot : Robot or str
    width, depth : int
        Hidden-layer size and number of hidden layers.
    terms : int
        Basis terms K per coordinate.
    device : str
        Torch device for evaluation (``"cpu"`` by default, e.g. ``"cuda"``).
    """

    name = "learned"

    def __init__(self, robot: Robot | str, width: int = DEFAULT_WIDTH, depth: int = DEFAULT_DEPTH,
                 terms: int = basis.DEFAULT_TERMS, device: str | torch.device = "cpu",
                 seed: int | None = 0, frame: str = DEFAULT_FRAME, direction: bool = False,
                 base: Any = None, base_spec: dict | None = None, pairs: bool = False):
        self.robot = load_robot(robot)
        if frame not in FRAMES:
            raise ValueError(f"frame must be one of {FRAMES}, got {frame!r}")
        self.frame = frame
        self.width, self.depth, self.terms = int(width), int(depth), int(terms)
        basis.coefficients(self.terms)  # validates terms
        n = self.robot.n
        if seed is not None:
            torch.manual_seed(seed)
        #: direction-aware: extra inputs from the sign of the last motion of each joint
        self.direction_inputs = bool(direction)
        #: pair inputs (:func:`pair_list`): cos, sin of the relative rotation of each pair of
        #: tubes not already an input, and per pair of tubes the overlap of their curved
        #: sections with its products with cos, sin of their relative rotation; before any
        #: direction inputs
        self.pair_inputs = bool(pairs)
        pl, ol, oinv = pair_list(self.robot, frame) if self.pair_inputs else ([], [], [])
        self._pairs = np.array(pl, dtype=np.int64).reshape(-1, 2)
        self._opairs = np.array(ol, dtype=np.int64).reshape(-1, 2)
        self._oinv = np.ascontiguousarray(oinv, dtype=np.float64).reshape(-1)
        self._straight = np.ascontiguousarray(self.robot.array("straight_length"))
        self.net = ShapeNet(self.n_q_features + (n_direction_features(n) if self.direction_inputs else 0),
                            3 * self.terms, self.width, self.depth)
        #: residual mode: the network predicts the difference to this model (None: pure)
        self.base = base
        self.base_spec = dict(base_spec) if base_spec else (
            {"kind": "learned"} if isinstance(base, LearnedModel) else None)
        if base is not None and self.base_spec is None:
            raise ValueError("a residual base other than a LearnedModel needs base_spec")
        #: held-out max-deviation quantiles (mm) {"p50", "p95", "p99", "max"} or None
        self.error_quantiles: dict[str, float] | None = None
        #: held-out deviation quantiles per arc-length fraction (the ``error_profile`` mapping
        #: of :mod:`ctrplan.shape.error_bounds`) or None
        self.error_profile: dict[str, list[float]] | None = None
        #: where the bound was measured: "measured" (a robot), "surrogate" (the simulated
        #: model the network imitates) or None (no bound; :mod:`ctrplan.shape.error_bounds`)
        self.error_bound: str | None = None
        #: training domain (joint ranges seen) or None (robot limits only)
        self.domain: dict[str, Any] | None = None
        lo, hi = self.robot.beta_bounds()
        span = np.where(hi - lo > 0, hi - lo, 1.0)
        self.beta_lo = torch.tensor(lo, dtype=torch.float32)
        self.beta_span = torch.tensor(span, dtype=torch.float32)
        self.coef_mean = torch.zeros(3 * self.terms)
        self.coef_std = torch.ones(3 * self.terms)
        self.lengths = torch.tensor(self.robot.lengths, dtype=torch.float32)
        self.straight_t = torch.tensor(self._straight, dtype=torch.float32)
        self.oinv_t = torch.tensor(self._oinv, dtype=torch.float32)
        self.meta: dict[str, Any] = {}
        self._device = torch.device("cpu")
        self._basis_cache: dict[tuple[int, str], torch.Tensor] = {}
        self.net.eval()
        self.to(device)

    # ------------------------------------------------------------------ device / repr
    @property
    def device(self) -> torch.device:
        return self._device

    @property
    def n_q_features(self) -> int:
        """Inputs computed from q: 3 per tube, with pair inputs 2 per relative rotation and 3 per
        overlap (:func:`pair_list`)."""
        return 3 * self.robot.n + 2 * len(self._pairs) + 3 * len(self._opairs)

    @property
    def needs_direction(self) -> bool:
        """True for direction-aware models (and residual models over one)."""
        return self.direction_inputs or _needs_direction(self.base)

    @property
    def residual(self) -> bool:
        return self.base is not None

    def to(self, device: str | torch.device) -> LearnedModel:
        """Move the network to ``device`` (in place; ``auto``: :func:`resolve_device`); returns
        self."""
        self._device = resolve_device(device)
        self.net.to(self._device)
        if isinstance(self.base, LearnedModel):
            self.base.to(device)
        for k in ("beta_lo", "beta_span", "coef_mean", "coef_std", "lengths", "straight_t", "oinv_t"):
            setattr(self, k, getattr(self, k).to(self._device))
        self._basis_cache = {}
        return self

    def __repr__(self) -> str:
        extra = (", direction=True" if self.direction_inputs else "") + (
            ", pairs=True" if self.pair_inputs else "") + (
            f", base={self.base_spec.get('kind')!r}" if self.base_spec else "")
        return (f"LearnedModel(robot={self.robot.name!r}, width={self.width}, depth={self.depth}, "
                f"terms={self.terms}, frame={self.frame!r}{extra}, device={str(self._device)!r})")

    def __getstate__(self) -> dict:  # picklable for process pools: move to CPU tensors
        st = dict(self.__dict__)
        st["_basis_cache"] = {}
        return st

    # ------------------------------------------------------------------ torch path
    def check_direction(self, q: np.ndarray, direction: Any) -> np.ndarray | None:
        """Direction of the last motion as float (B, 2n) in {-1, 0, 1}, or None (unknown)."""
        if direction is None:
            return None
        d = np.asarray(direction, dtype=float)
        if d.ndim == 1:
            d = d[None, :]
        if d.shape != q.shape:
            raise ValueError(f"direction must have the shape of q {q.shape}, got {d.shape}")
        if not np.all(np.isfinite(d)):
            raise ValueError("direction contains NaN or infinite values")
        return np.sign(d)

    def features(self, q: torch.Tensor, direction: torch.Tensor | None = None) -> torch.Tensor:
        """Network input (B, 3n [+ 2n]): per tube cos alpha, sin alpha, beta scaled to [-1, 1]
        (with frame "outer", alpha relative to the outermost tube's); with pair inputs cos, sin of
        alpha_i - alpha_j per pair (:func:`pair_list`); direction-aware models append the
        direction of the last motion of each joint (zeros when not given)."""
        n = self.robot.n
        a, b = q[:, :n], q[:, n:]
        if self.frame == "outer":
            a = a - a[:, n - 1:n]
        bs = 2.0 * (b - self.beta_lo) / self.beta_span - 1.0
        x = torch.stack([torch.cos(a), torch.sin(a), bs], dim=2).reshape(len(q), 3 * n)
        if self.pair_inputs:
            x = torch.cat([x, self._pair_features_t(q)], dim=1)
        if not self.direction_inputs:
            return x
        d = torch.zeros_like(q) if direction is None else direction.to(dtype=x.dtype, device=x.device)
        rel = torch.sign(d[:, :n - 1] - d[:, 1:n])
        return torch.cat([x, d, rel], dim=1)

    def _pair_features_t(self, q: torch.Tensor) -> torch.Tensor:
        """The pair inputs (B, 2P + 3O) of q (B, 2n) tensors (:func:`pair_list`)."""
        n, B = self.robot.n, len(q)
        i, j = self._pairs[:, 0].tolist(), self._pairs[:, 1].tolist()
        rel = q[:, i] - q[:, j]
        parts = [torch.stack([torch.cos(rel), torch.sin(rel)], dim=2).reshape(B, -1)]
        i, j = self._opairs[:, 0].tolist(), self._opairs[:, 1].tolist()
        b = q[:, n:]
        end = torch.minimum(b[:, i] + self.lengths[i], b[:, j] + self.lengths[j])
        start = torch.clamp(torch.maximum(b[:, i] + self.straight_t[i], b[:, j] + self.straight_t[j]), min=0.0)
        ov = torch.clamp(end - start, min=0.0) * self.oinv_t
        rel = q[:, i] - q[:, j]
        parts.append(torch.stack([ov, ov * torch.cos(rel), ov * torch.sin(rel)], dim=2).reshape(B, -1))
        return torch.cat(parts, dim=1)

    def coefficients_t(self, q: torch.Tensor) -> torch.Tensor:
        """Basis coefficients (B, K, 3) of the network's own output (dimensionless, base frame;
        for a residual model the coefficients of the difference to the base) for q (B, 2n)."""
        z = self.net(self.features(q))
        c = (self.coef_mean + self.coef_std * z).reshape(len(q), self.terms, 3)
        return self._to_base(q, c)

    def _to_base(self, q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
        """Turn vectors v (B, ..., 3) from the model frame to the robot base frame."""
        if self.frame != "outer":
            return v
        a = q[:, self.robot.n - 1]
        shape = (len(q),) + (1,) * (v.dim() - 2)
        c, s = torch.cos(a).view(shape), torch.sin(a).view(shape)
        x, y = v[..., 0], v[..., 1]
        return torch.stack([c * x - s * y, s * x + c * y, v[..., 2]], dim=-1)

    def to_model_frame(self, q: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Base-frame points (B, m, 3) -> the model's frame (training targets)."""
        if self.frame != "outer":
            return np.asarray(points, dtype=float)
        a = np.asarray(q, dtype=float)[:, self.robot.n - 1]
        c, s = np.cos(a)[:, None], np.sin(a)[:, None]
        p = np.array(points, dtype=float, copy=True)
        x, y = p[..., 0].copy(), p[..., 1].copy()
        p[..., 0] = c * x + s * y
        p[..., 1] = -s * x + c * y
        return p

    def tip_length_t(self, q: torch.Tensor) -> torch.Tensor:
        """Arc length to the tip (B,), mm."""
        return torch.max(q[:, self.robot.n:] + self.lengths, dim=1).values

    def _phi(self, points: int, dtype: torch.dtype) -> torch.Tensor:
        key = (int(points), str(dtype))
        phi = self._basis_cache.get(key)
        if phi is None:
            phi = torch.tensor(basis.design_matrix(points, self.terms), dtype=dtype, device=self._device)
            self._basis_cache[key] = phi
        return phi

    def points_t(self, q: torch.Tensor, points: int = 20, direction: torch.Tensor | None = None) -> torch.Tensor:
        """Differentiable backbones (B, points, 3) mm from q (B, 2n) tensors on the device
        (the network's own part: for a residual model, without the base)."""
        return self._to_base(q, self.points_from_features(self.features(q, direction),
                                                          self.tip_length_t(q), points))

    def points_from_features(self, x: torch.Tensor, length: torch.Tensor, points: int) -> torch.Tensor:
        """Differentiable backbones (B, points, 3) mm in the model frame from network inputs
        (B, 3n) and tip lengths (B,) mm (training precomputes both once)."""
        z = self.net(x)
        c = self.coef_mean + self.coef_std * z                       # (B, 3K), (k, xyz) order
        out = torch.mm(c, self._expand(points, c.dtype))             # (B, 3m)
        return (out * length[:, None]).view(len(x), points, 3)

    def _expand(self, points: int, dtype: torch.dtype) -> torch.Tensor:
        """kron(Phi, I3)^T: (3K, 3m) map from coefficients (k, xyz) to points (j, xyz)."""
        key = (int(points), "expand" + str(dtype))
        M = self._basis_cache.get(key)
        if M is None:
            phi = torch.tensor(basis.design_matrix(points, self.terms), dtype=torch.float64)
            M = torch.kron(phi, torch.eye(3, dtype=torch.float64)).t().contiguous().to(
                dtype=dtype, device=self._device)
            self._basis_cache[key] = M
        return M

    def invalidate(self) -> None:
        """Forget cached inference weights (call after changing the network's parameters)."""
        self._basis_cache = {}

    def _fused(self, points: int) -> tuple[list[tuple[torch.Tensor, ...]], torch.Tensor, torch.Tensor]:
        """Inference weights: hidden layers as (W^T, b, prelu slope) and one final affine map
        straight to backbone points per unit length (B, 3 points), the de-normalisation and
        the basis folded in: ``p / len = (h W^T + b) std + mean`` times ``kron(Phi, I3)``."""
        key = (int(points), "fused")
        hit = self._basis_cache.get(key)
        if hit is not None:
            return hit  # type: ignore[return-value]
        mods = list(self.net.net)
        hidden = []
        with torch.no_grad():
            for lin, act in zip(mods[0:-1:2], mods[1:-1:2]):
                hidden.append((lin.weight.detach().t().contiguous(), lin.bias.detach().clone(),
                               act.weight.detach().clone()))
            last = mods[-1]
            phi = torch.tensor(basis.design_matrix(points, self.terms), dtype=torch.float64)
            M = torch.kron(phi, torch.eye(3, dtype=torch.float64)).to(self._device)  # (3m, 3K)
            W = last.weight.detach().double() * self.coef_std.double()[:, None]      # (3K, width)
            b = last.bias.detach().double() * self.coef_std.double() + self.coef_mean.double()
            Wf = (M @ W).t().contiguous().float()                                    # (width, 3m)
            bf = (M @ b).float()
        out = (hidden, Wf, bf)
        self._basis_cache[key] = out  # type: ignore[assignment]
        return out

    def _chain(self) -> tuple[list[LearnedModel], Any]:
        """The networks whose outputs add up (this one and, in residual mode, learned bases
        with the same frame, basis and input scaling: evaluated in the same pass), and the
        remaining base model (physics, calibrated, ...) or None."""
        nets = [self]
        m = self
        while (isinstance(m.base, LearnedModel) and m.base.frame == self.frame
               and m.base.terms == self.terms and m.base.robot.n == self.robot.n
               and m.base.pair_inputs == self.pair_inputs
               and torch.equal(m.base.beta_lo.cpu(), self.beta_lo.cpu())
               and torch.equal(m.base.beta_span.cpu(), self.beta_span.cpu())):
            m = m.base
            nets.append(m)
        return nets, m.base

    def _fast_points(self, qt: torch.Tensor, points: int, dt: torch.Tensor | None = None) -> torch.Tensor:
        """Inference-only forward pass (no autograd, fused last layer), (B, points, 3);
        the network's own part."""
        hidden, Wf, bf = self._fused(points)
        h = self.features(qt, dt)
        for Wt, b, a in hidden:
            h = torch.prelu(torch.addmm(b, h, Wt), a)
        out = torch.addmm(bf, h, Wf)
        out.mul_(self.tip_length_t(qt)[:, None])
        out = out.view(len(qt), points, 3)
        if self.frame == "outer":
            a = qt[:, self.robot.n - 1:self.robot.n]
            c, s = torch.cos(a), torch.sin(a)
            x, y = out[:, :, 0].clone(), out[:, :, 1]
            out[:, :, 0].mul_(c).addcmul_(y, s, value=-1.0)
            out[:, :, 1].mul_(c).addcmul_(x, s)
        return out

    def _phi_np(self, points: int) -> np.ndarray:
        key = (int(points), "phi_np")
        phi = self._basis_cache.get(key)
        if phi is None:
            phi = np.ascontiguousarray(basis.design_matrix(points, self.terms))
            self._basis_cache[key] = phi  # type: ignore[assignment]
        return phi  # type: ignore[return-value]

    def _numba_weights(self):
        """float64 weights for the compiled kernels (cached until :meth:`invalidate`)."""
        hit = self._basis_cache.get((0, "numba"))
        if hit is None:
            with torch.no_grad():
                mods = list(self.net.net)
                lins = list(mods[0:-1:2])
                acts = list(mods[1:-1:2])
                W0 = lins[0].weight.detach().cpu().double().t().contiguous().numpy()
                w = W0.shape[1]
                Wh = (np.stack([li.weight.detach().cpu().double().t().numpy() for li in lins[1:]])
                      if len(lins) > 1 else np.zeros((0, w, w)))
                bh = np.stack([li.bias.detach().cpu().double().numpy() for li in lins])
                slopes = np.array([float(ac.weight.detach().reshape(-1)[0]) for ac in acts])
                last = mods[-1]
                std, mean = self.coef_std.detach().cpu().double(), self.coef_mean.detach().cpu().double()
                Wl = (last.weight.detach().cpu().double() * std[:, None]).t().contiguous().numpy()
                bl = (last.bias.detach().cpu().double() * std + mean).numpy()
            hit = (np.ascontiguousarray(W0), np.ascontiguousarray(Wh), np.ascontiguousarray(bh),
                   slopes, np.ascontiguousarray(Wl), np.ascontiguousarray(bl),
                   self.beta_lo.cpu().double().numpy().copy(),
                   (2.0 / self.beta_span.cpu().double().numpy()).copy(), self.robot.lengths.copy())
            self._basis_cache[(0, "numba")] = hit  # type: ignore[assignment]
        return hit

    def _numpy_points(self, q: np.ndarray, points: int, d: np.ndarray | None = None,
                      nets: list[LearnedModel] | None = None) -> np.ndarray:
        """The same forward pass in float64 by a small compiled (numba) kernel: the lowest
        latency for small batches (a torch call costs microseconds per operation). ``nets``:
        the networks whose outputs add up (default: this one)."""
        from ctrplan.shape import _learned_kernel

        q = np.ascontiguousarray(q, dtype=np.float64)
        phi = self._phi_np(points)
        out = np.empty((len(q), points, 3))
        tmp = np.empty_like(out) if nets and len(nets) > 1 else out
        none = np.zeros((len(q), 0))
        for k, net in enumerate(nets or [self]):
            W0, Wh, bh, slopes, Wl, bl, lo, inv, L = net._numba_weights()
            dirs = none
            if net.direction_inputs:
                dirs = direction_features(np.zeros_like(q) if d is None else d, self.robot.n)
            _learned_kernel.forward(q, dirs, net._pairs, net._opairs, net._straight, net._oinv,
                                    self.robot.n, self.frame == "outer", lo, inv, L,
                                    W0, Wh, bh, slopes, Wl, bl, phi, out if k == 0 else tmp)
            if k > 0:
                out += tmp
        return out

    def _cpu_weights(self, points: int):
        """float32 inference weights for the CPU path: hidden layers (W^T, b, slope), the last
        layer with the de-normalisation folded in (W^T (width, 3K), b (3K,)) and the basis
        expansion kron(Phi, I3)^T (3K, 3m)."""
        key = (int(points), "cpu")
        hit = self._basis_cache.get(key)
        if hit is None:
            with torch.no_grad():
                mods = list(self.net.net)
                hidden = [(lin.weight.detach().t().contiguous().float().cpu(),
                           lin.bias.detach().float().cpu().clone(), act.weight.detach().float().cpu().clone())
                          for lin, act in zip(mods[0:-1:2], mods[1:-1:2])]
                last = mods[-1]
                std, mean = self.coef_std.detach().cpu().double(), self.coef_mean.detach().cpu().double()
                Wl = (last.weight.detach().cpu().double() * std[:, None]).t().contiguous().float()
                bl = (last.bias.detach().cpu().double() * std + mean).float()
                phi = torch.tensor(basis.design_matrix(points, self.terms), dtype=torch.float64)
                M = torch.kron(phi, torch.eye(3, dtype=torch.float64)).t().contiguous().float()
            hit = (hidden, Wl, bl, M, self.beta_lo.cpu().numpy().astype(np.float32),
                   (2.0 / self.beta_span.cpu().numpy()).astype(np.float32),
                   self.robot.lengths.astype(np.float32))
            self._basis_cache[key] = hit  # type: ignore[assignment]
        return hit

    def _cpu_points(self, q: np.ndarray, points: int, d: np.ndarray | None = None,
                    nets: list[LearnedModel] | None = None) -> np.ndarray:
        """CPU inference in float32 chunks that stay in cache; returns float64 (B, points, 3).

        Features in numpy (vectorised float32 cos/sin), the MLP in torch, the rotation of the
        "outer" frame applied to the (B, K) coefficients before the basis expansion. ``nets``:
        networks whose coefficients add up (residual over a learned base: one pass, one
        expansion)."""
        nets = nets or [self]
        _, _, _, M, lo, inv, L = self._cpu_weights(points)
        n, K, B = self.robot.n, self.terms, len(q)
        q32 = np.asarray(q, dtype=np.float32)
        a, b = q32[:, :n], q32[:, n:]
        ar = a - a[:, n - 1:n] if self.frame == "outer" else a
        feats = np.empty((B, n, 3), dtype=np.float32)
        np.cos(ar, out=feats[:, :, 0])
        np.sin(ar, out=feats[:, :, 1])
        feats[:, :, 2] = (b - lo) * inv - 1.0
        f = feats.reshape(B, 3 * n)
        if self.pair_inputs:                                      # (all nets share the pairs)
            f = np.concatenate([f, pair_features(self, q32)], axis=1)
        nq = f.shape[1]
        X3 = torch.from_numpy(f)
        X5 = None
        if any(net.direction_inputs for net in nets):             # contiguous inputs per width
            f5 = np.zeros((B, nq + n_direction_features(n)), dtype=np.float32)
            f5[:, :nq] = f
            if d is not None:
                f5[:, nq:] = direction_features(d, n)
            X5 = torch.from_numpy(f5)
        length = torch.from_numpy(np.max(b + L, axis=1))
        if self.frame == "outer":
            cr = torch.from_numpy(np.cos(a[:, n - 1]))
            sr = torch.from_numpy(np.sin(a[:, n - 1]))
        out = np.empty((B, points, 3), dtype=np.float64)
        flat = out.reshape(B, 3 * points)
        rows = min(CHUNK, B)
        mlps = []
        for net in nets:
            hidden, Wl, bl = net._cpu_weights(points)[:3]
            mlps.append((hidden, Wl, bl, [float(sl.reshape(-1)[0]) for _, _, sl in hidden],
                         [torch.empty(rows, Wt.shape[1]) for Wt, _, _ in hidden],
                         X5 if net.direction_inputs else X3))
        cbuf = torch.empty(rows, 3 * K)
        c2buf = torch.empty(rows, 3 * K)
        pbuf = torch.empty(rows, M.shape[1])
        with torch.inference_mode():
            for i in range(0, B, CHUNK):
                r = min(CHUNK, B - i)
                c = cbuf[:r]
                for k, (hidden, Wl, bl, slopes, bufs, X) in enumerate(mlps):
                    h = X[i:i + r]
                    for (Wt, bb, _), a_, buf in zip(hidden, slopes, bufs):
                        hb = buf[:r]
                        torch.addmm(bb, h, Wt, out=hb)
                        torch.nn.functional.leaky_relu_(hb, a_)   # PReLU with one slope per layer
                        h = hb
                    if k == 0:
                        torch.addmm(bl, h, Wl, out=c)
                    else:
                        c2 = c2buf[:r]
                        torch.addmm(bl, h, Wl, out=c2)
                        c.add_(c2)
                c.mul_(length[i:i + r, None])
                if self.frame == "outer":
                    cv = c.view(-1, K, 3)
                    co, si = cr[i:i + r, None], sr[i:i + r, None]
                    x, y = cv[:, :, 0], cv[:, :, 1]
                    nx = x * co - y * si
                    y.mul_(co).add_(x * si)
                    x.copy_(nx)
                pb = pbuf[:r]
                torch.mm(c, M, out=pb)
                flat[i:i + r] = pb.numpy()
        return out

    def _as_tensor(self, q: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(q, dtype=np.float32), device=self._device)

    # ------------------------------------------------------------------ ShapeModel protocol
    def _evaluate(self, q: np.ndarray, points: int, d: np.ndarray | None,
                  want_pad: bool = False):
        """Backbones (B, points, 3) and the base model's ok (or None) for checked q; with
        ``want_pad`` also the continuity pad (B, points - 1) (see :func:`polynomial_pad`)."""
        nets, rest = self._chain()
        if self._on_device(len(q)):
            out, pad, rest = self._device_points(q, points, d, nets, rest, want_pad)
        else:
            out = self._net_points(q, points, d, nets)
            pad = None
            if want_pad:
                fit = out if points > self.terms else self._net_points(q, self.terms + 1, d, nets)
                pad = polynomial_pad(fit, points, self.terms, memo=_owned_memo(self, "pad_maps"))
        ok = None
        if isinstance(rest, RigidModel):      # closed form: never fails, its own sagitta pad
            out += rest.points(q, points)
            if pad is not None:
                pad = pad + rest.pad(q, points)
        elif rest is not None:
            if _needs_direction(rest) and d is not None:
                sh = rest.shape(q, points=points, direction=d)
            else:
                sh = rest.shape(q, points=points)
            out += sh.points
            ok = np.asarray(sh.ok, dtype=bool)
            if pad is not None:
                base_pad = getattr(sh, "pad", None)
                if base_pad is None:   # a base that states no bound: its curvature bound
                    from ctrplan.shape.bounds import curvature_bound, sagitta_pad

                    base_pad = sagitta_pad(sh.s, curvature_bound(rest))
                # the chord error of a sum is the sum of the chord errors (same s grid)
                pad = pad + base_pad
        if want_pad:
            return out, ok, pad
        return out, ok

    def _on_device(self, batch: int) -> bool:
        """True when a batch of this size runs on the model's (non-CPU) device."""
        return self._device.type != "cpu" and batch >= GPU_MIN_BATCH

    def _net_points(self, q: np.ndarray, points: int, d: np.ndarray | None,
                    nets: list[LearnedModel]) -> np.ndarray:
        """The summed networks' polynomial backbones (B, points, 3) (no base model)."""
        if not self._on_device(len(q)):
            if len(q) <= SMALL_BATCH:
                return self._numpy_points(q, points, d, nets)
            return self._cpu_points(q, points, d, nets)
        out, _, _ = self._device_points(q, points, d, nets, None, False)
        return out

    def _device_points(self, q: np.ndarray, points: int, d: np.ndarray | None,
                       nets: list[LearnedModel], rest: Any, want_pad: bool):
        """The whole batch on the model's (non-CPU) device: the summed networks (float32), the
        continuity pad of their polynomial (float64) and, for a closed-form rigid base, its
        backbones (float64); one transfer back. Returns (points (B, points, 3) float64, pad
        (B, points - 1) or None, the base model still to add on the CPU or None)."""
        qt = self._as_tensor(q)
        dt = None if d is None else self._as_tensor(d)
        with torch.inference_mode():
            acc = nets[0]._fast_points(qt, points, dt)
            for net in nets[1:]:
                acc += net._fast_points(qt, points, dt)
            pad = None
            if want_pad:
                fit = acc
                if points <= self.terms:
                    fit = nets[0]._fast_points(qt, self.terms + 1, dt)
                    for net in nets[1:]:
                        fit += net._fast_points(qt, self.terms + 1, dt)
                pad = polynomial_pad_torch(fit.double(), points, self.terms,
                                           memo=_owned_memo(self, "pad_maps"))
            out = acc.double()
            if isinstance(rest, RigidModel):
                q64 = torch.as_tensor(np.ascontiguousarray(q, dtype=np.float64), device=self._device)
                out += rest.points_torch(q64, points)
                if pad is not None:
                    pad += torch.as_tensor(rest.pad(q, points), device=self._device)
                rest = None
            out_np = out.cpu().numpy()
            pad_np = None if pad is None else pad.cpu().numpy()
        return out_np, pad_np, rest

    def backbone(self, q: np.ndarray, points: int = 20, direction: np.ndarray | None = None) -> np.ndarray:
        """(B, points, 3) backbone points, mm, robot base frame (one forward pass).

        direction : (B, 2n) sign of the last motion of each joint, for direction-aware models
        (ignored otherwise; None = unknown)."""
        if points < 2:
            raise ValueError("points must be >= 2 (base and tip)")
        q = check_q(self.robot, q)
        return self._evaluate(q, points, self.check_direction(q, direction))[0]

    def shape(self, q: np.ndarray, points: int = 20, direction: np.ndarray | None = None) -> Shape:
        """Backbones with radii. ``ok`` is False outside the training domain
        (:meth:`in_domain`) and where a residual model's base model failed."""
        if points < 2:
            raise ValueError("points must be >= 2 (base and tip)")
        q = check_q(self.robot, q)
        pts, base_ok, pad = self._evaluate(q, points, self.check_direction(q, direction),
                                           want_pad=True)
        ok = self.in_domain(q)
        if base_ok is not None:
            ok &= base_ok
        s = np.linspace(0.0, 1.0, points)[None, :] * self.robot.tip_length(q)[:, None]
        return Shape(points=pts, s=s, radius=radius_along(self.robot, q, s), ok=ok, pad=pad)

    def in_domain(self, q: np.ndarray) -> np.ndarray:
        """(B,) bool: inside the robot's joint limits and the joint ranges of the training
        data (:attr:`domain`; see the module docstring), each with a slack of
        :data:`DOMAIN_TOL` (mm / rad)."""
        q = check_q(self.robot, q)
        ok = np.all(self.robot.constraint_violations(q) >= -DOMAIN_TOL, axis=1)
        dom = self.domain
        if not dom:
            return ok
        n = self.robot.n
        tol = max(float(dom.get("tolerance", 0.0)), DOMAIN_TOL)
        lo = np.asarray(dom["beta_min_mm"], dtype=float)
        hi = np.asarray(dom["beta_max_mm"], dtype=float)
        ok &= np.all((q[:, n:] >= lo - tol) & (q[:, n:] <= hi + tol), axis=1)
        for i, arc in enumerate(dom["alpha_arcs_rad"]):
            if arc is None:
                continue
            centre, half = float(arc[0]), float(arc[1])
            off = (q[:, i] - centre + np.pi) % (2 * np.pi) - np.pi
            ok &= np.abs(off) <= half + tol
        return ok

    def set_domain(self, q: np.ndarray, source: str = "") -> None:
        """Record the training domain from the configurations a model was trained on: per
        tube the translation range seen and the smallest arc holding every rotation seen
        (None: the whole circle, when no gap between seen angles exceeds FULL_CIRCLE_GAP)."""
        self.domain = training_domain(self.robot, q, source)

    def set_error_profile(self, predicted: np.ndarray, measured: np.ndarray,
                          kind: str | None = None) -> dict[str, list[float]]:
        """Store the quantiles of the held-out deviation at each backbone point (predicted and
        measured (B, m, 3), evenly spaced in arc length) as :attr:`error_profile`; ``kind``
        (``measured`` / ``surrogate``) sets :attr:`error_bound` when given."""
        from ctrplan.shape.error_bounds import check_error_bound_kind, profile_from_backbones

        self.error_profile = profile_from_backbones(predicted, measured).to_dict()
        if kind is not None:
            self.error_bound = check_error_bound_kind(kind)
        return self.error_profile

    def set_error_quantiles(self, per_config_max: np.ndarray,
                            kind: str | None = None) -> dict[str, float]:
        """Store quantiles of held-out max deviations (mm) as :attr:`error_quantiles`;
        ``kind`` (``measured`` / ``surrogate``) sets :attr:`error_bound` when given."""
        from ctrplan.shape.error_bounds import check_error_bound_kind

        self.error_quantiles = error_quantiles(per_config_max)
        if kind is not None:
            self.error_bound = check_error_bound_kind(kind)
        return self.error_quantiles

    def tip_and_jacobian(self, q: np.ndarray, method: str = "auto",
                         direction: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Tip positions (B, 3) mm and their Jacobians d tip / d q (B, 3, 2n).

        Columns are per joint: alpha in mm/rad, beta in mm/mm. ``method``: "compiled"
        (forward-mode derivatives in a numba kernel, float64, the default on the CPU) or
        "autograd" (torch autograd through the float32 network, any device). The tip length
        ``max(beta + L)`` is piecewise linear; at a tie the derivative follows one tube.
        Direction inputs are held constant. A residual model adds its base's tip and
        Jacobian (a learned base's own; central differences of a physics/calibrated base).
        """
        q = check_q(self.robot, q)
        d = self.check_direction(q, direction)
        if method == "auto":
            method = "autograd" if self._on_device(len(q)) else "compiled"
        if method not in ("compiled", "autograd"):
            raise ValueError(f"method must be 'auto', 'compiled' or 'autograd', got {method!r}")
        tip, J = self._own_tip_jacobian(q, d, method)
        if self.base is None:
            return tip, J
        if isinstance(self.base, LearnedModel):
            bt, bJ = self.base.tip_and_jacobian(q, method=method, direction=d)
        else:
            bt, bJ = _fd_tip_jacobian(self.base, q, d)
        return tip + bt, J + bJ

    def _own_tip_jacobian(self, q: np.ndarray, d: np.ndarray | None, method: str):
        if method == "compiled":
            from ctrplan.shape import _learned_kernel

            W0, Wh, bh, slopes, Wl, bl, lo, inv, L = self._numba_weights()
            ptip = np.ascontiguousarray(basis.evaluate(np.array(1.0), self.terms))
            B, D = len(q), self.robot.dof
            tip = np.empty((B, 3))
            J = np.empty((B, 3, D))
            qc = np.ascontiguousarray(q, dtype=np.float64)
            dirs = np.zeros((B, 0))
            if self.direction_inputs:
                dirs = direction_features(np.zeros_like(qc) if d is None else d, self.robot.n)
            _learned_kernel.tip_jacobian(qc, dirs, self._pairs, self._opairs, self._straight, self._oinv,
                                         self.robot.n, self.frame == "outer", lo, inv, L,
                                         W0, Wh, bh, slopes, Wl, bl, ptip, tip, J)
            return tip, J
        qt = self._as_tensor(q).requires_grad_(True)
        dt = None if d is None else self._as_tensor(d)
        with torch.enable_grad():
            tip_t = self.points_t(qt, 2, dt)[:, -1, :]                  # (B, 3)
            rows = []
            for c in range(3):
                (g,) = torch.autograd.grad(tip_t[:, c].sum(), qt, retain_graph=c < 2)
                rows.append(g)
        Jt = torch.stack(rows, dim=1)
        return tip_t.detach().cpu().numpy().astype(np.float64), Jt.cpu().numpy().astype(np.float64)

    # ------------------------------------------------------------------ files
    def metadata(self) -> dict[str, Any]:
        meta = dict(self.meta)
        base_spec = None
        if self.base_spec is not None:
            base_spec = dict(self.base_spec)
            if isinstance(self.base, LearnedModel):
                base_spec["note"] = "stored in the file under 'base'"
        meta.update({
            "inputs": {"direction": self.direction_inputs,
                       "direction_layout": "D = sign of the last motion of each joint, q's layout "
                                           "(alpha_1..n, beta_1..n), -1/0/+1, 0 = unknown; inputs "
                                           "D and the relative rotation directions "
                                           "sign(D_alpha_i - D_alpha_i+1), i < n"},
            "residual": base_spec,
            "error_quantiles": self.error_quantiles,
            "error_profile": self.error_profile,
            "error_bound": (self.error_bound if (self.error_quantiles or self.error_profile)
                            else None),
            "domain": self.domain,
            "robot": self.robot.to_dict(),
            "architecture": {"width": self.width, "depth": self.depth, "activation": "PReLU",
                             "frame": self.frame, "pair_inputs": self.pair_inputs,
                             "inputs": "per tube: cos alpha, sin alpha, 2 (beta - lo) / (hi - lo) - 1"
                                       + (" (alpha relative to the outermost tube's; output "
                                          "turned by it)" if self.frame == "outer" else "")
                                       + ("; per pair (i, j) in pairs: cos, sin of alpha_i - alpha_j; "
                                          "per pair in overlap_pairs: the overlap of the curved "
                                          "sections beyond s = 0 over the shorter curved length, "
                                          "times 1, cos and sin of alpha_i - alpha_j"
                                          if self.pair_inputs else ""),
                             "pairs": self._pairs.tolist(), "overlap_pairs": self._opairs.tolist(),
                             "outputs": "3K normalised basis coefficients (c = mean + std * z), (K, 3)"},
            "basis": {"terms": self.terms, "kind": "Gram-Schmidt on s..s^K over [0, 1], orthonormal, P(0) = 0",
                      "backbone": "x(q, s) = tip_length(q) * sum_k c_k P_k(s / tip_length(q))"},
            "normalisation": {"beta_lo_mm": self.beta_lo.cpu().tolist(),
                              "beta_span_mm": self.beta_span.cpu().tolist(),
                              "coef_mean": self.coef_mean.cpu().tolist(),
                              "coef_std": self.coef_std.cpu().tolist()},
            "units": {"q": "alpha rad, beta mm", "points": "mm, robot base frame"},
        })
        return meta

    def save(self, path: str | os.PathLike) -> None:
        """Write the model file atomically (tensors + JSON metadata)."""
        from ctrplan.io import atomic_path

        # Serialise in memory first: torch.save reports a failed write (a full disk) as a
        # RuntimeError from its zip writer; a plain file write raises OSError, which the command
        # line reports as one line (and atomic_path leaves nothing behind).
        buf = io.BytesIO()
        torch.save(self._file_object(), buf)
        with atomic_path(path) as tmp:
            with open(tmp, "wb") as fh:
                fh.write(buf.getbuffer())

    def _file_object(self) -> dict[str, Any]:
        state = {k: v.detach().cpu().contiguous() for k, v in self.net.state_dict().items()}
        obj = {"format": FORMAT, "version": FORMAT_VERSION,
               "meta_json": json.dumps(jsonable(self.metadata()), allow_nan=False),
               "state": state}
        if isinstance(self.base, LearnedModel):
            obj["base"] = self.base._file_object()
        return obj

    @classmethod
    def load(cls, path: str | os.PathLike, robot: Robot | str | None = None,
             device: str | torch.device | None = None) -> LearnedModel:
        """Read a model file written by :meth:`save` / ``ctrplan train`` onto ``device``
        (None: :func:`current_device`, the CPU unless inside :class:`using_device`).

        ``robot``: check the file was trained for this robot (same tubes); by default the
        robot stored in the file is used. Errors (missing, corrupt, mismatched) raise
        :class:`InputError` naming the file.
        """
        src = str(path)
        p = Path(path)
        if not p.is_file():
            raise InputError(src, "", "model file not found")
        from ctrplan.io import check_input_file

        check_input_file(p, "model")
        try:
            obj = torch.load(p, map_location="cpu", weights_only=True)
        except Exception as exc:  # corrupt, truncated, or not a torch file
            raise InputError(src, "", f"not a readable ctrplan model file ({exc.__class__.__name__})") from None
        model = cls._from_object(obj, src, robot)
        return model.to(current_device() if device is None else device)

    @classmethod
    def _from_object(cls, obj: Any, src: str, robot: Robot | str | None, depth_left: int = 4) -> LearnedModel:
        """The model stored in ``obj`` (a loaded model file; :class:`InputError` naming ``src``
        and the field when anything is missing or malformed). ``depth_left``: how many learned
        bases deep a residual model may nest."""
        meta, arch = _read_header(obj, src)
        bound_kind = _check_error_bound(meta, arch.error_quantiles or arch.error_profile, src)
        robot = _stored_robot(meta, src, robot)
        base = None
        if arch.base_spec is not None:
            base = _load_base(arch.base_spec, obj, src, robot, depth_left)
        try:
            model = cls(robot, width=arch.width, depth=arch.depth, terms=arch.terms, seed=None,
                        frame=arch.frame, direction=arch.direction, base=base,
                        base_spec=arch.base_spec, pairs=arch.pairs)
            _load_weights(model, obj["state"], arch.normalisation)
        except (RuntimeError, KeyError, TypeError, ValueError, AttributeError) as exc:
            raise InputError(src, "state", f"weights do not match the stored architecture ({exc})".replace("\n", " ")[:400]) from None
        for t in list(model.net.state_dict().values()) + [model.coef_mean, model.coef_std, model.beta_span]:
            if not torch.all(torch.isfinite(t)):
                raise InputError(src, "state", "contains non-finite weights")
        _check_normalisation(model, src)
        domain = arch.domain
        if domain is not None and any(len(domain[k]) != robot.n for k in
                                      ("beta_min_mm", "beta_max_mm", "alpha_arcs_rad")):
            raise InputError(src, "domain", f"expects {robot.n} tubes")
        model.error_quantiles = arch.error_quantiles
        model.error_profile = arch.error_profile
        model.error_bound = bound_kind
        model.domain = domain
        keep = ("training", "metrics", "data", "created", "command", "ctrplan_version",
                "error_quantiles_source", "variant", "error_profile_source", "selection", "sim_base",
                "bistable")
        model.meta = {k: meta[k] for k in keep if k in meta}
        model.source = src
        return model


def _bernstein_second_derivative(fit_points: int, points: int, terms: int):
    """Sample indices and the (points - 1, terms - 1, len(indices)) map from a polynomial
    backbone's samples at those indices of ``fit_points`` even parameters t in [0, 1] to the
    Bernstein control points, on each of the ``points - 1`` even parameter segments, of its
    second derivative ``d^2 p / dt^2``."""
    from math import comb

    K = int(terms)
    d = K - 2
    # a few more samples than coefficients suffice (the backbone is exactly in the basis)
    idx = np.unique(np.round(np.linspace(0, fit_points - 1, min(fit_points, 2 * K + 2))).astype(int))
    phi = basis.design_matrix(fit_points, K)[idx]              # (mi, K)
    pinv = np.linalg.pinv(phi)                                 # (K, mi): points -> L c
    C = basis.coefficients(K)                                  # P_k = sum_j C[k, j] t^(j+1)
    # monomial coefficients of sum_k (L c_k) P_k''(t): a_i, i = 0..d
    D2 = np.zeros((d + 1, K))
    for i in range(d + 1):
        D2[i] = C[:, i + 1] * (i + 2) * (i + 1)
    mono = D2 @ pinv                                           # (d + 1, mi)
    h = 1.0 / (points - 1)
    # Bernstein conversion of u -> v(t0 + h u): b_l = sum_i a_i C(i, l) t0^(i-l) h^l, then
    # beta_r = sum_{l <= r} C(r, l) / C(d, l) b_l
    conv = np.array([[comb(r, j) / comb(d, j) if j <= r else 0.0 for j in range(d + 1)]
                     for r in range(d + 1)])
    out = np.empty((points - 1, d + 1, len(idx)))
    for k in range(points - 1):
        t0 = k * h
        shift = np.array([[comb(i, j) * t0 ** (i - j) * h ** j if j <= i else 0.0
                           for i in range(d + 1)] for j in range(d + 1)])   # (l, i)
        out[k] = conv @ shift @ mono
    return idx, out


def _owned_memo(obj, name: str) -> dict | None:
    """A dict kept on ``obj`` (freed with it; :mod:`ctrplan.objcache`), or None."""
    from ctrplan.objcache import owned

    cache = owned(obj)
    return None if cache is None else cache.setdefault(name, {})


#: allowance (mm) for the float32 round-off of evaluated backbone points in the padding
POINT_ROUNDOFF_MM = 1e-4


def polynomial_pad(fit: np.ndarray, points: int, terms: int, memo: dict | None = None) -> np.ndarray:
    """(B, points - 1) exact bound (mm) of the distance between a polynomial backbone and its
    chords between ``points`` even samples (the learned model's continuity padding).

    The backbone ``p(t) = len * sum_k c_k P_k(t)``, t in [0, 1], is recovered from ``fit``
    (B, mf, 3), its samples at mf > terms even parameters (exactly: the basis has ``terms``
    functions, all zero at t = 0). On each segment of parameter length ``h = 1/(points - 1)``
    the chord error is at most ``h^2 / 8 max |p''|`` (the linear-interpolation bound, for every
    direction), and ``|p''|`` is at most the largest norm of the Bernstein control points of
    ``p''`` on the segment (convex hull property): an exact polynomial bound, no sampling. This
    also bounds the curvature's effect without any curvature bound: the network may bend the
    backbone beyond the tubes' precurvature. ``memo`` : a dict keeping the per-sampling maps
    (the model's own, freed with it), or None."""
    fit = np.asarray(fit, dtype=float)
    B, mf, _ = fit.shape
    if terms < 2 or points < 2:
        return np.zeros((B, max(points - 1, 0)))
    key = (mf, int(points), int(terms))
    hit = None if memo is None else memo.get(key)
    if hit is None:   # (kept in ``memo``: the model's own, one entry per sampling it was asked for)
        hit = _bernstein_second_derivative(mf, points, terms)
        if memo is not None:
            memo[key] = hit
    idx, A = hit
    k, r, mi = A.shape
    # one matrix product for the whole batch: (K (d + 1), mi) @ (mi, B * 3)
    f = np.ascontiguousarray(fit[:, idx].transpose(1, 2, 0)).reshape(mi, 3 * B)
    ctrl = (A.reshape(k * r, mi) @ f).reshape(k, r, 3, B)     # control points of p''
    np.square(ctrl, out=ctrl)
    sq = ctrl[:, :, 0] + ctrl[:, :, 1] + ctrl[:, :, 2]          # (K, d + 1, B)
    peak = np.sqrt(sq.max(axis=1)).T                            # (B, K)
    h = 1.0 / (points - 1)
    # + float32 round-off of the evaluated points (the CPU path's ~1e-5 mm at 200 mm)
    return peak * h * h / 8.0 + POINT_ROUNDOFF_MM


def polynomial_pad_torch(fit: torch.Tensor, points: int, terms: int,
                         memo: dict | None = None) -> torch.Tensor:
    """:func:`polynomial_pad` of float64 backbone samples ``fit`` (B, mf, 3) on their device
    (``memo`` as there)."""
    B, mf, _ = fit.shape
    if terms < 2 or points < 2:
        return torch.zeros(B, max(points - 1, 0), dtype=fit.dtype, device=fit.device)
    key = (mf, int(points), int(terms))
    hit = None if memo is None else memo.get(key)
    if hit is None:
        hit = _bernstein_second_derivative(mf, points, terms)
        if memo is not None:
            memo[key] = hit
    idx, A = hit
    At = torch.as_tensor(A, dtype=fit.dtype, device=fit.device)         # (k, r, mi)
    ctrl = torch.einsum("kri,bic->bkrc", At, fit[:, torch.as_tensor(idx, device=fit.device)])
    peak = torch.sqrt((ctrl * ctrl).sum(dim=3).amax(dim=2))              # (B, k)
    h = 1.0 / (points - 1)
    return peak * (h * h / 8.0) + POINT_ROUNDOFF_MM


def n_direction_features(n: int) -> int:
    """Direction inputs of an n-tube model: 2n signs and n - 1 relative rotation directions."""
    return 3 * n - 1


def direction_features(d: np.ndarray, n: int) -> np.ndarray:
    """(B, 3n - 1) float64: the directions D (B, 2n) and the direction of relative rotation of
    each pair of neighbouring tubes, ``sign(D_alpha_i - D_alpha_i+1)`` (friction between tubes
    follows their relative motion)."""
    d = np.asarray(d, dtype=np.float64)
    return np.ascontiguousarray(np.concatenate([d, np.sign(d[:, :n - 1] - d[:, 1:n])], axis=1))


def error_quantiles(per_config_max: Any) -> dict[str, float]:
    """p50/p95/p99/max (mm) of per-configuration max deviations (non-finite rows ignored)."""
    v = np.asarray(per_config_max, dtype=float)
    v = v[np.isfinite(v)]
    if v.size == 0:
        raise ValueError("no finite errors to take quantiles of")
    return {k: float(np.percentile(v, p)) for k, p in QUANTILES.items()}


def training_domain(robot: Robot, q: np.ndarray, source: str = "") -> dict[str, Any]:
    """The joint ranges seen in ``q`` (see :meth:`LearnedModel.set_domain`)."""
    q = check_q(robot, q)
    n = robot.n
    arcs: list[list[float] | None] = []
    for i in range(n):
        a = np.sort(np.mod(q[:, i], 2 * np.pi))
        gaps = np.diff(np.concatenate([a, a[:1] + 2 * np.pi]))
        k = int(np.argmax(gaps))
        if gaps[k] <= FULL_CIRCLE_GAP:
            arcs.append(None)
            continue
        start = a[(k + 1) % len(a)]                  # the arc runs from after the gap ...
        width = 2 * np.pi - gaps[k]                  # ... around to the gap's start
        centre = (start + width / 2 + np.pi) % (2 * np.pi) - np.pi
        arcs.append([float(centre), float(width / 2)])
    return {"beta_min_mm": q[:, n:].min(axis=0).tolist(), "beta_max_mm": q[:, n:].max(axis=0).tolist(),
            "alpha_arcs_rad": arcs, "tolerance": 1e-6, "rows": int(len(q)), "source": source,
            "rule": "inside the robot's joint limits, the translation range seen per tube and "
                    "the rotation arc seen per tube ([centre, half-width] rad; null = whole circle)"}


def _check_normalisation(model: LearnedModel, src: str) -> None:
    """Refuse a model file whose input scaling cannot give finite shapes: every translation
    span must be a positive length no longer than the plausible tube length (a zero span
    divides by zero and gives NaN backbones), every offset a plausible length, every output
    scale finite and >= 0."""
    from ctrplan.robot import PLAUSIBLE

    top = PLAUSIBLE["length"][1]
    lo = model.beta_lo.double().numpy()
    span = model.beta_span.double().numpy()
    if not np.all(np.isfinite(lo)) or np.any(np.abs(lo) > top):
        raise InputError(src, "normalisation.beta_lo_mm", f"must be finite lengths within +-{top:g} mm")
    if not np.all(np.isfinite(span)) or np.any(span <= 0) or np.any(span > top):
        raise InputError(src, "normalisation.beta_span_mm",
                         f"every span must be > 0 and <= {top:g} mm, got {span.tolist()}"[:200])
    if np.any(model.coef_std.double().numpy() < 0):
        raise InputError(src, "normalisation.coef_std", "must be >= 0")


def _check_quantiles(eq: Any) -> dict[str, float] | None:
    if eq is None:
        return None
    if not isinstance(eq, dict) or set(QUANTILES) - set(eq):
        raise ValueError(f"error_quantiles must have keys {', '.join(QUANTILES)}")
    out = {k: float(eq[k]) for k in QUANTILES}
    if not all(np.isfinite(v) and v >= 0 for v in out.values()):
        raise ValueError("error_quantiles must be finite and >= 0")
    return out


def _check_error_bound(meta: dict, bound: Any, src: str) -> str | None:
    """The file's ``error_bound`` read strictly (``measured`` / ``surrogate``; only with a
    bound); a file without it (older) gets :func:`~ctrplan.shape.error_bounds.inferred_error_bound`."""
    from ctrplan.shape.error_bounds import check_error_bound_kind, inferred_error_bound

    try:
        kind = check_error_bound_kind(meta.get("error_bound"), "error_bound")
    except ValueError as exc:
        raise InputError(src, "error_bound", str(exc).partition(": ")[2]) from None
    if not bound:
        if kind is not None:
            raise InputError(src, "error_bound", "given without error_quantiles or error_profile")
        return None
    return kind if kind is not None else inferred_error_bound(meta)


def _check_domain(dom: Any) -> dict[str, Any] | None:
    if dom is None:
        return None
    if not isinstance(dom, dict):
        raise ValueError("domain is not a mapping")
    for k in ("beta_min_mm", "beta_max_mm", "alpha_arcs_rad"):
        if not isinstance(dom.get(k), list):
            raise ValueError(f"domain.{k} missing")
    for k in ("beta_min_mm", "beta_max_mm"):
        v = np.asarray(dom[k], dtype=float)
        if v.ndim != 1 or not np.all(np.isfinite(v)):
            raise ValueError(f"domain.{k} must be a list of finite numbers")
    lo, hi = np.asarray(dom["beta_min_mm"], dtype=float), np.asarray(dom["beta_max_mm"], dtype=float)
    if lo.shape != hi.shape or np.any(lo > hi):
        raise ValueError("domain.beta_min_mm / beta_max_mm must be finite with min <= max")
    for arc in dom["alpha_arcs_rad"]:
        if arc is not None and (not isinstance(arc, list) or len(arc) != 2
                                or not np.all(np.isfinite(np.asarray(arc, dtype=float)))):
            raise ValueError("domain.alpha_arcs_rad entries must be [centre, half-width] or null")
        if arc is not None:
            c, h = float(arc[0]), float(arc[1])
            if not (np.isfinite(c) and np.isfinite(h) and 0 <= h <= np.pi + 1e-9):
                raise ValueError("domain.alpha_arcs_rad: centre must be finite, half-width in [0, pi]")
    tol = dom.get("tolerance", 0.0)
    if isinstance(tol, bool) or not isinstance(tol, (int, float)) or not (0 <= tol <= 1.0):
        raise ValueError("domain.tolerance must be a number in [0, 1]")
    return dom


class _StoredArchitecture(NamedTuple):
    """What a model file's metadata says about the network (checked by :func:`_read_header`)."""

    width: int
    depth: int
    terms: int
    frame: str
    direction: bool
    pairs: bool
    #: the residual base's spec (None: not a residual model)
    base_spec: dict | None
    error_quantiles: dict[str, float] | None
    error_profile: dict | None
    domain: dict[str, Any] | None
    #: ``normalisation``: coef_mean, coef_std, beta_lo_mm, beta_span_mm (not yet checked)
    normalisation: dict


def _read_header(obj: Any, src: str) -> tuple[dict, _StoredArchitecture]:
    """The format, version and metadata of a loaded model file: (the metadata, its network
    description). :class:`InputError` (``format``, ``version``, ``meta_json``) otherwise."""
    if not isinstance(obj, dict) or not isinstance(obj.get("format"), str) \
            or obj.get("format") != FORMAT:
        raise InputError(src, "format", f"not a {FORMAT} file")
    if not isinstance(obj.get("version"), int) or obj.get("version") not in READ_VERSIONS:
        raise InputError(src, "version", f"unsupported version {obj.get('version')!r} "
                                         f"(reads {', '.join(map(str, READ_VERSIONS))})")
    try:
        meta = json.loads(obj["meta_json"])
        arch, bas, norm = meta["architecture"], meta["basis"], meta["normalisation"]
        width, depth, terms = int(arch["width"]), int(arch["depth"]), int(bas["terms"])
        frame = str(arch.get("frame", "base"))
        if frame not in FRAMES:
            raise ValueError(f"unknown frame {frame!r}")
        direction = bool((meta.get("inputs") or {}).get("direction", False))
        pairs = arch.get("pair_inputs", False)
        if not isinstance(pairs, bool):
            raise ValueError("architecture.pair_inputs must be true or false")
        base_spec = meta.get("residual")
        if base_spec is not None and not isinstance(base_spec, dict):
            raise ValueError("residual is not a mapping")
        eq = _check_quantiles(meta.get("error_quantiles"))
        profile = meta.get("error_profile")
        if profile is not None:
            from ctrplan.shape.error_bounds import profile_from_dict

            profile = profile_from_dict(profile).to_dict()
        domain = _check_domain(meta.get("domain"))
    except (KeyError, TypeError, ValueError, AttributeError) as exc:
        raise InputError(src, "meta_json", f"missing or malformed metadata ({exc})") from None
    return meta, _StoredArchitecture(width, depth, terms, frame, direction, pairs, base_spec, eq,
                                     profile, domain, norm)


def _stored_robot(meta: dict, src: str, robot: Robot | str | None) -> Robot:
    """The robot stored in the file's metadata; with ``robot``, that robot after checking
    that its tubes are the stored ones (:class:`InputError` ``robot`` otherwise)."""
    try:
        stored = robot_from_dict(meta.get("robot"), source=f"{src} (robot)")
    except InputError as exc:
        raise InputError(src, "robot", exc.message) from None
    if robot is None:
        return stored
    robot = load_robot(robot)
    if robot.to_dict()["tubes"] != stored.to_dict()["tubes"]:
        raise InputError(src, "robot", f"the model was trained for robot {stored.name!r}, "
                                       f"whose tubes differ from {robot.name!r}")
    return robot


def _load_weights(model: LearnedModel, state: Any, norm: dict) -> None:
    """Load the stored network weights ``state`` and the output / input normalisation
    ``norm`` into ``model`` (RuntimeError, TypeError, ValueError, ... when they do not fit
    its architecture)."""
    if not isinstance(state, dict):
        raise TypeError("state is not a mapping")
    model.net.load_state_dict(state, strict=True)
    K3 = 3 * model.terms
    for name in ("coef_mean", "coef_std"):
        v = torch.tensor(norm[name], dtype=torch.float32)
        if v.shape != (K3,):
            raise ValueError(f"{name} has shape {tuple(v.shape)}, expected ({K3},)")
        setattr(model, name, v)
    for name in ("beta_lo", "beta_span"):
        v = torch.tensor(norm[name + "_mm"], dtype=torch.float32)
        if v.shape != (model.robot.n,):
            raise ValueError(f"{name}_mm has shape {tuple(v.shape)}, expected ({model.robot.n},)")
        setattr(model, name, v)


def _load_base(spec: dict, obj: dict, src: str, robot: Robot, depth_left: int) -> Any:
    """The base model of a residual model file."""
    kind = spec.get("kind")
    if kind == "rigid":      # closed form (the same shapes as PhysicsModel(torsion=False))
        return RigidModel(robot)
    if kind == "physics":
        from ctrplan.shape.physics import PhysicsModel

        return PhysicsModel(robot)
    if kind == "learned":
        if depth_left <= 0 or not isinstance(obj.get("base"), dict):
            raise InputError(src, "base", "residual model over a learned base without a valid stored base")
        return LearnedModel._from_object(obj["base"], f"{src} (base)", robot, depth_left - 1)
    if kind == "effect":
        from ctrplan.shape.effects import EffectModel

        return EffectModel.from_dict(spec.get("model"), source=f"{src} (residual base)")
    raise InputError(src, "residual", f"unknown base model kind {kind!r}")


def base_model_spec(base: Any) -> dict[str, Any]:
    """The metadata that lets :meth:`LearnedModel.load` rebuild a residual base model."""
    from ctrplan.shape.physics import PhysicsModel

    if isinstance(base, LearnedModel):
        return {"kind": "learned"}
    if isinstance(base, RigidModel):
        return {"kind": "rigid"}
    if isinstance(base, PhysicsModel):
        return {"kind": "physics" if getattr(base, "torsion", True) else "rigid"}
    if hasattr(base, "to_dict") and getattr(base, "name", "") != "learned":
        return {"kind": "effect", "model": base.to_dict()}
    raise ValueError(f"cannot use {type(base).__name__} as a residual base")


def _fd_tip_jacobian(model: Any, q: np.ndarray, d: np.ndarray | None, h: float = 1e-5):
    """Tip and central-difference Jacobian of any shape model (float64 models)."""
    def tip(x):
        if d is not None and _needs_direction(model):
            return model.shape(x, points=2, direction=d).points[:, -1, :]
        return model.backbone(x, 2)[:, -1, :]
    t0 = tip(q)
    J = np.empty((len(q), 3, q.shape[1]))
    for j in range(q.shape[1]):
        e = np.zeros(q.shape[1])
        e[j] = h
        J[:, :, j] = (tip(q + e) - tip(q - e)) / (2 * h)
    return t0, J


def shipped_model_path(robot_name: str) -> Path | None:
    """Path of the shipped default model of a robot, or None."""
    ref = resources.files("ctrplan") / "data" / "models" / f"{robot_name}.pt"
    try:
        p = Path(str(ref))
    except TypeError:  # pragma: no cover - zipped installs
        return None
    return p if p.is_file() else None


def default_model_for(robot: Robot | str, device: str | torch.device | None = None) -> LearnedModel:
    """The shipped default learned model of ``robot`` (``ctrplan/data/models/<name>.pt``) on
    ``device`` (None: :func:`current_device`)."""
    robot = load_robot(robot)
    p = shipped_model_path(robot.name)
    if p is None:
        raise ArgumentError("model", f"no shipped learned model for robot {robot.name!r}; train "
                                     f"one with 'ctrplan train --robot {robot.name} --out model.pt' "
                                     f"and pass the file")
    return LearnedModel.load(p, robot=robot, device=device)
