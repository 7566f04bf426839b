"""Polynomial backbone basis: orthonormal polynomials on s in [0, 1] that vanish at s = 0.

Gram-Schmidt on ``s, s^2, ..., s^K`` with the inner product ``<f, g> = int_0^1 f g ds`` gives
``P_1 .. P_K``; ``P_k`` has degree ``k`` and ``P_k(0) = 0``. With ``K = 5`` the coefficients
are the ones quoted in the literature (P1 = 1.7321 s, P2 = -6.7082 s + 8.9943 s^2, ...).

A backbone is ``x(q, s) = len(q) * sum_k c_k P_k(s / len(q))`` (same for y and z), ``len(q)``
the arc length from the constraint plane to the tip, so the coefficients ``c`` (K, 3) are
dimensionless and the base point is always the origin.

The orthogonalisation runs in exact rational arithmetic (:mod:`fractions`); only the final
normalisation by the square root of each norm is rounded, so the coefficients are correct to
double precision for every K used here.
"""

from __future__ import annotations

import math
from fractions import Fraction
from functools import cache

import numpy as np

#: Default number of basis terms of the learned model (see ctrplan/data/models/README.md for
#: the fit-accuracy trade-off on seed1 that chose it).
DEFAULT_TERMS = 7
MAX_TERMS = 12


def _inner(a: list[Fraction], b: list[Fraction]) -> Fraction:
    """<f, g> on [0, 1] for f = sum a_j s^(j+1), g = sum b_j s^(j+1)."""
    tot = Fraction(0)
    for i, ai in enumerate(a):
        if ai == 0:
            continue
        for j, bj in enumerate(b):
            if bj:
                tot += ai * bj / (i + j + 3)  # int_0^1 s^(i+1) s^(j+1) ds = 1 / (i + j + 3)
    return tot


@cache
def _coefficients(terms: int) -> tuple[tuple[float, ...], ...]:
    ortho: list[list[Fraction]] = []
    norms: list[Fraction] = []
    for k in range(terms):
        v = [Fraction(0)] * terms
        v[k] = Fraction(1)
        for u, nu in zip(ortho, norms):
            f = _inner(v, u) / nu
            v = [vi - f * ui for vi, ui in zip(v, u)]
        ortho.append(v)
        norms.append(_inner(v, v))
    return tuple(tuple(float(c) / math.sqrt(float(n)) for c in v) for v, n in zip(ortho, norms))


def coefficients(terms: int = DEFAULT_TERMS) -> np.ndarray:
    """(K, K) array ``C`` with ``P_k(s) = sum_j C[k, j] s^(j+1)`` (row k = polynomial k+1)."""
    terms = int(terms)
    if not 1 <= terms <= MAX_TERMS:
        raise ValueError(f"terms must be in 1..{MAX_TERMS}, got {terms}")
    return np.array(_coefficients(terms), dtype=float)


def evaluate(s: np.ndarray, terms: int = DEFAULT_TERMS) -> np.ndarray:
    """Basis values ``P_k(s)``; s (...,) in [0, 1] -> (..., K)."""
    s = np.asarray(s, dtype=float)
    C = coefficients(terms)
    powers = s[..., None] ** np.arange(1, terms + 1)  # (..., K)
    return powers @ C.T


def design_matrix(points: int, terms: int = DEFAULT_TERMS) -> np.ndarray:
    """(points, K) basis values at ``points`` evenly spaced s in [0, 1] (0 and 1 included)."""
    if points < 2:
        raise ValueError("points must be >= 2 (base and tip)")
    return evaluate(np.linspace(0.0, 1.0, int(points)), terms)


def fit(points: np.ndarray, length: np.ndarray, terms: int = DEFAULT_TERMS) -> np.ndarray:
    """Least-squares coefficients of backbones sampled evenly in arc length.

    points : (B, m, 3) mm, base to tip; length : (B,) mm arc length. Returns (B, K, 3).
    """
    points = np.asarray(points, dtype=float)
    length = np.asarray(length, dtype=float).reshape(-1)
    Phi = design_matrix(points.shape[1], terms)
    pinv = np.linalg.pinv(Phi)  # (K, m)
    return np.einsum("km,bmc->bkc", pinv, points / length[:, None, None])


def reconstruct(coef: np.ndarray, length: np.ndarray, points: int) -> np.ndarray:
    """Backbones (B, points, 3) mm from coefficients (B, K, 3) and arc lengths (B,) mm."""
    coef = np.asarray(coef, dtype=float)
    Phi = design_matrix(points, coef.shape[1])
    return np.asarray(length, dtype=float).reshape(-1)[:, None, None] * np.einsum("mk,bkc->bmc", Phi, coef)


def fit_report(points: np.ndarray, length: np.ndarray, terms_list=range(3, 9)) -> list[dict]:
    """How well K-term bases represent backbones: per K, mean/std/max over the batch of the
    maximum point deviation (mm) between each backbone and its least-squares fit."""
    rows = []
    for K in terms_list:
        rec = reconstruct(fit(points, length, K), length, points.shape[1])
        dev = np.linalg.norm(rec - points, axis=2).max(axis=1)
        rows.append({"terms": int(K), "mean_max_dev_mm": float(dev.mean()),
                     "std_max_dev_mm": float(dev.std()), "p95_max_dev_mm": float(np.percentile(dev, 95)),
                     "worst_max_dev_mm": float(dev.max())})
    return rows
