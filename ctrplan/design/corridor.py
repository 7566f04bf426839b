"""Corridors through the clearance grid of :mod:`ctrplan.design.anatomy`: bottlenecks and
centrelines.

- :func:`bottlenecks`: for each target, the largest clearance ``b`` such that the base and the
  target's end nodes are connected through nodes with clearance >= ``b`` (the free nodes of the
  base's component joined in order of decreasing clearance by a union-find, numba,
  26-connected; each target a virtual node joined to its end nodes): exact over node paths;
- :func:`centrelines`: the cheapest node path (scikit-image's minimum-cost path, 26-connected)
  from the base to each target through nodes with clearance >= its bottleneck (rounded down to
  0.05 mm), each step costing its length times ``1 + (CENTRE_MM / clearance)^2`` (it keeps to
  the middle of the lumen); one search serves every target whose path keeps its own floor.

Grids are the ``_Grid`` of anatomy.py (``origin``, ``h``, ``d``: node clearance, -1 where not
free); ``crop`` is :func:`crop`'s (offsets, clearance over the base component's box).
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

#: Centring of the centreline: cost per mm is 1 + (CENTRE_MM / clearance)^2.
CENTRE_MM = 1.0


def component(free: np.ndarray, start: tuple) -> np.ndarray:
    """The connected component (26-connected) of ``free`` holding ``start`` (all False when
    ``start`` is not free)."""
    from scipy import ndimage

    if not free[start]:
        return np.zeros_like(free)
    lab, _ = ndimage.label(free, structure=np.ones((3, 3, 3), bool))
    return lab == lab[start]


@nb.njit(cache=True)
def _find(parent, x):
    r = x
    while parent[r] != r:
        r = parent[r]
    while parent[x] != r:          # path compression
        nxt = parent[x]
        parent[x] = r
        x = nxt
    return r


@nb.njit(cache=True)
def _maximin_kernel(order, d, nx, ny, nz, start, pair_node, pair_target, T):
    """Nodes added in order of decreasing clearance (union-find, 26-connected); each target is
    a virtual node joined to its end nodes; a target's bottleneck is the clearance of the node
    whose addition connected it to the start (exact maximin over node paths)."""
    n = nx * ny * nz
    parent = np.full(n + T, -1, dtype=np.int64)
    for j in range(T):
        parent[n + j] = n + j
    out = np.zeros(T)
    pending = T
    done = np.zeros(T, dtype=np.bool_)
    for x in order:
        parent[x] = x
        i = x // (ny * nz)
        jj = (x // nz) % ny
        k = x % nz
        for di in range(-1, 2):
            for dj in range(-1, 2):
                for dk in range(-1, 2):
                    a, b, c = i + di, jj + dj, k + dk
                    if a < 0 or b < 0 or c < 0 or a >= nx or b >= ny or c >= nz:
                        continue
                    y = (a * ny + b) * nz + c
                    if parent[y] == -1:
                        continue
                    ra, rb = _find(parent, x), _find(parent, y)
                    if ra != rb:
                        parent[rb] = ra
        p = np.searchsorted(pair_node, x)
        while p < len(pair_node) and pair_node[p] == x:
            ra, rb = _find(parent, x), _find(parent, n + pair_target[p])
            if ra != rb:
                parent[rb] = ra
            p += 1
        if parent[start] == -1:
            continue
        rs = _find(parent, start)
        for t in range(T):
            if not done[t] and _find(parent, n + t) == rs:
                done[t] = True
                out[t] = d[x]
                pending -= 1
        if pending == 0:
            break
    return out


def crop(grid, start: tuple):
    """(offsets (3,), clearance over the bounding box of the base's free component, -1 outside
    the component), or None when the base is not free."""
    from scipy import ndimage

    comp = component(grid.d > 0, start)
    if not comp.any():
        return None
    sl = ndimage.find_objects(comp.astype(np.int8))[0]
    return np.array([s.start for s in sl]), np.where(comp[sl], grid.d[sl], -1.0).astype(np.float32)


def _local(flat: np.ndarray, shape, offs: np.ndarray, sub_shape) -> np.ndarray:
    """Flat indices of the full grid -> flat indices of the sub-grid (those inside it)."""
    idx = np.stack(np.unravel_index(np.asarray(flat, np.int64), shape), 1) - offs
    inside = np.all((idx >= 0) & (idx < np.array(sub_shape)), axis=1)
    return np.ravel_multi_index(idx[inside].T, sub_shape) if inside.any() else np.zeros(0, np.int64)


def bottlenecks(crop, start: tuple, ends: list[np.ndarray], shape, cap: float) -> np.ndarray:
    """(T,) the largest clearance b <= cap such that the start and some end node of the target
    are connected through nodes with clearance >= b (0 where none)."""
    T = len(ends)
    if crop is None or T == 0:
        return np.zeros(T)
    offs, d = crop
    flat = d.ravel()
    loc = [_local(e, shape, offs, d.shape) for e in ends]
    pairs = sorted((int(n), j) for j, ln in enumerate(loc) for n in ln if flat[n] > 0)
    free = np.flatnonzero(flat > 0)
    order = free[np.argsort(-flat[free], kind="stable")]
    st = int(np.ravel_multi_index(tuple(np.array(start) - offs), d.shape))
    pn = np.array([p[0] for p in pairs], dtype=np.int64)
    pt = np.array([p[1] for p in pairs], dtype=np.int64)
    out = _maximin_kernel(order.astype(np.int64), flat.astype(np.float64), *d.shape, st, pn, pt, T)
    return np.minimum(out, cap)


def centrelines(grid, crop, start: tuple, ends: list[np.ndarray], floors: np.ndarray) -> list:
    """Node paths (K, 3) scene frame from the start to each target's cheapest end node through
    nodes with clearance >= its floor (None where there is none). One minimum-cost search
    (scikit-image) through the nodes above the lowest floor serves every target whose path
    keeps its own floor (the centring cost avoids narrow passages); the others are searched
    again above their own floors."""
    out: list = [None] * len(ends)
    if crop is None:
        return out
    pending = {j: math.floor(0.999 * f / 0.05) * 0.05 for j, f in enumerate(floors) if f > 0}
    while pending:
        floor = min(pending.values())
        found = _search(grid, crop, start, {j: ends[j] for j in pending}, floor)
        deeper = {}
        for j, level in pending.items():
            if j not in found:
                continue
            path, clr = found[j]
            if level <= floor or float(np.min(clr)) >= level - 1e-6:
                out[j] = path
            else:                           # dipped below its own floor: above it next round
                deeper[j] = level
        pending = deeper
    return out


def _search(grid, crop, start: tuple, ends: dict, floor: float) -> dict:
    """{target: (path (K, 3) scene frame, clearance (K,) of its nodes)} through nodes with
    clearance >= floor."""
    from skimage.graph import MCP_Geometric

    offs, d = crop
    st = tuple(int(v) for v in np.array(start) - offs)
    ok = d >= max(floor, 1e-6)
    if not ok[st]:
        return {}
    mine = {j: [tuple(int(v) for v in np.unravel_index(e, d.shape))
                for e in _local(e_, grid.d.shape, offs, d.shape) if ok.ravel()[e]] for j, e_ in ends.items()}
    every = sorted({e for v in mine.values() for e in v})
    if not every:
        return {}
    cost = np.where(ok, 1.0 + (CENTRE_MM / np.maximum(d, 1e-3)) ** 2, np.inf)
    mcp = MCP_Geometric(cost, fully_connected=True)
    cum, _ = mcp.find_costs([st], every, find_all_ends=True)
    out = {}
    for j, es in mine.items():
        best = min(es, key=lambda e: cum[e]) if es else None
        if best is not None and np.isfinite(cum[best]):
            idx = np.array(mcp.traceback(best))
            out[j] = ((idx + offs) * grid.h + grid.origin, d[tuple(idx.T)])
    return out
