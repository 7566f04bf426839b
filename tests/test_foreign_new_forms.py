"""The foreign generator's forms added so that every form lies outside what ctrplan's families
can combine (issue 36; tests/test_foreign_forms.py measures that), each against an oracle that
shares no code with it: a plain loop written here, scipy's root finder on the fixed point the
form defines, hand-composed rotations (scipy Rotation), closed-form arcs.

Forms: drive-coupling play (torsion), a gap crossing (clearance), stick-slip (friction), a
pre-twisted and relaxing precurvature, superelastic softening (stiffness), a soft wall the tip
presses on (load), a gear's transmission error and re-homing per sweep (joint offsets), the
coil's offset from the tip and a housing that turns with the configuration (registration), a
dipole tracker field (distortion), a wandering drift.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.optimize import root
from scipy.spatial.transform import Rotation

from tests.foreign import effects as E
from tests.foreign import generate, load_spec
from tests.foreign import mechanics as M
from tests.foreign.core import _joint_space, truth
from tests.foreign.robot import beta_from_unit


def _q(spec, rows=6, seed=3):
    rng = np.random.default_rng(seed)
    n = spec.n
    return np.c_[rng.uniform(-2.5, 2.5, (rows, n)), beta_from_unit(spec, rng.uniform(0.2, 0.9, (rows, n)))]


def test_coupling_play_is_the_fixed_point_scipy_finds():
    """Each tube's base turns within its coupling's play by play tanh(T / T0), T = GJ u_z(0) the
    torque it carries: scipy's root finder on that equation, with the generator's plain
    compliant mechanics inside, gives the same tips."""
    sp = load_spec("seed1")
    n = sp.n
    q = _q(sp, 4)
    eff = E.resolve({"torsion": {}}, n, sp)
    tor = eff["torsion"]
    play, T0 = np.asarray(tor["play"], float), float(tor["play_torque"])
    got, _, ok = truth(sp, q, eff)
    assert ok.all()
    from dataclasses import replace
    gsp = replace(sp, nu=(1.0 + sp.nu) / np.asarray(tor["gj_scale"], float) - 1.0)
    cpl = np.asarray(tor["coupling"], float)
    for i in range(len(q)):
        def f(a, i=i):
            bb = M.cosserat(gsp, a[None, :], q[i:i + 1, n:], torsion=True, coupling=cpl)
            T = gsp.GJ * bb.info["x"][0, :n]
            return a - q[i, :n] - play * np.tanh(T / T0)
        sol = root(f, q[i, :n], method="hybr", tol=1e-12)
        assert np.max(np.abs(f(sol.x))) < 1e-9            # (hybr may flag slow progress)
        ref = M.cosserat(gsp, sol.x[None, :], q[i:i + 1, n:], torsion=True, coupling=cpl).tip()[0]
        assert np.linalg.norm(got[i] - ref) < 3e-3, (i, got[i], ref)   # << 0.1 mm noise
    no_play, _, _ = truth(sp, q, {"torsion": {**tor, "play": 0.0}})
    assert np.linalg.norm(got - no_play, axis=1).max() > 0.2     # the play matters here


def test_soft_wall_is_the_fixed_point_scipy_finds():
    """Where the tip is beyond the wall plane it is pushed back by k times its depth: the tip
    force at the returned tip, applied as a fixed force with scipy's root on the tip, agrees."""
    sp = load_spec("seed1")
    n = sp.n
    d = generate("seed1", "sweeps", n=60, effects={}, noise_mm=0.0, seed=2, sweeps=2)
    ld = {"gravity": [9.81, 0.0, 0.0], "wall": 6e-3, "wall_normal": [-1.0, 0.0, 0.0], "wall_at": -18.0}
    tip, _, ok = truth(sp, d.q, {"load": ld})
    assert ok.all()
    nrm = np.array([-1.0, 0.0, 0.0])
    depth = np.maximum(-18.0 - tip @ nrm, 0.0)
    assert (depth > 1.0).sum() >= 5 and (depth == 0).sum() >= 5     # rows on both sides
    for i in np.flatnonzero(depth > 0)[:3]:
        def f(p, i=i):
            F = 6e-3 * max(-18.0 - p @ nrm, 0.0) * nrm
            bb = M.cosserat(sp, d.q[i:i + 1, :n], d.q[i:i + 1, n:], torsion=False,
                            gravity=[9.81, 0.0, 0.0], tip_force=F)
            return bb.tip()[0] - p
        sol = root(f, tip[i], method="hybr", tol=1e-12)
        assert np.linalg.norm(sol.x - tip[i]) < 2e-3, (i, sol.x, tip[i])


def test_superelastic_softening_against_hand_composed_arcs():
    """Two tubes, torsionally rigid: per section the curvature is the stiffness-weighted mean
    of the rotated precurvatures, each tube's EI times 1 - drop / (1 + exp(-(eps - onset) /
    width)), eps = (od / 2) |u_i - kappa_i| in its own frame; the fixed point solved with scipy
    and the arcs composed with scipy Rotation."""
    t1 = {"od": 1.3, "id": 1.0, "straight_length": 100.0, "curved_length": 80.0, "curvature": 0.02,
          "youngs_modulus": 60000.0, "poisson_ratio": 0.33}
    t2 = {"od": 1.9, "id": 1.5, "straight_length": 60.0, "curved_length": 70.0, "curvature": 0.012,
          "youngs_modulus": 60000.0, "poisson_ratio": 0.33}
    sp = load_spec({"name": "two", "tubes": [t1, t2]})
    soft = {"onset": 0.005, "width": 0.001, "drop": [0.5, 0.5]}
    a1, a2, b1, b2 = 2.6, 0.1, -30.0, -10.0
    # sections: straight both (0-50), outer curved + inner straight (50-70), both curved
    # (70-120), inner curved alone (120-150)
    EI = sp.EI
    kap_sec = [(0.0, 0.0), (0.0, 0.012), (0.02, 0.012), (0.02, 0.0)]
    present = [(1, 1), (1, 1), (1, 1), (1, 0)]
    lengths = [50.0, 20.0, 50.0, 30.0]
    alpha = np.array([a1, a2])

    def ubar(a, k):
        return np.array([-k * math.sin(a), k * math.cos(a)])

    def section_u(f, j):
        w = np.array(present[j]) * EI * f
        return sum(w[i] * ubar(alpha[i], kap_sec[j][i]) for i in range(2)) / w.sum()

    def strains(f):
        out = np.zeros(8)
        for j in range(4):
            u = section_u(f[2 * j:2 * j + 2], j)
            for i in range(2):
                Ri = Rotation.from_euler("z", -alpha[i]).as_matrix()[:2, :2]
                ui = Ri @ u
                out[2 * j + i] = 0.5 * sp.od[i] * math.hypot(ui[0], ui[1] - kap_sec[j][i])
        return out

    def g(f):
        target = 1.0 - 0.5 / (1.0 + np.exp(-(strains(f) - 0.005) / 0.001))
        return f - np.where(np.array(present).ravel() > 0, target, 1.0)
    f = root(g, np.ones(8), tol=1e-13).x
    assert np.max(np.abs(g(f))) < 1e-10 and f.min() < 0.9       # some section softened
    Rw, p = np.eye(3), np.zeros(3)
    for j in range(4):
        u = section_u(f[2 * j:2 * j + 2], j)
        uu = np.array([u[0], u[1], 0.0])
        k = np.linalg.norm(uu)
        h = lengths[j]
        if k:
            b = np.cross(uu / k, [0, 0, 1.0])
            dp = math.sin(k * h) / k * np.array([0, 0, 1.0]) + (1 - math.cos(k * h)) / k * b
            p, Rw = p + Rw @ dp, Rw @ Rotation.from_rotvec(uu * h).as_matrix()
        else:
            p = p + Rw @ np.array([0, 0, h])
    got = M.rigid(sp, alpha[None, :], np.array([[b1, b2]]), softening=soft).tip()[0]
    # the generator's damped iteration against the exact fixed point
    assert np.linalg.norm(got - p) < 1e-3, (got, p)
    plain = M.rigid(sp, alpha[None, :], np.array([[b1, b2]])).tip()[0]
    assert np.linalg.norm(plain - p) > 0.5


def test_stick_slip_sawtooth_by_hand():
    """One tube rotating back and forth with the others still: the lag sticks up to the static
    limit, slips to the kinetic one, sticks again (a loop over the commanded travel written
    here, the contact growth held fixed by fixed insertions; the limit follows the contact
    force, the pair's curvature mismatch at each relative rotation)."""
    sp = load_spec("seed1")
    n = sp.n
    beta = beta_from_unit(sp, np.array([[0.5, 0.5, 0.5]]))[0]
    a = np.r_[np.cumsum(np.full(30, 0.013)), 0.39 - np.cumsum(np.full(30, 0.021))]
    q = np.zeros((60, 2 * n))
    q[:, 0] = a
    q[:, n:] = beta
    sweep = np.array(["s0"] * 60)
    d = np.zeros((60, 2 * n), np.int8)
    d[1:30, 0], d[30:, 0] = 1, -1
    eff = E.resolve({"friction": {"form": "stick_slip"}}, n, sp)
    fr = eff["friction"]
    qe = _joint_space(eff, q, n, d, sweep, sp)
    # the held fraction of the inner tube's curved section, by sampling it
    u = (np.arange(4000) + 0.5) / 4000
    pos = beta[0] + sp.straight[0] + u * sp.curved[0]
    h = np.mean(pos < max(beta[1] + sp.L[1], 0.0))
    k1, k2 = sp.kappa[0], sp.kappa[1]
    e, lags = 0.0, [0.0]
    for k in range(1, 60):
        # the contact force: the pair's curvature mismatch at this relative rotation
        r = math.sqrt(k1 ** 2 + k2 ** 2 - 2 * k1 * k2 * math.cos(a[k])) / (k1 + k2)
        cs = fr["lag"] * (1.0 + fr["growth"] * h) * (1.0 + fr["moment"] * (2 * r - 1))
        ck = fr["kinetic"] * cs
        step = a[k] - a[k - 1]
        sg = math.copysign(1.0, step)
        e_new = e + step
        if sg * e_new > cs:
            e_new = sg * (ck + (sg * e_new - cs) % (cs - ck))
        e = e_new
        lags.append(e)
    np.testing.assert_allclose(q[:, 0] - qe[:, 0], lags, atol=1e-4)      # h sampled here
    assert max(lags) > 0.05 and min(lags) < -0.05


def test_joint_errors_gear_and_rehoming_by_hand():
    sp = load_spec("seed1")
    n = sp.n
    d = generate("seed1", "sweeps", n=90, effects={}, noise_mm=0.0, seed=7, sweeps=3)
    jo = E.resolve({"joint_offset": {}}, n, sp)["joint_offset"]
    jo["rehome_seed"] = 11
    qe = _joint_space({"joint_offset": jo}, d.q, n, None, d.sweep, sp)
    a = d.q[:, :n]
    expect_a = (a + np.array(jo["alpha"]) + np.array(jo["periodic"]) * np.sin(a + np.array(jo["periodic_phase"]))
                + np.array(jo["gear"]) * np.sin(jo["gear_order"] * a + np.array(jo["gear_phase"])))
    expect_b = d.q[:, n:] * (1 + np.array(jo["beta_scale"])) + np.array(jo["beta"])
    rest = qe - np.c_[expect_a, expect_b]
    for sw in np.unique(d.sweep):              # re-homing: one offset per sweep and joint
        r = rest[d.sweep == sw]
        assert np.ptp(r, axis=0).max() < 1e-12
    per = np.array([rest[d.sweep == sw][0] for sw in np.unique(d.sweep)])
    assert np.all(np.abs(per[:, :n]) < 5 * jo["rehome"][0]) and np.all(np.abs(per[:, n:]) < 5 * jo["rehome"][1])
    assert np.ptp(per[:, 0]) > 0.1 * jo["rehome"][0]
    # rows without sweeps (independent configurations): no re-homing
    qi = _joint_space({"joint_offset": jo}, d.q, n, None, None, sp)
    np.testing.assert_allclose(qi, np.c_[expect_a, expect_b], atol=1e-12)


def test_registration_coil_offset_and_turning_housing_by_hand():
    sp = load_spec("seed1")
    n = sp.n
    q = _q(sp, 5)
    rg = E.resolve({"registration": {}}, n, sp)["registration"]
    o = np.array(rg["sensor"])
    # the coil: |offset| = |o|, its component along the tip tangent = o_z (rigid truth)
    tip0, _, _ = truth(sp, q, {})
    tipc, _, _ = truth(sp, q, {"registration": {**rg}})
    off = tipc - tip0
    np.testing.assert_allclose(np.linalg.norm(off, axis=1), np.linalg.norm(o), atol=1e-9)
    pts = M.rigid(sp, q[:, :n], q[:, n:]).points(2001)
    t = pts[:, -1] - pts[:, -2]
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    np.testing.assert_allclose(np.sum(off * t, axis=1), o[2], atol=2e-3)
    # the sensor frame: the housing turned by the configuration's rotation vector, then the
    # rigid transform and the per-axis scale (scipy Rotation)
    got = E.sensor(tipc, {"registration": rg}, None, q, sp)
    lo = max(sp.beta_lo[-1], -sp.L[-1])
    u = (q[:, 2 * n - 1] - lo) / (0.0 - lo)
    un = math.tanh(1 / 0.2)
    rv = np.c_[rg["mount"][0] * np.tanh(np.cos(q[:, n - 1] - 0.4) / 0.2) / un,
               rg["mount"][1] * np.sin(np.pi * u), np.zeros(len(q))]
    R = Rotation.from_rotvec(rg["rotvec"]).as_matrix()
    expect = np.stack([(R @ Rotation.from_rotvec(r).as_matrix() @ p + rg["translation"])
                       * (1 + np.array(rg["scale"])) for r, p in zip(rv, tipc)])
    np.testing.assert_allclose(got, expect, atol=1e-9)


def test_dipole_field_and_wandering_drift_by_hand():
    sp = load_spec("seed1")
    ds = E.resolve({"distortion": {"form": "dipole"}}, sp.n, sp)["distortion"]
    p = np.random.default_rng(1).uniform([-30, -30, 100], [40, 30, 240], (50, 3))
    got = E.sensor(p, {"distortion": ds}, None) - p
    c, m, w = np.array(ds["centres"][0]), np.array(ds["vectors"][0]), ds["width"]
    m = m / np.linalg.norm(m)
    for pi, gi in zip(p, got):
        r = pi - c
        rn = math.sqrt(r @ r + (w / 4) ** 2)
        rh = r / rn
        np.testing.assert_allclose(gi, ds["amplitude"] * 0.5 * (w / rn) ** 3 * (3 * (m @ rh) * rh - m),
                                   atol=1e-12)
    dr = E.resolve({"drift": {"amplitude": 0.0, "step": 0.0, "wobble": 0.0, "wander_seed": 5}},
                   sp.n, sp)["drift"]
    t = np.linspace(0, 1, 5001)
    wnd = E.wander(dr, t)
    assert abs(wnd.std(axis=0).mean() / dr["wander"] - 1.0) < 0.35
    # smooth on the scale of its correlation time, not white
    lag = int(0.1 * dr["wander_time"] * 5000)
    corr = np.mean([np.corrcoef(wnd[:-lag, j], wnd[lag:, j])[0, 1] for j in range(3)])
    assert corr > 0.9
    np.testing.assert_allclose(E.sensor(np.zeros((5001, 3)), {"drift": dr}, t), wnd, atol=1e-12)


def test_relaxing_precurvature_row_by_row():
    """The precurvature relaxes with the bending cycles (turns relative to the tube around it,
    counted along the rows): each row equals the unrelaxed form with its scale times
    1 - relax (1 - exp(-turns / relax_turns)), computed here per row (within the generator's
    grouping of rows into 32 levels of the relaxation)."""
    sp = load_spec("seed1")
    n = sp.n
    d = generate("seed1", "sweeps", n=80, effects={}, noise_mm=0.0, seed=4, sweeps=2)
    pc = E.resolve({"precurvature": {}}, n, sp)["precurvature"]
    got, _, _ = truth(sp, d.q, {"precurvature": pc}, sweep=d.sweep)
    a = d.q[:, :n]
    rel = np.c_[a[:, :-1] - a[:, 1:], a[:, -1]]
    turns = np.r_[np.zeros((1, n)), np.cumsum(np.abs(np.diff(rel, axis=0)), axis=0)] / (2 * np.pi)
    f = 1.0 - np.array(pc["relax"]) * (1.0 - np.exp(-turns / pc["relax_turns"]))
    assert f.min() < 0.98                          # the rows relax measurably
    for i in range(0, 80, 7):
        ref, _, _ = truth(sp, d.q[i:i + 1], {"precurvature": {**pc, "scale": list(np.array(pc["scale"]) * f[i]),
                                                               "relax": 0.0}})
        assert np.linalg.norm(ref[0] - got[i]) < 0.1, (i, ref[0], got[i])
    settled, _, _ = truth(sp, d.q[:3], {"precurvature": pc})         # no row order: relaxed
    ref, _, _ = truth(sp, d.q[:3], {"precurvature": {**pc, "relax": 0.0, "scale":
                                                     list(np.array(pc["scale"]) * (1 - np.array(pc["relax"])))}})
    np.testing.assert_allclose(settled, ref, atol=1e-9)


def test_clearance_crossing_is_a_saturated_wave():
    """The tilt's first harmonic and the jump become tanh(cos(phi - phase) / snap) / tanh(1 /
    snap): +-1 over most of the turn, a quick crossing where cos = 0."""
    x = np.linspace(-math.pi, math.pi, 721)
    w = E.snap_wave(x, 0.15)
    assert np.allclose(w[np.abs(np.cos(x)) > 0.5], np.sign(np.cos(x[np.abs(np.cos(x)) > 0.5])), atol=0.04)
    np.testing.assert_allclose(E.snap_wave(x, 0.0), np.cos(x))
    ev = E.clearance_fn({"amplitude": 0.07, "phase_deg": 205.0, "harmonics": [0.5, 0.4, 0.18],
                         "lean": 0.007, "jump": 0.15, "snap": 0.15})
    tilt, lean, jb, ja = ev(x, 0)
    ph = math.radians(205.0)
    np.testing.assert_allclose(tilt, 0.07 * (0.5 + 0.4 * E.snap_wave(x - ph, 0.15)
                                             + 0.18 * np.cos(2 * (x - ph))), atol=1e-15)
    np.testing.assert_allclose(jb, 0.15 * E.snap_wave(x - ph, 0.15), atol=1e-15)
