"""One held-out splitter for every workflow that measures a model on rows it did not see
(``ctrplan diagnose``, ``diagnose --best``, ``ctrplan train``): :func:`split`.

Rows are cut into three roles: **fit** rows (parameters are fitted on them), **validation**
rows (effects, forms, variants and the fallback are chosen on them) and **test** rows (they
choose nothing; they only report the errors and the error bound). Rows between a test block and
the development rows may be left out altogether (the **gap**). The unit that is held out
depends on the data:

* **whole sweeps** - the rows are independent samples (every row its own sweep, or no sweep
  ids and no order of motion), or there are at least :data:`MIN_SWEEPS_WHOLE` sweeps: a seeded
  random order of the sweeps (rows), ``round(test * S)`` test sweeps (at least one, at most
  half of the rest), then ``round(val * S)`` validation sweeps, the rest fit.
* **blocks with gaps** - a continuous recording (fewer sweeps): every sweep is cut into
  ``L`` contiguous blocks (:func:`blocks_per_sweep`: 8, more for long sweeps), so that every
  role sees every sweep (a few experiments of one kind each would otherwise leave the fit rows
  without, e.g., any rotation). Test blocks are evenly spaced and end the sweep (blocks
  ``L/k - 1, 2L/k - 1, ...`` for ``k`` test blocks), validation blocks halfway between them.
  Rows within ``gap`` rows of a test block (in the same sweep) are left out: the gap is the
  **autocorrelation length of the commanded motion** (:func:`autocorrelation_rows`), so a
  test row's configuration is not a near copy of a fit row's (neighbouring rows of a slow
  trajectory differ by little more than the noise, and a flexible model fitted on one
  predicts the other). The gap is at most half a block; a sweep too short for that is
  flagged (``capped``), and the report warns.

The commanded configurations (not the measurements) set the gap, so every row may be used to
compute it. The number of independent test units (:attr:`HeldOut.test_units`: test sweeps,
test blocks, or test rows) is what the held-out numbers rest on; reports state it.

Layer: this module imports only numpy; calibration and shape both use it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["HeldOut", "split", "autocorrelation_rows", "blocks_per_sweep", "is_ordered",
           "MIN_SWEEPS_WHOLE", "BLOCK_TAG", "row_ranges"]

#: fewer sweeps than this (in order of motion): every sweep is cut into blocks (each role sees
#: every sweep)
MIN_SWEEPS_WHOLE = 8
#: blocks per sweep: at least this many (roles 8 apart: fit, validation, fit, test, ...)
MIN_BLOCKS = 8
#: and at most this many
MAX_BLOCKS = 32
#: a long sweep gets more blocks (more independent test blocks), each block at least this many
#: autocorrelation lengths long (so a gap takes at most a quarter of a neighbouring block)
BLOCK_GAPS = 4
#: the autocorrelation length is the first lag at which the motion's autocorrelation falls
#: below this level (1/e)
ACF_LEVEL = math.exp(-1.0)
#: labels of blocks: ``"<sweep>#block<k>"``
BLOCK_TAG = "#block"


@dataclass(frozen=True)
class HeldOut:
    """A split of B rows (module docstring). Masks are (B,) bool; ``labels`` (B,) object names
    the unit of each row (its sweep, ``"<sweep>#block<k>"`` or ``"row<k>"``); ``kind`` is
    ``"whole sweeps"``, ``"blocks"`` or ``"rows"``; ``test_units`` the number of independent
    test units; ``autocorrelation_rows`` the motion's autocorrelation length (rows; 0 when not
    measured) and ``gap_rows`` the gap left on each side of a test block (``capped``: shorter
    than the autocorrelation length in some sweep)."""

    fit: np.ndarray
    val: np.ndarray
    test: np.ndarray
    gap: np.ndarray
    labels: np.ndarray
    kind: str
    test_units: int
    autocorrelation_rows: int = 0
    gap_rows: int = 0
    capped: bool = False

    @property
    def dev(self) -> np.ndarray:
        """Development rows: fit | validation."""
        return self.fit | self.val

    def describe(self) -> dict:
        """JSON-ready description (report.json ``split``; docs/conventions.md)."""
        return {"kind": self.kind, "independent_test_blocks": int(self.test_units),
                "autocorrelation_rows": int(self.autocorrelation_rows),
                "gap_rows": int(self.gap_rows), "gap_rows_left_out": int(self.gap.sum()),
                "gap_capped": bool(self.capped),
                "gap_rule": "rows within the commanded motion's autocorrelation length (first "
                            "lag below 1/e) of a test block are left out; at most half a block"
                            if self.kind == "blocks" else "none (whole units held out)"}


def is_ordered(sweep: np.ndarray | None, rows: int) -> bool:
    """Rows are in order of motion unless every row is its own sweep (independent samples)."""
    if sweep is None:
        return True
    return len(set(np.asarray(sweep).tolist())) < max(2, rows // 2)


def split(sweep: np.ndarray | None, rows: int, test: float = 0.25, val: float = 0.25,
          seed: int = 0, q: np.ndarray | None = None, ordered: bool | None = None) -> HeldOut:
    """Fit / validation / test / gap rows of ``rows`` rows (module docstring).

    sweep : (B,) sweep ids or None (one sweep). test / val : fractions of the units for test
    and validation (val may be 0: no validation rows). q : (B, 2n) commanded configurations
    (rad, mm), for the gap; None: no gap. ordered : rows in order of motion (default
    :func:`is_ordered`; False with no sweep ids: independent rows).
    """
    B = int(rows)
    if ordered is None:
        ordered = is_ordered(sweep, B)
    if sweep is None:
        sw = (np.full(B, "0", dtype=object) if ordered
              else np.array([f"row{i}" for i in range(B)], dtype=object))
    else:
        sw = np.asarray(sweep, dtype=object)
    names = list(dict.fromkeys(sw.tolist()))
    if not ordered or len(names) >= MIN_SWEEPS_WHOLE:
        return _whole(sw, names, test, val, seed, "whole sweeps" if ordered else "rows")
    return _blocks(sw, names, test, val, q)


def _whole(sw: np.ndarray, names: list, test: float, val: float, seed: int,
           kind: str) -> HeldOut:
    """Whole units (sweeps or rows) in a seeded random order: test first, then validation."""
    S = len(names)
    rng = np.random.default_rng(seed)
    order = [names[i] for i in rng.permutation(S)]
    k = max(1, min(int(round(test * S)), (S - 1) // 2)) if S > 1 else 0
    kv = 0 if val <= 0 else max(1, min(int(round(val * S)), S - k - 1))
    held, valn = set(order[:k]), set(order[k:k + kv])
    lst = sw.tolist()
    t = np.array([s in held for s in lst], dtype=bool)
    v = np.array([s in valn for s in lst], dtype=bool)
    none = np.zeros(len(sw), dtype=bool)
    return HeldOut(~t & ~v, v, t, none, sw.copy(), kind, k)


def _blocks(sw: np.ndarray, names: list, test: float, val: float,
            q: np.ndarray | None) -> HeldOut:
    """Every sweep cut into blocks; evenly spaced test blocks with gaps (module docstring)."""
    B = len(sw)
    g = autocorrelation_rows(q, sw) if q is not None else 0
    fit = np.zeros(B, dtype=bool)
    v_m, t_m, gap = fit.copy(), fit.copy(), fit.copy()
    labels = np.empty(B, dtype=object)
    units, gap_used, capped = 0, 0, False
    for nm in names:
        idx = np.flatnonzero(sw == nm)
        m = len(idx)
        L = min(blocks_per_sweep(m, g), max(m, 1))
        b = np.minimum((np.arange(m) * L) // max(m, 1), L - 1)
        labels[idx] = [f"{nm}{BLOCK_TAG}{j}" for j in b]
        tests, vals = _block_roles(L, test, val)
        is_t = np.isin(b, tests)
        is_v = np.isin(b, vals)
        gs = min(g, m // (2 * L))
        capped |= gs < g
        gap_used = max(gap_used, gs)
        near = _near(is_t, gs) & ~is_t
        t_m[idx] = is_t
        v_m[idx] = is_v & ~near
        gap[idx] = near
        fit[idx] = ~is_t & ~is_v & ~near
        units += len(tests) if m else 0
    return HeldOut(fit, v_m, t_m, gap, labels, "blocks", units, g, gap_used, capped)


def _near(mask: np.ndarray, g: int) -> np.ndarray:
    """(m,) rows within ``g`` rows of a True row of ``mask`` (along one sweep)."""
    if g <= 0 or not mask.any():
        return np.zeros_like(mask)
    c = np.convolve(mask.astype(int), np.ones(2 * g + 1, dtype=int), mode="same")
    return c > 0


def _block_roles(L: int, test: float, val: float) -> tuple[list[int], list[int]]:
    """Test and validation block indices of a sweep cut into ``L`` blocks: ``k`` test blocks
    ending each ``L/k`` (the last block is a test block), validation blocks halfway between."""
    k = max(1, min(int(round(test * L)), L - 1))
    tests = sorted({int((i + 1) * L / k) - 1 for i in range(k)})
    vals: list[int] = []
    kv = 0 if val <= 0 else max(1, min(int(round(val * L)), L - len(tests) - 1))
    free = [j for j in range(L) if j not in tests]
    for i in range(kv):
        want = max(0, int((i + 0.5) * L / kv) - 1)
        pick = min((j for j in free if j not in vals), key=lambda j: (abs(j - want), j),
                   default=None)
        if pick is not None:
            vals.append(pick)
    return tests, sorted(vals)


def blocks_per_sweep(m: int, g: int) -> int:
    """Blocks a sweep of ``m`` rows is cut into: :data:`MIN_BLOCKS`, and more (a multiple of 4,
    at most :data:`MAX_BLOCKS`) while each block stays :data:`BLOCK_GAPS` autocorrelation
    lengths ``g`` long."""
    per = 4 * (m // (4 * BLOCK_GAPS * max(g, 1)))
    return int(min(MAX_BLOCKS, max(MIN_BLOCKS, per)))


def autocorrelation_rows(q: np.ndarray, sweep: np.ndarray | None = None) -> int:
    """Autocorrelation length (rows) of the commanded motion: the first lag at which the
    autocorrelation of the configuration, pooled over sweeps and coordinates, falls below
    :data:`ACF_LEVEL`. Coordinates: cos and sin of every rotation, every insertion scaled to
    unit variance; each centred per sweep. q : (B, 2n) rad, mm, rows in order of motion.
    Returns 0 for fewer than 4 rows in every sweep; the longest sweep's half when the
    autocorrelation never falls that low."""
    q = np.asarray(q, dtype=float)
    if q.ndim != 2 or len(q) < 4:
        return 0
    n = q.shape[1] // 2
    b = q[:, n:]
    sd = b.std(axis=0)
    X = np.hstack([np.cos(q[:, :n]), np.sin(q[:, :n]), b / np.where(sd > 0, sd, 1.0)])
    X = np.where(np.isfinite(X), X, 0.0)
    sw = np.zeros(len(q), dtype=object) if sweep is None else np.asarray(sweep, dtype=object)
    names = list(dict.fromkeys(sw.tolist()))
    longest = max(int((sw == nm).sum()) for nm in names)
    if longest < 4:
        return 0
    acf = np.zeros(longest)
    for nm in names:
        x = X[sw == nm]
        m = len(x)
        if m < 4:
            continue
        x = x - x.mean(axis=0)
        f = np.fft.rfft(x, n=2 * m, axis=0)
        c = np.fft.irfft(f * np.conj(f), n=2 * m, axis=0)[:m].sum(axis=1)
        acf[:m] += c
    if acf[0] <= 0:
        return 0
    counts = np.zeros(longest)            # unbiased: divide each lag by its number of pairs
    for nm in names:
        m = int((sw == nm).sum())
        if m >= 4:
            counts[:m] += np.arange(m, 0, -1)
    r = acf / np.maximum(counts, 1) / (acf[0] / counts[0])
    half = longest // 2
    below = np.flatnonzero(r[1:half + 1] < ACF_LEVEL)
    return int(below[0] + 1) if len(below) else half


def row_ranges(mask: np.ndarray) -> list[str]:
    """1-based data-row ranges ("rows a-b") of the rows a boolean mask selects."""
    idx = np.nonzero(mask)[0]
    if not len(idx):
        return []
    out = []
    start = prev = int(idx[0])
    for i in idx[1:]:
        i = int(i)
        if i != prev + 1:
            out.append(f"rows {start + 1}-{prev + 1}")
            start = i
        prev = i
    out.append(f"rows {start + 1}-{prev + 1}")
    return out
