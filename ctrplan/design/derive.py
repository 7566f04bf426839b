"""The design space derived from the anatomy (:mod:`ctrplan.design.anatomy`), inside the bounds.

Instead of searching fixed ranges, ``ctrplan design`` searches ranges read from the corridors to
the targets (each a sub-range of :class:`~ctrplan.design.space.Bounds`, which stay the hard
limits):

- **stock sizes**: the innermost tube must pass a corridor's bottleneck (``od / 2`` + margin at
  most the bottleneck's radius, plus half the grid spacing: the bottleneck is a lower bound of
  the passable radius) for at least one target; every other tube must fit the corridor over the
  first ``min curved length`` past the entry (it protrudes that far even when retracted);
- **curvature**: up to 1.5 times the sharpest bend on the way to any target (at least 0.02 1/mm),
  the turn out of the base's +z direction included;
- **curved length**: at most the entry room -- the longest arc of the tube's curvature that the
  retracted robot can protrude from the base with the tube's radius (:class:`EntryRoom`), plus
  :data:`ENTRY_SLACK_MM` -- evaluated for each design as it is decoded (a curvature-dependent
  cap), and at most the deepest corridor;
- **straight length**: the innermost tube long enough for the shallowest corridor and at most
  :data:`REACH_SLACK_MM` longer than the deepest; other tubes up to the deepest corridor.

A range that the anatomy leaves empty inside the bounds falls back to the bounds (noted);
targets no stock tube can reach are named by :mod:`ctrplan.design.explain`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

#: Slack (mm) on the entry room: the table assumes one arc, the robot's tubes bend each other.
ENTRY_SLACK_MM = 2.0
#: Length (mm) the innermost tube may have beyond the deepest corridor.
REACH_SLACK_MM = 15.0
#: Factor on the sharpest bend's curvature, and the least curvature range (1/mm).
BEND_FACTOR = 1.5
MIN_CURVATURE_RANGE = 0.02


@dataclass(frozen=True)
class TubeRanges:
    """Ranges of one designed tube: curvature (1/mm), curved and straight length (mm) and the
    allowed stock indices (ascending od)."""

    curvature: tuple[float, float]
    curved_length: tuple[float, float]
    straight_length: tuple[float, float]
    sizes: tuple[int, ...]

    def to_json(self, stock) -> dict:
        return {"curvature_per_mm": [round(v, 5) for v in self.curvature],
                "curved_length_mm": [round(v, 2) for v in self.curved_length],
                "straight_length_mm": [round(v, 2) for v in self.straight_length],
                "stock_od_mm": [stock[i][0] for i in self.sizes]}


@dataclass(frozen=True)
class Derived:
    """The derived space: ranges of the innermost designed tube and of the others, the entry
    room (curved-length cap per curvature and radius), and notes on how each was derived."""

    inner: TubeRanges
    outer: TubeRanges
    entry: object | None
    notes: tuple[str, ...]

    def ranges(self, i: int) -> TubeRanges:
        """Ranges of designed tube ``i`` (0: the innermost)."""
        return self.inner if i == 0 else self.outer

    def curved_cap(self, radius: float, kappa: float) -> float:
        """Longest curved length (mm) the entry lets a tube of ``radius`` and curvature
        ``kappa`` protrude (+ slack); inf without an entry table."""
        if self.entry is None:
            return math.inf
        return self.entry.longest(radius, kappa) + ENTRY_SLACK_MM

    def to_json(self, stock) -> dict:
        return {"innermost": self.inner.to_json(stock), "others": self.outer.to_json(stock),
                "curved_length_cap": "entry room of the tube's radius at its curvature + "
                                     f"{ENTRY_SLACK_MM:g} mm", "notes": list(self.notes)}


def _clip(lo: float, hi: float, bound: tuple[float, float], name: str, notes: list) -> tuple[float, float]:
    a, b = max(lo, bound[0]), min(hi, bound[1])
    if a > b:
        notes.append(f"{name}: the anatomy asks for [{lo:.4g}, {hi:.4g}], outside the bounds "
                     f"[{bound[0]:g}, {bound[1]:g}]; searching the bounds")
        return tuple(bound)
    return (a, b)


def _first_clearance(route, upto: float) -> float:
    """Least clearance (mm) of a corridor over its first ``upto`` mm."""
    sel = route.clearance[route.s <= upto]
    return float(sel.min()) if len(sel) else 0.0


def derive(anatomy, bounds, stock, margin_mm: float = 0.0) -> Derived:
    """The derived space (module docstring) from an :class:`~ctrplan.design.anatomy.Anatomy`.
    Without any open corridor the ranges that need one fall back to the bounds; the entry room
    still caps the curved lengths."""
    notes: list[str] = []
    routes = [r for r in anatomy.routes if r.connected]
    h = anatomy.resolution_mm
    radii = np.array([od / 2 for od, _ in stock])
    if not routes:
        notes.append("no open corridor reaches any target: the ranges that need one are the bounds")
    # stock: innermost through a bottleneck, the others through the first stretch
    first = bounds.curved_length[0]
    b = (max(r.bottleneck_mm for r in routes) if routes else anatomy.base_clearance_mm) + 0.5 * h
    inner_sizes = tuple(int(i) for i in np.flatnonzero(radii + margin_mm <= b)) or (0,)
    entry_clr = min(max((_first_clearance(r, first + 1.0) for r in routes), default=math.inf),
                    anatomy.base_clearance_mm) + 0.5 * h
    outer_sizes = tuple(int(i) for i in np.flatnonzero(radii + margin_mm <= entry_clr)) or inner_sizes
    notes.append(f"stock: innermost od <= {2 * (b - margin_mm):.2f} mm ("
                 + ("widest bottleneck" if routes else "clearance at the base")
                 + f" + half the grid), others od <= {2 * (entry_clr - margin_mm):.2f} mm (the corridor "
                 f"over the first {first + 1:g} mm)")
    # curvature: the sharpest bend of the corridors
    sharp = max((bd.curvature for r in routes for bd in r.bends), default=0.0)
    if routes:
        curv = _clip(bounds.curvature[0], max(MIN_CURVATURE_RANGE, BEND_FACTOR * sharp), bounds.curvature,
                     "curvature", notes)
        notes.append(f"curvature <= {curv[1]:.4g} 1/mm (sharpest bend {sharp:.4g} 1/mm x {BEND_FACTOR:g})")
    else:
        curv = tuple(bounds.curvature)
    # curved length: the entry room (for the thinnest allowed tube, best curvature) and depth
    deep = max((r.depth_mm for r in routes), default=bounds.curved_length[1])
    shallow = min((r.depth_mm for r in routes), default=bounds.straight_length[0])
    kk = anatomy.entry.kappa[anatomy.entry.kappa <= curv[1] + 1e-12]
    room = max(anatomy.entry.longest(radii[inner_sizes[0]], float(k)) for k in kk) + ENTRY_SLACK_MM
    curved = _clip(bounds.curved_length[0], min(room, deep), bounds.curved_length, "curved_length", notes)
    notes.append(f"curved length <= {curved[1]:.1f} mm (entry room {room:.1f} mm"
                 + (f", deepest corridor {deep:.1f} mm" if routes else "")
                 + "), capped per design by the room at its curvature")
    if routes:
        s_in = _clip(shallow - curved[1], deep + REACH_SLACK_MM - curved[0], bounds.straight_length,
                     "straight_length", notes)
        s_out = _clip(bounds.straight_length[0], deep, bounds.straight_length, "straight_length (outer)", notes)
        notes.append(f"straight length: innermost [{s_in[0]:.1f}, {s_in[1]:.1f}] mm (corridors "
                     f"{shallow:.1f}-{deep:.1f} mm deep), others [{s_out[0]:.1f}, {s_out[1]:.1f}] mm")
    else:
        s_in = s_out = tuple(bounds.straight_length)
    inner = TubeRanges(curv, curved, s_in, inner_sizes)
    outer = TubeRanges(curv, curved, s_out, outer_sizes)
    return Derived(inner, outer, anatomy.entry, tuple(notes))
