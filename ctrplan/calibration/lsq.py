"""Bounded nonlinear least squares of effect parameters against measured data: the engine
(:class:`Problem`) that the screening and selection stage (:mod:`ctrplan.calibration.select`)
and the fit stage (:mod:`ctrplan.calibration.fit`) both use; not a stage itself.

Every residual evaluation is one batched kernel call over the rows the problem uses (its
training and held-out rows; the joint-space stage, friction's history included, runs on all
rows in order of motion); the finite-difference Jacobian stacks all perturbed parameter sets
into one kernel call as well. Parameters that act only on the sensor side (``registration``)
reuse the mechanics solve.

Where the compliant model has two stable equilibria at a measured configuration (it probes for
the second one), the row is predicted on the one nearer its measurement: the branch the robot
was on (:meth:`Problem._on_measured_branch`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from ctrplan.measured import MeasuredData
from ctrplan.shape.branches import probing
from ctrplan.shape.effects import EffectModel, Param, Prepared, effect_params, prepare, to_sensor
from ctrplan.shape.physics import MechanicsParams

#: Penalty (mm) for a coordinate whose predicted shape is not finite.
NONFINITE_MM = 100.0

#: Effects whose parameters act only after the mechanics solve.
_SENSOR_SIDE = {"registration"}


@dataclass
class FitResult:
    """Fitted parameters of some effects.

    effects : complete parameter dicts of every effect in the model (fixed + fitted).
    values / sigma : fitted parameter -> value / standard uncertainty (from the Jacobian).
    rss : residual sum of squares on the training rows (mm^2); n_res : number of residuals.
    test_mean / test_max : held-out tip error (mm); train_mean : training tip error (mm).
    """

    effects: dict[str, dict[str, float]]
    values: dict[str, dict[str, float]] = field(default_factory=dict)
    sigma: dict[str, dict[str, float]] = field(default_factory=dict)
    rss: float = math.nan
    n_res: int = 0
    k: int = 0
    test_mean: float = math.nan
    test_max: float = math.nan
    train_mean: float = math.nan
    nfev: int = 0

    def bic(self) -> float:
        """Bayesian information criterion of the fit (Gaussian residuals, unknown variance)."""
        n = max(self.n_res, 1)
        return n * math.log(max(self.rss, 1e-300) / n) + self.k * math.log(n)


class Problem:
    """Data + base model + train/test masks; evaluates tip/backbone predictions in batches."""

    def __init__(self, model: EffectModel, data: MeasuredData, train: np.ndarray, test: np.ndarray):
        self.model = model
        self.robot = model.robot
        self.data = data
        self.train = np.asarray(train, dtype=bool)
        self.test = np.asarray(test, dtype=bool)
        #: rows a fit or a score solves (the others are NaN in its predictions)
        self.rows = self.train | self.test
        self.m = data.points.shape[1] if data.points is not None else 2
        self.sweep = data.sweeps()
        target = data.points if data.points is not None else np.stack(
            [np.full_like(data.tip, np.nan), data.tip], axis=1)
        self.target = target                       # (B, m, 3); row 0 unused without shapes
        self.target_raw = target
        self.tip = data.tip
        self.use = slice(None) if data.points is not None else slice(1, 2)
        self.evals = 0
        #: (B,) bool: rows of the last prediction (of the last effect set in it) where the model
        #: has two stable equilibria and the one nearer the measured tip was not the one the
        #: solve picks (:meth:`_on_measured_branch`)
        self.last_other_branch = np.zeros(len(data), dtype=bool)
        #: (B,) bool: rows of the last prediction where the model has two stable equilibria
        self.last_bistable = np.zeros(len(data), dtype=bool)
        #: smallest scale (mm per coordinate) of the robust soft-L1 loss; None: least squares
        self.robust: float | None = None

    # -------------------------------------------------------------- predictions
    def predict_many(self, effect_sets: Sequence[Mapping[str, Mapping[str, float]]],
                     rows: np.ndarray | None = None, probe: bool = True) -> list[np.ndarray]:
        """Predicted points (B, m, 3) for each complete effect set, one kernel call in all;
        ``rows`` (B,) bool: solve only these rows (the others are NaN; default all).
        ``probe``: the compliant model also probes for a second stable equilibrium where the
        first one found is stable (False inside a fit's iterations: the probe doubles the cost
        of a solve, and the robust loss already bounds what a row on the other branch weighs;
        every score and prediction of a fitted model probes)."""
        B = len(self.data)
        preps = [prepare(self.robot, self.model.base, e, self.data.q, self.sweep) for e in effect_sets]
        if rows is not None and not np.all(rows):
            return self._predict_rows(effect_sets, preps, np.flatnonzero(rows), probe)
        return self._solve(effect_sets, preps, B, np.arange(B), probe)

    def _solve(self, effect_sets, preps, B: int, idx: np.ndarray,
               probe: bool = True) -> list[np.ndarray]:
        """One kernel call for the prepared sets ``preps`` (rows B each, the data rows ``idx``):
        points in the sensor frame per set. Where a set's compliant mechanics has two stable
        equilibria (:attr:`ctrplan.shape.physics.SolveInfo.bistable`) the row's prediction is
        the one nearer its measured tip (:meth:`_on_measured_branch`)."""
        # sets that differ only in sensor-side parameters share a solve
        keys: list[int] = []
        uniq: list[int] = []
        for i, e in enumerate(effect_sets):
            found = -1
            for u in uniq:
                if _same_mechanics(effect_sets[u], e):
                    found = u
                    break
            if found < 0:
                uniq.append(i)
                found = i
            keys.append(found)
        tors = any(preps[u].torsion for u in uniq)
        q = np.concatenate([preps[u].q for u in uniq])
        params = MechanicsParams(
            kappa=np.concatenate([preps[u].params.kappa for u in uniq]),
            EI=np.concatenate([preps[u].params.EI for u in uniq]),
            ratio=np.concatenate([preps[u].params.ratio if preps[u].torsion
                                  else np.zeros_like(preps[u].params.ratio) for u in uniq]),
            kink=np.concatenate([preps[u].params.kink for u in uniq]),
            **_loads_of([preps[u].params for u in uniq]),
        )
        # the compliant model probes for a second stable equilibrium: a row's branch can only
        # be told from its measurement where both are known (_on_measured_branch); without the
        # probe, the second is known where the first one found was unstable
        if tors:
            phys = probing(self.model)._compliant if probe else self.model._compliant
        else:
            phys = self.model._rigid
        pts = phys.solve(q, self.m, params).points
        self.evals += 1
        alt = self._other_branch(phys, q, params) if tors else None
        out = []
        for i, e in enumerate(effect_sets):
            j = uniq.index(keys[i])
            part = slice(j * B, (j + 1) * B)
            self.last_other_branch = np.zeros(len(self.data), dtype=bool)
            self.last_bistable = np.zeros(len(self.data), dtype=bool)
            p = to_sensor(e, pts[part])
            if alt is not None and alt[0][part].any():
                self.last_bistable[idx[alt[0][part]]] = True
                p = self._on_measured_branch(e, p, alt, part, idx)
            out.append(p)
        return out

    def _other_branch(self, phys, q: np.ndarray, params: MechanicsParams):
        """(mask (R,), points (R, m, 3)) of the other stable equilibrium of the rows of the last
        solve where the model found two; None where it found none."""
        info = phys.last_info
        bi = None if info is None else info.bistable
        if bi is None or not bi.any():
            return None
        rows = np.flatnonzero(bi)
        other = np.full((len(q), self.m, 3), np.nan)
        sh = phys.solve(q[rows], self.m, _take(params, rows), uz_init=info.uz0_alt[rows])
        other[rows] = np.where(sh.ok[:, None, None], sh.points, np.nan)
        self.evals += 1
        return np.isfinite(other).all(axis=(1, 2)), other

    def _on_measured_branch(self, effects, pts: np.ndarray, alt, part: slice,
                            idx: np.ndarray) -> np.ndarray:
        """``pts`` (sensor frame) with each bistable row's prediction on the equilibrium nearer
        its measured tip, and :attr:`last_other_branch` set for those rows.

        Why: where the model has two stable equilibria the configuration alone does not say
        which shape the tubes take; the robot's history does (it stays on its branch until the
        branch ends). A plan starts from the robot's measured state and follows its branch
        (branch tracking), so the model's error on a measured row is its error on the branch
        the robot was measured on, identified here from the tip."""
        has, other = alt[0][part], to_sensor(effects, alt[1][part])
        tip = self.tip[idx]
        d0 = np.linalg.norm(pts[:, -1] - tip, axis=1)
        d1 = np.linalg.norm(other[:, -1] - tip, axis=1)
        use = has & np.isfinite(d1) & (~np.isfinite(d0) | (d1 < d0))
        if not use.any():
            return pts
        pts = pts.copy()
        pts[use] = other[use]
        self.last_other_branch[idx[use]] = True
        return pts

    def _predict_rows(self, effect_sets, preps, idx: np.ndarray,
                      probe: bool = True) -> list[np.ndarray]:
        """:meth:`predict_many` on the rows ``idx`` only (the joint-space stage ran on all)."""
        B = len(self.data)
        sub = [Prepared(q=p.q[idx], params=_take(p.params, idx), torsion=p.torsion)
               for p in preps]
        out = []
        for pts in self._solve(effect_sets, sub, len(idx), idx, probe):
            full = np.full((B, self.m, 3), np.nan)
            full[idx] = pts
            out.append(full)
        return out

    def errors(self, pts: np.ndarray) -> np.ndarray:
        """(B,) tip error (mm); non-finite predictions count as NONFINITE_MM."""
        e = np.linalg.norm(pts[:, -1, :] - self.tip, axis=1)
        return np.where(np.isfinite(e), e, NONFINITE_MM)

    def set_correction(self, corr: np.ndarray | None) -> None:
        """Subtract a sensor-side correction (B, m, 3) mm from the measurements (a nuisance
        outside the effect vocabulary, e.g. a drift in time); None restores the data."""
        if corr is None:
            self.target = self.target_raw
            self.tip = self.data.tip
        else:
            self.target = self.target_raw - corr
            self.tip = self.data.tip - corr[:, -1, :]

    def residual(self, pts: np.ndarray, rows: np.ndarray) -> np.ndarray:
        r = (pts[rows][:, self.use, :] - self.target[rows][:, self.use, :]).ravel()
        return np.where(np.isfinite(r), r, NONFINITE_MM)

    def score(self, effects: Mapping[str, Mapping[str, float]], pts: np.ndarray | None = None,
              k: int = 0) -> FitResult:
        """Errors of a complete effect set without fitting."""
        if pts is None:
            pts = self.predict_many([effects], self.rows)[0]
        r = self.residual(pts, self.train)
        e = self.errors(pts)
        return FitResult(effects={a: dict(b) for a, b in effects.items()}, rss=float(r @ r),
                         n_res=r.size, k=k, test_mean=float(e[self.test].mean()),
                         test_max=float(e[self.test].max()), train_mean=float(e[self.train].mean()))

    # -------------------------------------------------------------- fitting
    def _start(self, fixed: Mapping[str, Mapping[str, float]], free: Mapping[str, Sequence[str]],
               start: Mapping[str, Mapping[str, float]] | None):
        """(complete effects, free (effect, Param) specs, scales, scaled bounds lo / hi, scaled
        start z0) of a fit; parameters are scaled as ``(value - off) / scale``."""
        base = {a: dict(b) for a, b in fixed.items()}
        specs: list[tuple[str, Param]] = []
        for eff, names in free.items():
            ps = {p.name: p for p in effect_params(eff, self.robot, self.model.base)}
            specs += [(eff, ps[nm]) for nm in names]
        if start:
            for eff, vals in start.items():
                base.setdefault(eff, {}).update(vals)
        scale = np.array([param_scale(p) for _, p in specs])
        offv = np.array([p.off for _, p in specs])
        lo = (np.array([p.lo for _, p in specs]) - offv) / scale
        hi = (np.array([p.hi for _, p in specs]) - offv) / scale
        z0 = np.array([(base[e][p.name] - p.off) / s for (e, p), s in zip(specs, scale)])
        # why: trust-region reflective crawls when started on a bound (the Coleman-Li scaling
        # shrinks steps there), and many effects are off at a bound (lengths, lost angles)
        z0 = np.where(z0 <= lo + 1e-9, np.minimum(lo + 1.0, 0.5 * (lo + hi)), z0)
        z0 = np.where(z0 >= hi - 1e-9, np.maximum(hi - 1.0, 0.5 * (lo + hi)), z0)
        return base, specs, scale, lo, hi, z0

    def fit(self, fixed: Mapping[str, Mapping[str, float]], free: Mapping[str, Sequence[str]],
            start: Mapping[str, Mapping[str, float]] | None = None, max_iter: int = 20,
            k_total: int | None = None) -> FitResult:
        """Fit the ``free`` parameters (effect -> names) with everything else held at ``fixed``.

        ``fixed`` must hold complete dicts of every effect (free ones included, as start values
        unless ``start`` overrides them). ``k_total`` (default: the number of free parameters) is
        the parameter count used by the information criterion.
        """
        base, specs, scale, lo, hi, z0 = self._start(fixed, free, start)
        h = 1e-3

        def effects_at(z: np.ndarray) -> dict[str, dict[str, float]]:
            eff = {a: dict(b) for a, b in base.items()}
            for (e, p), zi, s in zip(specs, z, scale):
                eff[e][p.name] = float(np.clip(p.off + zi * s, p.lo, p.hi))
            return eff

        cache: dict[bytes, np.ndarray] = {}

        def fun(z: np.ndarray) -> np.ndarray:
            key = z.tobytes()
            if key not in cache:
                cache.clear()
                cache[key] = self.predict_many([effects_at(z)], self.rows, probe=False)[0]
            return self.residual(cache[key], self.train)

        def jac(z: np.ndarray) -> np.ndarray:
            f0 = fun(z)
            zs = []
            steps = []
            for i in range(len(z)):
                zi = z.copy()
                step = h if z[i] + h <= hi[i] else -h
                zi[i] += step
                zs.append(zi)
                steps.append(step)
            preds = self.predict_many([effects_at(zi) for zi in zs], self.rows, probe=False)
            J = np.empty((f0.size, len(z)))
            for i, p in enumerate(preds):
                J[:, i] = (self.residual(p, self.train) - f0) / steps[i]
            return J

        if len(specs):
            loss, f_scale = "linear", 1.0
            if self.robust is not None:
                # why: a scale from the noise floor alone would treat every row as an outlier
                # while the model is still far off; 3 robust sd of the start residual keeps the
                # fit least squares for the bulk of the rows and down-weights only the rows far
                # beyond them (tracker glitches, mis-synchronised samples)
                r0 = fun(z0)
                mad = float(np.median(np.abs(r0 - np.median(r0)))) * 1.4826
                loss, f_scale = "soft_l1", max(float(self.robust), 3.0 * mad)
            res = least_squares(fun, z0, jac=jac, bounds=(lo, hi), method="trf", x_scale=1.0,
                                max_nfev=max_iter, xtol=1e-6, ftol=1e-6, gtol=1e-8,
                                loss=loss, f_scale=f_scale)
            z = res.x
            J = res.jac
            nfev = int(res.nfev + res.njev)
        else:
            z = z0
            J = np.zeros((0, 0))
            nfev = 0
        eff = effects_at(z)
        pts = self.predict_many([eff], self.rows)[0]
        out = self.score(eff, pts, k=len(specs) if k_total is None else k_total)
        out.nfev = nfev
        sig = _uncertainty(J, out.rss, out.n_res) * scale if len(specs) else np.zeros(0)
        for (e, p), s in zip(specs, sig):
            out.values.setdefault(e, {})[p.name] = eff[e][p.name]
            out.sigma.setdefault(e, {})[p.name] = float(s)
        return out


def _take(p: MechanicsParams, idx: np.ndarray) -> MechanicsParams:
    """The parameter arrays of the rows ``idx``."""
    def pick(a):
        return None if a is None else a[idx]

    return MechanicsParams(kappa=p.kappa[idx], EI=p.EI[idx], ratio=p.ratio[idx],
                           kink=p.kink[idx], weight=pick(p.weight), force=pick(p.force),
                           moment=pick(p.moment))


def _loads_of(params: Sequence[MechanicsParams]) -> dict[str, np.ndarray]:
    """The load arrays of several parameter sets stacked (zeros where a set has none)."""
    out: dict[str, np.ndarray] = {}
    for name, tail in (("weight", params[0].EI.shape[1:] + (3,)), ("force", (3,)),
                       ("moment", (3,))):
        if any(getattr(p, name) is not None for p in params):
            out[name] = np.concatenate([np.zeros((len(p.EI),) + tail) if getattr(p, name) is None
                                        else getattr(p, name) for p in params])
    return out


def _same_mechanics(a: Mapping[str, Mapping[str, float]], b: Mapping[str, Mapping[str, float]]) -> bool:
    ka = {k for k in a if k not in _SENSOR_SIDE}
    kb = {k for k in b if k not in _SENSOR_SIDE}
    return ka == kb and all(a[k] == b[k] for k in ka)


def param_scale(p: Param) -> float:
    """A typical magnitude of a parameter (the unit of the optimiser's variable)."""
    # m/s^2 (load: gravity): light tubes sag little per m/s^2; a finer finite-difference step
    # at load off would compare the loaded kernel with the unloaded one, whose discretisations
    # differ by ~1e-4 mm
    typical = p.typical or {"mm": 1.0, "rad": 0.05, "1": 0.1, "m/s^2": 10.0}.get(p.unit, 1.0)
    return min(typical, (p.hi - p.lo) / 2.0)


def _uncertainty(J: np.ndarray, rss: float, n: int) -> np.ndarray:
    k = J.shape[1]
    if k == 0:
        return np.zeros(0)
    s2 = rss / max(n - k, 1)
    cov = np.linalg.pinv(J.T @ J) * s2
    return np.sqrt(np.clip(np.diag(cov), 0.0, None))

