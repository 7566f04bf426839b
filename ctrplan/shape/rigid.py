"""Closed-form torsionally rigid CTR kinematics: the learned model's analytic base.

The torsionally rigid ("traditional") model is piecewise constant curvature: between the
break points (where a tube's curved section starts or a tube ends) the backbone's bending
curvature is the EI-weighted mean of the rotated precurvatures of the tubes present,

    u = (ux, uy, 0) = sum_j EI_j kappa_j (-sin alpha_j, cos alpha_j, 0) / sum_j EI_j

(kappa_j only on tube j's curved section; the sums over the tubes present at s), so each
piece is a circular arc in closed form. With ``k = |u|``, ``A = sin(k t) / k`` and
``C = (1 - cos(k t)) / k^2`` (Taylor series for small ``k t``):

    p(s_a + t) = p(s_a) + R(s_a) (C uy, -C ux, A)
    R(s_a + t) = R(s_a) (I + A [u]x + C [u]x^2)

from ``p(0) = 0``, ``R(0) = I`` (conventions of :mod:`ctrplan.shape._kernel`, whose rigid model
integrates the same equations; the two agree to round-off, ``tests/test_rigid.py``). No
shooting and no stepping: one sin/cos per output point and per piece, so it costs a fraction
of the compliant model (about 0.2 us per shape against about 11 us). The compliant model's
shape differs from it only by the tubes' twist, a smooth function of the arc length: the
learned model predicts that difference (:mod:`ctrplan.shape.learned`, residual mode).

Two implementations of the same formulas: a numba kernel (CPU, any batch) and a batched
torch one (:func:`rigid_points_torch`, for the learned model on a GPU).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from ctrplan.robot import Robot, load_robot
from ctrplan.shape.base import Shape, check_q, radius_along

#: below this |k t| the arc coefficients use their Taylor series (no cancellation)
_SERIES_BELOW = 1e-3


@njit(cache=True, error_model="numpy", inline="always")
def _arc(k2, t):
    """(A, C) = (sin(k t) / k, (1 - cos(k t)) / k^2) for k^2 = k2 >= 0."""
    k = math.sqrt(k2)
    x = k * t
    if x < _SERIES_BELOW:
        x2 = x * x
        return t * (1.0 - x2 / 6.0 + x2 * x2 / 120.0), t * t * (0.5 - x2 / 24.0 + x2 * x2 / 720.0)
    return math.sin(x) / k, (1.0 - math.cos(x)) / k2


@njit(cache=True, error_model="numpy", inline="always")
def _break_points(q, b, L, straight, ca, sa, ev):
    """The pieces of configuration b: cos, sin of each tube's alpha into ca, sa (n,), the
    break points inside (0, tip) (curve starts, tube ends) sorted into ev[:ne] and the tip
    arc length into ev[ne] (mm). Returns (ne, tip)."""
    n = L.shape[0]
    tip = -1e300
    for i in range(n):
        ca[i] = math.cos(q[b, i])
        sa[i] = math.sin(q[b, i])
        e = q[b, n + i] + L[i]
        if e > tip:
            tip = e
    ne = 0
    for i in range(n):
        for v in (q[b, n + i] + straight[i], q[b, n + i] + L[i]):
            if v > 0.0 and v < tip:
                ev[ne] = v
                ne += 1
    for k in range(1, ne):                     # insertion sort of the break points
        v = ev[k]
        j = k - 1
        while j >= 0 and ev[j] > v:
            ev[j + 1] = ev[j]
            j -= 1
        ev[j + 1] = v
    ev[ne] = tip
    return ne, tip


@njit(cache=True, error_model="numpy", inline="always")
def _curvature(q, b, L, straight, kappa, EI, ca, sa, mid):
    """(ux, uy) 1/mm: the bending curvature of the piece around arc length ``mid``, the
    EI-weighted mean of the rotated precurvatures of the tubes present."""
    n = L.shape[0]
    eis = 0.0
    ux = 0.0
    uy = 0.0
    for i in range(n):
        if q[b, n + i] + L[i] > mid:
            eis += EI[i]
            if q[b, n + i] + straight[i] < mid:
                ux -= EI[i] * kappa[i] * sa[i]
                uy += EI[i] * kappa[i] * ca[i]
    if eis > 0.0:
        ux /= eis
        uy /= eis
    return ux, uy


@njit(cache=True, error_model="numpy", inline="always")
def _arc_points(out, b, j, m, h, tip, s_a, s_b, last, ux, uy, k2, R, px, py, pz):
    """Write the output points j, j + 1, ... that lie on the piece [s_a, s_b] (all remaining
    ones on the ``last`` piece) into out[b]: the arc of curvature (ux, uy) from the frame
    (R, p) at s_a. Returns the next point's index."""
    k = math.sqrt(k2)
    series = k * (s_b - s_a) < _SERIES_BELOW or k * (tip - s_a) < _SERIES_BELOW
    first = True
    chh = 1.0
    shh = 0.0
    cdh = 1.0
    sdh = 0.0
    while j < m and (last or j * h <= s_b):
        t = (tip if j == m - 1 else j * h) - s_a
        if series:
            A, C = _arc(k2, t)
        else:
            # half angles x / 2 = k t / 2 advanced by k h / 2 from point to point
            # (no trig per point); sin x = 2 s c, 1 - cos x = 2 s^2 (no cancellation)
            if first or j == m - 1:
                chh = math.cos(0.5 * k * t)
                shh = math.sin(0.5 * k * t)
                if first:
                    cdh = math.cos(0.5 * k * h)
                    sdh = math.sin(0.5 * k * h)
            A = 2.0 * shh * chh / k
            C = 2.0 * shh * shh / k2
            c_next = chh * cdh - shh * sdh
            shh = shh * cdh + chh * sdh
            chh = c_next
        first = False
        dx = C * uy
        dy = -C * ux
        out[b, j, 0] = px + R[0, 0] * dx + R[0, 1] * dy + R[0, 2] * A
        out[b, j, 1] = py + R[1, 0] * dx + R[1, 1] * dy + R[1, 2] * A
        out[b, j, 2] = pz + R[2, 0] * dx + R[2, 1] * dy + R[2, 2] * A
        j += 1
    return j


@njit(cache=True, error_model="numpy", inline="always")
def _advance(R, Rn, px, py, pz, ux, uy, k2, t):
    """The frame at the end of an arc of length t mm and curvature (ux, uy): R (3, 3) updated
    in place (Rn (3, 3) is scratch); returns the new position (px, py, pz) mm."""
    A, C = _arc(k2, t)
    dx = C * uy
    dy = -C * ux
    px += R[0, 0] * dx + R[0, 1] * dy + R[0, 2] * A
    py += R[1, 0] * dx + R[1, 1] * dy + R[1, 2] * A
    pz += R[2, 0] * dx + R[2, 1] * dy + R[2, 2] * A
    # E = I + A [u]x + C [u]x^2, [u]x^2 = u u^T - k^2 I (uz = 0)
    e00 = 1.0 + C * (ux * ux - k2)
    e01 = C * ux * uy
    e02 = A * uy
    e11 = 1.0 + C * (uy * uy - k2)
    e12 = -A * ux
    e22 = 1.0 - C * k2
    for r in range(3):
        r0 = R[r, 0]
        r1 = R[r, 1]
        r2 = R[r, 2]
        Rn[r, 0] = r0 * e00 + r1 * e01 - r2 * e02
        Rn[r, 1] = r0 * e01 + r1 * e11 - r2 * e12
        Rn[r, 2] = r0 * e02 + r1 * e12 + r2 * e22
    for r in range(3):
        for c in range(3):
            R[r, c] = Rn[r, c]
    return px, py, pz


@njit(cache=True, error_model="numpy")
def rigid_points(q, L, straight, kappa, EI, m, out):
    """Backbones of the torsionally rigid model.

    q (B, 2n) rad, mm; L, straight, kappa, EI (n,) tube length mm, straight length mm,
    precurvature 1/mm, bending stiffness; out (B, m, 3) mm, written in place: m points evenly
    spaced in arc length from s = 0 to the tip."""
    B = q.shape[0]
    n = L.shape[0]
    ev = np.empty(2 * n + 1)
    ca = np.empty(n)
    sa = np.empty(n)
    R = np.empty((3, 3))
    Rn = np.empty((3, 3))
    for b in range(B):
        ne, tip = _break_points(q, b, L, straight, ca, sa, ev)
        for r in range(3):
            for c in range(3):
                R[r, c] = 1.0 if r == c else 0.0
        px = 0.0
        py = 0.0
        pz = 0.0
        s_a = 0.0
        j = 0
        h = tip / (m - 1)
        for seg in range(ne + 1):
            s_b = ev[seg]
            last = seg == ne
            if s_b <= s_a and not last:
                continue
            ux, uy = _curvature(q, b, L, straight, kappa, EI, ca, sa, 0.5 * (s_a + s_b))
            k2 = ux * ux + uy * uy
            j = _arc_points(out, b, j, m, h, tip, s_a, s_b, last, ux, uy, k2, R, px, py, pz)
            if last:
                break
            px, py, pz = _advance(R, Rn, px, py, pz, ux, uy, k2, s_b - s_a)
            s_a = s_b


class RigidModel:
    """The torsionally rigid model in closed form (the same shapes as
    ``PhysicsModel(robot, torsion=False)``, to round-off, much faster).

    Implements the ShapeModel protocol; ``name`` is ``"rigid"``. Its ``pad`` is the sagitta of
    the robot's largest precurvature (the bending curvature is an EI-weighted mean of the
    rotated precurvatures), as the physics model's."""

    name = "rigid"
    torsion = False

    def __init__(self, robot: Robot | str):
        self.robot = load_robot(robot)
        r = self.robot
        self._L = np.ascontiguousarray(r.lengths)
        self._straight = np.ascontiguousarray(r.array("straight_length"))
        self._kappa = np.ascontiguousarray(r.array("curvature"))
        self._EI = np.ascontiguousarray(r.array("bending_stiffness"))
        self.max_curvature = float(np.max(np.abs(self._kappa))) if r.n else 0.0
        self._torch: dict = {}

    def __repr__(self) -> str:
        return f"RigidModel(robot={self.robot.name!r})"

    def points(self, q: np.ndarray, points: int = 20) -> np.ndarray:
        """(B, points, 3) mm for checked q (B, 2n) (no validation: internal fast path)."""
        out = np.empty((len(q), int(points), 3))
        rigid_points(np.ascontiguousarray(q, dtype=np.float64), self._L, self._straight,
                     self._kappa, self._EI, int(points), out)
        return out

    def points_torch(self, q, points: int = 20):
        """The backbones with torch on the device of ``q`` (B, 2n) (float64 advised):
        :func:`rigid_points_torch`."""
        import torch

        key = (str(q.device), q.dtype)
        consts = self._torch.get(key)
        if consts is None:
            consts = self._torch[key] = tuple(
                torch.as_tensor(a, dtype=q.dtype, device=q.device)
                for a in (self._L, self._straight, self._kappa, self._EI))
        return rigid_points_torch(q, *consts, int(points))

    def pad(self, q: np.ndarray, points: int = 20) -> np.ndarray:
        """(B, points - 1) mm: the sagitta ``kappa_max h^2 / 8`` of each segment between the
        ``points`` evenly spaced backbone points (``h`` = tip arc length / (points - 1))."""
        h = self.robot.tip_length(q) / (int(points) - 1)
        return np.repeat((self.max_curvature * h * h / 8.0)[:, None], int(points) - 1, axis=1)

    def backbone(self, q: np.ndarray, points: int = 20) -> np.ndarray:
        """(B, points, 3) backbone points, mm, robot base frame."""
        if points < 2:
            raise ValueError("points must be >= 2 (base and tip)")
        return self.points(check_q(self.robot, q), points)

    def shape(self, q: np.ndarray, points: int = 20) -> Shape:
        """Backbones with radii, ``ok`` (finite) and the sagitta pad. q : (B, 2n)."""
        if points < 2:
            raise ValueError("points must be >= 2 (base and tip)")
        q = check_q(self.robot, q)
        pts = self.points(q, points)
        s = np.linspace(0.0, 1.0, points)[None, :] * self.robot.tip_length(q)[:, None]
        return Shape(points=pts, s=s, radius=radius_along(self.robot, q, s),
                     ok=np.ones(len(q), dtype=bool), pad=self.pad(q, points))


def rigid_points_torch(q, L, straight, kappa, EI, m: int):
    """The same backbones with torch on q's device: q (B, 2n) tensor; L, straight, kappa, EI
    (n,) tensors of q's dtype and device; returns (B, m, 3). Batched over configurations: a
    loop over the (at most 2n + 1) arc pieces, every output point placed on its piece."""
    import torch

    B, n = q.shape[0], L.shape[0]
    alpha, beta = q[:, :n], q[:, n:]
    ends = beta + L                                              # (B, n)
    starts = beta + straight
    tip = ends.max(dim=1).values                                 # (B,)
    ev = torch.cat([starts, ends], dim=1).clamp(min=0.0)
    ev = torch.minimum(ev, tip[:, None])
    ev = torch.sort(torch.cat([torch.zeros_like(tip)[:, None], ev], dim=1), dim=1).values
    # the pieces [ev_k, ev_k+1], k = 0..2n - 1 (some of zero length)
    s_a, s_b = ev[:, :-1], ev[:, 1:]                             # (B, P)
    mid = 0.5 * (s_a + s_b)
    present = (ends[:, None, :] > mid[:, :, None]).to(q.dtype)   # (B, P, n)
    curved = present * (starts[:, None, :] < mid[:, :, None]).to(q.dtype)
    eis = (present * EI).sum(dim=2).clamp(min=torch.finfo(q.dtype).tiny)
    w = curved * (EI * kappa)
    ux = -(w * torch.sin(alpha)[:, None, :]).sum(dim=2) / eis    # (B, P)
    uy = (w * torch.cos(alpha)[:, None, :]).sum(dim=2) / eis

    def arc(k2, t):
        k = torch.sqrt(k2)
        x = k * t
        small = x < _SERIES_BELOW
        ks = torch.where(small, torch.ones_like(k), k)
        x2 = x * x
        A = torch.where(small, t * (1 - x2 / 6 + x2 * x2 / 120), torch.sin(x) / ks)
        C = torch.where(small, t * t * (0.5 - x2 / 24 + x2 * x2 / 720), (1 - torch.cos(x)) / (ks * ks))
        return A, C

    k2 = ux * ux + uy * uy
    A, C = arc(k2, s_b - s_a)
    P = s_a.shape[1]
    Rs = [torch.eye(3, dtype=q.dtype, device=q.device).expand(B, 3, 3)]
    ps = [torch.zeros(B, 3, dtype=q.dtype, device=q.device)]
    for k in range(P - 1):                                       # frames at each piece start
        d = torch.stack([C[:, k] * uy[:, k], -C[:, k] * ux[:, k], A[:, k]], dim=1)
        ps.append(ps[-1] + torch.einsum("bij,bj->bi", Rs[-1], d))
        a, c, x, y, kk = A[:, k], C[:, k], ux[:, k], uy[:, k], k2[:, k]
        E = torch.stack([torch.stack([1 + c * (x * x - kk), c * x * y, a * y], dim=1),
                         torch.stack([c * x * y, 1 + c * (y * y - kk), -a * x], dim=1),
                         torch.stack([-a * y, a * x, 1 - c * kk], dim=1)], dim=1)
        Rs.append(torch.bmm(Rs[-1], E))
    Rs_t, ps_t = torch.stack(Rs, dim=1), torch.stack(ps, dim=1)  # (B, P, 3, 3), (B, P, 3)
    s = torch.linspace(0.0, 1.0, m, dtype=q.dtype, device=q.device)[None, :] * tip[:, None]
    idx = (s[:, :, None] >= s_a[:, None, :]).sum(dim=2).clamp(min=1) - 1      # (B, m)
    g = lambda v: torch.gather(v, 1, idx)                        # noqa: E731
    t = s - g(s_a)
    kx, ky, kk = g(ux), g(uy), g(k2)
    a, c = arc(kk, t)
    d = torch.stack([c * ky, -c * kx, a], dim=2)                  # (B, m, 3)
    Rj = torch.gather(Rs_t, 1, idx[:, :, None, None].expand(B, m, 3, 3))
    pj = torch.gather(ps_t, 1, idx[:, :, None].expand(B, m, 3))
    return pj + torch.einsum("bmij,bmj->bmi", Rj, d)
