"""The foreign generator (tests/foreign) against oracles that share no code with it: closed-form
arcs, hand-composed rotations, scipy's adaptive integrators (solve_ivp + root, solve_bvp),
Euler-Bernoulli cantilever formulas; plus its contracts (effects off, determinism, CSV format,
valid designs, no ctrplan import)."""

from __future__ import annotations

import ast
import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.integrate import solve_bvp, solve_ivp
from scipy.optimize import root
from scipy.spatial.transform import Rotation

from tests.foreign import (
    DESIGNS,
    FRICTION_FORMS,
    OUTSIDE_EFFECTS,
    VOCAB_EFFECTS,
    backbones,
    generate,
    generate_study,
    load_spec,
    read_csv,
    valid,
)
from tests.foreign import mechanics as M
from tests.foreign.core import truth

ROBOTS = ("seed1", "two_tube_nylon")


def tube(straight, curved, kappa, od=1.3, id=1.0, E=60000.0, nu=0.33, density=6450.0):
    return {"od": od, "id": id, "straight_length": straight, "curved_length": curved,
            "curvature": kappa, "youngs_modulus": E, "poisson_ratio": nu, "density": density}


def one_tube(straight=100.0, curved=50.0, kappa=0.01, **kw):
    return load_spec({"name": "one", "tubes": [tube(straight, curved, kappa, **kw)]})


# ----------------------------------------------------------------------------- closed forms
def test_single_tube_straight_and_arc_closed_form():
    sp = one_tube()
    alpha, beta = 0.3, -20.0
    # exposed: straight 80 mm along z, then a 50 mm arc of curvature 0.01 toward Rz(alpha) e_x
    k, Lc, Ls = 0.01, 50.0, 80.0
    d = np.array([math.cos(alpha), math.sin(alpha), 0.0])
    tip = np.array([0, 0, Ls + math.sin(k * Lc) / k]) + (1 - math.cos(k * Lc)) / k * d
    q = np.array([[alpha, beta]])
    r = M.rigid(sp, q[:, :1], q[:, 1:])
    np.testing.assert_allclose(r.tip()[0], tip, atol=1e-9)
    c = M.cosserat(sp, q[:, :1], q[:, 1:], torsion=True)
    assert c.ok.all()
    np.testing.assert_allclose(c.tip()[0], tip, atol=2e-4)      # RK4 at h_max 10 mm
    # points: on the straight part exactly on the axis, on the arc at the arc's closed form
    pts = r.points(14)
    s = np.linspace(0, Ls + Lc, 14)
    for si, pi in zip(s, pts[0]):
        if si <= Ls:
            exp = np.array([0, 0, si])
        else:
            a = si - Ls
            exp = np.array([0, 0, Ls + math.sin(k * a) / k]) + (1 - math.cos(k * a)) / k * d
        np.testing.assert_allclose(pi, exp, atol=1e-9)
    np.testing.assert_allclose(c.points(14)[0], pts[0], atol=2e-4)
    # straight tube (curvature 0): tip on the axis at its exposed length
    st = one_tube(kappa=0.0)
    np.testing.assert_allclose(M.rigid(st, q[:, :1], q[:, 1:]).tip()[0], [0, 0, 130.0], atol=1e-12)


def _arc_step(Rw, p, u_body, h):
    """Hand composition with scipy Rotation: constant body curvature u over length h."""
    u = np.asarray(u_body, float)
    k = np.linalg.norm(u)
    if k == 0:
        return Rw, p + Rw @ np.array([0, 0, h])
    b = np.cross(u / k, [0, 0, 1.0])           # in-plane direction the tangent turns to
    dp = math.sin(k * h) / k * np.array([0, 0, 1.0]) + (1 - math.cos(k * h)) / k * b
    return Rw @ Rotation.from_rotvec(u * h).as_matrix(), p + Rw @ dp


def test_rigid_two_tube_closed_form():
    # inner: straight 100, curved 80 (k1); outer: straight 60, curved 70 (k2); stiffer outer
    t1 = tube(100.0, 80.0, 0.012, od=1.3, id=1.0)
    t2 = tube(60.0, 70.0, 0.008, od=1.9, id=1.5)
    sp = load_spec({"name": "two", "tubes": [t1, t2]})
    EI1 = 60000 * math.pi / 64 * (1.3 ** 4 - 1.0 ** 4)
    EI2 = 60000 * math.pi / 64 * (1.9 ** 4 - 1.5 ** 4)
    a1, a2, b1, b2 = 0.7, -1.1, -30.0, -10.0
    # break points: outer curved from 50 to 120 (its end); inner curved from 70 to 150
    def ub(a, k):
        return np.array([-k * math.sin(a), k * math.cos(a), 0.0])   # Rz(a) (0, k, 0)
    secs = [(50.0, np.zeros(3)),
            (20.0, EI2 * ub(a2, 0.008) / (EI1 + EI2)),
            (50.0, (EI1 * ub(a1, 0.012) + EI2 * ub(a2, 0.008)) / (EI1 + EI2)),
            (30.0, ub(a1, 0.012))]
    Rw, p = np.eye(3), np.zeros(3)
    for h, u in secs:
        Rw, p = _arc_step(Rw, p, u, h)
    q = np.array([[a1, a2, b1, b2]])
    r = M.rigid(sp, q[:, :2], q[:, 2:])
    np.testing.assert_allclose(r.tip()[0], p, atol=1e-9)
    c = M.cosserat(sp, q[:, :2], q[:, 2:], torsion=False)
    np.testing.assert_allclose(c.tip()[0], p, atol=2e-4)


# ----------------------------------------------------------------------------- scipy oracle
def _scipy_cosserat(spec, alpha, beta, gravity=None, F=None, torsion=True, mu=0.0, rel=None,
                    clear=None, contact=0.0, ramp=None, ei_curved=None, coupling=None, twist=None,
                    kink=None):
    """Independent shooting: scipy DOP853 (rtol 1e-11) per section + scipy.optimize.root.
    Optional point events where outer tube o ends: friction torque
    T = mu rel (|M_o| + contact M_c e_o / L_o), M_c = EI_o EI_i |kappa_o - kappa_i| / (EI_o + EI_i)
    (+T on the outer tube's end condition,
    -T on the inner tube: a jump of its u_z) and a clearance event: clear(phi) -> tilt, or
    (tilt, lean, jump_b, jump_a): the frame turns by the rotation vector
    tilt R Rz(psi_in) e_y + lean R Rz(psi_in) e_x (scipy Rotation) and the backbone jumps by
    R Rz(psi_in) (jump_b, jump_a, 0). ramp: precurvature kappa (1 + ramp (s_c - 1/2)) at the
    middle of each of 8 sub-sections of the curved section; ei_curved: EI factor on the curved
    section; coupling: extra transmission length (mm) of each tube's torsion; twist: the
    precurvature vector in each tube's frame turned by twist (s_c - 1/2) about the tangent
    (same 8 sub-sections), kappa (-sin th, cos th, 0) written out in the bending moment and in
    the twist equation's u_i x kappa_i; kink (angles, at, length): angle_i / length more
    precurvature over ``length`` mm centred at the fraction ``at`` of each curved section."""
    n = spec.n
    L = spec.straight + spec.curved
    e = np.maximum(beta + L, 0.0)
    cs = np.minimum(np.maximum(beta + spec.straight, 0.0), e)
    subs = []
    if ramp is not None or twist is not None:
        for i in range(n):
            subs += [min(max(beta[i] + spec.straight[i] + spec.curved[i] * k / 8, 0.0), e[i])
                     for k in range(1, 8)]
    if kink is not None:
        k_ang = np.asarray(kink[0], float)
        kc = beta + spec.straight + kink[1] * spec.curved
        k_lo, k_hi = kc - 0.5 * kink[2], kc + 0.5 * kink[2]
        subs += [min(max(v, 0.0), e[i]) for i in range(n) for v in (k_lo[i], k_hi[i])]
    bps = np.unique(np.r_[0.0, cs, e, subs])
    ramp = np.zeros(n) if ramp is None else np.asarray(ramp, float)
    twist = np.zeros(n) if twist is None else np.asarray(twist, float)
    eic = np.ones(n) if ei_curved is None else np.asarray(ei_curved, float)
    cpl = np.zeros(n) if coupling is None else np.asarray(coupling, float)
    EI, GJ, kap = spec.EI, spec.GJ, spec.kappa
    w = np.zeros((n, 3)) if gravity is None else spec.weight_per_mm[:, None] * np.asarray(gravity) / 9.81
    Fv = np.zeros(3) if F is None else np.asarray(F, float)
    loaded = gravity is not None or F is not None

    def rhs(s, y, k_i, pres, EIs, th):
        R, m = y[3:12].reshape(3, 3), y[12:15]
        psi, uz = y[15:15 + n], y[15 + n:15 + 2 * n]
        EIp = EIs * pres
        kx, ky = -k_i * np.sin(th), k_i * np.cos(th)           # precurvature, tube frame
        c, sn = np.cos(psi), np.sin(psi)
        S = np.array([np.sum(EIp * (c * kx - sn * ky)), np.sum(EIp * (sn * kx + c * ky))])
        mb = R.T @ m
        uxy = (mb[:2] + S) / EIp.sum()
        u = np.array([uxy[0], uxy[1], 0.0])
        nvec = Fv + ((np.maximum(e - s, 0) * pres) @ w)
        t = R[:, 2]
        dR = R @ np.array([[0, -u[2], u[1]], [u[2], 0, -u[0]], [-u[1], u[0], 0]])
        dpsi = uz * pres if torsion else np.zeros(n)
        ui_x = c * uxy[0] + sn * uxy[1]
        ui_y = -sn * uxy[0] + c * uxy[1]
        duz = (EIp / GJ) * (ui_x * ky - ui_y * kx) if torsion else np.zeros(n)
        return np.r_[t, dR.ravel(), -np.cross(t, nvec), dpsi, duz]

    def run(x, T_out=None):
        uz0 = x[:n] if torsion else np.zeros(n)
        m0 = np.zeros(3)
        if loaded:
            if torsion:
                m0 = np.r_[x[n:n + 2], np.sum(GJ * uz0)]
            else:
                m0 = np.asarray(x[:3])
        y = np.r_[np.zeros(3), np.eye(3).ravel(), m0, alpha - (beta - cpl) * uz0, uz0]
        for a, b in zip(bps[:-1], bps[1:]):
            mid = 0.5 * (a + b)
            pres = (mid < e).astype(float)
            curved = (mid >= cs) & (mid < e)
            sc = (mid - beta - spec.straight) / spec.curved
            mid8 = (np.floor(np.clip(sc, 0, 1 - 1e-12) * 8) + 0.5) / 8 - 0.5
            k_i = np.where(curved, kap * (1.0 + ramp * mid8), 0.0)
            if kink is not None:
                k_i = k_i + np.where(curved & (mid >= k_lo) & (mid < k_hi), k_ang / kink[2], 0.0)
            th = np.where(curved, twist * mid8, 0.0)
            EIs = EI * np.where(curved, eic, 1.0)
            sol = solve_ivp(rhs, (a, b), y, method="DOP853", rtol=1e-11, atol=1e-11,
                            args=(k_i, pres, EIs, th))
            y = sol.y[:, -1].copy()
            for o in range(1, n):
                if e[o] != b:
                    continue
                R, m = y[3:12].reshape(3, 3), y[12:15]
                psi = y[15:15 + n]
                EIp = EIs * pres
                S = np.array([np.sum(-EIp * k_i * np.sin(psi)), np.sum(EIp * k_i * np.cos(psi))])
                uxy = ((R.T @ m)[:2] + S) / EIp.sum()
                if mu:
                    uo = Rotation.from_euler("z", -psi[o]).as_matrix()[:2, :2] @ uxy
                    Mc = EI[o] * EI[o - 1] / (EI[o] + EI[o - 1]) * abs(kap[o] - kap[o - 1])
                    T = mu * rel[o - 1] * (EIs[o] * np.hypot(uo[0], uo[1] - k_i[o])
                                           + contact * Mc * e[o] / L[o])
                    if T_out is not None:
                        T_out[o] = T
                    y[15 + n + o - 1] += T / GJ[o - 1]
                if clear is not None:
                    ev = clear(psi[o - 1] - psi[o])
                    tilt, lean, jb, ja = ev if isinstance(ev, tuple) else (ev, 0.0, 0.0, 0.0)
                    Rz = Rotation.from_euler("z", psi[o - 1]).as_matrix()
                    Q = Rotation.from_rotvec(Rz @ np.array([lean, tilt, 0.0])).as_matrix()
                    y[0:3] = y[0:3] + R @ Rz @ np.array([jb, ja, 0.0])
                    y[3:12] = (R @ Q).ravel()
        return y

    def res(x):
        T = np.zeros(n)
        y = run(x, T)
        out = []
        if torsion:
            out.append(y[15 + n:15 + 2 * n] * GJ - T)
        if loaded:
            R, m = y[3:12].reshape(3, 3), y[12:15]
            out.append((R.T @ m)[:2] if torsion else m)
        return np.concatenate(out)

    k = (n if torsion else 0) + ((2 if torsion else 3) if loaded else 0)
    if k == 0:
        return run(np.zeros(0))[:3]
    sol = root(res, np.zeros(k), method="hybr", tol=1e-13)
    assert np.max(np.abs(res(sol.x))) < 1e-8
    return run(sol.x)[:3]


@pytest.mark.parametrize("robot", ROBOTS)
def test_compliant_and_loaded_vs_scipy(robot):
    sp = load_spec(robot)
    n = sp.n
    rng = np.random.default_rng(3)
    from tests.foreign.robot import beta_from_unit
    qs = np.c_[rng.uniform(-1.2, 1.2, (3, n)), beta_from_unit(sp, rng.uniform(0.2, 0.9, (3, n)))]
    cases = [dict(), dict(gravity=np.array([0.0, -9.81, 0.0]), F=np.array([0.02, 0.0, 0.0])),
             dict(gravity=np.array([9.81, 0.0, 0.0]), torsion=False)]
    for i, case in enumerate(cases):      # one configuration per case (scipy is slow)
        torsion = case.get("torsion", True)
        bb = M.cosserat(sp, qs[:, :n], qs[:, n:], torsion=torsion, gravity=case.get("gravity"),
                        tip_force=case.get("F"))
        assert bb.ok.all()
        got = bb.tip()
        ref = _scipy_cosserat(sp, qs[i, :n], qs[i, n:], case.get("gravity"), case.get("F"), torsion)
        # measured: <= 1.1e-5 mm at h_max 6, ~1e-4 at the default h_max 10
        assert np.linalg.norm(got[i] - ref) < 1e-3, (case, i, got[i], ref)
        if case.get("gravity") is not None:      # the load matters at this tolerance
            assert np.linalg.norm(got[i] - M.cosserat(sp, qs[i:i + 1, :n], qs[i:i + 1, n:],
                                                      torsion=torsion).tip()[0]) > 0.05


# ----------------------------------------------------------------------------- loads
def _straight_cantilever(L=150.0):
    # one straight tube, fully inserted: a cantilever of length L clamped at the plane
    sp = one_tube(straight=L, curved=1e-9, kappa=0.0)
    return sp, np.zeros((1, 1)), np.zeros((1, 1))


def test_tip_force_matches_euler_bernoulli():
    sp, a, b = _straight_cantilever()
    L, EI = 150.0, float(sp.EI[0])
    F = 1e-4 * 3 * EI / L ** 2        # tip deflection 1e-4 * L: linear regime
    for torsion in (True, False):
        bb = M.cosserat(sp, a, b, torsion=torsion, tip_force=[0.0, -F, 0.0])
        tip = bb.tip()[0]
        expect = F * L ** 3 / (3 * EI)
        assert abs(-tip[1] - expect) / expect < 1e-3
        assert abs(tip[0]) < 1e-9
    # deflection along the whole shaft: v(s) = F s^2 (3L - s) / (6 EI)
    pts = M.cosserat(sp, a, b, tip_force=[0.0, -F, 0.0]).points(11)[0]
    s = pts[:, 2]
    np.testing.assert_allclose(-pts[:, 1], F * s ** 2 * (3 * L - s) / (6 * EI), rtol=2e-3, atol=1e-9)


def test_gravity_matches_euler_bernoulli():
    sp, a, b = _straight_cantilever()
    L, EI, w = 150.0, float(sp.EI[0]), float(sp.weight_per_mm[0])
    bb = M.cosserat(sp, a, b, torsion=True, gravity=[0.0, 0.0, 0.0])
    np.testing.assert_allclose(bb.tip()[0], [0, 0, L], atol=1e-9)
    bb = M.cosserat(sp, a, b, torsion=True, gravity=[9.81, 0.0, 0.0])
    expect = w * L ** 4 / (8 * EI)
    assert 0.05 < expect < 1.0                      # a small, well-resolved deflection
    tip = bb.tip()[0]
    assert abs(tip[0] - expect) / expect < 2e-3
    # weight per length from density: rho * A * g (nitinol 6450 kg/m^3)
    A = math.pi / 4 * (1.3 ** 2 - 1.0 ** 2)
    assert abs(w - 6450e-9 * A * 9.81) < 1e-15


def _elastica_tip(FL2_EI, L=1.0):
    """Planar elastica, tip force perpendicular to the clamp axis: theta'' = -(F/EI) cos(theta),
    theta(0) = 0, theta'(L) = 0; tip = integral of (sin theta, cos theta)."""
    lam = FL2_EI / L ** 2

    def f(s, y):
        return np.vstack([y[1], -lam * np.cos(y[0]), np.sin(y[0]), np.cos(y[0])])

    def bc(ya, yb):
        return np.array([ya[0], yb[1], ya[2], ya[3]])
    s = np.linspace(0, L, 200)
    y0 = np.zeros((4, s.size))
    y0[3] = s
    sol = solve_bvp(f, bc, s, y0, tol=1e-10, max_nodes=100000)
    assert sol.success
    return sol.y[2, -1], sol.y[3, -1]


def test_large_tip_force_matches_elastica():
    sp, a, b = _straight_cantilever()
    L, EI = 150.0, float(sp.EI[0])
    for load in (1.0, 3.0):
        F = load * EI / L ** 2
        tip = M.cosserat(sp, a, b, torsion=True, tip_force=[0.0, -F, 0.0], h_max=2.0).tip()[0]
        dx, dz = _elastica_tip(load, 1.0)
        np.testing.assert_allclose([-tip[1] / L, tip[2] / L], [dx, dz], atol=2e-4)
        # sanity: far below the linear prediction at large load, arc length preserved
        assert -tip[1] < F * L ** 3 / (3 * EI)
    pts = M.cosserat(sp, a, b, tip_force=[0.0, -3 * EI / L ** 2, 0.0], h_max=2.0).points(400)[0]
    assert abs(np.sum(np.linalg.norm(np.diff(pts, axis=0), axis=1)) - L) < 1e-2


# ----------------------------------------------------------------------------- effects
ALL = VOCAB_EFFECTS + OUTSIDE_EFFECTS


def test_effects_off_reproduce_the_base_exactly():
    off = {
        "clearance": {"amplitude": 0.0, "lean": 0.0, "jump": 0.0}, "friction": {"mu": 0.0},
        "precurvature": {"scale": [1.0, 1.0, 1.0], "ramp": [0.0] * 3, "twist": 0.0, "relax": 0.0},
        "stiffness": {"scale": [1.0, 1.0, 1.0], "curved": [1.0] * 3, "torsion": [1.0] * 3,
                      "soften": 0.0},
        "load": {"gravity": None, "tip_force": None},
        "joint_offset": {"alpha": [0.0] * 3, "beta": [0.0] * 3, "periodic": [0.0] * 3,
                         "beta_scale": [0.0] * 3, "gear": 0.0, "rehome": 0.0},
        "registration": {"rotvec": [0.0] * 3, "translation": [0.0] * 3, "scale": 0.0,
                         "mount": 0.0, "sensor": 0.0},
        "distortion": {"amplitude": 0.0},
        "drift": {"amplitude": 0.0, "step": 0.0, "wobble": 0.0, "wander": 0.0},
    }
    for robot_effects in ({}, {"torsion": {}}):
        base = generate("seed1", "sweeps", n=120, effects=robot_effects, noise_mm=0.1, seed=5, points=5)
        for name, params in off.items():
            d = generate("seed1", "sweeps", n=120, effects={**robot_effects, name: params},
                         noise_mm=0.1, seed=5, points=5)
            assert np.array_equal(d.tip, base.tip), name
            assert np.array_equal(d.points, base.points), name
        d = generate("seed1", "sweeps", n=120, effects={**robot_effects, "distortion":
                                                          {"form": "dipole", "amplitude": 0.0}},
                     noise_mm=0.1, seed=5, points=5)
        assert np.array_equal(d.tip, base.tip)
        for form, params in (("coulomb_lag", {"lag": 0.0}), ("presliding", {"lag": 0.0}),
                             ("stick_slip", {"lag": 0.0})):
            d = generate("seed1", "sweeps", n=120, effects={**robot_effects, "friction": {"form": form, **params}},
                         noise_mm=0.1, seed=5)
            assert np.array_equal(d.tip, base.tip), form


@pytest.mark.parametrize("robot", ROBOTS)
def test_every_effect_at_default_moves_the_tip(robot):
    base = generate(robot, "sweeps", n=300, effects={}, noise_mm=0.0, seed=2)
    for name in ALL:
        d = generate(robot, "sweeps", n=300, effects={name: {}}, noise_mm=0.0, seed=2)
        mean = np.linalg.norm(d.tip_clean - base.tip_clean, axis=1).mean()
        # torsion is physical (GJ from E, nu): ~1 mm on seed1, ~11-13 mm on the nylon pair;
        # end-moment friction with its contact-length term is large on the nylon pair
        lo, hi = (0.3, 20.0) if name == "torsion" else (0.5, 8.0)
        if name == "friction" and robot == "two_tube_nylon":
            hi = 20.0
        if name == "stiffness":      # a 50 % stiffer middle and 30 % softer outer tube
            hi = 12.0
        assert lo < mean < hi, (name, mean)


def test_clearance_peaks_at_its_phase():
    sp = load_spec("two_tube_nylon")
    phi = np.deg2rad(np.arange(0, 360, 5.0))
    q = np.c_[phi, np.zeros_like(phi), np.full_like(phi, -60.0), np.full_like(phi, -0.0)]
    assert valid(sp, q).all()
    for phase in (205.0, 90.0):
        base, _, _ = truth(sp, q, {})
        cl, _, _ = truth(sp, q, {"clearance": {"amplitude": 0.05, "phase_deg": phase,
                                               "harmonics": [0.5, 0.5], "lean": 0.0, "jump": 0.0}})
        dev = np.linalg.norm(cl - base, axis=1)
        peak = np.rad2deg(phi[np.argmax(dev)])
        assert abs((peak - phase + 180) % 360 - 180) <= 5.0
        assert dev.min() < 1e-6                  # zero opposite the peak


@pytest.mark.parametrize("form", FRICTION_FORMS)
def test_friction_depends_on_direction_and_backbones_reproduce_rows(form):
    eff = {"friction": {"form": form}}
    d = generate("seed1", "sweeps", n=150, effects=eff, noise_mm=0.0, seed=4, points=6)
    sp = load_spec("seed1")
    q = d.q[10:40]
    dplus = np.zeros_like(d.direction[10:40])
    dplus[:, 0] = 1                      # inner tube last rotated +, the others not moved
    plus, _, _ = truth(sp, q, {"friction": d.effects["friction"]}, direction=dplus)
    minus, _, _ = truth(sp, q, {"friction": d.effects["friction"]}, direction=-dplus)
    assert np.linalg.norm(plus - minus, axis=1).mean() > 0.5
    if form not in ("presliding", "stick_slip"):   # history-free: a function of (q, direction)
        bb = backbones("seed1", d.q, eff, points=6, direction=d.direction)
        np.testing.assert_allclose(bb, d.points, atol=1e-9)


def test_compliant_end_moment_friction_and_study():
    st = generate_study(seed=0, noise_mm=0.1, n_per_experiment=90)
    sp = load_spec("two_tube_nylon")
    assert set(st) == {"feed", "inner_rotation", "outer_rotation"}
    for name, d in st.items():
        assert d.robot == "two_tube_nylon" and set(d.effects) == {"torsion", "clearance", "friction"}
        assert d.effects["clearance"]["phase_deg"] == 205.0
        assert d.effects["friction"]["form"] == "end_moment"
        rigid, _, _ = truth(sp, d.q, {})
        err = np.linalg.norm(d.tip - rigid, axis=1)
        assert 2.0 < err.mean() < 12.0 and err.max() < 40.0, (name, err.mean(), err.max())
    # friction through the compliant boundary condition: opposite directions differ
    d = st["inner_rotation"]
    eff = d.effects
    p, _, ok1 = truth(sp, d.q, eff, direction=np.tile([1, 0, 0, 0], (len(d), 1)))
    m, _, ok2 = truth(sp, d.q, eff, direction=np.tile([-1, 0, 0, 0], (len(d), 1)))
    assert ok1.all() and ok2.all()
    assert np.linalg.norm(p - m, axis=1).mean() > 0.5


# ----------------------------------------------------------------------------- contracts
def test_determinism_by_seed():
    eff = {"clearance": {}, "friction": {"form": "presliding"}, "drift": {}}
    a = generate("seed1", "sweeps", n=80, effects=eff, noise_mm=0.2, seed=11, points=4)
    b = generate("seed1", "sweeps", n=80, effects=eff, noise_mm=0.2, seed=11, points=4)
    c = generate("seed1", "sweeps", n=80, effects=eff, noise_mm=0.2, seed=12, points=4)
    for f in ("q", "tip", "time", "points", "direction"):
        assert np.array_equal(getattr(a, f), getattr(b, f))
    assert np.array_equal(a.sweep, b.sweep)
    assert not np.allclose(a.tip, c.tip)


def test_noise_level():
    d = generate("seed1", "uniform", n=400, effects={}, noise_mm=0.3, seed=1)
    r = d.tip - d.tip_clean
    assert abs(r.std() - 0.3) < 0.03 and abs(r.mean()) < 0.03


def test_csv_round_trip_in_the_design_format(tmp_path):
    d = generate("two_tube_nylon", "sweeps", n=60, effects={"clearance": {}}, noise_mm=0.1, seed=1, points=3)
    path = tmp_path / "measured.csv"
    d.write_csv(path)
    header = path.read_text().splitlines()[0].split(",")
    assert header == ["alpha1", "alpha2", "beta1", "beta2", "tip_x", "tip_y", "tip_z", "time", "sweep",
                      "p1_x", "p1_y", "p1_z", "p2_x", "p2_y", "p2_z", "p3_x", "p3_y", "p3_z"]
    cols = read_csv(path)
    np.testing.assert_array_equal(np.c_[cols["alpha1"], cols["alpha2"], cols["beta1"], cols["beta2"]], d.q)
    np.testing.assert_array_equal(np.c_[cols["tip_x"], cols["tip_y"], cols["tip_z"]], d.tip)
    np.testing.assert_array_equal(cols["time"], d.time)
    assert list(cols["sweep"]) == list(d.sweep)
    np.testing.assert_array_equal(cols["p2_y"], d.points[:, 1, 1])
    # and ctrplan's own reader accepts it (the DESIGN.md measured format)
    from ctrplan.measured import read_measured
    from ctrplan.robot import load_robot
    m = read_measured(path, load_robot("two_tube_nylon"))
    np.testing.assert_array_equal(m.q, d.q)
    np.testing.assert_array_equal(m.tip, d.tip)
    np.testing.assert_array_equal(m.time, d.time)
    assert list(m.sweep) == list(d.sweep)
    np.testing.assert_array_equal(m.points, d.points)


@pytest.mark.parametrize("robot", ROBOTS)
def test_designs_obey_constraints(robot):
    sp = load_spec(robot)
    n = sp.n
    for design in DESIGNS:
        d = generate(robot, design, n=300, effects={}, noise_mm=0.0, seed=2)
        assert len(d) == 300 and valid(sp, d.q).all(), design
        b = d.q[:, n:]
        assert np.all(b + sp.straight >= -1e-9) and np.all(b[:, -1] + sp.L[-1] >= 0)
        for sw in np.unique(d.sweep):
            t = d.time[d.sweep == sw]
            assert np.all(np.diff(t) > 0)
        if design == "uniform":
            assert len(np.unique(d.sweep)) == 300 and not d.direction.any()
            continue
        sweeps = np.unique(d.sweep)
        assert len(sweeps) >= 2
        for sw in sweeps:
            qs = d.q[d.sweep == sw]
            dq = np.diff(qs, axis=0)
            moving = np.flatnonzero(np.ptp(qs, axis=0) > 1e-9)
            if design == "sweeps":
                # back and forth in every joint: each changes sign of motion at least once
                for j in range(2 * n):
                    s = np.sign(dq[:, j][np.abs(dq[:, j]) > 1e-12])
                    assert np.any(s[1:] != s[:-1]), (sw, j)
            elif design == "feed":
                assert moving.tolist() == [n]
            elif design == "inner_rotation":
                assert moving.tolist() == [0] and np.ptp(qs[:, 0]) > 6.0
            elif design == "outer_rotation":
                assert moving.tolist() == [n - 1] and np.ptp(qs[:, n - 1]) > 6.0
            if design != "sweeps":
                s = np.sign(dq[:, moving[0]])
                assert np.any(s[1:] != s[:-1])     # back and forth


def test_direction_is_the_sign_of_the_last_motion():
    d = generate("seed1", "sweeps", n=100, effects={}, noise_mm=0.0, seed=9)
    for i in range(1, len(d)):
        if d.sweep[i] != d.sweep[i - 1]:
            assert not d.direction[i].any()
            continue
        dq = d.q[i] - d.q[i - 1]
        mv = np.abs(dq) > 1e-12
        assert np.array_equal(d.direction[i][mv], np.sign(dq[mv]).astype(np.int8))
        assert np.array_equal(d.direction[i][~mv], d.direction[i - 1][~mv])


def test_package_imports_nothing_from_ctrplan():
    root = Path(__file__).parent / "foreign"
    for f in root.glob("*.py"):
        tree = ast.parse(f.read_text())
        for node in ast.walk(tree):
            if isinstance(node, ast.Import):
                assert not any(a.name.split(".")[0] == "ctrplan" for a in node.names), f
            if isinstance(node, ast.ImportFrom):
                assert (node.module or "").split(".")[0] != "ctrplan", f
    code = ("import sys; from tests.foreign import generate; "
            "generate('seed1', 'sweeps', n=20, effects={'torsion': {}, 'load': {}}); "
            "assert not any(m == 'ctrplan' or m.startswith('ctrplan.') for m in sys.modules), 'ctrplan imported'")
    subprocess.run([sys.executable, "-c", code], check=True, cwd=Path(__file__).parents[1])


def _kabsch_residual(a, b):
    """Mean residual after the best rigid transform mapping a onto b."""
    ca, cb = a.mean(0), b.mean(0)
    H = (a - ca).T @ (b - cb)
    U, _, Vt = np.linalg.svd(H)
    dd = np.sign(np.linalg.det(Vt.T @ U.T))
    R = Vt.T @ np.diag([1, 1, dd]) @ U.T
    return np.linalg.norm((a - ca) @ R.T + cb - b, axis=1).mean()


def test_outside_effects_are_not_rigid_transforms():
    base = generate("seed1", "sweeps", n=400, effects={}, noise_mm=0.0, seed=3)
    plain = {"scale": 0.0, "mount": 0.0, "sensor": 0.0}
    rigid = generate("seed1", "sweeps", n=400, effects={"registration": plain},
                     noise_mm=0.0, seed=3)
    assert _kabsch_residual(base.tip_clean, rigid.tip_clean) < 1e-9    # scale 0: rigid
    reg = generate("seed1", "sweeps", n=400, effects={"registration": {"mount": 0.0, "sensor": 0.0}},
                   noise_mm=0.0, seed=3)
    assert _kabsch_residual(base.tip_clean, reg.tip_clean) > 0.2       # the scale error
    for name in OUTSIDE_EFFECTS:
        d = generate("seed1", "sweeps", n=400, effects={name: {}}, noise_mm=0.0, seed=3)
        assert _kabsch_residual(base.tip_clean, d.tip_clean) > 0.3, name
    # drift: exponential settling, a fast cycle and a step, closed form in the fraction of
    # recording time (its wander: tests/test_foreign_new_forms.py)
    d = generate("seed1", "sweeps", n=400, effects={"drift": {"wander": 0.0}}, noise_mm=0.0, seed=3)
    p = d.effects["drift"]
    t = (d.time - d.time.min()) / np.ptp(d.time)
    u = np.array(p["direction"]) / np.linalg.norm(p["direction"])
    v = np.array(p["step_direction"]) / np.linalg.norm(p["step_direction"])
    w = np.array(p["wobble_direction"]) / np.linalg.norm(p["wobble_direction"])
    tau = p["settle"]
    expect = (p["amplitude"] * ((1 - np.exp(-t / tau)) / (1 - np.exp(-1 / tau)))[:, None] * u
              + p["wobble"] * np.sin(2 * np.pi * t / p["wobble_period"])[:, None] * w
              + p["step"] * (t >= p["step_at"])[:, None] * v)
    np.testing.assert_allclose(d.tip_clean - base.tip_clean, expect, atol=1e-9)


def test_presliding_builds_up_after_a_reversal():
    # one tube rotating forward then back: the lag relaxes toward +c, then toward -c
    a = np.r_[np.linspace(0, 1.0, 41), np.linspace(1.0, 0.0, 41)[1:]]
    q = np.c_[a, np.full_like(a, -20.0)]
    sweep = np.array(["s0"] * len(a))
    from tests.foreign.core import _alpha_lag
    from tests.foreign.designs import directions
    eff = {"friction": {"form": "presliding", "lag": 0.06, "angle": 0.25}}
    qe = _alpha_lag(eff, q, 1, directions(q, sweep), sweep)
    lag = q[:, 0] - qe[:, 0]
    # Dahl exponent 2, w = 1 - z/c: w' = -w^2/angle per unit rotation from w = 1:
    # w = 1 / (1 + a/angle), lag = c (1 - w) (NOT ctrplan's exponential c (1 - exp(-a/angle)))
    np.testing.assert_allclose(lag[:41], 0.06 * (1 - 1 / (1 + a[:41] / 0.25)), atol=1e-12)
    assert np.max(np.abs(lag[:41] - 0.06 * (1 - np.exp(-a[:41] / 0.25)))) > 5e-3
    assert lag[-1] < -0.04 and np.all(np.diff(lag[41:]) < 0)


def test_presliding_lag_never_exceeds_its_breakaway_limit_when_the_limit_drops():
    """The presliding lag is a friction displacement: it cannot exceed the breakaway limit c.
    Where c depends on the configuration (here: the share of the curved section held inside
    the outer tube, through ``growth``) and drops while the tube turns on, the contact slides
    down to the limit. (Before the clamp, the Dahl update ran away there: a 0.04 rad lag became
    6 rad within 0.02 rad of rotation on a real-robot re-check path.)"""
    from tests.foreign.core import _alpha_lag, _held_curved
    from tests.foreign.designs import directions

    spec = load_spec("seed1")
    n = spec.n
    k = 400
    rng = np.random.default_rng(7)
    a1 = np.linspace(0.0, -2.0, k)                 # the inner tube turns one way throughout
    beta = np.stack([np.linspace(-200.0, -100.0, k),   # while it is pushed out of the others:
                     np.full(k, -120.0), np.full(k, -60.0)], axis=1)   # its held share drops
    q = np.c_[a1, rng.uniform(-0.01, 0.01, (k, 1)), np.zeros((k, 1)), beta]
    sweep = np.array(["s0"] * k)
    lag, growth = 0.04, 30.0
    eff = {"friction": {"form": "presliding", "lag": [lag, 0.0, 0.0], "angle": 0.0025,
                        "growth": [growth, 0.0, 0.0], "moment": 0.0}}
    qe = _alpha_lag(eff, q, n, directions(q, sweep), sweep, spec)
    held = _held_curved(spec, q)[:, 0]
    limit = lag * (1.0 + growth * held)            # the breakaway limit row by row
    assert np.ptp(limit) > 0.5 * limit.max()       # the limit really drops along the motion
    z = q[:, 0] - qe[:, 0]
    assert np.all(np.abs(z) <= limit + 1e-12)
    assert np.all(np.isfinite(qe))


def test_robot_from_yaml_path_equals_shipped_name(tmp_path):
    src = Path(__file__).parents[1] / "ctrplan" / "data" / "robots" / "seed1.yaml"
    p = tmp_path / "my_robot.yaml"
    p.write_text(src.read_text())
    a = generate("seed1", "sweeps", n=50, effects={"clearance": {}}, seed=1)
    b = generate(str(p), "sweeps", n=50, effects={"clearance": {}}, seed=1)
    assert np.array_equal(a.tip, b.tip)
    # density from the file is used for gravity
    text = src.read_text().replace("poisson_ratio: 0.33}", "poisson_ratio: 0.33, density: 12900}")
    p.write_text(text)
    assert np.allclose(load_spec(str(p)).density, 12900.0)


def test_compliant_friction_and_clearance_events_vs_scipy():
    sp = load_spec("seed1")
    n = sp.n
    from tests.foreign.effects import clearance_fn
    from tests.foreign.robot import beta_from_unit
    q = np.c_[np.array([[0.4, -0.9, 1.3]]), beta_from_unit(sp, np.array([[0.7, 0.5, 0.6]]))]
    rel = np.array([1.0, -1.0])
    for params, contact in (({"amplitude": 0.06, "phase_deg": 205.0, "harmonics": [0.5, 0.5]}, 0.0),
                            ({"amplitude": 0.06, "phase_deg": 205.0, "harmonics": [0.5, 0.3, 0.2],
                              "lean": 0.03, "jump": 0.4}, 10.0)):
        clear = clearance_fn(params)

        def one(phi, clear=clear):
            ev = clear(np.array([phi]), 0)
            return tuple(float(v[0]) for v in ev) if isinstance(ev, tuple) else float(ev[0])
        bb = M.cosserat(sp, q[:, :n], q[:, n:], torsion=True, gravity=[0.0, 9.81, 0.0],
                        clearance=clear, friction_mu=0.1, rel_dir=rel[None, :],
                        friction_contact=contact)
        ref = _scipy_cosserat(sp, q[0, :n], q[0, n:], np.array([0.0, 9.81, 0.0]), None, True,
                              mu=0.1, rel=rel, clear=one, contact=contact)
        assert bb.ok.all()
        assert np.linalg.norm(bb.tip()[0] - ref) < 1e-3, params
        plain = M.cosserat(sp, q[:, :n], q[:, n:], torsion=True, gravity=[0.0, 9.81, 0.0]).tip()[0]
        assert np.linalg.norm(plain - ref) > 1.0           # the events matter at this tolerance
        # the rigid closed form with the same clearance event
        rb = M.rigid(sp, q[:, :n], q[:, n:], clearance=clear).tip()[0]
        ref_r = _scipy_cosserat(sp, q[0, :n], q[0, n:], torsion=False, clear=one)
        assert np.linalg.norm(rb - ref_r) < 1e-6, params


def test_compliant_mechanics_forms_vs_scipy():
    """Curvature ramp, pre-twist and kink, curved-section stiffness and drive couplings in the
    compliant, loaded shooting against the scipy oracle (its own sub-sections and boundary
    conditions)."""
    sp = load_spec("seed1")
    n = sp.n
    from tests.foreign.robot import beta_from_unit
    q = np.c_[np.array([[1.1, -0.4, 2.0]]), beta_from_unit(sp, np.array([[0.6, 0.4, 0.7]]))]
    ramp, eic, cpl = np.array([0.6, -0.6, 0.6]), np.array([1.25, 0.8, 1.0]), np.array([60.0, 40, 30])
    tw, kk = np.array([0.8, -0.9, 0.8]), (np.array([0.04, -0.04, 0.04]), 0.6, 3.0)
    bb = M.cosserat(sp, q[:, :n], q[:, n:], torsion=True, gravity=[9.81, 0.0, 0.0],
                    ramp=ramp, ei_curved=eic, coupling=cpl, twist=tw, kink=kk)
    ref = _scipy_cosserat(sp, q[0, :n], q[0, n:], np.array([9.81, 0.0, 0.0]), None, True,
                          ramp=ramp, ei_curved=eic, coupling=cpl, twist=tw, kink=kk)
    assert bb.ok.all()
    assert np.linalg.norm(bb.tip()[0] - ref) < 1e-3
    plain = M.cosserat(sp, q[:, :n], q[:, n:], torsion=True, gravity=[9.81, 0.0, 0.0]).tip()[0]
    assert np.linalg.norm(plain - ref) > 1.0
    # the rigid closed form with the same forms equals the oracle without torsion
    rb = M.rigid(sp, q[:, :n], q[:, n:], ramp=ramp, ei_curved=eic, twist=tw, kink=kk).tip()[0]
    ref_r = _scipy_cosserat(sp, q[0, :n], q[0, n:], torsion=False, ramp=ramp, ei_curved=eic,
                            twist=tw, kink=kk)
    assert np.linalg.norm(rb - ref_r) < 1e-6
    for drop in ({"twist": None}, {"kink": None}):            # each matters here
        kw = {"ramp": ramp, "ei_curved": eic, "twist": tw, "kink": kk, **drop}
        assert np.linalg.norm(M.rigid(sp, q[:, :n], q[:, n:], **kw).tip()[0] - ref_r) > 0.3


def test_bistable_pair_returns_a_stable_twisted_equilibrium():
    # At a relative rotation of exactly 180 deg the untwisted state (u_z = 0) is an exact
    # equilibrium by symmetry. For the nylon pair with its physical GJ and deep overlap it is the
    # unstable middle state between two twisted stable ones (snapping regime): the generator
    # must return a twisted state. With 6x the torsional stiffness the pair is stable and the
    # untwisted state is the solution.
    sp = load_spec("two_tube_nylon")
    from tests.foreign.robot import beta_from_unit
    beta = beta_from_unit(sp, np.array([[0.05, 0.6]]))
    alpha = np.array([[math.pi, 0.0]])
    rigid_tip = M.rigid(sp, alpha, beta).tip()[0]
    soft = M.cosserat(sp, alpha, beta, torsion=True)
    assert soft.ok.all() and abs(soft.info["x"][0, 0]) > 1e-4
    assert np.linalg.norm(soft.tip()[0] - rigid_tip) > 1.0
    from dataclasses import replace
    stiff_sp = replace(sp, nu=(1.0 + sp.nu) / 6.0 - 1.0)        # GJ x 6
    stiff = M.cosserat(stiff_sp, alpha, beta, torsion=True)
    assert stiff.ok.all() and abs(stiff.info["x"][0, 0]) < 1e-9
    np.testing.assert_allclose(stiff.tip()[0], rigid_tip, atol=2e-4)


def test_load_parameters():
    from tests.foreign.effects import resolve
    sp = load_spec("seed1")
    full = resolve({"load": {}}, 3, sp)["load"]
    assert full["gravity"] == [9.81, 0.0, 0.0]
    assert np.allclose(full["tip_force"], [0.0, -1e-5 * sp.EI[0], 0.0])
    g_only = resolve({"load": {"gravity": [0, -9.81, 0]}}, 3, sp)["load"]
    assert g_only["tip_force"] is None
    q = generate("seed1", "uniform", n=20, effects={}, seed=1).q
    tg, _, _ = truth(sp, q, {"load": {"gravity": [0, -9.81, 0]}})
    tf, _, _ = truth(sp, q, {"load": {"tip_force": [0, -0.02, 0]}})
    tb, _, _ = truth(sp, q, {"load": {"gravity": [0, -9.81, 0], "tip_force": [0, -0.02, 0]}})
    t0, _, _ = truth(sp, q, {})
    # small loads: deflections superpose (linear regime) and point along -y
    np.testing.assert_allclose(tb - t0, (tg - t0) + (tf - t0), atol=0.02)
    assert np.all((tg - t0)[:, 1] < 0) and np.all((tf - t0)[:, 1] < 0)


def test_conventions_agree_with_ctrplan_physics():
    """Same DESIGN.md conventions (frames, alpha sign, beta, points) as ctrplan's physics model:
    the generator's base model equals ctrplan's rigid model to round-off and its compliant one
    on seed1 to the integration tolerance (two independent implementations)."""
    from ctrplan.shape.physics import PhysicsModel
    for robot, tors in (("seed1", (False, True)), ("two_tube_nylon", (False,))):
        d = generate(robot, "uniform", n=100, effects={}, seed=4)
        for torsion in tors:
            theirs = np.asarray(PhysicsModel(robot, torsion=torsion).shape(d.q, points=20).points)
            plain = {"torsion": {"gj_scale": 1.0, "coupling": 0.0, "play": 0.0}}
            mine = backbones(robot, d.q, plain if torsion else {}, points=20)
            dev = np.linalg.norm(theirs - mine, axis=2).max()
            assert dev < (1e-3 if torsion else 1e-9), (robot, torsion, dev)


# ----------------------------------------------------------------------------- the new forms
def test_joint_and_sensor_forms_by_hand():
    sp = load_spec("seed1")
    n = sp.n
    q = generate("seed1", "uniform", n=40, effects={}, seed=6).q
    jo = {"alpha": [0.05, -0.06, 0.04], "beta": [-1.5, -1.0, -0.5], "periodic": [0.03, 0.02, 0.01],
          "periodic_phase": [0.7, 2.1, -1.3], "beta_scale": [0.01, -0.008, 0.006], "gear": 0.0,
          "rehome": 0.0}   # the gear error and re-homing: tests/test_foreign_new_forms.py
    qt = q.copy()
    for i in range(n):     # eccentric encoder and lead-screw scale, written out per tube
        qt[:, i] = q[:, i] + jo["alpha"][i] + jo["periodic"][i] * np.sin(q[:, i] + jo["periodic_phase"][i])
        qt[:, n + i] = q[:, n + i] * (1 + jo["beta_scale"][i]) + jo["beta"][i]
    np.testing.assert_allclose(truth(sp, q, {"joint_offset": jo})[0], truth(sp, qt, {})[0], atol=1e-9)
    # registration with a per-axis scale: (1 + s) * (R p + t)
    rg = {"rotvec": [0.02, -0.01, 0.03], "translation": [1.0, 2.0, -3.0], "scale": [0.01, -0.005, 0.02],
          "mount": 0.0, "sensor": 0.0}
    base = backbones("seed1", q, {}, points=5)
    got = backbones("seed1", q, {"registration": rg}, points=5)
    R = Rotation.from_rotvec(rg["rotvec"]).as_matrix()
    np.testing.assert_allclose(got, (base @ R.T + rg["translation"]) * (1 + np.array(rg["scale"])),
                               atol=1e-9)
    # distortion: Gaussian bumps, by hand
    d = generate("seed1", "sweeps", n=300, effects={"distortion": {}}, noise_mm=0.0, seed=3)
    b = generate("seed1", "sweeps", n=300, effects={}, noise_mm=0.0, seed=3)
    p = d.effects["distortion"]
    exp = np.zeros_like(b.tip_clean)
    for c, v in zip(p["centres"], p["vectors"]):
        w = np.exp(-np.sum((b.tip_clean - np.array(c)) ** 2, axis=1) / (2 * p["width"] ** 2))
        exp += p["amplitude"] * w[:, None] * np.array(v) / np.linalg.norm(v)
    np.testing.assert_allclose(d.tip_clean - b.tip_clean, exp, atol=1e-9)


def _cubic_features(p):
    c = p - p.mean(0)
    c = c / np.abs(c).max()
    x, y, z = c.T
    one = np.ones_like(x)
    return np.stack([one, x, y, z, x * x, y * y, z * z, x * y, x * z, y * z, x ** 3, y ** 3, z ** 3,
                     x * x * y, x * x * z, y * y * x, y * y * z, z * z * x, z * z * y, x * y * z], 1)


def test_outside_effects_are_not_low_order_in_position_or_time():
    """The tracker field is not a cubic polynomial of the measured position, the drift neither a
    quadratic of the normalised time nor a linear spline in it with 10 evenly spaced knots
    (ctrplan's drift nuisance; the best unpenalised fit of one, written here, leaves its fast
    cycle and the step's edge)."""
    b = generate("seed1", "sweeps", n=400, effects={}, noise_mm=0.0, seed=8, sweeps=8)
    d = generate("seed1", "sweeps", n=400, effects={"distortion": {}}, noise_mm=0.0, seed=8, sweeps=8)
    disp = d.tip_clean - b.tip_clean
    A = _cubic_features(d.tip_clean)
    res = disp - A @ np.linalg.lstsq(A, disp, rcond=None)[0]
    left = np.linalg.norm(res, axis=1).mean() / np.linalg.norm(disp, axis=1).mean()
    assert left > 0.25, left             # a cubic leaves 40-50 % (seed 8), 20-25 % (seed 1)
    d = generate("seed1", "sweeps", n=400, effects={"drift": {}}, noise_mm=0.0, seed=8, sweeps=8)
    disp = d.tip_clean - b.tip_clean
    t = (d.time - d.time.min()) / np.ptp(d.time)
    A = np.stack([np.ones_like(t), t, t * t], 1)
    res = disp - A @ np.linalg.lstsq(A, disp, rcond=None)[0]
    assert np.linalg.norm(res, axis=1).mean() > 0.3
    knots = np.linspace(0.0, 1.0, 10)
    hat = np.clip(1.0 - np.abs(t[:, None] - knots[None, :]) / knots[1], 0.0, None)
    res = disp - hat @ np.linalg.lstsq(hat, disp, rcond=None)[0]
    # measured 0.29 mm mean (seeds 1, 8), above the 0.1 mm per axis noise of the statistics
    assert np.linalg.norm(res, axis=1).mean() > 0.2


def test_tether_is_a_fixed_point_and_lags_grow_with_contact():
    sp = load_spec("seed1")
    n = sp.n
    q = generate("seed1", "uniform", n=20, effects={}, seed=2).q
    from tests.foreign.effects import resolve
    ld = resolve({"load": {}}, n, sp)["load"]
    assert ld["tether"] > 0 and ld["lumen_density"] > 0 and ld["base_compliance"] > 0
    assert ld["wall"] > 0
    ld = {**ld, "wall": None}        # the soft wall: tests/test_foreign_new_forms.py
    mounted = truth(sp, q, {"load": ld})[0]
    ld = {**ld, "base_compliance": 0.0}
    tip, _, ok = truth(sp, q, {"load": ld})
    assert ok.all()
    # the compliant mount turns the whole robot about the base origin: distances from it are
    # kept, the tip moves by up to millimetres
    np.testing.assert_allclose(np.linalg.norm(mounted, axis=1), np.linalg.norm(tip, axis=1),
                               atol=1e-9)
    moved = np.linalg.norm(mounted - tip, axis=1)
    assert 0.05 < moved.mean() and moved.max() < 10.0
    # the tip force the tether exerts at the returned tip, applied as a fixed force: same tip
    F = np.array(ld["tip_force"])[None, :] + ld["tether"] * (np.array(ld["anchor"]) - tip)
    extra = np.zeros(n)
    extra[0] = ld["lumen_density"] * 1e-9 * math.pi / 4 * sp.id[0] ** 2 * 9.81
    again = M.cosserat(sp, q[:, :n], q[:, n:], torsion=False, gravity=ld["gravity"], tip_force=F,
                       extra_weight=extra).tip()
    assert np.max(np.linalg.norm(again - tip, axis=1)) < 1e-3
    no_tether = truth(sp, q, {"load": {**ld, "tether": 0.0}})[0]
    assert np.linalg.norm(no_tether - tip, axis=1).mean() > 0.2
    # coulomb lag: lag (1 + growth h) (1 + moment (2 r - 1)), h the held fraction of each
    # curved section, counted here by sampling the curved section (arc positions in the plane
    # frame: base at beta), r the pair's curvature mismatch (the vectors' difference)
    from tests.foreign.core import _alpha_lag
    eff = resolve({"friction": {"form": "coulomb_lag"}}, n, sp)
    dirs = np.tile([1, -1, 1, 0, 0, 0], (len(q), 1)).astype(np.int8)
    qe = _alpha_lag(eff, q, n, dirs, None, sp)
    fr = eff["friction"]
    u = (np.arange(4000) + 0.5) / 4000
    h = np.empty((len(q), n))
    for k, row in enumerate(q):
        beta = row[n:]
        for i in range(n):
            pos = beta[i] + sp.straight[i] + u * sp.curved[i]
            wall = max(beta[i + 1] + sp.L[i + 1], 0.0) if i + 1 < n else 0.0
            h[k, i] = np.mean(pos < wall)
    assert h[:, 0].std() > 0.1                           # the inner tubes' contact varies
    r = np.full((len(q), n), 0.5)
    for i in range(n - 1):
        ki = sp.kappa[i] * np.c_[np.cos(q[:, i]), np.sin(q[:, i])]
        ko = sp.kappa[i + 1] * np.c_[np.cos(q[:, i + 1]), np.sin(q[:, i + 1])]
        r[:, i] = np.linalg.norm(ki - ko, axis=1) / (sp.kappa[i] + sp.kappa[i + 1])
    np.testing.assert_allclose(q[:, :n] - qe[:, :n], fr["lag"] * (1 + fr["growth"] * h)
                               * (1 + fr["moment"] * (2 * r - 1)) * dirs[:, :n], atol=2e-4)


#: noise-free residual (mm, mean tip error) that the best fit of ctrplan's family of the same name
#: leaves on the generator's default form, at least (the noise floor of the statistical tests
#: is 0.16 mm mean); and at most this fraction of the effect (the family can still halve it).
NOT_EXACT_MM = 0.12
CUTTABLE = 0.5


def _best_family_fit(name, form=""):
    """Fit every variant of ctrplan's family ``name`` (rigid base) to noise-free generator rows;
    returns (effect mean mm, best residual mean mm, variant)."""
    from ctrplan.calibration.fit import Problem
    from ctrplan.measured import MeasuredData
    from ctrplan.robot import load_robot
    from ctrplan.shape.effects import EffectModel, effect_variants, off_values

    base = generate("seed1", "sweeps", n=120, effects={}, noise_mm=0.0, seed=1, sweeps=4)
    d = generate("seed1", "sweeps", n=120, effects={name: {"form": form} if form else {}},
                 noise_mm=0.0, seed=1, sweeps=4)
    r = load_robot("seed1")
    md = MeasuredData(q=d.q, tip=d.tip_clean, time=d.time, sweep=np.asarray(d.sweep, dtype=object))
    every = np.ones(len(d), bool)
    prob = Problem(EffectModel(r, "rigid"), md, every, every)
    best = (math.inf, "")
    for label, fixed, free in effect_variants(name, r, "rigid"):
        vals = off_values(name, r, "rigid")
        vals.update(fixed)
        fit = prob.fit({name: vals}, {name: free}, max_iter=40)
        best = min(best, (fit.test_mean, label))
    return np.linalg.norm(d.tip_clean - base.tip_clean, axis=1).mean(), best[0], best[1]


@pytest.mark.parametrize("case", list(VOCAB_EFFECTS) + ["friction:coulomb_lag", "friction:presliding"])
def test_forms_are_not_representable_by_ctrplan(case):
    """The claim of issue 19: no default form is exactly representable by ctrplan's effect family
    of the same name (any variant, parameters within bounds), yet that family still removes
    most of it (this test imports ctrplan: it tests a claim about ctrplan's families)."""
    name, _, form = case.partition(":")
    effect, left, variant = _best_family_fit(name, form)
    print(f"\n{case}: effect {effect:.2f} mm, best ctrplan fit ({variant}) leaves {left:.3f} mm")
    assert left > NOT_EXACT_MM, (case, effect, left, variant)
    assert left < CUTTABLE * effect, (case, effect, left, variant)


def test_real_robot_scenario():
    from tests.foreign.scenarios import real_robot
    rr = real_robot(seed=0, registration=True, outliers=0.02)
    q = generate("seed1", "uniform", n=60, effects={}, seed=5).q
    dev = np.linalg.norm(rr.backbones(q, points=20) - rr.nominal(q, points=20), axis=2).max(1)
    assert 1.5 < dev.mean() < 3.0, dev.mean()          # ~2 mm of max deviation along the shaft
    # hysteresis of the inner tube: opposite directions of its last motion differ
    dd = np.zeros_like(q, dtype=np.int8)
    dd[:, 0] = 1
    hyst = np.linalg.norm(rr.backbones(q, direction=dd)[:, -1] - rr.backbones(q, direction=-dd)[:, -1],
                          axis=1)
    assert hyst.mean() > 0.5
    # a path: rows in order build the history; a single row equals its independent replay
    path = np.linspace(q[0], q[1], 15)
    pp = rr.backbones(path, path=True)
    np.testing.assert_allclose(pp[0], rr.backbones(path[:1])[0], atol=1e-9)
    assert np.isfinite(pp).all() and not np.allclose(pp[-1], rr.backbones(path[-1:])[0], atol=1e-3)
    # measured rows: sweeps, registration (sensor frame), outliers recorded
    d = rr.measure(n=200, sweeps=4, points=5)
    assert len(d) == 200 and len(np.unique(d.sweep)) == 4 and d.points.shape == (200, 5, 3)
    assert len(d.info["outliers"]) == 4
    err = np.linalg.norm(d.tip - d.tip_clean, axis=1)
    assert np.all(err[d.info["outliers"]] > 2.5) and np.median(err) < 0.3
    sensor_pts = rr.backbones(d.q[:3], points=5, frame="sensor")
    assert np.linalg.norm(sensor_pts - rr.backbones(d.q[:3], points=5), axis=2).mean() > 1.0
