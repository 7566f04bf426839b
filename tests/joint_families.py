"""The best fit of EVERY family ``diagnose`` may select, together, to a generator form.

``tests/foreign`` makes its effects outside ctrplan's fitted families so that the statistics
on it measure calibration, not ctrplan fitting its own function class. One family at a time is
not enough: ``diagnose`` fits several effects together (forward selection may add any of them,
``load`` and ``torsion`` included; its joint model fits every effect that lowered the BIC; the
nuisances, a drift in time and a tracker field, are fitted to what is left), and combinations
can take in the part of a form its own family misses. So the question for every form is what
the UNION of the families leaves:

* the model: a rigid base with every effect of ``ctrplan.shape.effects`` at once, each with
  every parameter ``diagnose`` fits (``effect_variants``): torsion's compliance; friction in
  one form per fit (the forms are alternatives: ``FRICTION_FORMS``); clearance with both
  harmonics AND the gap length; precurvature; stiffness; registration; joint offsets; load
  (gravity across the axis and the tip force);
* the nuisances, jointly (variable projection): what the model leaves is projected off the
  span of the drift's features (ctrplan's linear spline in the recording time) and the tracker
  field's (a quadratic of the measured position), unpenalised, per axis: a superset of the
  ridge-penalised fits ``diagnose`` makes;
* several starts: ``diagnose``'s own (every effect off), and random starts within the
  parameters' typical magnitudes; the rigid-kernel parameters first (cheap), then torsion and
  the loads added and everything polished together from the best of them.

The misfit is the mean tip error (mm) of the noise-free rows that the best of these fits
leaves, in-sample (a lower bound on what any held-out fit of these families leaves). Imports
ctrplan: this is a claim about ctrplan's families, tested on data ctrplan did not make.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.optimize import least_squares

from ctrplan.calibration.lsq import Problem
from ctrplan.measured import MeasuredData
from ctrplan.robot import load_robot
from ctrplan.shape.effects import (
    EFFECT_NAMES,
    EffectModel,
    effect_params,
    effect_variants,
    off_values,
)
from tests.foreign.robot import robot_path

#: the kernel families that need a slower kernel (added in the polish from the best start)
SLOW = ("torsion", "load")
#: friction forms fitted (one per joint fit; the best is kept): every form label of
#: ``effect_variants("friction")`` with the most parameters of its kind
FRICTION_ALL = ("presliding/windup", "lag/windup", "relative", "end_moment+lag")


@dataclass
class JointFit:
    """effect_mm: mean tip displacement of the form (noise-free, against the same rows without
    it); misfit_mm: what the best joint fit leaves (mean tip error, mm); friction: its form in
    that fit; starts: the misfit of every start before the polish; values: fitted parameters."""

    effect_mm: float
    misfit_mm: float
    friction: str
    starts: list
    values: dict
    nfev: int
    model_misfit: float = math.nan
    modes: dict | None = None


def measured(d, tip=None) -> MeasuredData:
    return MeasuredData(q=np.asarray(d.q, float), tip=np.asarray(d.tip if tip is None else tip, float),
                        time=np.asarray(d.time, float), sweep=np.asarray(d.sweep, dtype=object))


def nuisance_basis(d, knots: int = 10) -> np.ndarray:
    """(B, k) the nuisances' features: the drift's linear spline in the fraction of the
    recording time (``knots`` evenly spaced hat functions, ctrplan's DRIFT_KNOTS) and the
    field's quadratic of the measured tip position (1, x, y, z, x^2, y^2, z^2, xy, xz, yz)."""
    t = np.asarray(d.time, float)
    x = (t - t.min()) / max(np.ptp(t), 1e-12)
    k = np.linspace(0.0, 1.0, knots)
    hat = np.clip(1.0 - np.abs(x[:, None] - k[None, :]) / (k[1] - k[0]), 0.0, None)
    p = np.asarray(d.tip, float)
    c = p - p.mean(0)
    c = c / max(float(np.abs(c).max()), 1e-12)
    X, Y, Z = c.T
    quad = np.stack([X, Y, Z, X * X, Y * Y, Z * Z, X * Y, X * Z, Y * Z], axis=1)
    return np.hstack([hat, quad])          # the hats sum to one: the constant is in their span


def diagnose_nuisances(md: MeasuredData, left: np.ndarray) -> float:
    """Mean norm (mm) of what ctrplan's nuisances, fitted as ``diagnose`` fits them (after the
    robot model, ridge-penalised, on all rows), leave of the residual ``left`` (B, 3): the drift
    and the field one after the other, in the order that leaves less."""
    from ctrplan.calibration.nuisance import _nuisance_features, _ridge

    rows = np.ones(len(md), bool)
    F = {k: _nuisance_features(k, md, rows) for k in ("~drift", "~field")}
    best = math.inf
    for order in (("~drift", "~field"), ("~field", "~drift")):
        r = left.copy()
        for k in order:
            if F[k] is not None:
                r = r - _ridge(F[k], r, rows, k == "~drift")
        best = min(best, float(np.linalg.norm(r, axis=1).mean()))
    return best


def projector(F: np.ndarray) -> np.ndarray:
    """(B, B) projection off the column span of F."""
    Q, s, _ = np.linalg.svd(F, full_matrices=False)
    Q = Q[:, s > 1e-10 * s[0]]
    return np.eye(len(F)) - Q @ Q.T


def _scale(p) -> float:
    typical = p.typical or {"mm": 1.0, "rad": 0.05, "1": 0.1, "m/s^2": 10.0}.get(p.unit, 1.0)
    return min(typical, (p.hi - p.lo) / 2.0)


class _Union:
    """The union of the families for one friction form, with its parameter vector."""

    def __init__(self, robot, friction: str, include: tuple[str, ...]):
        self.robot = robot
        self.fixed: dict[str, dict[str, float]] = {}
        self.specs: list[tuple[str, object]] = []
        for eff in EFFECT_NAMES:
            if eff not in include:
                continue
            variants = {lab: (fx, nm) for lab, fx, nm in effect_variants(eff, robot, "rigid")}
            if eff == "friction":
                fx, names = variants[friction]
            elif eff == "clearance":
                fx, names = {"limit": 0.0}, [*variants["harmonic2"][1], "length"]
            else:
                fx, names = next(iter(variants.values()))
            self.fixed[eff] = {**off_values(eff, robot, "rigid"), **fx}
            ps = {p.name: p for p in effect_params(eff, robot, "rigid")}
            self.specs += [(eff, ps[nm]) for nm in names]
        self.scale = np.array([_scale(p) for _, p in self.specs])
        self.off = np.array([p.off for _, p in self.specs])
        self.lo = (np.array([p.lo for _, p in self.specs]) - self.off) / self.scale
        self.hi = (np.array([p.hi for _, p in self.specs]) - self.off) / self.scale

    def effects(self, z: np.ndarray) -> dict[str, dict[str, float]]:
        eff = {a: dict(b) for a, b in self.fixed.items()}
        for (e, p), zi, s in zip(self.specs, z, self.scale):
            eff[e][p.name] = float(np.clip(p.off + zi * s, p.lo, p.hi))
        return eff

    def z_of(self, values: dict) -> np.ndarray:
        z = np.zeros(len(self.specs))
        for i, (e, p) in enumerate(self.specs):
            v = values.get(e, {}).get(p.name, p.off)
            z[i] = (v - p.off) / self.scale[i]
        return self.inside(z)

    def inside(self, z: np.ndarray) -> np.ndarray:
        """Off bounds (trust-region reflective crawls on a bound), as ctrplan's fit starts."""
        z = np.where(z <= self.lo + 1e-9, np.minimum(self.lo + 1.0, 0.5 * (self.lo + self.hi)), z)
        return np.where(z >= self.hi - 1e-9, np.maximum(self.hi - 1.0, 0.5 * (self.lo + self.hi)), z)


def _solve(prob: Problem, u: _Union, P: np.ndarray, target: np.ndarray, z0: np.ndarray,
           max_nfev: int):
    """Bounded least squares of P (predicted tip - target) from z0; -> (z, misfit mm, nfev)."""
    h = 1e-3

    def res(pts):
        r = P @ (pts[:, -1, :] - target)
        return np.where(np.isfinite(r), r, 100.0).ravel()

    cache: dict[bytes, np.ndarray] = {}

    def fun(z):
        key = z.tobytes()
        if key not in cache:
            cache.clear()
            cache[key] = res(prob.predict_many([u.effects(z)])[0])
        return cache[key]

    def jac(z):
        f0 = fun(z)
        steps = np.where(z + h <= u.hi, h, -h)
        zs = [z + np.eye(len(z))[i] * steps[i] for i in range(len(z))]
        preds = prob.predict_many([u.effects(zi) for zi in zs])
        return np.stack([(res(p) - f0) / s for p, s in zip(preds, steps)], axis=1)

    out = least_squares(fun, z0, jac=jac, bounds=(u.lo, u.hi), method="trf", x_scale=1.0,
                        max_nfev=max_nfev, xtol=1e-8, ftol=1e-8, gtol=1e-10)
    r = out.fun.reshape(-1, 3)
    return out.x, float(np.linalg.norm(r, axis=1).mean()), int(out.nfev + out.njev)


def joint_fit(robot: str, effects: dict, base_data, data, starts: int = 3, seed: int = 0,
              friction_forms: tuple[str, ...] = ("presliding/windup",),
              iters: int = 40, polish_iters: int = 20, nuisances: str = "after") -> JointFit:
    """The best fit of the union of ctrplan's families (module docstring) to ``data``'s
    noise-free tips (``tip_clean``); ``base_data``: the same rows without the effects (for
    the effect's size). ``starts`` starts per friction form on the rigid kernel, then the
    best is polished with torsion and the loads added."""
    r = load_robot(str(robot_path(robot)))
    md = measured(data, data.tip_clean)
    every = np.ones(len(md), bool)
    prob = Problem(EffectModel(r, "rigid"), md, every, every)
    Pn = projector(nuisance_basis(data))
    P = Pn if nuisances == "joint" else np.eye(len(md))
    target = np.asarray(data.tip_clean, float)
    rng = np.random.default_rng(seed)
    fast = tuple(e for e in EFFECT_NAMES if e not in SLOW)
    best = (math.inf, None, None, None)
    tried = []
    nfev = 0
    for form in friction_forms:
        u = _Union(r, form, fast)
        for k in range(starts):
            z0 = u.inside(np.zeros(len(u.specs))) if k == 0 else u.inside(
                np.clip(rng.normal(0.0, 1.0, len(u.specs)), u.lo, u.hi))
            z, mis, nf = _solve(prob, u, P, target, z0, iters)
            nfev += nf
            tried.append((form, k, mis))
            if mis < best[0]:
                best = (mis, form, u, z)
    _, form, u, z = best
    full = _Union(r, form, EFFECT_NAMES)
    z_full, mis, nf = _solve(prob, full, P, target, full.z_of(u.effects(z)), polish_iters)
    nfev += nf
    values = full.effects(z_full) if mis <= best[0] else u.effects(z)
    model_misfit = min(mis, best[0])
    left = prob.predict_many([values])[0][:, -1, :] - target
    after = {"model": model_misfit, "after": float(np.linalg.norm(Pn @ left, axis=1).mean()),
             "diagnose": diagnose_nuisances(md, left)}
    misfit = after.get(nuisances, model_misfit)
    effect = float(np.linalg.norm(data.tip_clean - base_data.tip_clean, axis=1).mean())
    return JointFit(effect, misfit, form, tried, values, nfev, model_misfit, after)


def noise_floor(data) -> tuple[float, float]:
    """The suite's noise floor from a generated data set's own noise (``tip - tip_clean``):
    (mean tip-noise norm, mm; its robust version: the per-axis sd by the MAD, times the mean
    norm of a unit 3-d Gaussian, sqrt(8 / pi))."""
    e = np.asarray(data.tip, float) - np.asarray(data.tip_clean, float)
    mean = float(np.linalg.norm(e, axis=1).mean())
    sd = 1.4826 * float(np.median(np.abs(e - np.median(e, axis=0))))
    return mean, sd * math.sqrt(8.0 / math.pi)
