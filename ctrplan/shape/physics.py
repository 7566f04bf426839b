"""Batched mechanics shape models: torsionally rigid and torsionally compliant CTRs.

See :mod:`ctrplan.shape._kernel` for the equations. Both models run a whole batch in one
compiled call; the single-configuration call is the same function with ``B = 1``.
"""

from __future__ import annotations

import subprocess
import sys
from dataclasses import dataclass, replace
from typing import NamedTuple

import numpy as np

from ctrplan.robot import Robot, load_robot
from ctrplan.shape import _loaded, _shooting
from ctrplan.shape.base import Shape, check_q, radius_along
from ctrplan.shape.bounds import continuity_pad

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
    stability : reject unstable equilibria of the unloaded compliant model and search stable
        ones (:mod:`ctrplan.shape._shooting`); False returns the first equilibrium Newton finds (only for
        comparisons and benchmarks: it may be unstable).
    probe_bistable : also probe rows whose first equilibrium is stable for a second stable
        one where two curved tubes are rotated apart by more than 90 deg (``branch`` 4,
        ``bistable`` True, the other in ``uz0_alt``; shapes unchanged). Costs about one more
        Newton solve on those rows; for planning, which should avoid snapping configurations.
    """

    step_mm: float = 10.0
    tol: float = 1e-10
    max_iter: int = 30
    stability: bool = True
    probe_bistable: bool = False

    def __post_init__(self) -> None:
        if not self.step_mm > 0:
            raise ValueError("step_mm must be > 0")
        if not self.tol > 0:
            raise ValueError("tol must be > 0")
        if self.max_iter < 1:
            raise ValueError("max_iter must be >= 1")


#: Standard gravity, m/s^2 (for ``Loads.gravity`` written as a direction times this).
STANDARD_GRAVITY = 9.80665


@dataclass(frozen=True)
class Loads:
    """External loads on the robot, all in the robot base frame (default: none).

    gravity : (gx, gy, gz) m/s^2, acceleration of gravity. Each tube present beyond the
        constraint plane weighs ``density * area * |g|`` per unit length (N/mm), with the
        tube's ``density`` from the robot YAML (kg/m^3) or, where not given, nitinol's 6450.
        (The parts behind the plane lie in the actuation unit and are supported.)
    tip_force : (fx, fy, fz) N, a fixed-direction force at the tip (innermost tube's end).
    tip_moment : (mx, my, mz) N mm, a fixed-direction moment at the tip; its component
        along the tip tangent twists the innermost tube.
    """

    gravity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tip_force: tuple[float, float, float] = (0.0, 0.0, 0.0)
    tip_moment: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def __post_init__(self) -> None:
        for name in ("gravity", "tip_force", "tip_moment"):
            v = tuple(float(c) for c in getattr(self, name))
            if len(v) != 3 or not all(np.isfinite(v)):
                raise ValueError(f"Loads.{name} must be 3 finite numbers, got {getattr(self, name)!r}")
            object.__setattr__(self, name, v)

    @property
    def zero(self) -> bool:
        """True when every load is exactly zero."""
        return not any(self.gravity) and not any(self.tip_force) and not any(self.tip_moment)


def tube_weights(robot: Robot, gravity: np.ndarray) -> np.ndarray:
    """Weight per unit length of each tube (N/mm, base frame) under gravity (..., 3) m/s^2:
    returns (..., n, 3). Mass per length is density * area (kg/mm; nitinol's density where
    the tube gives none)."""
    mass = robot.array("weight_density")                      # kg/mm
    g = np.asarray(gravity, dtype=float)
    return mass[:, None] * g[..., None, :]


@dataclass(frozen=True)
class MechanicsParams:
    """Per-configuration mechanical parameters handed to the kernel (effects modify these).

    kappa, EI, ratio : (B, n) precurvature 1/mm, bending stiffness N mm^2, EI/GJ.
    kink : (B, n, 2) rad, rotation of the backbone frame where tube j ends.
    weight : (B, n, 3) N/mm or None, weight per unit length of each tube (base frame).
    force : (B, 3) N or None, tip force (base frame).
    moment : (B, 3) N mm or None, tip moment (base frame).
    Configurations whose loads are all zero (or None) are solved by the unloaded kernel.
    """

    kappa: np.ndarray
    EI: np.ndarray
    ratio: np.ndarray
    kink: np.ndarray
    weight: np.ndarray | None = None
    force: np.ndarray | None = None
    moment: np.ndarray | None = None

    def loaded_rows(self) -> np.ndarray:
        """(B,) bool: configurations with a nonzero load."""
        B = len(self.kappa)
        out = np.zeros(B, dtype=bool)
        for a in (self.weight, self.force, self.moment):
            if a is not None:
                out |= np.asarray(a).reshape(B, -1).any(axis=1)
        return out


@dataclass(frozen=True)
class SolveInfo:
    """Diagnostics of a physics solve: uz0 (B, n) 1/mm, iterations (B,), residual (B,) 1/mm;
    moment0 (B, 2) N mm or None: bending moment at s = 0 (base frame x, y; loaded solves).

    Elastic stability of the unloaded compliant solves (derivation: :mod:`ctrplan.shape._shooting`):
    detj (B,) det of the shooting Jacobian d uz(end) / d uz(0) at the returned equilibrium
    (> 0: stable; 1 for the rigid model, NaN for loaded rows, which are not checked);
    branch (B,) int8: 0 the first equilibrium found was stable (or rigid / loaded row),
    1 an unstable equilibrium was rejected and one stable found, 2 an unstable one rejected
    and two stable ones found (returned: the one nearer ``uz_init``, i.e. by default the less
    twisted, smaller max |uz(0)|; a warm start keeps a motion on its branch), 3 unstable
    rejected and the stable one found by continuation from the rigid solution, -1 unstable
    rejected and none stable found (ok = False), 4 (with ``probe_bistable``) the first was
    stable and a second stable one was found by probing (the first is returned).
    uz0_alt (B, n) 1/mm: where two stable equilibria were found (``bistable``) the uz(0) of
    the one NOT returned, NaN elsewhere: ``model.solve(q, m, params, uz_init=uz0_alt)`` on
    those rows gives the other branch's shape (Newton starts on it).
    """

    uz0: np.ndarray
    iterations: np.ndarray
    residual: np.ndarray
    moment0: np.ndarray | None = None
    detj: np.ndarray | None = None
    branch: np.ndarray | None = None
    uz0_alt: np.ndarray | None = None
    #: (B,) bool, chained solves only (``solve(..., chain=...)``): the row's equilibrium is the
    #: continuation of its chain start's (:mod:`ctrplan.shape._continuation`); None otherwise
    continued: np.ndarray | None = None

    @property
    def bistable(self) -> np.ndarray | None:
        """(B,) bool: two stable equilibria were found (the configuration can snap between
        them). Searched where the first equilibrium found was unstable, and with
        ``PhysicsConfig(probe_bistable=True)`` also where it was stable but two curved tubes
        are rotated apart by > 90 deg; False does not prove uniqueness."""
        return None if self.branch is None else (self.branch == 2) | (self.branch == 4)

    @property
    def unstable_rejected(self) -> np.ndarray | None:
        """(B,) bool: an unstable equilibrium was found and rejected in this row."""
        return None if self.branch is None else (self.branch != 0) & (self.branch != 4)


class _Batch(NamedTuple):
    """The checked, contiguous arrays of one :meth:`PhysicsModel.solve` (shapes there)."""

    alpha: np.ndarray
    beta: np.ndarray
    x0: np.ndarray
    kappa: np.ndarray
    EI: np.ndarray
    ratio: np.ndarray
    kink: np.ndarray
    weight: np.ndarray | None
    force: np.ndarray | None
    moment: np.ndarray | None
    loaded: np.ndarray


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
    loads : Loads
        External loads (gravity, tip force/moment; default none). Loaded configurations are
        solved as a boundary value problem with force and moment states
        (:mod:`ctrplan.shape._loaded`); the torsionally rigid model under loads is its limit of
        infinite torsional stiffness (tubes do not twist but carry torsional moments). With no
        load the unloaded kernels run unchanged. The first loaded solve compiles the loaded
        kernel (about 14 s of CPU on the development machine; numba caches it on disk).
    """

    def __init__(self, robot: Robot | str, torsion: bool = True, config: PhysicsConfig | None = None,
                 loads: Loads | None = None):
        self.robot = load_robot(robot)
        self.torsion = bool(torsion)
        self.config = config or PhysicsConfig()
        self.loads = loads if loads is not None and not loads.zero else None
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
        extra = "" if self.loads is None else f", loads={self.loads!r}"
        return f"PhysicsModel(robot={self.robot.name!r}, torsion={self.torsion}{extra})"

    def with_config(self, **kw) -> PhysicsModel:
        """A copy with some :class:`PhysicsConfig` fields changed."""
        return PhysicsModel(self.robot, self.torsion, replace(self.config, **kw), self.loads)

    def base_params(self, B: int) -> MechanicsParams:
        """The robot's nominal parameters (and loads) broadcast to a batch of ``B``."""
        n = self.robot.n
        p = MechanicsParams(kappa=np.tile(self._kappa, (B, 1)), EI=np.tile(self._EI, (B, 1)),
                            ratio=np.tile(self._ratio, (B, 1)), kink=np.zeros((B, n, 2)))
        if self.loads is not None:
            ld = self.loads
            p = replace(p, weight=np.tile(tube_weights(self.robot, ld.gravity), (B, 1, 1)),
                        force=np.tile(np.array(ld.tip_force), (B, 1)),
                        moment=np.tile(np.array(ld.tip_moment), (B, 1)))
        return p

    def shape(self, q: np.ndarray, points: int = 20) -> Shape:
        """Backbones of a batch. q : (B, 2n) rad and mm; returns a :class:`Shape` in mm."""
        q = check_q(self.robot, q)
        return self.solve(q, points, self.base_params(len(q)))

    def backbone(self, q: np.ndarray, points: int = 20) -> np.ndarray:
        """(B, points, 3) backbone points, mm, robot base frame."""
        return self.shape(q, points).points

    def solve(self, q: np.ndarray, points: int, params: MechanicsParams,
              uz_init: np.ndarray | None = None, chain: np.ndarray | None = None) -> Shape:
        """Run the kernel with explicit per-configuration parameters (used by effects).

        q : (B, 2n) rad and mm (checked by the caller); points : m >= 2;
        params : :class:`MechanicsParams` with arrays of shape (B, n) (kink (B, n, 2));
        uz_init : optional (B, n) initial guess of uz(0), 1/mm.
        chain : optional (B,) bool, the rows are motions (compliant, unloaded model only): a
            True row starts a chain at the equilibrium Newton finds from its ``uz_init`` (a NaN
            row: the equilibrium the ordinary solve picks), every other row continues the
            previous row's equilibrium (:mod:`ctrplan.shape._continuation`); ``last_info``
            then has ``continued``. Shapes of rows whose branch ended are ``ok = False``.
        Returns a :class:`Shape`; diagnostics go to ``self.last_info``.
        """
        if chain is not None:
            return self._solve_chain(q, points, params, uz_init, chain)
        if points < 2:
            raise ValueError("points must be >= 2 (base and tip)")
        q = np.ascontiguousarray(q, dtype=float)
        b = self._checked(q, params, uz_init)
        _wait_for_warmup()
        moment0 = None
        if not b.loaded.any():
            pts, s, uz0, iters, resid, ok, detj, branch, uz0_alt = self._unloaded(b, None, int(points))
        else:
            (pts, s, uz0, iters, resid, ok, detj, branch, uz0_alt), moment0 = self._solve_mixed(
                b, int(points))
        ok = ok & np.all(np.isfinite(pts), axis=(1, 2))
        ok &= chords_within_arc(pts, s)
        self.last_info = SolveInfo(uz0=uz0, iterations=iters, residual=resid, moment0=moment0,
                                   detj=detj, branch=branch, uz0_alt=uz0_alt)
        return Shape(points=pts, s=s, radius=radius_along(self.robot, q, s), ok=ok,
                     pad=self._pad(q, b, s, pts))

    def _checked(self, q: np.ndarray, params: MechanicsParams, uz_init) -> _Batch:
        """The kernels' arrays of a solve, contiguous, their shapes checked (the compiled
        kernels do not bounds-check)."""
        n = self.robot.n
        if q.ndim != 2 or q.shape[1] != 2 * n:
            raise ValueError(f"q must have shape (B, {2 * n}), got {q.shape}")
        B = len(q)

        def arr(name: str, v, shape: tuple[int, ...]) -> np.ndarray:
            a = np.ascontiguousarray(v, dtype=float)
            if a.shape != shape:
                raise ValueError(f"{name} must have shape {shape}, got {a.shape}")
            return a

        x0 = np.zeros((B, n)) if uz_init is None else arr("uz_init", uz_init, (B, n))
        kappa = arr("kappa", params.kappa, (B, n))
        EI = arr("EI", params.EI, (B, n))
        ratio = arr("ratio", params.ratio, (B, n))
        kink = arr("kink", params.kink, (B, n, 2))
        weight = None if params.weight is None else arr("weight", params.weight, (B, n, 3))
        force = None if params.force is None else arr("force", params.force, (B, 3))
        moment = None if params.moment is None else arr("moment", params.moment, (B, 3))
        return _Batch(
            alpha=np.ascontiguousarray(q[:, :n]), beta=np.ascontiguousarray(q[:, n:]), x0=x0,
            kappa=kappa, EI=EI, ratio=ratio, kink=kink, weight=weight, force=force, moment=moment,
            loaded=replace(params, weight=weight, force=force, moment=moment).loaded_rows())

    def _unloaded(self, b: _Batch, rows: np.ndarray | None, m: int) -> tuple:
        """The unloaded kernel on all rows or (index array) a subset, a chunk at a time: the
        kernel returns to Python every few thousand rows, where a pending SIGINT / SIGTERM is
        acted on (ctrplan.interrupt). Returns the kernel's arrays."""
        from ctrplan import interrupt

        cfg = self.config
        B = len(b.alpha)

        def kernel(r_):
            c = np.ascontiguousarray
            pick = (lambda a: a) if r_ is None else (lambda a: c(a[r_]))   # noqa: E731
            return _shooting.solve_batch(
                pick(b.alpha), pick(b.beta), self._lengths, self._straight, pick(b.kappa),
                pick(b.EI), pick(b.ratio), pick(b.kink), self.torsion, m, float(cfg.step_mm),
                float(cfg.tol), int(cfg.max_iter), pick(b.x0), bool(cfg.stability),
                bool(cfg.probe_bistable))

        if rows is None and B <= interrupt.CHUNK:
            return kernel(None)
        rows = np.arange(B) if rows is None else np.asarray(rows)
        parts = []
        for k in range(0, len(rows), interrupt.CHUNK):
            interrupt.check()
            parts.append(kernel(rows[k:k + interrupt.CHUNK]))
        interrupt.check()
        if len(parts) == 1:
            return parts[0]
        if not parts:
            return kernel(rows[:0])
        return tuple(np.concatenate(z, axis=0) for z in zip(*parts))

    def _solve_mixed(self, b: _Batch, points: int) -> tuple[tuple, np.ndarray]:
        """A batch with loaded rows: the unloaded kernel on the others, the loaded one (from
        the unloaded solution) on those. Returns the arrays of :meth:`_unloaded` for the batch
        and the base moment (B, 2)."""
        B, n = b.alpha.shape
        detj = np.full(B, np.nan)
        branch = np.zeros(B, dtype=np.int8)
        uz0_alt = np.full((B, n), np.nan)
        pts = np.zeros((B, points, 3))
        s = np.zeros((B, points))
        uz0 = np.zeros((B, n))
        iters = np.zeros(B, dtype=np.int64)
        resid = np.zeros(B)
        ok = np.zeros(B, dtype=bool)
        free = np.flatnonzero(~b.loaded)
        if len(free):
            (pts[free], s[free], uz0[free], iters[free], resid[free], ok[free], detj[free],
             branch[free], uz0_alt[free]) = self._unloaded(b, free, points)
        idx = np.flatnonzero(b.loaded)
        W = np.zeros((B, n, 3)) if b.weight is None else b.weight
        F = np.zeros((B, 3)) if b.force is None else b.force
        M = np.zeros((B, 3)) if b.moment is None else b.moment
        # first guess from the unloaded solution of the loaded rows (33 points)
        gp, gs, guz, _, _, gok, _, _, _ = self._unloaded(b, idx, 33)
        lp, ls, luz, lit, lres, lm = self._solve_loaded(
            b.alpha[idx], b.beta[idx], b.kappa[idx], b.EI[idx], b.ratio[idx], b.kink[idx], W[idx],
            F[idx], M[idx], gp, gs, guz, gok, points)
        pts[idx], s[idx], uz0[idx], iters[idx], resid[idx] = lp, ls, luz, lit, lres
        moment0 = np.zeros((B, 2))
        moment0[idx] = lm
        ok[idx] = lres < self.config.tol
        return (pts, s, uz0, iters, resid, ok, detj, branch, uz0_alt), moment0

    def _pad(self, q: np.ndarray, b: _Batch, s: np.ndarray, pts: np.ndarray) -> np.ndarray:
        """:func:`ctrplan.shape.bounds.continuity_pad` with the loads of the loaded rows."""
        W = F = M = None
        if b.loaded.any():   # the loads' curvature on the loaded rows (zero loads elsewhere)
            B, n = b.alpha.shape
            ld = b.loaded
            W = np.zeros((B, n, 3)) if b.weight is None else np.where(ld[:, None, None], b.weight, 0.0)
            F = np.zeros((B, 3)) if b.force is None else np.where(ld[:, None], b.force, 0.0)
            M = np.zeros((B, 3)) if b.moment is None else np.where(ld[:, None], b.moment, 0.0)
        return continuity_pad(q, self._lengths, s, pts, b.kappa, b.EI, b.kink, W, F, M)

    def _solve_chain(self, q, points, params, uz_init, chain) -> Shape:
        """The chained solve of :meth:`solve` (a chunk of rows at a time; a chunk continues
        the previous one's last row)."""
        from ctrplan import interrupt
        from ctrplan.shape import _continuation

        if points < 2:
            raise ValueError("points must be >= 2 (base and tip)")
        if not self.torsion or not self.config.stability:
            raise ValueError("a chained solve needs the compliant model with its stability check")
        if params.loaded_rows().any():
            raise ValueError("a chained solve is for unloaded configurations only")
        n = self.robot.n
        q = np.ascontiguousarray(q, dtype=float)
        B = len(q)
        c = np.ascontiguousarray
        start = np.asarray(chain, dtype=bool).reshape(B).copy()
        if B:
            start[0] = True
        x0 = np.full((B, n), np.nan) if uz_init is None else np.array(uz_init, dtype=float).reshape(B, n)
        pick = np.flatnonzero(start & ~np.all(np.isfinite(x0), axis=1))
        if len(pick):      # chain starts without a given equilibrium: the ordinary solve's
            self.solve(q[pick], 2, _rows(params, pick))
            x0[pick] = self.last_info.uz0
        d = np.zeros(B)
        if B > 1:
            dq = np.diff(q, axis=0)
            dq[:, :n] = (dq[:, :n] + np.pi) % (2 * np.pi) - np.pi
            d[1:] = np.hypot(30.0 * np.linalg.norm(dq[:, :n], axis=1), np.linalg.norm(dq[:, n:], axis=1))
        parts = []
        cfg = self.config
        for a in range(0, max(B, 1), interrupt.CHUNK):
            interrupt.check()
            b = min(B, a + interrupt.CHUNK)
            lead = 1 if a > 0 and not start[a] else 0
            r_ = np.arange(a - lead, b)
            st = start[r_].copy()
            xi = x0[r_].copy()
            if lead:         # continue from the previous chunk's last row (NaN: its branch ended)
                st[0] = True
                prev = parts[-1]
                xi[0] = prev[2][-1] if prev[7][-1] else np.nan
            out = _continuation.solve_chain(
                c(q[r_, :n]), c(q[r_, n:]), self._lengths, self._straight, c(params.kappa[r_]),
                c(params.EI[r_]), c(params.ratio[r_]), c(params.kink[r_]), int(points),
                float(cfg.step_mm), float(cfg.tol), int(cfg.max_iter), c(xi), c(st), c(d[r_]),
                int(CHAIN_LEVELS))
            parts.append(tuple(z[lead:] for z in out))
        interrupt.check()
        pts, s, uz0, iters, resid, ok, detj, cont = (np.concatenate(z, axis=0) for z in zip(*parts))
        ok = ok & chords_within_arc(pts, s)
        self.last_info = SolveInfo(uz0=uz0, iterations=iters, residual=resid, detj=detj,
                                   branch=np.zeros(B, dtype=np.int8), continued=cont)
        return Shape(points=pts, s=s, radius=radius_along(self.robot, q, s), ok=ok,
                     pad=continuity_pad(q, self._lengths, s, pts, params.kappa, params.EI,
                                        params.kink))

    def _solve_loaded(self, alpha, beta, kappa, EI, ratio, kink, W, F, M, pts0, s0, uz00, ok0,
                      points):
        """The loaded rows: first guess from the unloaded solution (its torsions, and the base
        moment of the loads about the base on the unloaded backbone), then the loaded kernel.
        Returns points, s, uz(0), iterations, residual (1/mm), base moment (N mm, x/y) of
        those rows."""
        n = self.robot.n
        B = len(alpha)
        ratio = ratio if self.torsion else np.zeros_like(ratio)
        # torsional moments of the unloaded solution; zero where it failed or for the rigid model
        tau0 = np.where(ok0[:, None] & (ratio > 0), uz00 * EI / np.where(ratio > 0, ratio, 1.0), 0.0)
        x_start = np.concatenate([tau0, np.zeros((B, 2))], axis=1)
        # base moment of the loads on the unloaded backbone (trapezoid over its points)
        ends = beta + self._lengths                                    # (B, n)
        present = s0[:, :, None] < ends[:, None, :] + 1e-9             # (B, m, n)
        f = np.einsum("bmn,bnc->bmc", present.astype(float), W)        # (B, m, 3) N/mm
        mom = np.cross(pts0, f)                                        # (B, m, 3)
        ds = np.diff(s0, axis=1)[:, :, None]
        m0 = M + np.cross(pts0[:, -1], F) + np.sum(0.5 * (mom[:, 1:] + mom[:, :-1]) * ds, axis=1)
        m0 = np.where(np.isfinite(m0), m0, 0.0)
        x_init = np.concatenate([tau0, m0[:, :2]], axis=1)
        c = lambda a: np.ascontiguousarray(a, dtype=float)   # noqa: E731
        p, s, x, it, res, _ = _loaded.solve_loaded_batch(
            c(alpha), c(beta), self._lengths, self._straight, c(kappa), c(EI), c(ratio), c(kink),
            c(W), c(F), c(M), points, float(self.config.step_mm), float(self.config.tol),
            int(self.config.max_iter), c(x_init), c(x_start))
        uz0 = x[:, :n] * ratio / EI
        return p, s, uz0, it, res, x[:, n:]


#: halvings of a row step the chained solve may take before it declares the branch ended there
CHAIN_LEVELS = 5


def _rows(params: MechanicsParams, idx: np.ndarray) -> MechanicsParams:
    """The parameters of the rows ``idx``."""
    pick = lambda a: None if a is None else np.asarray(a)[idx]   # noqa: E731
    return MechanicsParams(kappa=params.kappa[idx], EI=params.EI[idx], ratio=params.ratio[idx],
                           kink=params.kink[idx], weight=pick(params.weight),
                           force=pick(params.force), moment=pick(params.moment))


def chords_within_arc(points: np.ndarray, s: np.ndarray, rtol: float = 1e-4) -> np.ndarray:
    """(B,) bool: no straight segment between consecutive backbone points is longer than the
    arc length between them (a unit-speed curve cannot do that; the solver failed if it did).
    points : (B, m, 3) mm; s : (B, m) mm."""
    with np.errstate(invalid="ignore", over="ignore"):
        chord = np.linalg.norm(np.diff(points, axis=1), axis=2)
        arc = np.diff(s, axis=1)
        good = chord <= arc * (1.0 + rtol) + 1e-6
    return np.all(good, axis=1)
