"""External loads in the mechanics model (tip force/moment, gravity).

Oracles, none sharing code with ctrplan.shape._loaded:
- Euler-Bernoulli cantilever deflections of a single straight tube at small loads;
- an independent integration written here: the loaded Cosserat rod equations in a different
  formulation (material frame of tube 1, the global internal force and moment integrated as
  states, the base force as an unknown), scipy DOP853 between break points, scipy root;
- finite differences of the shooting residual (the variational Jacobian);
- the unloaded kernels (bit-identical results when every load is zero).
"""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
from scipy.integrate import solve_ivp
from scipy.optimize import root

from ctrplan.errors import InputError
from ctrplan.robot import Robot, Tube, load_robot, robot_from_dict
from ctrplan.shape import _loaded
from ctrplan.shape._ode import _tube_events
from ctrplan.shape.effects import EffectModel, effect_params
from ctrplan.shape.physics import Loads, MechanicsParams, PhysicsModel

G = 9.81


def straight_robot(L=200.0, od=1.3, id=1.0, E=60000.0, density=None) -> Robot:
    # a tiny curved section (curvature 0) keeps the usual tube layout
    t = Tube(od=od, id=id, straight_length=L, curved_length=0.0, curvature=0.0,
             youngs_modulus=E, poisson_ratio=0.33, density=density)
    return Robot(name="straight", tubes=(t,))


# ----------------------------------------------------------------------------- Euler-Bernoulli
@pytest.mark.parametrize("torsion", [True, False])
def test_cantilever_tip_force(torsion):
    r = straight_robot()
    EI = r.tubes[0].bending_stiffness
    L = r.lengths[0]
    F = 0.002                                         # N, along +y: delta / L ~ 5e-3
    m = PhysicsModel(r, torsion=torsion, loads=Loads(tip_force=(0.0, F, 0.0)))
    shp = m.shape(np.array([[0.3, 0.0]]), 41)
    assert shp.ok.all()
    d = shp.tip[0, 1]
    exact = F * L**3 / (3 * EI)
    assert abs(d / exact - 1) < 1e-2
    # and the whole deflection curve: w(s) = F s^2 (3L - s) / (6 EI)
    s = shp.s[0]
    w = F * s**2 * (3 * L - s) / (6 * EI)
    assert np.max(np.abs(shp.points[0, :, 1] - w)) < 1e-2 * exact
    assert np.max(np.abs(shp.points[0, :, 0])) < 1e-9


@pytest.mark.parametrize("density", [None, 1140.0])
def test_cantilever_gravity(density):
    r = straight_robot(density=density)
    t = r.tubes[0]
    EI = t.bending_stiffness
    L = r.lengths[0]
    rho = 6450.0 if density is None else density        # nitinol default (documented)
    wlin = rho * math.pi / 4 * (t.od**2 - t.id**2) * 1e-9 * G   # N/mm
    m = PhysicsModel(r, loads=Loads(gravity=(-G, 0.0, 0.0)))
    shp = m.shape(np.array([[0.0, 0.0]]), 41)
    assert shp.ok.all()
    exact = wlin * L**4 / (8 * EI)
    assert abs(-shp.tip[0, 0] / exact - 1) < 1e-2
    s = shp.s[0]
    w = wlin * s**2 * (6 * L**2 - 4 * L * s + s**2) / (24 * EI)
    assert np.max(np.abs(-shp.points[0, :, 0] - w)) < 1e-2 * exact


def test_cantilever_tip_moment():
    r = straight_robot()
    EI = r.tubes[0].bending_stiffness
    L = r.lengths[0]
    Mm = 1.0                                            # N mm about -x bends toward +y
    m = PhysicsModel(r, loads=Loads(tip_moment=(-Mm, 0.0, 0.0)))
    shp = m.shape(np.array([[0.0, 0.0]]), 21)
    assert shp.ok.all()
    exact = Mm * L**2 / (2 * EI)
    assert abs(shp.tip[0, 1] / exact - 1) < 1e-2
    s = shp.s[0]
    assert np.max(np.abs(shp.points[0, :, 1] - Mm * s**2 / (2 * EI))) < 1e-2 * exact


def test_cantilever_partly_inserted():
    """beta < 0: only the part beyond the constraint plane bends (L_free = beta + L)."""
    r = straight_robot()
    EI = r.tubes[0].bending_stiffness
    F = 0.002
    m = PhysicsModel(r, loads=Loads(tip_force=(F, 0.0, 0.0)))
    shp = m.shape(np.array([[0.0, -80.0]]), 21)
    Lf = 120.0
    assert abs(shp.tip[0, 0] / (F * Lf**3 / (3 * EI)) - 1) < 1e-2


# ----------------------------------------------------------------------------- independent BVP
class Reference:
    """Loaded CTR, one configuration, written independently of the kernel.

    States: p (3), R1 (9, material frame of tube 1), n (3, global force), m (3, global
    moment), theta_i = psi_i - psi_1 (i >= 2), uz_i (n). Unknowns at s = 0: m_x, m_y (global),
    n(0) (3), uz_i(0); m_z(0) = sum GJ_i uz_i(0) (torsional balance at the base).
    Residuals: n(l) = F, (R1^T (m - M))_xy = 0 at the tip, GJ_1 uz_1(l) = (R1^T M)_z,
    uz_i(l_i) = 0 for the outer tubes. Torsionally rigid: psi_i = alpha_i, uz = 0, and the
    unknown m_z(0) is fixed by (R1^T (m - M))_z = 0 at the tip.
    """

    def __init__(self, robot, q, torsion=True, gravity=(0, 0, 0), F=(0, 0, 0), M=(0, 0, 0),
                 kink=None):
        self.r = robot
        n = robot.n
        self.n = n
        self.alpha = q[:n]
        self.beta = q[n:]
        self.L = robot.lengths
        self.ends = self.beta + self.L
        self.cstart = self.beta + robot.array("straight_length")
        self.kappa = robot.array("curvature")
        self.EI = robot.array("bending_stiffness")
        self.GJ = robot.array("torsional_stiffness")
        self.torsion = torsion
        rho = np.array([6450.0 if t.density is None else t.density for t in robot.tubes])
        area = np.array([math.pi / 4 * (t.od**2 - t.id**2) for t in robot.tubes])
        self.wl = rho * area * 1e-9                     # kg/mm
        self.g = np.asarray(gravity, float)
        self.F = np.asarray(F, float)
        self.M = np.asarray(M, float)
        self.tip = float(self.ends.max())
        self.kink = np.zeros((n, 2)) if kink is None else np.asarray(kink, float)

    def rhs(self, s, y):
        n = self.n
        R = y[3:12].reshape(3, 3)
        nf = y[12:15]
        mm = y[15:18]
        theta = np.concatenate([[0.0], y[18:18 + n - 1]])
        uz = y[18 + n - 1:18 + 2 * n - 1]
        present = s < self.ends
        curved = present & (s >= self.cstart)
        eis = self.EI[present].sum()
        mb = R.T @ mm
        acc = mb[:2].copy()
        for i in range(n):
            if curved[i]:
                c, sn = math.cos(theta[i]), math.sin(theta[i])
                acc += self.EI[i] * self.kappa[i] * np.array([-sn, c])  # Rz(theta) (0, k)
        u1 = np.array([acc[0] / eis, acc[1] / eis, uz[0]])
        duz = np.zeros(n)
        if self.torsion:
            for i in range(n):
                if curved[i]:
                    c, sn = math.cos(theta[i]), math.sin(theta[i])
                    uix = c * u1[0] + sn * u1[1]           # Rz(theta)^T u1
                    uiy = -sn * u1[0] + c * u1[1]
                    duz[i] = self.EI[i] / self.GJ[i] * (uix * self.kappa[i] - uiy * 0.0)
        f = self.g * np.sum(self.wl[present])
        hat = np.array([[0, -u1[2], u1[1]], [u1[2], 0, -u1[0]], [-u1[1], u1[0], 0]])
        dy = np.zeros_like(y)
        dy[0:3] = R[:, 2]
        dy[3:12] = (R @ hat).reshape(-1)
        dy[12:15] = -f
        dy[15:18] = -np.cross(R[:, 2], nf)
        dy[18:18 + n - 1] = uz[1:] - uz[0]
        dy[18 + n - 1:18 + 2 * n - 1] = duz
        dy[-1] = uz[0]                      # psi_1, tube 1's angle to a twist-free frame
        return dy

    def run(self, x, s_out=None):
        n = self.n
        uz0 = x[5:5 + n] if self.torsion else np.zeros(n)
        psi0 = self.alpha - self.beta * uz0
        c, sn = math.cos(psi0[0]), math.sin(psi0[0])
        R0 = np.array([[c, -sn, 0], [sn, c, 0], [0, 0, 1.0]])
        m0 = np.array([x[0], x[1], np.sum(self.GJ * uz0) if self.torsion else x[-1]])
        y = np.concatenate([np.zeros(3), R0.reshape(-1), x[2:5], m0, psi0[1:] - psi0[0], uz0,
                            psi0[:1]])
        brk = sorted({0.0, *np.maximum(self.cstart, 0).tolist(), *self.ends.tolist(),
                      *([] if s_out is None else list(s_out))})
        res_t = np.zeros(n)
        pts = {}
        s_now = 0.0
        for s_next in brk:
            if s_next > s_now:
                lo, hi = s_now, s_next
                eps = 1e-9 * (hi - lo)

                def f(s, yy, a=lo + eps, b=hi - eps):
                    return self.rhs(min(max(s, a), b), yy)

                sol = solve_ivp(f, (lo, hi), y, method="DOP853", rtol=1e-12, atol=1e-13)
                y = sol.y[:, -1].copy()
                s_now = s_next
            for i in range(n):
                if abs(self.ends[i] - s_now) < 1e-12:
                    k = 18 + n - 1 + i
                    R = y[3:12].reshape(3, 3)
                    tgt = (R.T @ self.M)[2] if i == 0 else 0.0
                    res_t[i] = (self.GJ[i] * y[k] - tgt) / self.EI[i] if self.torsion else 0.0
                    y[k] = 0.0
                    if np.any(self.kink[i] != 0):
                        # the twist-free frame Rt = R1 Rz(-psi_1) turns by K = Exp([kx, ky, 0]);
                        # the bending moment turns with it, the twisting moment carries over
                        from scipy.spatial.transform import Rotation

                        K = Rotation.from_rotvec([*self.kink[i], 0.0]).as_matrix()
                        c1, s1 = math.cos(y[-1]), math.sin(y[-1])
                        Rz = np.array([[c1, -s1, 0], [s1, c1, 0], [0, 0, 1.0]])
                        Rt = y[3:12].reshape(3, 3) @ Rz.T
                        mb = Rt.T @ y[15:18]
                        mb_new = np.array([*(K.T @ mb)[:2], mb[2]])
                        Rt = Rt @ K
                        y[15:18] = Rt @ mb_new
                        y[3:12] = (Rt @ Rz).reshape(-1)
            pts[round(s_now, 9)] = y[0:3].copy()
        R = y[3:12].reshape(3, 3)
        mres = (R.T @ (y[15:18] - self.M)) / self.EI[0]
        nres = y[12:15] - self.F
        # compliant: the tip twist condition is on tube 1's torsion (res_t); rigid: on m_z
        resid = np.concatenate([mres[:2], nres, res_t if self.torsion else mres[2:]])
        return resid, pts

    def solve(self, s_out, uz0=None, m0=None):
        """Points at s_out; optional first guesses of uz(0) and (m_x, m_y)(0)."""
        n = self.n
        # unknowns: m_x, m_y, n(0), then uz(0) (torsion) or m_z (rigid)
        tot_w = self.g * np.sum(self.wl * np.maximum(self.ends, 0.0))
        x0 = np.concatenate([[0.0, 0.0] if m0 is None else m0, self.F + tot_w,
                             (np.zeros(n) if uz0 is None else uz0) if self.torsion else [0.0]])
        sol = root(lambda x: self.run(x)[0], x0, method="hybr", options={"xtol": 1e-13})
        resid, pts = self.run(sol.x, s_out)
        assert np.max(np.abs(resid)) < 1e-9, resid
        return np.array([pts[round(s, 9)] for s in s_out])


CASES = [
    # robot, q, loads (gravity m/s^2, tip force N, tip moment N mm)
    ("seed1", [0.4, -1.2, 2.5, -60.0, -30.0, -10.0], dict(gravity=(0.0, -G, 0.0))),
    ("seed1", [0.0, 2.0, -0.7, -20.0, -20.0, -5.0],
     dict(gravity=(G * 0.6, 0.0, -G * 0.8), F=(0.05, -0.03, 0.01), M=(2.0, -1.0, 0.5))),
    ("two_tube_nylon", [1.0, -2.0, -40.0, -30.0], dict(F=(0.0, 0.2, -0.1), gravity=(0.0, 0.0, G))),
    ("two_tube_nylon", [0.2, 2.9, -10.0, -5.0], dict(gravity=(G, 0.0, 0.0), M=(0.0, 0.0, 5.0))),
    # an axial pull alone (a sensor lead tensioned along the axis) bends a curved robot
    ("seed1", [0.3, -2.0, 1.0, -40.0, -25.0, -8.0], dict(F=(0.0, 0.0, 0.1))),
]


@pytest.mark.parametrize("torsion", [True, False])
@pytest.mark.parametrize("case", range(len(CASES)))
def test_independent_integration(case, torsion):
    name, q, ld = CASES[case]
    robot = load_robot(name)
    q = np.array(q, float)
    loads = Loads(gravity=ld.get("gravity", (0, 0, 0)), tip_force=ld.get("F", (0, 0, 0)),
                  tip_moment=ld.get("M", (0, 0, 0)))
    m = PhysicsModel(robot, torsion=torsion, loads=loads)
    shp = m.shape(q[None], 15)
    assert shp.ok.all()
    ref = Reference(robot, q, torsion, loads.gravity, loads.tip_force, loads.tip_moment)
    want = ref.solve(shp.s[0])
    err = np.max(np.linalg.norm(shp.points[0] - want, axis=1))
    unloaded = PhysicsModel(robot, torsion=torsion).shape(q[None], 15).points[0]
    moved = np.max(np.linalg.norm(unloaded - want, axis=1))
    assert moved > 0.2          # the load matters
    assert err < 1e-3, (err, moved)


# ----------------------------------------------------------------------------- kernel properties
def _workspace(n):
    N = 3 * n + 14
    nx = n + 2
    return dict(y=np.zeros(N), T=np.zeros((N, nx)), k=np.zeros(n), w=np.zeros(n),
                n0=np.zeros(3), wsum=np.zeros(3), ws=np.zeros((5, N)), WS=np.zeros((5, N, nx)),
                K=np.zeros((3, 3)))


def _residual(robot, q, x, W, F, M, kink=None, torsion=True, sens=True):
    n = robot.n
    L = robot.lengths
    st = robot.array("straight_length")
    EI = robot.array("bending_stiffness")
    ratio = EI / robot.array("torsional_stiffness") if torsion else np.zeros(n)
    kink = np.zeros((n, 2)) if kink is None else kink
    tpos, ttyp, tidx = np.zeros(2 * n), np.zeros(2 * n, np.int64), np.zeros(2 * n, np.int64)
    _tube_events(q[n:], L, st, tpos, ttyp, tidx)
    resid, jac = np.zeros(n + 2), np.zeros((n + 2, n + 2))
    ws = _workspace(n)
    _loaded._integrate(q[:n].copy(), q[n:].copy(), x, L, st, robot.array("curvature"), EI, ratio,
                       kink, W, F, M, tpos, ttyp, tidx, np.zeros(1), 0, 10.0, sens,
                       np.zeros((0, 3)), resid, jac, ws["y"], ws["T"], ws["k"], ws["w"],
                       ws["n0"], ws["wsum"], ws["ws"], ws["WS"], ws["K"])
    return resid, jac


@pytest.mark.parametrize("torsion", [True, False])
@pytest.mark.parametrize("with_kink", [False, True])
def test_variational_jacobian_matches_finite_differences(torsion, with_kink):
    robot = load_robot("seed1")
    q = np.array([0.4, -1.2, 2.5, -60.0, -30.0, -10.0])
    W = np.array([[0.0, -3e-5, 1e-5]] * 3)
    F = np.array([0.05, -0.02, 0.01])
    M = np.array([1.0, 2.0, -0.5])
    kink = np.array([[0.0, 0.0], [0.01, -0.02], [0.03, 0.01]]) if with_kink else None
    x = np.array([3.0, -2.0, 1.0, 5.0, -4.0])
    _, jac = _residual(robot, q, x, W, F, M, kink, torsion)
    fd = np.zeros_like(jac)
    for c in range(len(x)):
        h = 1e-4
        xp, xm = x.copy(), x.copy()
        xp[c] += h
        xm[c] -= h
        fd[:, c] = (_residual(robot, q, xp, W, F, M, kink, torsion, False)[0]
                    - _residual(robot, q, xm, W, F, M, kink, torsion, False)[0]) / (2 * h)
    assert np.max(np.abs(jac)) > 1e-6
    np.testing.assert_allclose(jac, fd, rtol=1e-6, atol=1e-7 * np.max(np.abs(jac)))


@pytest.mark.parametrize("robot", ["seed1", "two_tube_nylon"])
@pytest.mark.parametrize("torsion", [True, False])
def test_zero_loads_are_the_unloaded_kernels_bit_for_bit(robot, torsion):
    r = load_robot(robot)
    q = r.sample(60, seed=4)
    ref = PhysicsModel(r, torsion=torsion).shape(q, 9)
    a = PhysicsModel(r, torsion=torsion, loads=Loads()).shape(q, 9)
    m = PhysicsModel(r, torsion=torsion)
    B, n = len(q), r.n
    p = m.base_params(B)
    zeros = MechanicsParams(p.kappa, p.EI, p.ratio, p.kink, weight=np.zeros((B, n, 3)),
                            force=np.zeros((B, 3)), moment=np.zeros((B, 3)))
    b = m.solve(q, 9, zeros)
    off = EffectModel(r, "compliant" if torsion else "rigid", {"load": {}}).shape(q, 9)
    for s in (a, b, off):
        assert np.array_equal(s.points, ref.points, equal_nan=True)
        assert np.array_equal(s.ok, ref.ok)


def test_mixed_batch_and_batch_order():
    """Per-row loads: unloaded rows are bit-identical to the unloaded kernel, loaded rows equal
    their own single solves, and a permuted batch gives the same rows."""
    r = load_robot("seed1")
    q = r.sample(24, seed=7)
    m = PhysicsModel(r)
    B, n = len(q), r.n
    rng = np.random.default_rng(0)
    p = m.base_params(B)
    on = np.arange(B) % 3 != 0
    force = rng.normal(0, 0.05, (B, 3)) * on[:, None]
    weight = np.zeros((B, n, 3))
    weight[:, :, 1] = -6e-5 * on[:, None]
    params = MechanicsParams(p.kappa, p.EI, p.ratio, p.kink, weight=weight, force=force)
    shp = m.solve(q, 11, params)
    assert shp.ok.all()
    ref = m.shape(q, 11)
    assert np.array_equal(shp.points[~on], ref.points[~on])
    assert np.all(np.linalg.norm(shp.tip[on] - ref.tip[on], axis=1) > 1e-3)
    perm = rng.permutation(B)
    pp = MechanicsParams(p.kappa[perm], p.EI[perm], p.ratio[perm], p.kink[perm],
                         weight=weight[perm], force=force[perm])
    again = m.solve(q[perm], 11, pp)
    assert np.array_equal(again.points, shp.points[perm])
    for i in np.flatnonzero(on)[:3]:
        one = m.solve(q[i:i + 1], 11, MechanicsParams(p.kappa[i:i + 1], p.EI[i:i + 1],
                                                      p.ratio[i:i + 1], p.kink[i:i + 1],
                                                      weight=weight[i:i + 1],
                                                      force=force[i:i + 1]))
        assert np.array_equal(one.points[0], shp.points[i])


def test_not_converged_is_not_ok():
    from ctrplan.shape.physics import PhysicsConfig

    r = load_robot("seed1")
    q = r.sample(5, seed=1)
    m = PhysicsModel(r, config=PhysicsConfig(max_iter=1), loads=Loads(tip_force=(1.0, -1.0, 0.0)))
    shp = m.shape(q, 5)
    assert not shp.ok.any()
    good = PhysicsModel(r, loads=Loads(tip_force=(1.0, -1.0, 0.0))).shape(q, 5)
    assert good.ok.all()


def test_large_load_converges_by_continuation():
    """A load that bends the robot by tens of mm: ok, and equal to the independent solver."""
    r = load_robot("two_tube_nylon")
    q = np.array([0.5, 2.0, -30.0, -20.0])
    loads = Loads(tip_force=(0.0, 1.5, 0.0), gravity=(0.0, 0.0, G))
    shp = PhysicsModel(r, loads=loads).shape(q[None], 9)
    assert shp.ok.all()
    unl = PhysicsModel(r).shape(q[None], 9)
    assert np.linalg.norm(shp.tip - unl.tip) > 20.0
    want = Reference(r, q, True, loads.gravity, loads.tip_force).solve(shp.s[0])
    assert np.max(np.linalg.norm(shp.points[0] - want, axis=1)) < 1e-3


# ----------------------------------------------------------------------------- load effect
@pytest.mark.parametrize("base", ["rigid", "compliant"])
def test_load_effect_is_the_loaded_physics_model(base):
    r = load_robot("seed1")
    q = r.sample(10, seed=2)
    eff = EffectModel(r, base, {"load": {"gx": 3.0, "gy": -9.0, "fz": 0.2, "fx": 0.01}})
    phys = PhysicsModel(r, torsion=base == "compliant",
                        loads=Loads(gravity=(3.0, -9.0, 0.0), tip_force=(0.01, 0.0, 0.2)))
    a = eff.shape(q, 7)
    b = phys.shape(q, 7)
    assert a.ok.all()
    assert np.array_equal(a.points, b.points)


def test_load_effect_params():
    r = load_robot("seed1")
    ps = {p.name: p for p in effect_params("load", r)}
    assert set(ps) == {"gx", "gy", "gz", "fx", "fy", "fz"}
    assert all(p.off == 0.0 and p.lo < 0 < p.hi for p in ps.values())
    # the axial tip force is fitted (it bends a curved robot), the axial weight is not
    assert [k for k, p in ps.items() if p.fit] == ["gx", "gy", "fx", "fy", "fz"]


def test_cli_simulate_with_load(tmp_path):
    from ctrplan.cli import main
    from ctrplan.measured import read_measured

    r = load_robot("seed1")
    cfg = tmp_path / "c.csv"
    q = r.sample(6, seed=3)
    from ctrplan.robot import write_configs

    write_configs(cfg, r, q)
    out = tmp_path / "m.csv"
    assert main(["-q", "simulate", "--robot", "seed1", "--configs", str(cfg), "--effect",
                 "load:gy=-9.81,fx=0.02", "--out", str(out)]) == 0
    d = read_measured(out, r)
    want = PhysicsModel(r, torsion=False, loads=Loads(gravity=(0, -9.81, 0),
                                                      tip_force=(0.02, 0, 0))).shape(q, 2).tip
    np.testing.assert_allclose(d.tip, want, atol=1e-9)


# ----------------------------------------------------------------------------- robot YAML
def test_density_yaml_round_trip_and_validation(tmp_path):
    data = load_robot("seed1").to_dict()
    assert all("density" not in t for t in data["tubes"])      # optional: not written if unset
    data["tubes"][1]["density"] = 1140
    r = robot_from_dict(data, "r.yaml")
    assert r.tubes[1].density == 1140.0 and r.tubes[0].density is None
    path = tmp_path / "r.yaml"
    r.save(path)
    back = load_robot(path)
    assert back.tubes[1].density == 1140.0 and back.tubes[0].density is None
    assert back == r
    for bad in (-1.0, 0.0, float("nan"), float("inf"), "heavy", True):
        d = load_robot("seed1").to_dict()
        d["tubes"][2]["density"] = bad
        with pytest.raises(InputError, match=r"tubes\[2\]\.density"):
            robot_from_dict(d, "bad.yaml")


def test_gravity_uses_density():
    """Weight scales with density: doubling every density doubles the small gravity sag."""
    base = load_robot("seed1").to_dict()
    heavy = load_robot("seed1").to_dict()
    for t in heavy["tubes"]:
        t["density"] = 2 * 6450.0
    q = np.array([[0.0, 0.0, 0.0, -40.0, -30.0, -20.0]])
    r0 = robot_from_dict(base)
    r2 = robot_from_dict(heavy)
    un = PhysicsModel(r0).shape(q, 5).tip
    d1 = PhysicsModel(r0, loads=Loads(gravity=(0, -G, 0))).shape(q, 5).tip - un
    d2 = PhysicsModel(r2, loads=Loads(gravity=(0, -G, 0))).shape(q, 5).tip - un
    assert np.linalg.norm(d1) > 0.1
    assert np.linalg.norm(d2 - 2 * d1) < 2e-2 * np.linalg.norm(2 * d1)


def test_continuation_when_newton_cannot_start():
    """A first guess Newton cannot use (NaN) falls back to ramping the load up from the unloaded
    solution: same answer as the normal solve."""
    r = load_robot("seed1")
    q = np.array([0.4, -1.2, 2.5, -60.0, -30.0, -10.0])
    loads = Loads(gravity=(0.0, -G, 0.0), tip_force=(0.2, 0.0, 0.0))
    m = PhysicsModel(r, loads=loads)
    ref = m.shape(q[None], 9)
    n = r.n
    p = m.base_params(1)
    unl = PhysicsModel(r)
    unl.shape(q[None], 2)
    tau = unl.last_info.uz0 * r.array("torsional_stiffness")
    x_start = np.concatenate([tau, np.zeros((1, 2))], axis=1)
    pts, _, x, it, res, ok = _loaded.solve_loaded_batch(
        q[None, :n].copy(), q[None, n:].copy(), r.lengths, r.array("straight_length"), p.kappa,
        p.EI, p.ratio, p.kink, p.weight, p.force, np.zeros((1, 3)), 9, 10.0, 1e-10, 30,
        np.full((1, n + 2), np.nan), x_start)
    assert ok[0] and it[0] >= 8                      # at least one Newton step per stage
    assert np.max(np.abs(pts[0] - ref.points[0])) < 1e-7


# ----------------------------------------------------------------------------- foreign generator
@pytest.mark.parametrize("robot", ["seed1", "two_tube_nylon"])
@pytest.mark.parametrize("torsion", [True, False])
def test_agrees_with_the_foreign_generator(robot, torsion):
    """tests/foreign (its own YAML parsing and loaded rod integration, no ctrplan import) with
    its plain load (horizontal gravity + tip force), a gravity-only and a force-only load."""
    foreign = pytest.importorskip("tests.foreign")
    # the generator's plain forms (its defaults add drive couplings, a filled lumen, a tether)
    plain_torsion = {"torsion": {"gj_scale": 1.0, "coupling": 0.0, "play": 0.0}}
    r = load_robot(robot)
    q = r.sample(12, seed=5)
    unloaded = PhysicsModel(r, torsion=torsion).shape(q, 15).points
    if torsion:
        # two_tube_nylon is bistable in places (a stable and an unstable equilibrium; the
        # generator follows a stable branch, the unloaded shooting may return the other): compare
        # where both find the same unloaded equilibrium (the loaded solve continues from it)
        same = np.max(np.linalg.norm(foreign.backbones(robot, q, plain_torsion, points=15)
                                     - unloaded, axis=2), axis=1) < 1e-3
        assert same.sum() >= 8
        q, unloaded = q[same], unloaded[same]
    tip_force = (0.0, -1e-5 * r.tubes[0].bending_stiffness, 0.0)     # the generator's default
    for eff, loads in (({"load": {"gravity": [9.81, 0, 0], "tip_force": "auto"}},
                        Loads(gravity=(9.81, 0, 0), tip_force=tip_force)),
                       ({"load": {"gravity": [0, -9.81, 3.0]}}, Loads(gravity=(0, -9.81, 3.0))),
                       ({"load": {"tip_force": [0.05, 0.0, -0.1]}},
                        Loads(tip_force=(0.05, 0.0, -0.1)))):
        if torsion:
            eff = {**eff, **plain_torsion}
        theirs = foreign.backbones(robot, q, eff, points=15)
        ours = PhysicsModel(r, torsion=torsion, loads=loads).shape(q, 15)
        assert ours.ok.all() and np.isfinite(theirs).all()
        assert np.max(np.linalg.norm(theirs - unloaded, axis=2)) > 0.3
        assert np.max(np.linalg.norm(theirs - ours.points, axis=2)) < 1e-3


def test_hard_configurations_converge_and_satisfy_the_equations():
    """Compliant two_tube_nylon under a large tip moment: every configuration converges (those
    near snapping by continuation), and the hardest ones satisfy the independent rod equations
    (the scipy solver started on the kernel's branch lands on the same backbone)."""
    r = load_robot("two_tube_nylon")
    q = r.sample(600, seed=2)
    loads = Loads(tip_moment=(20.0, 0.0, 10.0))
    m = PhysicsModel(r, loads=loads)
    shp = m.shape(q, 9)
    info = m.last_info
    assert shp.ok.all()
    hard = np.argsort(info.iterations)[-2:]
    assert info.iterations[hard].min() > 10               # they needed the fallbacks
    for i in hard:
        ref = Reference(r, q[i], True, M=loads.tip_moment)
        want = ref.solve(shp.s[i], uz0=info.uz0[i], m0=info.moment0[i])
        assert np.max(np.linalg.norm(shp.points[i] - want, axis=1)) < 1e-3


@pytest.mark.parametrize("torsion", [True, False])
def test_kinks_with_loads_match_the_independent_integration(torsion):
    """The clearance effect's kinks (frame rotations where outer tubes end) under loads: the
    total moment is continuous across a kink."""
    r = load_robot("seed1")
    q = np.array([0.4, -1.2, 2.5, -60.0, -30.0, -10.0])
    kink = np.array([[0.0, 0.0], [0.02, -0.03], [-0.01, 0.04]])
    loads = Loads(gravity=(0.0, -G, 0.0), tip_force=(0.1, 0.05, 0.0), tip_moment=(1.0, 0.0, 0.5))
    m = PhysicsModel(r, torsion=torsion, loads=loads)
    p = replace(m.base_params(1), kink=kink[None])
    shp = m.solve(q[None], 15, p)
    assert shp.ok.all()
    want = Reference(r, q, torsion, loads.gravity, loads.tip_force, loads.tip_moment,
                     kink=kink).solve(shp.s[0])
    no_kink = m.shape(q[None], 15).points[0]
    assert np.max(np.linalg.norm(no_kink - want, axis=1)) > 1.0
    assert np.max(np.linalg.norm(shp.points[0] - want, axis=1)) < 1e-3


def test_load_effect_model_file_round_trip(tmp_path):
    r = load_robot("two_tube_nylon")
    q = r.sample(5, seed=1)
    m = EffectModel(r, "rigid", {"load": {"gx": 9.0, "fy": -0.2}})
    m.save(tmp_path / "cal.yaml")
    back = EffectModel.load(tmp_path / "cal.yaml")
    assert back.effects == m.effects
    assert np.array_equal(back.shape(q, 5).points, m.shape(q, 5).points)
