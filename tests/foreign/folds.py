"""Bistable ranges and fold-crossing problems of two-tube robots (foreign generator; imports
nothing from ctrplan). Built on :mod:`tests.foreign.continuation`.

* ``bistable_range(robot, beta)`` -> (a, b) rad or None: at translations beta (2,) the relative
  rotations alpha_1 - alpha_2 (mod 2 pi) where two stable equilibria coexist. At relative
  rotation pi the untwisted state psi_i = alpha_i is an equilibrium; it is unstable (stability
  measure < 0) exactly when the pair is bistable there. The upper fold b is where the branch
  followed up from a relative rotation near 0 ends (a continuation sweep, fold located to
  ``MIN_STEP``); a = 2 pi - b by the mirror symmetry psi -> -psi of the energy.
* ``fold_crossing_cases(robot, count, seed)`` -> list of FoldCase and
  ``fold_crossing_pairs(robot, count, seed)`` -> list of (start_q (4,), target_xyz (3,)):
  start and target configurations on opposite sides of the bistable range (each monostable:
  one stable equilibrium), such that the shortest joint motion between them (straight line,
  every rotation along its shorter arc: |target_q - start_q| < pi per rotation) crosses a fold:
  replayed by continuation the robot snaps on it (``FoldCase.snaps`` >= 1, checked for every
  case). target_xyz is the tip (mm, base frame) of the target configuration. Deterministic per
  seed.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import energy as EN
from .continuation import continue_path, equilibria
from .robot import Spec, beta_from_unit, load_spec, valid

SWEEP_STEP = 0.1          # rad: state spacing of the sweep that locates a fold (sub-steps adapt)
MARGIN = 0.15             # rad: least distance of start / target relative rotation from the folds
REACH = 1.0               # rad: largest distance of start / target relative rotation from the folds
MOTION_STATES = 41        # states of the replayed straight motion
BISTABLE_MU = -0.05       # measure at relative rotation pi below which a case is drawn there


@dataclass(frozen=True)
class FoldCase:
    """start_q (4,) and target_q (4,) (rad, mm; target_q - start_q is the shortest motion);
    target (3,) the target configuration's tip, mm, base frame; snaps: snaps of the robot
    along the straight motion (continuation); folds (a, b) rad: the bistable range of relative
    rotation at the start's translations; up: the motion raises the relative rotation."""

    start_q: np.ndarray
    target: np.ndarray
    target_q: np.ndarray
    snaps: int
    folds: tuple
    up: bool


def mu_at_pi(robot, beta, h: float = 1.0) -> float:
    """Stability measure of the untwisted state at relative rotation pi (two tubes)."""
    spec = load_spec(robot)
    en = EN.build(spec, np.array([np.pi, 0.0, *np.asarray(beta, float)]), h)
    x = np.zeros(en.nvar)
    for i in range(spec.n):
        k = np.flatnonzero(en.var[:, i] >= 0)
        x[en.var[k, i]] = en.alpha[i]
    return en.stability(x)


def bistable_range(robot, beta, h: float = 1.0):
    """(a, b) rad, the bistable range of relative rotation at translations beta (2,), or None
    where the pair is monostable at relative rotation pi (module docstring)."""
    spec = _two(robot)
    beta = np.asarray(beta, float)
    if mu_at_pi(spec, beta, h) >= 0.0:
        return None
    for lo in (np.pi - 2.2, 0.2):          # the usual ranges first, then nearly all of 2 pi
        d = np.arange(lo, 2.0 * np.pi - lo + 1e-9, SWEEP_STEP)
        Q = np.column_stack([d, np.zeros_like(d), np.tile(beta, (len(d), 1))])
        r = continue_path(spec, Q, uz0="least_twisted", points=2, h=h, measure=False)
        if len(r.snap_q):
            b = float(r.snap_q[0, 0] - r.snap_q[0, 1])
            return (2.0 * np.pi - b, b)
    return None


def _two(robot) -> Spec:
    spec = load_spec(robot)
    if spec.n != 2:
        raise ValueError(f"fold-crossing problems are built for two-tube robots, {spec.name!r} has {spec.n}")
    return spec


def _draw(spec: Spec, rng, folds, beta_s, u_s):
    a, b = folds
    up = bool(rng.random() < 0.5)
    if up:
        ds, dt = a - rng.uniform(MARGIN, REACH), b + rng.uniform(MARGIN, REACH)
    else:
        ds, dt = b + rng.uniform(MARGIN, REACH), a - rng.uniform(MARGIN, REACH)
    D = dt - ds
    lim = np.pi - 0.05
    lo, hi = max(-lim, -lim - D), min(lim, lim - D)
    if lo >= hi:
        return None
    d2 = rng.uniform(lo, hi)
    a2 = rng.uniform(-np.pi, np.pi)
    start = np.array([a2 + ds, a2, *beta_s])
    u_t = np.clip(u_s + rng.normal(0.0, 0.03, 2), 0.0, 1.0)
    beta_t = beta_from_unit(spec, u_t[None])[0]
    target = np.array([start[0] + d2 + D, a2 + d2, *beta_t])
    if not (valid(spec, start)[0] and valid(spec, target)[0]):
        return None
    return start, target, up


def fold_crossing_cases(robot, count: int, seed: int, h: float = 1.0) -> list[FoldCase]:
    """``count`` fold-crossing problems (module docstring), deterministic per seed."""
    spec = _two(robot)
    rng = np.random.default_rng(seed)
    out: list[FoldCase] = []
    tries = 0
    while len(out) < count:
        tries += 1
        if tries > 40 * count + 40:
            raise RuntimeError(f"{spec.name}: only {len(out)} of {count} fold-crossing cases in {tries} draws")
        u_s = rng.uniform(size=2)
        beta_s = beta_from_unit(spec, u_s[None])[0]
        if mu_at_pi(spec, beta_s, h) > BISTABLE_MU:
            continue
        folds = bistable_range(spec, beta_s, h)
        if folds is None:
            continue
        drawn = _draw(spec, rng, folds, beta_s, u_s)
        if drawn is None:
            continue
        start, target, up = drawn
        if len(equilibria(spec, start, h)) != 1 or len(equilibria(spec, target, h)) != 1:
            continue
        t = np.linspace(0.0, 1.0, MOTION_STATES)[:, None]
        r = continue_path(spec, start + t * (target - start), points=2, h=h, measure=False)
        if len(r.snap_q) == 0:
            continue
        out.append(FoldCase(start, r.tips[-1].copy(), target, len(r.snap_q), folds, up))
    return out


def fold_crossing_pairs(robot, count: int, seed: int, h: float = 1.0) -> list[tuple]:
    """[(start_q (4,), target_xyz (3,))] of :func:`fold_crossing_cases` (same seed, same
    cases)."""
    return [(c.start_q, c.target) for c in fold_crossing_cases(robot, count, seed, h)]
