"""The elastic energy of an unloaded CTR as a functional of the tube angles, discretised here by
finite elements (independent of ctrplan's shooting and of mechanics.py's): minimised, it gives
the equilibria; its second variation decides their stability.

With no external load the common backbone curvature minimises the bending energy pointwise,
u_xy = sum_i w_i e(psi_i) / EIsum (e(psi) = (-sin psi, cos psi), w_i = EI_i kappa_i on tube i's
curved section, EIsum over the tubes present), and what is left is a functional of the tubes'
material angles psi_i(s) (relative to the twist-free backbone frame, as in mechanics.py):

    E[psi] = sum_i GJ_i/2 int_{beta_i}^{e_i} psi_i'^2 ds
             - int sum_{i<j} w_i w_j / EIsum(s) cos(psi_i - psi_j) ds,   psi_i(beta_i) = alpha_i

(Dirichlet at the actuator, arc length beta_i <= 0; free at the tube end e_i = beta_i + L_i; the
part behind the constraint plane is a straight torsion spring GJ_i / -beta_i). Its stationary
points are the torsion equations GJ_i psi_i'' = dV/dpsi_i with u_iz(e_i) = 0 and
psi_i(0) = alpha_i - beta_i u_iz(0): the compliant model of mechanics.py and of ctrplan.

Discretisation: nodes at every break point (s = 0, curved-section starts, tube ends); a stretch
where two or more curved sections overlap is cut into elements of at most ``h`` mm, any other
stretch is one element (there psi is exactly linear: no coupling). psi is piecewise linear
(torsion term exact), the coupling integral uses the trapezoid rule with each element's own
coefficients (error O(h^2)). Unknowns are psi_i at the nodes tube i reaches, ordered node by node,
so every matrix is banded (half-bandwidth n) and Newton steps cost O(nodes).

Stability measure (``Energy.stability``): the smallest generalised eigenvalue mu of
H v = mu T v, H the Hessian of the discrete energy and T the Hessian of its torsion term alone
(element stiffnesses GJ_i / h and actuator springs GJ_i / -beta_i): the fraction of the torsional
stiffness that the softest twist mode keeps once bending acts on it. Dimensionless, at most 1
(a common rotation of all tubes meets no coupling), 0 exactly at a fold (the equilibrium stops
existing: snap-through), negative at an unstable equilibrium, and it converges as h -> 0 (it is
the Rayleigh quotient Q[eta] / T[eta] of the continuous second variation). For two equal tubes at
relative rotation pi on the untwisted equilibrium, mu = 1 - lambda^2 / omega^2 with
lambda^2 = 2 c / GJ and omega L the root of cot(omega L) = omega l (tests/test_foreign_continuation.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import LinAlgError, cho_solve_banded, cholesky_banded, eigh, eigvals_banded

from .robot import Spec

TOL_S = 1e-9                  # mm: break points closer than this are one node
FIXED_ELL = 1e-6              # mm: an actuator closer than this to the plane holds psi_i(0)


@dataclass
class Energy:
    """The discrete energy of one configuration (one geometry: beta fixed, alpha any).

    s (N,) node arc lengths (mm, 0 .. tip); var (N, n) index of psi_i at node k (-1: absent);
    ell (n,) transmission lengths -beta_i (mm); alpha (n,) rad; the element and node lists
    hold the torsion stiffnesses (N mm) and the nodal coupling weights (N mm)."""

    spec: Spec
    beta: np.ndarray
    alpha: np.ndarray
    s: np.ndarray
    var: np.ndarray
    nvar: int
    ell: np.ndarray
    el_p: np.ndarray              # element torsion terms: GJ/h (x_q - x_p)^2 / 2
    el_q: np.ndarray
    el_g: np.ndarray
    pr_p: np.ndarray              # nodal coupling terms: -W cos(x_p - x_q)
    pr_q: np.ndarray
    pr_w: np.ndarray
    act: np.ndarray               # (n,) index of psi_i(0)
    fixed: np.ndarray             # (n,) bool: beta_i = 0, psi_i(0) = alpha_i held
    ks: np.ndarray                # (n,) N mm: actuator springs GJ_i / -beta_i (0 where held)

    @property
    def n(self) -> int:
        return self.spec.n

    # ------------------------------------------------------------------ values
    def value(self, x: np.ndarray) -> float:
        """Energy (N mm) of the nodal angles x (nvar,)."""
        d = x[self.el_q] - x[self.el_p]
        e = 0.5 * np.sum(self.el_g * d * d)
        a = x[self.act] - self.alpha
        e += 0.5 * np.sum(self.ks * a * a)
        e -= np.sum(self.pr_w * np.cos(x[self.pr_p] - x[self.pr_q]))
        return float(e)

    def gradient(self, x: np.ndarray) -> np.ndarray:
        g = np.zeros(self.nvar)
        d = self.el_g * (x[self.el_q] - x[self.el_p])
        np.add.at(g, self.el_q, d)
        np.add.at(g, self.el_p, -d)
        g[self.act] += self.ks * (x[self.act] - self.alpha)
        sn = self.pr_w * np.sin(x[self.pr_p] - x[self.pr_q])
        np.add.at(g, self.pr_p, sn)
        np.add.at(g, self.pr_q, -sn)
        g[self.act[self.fixed]] = 0.0
        return g

    def _banded(self, x: np.ndarray | None) -> np.ndarray:
        """Lower banded form (n+1, nvar) of the Hessian (x given) or of the torsion part T
        (x None)."""
        u = self.n
        ab = np.zeros((u + 1, self.nvar))
        np.add.at(ab[0], self.el_p, self.el_g)
        np.add.at(ab[0], self.el_q, self.el_g)
        np.add.at(ab, (self.el_q - self.el_p, self.el_p), -self.el_g)
        ab[0, self.act] += self.ks
        if x is not None:
            c = self.pr_w * np.cos(x[self.pr_p] - x[self.pr_q])
            np.add.at(ab[0], self.pr_p, c)
            np.add.at(ab[0], self.pr_q, c)
            np.add.at(ab, (self.pr_q - self.pr_p, self.pr_p), -c)
        for p in self.act[self.fixed]:          # held: identity row and column
            ab[:, p] = 0.0
            ab[0, p] = 1.0
            for d in range(1, u + 1):
                if p - d >= 0:
                    ab[d, p - d] = 0.0
        return ab

    def hessian_banded(self, x: np.ndarray) -> np.ndarray:
        return self._banded(x)

    def _dense(self, ab: np.ndarray) -> np.ndarray:
        N = self.nvar
        M = np.diag(ab[0].copy())
        for d in range(1, ab.shape[0]):
            idx = np.arange(N - d)
            M[idx + d, idx] = ab[d, :N - d]
            M[idx, idx + d] = ab[d, :N - d]
        return M

    def stability(self, x: np.ndarray) -> float:
        """mu, the smallest eigenvalue of H v = mu T v (module docstring): dimensionless,
        > 0 stable, 0 at a fold, < 0 unstable."""
        keep = np.ones(self.nvar, bool)
        keep[self.act[self.fixed]] = False
        H = self._dense(self._banded(x))[np.ix_(keep, keep)]
        T = self._dense(self._banded(None))[np.ix_(keep, keep)]
        return float(eigh(H, T, eigvals_only=True, subset_by_index=[0, 0])[0])

    def min_eig(self, x: np.ndarray) -> float:
        """Smallest eigenvalue of the Hessian itself (N mm per rad^2 of nodal angle)."""
        return float(eigvals_banded(self._banded(x), lower=True, select="i", select_range=(0, 0))[0])

    # ------------------------------------------------------------------ derived quantities
    def tube_values(self, x: np.ndarray, i: int) -> tuple[np.ndarray, np.ndarray]:
        """(s, psi) at the nodes tube i reaches."""
        k = np.flatnonzero(self.var[:, i] >= 0)
        return self.s[k], x[self.var[k, i]]

    def uz0(self, x: np.ndarray) -> np.ndarray:
        """(n,) torsion u_iz at s = 0 (1/mm), ctrplan's uz(0): psi_i(0) = alpha_i - beta_i uz0_i."""
        out = np.zeros(self.n)
        for i in range(self.n):
            if self.fixed[i]:
                s, p = self.tube_values(x, i)
                out[i] = (p[1] - p[0]) / (s[1] - s[0]) if len(s) > 1 else 0.0
            else:
                out[i] = (x[self.act[i]] - self.alpha[i]) / self.ell[i]
        return out

    def initial(self, uz0: np.ndarray) -> np.ndarray:
        """Nodal angles of a linear twist psi_i = alpha_i + (s - beta_i) uz0_i (a start guess)."""
        x = np.zeros(self.nvar)
        for i in range(self.n):
            k = np.flatnonzero(self.var[:, i] >= 0)
            x[self.var[k, i]] = self.alpha[i] + (self.s[k] - self.beta[i]) * uz0[i]
        return x

    def transfer(self, other: Energy, y: np.ndarray) -> np.ndarray:
        """Nodal angles of ``other`` (solution y) interpolated onto this mesh in arc length,
        each tube turned by the change of its actuator angle (the continuation predictor)."""
        x = np.zeros(self.nvar)
        for i in range(self.n):
            s, p = other.tube_values(y, i)
            k = np.flatnonzero(self.var[:, i] >= 0)
            x[self.var[k, i]] = np.interp(self.s[k], s, p) + (self.alpha[i] - other.alpha[i])
        x[self.act[self.fixed]] = self.alpha[self.fixed]
        return x


def build(spec: Spec, q: np.ndarray, h: float = 1.0) -> Energy:
    """The discrete energy of configuration q (2n,) (rad, mm); h the largest element (mm)
    where curved sections overlap."""
    q = np.asarray(q, float)
    n = spec.n
    alpha, beta = q[:n].copy(), q[n:].copy()
    e = beta + spec.L
    c = np.clip(beta + spec.straight, 0.0, None)
    raw = np.sort(np.concatenate([[0.0], c, e]))
    raw = raw[(raw >= 0.0) & (raw <= e.max() + TOL_S)]
    bps = [raw[0]]
    for v in raw[1:]:
        if v - bps[-1] > TOL_S:
            bps.append(v)
    EI, kap = spec.EI, spec.kappa
    nodes = [0.0]
    for a, b in zip(bps[:-1], bps[1:]):
        mid = 0.5 * (a + b)
        curved = (mid < e) & (mid >= c) & (kap != 0.0)
        m = int(np.ceil((b - a) / h)) if curved.sum() >= 2 else 1
        nodes.extend(list(np.linspace(a, b, m + 1)[1:]))
    s = np.array(nodes)
    present = s[:, None] <= e[None, :] + TOL_S                          # (N, n)
    var = -np.ones(present.shape, int)
    var[present] = np.arange(int(present.sum()))                       # node-major order
    ell = -beta
    fixed = ell < FIXED_ELL
    # elements
    sm = 0.5 * (s[1:] + s[:-1])
    hk = np.diff(s)
    pres_e = present[1:]                                               # tube reaches the far node
    curv_e = pres_e & (sm[:, None] >= c[None, :]) & (kap[None, :] != 0.0)
    el = np.nonzero(pres_e)
    el_p = var[el[0], el[1]]
    el_q = var[el[0] + 1, el[1]]
    el_g = spec.GJ[el[1]] / hk[el[0]]
    # nodal coupling weights: trapezoid, each element's own coefficients at both its nodes
    EIs = np.sum(np.where(pres_e, EI[None, :], 0.0), axis=1)
    w = np.where(curv_e, (EI * kap)[None, :], 0.0)
    pp, pq, pw = [], [], []
    for i in range(n):
        for j in range(i + 1, n):
            ce = w[:, i] * w[:, j] / EIs                                # (N-1,) N mm^2 / mm^2
            on = ce != 0.0
            for side in (0, 1):
                kk = np.flatnonzero(on) + side
                pp.append(var[kk, i])
                pq.append(var[kk, j])
                pw.append(0.5 * hk[on] * ce[on])
    if pp:
        pr_p, pr_q, pr_w = np.concatenate(pp), np.concatenate(pq), np.concatenate(pw)
    else:
        pr_p = pr_q = np.zeros(0, int)
        pr_w = np.zeros(0)
    ks = np.where(fixed, 0.0, spec.GJ / np.maximum(ell, FIXED_ELL))
    return Energy(spec, beta, alpha, s, var, int(present.sum()), ell, el_p, el_q, el_g,
                  pr_p, pr_q, pr_w, var[0].copy(), fixed, ks)


def minimise(en: Energy, x0: np.ndarray, max_iter: int = 60, tol: float = 1e-10,
             require_pd: bool = False):
    """Local minimum of the energy from x0 by Newton's method with a line search on the energy
    (a Hessian that is not positive definite is shifted until it is, so every step descends;
    from a saddle it leaves along the softest mode). Returns (x, converged, iterations):
    converged means the last Newton step was below ``tol`` rad at a positive definite Hessian.
    require_pd: give up (not converged) at the first Hessian that is not positive definite.
    A quasi-static robot does the same: it goes down in energy to the nearest minimum."""
    x = x0.copy()
    x[en.act[en.fixed]] = en.alpha[en.fixed]
    f = en.value(x)
    for it in range(1, max_iter + 1):
        g = en.gradient(x)
        ab = en.hessian_banded(x)
        pd = True
        try:
            cb = cholesky_banded(ab, lower=True)
        except LinAlgError:
            if require_pd:
                return x, False, it
            pd = False
            lam = float(eigvals_banded(ab, lower=True, select="i", select_range=(0, 0))[0])
            shift = 2.0 * abs(lam) + 1e-9 * float(np.max(ab[0]))
            ab2 = ab.copy()
            ab2[0] += shift
            cb = cholesky_banded(ab2, lower=True)
        dx = cho_solve_banded((cb, True), -g)
        slope = float(g @ dx)
        if not pd and abs(slope) < 1e-14 * max(1.0, abs(f)):
            # at (or next to) a saddle: push along the softest direction, downhill
            _, v = _softest(en, x)
            dx = 0.05 * v / np.max(np.abs(v))
            slope = -abs(float(g @ dx))
            if en.value(x - dx) < en.value(x + dx):
                dx = -dx
        t = 1.0
        for _ in range(40):
            ft = en.value(x + t * dx)
            if ft <= f + 1e-4 * t * slope or (pd and t == 1.0 and ft <= f + 1e-12 * abs(f)):
                break
            t *= 0.5
        x = x + t * dx
        f = en.value(x)
        if pd and np.max(np.abs(t * dx)) < tol:
            return x, True, it
    return x, False, max_iter


def _softest(en: Energy, x: np.ndarray):
    """Smallest eigenpair of the Hessian (dense; used only at saddles)."""
    from scipy.linalg import eig_banded
    lam, v = eig_banded(en.hessian_banded(x), lower=True, select="i", select_range=(0, 0))
    return float(lam[0]), v[:, 0]


def backbone(en: Energy, x: np.ndarray, points: int, step: float = 0.5) -> np.ndarray:
    """Backbone (points, 3), mm, base frame, evenly spaced in arc length from s = 0 to the tip,
    for the nodal angles x: the frame is integrated with the curvature u_xy of the module
    docstring, piecewise constant on sub-steps of at most ``step`` mm (its value at the
    sub-step's middle, psi linear between nodes) as exact arcs."""
    spec = en.spec
    n = spec.n
    e = en.beta + spec.L
    c = np.clip(en.beta + spec.straight, 0.0, None)
    tip = float(e.max())
    s_out = np.linspace(0.0, tip, points)
    he = np.diff(en.s)
    m = np.maximum(1, np.ceil(he / step)).astype(int)                 # sub-steps per element
    first = np.repeat(np.cumsum(m) - m, m)
    sub = np.repeat(en.s[:-1], m) + (np.arange(m.sum()) - first) / np.repeat(m, m) * np.repeat(he, m)
    g = np.unique(np.concatenate([en.s, sub, s_out]))
    keep = np.concatenate([[True], np.diff(g) > TOL_S])
    g = g[keep]
    sm = 0.5 * (g[1:] + g[:-1])
    hs = np.diff(g)
    pres = sm[:, None] < e[None, :]
    curv = pres & (sm[:, None] >= c[None, :]) & (spec.kappa[None, :] != 0.0)
    EIs = np.sum(np.where(pres, spec.EI[None, :], 0.0), axis=1)
    ux = np.zeros(len(sm))
    uy = np.zeros(len(sm))
    for i in range(n):
        si, pi = en.tube_values(x, i)
        psi = np.interp(sm, si, pi)
        wi = np.where(curv[:, i], spec.EI[i] * spec.kappa[i], 0.0)
        ux -= wi * np.sin(psi)
        uy += wi * np.cos(psi)
    ux /= np.where(EIs > 0, EIs, 1.0)
    uy /= np.where(EIs > 0, EIs, 1.0)
    k = np.hypot(ux, uy)
    th = k * hs
    safe = np.where(k > 0, k, 1.0)
    # displacement in the local frame and rotation over each sub-step (axis (ux, uy, 0) / k)
    a1 = np.where(k > 0, (1.0 - np.cos(th)) / safe ** 2, 0.5 * hs ** 2)
    a0 = np.where(k > 0, np.sin(th) / safe, hs)
    d = np.stack([a1 * uy, -a1 * ux, a0], axis=1)
    ax, ay = np.where(k > 0, ux / safe, 1.0), np.where(k > 0, uy / safe, 0.0)
    sn, cs = np.sin(th), np.cos(th)
    Kx = np.zeros((len(sm), 3, 3))
    Kx[:, 0, 2], Kx[:, 1, 2] = ay, -ax
    Kx[:, 2, 0], Kx[:, 2, 1] = -ay, ax
    Q = np.eye(3)[None] + sn[:, None, None] * Kx + (1.0 - cs)[:, None, None] * (Kx @ Kx)
    # frames before each sub-step: exclusive prefix products Q_0 ... Q_(j-1), by a parallel
    # (Hillis-Steele) scan in log2(steps) batched products
    R = np.concatenate([np.eye(3)[None], Q[:-1]], axis=0)
    shift = 1
    while shift < len(R):
        R[shift:] = R[:-shift] @ R[shift:]
        shift *= 2
    P = np.zeros((len(g), 3))
    P[1:] = np.cumsum(np.einsum("kij,kj->ki", R, d), axis=0)
    idx = np.searchsorted(g, s_out - TOL_S)
    idx = np.clip(idx, 0, len(g) - 1)
    return P[idx]
