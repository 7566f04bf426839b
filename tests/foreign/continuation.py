"""What the physical robot does along a motion: quasi-static continuation of the unloaded,
torsionally compliant equilibrium, with snap-through where the branch it follows ends.

Code of the foreign generator (imports nothing from ctrplan). Equilibria and their stability come
from the finite-element energy of :mod:`tests.foreign.energy` (a discretisation that shares
nothing with ctrplan's shooting nor with mechanics.py's):

* ``continue_path(robot, states, uz0=None, points=20, max_step=0.05, max_step_mm=1.0, h=1.0,
  measure=True) -> Continued``: the robot moves linearly in joint space between consecutive
  states (rotations unwrapped, as in plan.json ``path``). Each motion is cut into sub-steps
  that adapt: a sub-step is accepted only if Newton on the energy, started from the previous
  solution turned with the actuators, converges to a minimum (positive definite Hessian) within ``DPSI_MAX`` rad of that
  prediction; otherwise it is halved, down to ``MIN_STEP`` (rad or mm) of joint motion. A
  sub-step that still fails there lies just past a fold: the equilibrium being followed has
  ceased to exist, and the robot does what a quasi-static robot does, it goes downhill in energy
  from where it was to the remaining minimum (``energy.minimise``): a snap, recorded when the
  angles jump by more than ``SNAP_JUMP`` rad.
* ``equilibria(robot, q)``: every stable equilibrium found by descending the energy from a fan of
  twisted starts (tubes' base torsions on the torque-balanced set).
* ``stability(robot, q, uz0)`` / ``is_stable``: the measure of :mod:`tests.foreign.energy`
  (smallest eigenvalue of H v = mu T v; > 0 stable) at the equilibrium whose base torsions are
  ``uz0`` (ctrplan's uz(0) convention, psi_i(0) = alpha_i - beta_i uz0_i): the tube angles are
  integrated here from uz0 (scipy) and the discrete Hessian evaluated on them.
* ``bistable_range(robot, beta)`` and ``fold_crossing_cases`` / ``fold_crossing_pairs``: see
  :mod:`tests.foreign.folds`.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np

from . import energy as EN
from .robot import Spec, load_spec

log = logging.getLogger(__name__)

DPSI_MAX = 0.1        # rad: largest correction of the predictor a sub-step may need
MIN_STEP = 1e-6       # rad (rotations) or mm (translations): the sub-step below which a failure is a fold
SNAP_JUMP = 0.3       # rad: a descent that moves some tube angle by more is a snap
NEWTON_ITER = 12      # Newton iterations a sub-step may take


@dataclass(frozen=True)
class Continued:
    """Result of :func:`continue_path` on S states of an n-tube robot.

    backbones (S, m, 3) mm, robot base frame, evenly spaced in arc length from s = 0 to the tip;
    snaps: sorted state indices i such that the robot snapped on the motion from state i-1 to i;
    stability (S,) the energy measure mu (dimensionless, <= 1; > 0 stable; 0 at a fold);
    uz0 (S, n) 1/mm base torsions (ctrplan's convention: psi_i(0) = alpha_i - beta_i uz0_i);
    branch (S,) int: 0 at the start, changed by +1 / -1 at each snap (the sign of the jump of
    ``twist``); twist (S,) rad: psi_1 - psi_n at the outermost tube's end minus
    alpha_1 - alpha_n (the relative twist the tubes store; its sign tells the branches of a
    bistable pair apart); snap_q (k, 2n) the joint values where each snap happened (first
    sub-step past the fold) and snap_mu (k,) the stability of the last solution before it
    (small: the branch ended at a fold); energy (S,) N mm; substeps: sub-steps taken."""

    backbones: np.ndarray
    snaps: list
    stability: np.ndarray
    uz0: np.ndarray
    branch: np.ndarray
    twist: np.ndarray
    snap_q: np.ndarray
    snap_mu: np.ndarray
    energy: np.ndarray
    substeps: int = 0
    info: dict = field(default_factory=dict)

    @property
    def tips(self) -> np.ndarray:
        """(S, 3) mm."""
        return self.backbones[:, -1]


# ----------------------------------------------------------------------------- equilibria
@dataclass(frozen=True)
class Equilibrium:
    """One stable equilibrium: nodal angles x on the energy ``en``; uz0 (n,) 1/mm; twist rad;
    energy N mm; mu the stability measure."""

    en: EN.Energy
    x: np.ndarray
    uz0: np.ndarray
    twist: float
    energy: float
    mu: float


def _twist(en: EN.Energy, x: np.ndarray) -> float:
    n = en.n
    e_out = en.beta[n - 1] + en.spec.L[n - 1]
    s1, p1 = en.tube_values(x, 0)
    sn, pn = en.tube_values(x, n - 1)
    return float(np.interp(e_out, s1, p1) - np.interp(e_out, sn, pn) - (en.alpha[0] - en.alpha[n - 1]))


def _equilibrium(en: EN.Energy, x: np.ndarray, measure: bool = True) -> Equilibrium:
    mu = en.stability(x) if measure else float("nan")
    return Equilibrium(en, x, en.uz0(x), _twist(en, x), en.value(x), mu)


def _fan(spec: Spec, q: np.ndarray, m: int) -> np.ndarray:
    """Start base torsions (k, n) on the torque-balanced set sum GJ_i uz_i = 0 that twist the
    tubes relative to each other by up to about 2.5 pi over their length."""
    n = spec.n
    beta = q[n:]
    span = max(float(np.max(beta + spec.L) - np.min(beta)), 1.0)
    amp = 2.5 * np.pi / span
    if n == 1:
        return np.zeros((1, 1))
    grids = np.meshgrid(*[np.linspace(-amp, amp, m)] * (n - 1), indexing="ij")
    v = np.stack([g.ravel() for g in grids], axis=1)              # relative to the outermost
    uz = np.zeros((len(v), n))
    uz[:, :n - 1] = v
    uz[:, n - 1] = -(v @ spec.GJ[:n - 1]) / spec.GJ[n - 1]
    return np.vstack([np.zeros((1, n)), uz])


def equilibria(robot, q, h: float = 1.0, fan: int | None = None) -> list[Equilibrium]:
    """Every stable equilibrium of configuration q (2n,) found by descending the energy from a
    fan of twisted starts (``fan`` per relative angle; default 25 for two tubes, 9 for more),
    sorted by max |uz0| (least twisted first). Distinct: nodal angles differ by > 1e-3 rad."""
    spec = load_spec(robot)
    q = np.asarray(q, float)
    en = EN.build(spec, q, h)
    m = fan or (25 if spec.n == 2 else 9)
    found: list[Equilibrium] = []
    for uz in _fan(spec, q, m):
        x, conv, _ = EN.minimise(en, en.initial(uz), max_iter=200)
        if not conv:
            continue
        if any(np.max(np.abs(x - e.x)) < 1e-3 for e in found):
            continue
        eq = _equilibrium(en, x)
        if eq.mu > 0:
            found.append(eq)
    found.sort(key=lambda e: float(np.max(np.abs(e.uz0))))
    return found


def _start(spec: Spec, q: np.ndarray, uz0, h: float) -> Equilibrium:
    eqs = equilibria(spec, q, h)
    if not eqs:
        raise RuntimeError(f"no stable equilibrium found at the start {q.tolist()}")
    if uz0 is None:
        if len(eqs) > 1:
            raise ValueError(f"the start {np.round(q, 4).tolist()} is multistable ({len(eqs)} stable "
                             "equilibria): give uz0 (its base torsions) or uz0='least_twisted'")
        return eqs[0]
    if isinstance(uz0, str):
        if uz0 != "least_twisted":
            raise ValueError(f"uz0 must be None, 'least_twisted' or (n,) base torsions, got {uz0!r}")
        return eqs[0]
    u = np.asarray(uz0, float).reshape(spec.n)
    return min(eqs, key=lambda e: float(np.max(np.abs(e.uz0 - u))))


# ----------------------------------------------------------------------------- continuation
def _segment(spec, eq: Equilibrium, qa, qb, max_step, max_step_mm, h, snaps_out, counter, measure):
    """Follow eq from qa to qb; returns the equilibrium at qb. Appends (q, mu_before, x_before,
    x_after, en) per snap to snaps_out."""
    n = spec.n
    dq = qb - qa
    # joint length of the motion in units of the largest allowed sub-step
    span = max(np.max(np.abs(dq[:n])) / max_step, np.max(np.abs(dq[n:])) / max_step_mm)
    if span == 0.0:
        return eq
    t_min = MIN_STEP / max(np.max(np.abs(dq[:n])), np.max(np.abs(dq[n:])), 1e-300)
    dt_max = 1.0 / np.ceil(span)
    t, dt = 0.0, dt_max
    en, x = eq.en, eq.x
    same_geom = not np.any(dq[n:])
    while t < 1.0 - 1e-15:
        t_try = min(1.0, t + dt)
        q_try = qa + t_try * dq
        if same_geom:
            en_try = EN.Energy(**{**en.__dict__, "alpha": q_try[:n].copy()})
        else:
            en_try = EN.build(spec, q_try, h)
        pred = en_try.transfer(en, x)
        y, conv, _ = EN.minimise(en_try, pred, max_iter=NEWTON_ITER, require_pd=True)
        counter[0] += 1
        if conv and np.max(np.abs(y - pred)) <= DPSI_MAX:
            en, x, t = en_try, y, t_try
            dt = min(dt_max, 2.0 * dt)
            continue
        if t_try - t > t_min:
            dt = 0.5 * (t_try - t)
            continue
        # the branch ended between t and t_try: descend to the remaining minimum
        mu_before = en.stability(x)
        y, conv, _ = EN.minimise(en_try, pred, max_iter=5000)
        if not conv:
            raise RuntimeError(f"no minimum reached after the fold at q = {q_try.tolist()}")
        if np.max(np.abs(y - pred)) > SNAP_JUMP:
            snaps_out.append((q_try.copy(), mu_before, en, x, en_try, y))
        en, x, t = en_try, y, t_try
        dt = max(t_min, min(dt_max, 1e-3))
    return _equilibrium(en, x, measure)


def continue_path(robot, states, uz0=None, points: int = 20, max_step: float = 0.05,
                  max_step_mm: float = 1.0, h: float = 1.0, measure: bool = True) -> Continued:
    """Replay the joint motion ``states`` (S, 2n) (rad, mm; rotations unwrapped; the robot moves
    linearly between consecutive states) as the physical robot would, by continuation.

    robot: a shipped name, a robot YAML path or a foreign ``Spec``. uz0 picks the start branch:
    None (the start must have a unique stable equilibrium, else ValueError), 'least_twisted'
    (the stable equilibrium with the smallest max |uz0|, ctrplan's default), or (n,) base
    torsions (1/mm; the stable equilibrium nearest to them, e.g. ctrplan's ``last_info.uz0``).
    max_step / max_step_mm: largest sub-step of rotation (rad) / translation (mm); sub-steps
    shrink as needed (module docstring). h: element size of the energy (mm; the folds of the
    closed-form case move by about 4e-5 rad from 0.5 to 1 mm). points: backbone points m.
    measure: compute the stability measure at every state (False: NaN, faster; snap_mu is
    always computed)."""
    spec = load_spec(robot)
    Q = np.atleast_2d(np.asarray(states, float))
    if Q.shape[1] != 2 * spec.n or not np.all(np.isfinite(Q)):
        raise ValueError(f"states must be finite (S, {2 * spec.n}), got shape {Q.shape}")
    eq = _start(spec, Q[0], uz0, h)
    S = len(Q)
    bbs = np.zeros((S, points, 3))
    mu = np.zeros(S)
    uz = np.zeros((S, spec.n))
    tw = np.zeros(S)
    en_v = np.zeros(S)
    branch = np.zeros(S, int)
    snaps: list[int] = []
    snap_q, snap_mu = [], []
    counter = [0]
    for i in range(S):
        if i > 0:
            events: list = []
            eq = _segment(spec, eq, Q[i - 1], Q[i], max_step, max_step_mm, h, events, counter, measure)
            branch[i] = branch[i - 1]
            for (qs, mb, en0, x0, en1, x1) in events:
                snap_q.append(qs)
                snap_mu.append(mb)
                branch[i] += int(np.sign(_twist(en1, x1) - _twist(en0, x0) or 1.0))
            if events:
                snaps.append(i)
        bbs[i] = EN.backbone(eq.en, eq.x, points)
        mu[i], uz[i], tw[i], en_v[i] = eq.mu, eq.uz0, eq.twist, eq.energy
    return Continued(bbs, snaps, mu, uz, branch, tw,
                     np.array(snap_q).reshape(-1, 2 * spec.n), np.array(snap_mu), en_v, counter[0])


# ----------------------------------------------------------------------------- stability test
def _psi_from_uz0(spec: Spec, q: np.ndarray, uz0: np.ndarray, en: EN.Energy) -> np.ndarray:
    """Nodal angles of the equilibrium with base torsions uz0: the torsion equations integrated
    from s = 0 (scipy DOP853, tight) and sampled at the energy's nodes."""
    from scipy.integrate import solve_ivp
    n = spec.n
    alpha, beta = q[:n], q[n:]
    e = beta + spec.L
    c = np.clip(beta + spec.straight, 0.0, None)
    y = np.concatenate([alpha - beta * uz0, uz0])
    bps = np.unique(np.concatenate([[0.0], c, e]))
    bps = bps[bps >= 0.0]
    x = np.zeros(en.nvar)
    node_vals = {}
    for a, b in zip(bps[:-1], bps[1:]):
        if b - a <= EN.TOL_S:
            continue
        mid = 0.5 * (a + b)
        pres = mid < e
        w = np.where(pres & (mid >= c), spec.EI * spec.kappa, 0.0)
        EIs = float(np.sum(spec.EI[pres]))

        def f(s, yy, w=w, EIs=EIs, pres=pres):
            psi, u = yy[:n], yy[n:]
            d = np.sin(psi[:, None] - psi[None, :])
            return np.concatenate([np.where(pres, u, 0.0), np.where(pres, w * (d @ w) / (EIs * spec.GJ), 0.0)])

        ks = np.flatnonzero((en.s >= a - EN.TOL_S) & (en.s <= b + EN.TOL_S))
        sol = solve_ivp(f, (a, b), y, method="DOP853", rtol=1e-11, atol=1e-13, t_eval=np.clip(en.s[ks], a, b))
        for j, k in enumerate(ks):
            node_vals[k] = sol.y[:n, j]
        y = sol.y[:, -1].copy()
    for k, vals in node_vals.items():
        for i in range(n):
            if en.var[k, i] >= 0:
                x[en.var[k, i]] = vals[i]
    return x


def stability(robot, q, uz0, h: float = 1.0) -> np.ndarray:
    """Energy stability measure mu (B,) of the equilibria with base torsions uz0 (B, n) (1/mm,
    ctrplan's convention) at configurations q (B, 2n): > 0 stable, < 0 unstable, 0 at a fold.
    Also accepts a single q (2n,) and uz0 (n,) and then returns a float."""
    spec = load_spec(robot)
    single = np.ndim(q) == 1
    Q = np.atleast_2d(np.asarray(q, float))
    U = np.atleast_2d(np.asarray(uz0, float))
    out = np.zeros(len(Q))
    for b in range(len(Q)):
        en = EN.build(spec, Q[b], h)
        out[b] = en.stability(_psi_from_uz0(spec, Q[b], U[b], en))
    return float(out[0]) if single else out


def is_stable(robot, q, uz0, h: float = 1.0):
    """``stability(robot, q, uz0) > 0`` (bool, or (B,) bool for a batch)."""
    mu = stability(robot, q, uz0, h)
    return bool(mu > 0) if np.ndim(mu) == 0 else mu > 0
