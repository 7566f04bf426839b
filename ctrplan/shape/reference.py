"""A slow, tight-tolerance reference solver of the mechanics model (a test oracle only).

It shares no code with :mod:`ctrplan.shape._kernel`: the equations (units and frames: docs/conventions.md) are transcribed
literally (angles ``psi`` instead of cos/sin, the full vector ``u`` built from rotated
precurvatures, ``u_i = Rz(psi_i)^T u``), integrated piecewise between break points with
``scipy.integrate.solve_ivp`` (DOP853, rtol/atol 1e-12 by default) and shot with
``scipy.optimize.root`` on ``uz(0)``. One configuration at a time; milliseconds to seconds each.
Never used on a hot path.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.integrate import solve_ivp
from scipy.optimize import root
from scipy.spatial.transform import Rotation

from ctrplan.robot import Robot, load_robot


@dataclass(frozen=True)
class ReferenceResult:
    """One configuration's reference solution.

    points : (m, 3) mm, base frame, at arc lengths ``s`` (m,) mm.
    uz0 : (n,) 1/mm, torsion of each tube at s = 0.
    residual : max |uz_i(end_i)| (1/mm) of the shooting.
    success : the shooting converged.
    """

    points: np.ndarray
    s: np.ndarray
    uz0: np.ndarray
    residual: float
    success: bool


def _hat(v: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _rz(a: float) -> np.ndarray:
    c, s = np.cos(a), np.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class _Problem:
    def __init__(self, robot: Robot, q: np.ndarray, kappa, EI, ratio, kink, torsion: bool,
                 rtol: float, atol: float):
        n = robot.n
        self.n = n
        self.alpha = q[:n]
        self.beta = q[n:]
        self.L = robot.lengths
        self.straight = robot.array("straight_length")
        self.kappa = np.asarray(kappa, dtype=float)
        self.EI = np.asarray(EI, dtype=float)
        self.ratio = np.asarray(ratio, dtype=float)
        self.kink = np.asarray(kink, dtype=float)
        self.torsion = torsion
        self.rtol = rtol
        self.atol = atol
        self.ends = self.beta + self.L
        self.curve_starts = np.maximum(self.beta + self.straight, 0.0)
        self.tip = float(self.ends.max())

    def u_and_uzdot(self, s: float, psi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Backbone curvature u (3,) (uz component 0: the frame is twist-free) and uz_i'."""
        n = self.n
        present = s < self.ends
        curved = present & (s >= self.beta + self.straight)
        uhat = [np.array([0.0, self.kappa[i] if curved[i] else 0.0, 0.0]) for i in range(n)]
        eisum = float(np.sum(self.EI[present]))
        u = np.zeros(3)
        if eisum > 0:
            for j in range(n):
                if present[j]:
                    u += self.EI[j] * (_rz(psi[j]) @ uhat[j])
            u /= eisum
        u[2] = 0.0
        uzdot = np.zeros(n)
        if self.torsion:
            for i in range(n):
                if present[i]:
                    ui = _rz(psi[i]).T @ u
                    uzdot[i] = self.ratio[i] * (ui[0] * uhat[i][1] - ui[1] * uhat[i][0])
        return u, uzdot

    def rhs(self, s: float, y: np.ndarray, frame: bool) -> np.ndarray:
        n = self.n
        psi = y[:n]
        uz = y[n:2 * n]
        u, uzdot = self.u_and_uzdot(s, psi)
        dy = np.zeros_like(y)
        dy[:n] = uz
        dy[n:2 * n] = uzdot
        if frame:
            R = y[2 * n:2 * n + 9].reshape(3, 3)
            dy[2 * n:2 * n + 9] = (R @ _hat(u)).reshape(-1)
            dy[2 * n + 9:] = R[:, 2]
        return dy

    def run(self, x: np.ndarray, s_out: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """Integrate from s = 0; returns (uz at each tube's end (n,), points at s_out)."""
        n = self.n
        frame = s_out is not None
        psi0 = self.alpha - self.beta * x if self.torsion else self.alpha.copy()
        uz0 = x if self.torsion else np.zeros(n)
        y = np.concatenate([psi0, uz0] + ([np.eye(3).reshape(-1), np.zeros(3)] if frame else []))
        breaks = sorted(set([0.0, *self.curve_starts.tolist(), *self.ends.tolist(),
                             *([] if s_out is None else np.asarray(s_out).tolist())]))
        resid = np.zeros(n)
        pts = np.zeros((0 if s_out is None else len(s_out), 3))
        s_now = 0.0

        def record(s_here: float, y: np.ndarray) -> np.ndarray:
            for i in range(n):
                if abs(self.ends[i] - s_here) <= 1e-12:
                    resid[i] = y[n + i]
                    y[n + i] = 0.0
                    if frame and np.any(self.kink[i] != 0):
                        R = y[2 * n:2 * n + 9].reshape(3, 3)
                        rv = np.array([self.kink[i, 0], self.kink[i, 1], 0.0])
                        y[2 * n:2 * n + 9] = (R @ Rotation.from_rotvec(rv).as_matrix()).reshape(-1)
            if frame:
                for k in np.nonzero(np.abs(np.asarray(s_out) - s_here) <= 1e-12)[0]:
                    pts[k] = y[2 * n + 9:]
            return y

        y = record(0.0, y)
        for s_next in breaks[1:]:
            if s_next > s_now:
                # the right-hand side is smooth inside (s_now, s_next); clamping keeps the
                # solver's stage evaluations on this side of the break points
                def f(s, yy, lo=s_now, hi=s_next):
                    return self.rhs(_clamp(s, lo, hi), yy, frame)

                sol = solve_ivp(f, (s_now, s_next), y, method="DOP853", rtol=self.rtol,
                                atol=self.atol)
                if not sol.success:
                    raise RuntimeError(f"reference integration failed: {sol.message}")
                y = sol.y[:, -1].copy()
            y = record(s_next, y)
            s_now = s_next
        return resid, pts


def _clamp(s: float, lo: float, hi: float) -> float:
    # evaluate the regime strictly inside the interval (the ends are break points)
    eps = 1e-9 * max(1.0, hi - lo)
    return min(max(s, lo + eps), hi - eps)


def reference_shape(robot: Robot | str, q: np.ndarray, s_out: np.ndarray | None = None, *,
                    points: int = 20, torsion: bool = True, kappa=None, EI=None, ratio=None,
                    kink=None, x0: np.ndarray | None = None, rtol: float = 1e-12,
                    atol: float = 1e-12, xtol: float = 1e-14) -> ReferenceResult:
    """Reference backbone of ONE configuration.

    q : (2n,) rad and mm. s_out : (m,) arc lengths (mm) of the points; default ``points``
    evenly spaced from 0 to the tip. kappa/EI/ratio : (n,) overrides (1/mm, N mm^2, EI/GJ);
    kink : (n, 2) rad. x0 : (n,) initial guess of uz(0) (default zeros).
    """
    robot = load_robot(robot)
    q = np.asarray(q, dtype=float).reshape(-1)
    n = robot.n
    kappa = robot.array("curvature") if kappa is None else kappa
    EI = robot.array("bending_stiffness") if EI is None else EI
    ratio = (robot.array("bending_stiffness") / robot.array("torsional_stiffness")
             if ratio is None else ratio)
    kink = np.zeros((n, 2)) if kink is None else kink
    prob = _Problem(robot, q, kappa, EI, ratio, kink, torsion, rtol, atol)
    if s_out is None:
        s_out = np.linspace(0.0, prob.tip, points)
    s_out = np.asarray(s_out, dtype=float)
    x = np.zeros(n) if x0 is None else np.asarray(x0, dtype=float).copy()
    success = True
    resid = 0.0
    if torsion:
        sol = root(lambda xx: prob.run(xx, None)[0], x, method="hybr", options={"xtol": xtol})
        x = sol.x
        resid = float(np.max(np.abs(prob.run(x, None)[0])))
        success = bool(resid < 1e-10)
    else:
        x = np.zeros(n)
    _, pts = prob.run(x, s_out)
    return ReferenceResult(points=pts, s=s_out, uz0=x, residual=resid, success=success)
