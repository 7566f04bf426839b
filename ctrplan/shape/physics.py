"""Batched mechanics shape models: torsionally rigid and torsionally compliant CTRs.

See :mod:`ctrplan.shape._kernel` for the equations. Both models run a whole batch in one
compiled call; the single-configuration call is the same function with ``B = 1``.
"""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass, replace

import numpy as np

from ctrplan.robot import Robot, load_robot
from ctrplan.shape import _shooting
from ctrplan.shape.base import Shape, check_q, radius_along

_warmup: subprocess.Popen | None = None


def compile_in_background() -> None:
    """Start compiling the mechanics kernel in a separate process, so that a caller that needs
    it only later (``ctrplan demo``: the physics check of a plan made with the learned model)
    overlaps numba's first, uncached compile (~15-25 s) with its own work on another core.

    numba writes the compiled kernel to its on-disk cache; the first :meth:`PhysicsModel.solve`
    in this process waits for the helper and then loads it from there. With a warm cache the
    helper only imports and exits (about a second on the other core); if it fails, the solve
    compiles in process as usual.
    """
    global _warmup
    if _warmup is None:
        _warmup = subprocess.Popen(
            [sys.executable, "-c", "import ctrplan.shape.physics as p; p._compile_now()"],
            stdin=subprocess.DEVNULL, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def _compile_now() -> None:
    robot = load_robot("seed1")
    PhysicsModel(robot).backbone(robot.sample(1, seed=0), 2)


def _wait_for_warmup() -> None:
    """Wait for the helper of :func:`compile_in_background`, if one was started."""
    global _warmup
    proc, _warmup = _warmup, None
    if proc is not None:
        try:
            proc.wait(timeout=600)
        except subprocess.TimeoutExpired:  # pragma: no cover - compiles in process instead
            proc.kill()


@dataclass(frozen=True)
class PhysicsConfig:
    """Numerical settings of the mechanics model.

    step_mm : largest RK4 step (mm), used only where two or more curved sections overlap in
        the torsionally compliant model (everything else is integrated exactly); such
        intervals between break points are cut into equal steps. At the default 10 mm the
        ``seed1`` backbones agree with a tight scipy solution to about 1e-5 mm.
    tol : shooting tolerance on the distal torsion boundary values max_i |uz_i(end)| (1/mm).
    max_iter : Newton iterations before a configuration is reported as not converged.
    """

    step_mm: float = 10.0
    tol: float = 1e-10
    max_iter: int = 30

    def __post_init__(self) -> None:
        if not self.step_mm > 0:
            raise ValueError("step_mm must be > 0")
        if not self.tol > 0:
            raise ValueError("tol must be > 0")
        if self.max_iter < 1:
            raise ValueError("max_iter must be >= 1")


@dataclass(frozen=True)
class MechanicsParams:
    """Per-configuration mechanical parameters handed to the kernel (effects modify these).

    kappa, EI, ratio : (B, n) precurvature 1/mm, bending stiffness N mm^2, EI/GJ.
    kink : (B, n, 2) rad, rotation of the backbone frame where tube j ends.
    """

    kappa: np.ndarray
    EI: np.ndarray
    ratio: np.ndarray
    kink: np.ndarray


@dataclass(frozen=True)
class SolveInfo:
    """Diagnostics of a physics solve: uz0 (B, n) 1/mm, iterations (B,), residual (B,) 1/mm."""

    uz0: np.ndarray
    iterations: np.ndarray
    residual: np.ndarray


class PhysicsModel:
    """Mechanics shape model of a concentric tube robot.

    Parameters
    ----------
    robot : Robot or str
        The robot (or a shipped name / YAML path).
    torsion : bool
        True: torsionally compliant Cosserat-rod model (shooting on uz(0)); False: the
        torsionally rigid ("traditional") model.
    config : PhysicsConfig
        Integrator and solver settings.
    """

    def __init__(self, robot: Robot | str, torsion: bool = True, config: PhysicsConfig | None = None):
        self.robot = load_robot(robot)
        self.torsion = bool(torsion)
        self.config = config or PhysicsConfig()
        self.name = "physics" if self.torsion else "rigid"
        self.last_info: SolveInfo | None = None
        r = self.robot
        # per-tube constants, computed once (Robot.array builds them from the tubes each call)
        self._lengths = np.ascontiguousarray(r.lengths)
        self._straight = np.ascontiguousarray(r.array("straight_length"))
        self._kappa = r.array("curvature")
        self._EI = r.array("bending_stiffness")
        self._ratio = self._EI / r.array("torsional_stiffness")

    def __repr__(self) -> str:
        return f"PhysicsModel(robot={self.robot.name!r}, torsion={self.torsion})"

    def with_config(self, **kw) -> PhysicsModel:
        """A copy with some :class:`PhysicsConfig` fields changed."""
        return PhysicsModel(self.robot, self.torsion, replace(self.config, **kw))

    def base_params(self, B: int) -> MechanicsParams:
        """The robot's nominal parameters broadcast to a batch of ``B``."""
        n = self.robot.n
        return MechanicsParams(kappa=np.tile(self._kappa, (B, 1)), EI=np.tile(self._EI, (B, 1)),
                               ratio=np.tile(self._ratio, (B, 1)), kink=np.zeros((B, n, 2)))

    def shape(self, q: np.ndarray, points: int = 20) -> Shape:
        """Backbones of a batch. q : (B, 2n) rad and mm; returns a :class:`Shape` in mm."""
        q = check_q(self.robot, q)
        return self.solve(q, points, self.base_params(len(q)))

    def backbone(self, q: np.ndarray, points: int = 20) -> np.ndarray:
        """(B, points, 3) backbone points, mm, robot base frame."""
        return self.shape(q, points).points

    def solve(self, q: np.ndarray, points: int, params: MechanicsParams,
              uz_init: np.ndarray | None = None) -> Shape:
        """Run the kernel with explicit per-configuration parameters (used by effects).

        q : (B, 2n) rad and mm (checked by the caller); points : m >= 2;
        params : :class:`MechanicsParams` with arrays of shape (B, n) (kink (B, n, 2));
        uz_init : optional (B, n) initial guess of uz(0), 1/mm.
        Returns a :class:`Shape`; diagnostics go to ``self.last_info``.
        """
        if points < 2:
            raise ValueError("points must be >= 2 (base and tip)")
        r = self.robot
        n = r.n
        q = np.ascontiguousarray(q, dtype=float)
        if q.ndim != 2 or q.shape[1] != 2 * n:
            raise ValueError(f"q must have shape (B, {2 * n}), got {q.shape}")
        B = len(q)
        alpha = np.ascontiguousarray(q[:, :n])
        beta = np.ascontiguousarray(q[:, n:])

        def arr(name: str, v, shape: tuple[int, ...]) -> np.ndarray:
            # the compiled kernel does not bounds-check: shapes are checked here
            a = np.ascontiguousarray(v, dtype=float)
            if a.shape != shape:
                raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
            return a

        x0 = np.zeros((B, n)) if uz_init is None else arr("uz_init", uz_init, (B, n))
        _wait_for_warmup()
        pts, s, uz0, iters, resid, ok = _shooting.solve_batch(
            alpha, beta, self._lengths, self._straight,
            arr("kappa", params.kappa, (B, n)), arr("EI", params.EI, (B, n)),
            arr("ratio", params.ratio, (B, n)), arr("kink", params.kink, (B, n, 2)),
            self.torsion, int(points), float(self.config.step_mm), float(self.config.tol),
            int(self.config.max_iter), x0,
        )
        ok = ok & np.all(np.isfinite(pts), axis=(1, 2))
        ok &= chords_within_arc(pts, s)
        self.last_info = SolveInfo(uz0=uz0, iterations=iters, residual=resid)
        return Shape(points=pts, s=s, radius=radius_along(r, q, s), ok=ok)


def chords_within_arc(points: np.ndarray, s: np.ndarray, rtol: float = 1e-4) -> np.ndarray:
    """(B,) bool: no straight segment between consecutive backbone points is longer than the
    arc length between them (a unit-speed curve cannot do that; the solver failed if it did).
    points : (B, m, 3) mm; s : (B, m) mm."""
    with np.errstate(invalid="ignore", over="ignore"):
        chord = np.linalg.norm(np.diff(points, axis=1), axis=2)
        arc = np.diff(s, axis=1)
        good = chord <= arc * (1.0 + rtol) + 1e-6
    return np.all(good, axis=1)
