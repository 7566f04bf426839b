"""Model error bounds along the shaft: profiles, the tip-to-shaft extension rule, margins.

A model's error bound is a function of arc length. Model files carry (docs/conventions.md):

* ``error_quantiles: {p50, p95, p99, max}`` (mm) — quantiles of the largest deviation along the
  shaft (learned models) or of the tip residual (calibrated models) on held-out data;
* optionally ``error_profile: {fractions: [M], p50: [M], p95: [M], p99: [M], max: [M]}`` (mm) —
  quantiles of the deviation of the backbone point at each arc-length fraction (0 = constraint
  plane, 1 = tip) on held-out data.

``--margin auto`` pads each collision capsule by the profile's p99 at the capsule's arc-length
fractions (the largest value over the capsule's interval: the profile is piecewise linear, so
this is the largest of its end values and the knots inside); without a profile by the uniform
p99 of ``error_quantiles``; a model with neither is **uncalibrated** (:func:`is_calibrated`) and
gets margin 0 unless the user states one.

Extension rule (tip-only data). With only tip residuals measured, the deviation at arc-length
fraction ``f`` is bounded by ``tip_bound * g(f)`` with ``g(f) = f`` (:func:`extend_tip_bound`).
Derivation: to first order a perturbation of the mechanics (a curvature or stiffness error over
a section, a tilt where a tube ends, a rotation or translation error of a joint) changes the
backbone by ``dp(s) = int_0^s dtheta(sigma) x t(sigma) dsigma`` where ``dtheta`` (the frame's
rotation error) is zero before the perturbation's source and grows (or stays) after it: the
deviation is a convex, non-decreasing function of ``s`` that starts at 0 at the constraint
plane, so ``|dp(s)| <= |dp(L)| s / L`` when the contributions do not cancel at the tip (uniform
curvature error: ``(s/L)^2 <= s/L``; rotation at the base: exactly linear; a kink at ``s_k``:
``(s - s_k)/(L - s_k) <= s/L``). Single configurations where sources cancel at the tip break
it; the rule is a statement about quantiles over configurations, and it is checked on the
foreign generator (tests/test_error_bounds.py: a robot ~2-5 mm from nominal with curvature,
stiffness, clearance, torsion and friction-lag differences; the extended p50/p95/p99 cover the
true per-point quantiles at every fraction).

Where a bound was measured (``error_bound``, :func:`error_bound_kind`). A bound is either
``measured`` — the held-out deviation from measurements of a robot (``ctrplan train --real``
on a measured CSV, ``ctrplan diagnose`` and its ``--best`` models): the model is
**calibrated** (:func:`is_calibrated`) — or ``surrogate`` — the held-out deviation of a network
from the simulated model it was trained to imitate (``ctrplan train --sim`` alone; the shipped
``learned`` networks imitate the nominal physics model): the model is an uncalibrated surrogate
and its bound is its **surrogate error** (:func:`surrogate_error`, plan.json's
``surrogate_error``), still what ``--margin auto`` pads with, never called calibrated. Model
files record it (learned ``.pt`` metadata and ``calibrated.yaml``: ``error_bound: measured |
surrogate``; any other value is refused). Files written before the field existed: a
``calibrated.yaml`` is ``measured`` (only ``diagnose`` writes a bound there); a learned file is
``measured`` only when its metadata shows the bound came from measured rows (``data.real`` from
a file, or ``diagnose --best``'s test rows), else ``surrogate``
(:func:`inferred_error_bound`). A model object that carries a bound without saying where it
came from is a ``surrogate``: calibration is a claim that needs its evidence.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

QUANTILES = {"p50": 50.0, "p95": 95.0, "p99": 99.0, "max": 100.0}
#: the quantile ``--margin auto`` uses
MARGIN_QUANTILE = "p99"


@dataclass(frozen=True)
class ErrorProfile:
    """Quantiles of a model's deviation (mm) at arc-length fractions along the shaft.

    fractions : (M,) increasing, in [0, 1] (0 = constraint plane, 1 = tip), M >= 1.
    values : {"p50", "p95", "p99", "max"} -> (M,) mm, finite and >= 0.
    """

    fractions: np.ndarray
    values: Mapping[str, np.ndarray]

    def at(self, f: np.ndarray, quantile: str = MARGIN_QUANTILE) -> np.ndarray:
        """The profile's ``quantile`` interpolated linearly at fractions ``f`` (any shape),
        constant beyond its first and last fraction."""
        return np.interp(np.clip(np.asarray(f, dtype=float), 0.0, 1.0), self.fractions,
                         self.values[quantile])

    def over(self, f0: np.ndarray, f1: np.ndarray, quantile: str = MARGIN_QUANTILE) -> np.ndarray:
        """Largest value of the interpolated ``quantile`` over each interval [f0, f1] (same
        shapes): the larger end value or any knot inside (the profile is piecewise linear)."""
        f0 = np.asarray(f0, dtype=float)
        f1 = np.asarray(f1, dtype=float)
        lo, hi = np.minimum(f0, f1), np.maximum(f0, f1)
        out = np.maximum(self.at(lo, quantile), self.at(hi, quantile))
        # the knots strictly inside (lo, hi) are fractions[i0:i1]: their largest value from a
        # table of range maxima (-inf for an empty range), the same numbers as a knot loop
        fr = np.asarray(self.fractions, dtype=float)
        i0 = np.searchsorted(fr, lo, side="right")
        i1 = np.searchsorted(fr, hi, side="left")
        return np.maximum(out, self._range_max[quantile][i0, i1])

    @functools.cached_property
    def _range_max(self) -> dict[str, np.ndarray]:
        """Per quantile, the (M + 1, M + 1) table whose entry [i, j] is max(values[i:j]),
        -inf where i >= j (M is a few dozen knots at most; kept by this profile)."""
        return {k: _range_max(np.asarray(v, dtype=float)) for k, v in self.values.items()}

    @property
    def peak_mm(self) -> float:
        """Largest p99 anywhere along the shaft (mm)."""
        return float(np.max(self.values[MARGIN_QUANTILE]))

    @property
    def least_mm(self) -> float:
        """Smallest p99 anywhere along the shaft (mm)."""
        return float(np.min(self.values[MARGIN_QUANTILE]))

    def capsule_margins(self, s: np.ndarray, quantile: str = MARGIN_QUANTILE) -> np.ndarray:
        """(B, m - 1) margin (mm) of each capsule of backbones sampled at arc lengths ``s``
        (B, m): the profile's largest value over the capsule's fraction interval
        ``[s_k, s_k+1] / s_tip``."""
        s = np.asarray(s, dtype=float)
        tip = np.where(s[:, -1:] > 0, s[:, -1:], 1.0)
        f = s / tip
        return self.over(f[:, :-1], f[:, 1:], quantile)

    def to_dict(self) -> dict[str, list[float]]:
        """The model-file form ``{fractions, p50, p95, p99, max}`` (plain floats)."""
        d = {"fractions": [float(v) for v in self.fractions]}
        d.update({k: [float(v) for v in self.values[k]] for k in QUANTILES})
        return d

    def key(self) -> tuple:
        """A hashable identity (for caches keyed by margin)."""
        return ("profile",) + tuple(float(v) for v in self.fractions) + tuple(
            float(v) for k in QUANTILES for v in self.values[k])


def _range_max(v: np.ndarray) -> np.ndarray:
    """(M + 1, M + 1) table: entry [i, j] is max(v[i:j]), -inf where i >= j."""
    m = len(v)
    out = np.full((m + 1, m + 1), -np.inf)
    for i in range(m):
        out[i, i + 1:] = np.maximum.accumulate(v[i:])
    out.setflags(write=False)
    return out


def profile_from_dict(data: Any, source: str = "error_profile") -> ErrorProfile:
    """Validate a model file's ``error_profile`` mapping; raises ValueError naming the field."""
    if isinstance(data, ErrorProfile):
        return data
    if not isinstance(data, Mapping):
        raise ValueError(f"{source}: must be a mapping with fractions, {', '.join(QUANTILES)}")
    unknown = set(data) - {"fractions", *QUANTILES}
    if unknown:
        raise ValueError(f"{source}.{sorted(unknown, key=str)[0]}: unknown key")
    arrays = {}
    for k in ("fractions", *QUANTILES):
        if k not in data:
            raise ValueError(f"{source}.{k}: missing")
        try:
            a = np.asarray(data[k], dtype=float).reshape(-1)
        except (TypeError, ValueError):
            raise ValueError(f"{source}.{k}: must be a list of numbers") from None
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{source}.{k}: must be finite numbers")
        arrays[k] = a
    f = arrays["fractions"]
    if f.size < 1 or np.any(f < 0) or np.any(f > 1) or np.any(np.diff(f) <= 0):
        raise ValueError(f"{source}.fractions: must be increasing numbers in [0, 1]")
    for k in QUANTILES:
        if arrays[k].shape != f.shape:
            raise ValueError(f"{source}.{k}: needs {f.size} values (one per fraction), "
                             f"got {arrays[k].size}")
        if np.any(arrays[k] < 0):
            raise ValueError(f"{source}.{k}: must be >= 0 (mm)")
    return ErrorProfile(fractions=f, values={k: arrays[k] for k in QUANTILES})


def profile_from_backbones(predicted: np.ndarray, measured: np.ndarray,
                           fractions: np.ndarray | None = None) -> ErrorProfile:
    """Error profile from held-out backbones: per backbone point, quantiles over the
    configurations of the distance between prediction and measurement.

    predicted, measured : (B, m, 3) mm, sampled at the same arc-length fractions (default
    ``linspace(0, 1, m)``: evenly from the constraint plane to the tip). Rows with a non-finite
    value are skipped. Returns an :class:`ErrorProfile` over those fractions.
    """
    p = np.asarray(predicted, dtype=float)
    q = np.asarray(measured, dtype=float)
    if p.shape != q.shape or p.ndim != 3 or p.shape[-1] != 3 or p.shape[1] < 2:
        raise ValueError(f"predicted and measured must both have shape (B, m>=2, 3), got "
                         f"{p.shape} and {q.shape}")
    return profile_from_deviations(np.linalg.norm(p - q, axis=-1), fractions)


def profile_from_deviations(deviation: np.ndarray,
                            fractions: np.ndarray | None = None) -> ErrorProfile:
    """Error profile from point deviations (B, m) mm at m arc-length fractions (default evenly
    from base 0 to tip 1): per fraction the quantiles over configurations; rows with a
    non-finite value are skipped."""
    dev = np.asarray(deviation, dtype=float)
    if dev.ndim != 2 or dev.shape[1] < 2:
        raise ValueError(f"deviations must have shape (B, m>=2), got {dev.shape}")
    m = dev.shape[1]
    dev = dev[np.all(np.isfinite(dev), axis=1)]
    if len(dev) == 0:
        raise ValueError("no finite held-out backbone to compute an error profile from")
    f = np.linspace(0.0, 1.0, m) if fractions is None else np.asarray(fractions, float)
    vals = {k: np.percentile(dev, v, axis=0) for k, v in QUANTILES.items()}
    return profile_from_dict({"fractions": f, **vals})


def shaft_growth(f: np.ndarray) -> np.ndarray:
    """The extension rule's ``g(f) = f`` (see the module docstring): the fraction of the tip's
    bound that bounds the deviation at arc-length fraction ``f``."""
    return np.clip(np.asarray(f, dtype=float), 0.0, 1.0)


def extend_tip_bound(tip_quantiles: Mapping[str, float], points: int = 11) -> ErrorProfile:
    """An error profile from tip-only quantiles ``{p50, p95, p99, max}`` (mm): each quantile at
    fraction ``f`` is ``tip * g(f)`` (:func:`shaft_growth`), at ``points`` fractions evenly
    from 0 to 1 (g is linear, so 2 points describe it exactly; more make the file readable)."""
    missing = [k for k in QUANTILES if k not in tip_quantiles]
    if missing:
        raise ValueError(f"tip quantiles need keys {', '.join(QUANTILES)} (missing {missing[0]})")
    f = np.linspace(0.0, 1.0, max(2, int(points)))
    g = shaft_growth(f)
    return profile_from_dict({"fractions": f, **{k: float(tip_quantiles[k]) * g for k in QUANTILES}})


def error_profile_of(model) -> ErrorProfile | None:
    """The model's error profile (``model.error_profile``: an ErrorProfile or the file's
    mapping), or None. Raises ValueError on a malformed profile."""
    prof = getattr(model, "error_profile", None)
    if prof is None or (isinstance(prof, Mapping) and not prof):
        return None
    return profile_from_dict(prof)


#: ``error_bound`` values: measured on a robot / a surrogate's error against its simulated model
MEASURED = "measured"
SURROGATE = "surrogate"
ERROR_BOUND_KINDS = (MEASURED, SURROGATE)


def has_error_bound(model) -> bool:
    """True when the model carries an error bound (``error_profile`` or ``error_quantiles``)."""
    try:
        if error_profile_of(model) is not None:
            return True
    except ValueError:
        return False
    return bool(getattr(model, "error_quantiles", None))


def check_error_bound_kind(value: Any, source: str = "error_bound") -> str | None:
    """A model file's ``error_bound`` (None, ``measured`` or ``surrogate``); ValueError naming
    ``source`` otherwise."""
    if value is None or value in ERROR_BOUND_KINDS:
        return value
    raise ValueError(f"{source}: must be {' or '.join(ERROR_BOUND_KINDS)}, got {str(value)[:40]!r}")


def inferred_error_bound(meta: Mapping[str, Any]) -> str:
    """``error_bound`` of a learned model file written before the field existed, from its
    metadata: ``measured`` when the bound's rows were measured (the last data trained on,
    ``data.real``, came from a file rather than the simulated ``hidden-effects:`` rows, or the
    bound is ``diagnose --best``'s test rows), else ``surrogate``."""
    src = meta.get("error_quantiles_source")
    if isinstance(src, Mapping) and str(src.get("part", "")).startswith("best-model"):
        return MEASURED
    data = meta.get("data")
    real = data.get("real") if isinstance(data, Mapping) else None
    if isinstance(real, Mapping) and not str(real.get("source", "")).startswith(
            ("hidden-effects:", "physics:", "<memory>")):
        return MEASURED
    return SURROGATE


def error_bound_kind(model) -> str | None:
    """Where the model's error bound was measured: ``measured`` (on a robot), ``surrogate``
    (against the simulated model a network imitates; also a bound whose origin the model does
    not state), or None (no bound: the nominal physics model)."""
    if not has_error_bound(model):
        return None
    kind = getattr(model, "error_bound", None)
    return kind if kind in ERROR_BOUND_KINDS else SURROGATE


def is_calibrated(model) -> bool:
    """True only when the model carries an error bound measured on a robot
    (:func:`error_bound_kind` is ``measured``). The nominal physics model, a model file
    without quantiles and a surrogate (the shipped learned networks) are uncalibrated: their
    clearances are relative to the nominal model."""
    return error_bound_kind(model) == MEASURED


def surrogate_error(model) -> dict[str, Any] | None:
    """plan.json's ``surrogate_error`` of a surrogate model: its held-out deviation quantiles
    ``{p50, p95, p99, max}`` (mm; the largest along the shaft where only a profile is known)
    and ``against`` (the simulated data it was measured on, e.g.
    ``physics:seed1:n=100000:seed=0``, or null); None for other models."""
    if error_bound_kind(model) != SURROGATE:
        return None
    eq = getattr(model, "error_quantiles", None)
    try:
        prof = error_profile_of(model)
    except ValueError:
        prof = None
    if eq:
        out = {k: float(eq[k]) for k in QUANTILES if k in eq}
    elif prof is not None:
        out = {k: float(np.max(prof.values[k])) for k in QUANTILES}
    else:
        return None
    meta = getattr(model, "meta", None)
    src = meta.get("error_quantiles_source") if isinstance(meta, Mapping) else None
    against = src.get("data") if isinstance(src, Mapping) else None
    out["against"] = None if against is None else str(against)
    return out


def surrogate_of(against: str | None) -> str:
    """Words for what a surrogate imitates, from ``surrogate_error["against"]``."""
    a = str(against or "")
    if a.startswith("physics:"):
        return "the nominal physics model"
    if a.startswith("hidden-effects:"):
        return "a simulated robot with hidden effects"
    return "the simulated model it was trained on"


def auto_margin(model) -> float | ErrorProfile:
    """What ``--margin auto`` pads with: the model's :class:`ErrorProfile` when it has one,
    else the uniform p99 of ``error_quantiles`` (mm), else 0.0 (uncalibrated).
    Raises ValueError on a malformed bound."""
    prof = error_profile_of(model)
    if prof is not None:
        return prof
    from ctrplan.shape.base import model_error_bound

    return model_error_bound(model, MARGIN_QUANTILE)


def margin_peak(margin: float | ErrorProfile | None) -> float:
    """The largest margin (mm) anywhere along the shaft (0 for None)."""
    if margin is None:
        return 0.0
    return margin.peak_mm if isinstance(margin, ErrorProfile) else float(margin)


def margin_least(margin: float | ErrorProfile | None) -> float:
    """The smallest margin (mm) anywhere along the shaft: what can be added back to a clearance
    measured with the padded capsules and stay a lower bound of the unpadded clearance."""
    if margin is None:
        return 0.0
    return margin.least_mm if isinstance(margin, ErrorProfile) else float(margin)


def margin_key(margin: float | ErrorProfile | None) -> Any:
    """A hashable key of a margin (float or profile)."""
    if isinstance(margin, ErrorProfile):
        return margin.key()
    return float(margin or 0.0)


#: insertions within this distance (mm) of the measured range count as measured
MEASURED_SLACK_MM = 1.0


def outside_measured(path: np.ndarray, measured: Mapping[str, Any], n: int) -> int:
    """Number of path states (rows of ``path``, (K, 2n)) with a tube's insertion beta more than
    :data:`MEASURED_SLACK_MM` outside ``measured`` ({"min": [n], "max": [n]} mm)."""
    b = np.asarray(path, dtype=float)[:, n:]
    lo = np.asarray(measured["min"], dtype=float) - MEASURED_SLACK_MM
    hi = np.asarray(measured["max"], dtype=float) + MEASURED_SLACK_MM
    return int(np.sum(np.any((b < lo) | (b > hi), axis=1)))


def measured_text(measured: Mapping[str, Any]) -> str:
    """``measured`` ({"min": [n], "max": [n]} mm) as text, one range per tube."""
    return ", ".join(f"beta{i + 1} {a:.1f} to {b:.1f} mm"
                     for i, (a, b) in enumerate(zip(measured["min"], measured["max"])))
