"""Elastic stability of the torsionally compliant model (snap-through, two_tube_nylon).

The oracle is independent of ctrplan's kernel: the tube data come from the foreign generator's
own YAML reader, the torsion ODE is integrated here with scipy (from ctrplan's returned
uz(0)), and stability is decided by the smallest eigenvalue of the Hessian of an elastic
energy discretised here (finite elements, linear in psi on a ~1 mm grid):

    E[psi] = sum_i int GJ_i psi_i'^2 / 2 + int V(psi),  V = -|sum_j w_j e^{i psi_j}|^2 / (2 EIsum)

with psi_i(beta_i) = alpha_i fixed and free tube ends. A stable equilibrium is a strict local
minimum: the Hessian is positive definite. Second oracle: the foreign generator's solution
(tests/foreign, which never returns an unstable equilibrium).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.linalg import eigvals_banded

from ctrplan.shape.physics import PhysicsModel
from tests.foreign import generate
from tests.foreign import mechanics as FM
from tests.foreign.core import load_spec

ROBOT = "two_tube_nylon"
N_ROWS = 320


def _regime(sp, beta, s):
    """Present and curved tubes at arc length s (open interval midpoints)."""
    ends = beta + sp.L
    present = s < ends
    curved = present & (s >= beta + sp.straight) & (sp.kappa != 0)
    return present, curved


def _breaks(sp, beta):
    pts = np.concatenate([[0.0], np.maximum(beta + sp.straight, 0.0), beta + sp.L])
    return np.unique(pts[pts >= 0.0])


def _torsion_ode(sp, alpha, beta, x):
    """Integrate psi, uz from s = 0 with uz(0) = x (scipy, tight). Returns (interp, resid):
    interp(s) -> psi (n,) for s >= 0, resid = uz_i at tube i's end."""
    n = sp.n
    EI, GJ = sp.EI, sp.GJ
    psi0 = alpha - beta * x                 # straight, untwisting-free part behind the plane
    ys = np.concatenate([psi0, x])
    br = _breaks(sp, beta)
    pieces = []
    resid = np.full(n, np.nan)
    ends = beta + sp.L
    for a, b in zip(br[:-1], br[1:]):
        present, curved = _regime(sp, beta, 0.5 * (a + b))
        w = np.where(curved, EI * sp.kappa, 0.0)
        S = EI[present].sum()

        def f(s, y, w=w, S=S, present=present):
            psi, uz = y[:n], y[n:]
            d = np.sin(psi[:, None] - psi[None, :])
            duz = np.where(present, w * (d @ w) / (S * GJ), 0.0)
            return np.concatenate([np.where(present, uz, 0.0), duz])

        sol = solve_ivp(f, (a, b), ys, method="DOP853", rtol=1e-11, atol=1e-13, dense_output=True)
        pieces.append((a, b, sol.sol))
        ys = sol.y[:, -1].copy()
        for i in range(n):
            if abs(ends[i] - b) < 1e-9:
                resid[i] = ys[n + i]
                ys[n + i] = 0.0

    def interp(s):
        for a, b, so in pieces:
            if s <= b + 1e-12:
                return so(min(max(s, a), b))[:n]
        return pieces[-1][2](pieces[-1][1])[:n]

    return interp, resid


def _hessian_min_eig(sp, alpha, beta, x, h=1.0):
    """Smallest eigenvalue of the discretised energy Hessian at the equilibrium uz(0) = x
    (N mm; > 0: stable), and the distal torsion residual of the independent integration."""
    n = sp.n
    EI, GJ = sp.EI, sp.GJ
    interp, resid = _torsion_ode(sp, alpha, beta, x)
    ends = beta + sp.L
    # grid: every break point, each interval cut into ~h pieces; behind s = 0 psi is linear
    br = np.unique(np.concatenate([[beta.min()], beta, _breaks(sp, beta)]))
    grid = [br[0]]
    for a, b in zip(br[:-1], br[1:]):
        k = max(1, int(math.ceil((b - a) / h)))
        grid.extend(list(np.linspace(a, b, k + 1)[1:]))
    s = np.array(grid)
    psi = np.array([alpha + (sk - beta) * x if sk <= 0 else interp(sk) for sk in s])  # (K, n)
    # variables: psi_i at nodes beta_i < s_k <= e_i; order node-major so the Hessian is banded
    var = {}
    for k, sk in enumerate(s):
        for i in range(n):
            if beta[i] + 1e-9 < sk <= ends[i] + 1e-9:
                var[(k, i)] = len(var)
    N = len(var)
    Hd = {}

    def add(p, q, v):
        if p is None or q is None:
            return
        if p > q:
            p, q = q, p
        Hd[(p, q)] = Hd.get((p, q), 0.0) + v

    for k in range(len(s) - 1):
        hk = s[k + 1] - s[k]
        mid = 0.5 * (s[k] + s[k + 1])
        present, curved = _regime(sp, beta, mid)
        # twist: GJ_i (psi_{k+1} - psi_k)^2 / (2 h) on tube i's own domain
        for i in range(n):
            if beta[i] - 1e-9 <= s[k] and s[k + 1] <= ends[i] + 1e-9:
                p, q = var.get((k, i)), var.get((k + 1, i))
                c = GJ[i] / hk
                add(p, p, c)
                add(q, q, c)
                add(p, q, -c)
        if mid < 0 or curved.sum() < 2:
            continue            # V is constant in psi there
        w = np.where(curved, EI * sp.kappa, 0.0)
        S = EI[present].sum()
        for kk in (k, k + 1):            # trapezoid rule, regime of the element
            ps = psi[kk]
            for i in range(n):
                for j in range(n):
                    if w[i] == 0 or w[j] == 0:
                        continue
                    cij = w[i] * w[j] * math.cos(ps[i] - ps[j]) / S * 0.5 * hk
                    if i == j:
                        continue
                    # d2V/dpsi_i^2 += w_i w_j cos / S ; d2V/dpsi_i dpsi_j = -w_i w_j cos / S
                    add(var.get((kk, i)), var.get((kk, i)), cij)
                    if i < j:
                        add(var.get((kk, i)), var.get((kk, j)), -cij)
    bw = max(q - p for p, q in Hd) if Hd else 0
    ab = np.zeros((bw + 1, N))          # lower banded form: ab[q - p, p] = H[q, p]
    for (p, q), v in Hd.items():
        ab[q - p, p] = v
    lam = eigvals_banded(ab, lower=True, select="i", select_range=(0, 0))[0]
    return float(lam), resid


@pytest.fixture(scope="module")
def nylon_uniform():
    d = generate(ROBOT, "uniform", n=N_ROWS, effects={}, seed=0)
    model = PhysicsModel(ROBOT, torsion=True)
    shape = model.shape(d.q, points=20)
    return d, model, shape, model.last_info


def test_energy_oracle_detects_the_unstable_untwisted_state():
    """The oracle can fail: at a relative rotation of exactly 180 deg with deep overlap the
    untwisted state uz = 0 is an equilibrium (by symmetry) and unstable for the nylon pair
    (Hessian indefinite); ctrplan rejects it and returns a twisted, stable equilibrium."""
    sp = load_spec(ROBOT)
    from tests.foreign.robot import beta_from_unit
    beta = beta_from_unit(sp, np.array([[0.05, 0.6]]))[0]
    alpha = np.array([math.pi, 0.0])
    lam0, res0 = _hessian_min_eig(sp, alpha, beta, np.zeros(2))
    assert np.all(np.abs(res0) < 1e-12) and lam0 < 0
    model = PhysicsModel(ROBOT)
    q = np.concatenate([alpha, beta])[None]
    shape = model.shape(q)
    info = model.last_info
    assert shape.ok[0] and info.branch[0] != 0 and info.detj[0] > 0
    assert np.abs(info.uz0[0]).max() > 1e-3
    lam, res = _hessian_min_eig(sp, alpha, beta, info.uz0[0])
    assert np.all(np.abs(res) < 1e-7) and lam > 0
    # without the stability check the first equilibrium Newton finds is returned: uz = 0 here
    plain = PhysicsModel(ROBOT, config=model.config.__class__(stability=False))
    plain.shape(q)
    assert np.abs(plain.last_info.uz0[0]).max() < 1e-9


def test_never_returns_an_unstable_equilibrium(nylon_uniform):
    """320 uniform configurations of two_tube_nylon, physical GJ: every returned equilibrium is
    a strict minimum of the independently discretised energy and meets the distal boundary
    conditions of an independent integration. Before the fix ~10 % of them were unstable."""
    d, model, shape, info = nylon_uniform
    sp = load_spec(ROBOT)
    assert shape.ok.all()
    assert (info.branch != 0).mean() > 0.08         # the snapping regime is exercised (README)
    assert np.all(info.detj > 0)
    n = sp.n
    for k in range(len(d.q)):
        lam, res = _hessian_min_eig(sp, d.q[k, :n], d.q[k, n:], info.uz0[k], h=2.0)
        assert np.all(np.abs(res) < 1e-7), (k, res)
        assert lam > 0, (k, lam, info.branch[k])
    # and the rejected ones were unstable by the same oracle: the equilibrium the solve without
    # the check returns in those rows is a saddle of the energy (tip off by 3-50 mm)
    from ctrplan.shape.physics import PhysicsConfig
    unchecked = PhysicsModel(ROBOT, config=PhysicsConfig(stability=False))
    us = unchecked.shape(d.q, points=20)
    for k in np.flatnonzero(info.branch != 0):
        lam, res = _hessian_min_eig(sp, d.q[k, :n], d.q[k, n:], unchecked.last_info.uz0[k], h=2.0)
        assert np.all(np.abs(res) < 1e-7) and lam < 0, (k, lam)
        assert np.linalg.norm(us.points[k, -1] - shape.points[k, -1]) > 1.0


def test_agrees_with_the_foreign_generator(nylon_uniform):
    """Rows whose first equilibrium was stable (branch 0): tips equal to the generator's to
    1e-3 mm. Rows where an unstable one was rejected: the tip equals the generator's, or both
    solutions are distinct stable equilibria (bistable; the two pick different branches)."""
    d, model, shape, info = nylon_uniform
    sp = load_spec(ROBOT)
    n = sp.n
    gen = FM.cosserat(sp, d.q[:, :n], d.q[:, n:], torsion=True)
    assert gen.ok.all()
    dev = np.linalg.norm(shape.points[:, -1] - gen.tip(), axis=1)
    plain = info.branch == 0
    assert dev[plain].max() < 1e-3
    other = np.flatnonzero(~plain & (dev >= 1e-3))
    assert len(other) < (~plain).sum()              # most rejected rows now agree
    for k in other:
        xg = gen.info["x"][k]
        assert np.abs(xg - info.uz0[k]).max() > 1e-4   # a different equilibrium
        lam, res = _hessian_min_eig(sp, d.q[k, :n], d.q[k, n:], xg, h=2.0)
        assert lam > 0 and np.all(np.abs(res) < 1e-7)
    # bistable rows (two stable found) are flagged
    assert np.array_equal(info.bistable, info.branch == 2)
    assert info.bistable.sum() >= 10


def test_stable_rows_are_bit_identical_to_the_unchecked_solve(nylon_uniform):
    """The check only adds work where the first equilibrium is unstable: everywhere else the
    result is bit-identical to the solve without it (seed1: every row)."""
    from ctrplan.robot import load_robot
    from ctrplan.shape.physics import PhysicsConfig
    d, model, shape, info = nylon_uniform
    plain = PhysicsModel(ROBOT, config=PhysicsConfig(stability=False))
    ps = plain.shape(d.q, points=20)
    keep = info.branch == 0
    assert np.array_equal(ps.points[keep], shape.points[keep])
    assert not np.array_equal(ps.points[~keep], shape.points[~keep])
    r = load_robot("seed1")
    q = r.sample(1000, seed=3)
    a = PhysicsModel(r)
    sa = a.shape(q)
    sb = PhysicsModel(r, config=PhysicsConfig(stability=False)).shape(q)
    assert np.array_equal(sa.points, sb.points) and np.array_equal(sa.ok, sb.ok)
    assert np.all(a.last_info.branch == 0) and np.all(a.last_info.detj > 0)


def test_the_other_stable_branch_of_a_bistable_row_is_reachable(nylon_uniform):
    """uz0_alt of a bistable row starts Newton on the other stable equilibrium: the solve from
    it keeps it (first equilibrium stable, branch 0), the oracle confirms it is a minimum too,
    and its tip lies far from the returned one (the snap)."""
    d, model, shape, info = nylon_uniform
    sp = load_spec(ROBOT)
    n = sp.n
    rows = np.flatnonzero(info.bistable)
    assert np.all(np.isfinite(info.uz0_alt[rows])) and np.all(np.isnan(info.uz0_alt[~info.bistable]))
    rows = rows[:8]
    q = d.q[rows]
    alt = model.solve(q, 20, model.base_params(len(rows)), uz_init=info.uz0_alt[rows])
    ai = model.last_info
    assert alt.ok.all() and np.all(ai.branch == 0) and np.all(ai.detj > 0)
    np.testing.assert_allclose(ai.uz0, info.uz0_alt[rows], atol=1e-9)
    assert np.all(np.linalg.norm(alt.points[:, -1] - shape.points[rows, -1], axis=1) > 1.0)
    for k in range(len(rows)):
        lam, res = _hessian_min_eig(sp, q[k, :n], q[k, n:], ai.uz0[k], h=2.0)
        assert lam > 0 and np.all(np.abs(res) < 1e-7)


def test_probe_flags_bistable_rows_whose_first_root_is_stable():
    """PhysicsConfig(probe_bistable=True): rows whose first equilibrium is stable but which have
    a second stable one (near the edges of the snapping range) are flagged too; shapes are
    unchanged, and each flagged second equilibrium is a minimum of the oracle's energy."""
    from ctrplan.robot import load_robot
    from ctrplan.shape.physics import PhysicsConfig
    rb = load_robot(ROBOT)
    q = rb.sample(3000, seed=7)
    plain = PhysicsModel(rb)
    probed = PhysicsModel(rb, config=PhysicsConfig(probe_bistable=True))
    a = plain.shape(q)
    b = probed.shape(q)
    ia, ib = plain.last_info, probed.last_info
    assert np.array_equal(a.points, b.points) and np.array_equal(a.ok, b.ok)
    assert np.all(ib.bistable[ia.bistable])
    extra = np.flatnonzero(ib.branch == 4)
    assert len(extra) >= 5
    sp = load_spec(ROBOT)
    n = sp.n
    for k in extra[:6]:
        for x in (ib.uz0[k], ib.uz0_alt[k]):
            lam, res = _hessian_min_eig(sp, q[k, :n], q[k, n:], x, h=2.0)
            assert lam > 0 and np.all(np.abs(res) < 1e-7), (k, lam)
        assert np.abs(ib.uz0[k] - ib.uz0_alt[k]).max() > 1e-4


def test_of_two_stable_roots_the_one_nearest_the_initial_guess_is_returned(nylon_uniform):
    """Warm start exactly on the unstable equilibrium (from the unchecked solve): it is
    rejected and, of the two stable ones, the nearer the initial guess is returned (default
    guess 0: the less twisted one)."""
    from ctrplan.shape.physics import PhysicsConfig
    d, model, shape, info = nylon_uniform
    rows = np.flatnonzero(info.branch == 2)[:10]
    q = d.q[rows]
    xa, xb = info.uz0[rows], info.uz0_alt[rows]
    # default guess 0: the returned one is the less twisted
    assert np.all(np.abs(xa).max(axis=1) <= np.abs(xb).max(axis=1))
    unchecked = PhysicsModel(ROBOT, config=PhysicsConfig(stability=False))
    unchecked.shape(q)
    xu = unchecked.last_info.uz0
    warm = PhysicsModel(ROBOT)
    warm.solve(q, 20, warm.base_params(len(rows)), uz_init=xu)
    wi = warm.last_info
    assert np.all(wi.branch == 2)
    nearer_a = np.abs(xa - xu).max(axis=1) < np.abs(xb - xu).max(axis=1)
    assert nearer_a.any() and (~nearer_a).any()      # the rule decides both ways here
    expect = np.where(nearer_a[:, None], xa, xb)
    np.testing.assert_allclose(wi.uz0, expect, atol=1e-9)
