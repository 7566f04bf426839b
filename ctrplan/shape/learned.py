"""Learned full-shape model: configuration -> polynomial backbone coefficients (torch MLP).

Network (one per robot):

* input, per tube i: ``cos alpha_i, sin alpha_i, beta_i~`` with ``beta_i~`` the translation
  scaled to [-1, 1] over the robot's joint range (``2 (beta - lo) / (hi - lo) - 1``);
* ``depth`` hidden layers of ``width`` neurons, each Linear + PReLU (default 3 hidden layers of
  30 neurons, "3 x 30");
* output: ``3 K`` numbers ``z``, de-normalised to coefficients ``c = mean + std * z`` (mean, std
  from the training set) and arranged as (K, 3);
* backbone ``x(q, s) = len(q) * sum_k c_k P_k(s / len(q))`` with :mod:`ctrplan.shape.basis`,
  ``len(q)`` the arc length to the tip (:meth:`Robot.tip_length`).

Frame ``outer`` (default): the angles enter relative to the outermost tube's and the backbone
is predicted in a frame turned with that tube, which is exact for an unloaded CTR (turning
every tube by the same angle turns the backbone about the insertion axis) and leaves one angle
less to learn; frame ``base`` uses the absolute angles as the literature does.

The whole batch goes through one forward pass (float32, CPU unless ``device=`` says otherwise;
batches up to :data:`SMALL_BATCH` use a compiled float64 kernel for low latency).
``tip_and_jacobian`` differentiates the torch path with autograd (for inverse kinematics).
Model files are written with :func:`torch.save` and read with ``torch.load(weights_only=True)``:
they hold only tensors and a JSON string of metadata (robot, basis, normalisation,
architecture, training-data hashes, metrics), never pickled code.
"""

from __future__ import annotations

import json
import os
from importlib import resources
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from ctrplan.errors import InputError
from ctrplan.io import jsonable
from ctrplan.robot import Robot, load_robot, robot_from_dict
from ctrplan.shape import basis
from ctrplan.shape.base import Shape, check_q, radius_along

FORMAT = "ctrplan-learned-model"
FORMAT_VERSION = 1
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
                 seed: int | None = 0, frame: str = DEFAULT_FRAME):
        self.robot = load_robot(robot)
        if frame not in FRAMES:
            raise ValueError(f"frame must be one of {FRAMES}, got {frame!r}")
        self.frame = frame
        self.width, self.depth, self.terms = int(width), int(depth), int(terms)
        basis.coefficients(self.terms)  # validates terms
        n = self.robot.n
        if seed is not None:
            torch.manual_seed(seed)
        self.net = ShapeNet(3 * n, 3 * self.terms, self.width, self.depth)
        lo, hi = self.robot.beta_bounds()
        span = np.where(hi - lo > 0, hi - lo, 1.0)
        self.beta_lo = torch.tensor(lo, dtype=torch.float32)
        self.beta_span = torch.tensor(span, dtype=torch.float32)
        self.coef_mean = torch.zeros(3 * self.terms)
        self.coef_std = torch.ones(3 * self.terms)
        self.lengths = torch.tensor(self.robot.lengths, dtype=torch.float32)
        self.meta: dict[str, Any] = {}
        self._device = torch.device("cpu")
        self._basis_cache: dict[tuple[int, str], torch.Tensor] = {}
        self.net.eval()
        self.to(device)

    # ------------------------------------------------------------------ device / repr
    @property
    def device(self) -> torch.device:
        return self._device

    def to(self, device: str | torch.device) -> LearnedModel:
        """Move the network to ``device`` (in place); returns self."""
        self._device = torch.device(device)
        self.net.to(self._device)
        for k in ("beta_lo", "beta_span", "coef_mean", "coef_std", "lengths"):
            setattr(self, k, getattr(self, k).to(self._device))
        self._basis_cache = {}
        return self

    def __repr__(self) -> str:
        return (f"LearnedModel(robot={self.robot.name!r}, width={self.width}, depth={self.depth}, "
                f"terms={self.terms}, frame={self.frame!r}, device={str(self._device)!r})")

    def __getstate__(self) -> dict:  # picklable for process pools: move to CPU tensors
        st = dict(self.__dict__)
        st["_basis_cache"] = {}
        return st

    # ------------------------------------------------------------------ torch path
    def features(self, q: torch.Tensor) -> torch.Tensor:
        """Network input (B, 3n): per tube cos alpha, sin alpha, beta scaled to [-1, 1]
        (with frame "outer", alpha relative to the outermost tube's)."""
        n = self.robot.n
        a, b = q[:, :n], q[:, n:]
        if self.frame == "outer":
            a = a - a[:, n - 1:n]
        bs = 2.0 * (b - self.beta_lo) / self.beta_span - 1.0
        return torch.stack([torch.cos(a), torch.sin(a), bs], dim=2).reshape(len(q), 3 * n)

    def coefficients_t(self, q: torch.Tensor) -> torch.Tensor:
        """Basis coefficients (B, K, 3) (dimensionless, base frame) for q (B, 2n)."""
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

    def points_t(self, q: torch.Tensor, points: int = 20) -> torch.Tensor:
        """Differentiable backbones (B, points, 3) mm from q (B, 2n) tensors on the device."""
        return self._to_base(q, self.points_from_features(self.features(q), self.tip_length_t(q), points))

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

    def _fast_points(self, qt: torch.Tensor, points: int) -> torch.Tensor:
        """Inference-only forward pass (no autograd, fused last layer), (B, points, 3)."""
        hidden, Wf, bf = self._fused(points)
        h = self.features(qt)
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

    def _numpy_points(self, q: np.ndarray, points: int) -> np.ndarray:
        """The same forward pass in float64 by a small compiled (numba) kernel: the lowest
        latency for small batches (a torch call costs microseconds per operation)."""
        from ctrplan.shape import _learned_kernel

        W0, Wh, bh, slopes, Wl, bl, lo, inv, L = self._numba_weights()
        phi = self._phi_np(points)
        out = np.empty((len(q), points, 3))
        _learned_kernel.forward(np.ascontiguousarray(q, dtype=np.float64), self.robot.n,
                                self.frame == "outer", lo, inv, L, W0, Wh, bh, slopes, Wl, bl, phi, out)
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

    def _cpu_points(self, q: np.ndarray, points: int) -> np.ndarray:
        """CPU inference in float32 chunks that stay in cache; returns float64 (B, points, 3).

        Features in numpy (vectorised float32 cos/sin), the MLP in torch, the rotation of the
        "outer" frame applied to the (B, K) coefficients before the basis expansion."""
        hidden, Wl, bl, M, lo, inv, L = self._cpu_weights(points)
        n, K, B = self.robot.n, self.terms, len(q)
        q32 = np.asarray(q, dtype=np.float32)
        a, b = q32[:, :n], q32[:, n:]
        ar = a - a[:, n - 1:n] if self.frame == "outer" else a
        feats = np.empty((B, n, 3), dtype=np.float32)
        np.cos(ar, out=feats[:, :, 0])
        np.sin(ar, out=feats[:, :, 1])
        feats[:, :, 2] = (b - lo) * inv - 1.0
        length = torch.from_numpy(np.max(b + L, axis=1))
        X = torch.from_numpy(feats.reshape(B, 3 * n))
        if self.frame == "outer":
            cr = torch.from_numpy(np.cos(a[:, n - 1]))
            sr = torch.from_numpy(np.sin(a[:, n - 1]))
        out = np.empty((B, points, 3), dtype=np.float64)
        flat = out.reshape(B, 3 * points)
        slopes = [float(sl.reshape(-1)[0]) for _, _, sl in hidden]
        rows = min(CHUNK, B)
        bufs = [torch.empty(rows, Wt.shape[1]) for Wt, _, _ in hidden]
        cbuf = torch.empty(rows, Wl.shape[1])
        pbuf = torch.empty(rows, M.shape[1])
        with torch.inference_mode():
            for i in range(0, B, CHUNK):
                r = min(CHUNK, B - i)
                h = X[i:i + r]
                for (Wt, bb, _), a_, buf in zip(hidden, slopes, bufs):
                    hb = buf[:r]
                    torch.addmm(bb, h, Wt, out=hb)
                    torch.nn.functional.leaky_relu_(hb, a_)   # PReLU with one slope per layer
                    h = hb
                c = cbuf[:r]
                torch.addmm(bl, h, Wl, out=c)
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
    def backbone(self, q: np.ndarray, points: int = 20) -> np.ndarray:
        """(B, points, 3) backbone points, mm, robot base frame (one forward pass)."""
        if points < 2:
            raise ValueError("points must be >= 2 (base and tip)")
        q = check_q(self.robot, q)
        if self._device.type == "cpu":
            if len(q) <= SMALL_BATCH:
                return self._numpy_points(q, points)
            return self._cpu_points(q, points)
        with torch.inference_mode():
            out = self._fast_points(self._as_tensor(q), points)
        return out.cpu().numpy().astype(np.float64)

    def shape(self, q: np.ndarray, points: int = 20) -> Shape:
        """Backbones with radii; ``ok`` is all True (the network always answers)."""
        q = check_q(self.robot, q)
        pts = self.backbone(q, points)
        s = np.linspace(0.0, 1.0, points)[None, :] * self.robot.tip_length(q)[:, None]
        return Shape(points=pts, s=s, radius=radius_along(self.robot, q, s),
                     ok=np.ones(len(q), dtype=bool))

    def tip_and_jacobian(self, q: np.ndarray, method: str = "auto") -> tuple[np.ndarray, np.ndarray]:
        """Tip positions (B, 3) mm and their Jacobians d tip / d q (B, 3, 2n).

        Columns are per joint: alpha in mm/rad, beta in mm/mm. ``method``: "compiled"
        (forward-mode derivatives in a numba kernel, float64, the default on the CPU) or
        "autograd" (torch autograd through the float32 network, any device). The tip length
        ``max(beta + L)`` is piecewise linear; at a tie the derivative follows one tube.
        """
        q = check_q(self.robot, q)
        if method == "auto":
            method = "compiled" if self._device.type == "cpu" else "autograd"
        if method == "compiled":
            from ctrplan.shape import _learned_kernel

            W0, Wh, bh, slopes, Wl, bl, lo, inv, L = self._numba_weights()
            ptip = np.ascontiguousarray(basis.evaluate(np.array(1.0), self.terms))
            B, D = len(q), self.robot.dof
            tip = np.empty((B, 3))
            J = np.empty((B, 3, D))
            _learned_kernel.tip_jacobian(np.ascontiguousarray(q, dtype=np.float64), self.robot.n,
                                         self.frame == "outer", lo, inv, L, W0, Wh, bh, slopes,
                                         Wl, bl, ptip, tip, J)
            return tip, J
        if method != "autograd":
            raise ValueError(f"method must be 'auto', 'compiled' or 'autograd', got {method!r}")
        qt = self._as_tensor(q).requires_grad_(True)
        with torch.enable_grad():
            tip_t = self.points_t(qt, 2)[:, -1, :]                      # (B, 3)
            rows = []
            for c in range(3):
                (g,) = torch.autograd.grad(tip_t[:, c].sum(), qt, retain_graph=c < 2)
                rows.append(g)
        Jt = torch.stack(rows, dim=1)
        return tip_t.detach().cpu().numpy().astype(np.float64), Jt.cpu().numpy().astype(np.float64)

    # ------------------------------------------------------------------ files
    def metadata(self) -> dict[str, Any]:
        meta = dict(self.meta)
        meta.update({
            "robot": self.robot.to_dict(),
            "architecture": {"width": self.width, "depth": self.depth, "activation": "PReLU",
                             "frame": self.frame,
                             "inputs": "per tube: cos alpha, sin alpha, 2 (beta - lo) / (hi - lo) - 1"
                                       + (" (alpha relative to the outermost tube's; output "
                                          "turned by it)" if self.frame == "outer" else ""),
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

        state = {k: v.detach().cpu().contiguous() for k, v in self.net.state_dict().items()}
        obj = {"format": FORMAT, "version": FORMAT_VERSION,
               "meta_json": json.dumps(jsonable(self.metadata()), allow_nan=False),
               "state": state}
        with atomic_path(path) as tmp:
            torch.save(obj, tmp)

    @classmethod
    def load(cls, path: str | os.PathLike, robot: Robot | str | None = None,
             device: str | torch.device = "cpu") -> LearnedModel:
        """Read a model file written by :meth:`save` / ``ctrplan train``.

        ``robot``: check the file was trained for this robot (same tubes); by default the
        robot stored in the file is used. Errors (missing, corrupt, mismatched) raise
        :class:`InputError` naming the file.
        """
        src = str(path)
        p = Path(path)
        if not p.is_file():
            raise InputError(src, "", "model file not found")
        try:
            obj = torch.load(p, map_location="cpu", weights_only=True)
        except Exception as exc:  # corrupt, truncated, or not a torch file
            raise InputError(src, "", f"not a readable ctrplan model file ({exc.__class__.__name__})") from None
        if not isinstance(obj, dict) or obj.get("format") != FORMAT:
            raise InputError(src, "format", f"not a {FORMAT} file")
        if obj.get("version") != FORMAT_VERSION:
            raise InputError(src, "version", f"unsupported version {obj.get('version')!r} (expected {FORMAT_VERSION})")
        try:
            meta = json.loads(obj["meta_json"])
            arch, bas, norm = meta["architecture"], meta["basis"], meta["normalisation"]
            width, depth, terms = int(arch["width"]), int(arch["depth"]), int(bas["terms"])
            frame = str(arch.get("frame", "base"))
            if frame not in FRAMES:
                raise ValueError(f"unknown frame {frame!r}")
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(src, "meta_json", f"missing or malformed metadata ({exc})") from None
        try:
            stored = robot_from_dict(meta.get("robot"), source=f"{src} (robot)")
        except InputError as exc:
            raise InputError(src, "robot", exc.message) from None
        if robot is not None:
            robot = load_robot(robot)
            if robot.to_dict()["tubes"] != stored.to_dict()["tubes"]:
                raise InputError(src, "robot", f"the model was trained for robot {stored.name!r}, "
                                               f"whose tubes differ from {robot.name!r}")
        else:
            robot = stored
        try:
            model = cls(robot, width=width, depth=depth, terms=terms, seed=None, frame=frame)
            state = obj["state"]
            if not isinstance(state, dict):
                raise TypeError("state is not a mapping")
            model.net.load_state_dict(state, strict=True)
            K3 = 3 * terms
            for name in ("coef_mean", "coef_std"):
                v = torch.tensor(norm[name], dtype=torch.float32)
                if v.shape != (K3,):
                    raise ValueError(f"{name} has shape {tuple(v.shape)}, expected ({K3},)")
                setattr(model, name, v)
            for name in ("beta_lo", "beta_span"):
                v = torch.tensor(norm[name + "_mm"], dtype=torch.float32)
                if v.shape != (robot.n,):
                    raise ValueError(f"{name}_mm has shape {tuple(v.shape)}, expected ({robot.n},)")
                setattr(model, name, v)
        except (RuntimeError, KeyError, TypeError, ValueError) as exc:
            raise InputError(src, "state", f"weights do not match the stored architecture ({exc})".replace("\n", " ")[:400]) from None
        for t in list(model.net.state_dict().values()) + [model.coef_mean, model.coef_std, model.beta_span]:
            if not torch.all(torch.isfinite(t)):
                raise InputError(src, "state", "contains non-finite weights")
        keep = ("training", "metrics", "data", "created", "command", "ctrplan_version")
        model.meta = {k: meta[k] for k in keep if k in meta}
        model.source = src
        return model.to(device)


def shipped_model_path(robot_name: str) -> Path | None:
    """Path of the shipped default model of a robot, or None."""
    ref = resources.files("ctrplan") / "data" / "models" / f"{robot_name}.pt"
    try:
        p = Path(str(ref))
    except TypeError:  # pragma: no cover - zipped installs
        return None
    return p if p.is_file() else None


def default_model_for(robot: Robot | str, device: str | torch.device = "cpu") -> LearnedModel:
    """The shipped default learned model of ``robot`` (``ctrplan/data/models/<name>.pt``)."""
    robot = load_robot(robot)
    p = shipped_model_path(robot.name)
    if p is None:
        raise InputError("--model", "learned",
                         f"no shipped learned model for robot {robot.name!r}; train one with "
                         f"'ctrplan train --robot {robot.name} --out model.pt' and pass the file")
    return LearnedModel.load(p, robot=robot, device=device)
