"""Own CTR mechanics for the foreign generator, written from the equations (no ctrplan code).

Frames and conventions (DESIGN.md): base frame at the constraint plane, +z insertion, at
alpha_i = 0 tube i's precurvature (0, kappa_i, 0) in its own frame bends it toward +x,
p' = R e_z, R' = R [u]x.

The backbone frame R used here is a Bishop (twist-free) frame: u = (u_x, u_y, 0) and tube i's
material frame is R Rz(psi_i), so psi_i' = u_iz (tube i's torsion) and R(0) = I.

Rigid model (torsionally rigid tubes, psi_i = alpha_i): in each section between break points
(curved-section starts and tube ends) the curvature is the stiffness-weighted mean of the rotated
precurvatures, u_xy = sum EI_i Rz(alpha_i) uhat_i / sum EI_i, integrated as exact arcs.

Torsionally compliant model (Rucker / Dupont) with external loads: states psi_i, u_iz, p, R, and
the internal moment m (base frame). The internal force is known in closed form because the loads
are a tip force F and gravity (weight per length w_i of every tube present at s):
    n(s) = F + sum_i w_i max(0, e_i - s)     (e_i: tube i's distal end)
    m'   = -(R e_z) x n(s)
    u_xy = (sum EI_i)^-1 [ (R^T m)_xy + sum EI_i Rz(psi_i) uhat_i ]
    u_iz' = (EI_i / GJ_i) (u_ix uhat_iy - u_iy uhat_ix),  u_i = Rz(psi_i)^T u
Boundary values: psi_i(0) = alpha_i - beta_i u_iz(0) (straight transmission behind the plane),
u_iz(e_i) = T_i / GJ_i (T_i: a friction torque at the tube end, else 0), m(L) = 0 (no tip moment);
(R^T m)_z(0) = sum GJ_i u_iz(0). Unknowns u_iz(0) (and m_x(0), m_y(0) with loads) are found by
Newton with a finite-difference Jacobian, all configurations at once (numpy, RK4 with steps
aligned to each configuration's break points). Without torsion but with loads the tubes keep
psi_i = alpha_i and the unknown is m(0) (3 components).

Point discontinuities at the end of an outer tube j (node of e_j), used by the effects:
  * clearance: the frame turns by delta about the axis R Rz(psi_in) e_y (the tangent tilts toward
    the inner tube's bending direction R Rz(psi_in) e_x), psi_in the next inner tube's angle;
  * friction (end moment): a torque T_j = mu * sign * |M_j| on tube j (its end condition) and -T_j
    on the tube inside it (a jump in its u_z); |M_j| is tube j's bending moment at its end.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .robot import Spec


# ----------------------------------------------------------------------------- geometry
@dataclass
class Geom:
    bp: np.ndarray        # (B, S+1) sorted break points
    kappa: np.ndarray     # (B, S, n) precurvature in each segment (0 where straight/absent)
    present: np.ndarray   # (B, S, n) bool
    endnode: np.ndarray   # (B, n) node index (1..S) of each tube's end
    ends: np.ndarray      # (B, n) e_i
    beta: np.ndarray      # (B, n)
    eif: np.ndarray | None = None   # (B, S, n) factor on each tube's EI in each segment
    kphase: np.ndarray | None = None  # (B, S, n) angle of the precurvature in the tube's frame

    def take(self, idx):
        return Geom(self.bp[idx], self.kappa[idx], self.present[idx], self.endnode[idx],
                    self.ends[idx], self.beta[idx], None if self.eif is None else self.eif[idx],
                    None if self.kphase is None else self.kphase[idx])

    def EIp(self, spec, j):
        """(B, n) bending stiffness of each tube present in segment j (0 where absent)."""
        EI = spec.EI[None, :] if self.eif is None else spec.EI[None, :] * self.eif[:, j]
        return np.where(self.present[:, j], EI, 0.0)


def geometry(spec: Spec, beta: np.ndarray, ramp=None, steps: int = 8, ei_curved=None,
             twist=None, kink=None) -> Geom:
    """Break points and per-segment data. Optional effects of the generator:

    ramp (n,): precurvature varying along each tube's curved section,
    kappa_i(s) = kappa_i (1 + ramp_i (s_c - 1/2)), s_c in [0, 1] the fraction of the curved
    section (0 at its proximal start), held piecewise constant over ``steps`` equal sub-sections
    (value at each sub-section's middle; extra break points).
    ei_curved (n,): factor on tube i's EI over its curved (shape-set) section.
    twist (n,): the precurvature's plane turns along the curved section (a helix, not a planar
    arc): in the tube's frame the precurvature is kappa_i (-sin th, cos th, 0) with th =
    twist_i (s_c - 1/2), on the same sub-sections as the ramp.
    kink (angles (n,) rad, at, length mm): a concentrated bend set into each curved section
    (the shape-setting fixture's joint): over ``length`` mm centred at the fraction ``at`` of
    the curved section the precurvature is larger by angle_i / length (extra break points)."""
    B, n = beta.shape
    e = np.maximum(beta + spec.L, 0.0)
    cst = np.minimum(np.maximum(beta + spec.straight, 0.0), e)
    use_ramp = ramp is not None and np.any(np.asarray(ramp, float) != 0.0)
    use_twist = twist is not None and np.any(np.asarray(twist, float) != 0.0)
    use_kink = kink is not None and np.any(np.asarray(kink[0], float) != 0.0)
    extra = np.zeros((B, 0))
    if use_ramp or use_twist:
        f = np.arange(1, steps) / steps
        c0 = beta + spec.straight                                      # (B, n) curved start
        extra = c0[:, :, None] + f[None, None, :] * spec.curved[None, :, None]
        extra = np.clip(extra, 0.0, e[:, :, None]).reshape(B, -1)
    if use_kink:
        k_ang = np.asarray(kink[0], float)
        k_len = float(kink[2])
        k0 = beta + spec.straight + float(kink[1]) * spec.curved - 0.5 * k_len       # (B, n)
        k1 = k0 + k_len
        extra = np.concatenate([extra, np.clip(k0, 0.0, e), np.clip(k1, 0.0, e)], axis=1)
    raw = np.concatenate([np.zeros((B, 1)), cst, e, extra], axis=1)
    order = np.argsort(raw, axis=1, kind="stable")
    bp = np.take_along_axis(raw, order, axis=1)
    inv = np.argsort(order, axis=1, kind="stable")                    # position of each raw entry
    endnode = inv[:, 1 + n:1 + 2 * n]
    mid = 0.5 * (bp[:, 1:] + bp[:, :-1])                              # (B, S)
    present = mid[:, :, None] < e[:, None, :]
    curved = present & (mid[:, :, None] >= cst[:, None, :])
    kap = np.broadcast_to(spec.kappa[None, None, :], curved.shape)
    kphase = None
    if use_ramp or use_twist:
        sc = (mid[:, :, None] - (beta + spec.straight)[:, None, :]) / spec.curved[None, None, :]
        k = np.clip(np.floor(sc * steps), 0, steps - 1)
        sc_mid = (k + 0.5) / steps
        if use_ramp:
            kap = kap * (1.0 + np.asarray(ramp, float)[None, None, :] * (sc_mid - 0.5))
        if use_twist:
            kphase = np.where(curved, np.asarray(twist, float)[None, None, :] * (sc_mid - 0.5), 0.0)
    if use_kink:
        inside = (mid[:, :, None] >= k0[:, None, :]) & (mid[:, :, None] < k1[:, None, :])
        kap = kap + np.where(inside, k_ang[None, None, :] / k_len, 0.0)
    kappa = np.where(curved, kap, 0.0)
    eif = None
    if ei_curved is not None and np.any(np.asarray(ei_curved, float) != 1.0):
        eif = np.where(curved, np.asarray(ei_curved, float)[None, None, :], 1.0)
    return Geom(bp, kappa, present, endnode, e, beta, eif, kphase)


# ----------------------------------------------------------------------------- small helpers
def _rot_axis_angle(axis: np.ndarray, ang: np.ndarray) -> np.ndarray:
    """(B,3) unit axes, (B,) angles -> (B,3,3) rotation matrices (Rodrigues)."""
    x, y, z = axis[:, 0], axis[:, 1], axis[:, 2]
    K = np.zeros(axis.shape[:1] + (3, 3))
    K[:, 0, 1], K[:, 0, 2] = -z, y
    K[:, 1, 0], K[:, 1, 2] = z, -x
    K[:, 2, 0], K[:, 2, 1] = -y, x
    s, c = np.sin(ang)[:, None, None], np.cos(ang)[:, None, None]
    return np.eye(3)[None] + s * K + (1.0 - c) * (K @ K)


def _clearance_rot(psi_in: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """Body-frame rotation Rz(psi) Ry(delta) Rz(-psi): about (-sin psi, cos psi, 0)."""
    axis = np.stack([-np.sin(psi_in), np.cos(psi_in), np.zeros_like(psi_in)], axis=1)
    return _rot_axis_angle(axis, delta)


def _clearance_event(clearance, psi_in, phi, pair):
    """Body-frame rotation (B,3,3) and body-frame offset (B,3) where an outer tube ends.

    ``clearance(phi, pair)`` returns either the in-plane tilt delta (B,) (rad, about the inner
    tube's curvature axis a = (-sin psi, cos psi, 0), turning the tangent toward its bending
    direction b = (cos psi, sin psi, 0)) or a tuple (tilt_in, tilt_out, jump_b, jump_a): tilt_out
    (rad) about b (a sideways lean), and a lateral jump of the backbone (mm) along b and a."""
    out = clearance(phi, pair)
    B = psi_in.shape[0]
    if isinstance(out, tuple):
        t_in, t_out, j_b, j_a = (np.broadcast_to(np.asarray(v, float), (B,)) for v in out)
    else:
        t_in = np.asarray(out, float)
        t_out = j_b = j_a = np.zeros(B)
    c, s = np.cos(psi_in), np.sin(psi_in)
    z = np.zeros(B)
    a = np.stack([-s, c, z], axis=1)
    b = np.stack([c, s, z], axis=1)
    rv = t_in[:, None] * a + t_out[:, None] * b
    ang = np.linalg.norm(rv, axis=1)
    axis = np.where(ang[:, None] > 0, rv / np.where(ang > 0, ang, 1.0)[:, None], a)
    Q = _rot_axis_angle(axis, ang)
    off = j_b[:, None] * b + j_a[:, None] * a
    return Q, off


def _bend_xy(psi, kap, EIp):
    """sum EI_i Rz(psi_i) (0, kappa_i) -> (Sx, Sy), and sum EI_i over present tubes."""
    Sx = -np.sum(EIp * kap * np.sin(psi), axis=-1)
    Sy = np.sum(EIp * kap * np.cos(psi), axis=-1)
    return Sx, Sy, np.sum(EIp, axis=-1)


# ----------------------------------------------------------------------------- rigid, closed form
def _arc(ux, uy, h):
    """Exact arc of constant body curvature (ux, uy, 0) over length h.
    Returns body-frame displacement (B,3) and rotation (B,3,3)."""
    k = np.hypot(ux, uy)
    c1 = h * np.sinc(k * h / np.pi)                        # sin(kh)/k
    c2 = 0.5 * h * h * np.sinc(k * h / (2 * np.pi)) ** 2   # (1-cos(kh))/k^2
    # displacement: int_0^h Exp(s[u]) e3 ds = sin(kh)/k e3 + (1-cos(kh))/k^2 (u x e3),
    # u x e3 = (uy, -ux, 0) (u is perpendicular to e3)
    dp = np.stack([c2 * uy, -c2 * ux, c1], axis=1)
    K = np.zeros(ux.shape + (3, 3))
    K[:, 0, 2], K[:, 1, 2] = uy, -ux
    K[:, 2, 0], K[:, 2, 1] = -uy, ux
    Rj = np.eye(3)[None] + c1[:, None, None] * K + c2[:, None, None] * (K @ K)
    return dp, Rj


def end_torque(spec, g, o, M, mu, contact, rel):
    """Friction torque where outer tube o ends (N mm): T = s mu (|M| + contact M_c l_c / L_o),
    s = ``rel`` the direction of the relative rotation of the pair (inner minus outer), |M| the
    outer tube's bending moment there, M_c = EI_o EI_i / (EI_o + EI_i) |kappa_o - kappa_i| the
    moment scale of the pair's contact (i = o - 1; their curvature mismatch, nominal), l_c = the
    outer tube's exposed length (the contact length in front of the plane), L_o its length.
    ``contact`` 0 is the study's concentrated end moment."""
    T = np.abs(M)
    if contact:
        i = o - 1
        Mc = spec.EI[o] * spec.EI[i] / (spec.EI[o] + spec.EI[i]) * abs(spec.kappa[o] - spec.kappa[i])
        T = T + contact * Mc * g.ends[:, o] / spec.L[o]
    return mu * rel * T


#: damped fixed-point iterations of the superelastic softening (the strain depends on the EI)
SOFTEN_ITERATIONS = 30


def soften(spec: Spec, g: Geom, alpha, softening) -> None:
    """Superelastic softening (sets ``g.eif``): nitinol's stress-strain curve bends over into
    its plateau, so a tube's secant bending stiffness drops where its bending strain is large:
    EI_i -> EI_i (1 - drop_i / (1 + exp(-(eps - onset) / width))), eps = (od_i / 2) |u_i -
    kappa_i| the strain at its surface (u_i: the backbone curvature in the tube's frame, from
    the torsionally rigid shape), per segment; a damped fixed point (the strain depends on the
    stiffness). ``softening``: dict of per-tube ``onset`` and ``width`` (strain) and ``drop``."""
    n = spec.n
    onset = np.broadcast_to(np.asarray(softening["onset"], float), (n,))
    width = np.broadcast_to(np.asarray(softening["width"], float), (n,))
    drop = np.broadcast_to(np.asarray(softening["drop"], float), (n,))
    base = np.ones(g.kappa.shape) if g.eif is None else g.eif.copy()
    f = np.ones(g.kappa.shape)
    c, s_ = np.cos(alpha)[:, None, :], np.sin(alpha)[:, None, :]
    for _ in range(SOFTEN_ITERATIONS):
        g.eif = base * f
        u = _rigid_pass(spec, g, alpha, None).u                   # (B, S, 2) backbone frame
        uix = c * u[:, :, :1] + s_ * u[:, :, 1:]                   # tube i's frame, (B, S, n)
        uiy = -s_ * u[:, :, :1] + c * u[:, :, 1:]
        eps = 0.5 * spec.od[None, None, :] * np.hypot(uix, uiy - g.kappa)
        target = 1.0 - drop / (1.0 + np.exp(-(eps - onset) / width))
        f = 0.5 * f + 0.5 * np.where(g.present, target, 1.0)
    g.eif = base * f


def rigid(spec: Spec, alpha, beta, *, clearance=None, friction_mu=0.0, rel_dir=None,
          friction_contact=0.0, ramp=None, ei_curved=None, softening=None, twist=None, kink=None):
    """Closed-form rigid backbone. Returns a Backbone (node frames per break point).

    clearance: callable(phi (B,) relative rotation inner - outer, pair index j) -> delta (B,) rad
    or (tilt_in, tilt_out, jump_b, jump_a) (see _clearance_event).
    friction_mu with rel_dir (B, n-1): end-moment friction as a rotation correction dtheta of
    each tube of a pair: the end torque T (:func:`end_torque`) twists the straight transmission
    of the outer tube by +T l_o/GJ_o and of the inner tube by -T l_i/GJ_i (l: base to the outer
    end). ramp / ei_curved: see :func:`geometry`.
    """
    alpha = np.asarray(alpha, float)
    beta = np.asarray(beta, float)
    g = geometry(spec, beta, ramp=ramp, ei_curved=ei_curved, twist=twist, kink=kink)
    if softening is not None:
        soften(spec, g, alpha, softening)
    if friction_mu and rel_dir is not None and spec.n > 1:
        bb0 = _rigid_pass(spec, g, alpha, None)
        alpha = alpha + _friction_dtheta(spec, g, alpha, bb0.u, friction_mu, rel_dir,
                                         friction_contact)
    bb = _rigid_pass(spec, g, alpha, clearance)
    bb.alpha_eff = alpha
    return bb


def _friction_dtheta(spec, g, alpha, u, mu, rel_dir, contact=0.0):
    B, n = alpha.shape
    d = np.zeros_like(alpha)
    rows = np.arange(B)
    for o in range(1, n):
        j = g.endnode[:, o] - 1                               # segment ending at e_o
        ux, uy = u[rows, j, 0], u[rows, j, 1]
        a = alpha[:, o]
        uox = np.cos(a) * ux + np.sin(a) * uy
        uoy = -np.sin(a) * ux + np.cos(a) * uy
        EIo = spec.EI[o] if g.eif is None else spec.EI[o] * g.eif[rows, j, o]
        M = EIo * np.hypot(uox, uoy - g.kappa[rows, j, o])
        T = end_torque(spec, g, o, M, mu, contact, rel_dir[:, o - 1])
        d[:, o] += T * (g.ends[:, o] - g.beta[:, o]) / spec.GJ[o]
        d[:, o - 1] -= T * (g.ends[:, o] - g.beta[:, o - 1]) / spec.GJ[o - 1]
    return d


class Backbone:
    """Node data of one solution; evaluate(s) gives points at arc lengths s (B, M)."""

    kind: str

    def tip(self):
        return self.evaluate(self.g.ends[:, :1])[:, 0]

    def points(self, m: int):
        s = np.linspace(0.0, 1.0, m)[None, :] * self.g.ends[:, :1]
        return self.evaluate(s)


class RigidBackbone(Backbone):
    kind = "rigid"

    def __init__(self, g, P, R, u):
        self.g, self.P, self.R, self.u = g, P, R, u       # P (B,S+1,3), R (B,S+1,3,3), u (B,S,2)

    def evaluate(self, s):
        g = self.g
        B, M = s.shape
        S = g.bp.shape[1] - 1
        # segment j with bp_j <= s <= bp_{j+1}: count ends strictly below s
        j = np.sum(g.bp[:, None, 1:] < s[:, :, None], axis=2)
        j = np.minimum(j, S - 1)
        rows = np.repeat(np.arange(B), M)
        jf = j.ravel()
        h = s.ravel() - g.bp[rows, jf]
        dp, _ = _arc(self.u[rows, jf, 0], self.u[rows, jf, 1], np.maximum(h, 0.0))
        out = self.P[rows, jf] + np.einsum("bij,bj->bi", self.R[rows, jf], dp)
        return out.reshape(B, M, 3)


def _rigid_pass(spec, g, alpha, clearance):
    B, n = alpha.shape
    S = g.bp.shape[1] - 1
    EIp = np.where(g.present, spec.EI[None, None, :], 0.0)
    if g.eif is not None:
        EIp = EIp * g.eif
    psi = alpha[:, None, :] if g.kphase is None else alpha[:, None, :] + g.kphase
    Sx, Sy, EIt = _bend_xy(psi, g.kappa, EIp)
    EIt = np.where(EIt > 0, EIt, 1.0)
    u = np.stack([Sx / EIt, Sy / EIt], axis=2)                      # (B, S, 2)
    P = np.zeros((B, S + 1, 3))
    R = np.zeros((B, S + 1, 3, 3))
    R[:, 0] = np.eye(3)
    Rc = R[:, 0].copy()
    pc = np.zeros((B, 3))
    for j in range(S):
        h = g.bp[:, j + 1] - g.bp[:, j]
        dp, Rj = _arc(u[:, j, 0], u[:, j, 1], h)
        pc = pc + np.einsum("bij,bj->bi", Rc, dp)
        Rc = Rc @ Rj
        if clearance is not None:
            for o in range(1, n):
                msk = g.endnode[:, o] == j + 1
                if msk.any():
                    phi = alpha[msk, o - 1] - alpha[msk, o]
                    Q, off = _clearance_event(clearance, alpha[msk, o - 1], phi, o - 1)
                    pc[msk] = pc[msk] + np.einsum("bij,bj->bi", Rc[msk], off)
                    Rc[msk] = Rc[msk] @ Q
        P[:, j + 1] = pc
        R[:, j + 1] = Rc
    return RigidBackbone(g, P, R, u)


# ----------------------------------------------------------------------------- Cosserat shooting
class CosseratBackbone(Backbone):
    kind = "cosserat"

    def __init__(self, g, s, p, t, ok, info):
        self.g, self.s, self.p, self.t, self.ok, self.info = g, s, p, t, ok, info
        # s, p, t: (B, S, K+1[, 3]) node arc lengths, positions, unit tangents

    def evaluate(self, sq):
        g = self.g
        B, M = sq.shape
        S = g.bp.shape[1] - 1
        Kseg = np.maximum(np.asarray(self.info["K"]), 1)
        j = np.minimum(np.sum(g.bp[:, None, 1:] < sq[:, :, None], axis=2), S - 1)
        rows = np.repeat(np.arange(B), M)
        jf = j.ravel()
        s0 = g.bp[rows, jf]
        Kj = Kseg[jf]
        h = (g.bp[rows, jf + 1] - s0) / Kj
        x = np.where(h > 0, (sq.ravel() - s0) / np.where(h > 0, h, 1.0), 0.0)
        k = np.clip(np.floor(x).astype(int), 0, Kj - 1)
        tt = np.clip(x - k, 0.0, 1.0)[:, None]
        p0, p1 = self.p[rows, jf, k], self.p[rows, jf, k + 1]
        m0, m1 = self.t[rows, jf, k] * h[:, None], self.t[rows, jf, k + 1] * h[:, None]
        h00 = 2 * tt ** 3 - 3 * tt ** 2 + 1
        h10 = tt ** 3 - 2 * tt ** 2 + tt
        h01 = -2 * tt ** 3 + 3 * tt ** 2
        h11 = tt ** 3 - tt ** 2
        out = h00 * p0 + h10 * m0 + h01 * p1 + h11 * m1
        return out.reshape(B, M, 3)


class _Problem:
    """Everything the integrator needs for a batch (rows may be replicated for the Jacobian)."""

    def __init__(self, spec, g, alpha, torsion, wvec, F, clearance, mu, rel_dir, contact=0.0,
                 coupling=None):
        self.spec, self.g, self.alpha = spec, g, alpha
        self.contact = contact    # friction torque growth with contact length (end_torque)
        self.coupling = coupling  # (n,) mm: torsional compliance of the drive couplings
        self.torsion = torsion
        self.wvec = wvec          # (n, 3) weight per length of each tube, N/mm, base frame
        self.F = F                # (3,) or (B, 3) tip force N
        self.clearance = clearance
        self.mu = mu
        self.rel_dir = rel_dir    # (B, n-1) or None
        self.loaded = wvec is not None or F is not None

    def take(self, idx):
        return _Problem(self.spec, self.g.take(idx), self.alpha[idx], self.torsion, self.wvec,
                        self.F if self.F is None or self.F.ndim == 1 else self.F[idx],
                        self.clearance, self.mu,
                        None if self.rel_dir is None else self.rel_dir[idx], self.contact,
                        self.coupling)


def _deriv(X, s, kap, EIp, GJ, EIt, nA, nB, n, full, torsion, kph=None):
    """State derivative. Reduced state (full=False): [psi (n), u_z (n)]; full state adds
    p (3), R (9, row-major), m (3). ``kph`` (B, n): the precurvature's angle in each tube's
    frame (a pre-twisted curve); the bending and twist terms see psi + kph."""
    psi = X[:, 0:n] if kph is None else X[:, 0:n] + kph
    c, sn = np.cos(psi), np.sin(psi)
    ek = EIp * kap
    Sx = -(ek * sn).sum(axis=1)
    Sy = (ek * c).sum(axis=1)
    parts = []
    if full:
        r = X[:, 2 * n + 3:2 * n + 12]
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = (r[:, i] for i in range(9))
        if nA is not None:
            m0, m1, m2 = X[:, 2 * n + 12], X[:, 2 * n + 13], X[:, 2 * n + 14]
            ux = (r00 * m0 + r10 * m1 + r20 * m2 + Sx) / EIt
            uy = (r01 * m0 + r11 * m1 + r21 * m2 + Sy) / EIt
        else:
            ux, uy = Sx / EIt, Sy / EIt
    else:
        ux, uy = Sx / EIt, Sy / EIt
    if torsion:
        parts.append(X[:, n:2 * n] * (EIp > 0))
        parts.append((EIp / GJ) * kap * (c * ux[:, None] + sn * uy[:, None]))
    else:
        parts.append(np.zeros((X.shape[0], 2 * n)))
    if full:
        # p' = R e3; R' = R [u]x with u = (ux, uy, 0): columns (-uy t, ux t, uy R e1 - ux R e2)
        t0, t1, t2 = r02, r12, r22
        dR = np.stack([-uy * t0, ux * t0, uy * r00 - ux * r01,
                       -uy * t1, ux * t1, uy * r10 - ux * r11,
                       -uy * t2, ux * t2, uy * r20 - ux * r21], axis=1)
        parts.append(np.stack([t0, t1, t2], axis=1))
        parts.append(dR)
        if nA is not None:
            nf = nA - s[:, None] * nB
            dm = -np.stack([t1 * nf[:, 2] - t2 * nf[:, 1], t2 * nf[:, 0] - t0 * nf[:, 2],
                            t0 * nf[:, 1] - t1 * nf[:, 0]], axis=1)
            parts.append(dm)
        else:
            parts.append(np.zeros((X.shape[0], 3)))
    return np.concatenate(parts, axis=1), ux, uy


def _integrate(pb: _Problem, X, full, K, record=False):
    spec, g = pb.spec, pb.g
    n = spec.n
    B = X.shape[0]
    S = g.bp.shape[1] - 1
    GJ = spec.GJ[None, :]
    T = np.zeros((B, n))                           # friction torque at each tube's end
    rec = None
    Kmax = int(np.max(K)) if np.size(K) else 1
    Kmax = max(Kmax, 1)
    if record:
        rec_s = np.zeros((B, S, Kmax + 1))
        rec_p = np.zeros((B, S, Kmax + 1, 3))
        rec_t = np.zeros((B, S, Kmax + 1, 3))
    for j in range(S):
        Kj = int(K[j])
        kap = g.kappa[:, j]
        pres = g.present[:, j]
        EIp = g.EIp(spec, j)
        EIt = np.sum(EIp, axis=1)
        EIt = np.where(EIt > 0, EIt, 1.0)
        nA = nB = None
        if full and pb.loaded:
            nA = np.zeros((B, 3)) if pb.F is None else np.broadcast_to(pb.F, (B, 3)).copy()
            nB = np.zeros((B, 3))
            if pb.wvec is not None:
                wsum_e = (pres * g.ends) @ pb.wvec          # sum_i present w_i e_i  (B,3)
                nA = nA + wsum_e
                nB = pres.astype(float) @ pb.wvec
        s = g.bp[:, j].copy()
        h = (g.bp[:, j + 1] - g.bp[:, j]) / max(Kj, 1)
        args = (kap, EIp, GJ, EIt, nA, nB, n, full, pb.torsion,
                None if g.kphase is None else g.kphase[:, j])
        if record:
            rec_s[:, j, :] = s[:, None]
            rec_p[:, j, :] = X[:, None, 2 * n:2 * n + 3]
            rec_t[:, j, :] = X[:, None, 2 * n + 3:2 * n + 12].reshape(-1, 1, 3, 3)[..., 2]
        hc = h[:, None]
        for k in range(Kj):
            k1, _, _ = _deriv(X, s, *args)
            k2, _, _ = _deriv(X + 0.5 * hc * k1, s + 0.5 * h, *args)
            k3, _, _ = _deriv(X + 0.5 * hc * k2, s + 0.5 * h, *args)
            k4, _, _ = _deriv(X + hc * k3, s + h, *args)
            X = X + hc / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)
            s = s + h
            if record:
                rec_s[:, j, k + 1:] = s[:, None]
                rec_p[:, j, k + 1:] = X[:, None, 2 * n:2 * n + 3]
                rec_t[:, j, k + 1:] = X[:, None, 2 * n + 3:2 * n + 12].reshape(-1, 1, 3, 3)[..., 2]
        # point events at tube ends (node j+1)
        if n > 1 and (pb.clearance is not None or (pb.mu and pb.rel_dir is not None)):
            for o in range(1, n):
                msk = g.endnode[:, o] == j + 1
                if not msk.any():
                    continue
                if pb.mu and pb.rel_dir is not None:
                    _, ux, uy = _deriv(X[msk], s[msk], kap[msk], EIp[msk], GJ, EIt[msk],
                                       None if nA is None else nA[msk],
                                       None if nB is None else nB[msk], n, full, pb.torsion,
                                       None if args[-1] is None else args[-1][msk])
                    a = X[msk, o]
                    uox = np.cos(a) * ux + np.sin(a) * uy
                    uoy = -np.sin(a) * ux + np.cos(a) * uy
                    M = EIp[msk, o] * np.sqrt(uox ** 2 + (uoy - kap[msk, o]) ** 2 + 1e-30)
                    To = end_torque(spec, g.take(msk), o, M, pb.mu, pb.contact,
                                    pb.rel_dir[msk, o - 1])
                    T[msk, o] = To
                    if pb.torsion:
                        X[msk, n + o - 1] += To / spec.GJ[o - 1]
                if full and pb.clearance is not None:
                    psi_in = X[msk, o - 1]
                    phi = psi_in - X[msk, o]
                    Q, off = _clearance_event(pb.clearance, psi_in, phi, o - 1)
                    R = X[msk, 2 * n + 3:2 * n + 12].reshape(-1, 3, 3)
                    X[msk, 2 * n:2 * n + 3] += np.einsum("bij,bj->bi", R, off)
                    X[msk, 2 * n + 3:2 * n + 12] = (R @ Q).reshape(-1, 9)
        if record:
            # the jump changes the tangent at the node; the next segment records it afresh
            pass
    if record:
        rec = (rec_s, rec_p, rec_t)
    return X, T, rec


def _initial(pb: _Problem, x, EIref):
    """State at s = 0 from the unknowns x (B, k) (scaled: u_z in 1/mm, moments / EIref)."""
    spec = pb.spec
    n = spec.n
    B = x.shape[0]
    X = np.zeros((B, 2 * n + 15))
    if pb.torsion:
        uz0 = x[:, :n]
        lt = pb.g.beta if pb.coupling is None else pb.g.beta - pb.coupling[None, :]
        X[:, 0:n] = pb.alpha - lt * uz0
        X[:, n:2 * n] = uz0
    else:
        X[:, 0:n] = pb.alpha
    X[:, 2 * n + 3:2 * n + 12] = np.eye(3).reshape(1, 9)
    if pb.loaded:
        if pb.torsion:
            X[:, 2 * n + 12] = x[:, n] * EIref
            X[:, 2 * n + 13] = x[:, n + 1] * EIref
            X[:, 2 * n + 14] = np.sum(spec.GJ[None, :] * x[:, :n], axis=1)
        else:
            X[:, 2 * n + 12:2 * n + 15] = x[:, :3] * EIref
    return X


def _residual(pb: _Problem, X, T, EIref, reduced=False):
    spec = pb.spec
    n = spec.n
    parts = []
    if pb.torsion:
        parts.append((X[:, n:2 * n] - T / spec.GJ[None, :]) * spec.GJ[None, :] / EIref)
    if pb.loaded and not reduced:
        R = X[:, 2 * n + 3:2 * n + 12].reshape(-1, 3, 3)
        m = X[:, 2 * n + 12:2 * n + 15]
        if pb.torsion:
            mb = np.einsum("bji,bj->bi", R, m)
            parts.append(mb[:, :2] / EIref)
        else:
            parts.append(m / EIref)
    return np.concatenate(parts, axis=1)


def _eval(pb, x, full, K, EIref, reduced_residual):
    n = pb.spec.n
    X0 = _initial(pb, x, EIref)
    if not full:
        X0 = X0[:, :2 * n]
    XL, T, _ = _integrate(pb, X0, full, K)
    return _residual(pb, XL, T, EIref, reduced_residual)


def _newton(pb, x, full, K, EIref, tol, max_iter, reduced_residual=False):
    """Damped Newton / chord iteration on all rows at once; returns (x, converged).

    The Jacobian (forward differences) is recomputed only where the last step did not shrink
    the residual by at least 3x (chord steps elsewhere); a step that does not lower the residual
    norm is halved (up to 4 times) with a fresh Jacobian."""
    B, k = x.shape
    eps = 1e-7
    r = _eval(pb, x, full, K, EIref, reduced_residual)
    J = np.zeros((B, k, k))
    fresh = np.zeros(B, bool)
    need_J = np.ones(B, bool)
    active = np.arange(B)
    def clean(v):
        return np.nan_to_num(v, nan=1e3, posinf=1e3, neginf=-1e3)
    for _ in range(max_iter):
        small = np.max(np.abs(clean(r[active])), axis=1) < 1e-14
        active = active[~small]
        if active.size == 0:
            break
        jrows = active[need_J[active]]
        if jrows.size:
            nj = jrows.size
            idx = np.tile(jrows, k)
            xs = np.tile(x[jrows], (k, 1))
            for c in range(k):
                xs[c * nj:(c + 1) * nj, c] += eps
            rp = _eval(pb.take(idx), xs, full, K, EIref, reduced_residual)
            Jn = np.stack([(rp[c * nj:(c + 1) * nj] - r[jrows]) / eps for c in range(k)], axis=2)
            badJ = ~np.isfinite(Jn).all(axis=(1, 2))
            Jn[badJ] = np.eye(k)
            J[jrows] = Jn
            fresh[jrows] = True
            need_J[jrows] = False
        ra = clean(r[active])
        try:
            dx = np.linalg.solve(J[active], -ra[:, :, None])[:, :, 0]
        except np.linalg.LinAlgError:
            dx = np.stack([np.linalg.lstsq(Ji, -ri, rcond=None)[0] for Ji, ri in zip(J[active], ra)])
        f0 = np.sum(ra ** 2, axis=1)
        lam = np.ones(active.size)
        accepted = np.zeros(active.size, bool)
        rnew = np.zeros_like(ra)
        pending = np.arange(active.size)
        for _t in range(5):
            if pending.size == 0:
                break
            trial = x[active[pending]] + lam[pending, None] * dx[pending]
            rt = _eval(pb.take(active[pending]), trial, full, K, EIref, reduced_residual)
            ft = np.sum(clean(rt) ** 2, axis=1)
            good = ft < f0[pending] * (1 - 1e-4 * lam[pending]) + 1e-30
            gi = pending[good]
            accepted[gi] = True
            rnew[gi] = rt[good]
            # a stale Jacobian gets no line search: recompute it instead
            stale = pending[~good & ~fresh[active[pending]]]
            need_J[active[stale]] = True
            pending = pending[~good & fresh[active[pending]]]
            lam[pending] *= 0.5
        acc = active[accepted]
        step = lam[accepted, None] * dx[accepted]
        x[acc] += step
        r[acc] = rnew[accepted]
        slow = np.sum(rnew[accepted] ** 2, axis=1) > f0[accepted] / 9.0
        need_J[acc[slow]] = True
        fresh[acc] = False
        done = np.max(np.abs(step), axis=1) < tol
        # rows with a fresh Jacobian and no acceptable step are stuck: give up on them
        stuck = active[~accepted & ~need_J[active]]
        finished = np.concatenate([acc[done], stuck])
        active = np.setdiff1d(active, finished, assume_unique=True)
        if stuck.size:
            r[stuck] = np.where(np.isfinite(r[stuck]), r[stuck], 1e3)
    conv = np.max(np.abs(clean(r)), axis=1) < 1e-9
    return x, conv


def _line(pb, c, d, K, EIref):
    """Residual of the first tube along the torque-balanced line u_z(0) = c d (two tubes)."""
    return _eval(pb, c[:, None] * d, False, K, EIref, False)[:, 0]


def _two_tube_stable(pb, spec, x, K, EIref):
    """Two tubes: is the solution x on a stable branch? Along the torque-balanced line the tip
    residual r(c) has an odd number of roots; the outer ones (slope of the same sign as the
    chord r(+A) - r(-A)) are the stable equilibria, a middle one (opposite slope) is the
    unstable equilibrium between two stable ones (the snapping regime)."""
    B = x.shape[0]
    amp = 4.0 * float(np.max(spec.kappa))
    d = np.array([1.0, -spec.GJ[0] / spec.GJ[1]])
    c = x[:, 0]
    h = 1e-6
    idx = np.tile(np.arange(B), 4)
    cc = np.concatenate([c + h, c - h, np.full(B, amp), np.full(B, -amp)])
    r = _line(pb.take(idx), cc, d, K, EIref).reshape(4, B)
    return np.sign(r[0] - r[1]) == np.sign(r[2] - r[3])


def _bracket_solve(pb, spec, K, EIref, m=81, iters=60):
    """Two tubes: on the torque-balanced line u_z(0) = c (1, -GJ_1/GJ_2) the residual is a
    scalar function of c; bracket the STABLE root (slope sign of the chord over the scan range)
    nearest c = 0 on a grid, then regula falsi (Illinois). Robust where the twist is strongly
    nonlinear, and it never returns the unstable middle equilibrium of a bistable pair."""
    B = pb.alpha.shape[0]
    amp = 4.0 * float(np.max(spec.kappa))
    d = np.array([1.0, -spec.GJ[0] / spec.GJ[1]])
    c = np.linspace(-amp, amp, m)
    idx = np.repeat(np.arange(B), m)
    r = _line(pb.take(idx), np.tile(c, B), d, K, EIref).reshape(B, m)
    sgn = np.sign(r)
    normal = np.sign(r[:, -1] - r[:, 0])[:, None]
    ch = ((sgn[:, :-1] * sgn[:, 1:]) <= 0) & (np.sign(r[:, 1:] - r[:, :-1]) == normal)
    dist = np.where(ch, np.abs(0.5 * (c[:-1] + c[1:]))[None, :], np.inf)
    k = np.argmin(dist, axis=1)
    rows = np.arange(B)
    found = np.isfinite(dist[rows, k])
    a, b = c[k], c[k + 1]
    fa, fb = r[rows, k], r[rows, k + 1]
    side = np.zeros(B)
    cm = 0.5 * (a + b)
    for _ in range(iters):
        den = np.where(fb - fa != 0, fb - fa, 1.0)
        cm = np.where(fb - fa != 0, b - fb * (b - a) / den, 0.5 * (a + b))
        fm = _line(pb, cm, d, K, EIref)
        left = np.sign(fm) == np.sign(fa)
        # Illinois modification
        fb_new = np.where(left, fb * np.where(side == -1, 0.5, 1.0), fm)
        fa_new = np.where(left, fm, fa * np.where(side == 1, 0.5, 1.0))
        a, b = np.where(left, cm, a), np.where(left, b, cm)
        fa, fb = fa_new, fb_new
        side = np.where(left, -1, 1)
        if np.all(np.abs(b - a) < 1e-13) or np.all(np.abs(fm) < 1e-15):
            break
    x = cm[:, None] * d
    rf = _eval(pb, x, False, K, EIref, False)
    conv = found & (np.max(np.abs(rf), axis=1) < 1e-10)
    return x, conv


def _scan_starts(pb, spec, K, EIref, m=48):
    B = pb.alpha.shape[0]
    n = spec.n
    rng = np.random.default_rng(12345)
    amp = 4.0 * float(np.max(spec.kappa))
    if n == 2:
        c = np.linspace(-amp, amp, m)[:, None]
        dirs = np.array([[1.0, -spec.GJ[0] / spec.GJ[1]]])
        cand = c * dirs                                              # (m, 2)
    else:
        v = rng.uniform(-amp, amp, (m, n))
        v[:, -1] = -(v[:, :-1] @ spec.GJ[:-1]) / spec.GJ[-1]
        cand = v
    cand = np.vstack([np.zeros((1, n)), cand])
    mc = cand.shape[0]
    idx = np.repeat(np.arange(B), mc)
    r = _eval(pb.take(idx), np.tile(cand, (B, 1)), False, K, EIref, False)
    f = np.nan_to_num(np.sum(r ** 2, axis=1), nan=1e9).reshape(B, mc)
    return cand[np.argmin(f, axis=1)].copy()


def _m0_guess(pb, bb):
    """m(0) = int_0^L p'(s) x n(s) ds on a known shape (m' = -p' x n, m(L) = 0)."""
    g = pb.g
    B, S, K1 = bb.s.shape
    nf = np.zeros((B, S, K1, 3))
    if pb.F is not None:
        nf += pb.F if pb.F.ndim == 1 else pb.F[:, None, None, :]
    if pb.wvec is not None:
        pres = (g.ends[:, None, None, :] > bb.s[..., None])
        rem = np.where(pres, g.ends[:, None, None, :] - bb.s[..., None], 0.0)
        nf += rem @ pb.wvec
    integrand = np.cross(bb.t, nf)
    ds = np.diff(bb.s, axis=2)[..., None]
    return np.sum(0.5 * (integrand[:, :, 1:] + integrand[:, :, :-1]) * ds, axis=(1, 2))


def cosserat(spec: Spec, alpha, beta, *, torsion=True, gravity=None, tip_force=None,
             clearance=None, friction_mu=0.0, rel_dir=None, h_max=10.0, tol=1e-10, max_iter=12,
             friction_contact=0.0, ramp=None, ei_curved=None, coupling=None, extra_weight=None,
             softening=None, twist=None, kink=None):
    """Solve the (loaded) Cosserat rod BVP for a batch. gravity: (3,) m/s^2 in the base frame
    (None = no weight); tip_force: (3,) N. Returns a CosseratBackbone (with .ok per row).

    Order: (1) unloaded torsion problem on the reduced state (psi, u_z) by Newton; (2) with
    loads, m(0) guessed from that shape, then Newton on the full state (u_z(0), m(0))."""
    alpha = np.asarray(alpha, float)
    beta = np.asarray(beta, float)
    B, n = alpha.shape
    g = geometry(spec, beta, ramp=ramp, ei_curved=ei_curved, twist=twist, kink=kink)
    if softening is not None:
        soften(spec, g, alpha, softening)       # the strain of the torsionally rigid shape
    wvec = None
    if gravity is not None and np.any(np.asarray(gravity) != 0):
        w = spec.weight_per_mm if extra_weight is None else spec.weight_per_mm + extra_weight
        wvec = w[:, None] * (np.asarray(gravity, float) / 9.81)[None, :]
    F = None if tip_force is None or not np.any(np.asarray(tip_force) != 0) else np.asarray(tip_force, float)
    cpl = None if coupling is None or not np.any(np.asarray(coupling) != 0) else \
        np.asarray(coupling, float)
    pb = _Problem(spec, g, alpha, torsion, wvec, F, clearance, friction_mu, rel_dir,
                  friction_contact, cpl)
    seg = np.diff(g.bp, axis=1)
    K = np.maximum(1, np.ceil(seg.max(axis=0) / h_max)).astype(int) if B else np.ones(seg.shape[1], int)
    K[seg.max(axis=0) <= 0] = 0 if B else 1
    EIref = float(np.sum(spec.EI))
    ok = np.ones(B, bool)
    # (1) unloaded torsion
    pb0 = _Problem(spec, g, alpha, torsion, None, None, clearance, friction_mu, rel_dir,
                   friction_contact, cpl)
    if torsion:
        x, conv = _newton(pb0, np.zeros((B, n)), False, K, EIref, tol, max_iter)
        if n == 2 and conv.any():
            # Newton may land on the unstable middle equilibrium where the pair is bistable
            ci = np.flatnonzero(conv)
            conv[ci[~_two_tube_stable(pb0.take(ci), spec, x[ci], K, EIref)]] = False
        if not conv.all():
            # multi-start for the rows Newton did not solve from u_z = 0 (strongly nonlinear
            # twist near a fold): scan starts on the torque-balanced set sum GJ u_z = 0 and
            # restart Newton from the one with the smallest residual
            bad = np.flatnonzero(~conv)
            if n == 2:
                xb, cb = _bracket_solve(pb0.take(bad), spec, K, EIref)
            else:
                xs = _scan_starts(pb0.take(bad), spec, K, EIref)
                xb, cb = _newton(pb0.take(bad), xs, False, K, EIref, tol, max_iter)
            x[bad] = xb
            conv[bad] = cb
        if not conv.all() and cpl is not None:
            # compliant couplings: continue from the solution without them (the branch the
            # robot is on as the coupling compliance grows from 0)
            bad = np.flatnonzero(~conv)
            pbb = pb0.take(bad)
            xb = np.zeros((bad.size, n))
            cb = np.ones(bad.size, bool)
            for f in (0.0, 0.25, 0.5, 0.75, 1.0):
                pbb.coupling = f * cpl
                xb, cf = _newton(pbb, xb, False, K, EIref, tol, max_iter)
                cb &= cf
            x[bad] = xb
            conv[bad] = cb
        ok &= conv
    else:
        x = np.zeros((B, 0))
    X0 = _initial(pb0, x, EIref)
    XL, T, rec = _integrate(pb0, X0, True, K, record=True)
    bb = CosseratBackbone(g, rec[0], rec[1], rec[2], ok, dict(K=K, x=x, state_end=XL))
    if not pb.loaded:
        return bb
    # (2) loads
    m0 = _m0_guess(pb, bb)
    if torsion:
        x = np.concatenate([x, m0[:, :2] / EIref], axis=1)
    else:
        x = m0 / EIref
    x, conv = _newton(pb, x, True, K, EIref, tol, max_iter)
    X0 = _initial(pb, x, EIref)
    XL, T, rec = _integrate(pb, X0, True, K, record=True)
    r = _residual(pb, XL, T, EIref)
    ok = ok & conv & (np.max(np.abs(r), axis=1) < 1e-8)
    return CosseratBackbone(g, rec[0], rec[1], rec[2], ok,
                            dict(K=K, x=x, state_end=XL, m0=X0[:, 2 * n + 12:2 * n + 15].copy()))
