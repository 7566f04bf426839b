"""generate / backbones / generate_study: foreign measurements (see package docstring)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from . import designs as D
from . import effects as E
from . import mechanics as M
from .robot import Spec, load_spec


@dataclass
class ForeignData:
    q: np.ndarray                 # (N, 2n) commanded configurations
    tip: np.ndarray               # (N, 3) measured tips (effects + noise), mm
    time: np.ndarray              # (N,) s
    sweep: np.ndarray             # (N,) str
    points: np.ndarray | None     # (N, M, 3) or None
    direction: np.ndarray         # (N, 2n) int8
    effects: dict                 # parameters actually used
    robot: str
    tip_clean: np.ndarray | None = None      # (N, 3) noise-free tips (for tests)
    info: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return self.q.shape[0]

    @property
    def n(self) -> int:
        return self.q.shape[1] // 2

    def subset(self, mask) -> ForeignData:
        m = np.asarray(mask)
        if m.dtype == bool:
            m = np.flatnonzero(m)
        return ForeignData(self.q[m], self.tip[m], self.time[m], self.sweep[m],
                           None if self.points is None else self.points[m], self.direction[m],
                           self.effects, self.robot,
                           None if self.tip_clean is None else self.tip_clean[m], dict(self.info))

    def header(self) -> list[str]:
        n = self.n
        h = [f"alpha{i + 1}" for i in range(n)] + [f"beta{i + 1}" for i in range(n)]
        h += ["tip_x", "tip_y", "tip_z", "time", "sweep"]
        if self.points is not None:
            for j in range(self.points.shape[1]):
                h += [f"p{j + 1}_x", f"p{j + 1}_y", f"p{j + 1}_z"]
        return h

    def write_csv(self, path) -> None:
        """DESIGN.md measured CSV: alpha..,beta..,tip_x,tip_y,tip_z,time,sweep[,p1_x..pM_z]
        (rad, mm, s). Written to a temporary file and renamed (never half-written)."""
        import os
        lines = [",".join(self.header())]
        for i in range(len(self)):
            vals = [repr(float(v)) for v in self.q[i]] + [repr(float(v)) for v in self.tip[i]]
            vals += [repr(float(self.time[i])), str(self.sweep[i])]
            if self.points is not None:
                vals += [repr(float(v)) for v in self.points[i].ravel()]
            lines.append(",".join(vals))
        tmp = str(path) + ".tmp"
        with open(tmp, "w", encoding="utf-8") as f:
            f.write("\n".join(lines) + "\n")
        os.replace(tmp, path)


def read_csv(path) -> dict:
    """Read a measured CSV back (plain parser; returns columns as arrays)."""
    with open(path, encoding="utf-8") as f:
        rows = [ln.rstrip("\n").split(",") for ln in f if ln.strip()]
    header, body = rows[0], rows[1:]
    cols = {}
    for j, h in enumerate(header):
        vals = [r[j] for r in body]
        cols[h] = np.array(vals) if h == "sweep" else np.array([float(v) for v in vals])
    return cols


# ----------------------------------------------------------------------------- the truth
def _held_curved(spec: Spec, q: np.ndarray) -> np.ndarray:
    """(N, n) fraction of each tube's curved section held inside the tubes around it: proximal
    of the distal end of the next outer tube (of the base plane, for the outermost tube), where
    the pre-curved section is pressed against the wall around it (the contact that makes the
    friction torque). Innermost tube first."""
    n = spec.n
    beta = q[:, n:]
    held_to = np.concatenate([np.maximum(beta[:, 1:] + spec.L[None, 1:], 0.0),
                              np.zeros((len(q), 1))], axis=1)
    start = beta + spec.straight[None, :]                   # proximal end of the curved section
    return np.clip(held_to - start, 0.0, spec.curved[None, :]) / spec.curved[None, :]


def _contact_moment(spec: Spec, q: np.ndarray, moment: float) -> np.ndarray:
    """(N, n) factor of the friction lags from the contact force (torque-dependent friction):
    tube i presses on the tube around it with a force that grows with their curvature mismatch
    |kappa_i e(alpha_i) - kappa_o e(alpha_o)|, r in [0, 1] as a fraction of kappa_i + kappa_o;
    factor 1 + moment (2 r - 1) (1 for the outermost tube, which has no tube around it)."""
    n = spec.n
    out = np.ones((q.shape[0], n))
    if not moment or n < 2:
        return out
    a = q[:, :n]
    k = spec.kappa
    for i in range(n - 1):
        phi = a[:, i] - a[:, i + 1]
        mis = np.sqrt(np.maximum(k[i] ** 2 + k[i + 1] ** 2 - 2 * k[i] * k[i + 1] * np.cos(phi), 0.0))
        r = mis / max(k[i] + k[i + 1], 1e-12)
        out[:, i] = 1.0 + moment * (2.0 * r - 1.0)
    return out


def _alpha_lag(eff, q, n, direction, sweep, spec=None):
    """Friction lag forms acting on the transmitted joint values: returns q_eff."""
    q = q.copy()
    fr = eff.get("friction")
    if fr is None or fr["form"] == "end_moment" or direction is None:
        return q
    d = direction.astype(float)
    lag = E._per_tube(fr["lag"], n, "lag")
    growth = E._per_tube(fr.get("growth", 0.0), n, "growth")
    if spec is not None:
        c = lag[None, :] * (1.0 + growth[None, :] * _held_curved(spec, q))
        c = c * _contact_moment(spec, q, float(fr.get("moment", 0.0) or 0.0))
    else:
        c = np.broadcast_to(lag[None, :], (q.shape[0], n))
    if fr["form"] == "coulomb_lag":
        q[:, :n] -= c * d[:, :n]
        q[:, n:] -= E._per_tube(fr.get("beta_lag", 0.0), n, "beta_lag") * d[:, n:]
        return q
    if fr["form"] == "stick_slip":
        return _stick_slip(q, n, c, float(fr["kinetic"]), d, sweep)
    # presliding: history along each sweep when rows are in motion order, else developed lag
    ang = float(fr["angle"])
    if sweep is None:
        q[:, :n] -= c * d[:, :n]
        return q
    z = np.zeros(n)
    a0 = q[:, :n].copy()
    last = np.zeros(n)
    for i in range(q.shape[0]):
        if i == 0 or sweep[i] != sweep[i - 1]:
            z = np.zeros(n)
            last = np.zeros(n)
        else:
            da = a0[i] - a0[i - 1]
            sg = np.sign(da)
            last = np.where(sg != 0, sg, last)
            ci = c[i]
            with np.errstate(invalid="ignore", divide="ignore"):
                w = np.where(ci > 0, 1.0 - z * sg / np.where(ci > 0, ci, 1.0), 0.0)
            # the held lag cannot exceed the breakaway limit: where the limit c (it depends on
            # the configuration) dropped below |z| while moving on, the contact slides until
            # the lag is at the limit (w = 0). Without this, w < 0 makes the update below run
            # away within a finite motion (w / (1 + w |dalpha| / angle) has a pole), turning a
            # few-hundredths-rad lag into radians.
            w = np.maximum(w, 0.0)
            # Dahl exponent 2: dw/d|alpha| = -w^2 / angle  ->  w / (1 + w |dalpha| / angle)
            w = w / (1.0 + w * np.abs(da) / ang)
            z = np.where(sg != 0, ci * sg * (1.0 - w), z)
        q[i, :n] -= z
    return q


def _stick_slip(q, n, c, kinetic, d, sweep):
    """Stick-slip lags along the rows (one motion per sweep, each sweep starting settled): each
    tube's transmitted angle sticks while the lag e (commanded - actual) stays within the static
    limit c (per row: the torque-dependent ``lag (1 + growth h)``); where the command pushes it
    beyond, the tube slips until the lag is the kinetic ``kinetic c``, sticks again, and so on
    (a sawtooth over the commanded travel). Without row order the mean lag (1 + kinetic) c / 2
    against the direction of motion."""
    if not np.any(c > 0.0):
        return q
    if sweep is None:
        q[:, :n] -= 0.5 * (1.0 + kinetic) * c * d[:, :n]
        return q
    a0 = q[:, :n].copy()
    e = np.zeros(n)
    for i in range(q.shape[0]):
        if i == 0 or sweep[i] != sweep[i - 1]:
            e = np.zeros(n)
        else:
            da = a0[i] - a0[i - 1]
            sg = np.sign(da)
            cs, ck = c[i], kinetic * c[i]
            e1 = e + da
            over = sg * e1 - cs
            slip = (sg != 0) & (over > 0)
            width = np.maximum(cs - ck, 1e-12)
            e = np.where(slip, sg * (ck + np.mod(over, width)), e1)
        q[i, :n] -= e
    return q


def _joint_space(eff, q, n, direction, sweep, spec):
    """The joints the tubes really reach: joint offsets (encoder, gear and lead-screw errors)
    and friction lags."""
    if "joint_offset" in eff:
        jo = eff["joint_offset"]
        q = q.copy()
        a = q[:, :n]
        amp = E._per_tube(jo.get("periodic", 0.0), n, "periodic")
        ph = E._per_tube(jo.get("periodic_phase", 0.0), n, "periodic_phase")
        gear = E._per_tube(jo.get("gear", 0.0), n, "gear")
        gph = E._per_tube(jo.get("gear_phase", 0.0), n, "gear_phase")
        order = float(jo.get("gear_order", 3))
        q[:, :n] = (a + E._per_tube(jo["alpha"], n, "alpha") + amp * np.sin(a + ph)
                    + gear * np.sin(order * a + gph))
        bs = E._per_tube(jo.get("beta_scale", 0.0), n, "beta_scale")
        q[:, n:] = q[:, n:] * (1.0 + bs) + E._per_tube(jo["beta"], n, "beta")
        q = q + _rehome(jo, n, sweep, q.shape[0])
    return _alpha_lag(eff, q, n, direction, sweep, spec)


def _rehome(jo: dict, n: int, sweep, B: int) -> np.ndarray:
    """(B, 2n) the joint offsets' part that changes from sweep to sweep: the robot homes its
    joints before every sweep and the home switches repeat only to ``rehome`` = (rad, mm)
    (standard deviations, per joint, drawn from ``rehome_seed`` and the sweep's position in the
    recording). Without sweeps (rows as independent configurations): none."""
    sd = np.broadcast_to(np.asarray(jo.get("rehome", 0.0) or 0.0, float), (2,))
    out = np.zeros((B, 2 * n))
    if sweep is None or not np.any(sd != 0.0):
        return out
    sw = np.asarray(sweep)
    starts = np.r_[True, sw[1:] != sw[:-1]]
    k = np.cumsum(starts) - 1                                   # sweep index of each row
    rng = np.random.default_rng([int(jo.get("rehome_seed") or 0), 4242])
    draw = rng.normal(size=(int(k.max()) + 1, 2 * n)) * np.repeat(sd, n)[None, :]
    return draw[k]


#: levels of the relaxation's progress (0..1) within which rows share one mechanics solve
AGING_LEVELS = 32


def _aging(spec: Spec, eff: dict, q: np.ndarray, sweep):
    """Per-row factors (N, n) on the precurvature as it relaxes with bending cycles and the
    relaxation's progress (N, n), or None when it is off. Rows in order (``sweep`` given): the
    cycles of tube i are its accumulated rotation relative to the tube around it (the base, for
    the outermost) in turns, counted over all rows in order (the robot also moves between
    sweeps). Without order: the settled state (fully relaxed)."""
    n = spec.n
    pc = eff.get("precurvature")
    relax = E._per_tube(pc.get("relax", 0.0) or 0.0, n, "relax") if pc else np.zeros(n)
    if not np.any(relax != 0.0):
        return None
    B = q.shape[0]
    if sweep is None:
        progress = np.ones((B, n))
    else:
        a = q[:, :n]
        rel = a - np.concatenate([a[:, 1:], np.zeros((B, 1))], axis=1)
        turns = np.concatenate([np.zeros((1, n)),
                                np.cumsum(np.abs(np.diff(rel, axis=0)), axis=0)]) / (2 * np.pi)
        progress = 1.0 - np.exp(-turns / float(pc["relax_turns"]))
    return 1.0 - relax * progress, progress


def truth(spec: Spec, q: np.ndarray, eff: dict, direction=None, sweep=None, points: int = 0,
          h_max: float = 10.0, tfrac=None):
    """Noise-free tips (N,3) and points (N,M,3) or None in the robot base frame (before tracker
    effects), and ok (N,) (mechanics converged). ``tfrac`` (N,): the fraction of the recording
    time of each row (unused by the mechanics; kept for time-dependent forms)."""
    q = np.atleast_2d(np.asarray(q, float))
    n = spec.n
    eff = E.resolve(eff, n, spec)       # idempotent on resolved parameters; {} -> defaults
    q_cmd = q
    q = _joint_space(eff, q, n, direction, sweep, spec)
    aging = _aging(spec, eff, q_cmd, sweep)
    if aging is None:
        return _mechanics(spec, q, eff, direction, points, h_max)
    kf, progress = aging
    _, group = np.unique(np.round(progress * AGING_LEVELS), axis=0, return_inverse=True)
    group = group.ravel()
    B = q.shape[0]
    tip = np.full((B, 3), np.nan)
    pts = np.full((B, points, 3), np.nan) if points else None
    ok = np.zeros(B, bool)
    for g in np.unique(group):
        idx = np.flatnonzero(group == g)
        t, p, o = _mechanics(spec, q[idx], eff, None if direction is None else direction[idx],
                             points, h_max, kf[idx].mean(0))
        tip[idx], ok[idx] = t, o
        if pts is not None:
            pts[idx] = p
    return tip, pts, ok


#: fixed-point iterations of the drive couplings' play (damped by half)
PLAY_ITERATIONS = 14
#: fixed-point iterations of the soft wall's contact force (damped by half)
WALL_ITERATIONS = 8


def _mechanics(spec: Spec, q: np.ndarray, eff: dict, direction, points: int, h_max: float,
               kscale=None):
    """The truth's mechanics for joint values ``q`` the tubes really reach (see :func:`truth`);
    ``kscale`` (n,): an extra factor on the precurvature (its relaxation)."""
    n = spec.n
    sp = spec if kscale is None else spec.scaled(kscale, None)
    ramp, ei_curved, softening, twist, kink = None, None, None, None, None
    if "precurvature" in eff or "stiffness" in eff:
        pc = eff.get("precurvature")
        st = eff.get("stiffness")
        sp = sp.scaled(E._per_tube(pc["scale"], n, "scale") if pc else None,
                       E._per_tube(st["scale"], n, "scale") if st else None)
        if pc is not None:
            ramp = E._per_tube(pc.get("ramp", 0.0), n, "ramp")
            twist = E._per_tube(pc.get("twist", 0.0) or 0.0, n, "twist")
            if np.any(E._per_tube(pc.get("kink", 0.0) or 0.0, n, "kink") != 0.0):
                kink = (E._per_tube(pc["kink"], n, "kink"), float(pc["kink_at"]),
                        float(pc["kink_length"]))
        if st is not None:
            ei_curved = E._per_tube(st.get("curved", 1.0), n, "curved")
            if np.any(E._per_tube(st.get("soften", 0.0) or 0.0, n, "soften") != 0.0):
                softening = {"onset": st["soften_onset"], "width": st["soften_width"],
                             "drop": E._per_tube(st["soften"], n, "soften")}
    torsion = "torsion" in eff
    gj = np.ones(n)
    coupling = None
    if torsion:
        gj = gj * E._per_tube(eff["torsion"].get("gj_scale", 1.0), n, "gj_scale")
        coupling = E._per_tube(eff["torsion"].get("coupling", 0.0), n, "coupling")
    if "stiffness" in eff:
        # GJ follows E (the scale), then its own factor; EI on the curved section is separate
        gj = gj * E._per_tube(eff["stiffness"].get("torsion", 1.0), n, "torsion")
    if torsion and np.any(gj != 1.0):
        from dataclasses import replace
        # scale GJ alone: G = E/(2(1+nu)) -> nu' with G' = g G
        sp = replace(sp, nu=(1.0 + sp.nu) / gj - 1.0)
    clear = E.clearance_fn(eff["clearance"]) if "clearance" in eff else None
    mu, rel, contact = 0.0, None, 0.0
    fr = eff.get("friction")
    if fr is not None and fr["form"] == "end_moment" and direction is not None and n > 1:
        mu = float(fr["mu"])
        contact = float(fr.get("contact", 0.0))
        da = direction[:, :n].astype(float)
        rel = np.sign(da[:, :-1] - da[:, 1:])
    load = eff.get("load")
    if load is not None and not np.any(np.asarray(load.get("gravity") or [0.0]) != 0) \
            and not np.any(np.asarray(load.get("tip_force") or [0.0]) != 0):
        load = None                      # no load at all: the unloaded model exactly
    alpha, beta = q[:, :n], q[:, n:]
    if torsion or load is not None:
        grav, F, extra = None, None, None
        if load is not None:
            if load.get("density") is not None:
                from dataclasses import replace
                sp = replace(sp, density=E._per_tube(load["density"], n, "density"))
            grav = load.get("gravity")
            F = load.get("tip_force")
            if load.get("lumen_density"):
                extra = np.zeros(n)
                extra[0] = float(load["lumen_density"]) * 1e-9 * np.pi / 4 * sp.id[0] ** 2 * 9.81
        kw = dict(torsion=torsion, gravity=grav, clearance=clear, friction_mu=mu, rel_dir=rel,
                  h_max=h_max, friction_contact=contact, ramp=ramp, ei_curved=ei_curved,
                  coupling=coupling, extra_weight=extra, softening=softening, twist=twist,
                  kink=kink)
        tor = eff.get("torsion") or {}
        play = E._per_tube(tor.get("play", 0.0) or 0.0, n, "play") if torsion else np.zeros(n)
        if np.any(play != 0.0):
            # the drive couplings' play (an elastomer jaw coupling): the tube's base turns
            # within it by play tanh(T / play_torque) in the direction that relieves the
            # torque T = GJ u_z(0) it carries; a damped fixed point in the base angles
            a0 = alpha
            T0 = float(tor["play_torque"])
            for _ in range(PLAY_ITERATIONS):
                bb = _loaded(sp, alpha, beta, F, load, kw)
                T = sp.GJ[None, :] * bb.info["x"][:, :n]
                alpha = 0.5 * alpha + 0.5 * (a0 + play * np.tanh(T / T0))
        bb = _loaded(sp, alpha, beta, F, load, kw)
        ok = bb.ok
    else:
        bb = M.rigid(sp, alpha, beta, clearance=clear, friction_mu=mu, rel_dir=rel,
                     friction_contact=contact, ramp=ramp, ei_curved=ei_curved, softening=softening,
                     twist=twist, kink=kink)
        ok = np.ones(q.shape[0], bool)
    tip = bb.tip()
    pts = bb.points(points) if points else None
    rg = eff.get("registration")
    if rg is not None and np.any(np.asarray(rg.get("sensor", 0.0) or 0.0, float) != 0.0):
        tip = tip + sensor_offset(bb, n, np.asarray(rg["sensor"], float))
    c_b = float(load.get("base_compliance") or 0.0) if load is not None else 0.0
    if c_b:
        # a compliant mount: the whole robot turns about the base origin by c_b times the
        # bending moment the loads put on it there (m(0), base frame, its x and y components)
        m0 = bb.info["m0"]
        rv = c_b * np.c_[m0[:, 0], m0[:, 1], np.zeros(len(m0))]
        Rb = np.stack([E.rotation_matrix(r) for r in rv])
        tip = np.einsum("bij,bj->bi", Rb, tip)
        if pts is not None:
            pts = np.einsum("bij,bmj->bmi", Rb, pts)
    return tip, pts, ok


def sensor_offset(bb, n: int, o: np.ndarray) -> np.ndarray:
    """(B, 3) where the tracker's coil sits relative to the tip: ``o`` (mm) in the innermost
    tube's material frame at its tip (x toward its precurvature's bending direction, z along
    the tangent), R Rz(psi_1) o with R the backbone frame at the tip."""
    if bb.kind == "rigid":
        R = bb.R[:, -1]
        psi = bb.alpha_eff[:, 0]
    else:
        X = bb.info["state_end"]
        R = X[:, 2 * n + 3:2 * n + 12].reshape(-1, 3, 3)
        psi = X[:, 0]
    c, s = np.cos(psi), np.sin(psi)
    local = np.stack([c * o[0] - s * o[1], s * o[0] + c * o[1], np.full_like(c, o[2])], axis=1)
    return np.einsum("bij,bj->bi", R, local)


#: fixed-point iterations of the tether force (contraction ~ k L^3 / 3 EI ~ 0.1 on seed1)
TETHER_ITERATIONS = 4


def _loaded(sp, alpha, beta, F, load, kw):
    """The Cosserat solve with the tip forces of the tether and the soft wall (fixed points in
    the tip position)."""
    bb = M.cosserat(sp, alpha, beta, tip_force=F, **kw)
    k_t = float(load.get("tether") or 0.0) if load is not None else 0.0
    k_w = float(load.get("wall") or 0.0) if load is not None else 0.0
    if not (k_t or k_w):
        return bb
    F0 = np.zeros(3) if F is None else np.asarray(F, float)
    if not k_w:
        # a tether (the tracker sensor's cable, a tissue attachment) pulls the tip toward an
        # anchor: F_t = k (anchor - tip), fixed point in the tip position (k is small)
        anchor = np.asarray(load["anchor"], float)
        for _ in range(TETHER_ITERATIONS):
            Ft = F0[None, :] + k_t * (anchor[None, :] - bb.tip())
            bb = M.cosserat(sp, alpha, beta, tip_force=Ft, **kw)
        return bb
    # a soft wall (tissue the tip presses on): where the tip is beyond the plane
    # {p: nrm . p = at} it pushes back along nrm with k_w times the depth; damped by half
    nrm = E._unit(load["wall_normal"])
    at = float(load["wall_at"])
    anchor = np.asarray(load["anchor"], float)
    tip = bb.tip()
    Fw = np.zeros((len(tip), 3))
    for _ in range(WALL_ITERATIONS):
        depth = np.maximum(at - tip @ nrm, 0.0)
        Fw = 0.5 * Fw + 0.5 * k_w * depth[:, None] * nrm[None, :]
        Ft = F0[None, :] + k_t * (anchor[None, :] - tip) + Fw
        bb = M.cosserat(sp, alpha, beta, tip_force=Ft, **kw)
        tip = bb.tip()
    return bb


def _tfrac(time):
    t = np.asarray(time, float)
    if t.size == 0:
        return t
    span = t.max() - t.min()
    return (t - t.min()) / (span if span > 0 else 1.0)


# ----------------------------------------------------------------------------- public API
def generate(robot="seed1", design="sweeps", n=1000, effects=None, noise_mm=0.1, seed=0,
             points=0, sweeps=None) -> ForeignData:
    """Foreign measurements; see /work/coord/GENERATOR_API.md. Rows whose mechanics did not
    converge are dropped (their count is in ``info['dropped']``; none on the shipped robots
    in our runs)."""
    spec = load_spec(robot)
    rng = np.random.default_rng(seed)
    eff = E.resolve(effects, spec.n, spec)
    q, t, sw = D.design(spec, design, int(n), rng, sweeps=sweeps)
    direction = D.directions(q, sw)
    tf = _tfrac(t)
    for name, key in (("drift", "wander_seed"), ("joint_offset", "rehome_seed")):
        if name in eff and eff[name].get(key) is None:      # drawn with the data
            eff[name][key] = int(np.random.SeedSequence(seed).generate_state(1)[0])
    tip, pts, ok = truth(spec, q, eff, direction=direction, sweep=sw, points=points, tfrac=tf)
    tip = E.sensor(tip, eff, tf, q, spec)
    if pts is not None:
        pts = E.sensor(pts, eff, tf, q, spec)
    nrng = np.random.default_rng([seed, 7919])
    tip_meas = tip + nrng.normal(0.0, noise_mm, tip.shape) if noise_mm > 0 else tip.copy()
    if pts is not None and noise_mm > 0:
        pts = pts + nrng.normal(0.0, noise_mm, pts.shape)
    data = ForeignData(q, tip_meas, t, sw, pts, direction, eff, spec.name, tip_clean=tip,
                       info={"design": design, "seed": seed, "noise_mm": noise_mm,
                             "dropped": int(np.sum(~ok))})
    return data.subset(ok) if not ok.all() else data


def backbones(robot, q, effects=None, points=20, direction=None) -> np.ndarray:
    """Noise-free backbones (N, points, 3), evenly spaced in arc length from s = 0 to the tip,
    with the given effects (mechanics effects; registration and distortion map them into the
    sensor frame like measured points; drift needs time and is not applied). Friction uses
    ``direction`` (N, 2n) in {-1, 0, +1} as a pure function of (q, direction) (presliding:
    fully developed lag); direction=None: no friction direction (friction inactive)."""
    spec = load_spec(robot)
    eff = E.resolve(effects, spec.n, spec)
    q = np.atleast_2d(np.asarray(q, float))
    d = None if direction is None else np.asarray(direction)
    _, pts, ok = truth(spec, q, eff, direction=d, sweep=None, points=max(int(points), 2))
    pts = E.sensor(pts, eff, None, q, spec)
    if not ok.all():
        pts[~ok] = np.nan
    return pts


STUDY_EFFECTS = {
    "torsion": {"gj_scale": 6.0, "coupling": [40.0, 20.0], "play": 0.0},
    "clearance": {"amplitude": 0.15, "phase_deg": 205.0, "harmonics": [0.5, 0.32, 0.18],
                  "lean": 0.015, "jump": "gap", "snap": 0.0},
    "friction": {"form": "end_moment", "mu": 0.06, "contact": 12.0},
}
# The generator's own forms (outside ctrplan's families, tests/foreign/effects.py): clearance with
# a second harmonic, a sideways lean and a jump within the gap; end-moment friction growing with
# the contact length; torsion with compliant drive couplings. Magnitudes chosen so that the rigid
# ("traditional") model errs like in the study's Table 2 (traditional mean / max: feed 4.95 /
# 9.7, inner rotation 4.2 / 5.9, outer rotation 6.7 / 12.1 mm).
# gj_scale 6: the printed nylon tubes are torsionally much stiffer relative to bending than the
# solid-tube formula GJ = E J / (1 + nu) gives (diamond cut-outs weaken bending most); with
# gj_scale 1 torsion alone moves the tip by ~15 mm on these designs, far more than the study saw.
STUDY_EXPERIMENTS = ("feed", "inner_rotation", "outer_rotation")


def generate_study(seed=0, noise_mm=0.1, n_per_experiment=200, points=0) -> dict:
    """The Sensors 2023 study's three experiments on two_tube_nylon, with clearance (peak at a
    relative rotation of 205 deg), end-moment friction (with its dtheta through the compliant
    torsion) and torsion hidden. Returns {"feed", "inner_rotation", "outer_rotation"} ->
    ForeignData."""
    out = {}
    for k, name in enumerate(STUDY_EXPERIMENTS):
        out[name] = generate("two_tube_nylon", name, n=n_per_experiment, effects=STUDY_EFFECTS,
                             noise_mm=noise_mm, seed=[seed, k] if not isinstance(seed, list) else seed + [k],
                             points=points)
    return out
