"""The foreign continuation oracle (tests/foreign/energy.py, continuation.py, folds.py).

Known answers: two equal tubes ("a balanced pair") whose curved sections overlap over L with
torsion-only transmissions l between actuators and overlap. Their relative angle
theta = psi_1 - psi_2 obeys theta'' = lambda^2 sin theta (lambda^2 = 2 c / GJ,
c = (EI kappa)^2 / (2 EI)), free at the distal end (theta'(L) = 0) and
theta(0) - l theta'(0) = alpha_1 - alpha_2 at the actuators (the transmission is a torsion
spring). With phi = theta - pi this is a pendulum released from rest at phi_L = phi(L), so
(Jacobi elliptic functions, m = k^2, k = sin(phi_L / 2), tau = L - s):

    sin(phi / 2) = k cd(lambda tau | m),   dphi/dtau = -2 k lambda (1 - m) sd nd / cos(phi / 2)
    alpha_1 - alpha_2 = pi + phi(tau = L) + l dphi/dtau(tau = L)

a closed-form curve of actuator rotations over distal angles. Its extrema are the folds (Dupont
et al., T-RO 2010; Gilbert, Hendrick & Webster, T-RO 2016: snapping where a stable branch
meets an unstable one). Linearised about the untwisted state at pi: the second variation's
relative mode is cos(omega (L - s)) with cot(omega L) = omega l, and the energy measure
mu = min Q / T = 1 - lambda^2 / omega^2; the pair is bistable iff cot(lambda L) < lambda l
(the critical overlap L_crit solves cot(lambda L) = lambda l; l = 0 gives lambda L = pi / 2).
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.optimize import brentq, minimize_scalar
from scipy.special import ellipj

from tests.foreign import continuation as C
from tests.foreign import folds as F
from tests.foreign.robot import beta_from_unit, load_spec

ROBOTS = ("two_tube_nylon", "two_tube_wide")
ROBOT_DIR = Path(__file__).parents[1] / "ctrplan" / "data" / "robots"
KAPPA, NU = 0.02, 0.33
LAM = KAPPA * np.sqrt(1.0 + NU)          # lambda^2 = EI kappa^2 / GJ = kappa^2 (1 + nu)


def _ct(robot):
    """ctrplan's name for the robot (two_tube_wide by its YAML path)."""
    return robot if robot == "two_tube_nylon" else str(ROBOT_DIR / f"{robot}.yaml")


def _pair(L, straight):
    t = dict(od=2.0, id=1.6, straight_length=straight, curved_length=L, curvature=KAPPA,
             youngs_modulus=60000.0, poisson_ratio=NU)
    return load_spec({"name": "balanced", "tubes": [dict(t), dict(t)]})


def _dalpha(phi_l, L, ell):
    """Closed-form actuator relative rotation of the balanced pair with distal angle pi + phi_l."""
    k = np.sin(phi_l / 2.0)
    m = k * k
    sn, cn, dn, _ = ellipj(LAM * L, m)
    cd, sd, nd = cn / dn, sn / dn, 1.0 / dn
    phi = 2.0 * np.arcsin(k * cd)
    dphi = -2.0 * k * LAM * (1.0 - m) * sd * nd / np.sqrt(1.0 - (k * cd) ** 2)
    return np.pi + phi + ell * dphi


def _closed_fold(L, ell):
    """Upper fold b (rad) of the closed-form curve, or None (monostable)."""
    ph = np.linspace(-3.1, 0.0, 3101)
    v = _dalpha(ph, L, ell)
    i = int(np.argmax(v))
    if i in (0, len(ph) - 1):
        return None
    r = minimize_scalar(lambda p: -_dalpha(p, L, ell), bounds=(ph[i - 1], ph[i + 1]),
                        method="bounded", options={"xatol": 1e-12})
    return float(-r.fun)


def _omega(L, ell):
    return brentq(lambda o: np.cos(o * L) - o * ell * np.sin(o * L), 1e-12, np.pi / (2 * L))


def _loop(d_lo, d_hi, beta, step=0.05):
    d = np.arange(d_lo, d_hi + 1e-9, step)
    d = np.concatenate([d, d[::-1]])
    return np.column_stack([d, np.zeros_like(d), np.tile(beta, (len(d), 1))])


@pytest.mark.parametrize("L,straight,beta", [(80.0, 30.0, 0.0), (60.0, 50.0, -25.0)])
def test_balanced_pair_snaps_once_each_way_at_the_closed_form_folds(L, straight, beta):
    """A closed loop of relative rotation through the bistable range: exactly one snap up (at the
    closed-form fold b) and one down (at 2 pi - b), the branch back where it started; just
    before each snap the measure is near 0 (the branch ended at a fold)."""
    sp = _pair(L, straight)
    ell = straight            # actuator at the tube's proximal end, overlap from its curved start
    b = _closed_fold(L, ell)
    assert b is not None and b > np.pi + 0.3
    Q = _loop(np.pi - 1.6, np.pi + 1.6, np.array([beta, beta]))
    r = C.continue_path(sp, Q, points=10)
    S = len(Q)
    assert len(r.snap_q) == 2 and len(r.snaps) == 2
    assert r.snaps[0] < S // 2 <= r.snaps[1]
    up, down = r.snap_q[:, 0] - r.snap_q[:, 1]
    assert abs(up - b) < 2e-3
    assert abs(down - (2 * np.pi - b)) < 2e-3
    assert np.all(r.snap_mu < 0.01) and np.all(r.snap_mu > 0)
    assert r.branch[0] == 0 and r.branch[-1] == 0 and set(r.branch[S // 2 - 1:S // 2 + 1]) == {1}
    # hysteresis: at the same relative rotation inside the range, up and down differ
    i = int(np.argmin(np.abs(Q[:S // 2, 0] - np.pi)))
    assert np.max(np.abs(r.backbones[i] - r.backbones[S - 1 - i])) > 1.0
    # the backbone moves continuously between snaps and jumps at them
    jump = np.max(np.linalg.norm(np.diff(r.backbones, axis=0), axis=2), axis=1)
    at = np.array(r.snaps) - 1
    assert jump[at].min() > 5.0 * np.delete(jump, at).max()


@pytest.mark.parametrize("robot,beta", [("two_tube_nylon", (-60.0, 0.0)), ("two_tube_wide", (-80.0, 0.0))])
def test_closed_loop_on_the_robots_snaps_once_each_way_where_ctrplans_branch_ends(robot, beta):
    """Relative rotation up through the bistable range and back (curved sections overlapping):
    one snap each way, mirror images (a = 2 pi - b), and ctrplan's compliant model, warm-started
    along the same branch in steps of 0.002 rad, loses that branch (its solution jumps) within
    one step past the oracle's fold."""
    from ctrplan.shape.physics import PhysicsModel

    Q = _loop(np.pi - 1.6, np.pi + 1.6, np.array(beta))
    r = C.continue_path(robot, Q, points=5, measure=False)
    S = len(Q)
    assert len(r.snap_q) == 2 and r.snaps[0] < S // 2 <= r.snaps[1]
    up, down = r.snap_q[:, 0] - r.snap_q[:, 1]
    assert up > np.pi + 0.3 and abs(down - (2 * np.pi - up)) < 1e-4
    pm = PhysicsModel(_ct(robot))
    i = r.snaps[0] - 1                       # last state on the branch before the fold
    uz = r.uz0[i]
    jump = None
    for d in np.arange(Q[i, 0], up + 0.05, 0.002):
        q = np.array([[d, 0.0, *beta]])
        pm.solve(q, 2, pm.base_params(1), uz_init=uz[None])
        u = pm.last_info.uz0[0]
        if np.max(np.abs(u - uz)) > 2e-3:
            jump = d
            break
        uz = u
    assert jump is not None and 0.0 < jump - up <= 0.002 + 1e-9


def test_balanced_pair_stability_measure_and_critical_overlap():
    """mu of the untwisted state at pi equals the closed form 1 - lambda^2 / omega^2, changes sign
    at the critical overlap L_crit (cot(lambda L) = lambda l), and a pair just below it never
    snaps."""
    straight = 40.0
    ell = straight
    L_crit = brentq(lambda L: np.cos(LAM * L) - LAM * ell * np.sin(LAM * L), 1.0, np.pi / (2 * LAM))
    for L in (0.9 * L_crit, 1.1 * L_crit, 2.0 * L_crit):
        sp = _pair(L, straight)
        mu = C.stability(sp, [np.pi, 0.0, 0.0, 0.0], [0.0, 0.0])
        assert abs(mu - (1.0 - LAM ** 2 / _omega(L, ell) ** 2)) < 1e-4
        assert (mu > 0) == (L < L_crit)
        assert C.is_stable(sp, [np.pi, 0.0, 0.0, 0.0], [0.0, 0.0]) == (L < L_crit)
    r = C.continue_path(_pair(0.9 * L_crit, straight), _loop(np.pi - 1.6, np.pi + 1.6, np.zeros(2)), points=5)
    assert r.snaps == [] and np.all(r.stability > 0)


def test_start_branch_rules():
    """A bistable start needs its branch: None refuses, 'least_twisted' and uz0 pick one."""
    q = np.array([np.pi + 0.3, 0.0, -60.0, 0.0])
    eqs = C.equilibria("two_tube_nylon", q)
    assert len(eqs) == 2 and all(e.mu > 0 for e in eqs)
    with pytest.raises(ValueError, match="multistable"):
        C.continue_path("two_tube_nylon", q[None])
    lt = C.continue_path("two_tube_nylon", q[None], uz0="least_twisted")
    assert np.allclose(lt.uz0[0], eqs[0].uz0)
    other = C.continue_path("two_tube_nylon", q[None], uz0=eqs[1].uz0 + 1e-4)
    assert np.allclose(other.uz0[0], eqs[1].uz0)
    assert np.max(np.abs(lt.backbones[0] - other.backbones[0])) > 20.0


@pytest.mark.parametrize("robot", ROBOTS)
def test_equilibria_equal_ctrplan_compliant_model(robot):
    """Where both are on the same branch (the foreign equilibrium nearest ctrplan's uz(0)), the
    energy's equilibria give ctrplan's compliant backbones to 0.01 mm."""
    from ctrplan.shape.physics import PhysicsModel

    sp = load_spec(robot)
    rng = np.random.default_rng(3)
    B = 6
    q = np.column_stack([rng.uniform(-np.pi, np.pi, (B, 2)), beta_from_unit(sp, rng.uniform(size=(B, 2)))])
    pm = PhysicsModel(_ct(robot))
    ref = pm.backbone(q, 15)
    for b in range(B):
        r = C.continue_path(sp, q[b:b + 1], uz0=pm.last_info.uz0[b], points=15)
        assert np.max(np.abs(r.backbones[0] - ref[b])) < 0.01
        assert np.max(np.abs(r.uz0[0] - pm.last_info.uz0[b])) < 1e-5


def _sign_rows(robot, B, seed):
    """Random states near relative rotation pi (where unstable roots exist): the first root
    ctrplan's Newton finds without its stability check, and ctrplan's verdict on that root (its
    det J > 0 test, run by solving again from the root itself: ``branch`` 0 keeps it as stable,
    1, 2, 3 or -1 reject it as unstable)."""
    from ctrplan.shape.physics import PhysicsConfig, PhysicsModel

    sp = load_spec(robot)
    rng = np.random.default_rng(seed)
    d = np.pi + rng.uniform(-1.3, 1.3, B)
    a2 = rng.uniform(-np.pi, np.pi, B)
    q = np.column_stack([a2 + d, a2, beta_from_unit(sp, rng.uniform(size=(B, 2)))])
    free = PhysicsModel(_ct(robot), config=PhysicsConfig(stability=False))
    free.backbone(q, 2)
    roots = free.last_info.uz0.copy()
    q, roots = q[free.last_info.residual < 1e-9], roots[free.last_info.residual < 1e-9]
    pm = PhysicsModel(_ct(robot))
    pm.solve(q, 2, pm.base_params(len(q)), uz_init=roots)
    br = pm.last_info.branch
    kept = (br == 0) & (np.max(np.abs(pm.last_info.uz0 - roots), axis=1) < 1e-7)
    rejected = np.isin(br, (1, 2, 3, -1))
    use = kept | rejected
    return sp, q[use], roots[use], kept[use]


@pytest.mark.parametrize("robot", ROBOTS)
def test_stability_sign_agrees_with_ctrplan_det_j(robot):
    """The energy measure and ctrplan's det J > 0 test call the same equilibria stable (away
    from folds, |mu| > 1e-3), on stable and unstable roots alike."""
    sp, q, uz0, ct_stable = _sign_rows(robot, 40, seed=5)
    mu = C.stability(sp, q, uz0)
    far = np.abs(mu) > 1e-3
    assert far.sum() >= 30
    assert np.array_equal(mu[far] > 0, ct_stable[far])
    assert (mu[far] < 0).sum() >= 3 and (mu[far] > 0).sum() >= 3


@pytest.mark.parametrize("robot", ROBOTS)
def test_fold_crossing_pairs_cross_a_fold(robot):
    """Each generated pair: start and target on opposite sides of the bistable range (both
    monostable for the oracle and not flagged bistable by ctrplan's probe), the shortest joint
    motion crosses states ctrplan flags bistable, and replayed by continuation it snaps at a
    fold."""
    from ctrplan.shape.physics import PhysicsConfig, PhysicsModel

    cases = F.fold_crossing_cases(robot, 1, seed=11)
    pm = PhysicsModel(_ct(robot), config=PhysicsConfig(probe_bistable=True))
    for c in cases:
        d = c.target_q - c.start_q
        assert np.all(np.abs(d[:2]) < np.pi)
        a, b = c.folds
        rel_s = (c.start_q[0] - c.start_q[1]) % (2 * np.pi)
        rel_t = (c.target_q[0] - c.target_q[1]) % (2 * np.pi)
        lo, hi = (rel_s, rel_t) if c.up else (rel_t, rel_s)
        assert lo < a and hi > b
        t = np.linspace(0.0, 1.0, 41)[:, None]
        Q = c.start_q + t * d
        r = C.continue_path(robot, Q, points=10)
        assert len(r.snap_q) == c.snaps >= 1 and np.all(r.snap_mu < 0.02)
        assert np.allclose(r.tips[-1], c.target, atol=1e-6)
        pm.backbone(Q, 2)
        bi = pm.last_info.bistable
        assert not bi[0] and not bi[-1] and bi.any()


def test_foreign_continuation_imports_nothing_from_ctrplan():
    code = ("import sys; from tests.foreign import continuation, folds; "
            "continuation.continue_path('two_tube_nylon', [[2.0, 0.0, -60.0, 0.0], [2.1, 0.0, -60.0, 0.0]]); "
            "assert not any(m == 'ctrplan' or m.startswith('ctrplan.') for m in sys.modules), 'ctrplan imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).parents[1])


# ----------------------------------------------------------------------------- statistical
@pytest.mark.statistical
@pytest.mark.parametrize("robot", ROBOTS)
def test_stability_sign_agrees_with_ctrplan_det_j_many(robot):
    sp, q, uz0, ct_stable = _sign_rows(robot, 300, seed=21)
    mu = C.stability(sp, q, uz0)
    far = np.abs(mu) > 1e-3
    assert far.sum() >= 250
    assert np.array_equal(mu[far] > 0, ct_stable[far])
    assert (mu[far] < 0).sum() >= 30


@pytest.mark.statistical
@pytest.mark.parametrize("robot", ROBOTS)
def test_bistable_range_agrees_with_ctrplan(robot):
    """At random translations: every relative rotation ctrplan's probe flags bistable lies in the
    oracle's range [a, b] (to its grid), and the probe finds at least 70 % of that range."""
    from ctrplan.shape.physics import PhysicsConfig, PhysicsModel

    sp = load_spec(robot)
    rng = np.random.default_rng(8)
    pm = PhysicsModel(_ct(robot), config=PhysicsConfig(probe_bistable=True))
    d = np.arange(0.0, 2 * np.pi, 0.01)
    seen = 0
    for u in rng.uniform(size=(12, 2)):
        beta = beta_from_unit(sp, u[None])[0]
        rng_ab = F.bistable_range(sp, beta)
        pm.backbone(np.column_stack([d, np.zeros_like(d), np.tile(beta, (len(d), 1))]), 2)
        bi = pm.last_info.bistable
        if rng_ab is None:
            assert not bi.any()
            continue
        a, b = rng_ab
        seen += 1
        assert np.all((d[bi] > a - 0.01) & (d[bi] < b + 0.01))
        assert bi.sum() * 0.01 >= 0.7 * (b - a) - 0.02
    assert seen >= 4


@pytest.mark.statistical
@pytest.mark.parametrize("robot", ROBOTS)
def test_twenty_fold_crossing_pairs_snap(robot):
    """20 fold-crossing cases per robot, each snapping exactly as generated when replayed with
    twice the state density; same seed, same pairs."""
    cases = F.fold_crossing_cases(robot, 20, seed=2)
    assert len(cases) == 20
    pairs = F.fold_crossing_pairs(robot, 2, seed=2)
    for (s, t), c in zip(pairs, cases):
        assert np.array_equal(s, c.start_q) and np.array_equal(t, c.target)
    for c in cases:
        t = np.linspace(0.0, 1.0, 81)[:, None]
        r = C.continue_path(robot, c.start_q + t * (c.target_q - c.start_q), points=5)
        assert len(r.snap_q) == c.snaps >= 1
        assert np.allclose(r.tips[-1], c.target, atol=1e-6)
