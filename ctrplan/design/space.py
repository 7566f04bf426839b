"""Design variables, bounds and hard constraints of ``ctrplan design``.

A design is a vector ``u`` in the unit cube, ``4`` numbers per designed tube (innermost first):
curvature, curved length, straight length and the stock size, each scaled to its range: the
range derived from the anatomy (:mod:`ctrplan.design.derive`) inside the bounds, or the bounds
themselves (``derive=False``). Decoding
(:func:`decode`) turns it into a :class:`~ctrplan.robot.Robot` and repairs it onto the hard
constraints, naming each one that binds:

- ``strain``: recoverable strain of nitinol, ``(od / 2) x curvature <= strain_limit``;
- ``nesting``: a radial gap of at least ``min_gap_mm`` between a tube and the one around it,
  ``(id_outer - od_inner) / 2 >= min_gap_mm`` (sizes from the stock table);
- ``length``: total tube length ``straight + curved <= max_length_mm``;
- ``stroke``: translation range of a tube (its straight length, beta in [-straight, 0])
  ``<= max_stroke_mm``;
- ``joints``: an inner tube at least as long as the tube around it (else the joint
  constraints admit no configuration).

Tubes given with ``--from`` (the user's own, outermost) are kept as they are.
Units: mm, 1/mm.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from importlib import resources
from pathlib import Path

import numpy as np

from ctrplan.errors import InputError
from ctrplan.robot import Robot, Tube

#: Recoverable bending strain of superelastic nitinol used by default. Nitinol recovers about
#: 8 % strain (Duerig, Pelton & Stoeckel 1999, "An overview of nitinol medical applications",
#: Mater. Sci. Eng. A 273-275:149-160); concentric tube designs keep to 6-8 % (Dupont, Lock,
#: Itkowitz & Butler 2010, "Design and control of concentric-tube robots", IEEE T-RO
#: 26(2):209-225; Gilbert, Rucker & Webster 2016, "Concentric tube robots: the state of the
#: art and future directions", ISRR). The default takes the conservative end.
DEFAULT_STRAIN_LIMIT = 0.06

#: Material of designed tubes: superelastic nitinol (as the shipped seed1 robot).
NITINOL_E_MPA = 60000.0
NITINOL_POISSON = 0.33

#: Number of design variables per tube.
PER_TUBE = 4


def load_stock(path: str | Path | None = None) -> tuple[tuple[float, float], ...]:
    """Stock tube sizes ``((od, id), ...)`` mm, sorted by od (default: the shipped table
    ``ctrplan/data/nitinol_tubes.csv``; lines starting with ``#`` are comments)."""
    if path is None:
        text = resources.files("ctrplan").joinpath("data/nitinol_tubes.csv").read_text(encoding="utf-8")
        src = "nitinol_tubes.csv"
    else:
        src = str(path)
        from ctrplan.io import read_text

        text = read_text(path, "csv")   # size-capped, regular files only
    rows = [ln.strip() for ln in text.splitlines() if ln.strip() and not ln.lstrip().startswith("#")]
    if not rows or [c.strip() for c in rows[0].split(",")] != ["od_mm", "id_mm"]:
        raise InputError(src, "header", "must be od_mm,id_mm")
    sizes = []
    for k, ln in enumerate(rows[1:]):
        try:
            od, id_ = (float(c) for c in ln.split(","))
        except ValueError:
            raise InputError(src, f"row {k + 2}", "od_mm, id_mm must be two numbers") from None
        if not (math.isfinite(od) and math.isfinite(id_) and 0 <= id_ < od):
            raise InputError(src, f"row {k + 2}", "need finite 0 <= id_mm < od_mm")
        sizes.append((od, id_))
    if not sizes:
        raise InputError(src, "rows", "no tube sizes")
    return tuple(sorted(sizes))


@dataclass(frozen=True)
class Bounds:
    """Bounds of the design variables and limits of the hard constraints (mm, 1/mm)."""

    curvature: tuple[float, float] = (0.0, 0.08)
    curved_length: tuple[float, float] = (5.0, 150.0)
    straight_length: tuple[float, float] = (10.0, 300.0)
    strain_limit: float = DEFAULT_STRAIN_LIMIT
    min_gap_mm: float = 0.05
    max_length_mm: float = 400.0
    max_stroke_mm: float = 250.0


@dataclass(frozen=True)
class Space:
    """The design space: bounds, stock sizes, the user's fixed outer tubes, the number of
    tubes designed (``k_min..k_max``) and the ranges derived from the anatomy
    (:class:`~ctrplan.design.derive.Derived`; None: the bounds as they are)."""

    bounds: Bounds
    stock: tuple[tuple[float, float], ...]
    fixed: tuple[Tube, ...]
    k_min: int
    k_max: int
    derived: object | None = None

    @property
    def dim(self) -> int:
        return PER_TUBE * self.k_max


@dataclass(frozen=True)
class Decoded:
    """A decoded design: the robot (or None where no robot satisfies the constraints) and the
    constraints that bound (repairs made) or were violated."""

    robot: Robot | None
    binding: tuple[str, ...]
    parameters: dict


def make_space(bounds: Bounds, stock, fixed: tuple[Tube, ...], tubes: int, source: str = "",
               derived=None) -> Space:
    """Check the bounds (InputError naming the infeasible one) and build the :class:`Space`
    (``derived``: the ranges read from the anatomy, :func:`ctrplan.design.derive.derive`)."""
    b = bounds
    for name in ("curvature", "curved_length", "straight_length"):
        lo, hi = getattr(b, name)
        if not (math.isfinite(lo) and math.isfinite(hi) and 0 <= lo <= hi):
            raise InputError("bounds", name, f"infeasible bounds [{lo:g}, {hi:g}]: need 0 <= min <= max")
    if not (0 < b.strain_limit < 0.1):
        raise InputError("--strain-limit", "", f"must be in (0, 0.1), got {b.strain_limit:g}")
    if not (b.min_gap_mm >= 0 and math.isfinite(b.min_gap_mm)):
        raise InputError("--min-gap", "", f"must be a number >= 0 (mm), got {b.min_gap_mm:g}")
    if b.curved_length[0] + b.straight_length[0] > b.max_length_mm:
        raise InputError("bounds", "max_length_mm",
                         f"infeasible bounds: the shortest tube ({b.curved_length[0]:g} + "
                         f"{b.straight_length[0]:g} mm) exceeds the length limit {b.max_length_mm:g} mm")
    if b.straight_length[0] > b.max_stroke_mm:
        raise InputError("bounds", "max_stroke_mm",
                         f"infeasible bounds: the shortest straight length {b.straight_length[0]:g} mm "
                         f"exceeds the stroke limit {b.max_stroke_mm:g} mm")
    kmin_strain = min(2 * b.strain_limit / od for od, _ in stock)
    if b.curvature[0] > kmin_strain:
        raise InputError("bounds", "curvature",
                         f"infeasible bounds: minimum curvature {b.curvature[0]:g} 1/mm strains even the "
                         f"thinnest stock tube beyond the strain limit {b.strain_limit:g}")
    for i, t in enumerate(fixed):
        strain = 0.5 * t.od * abs(t.curvature)
        if strain > b.strain_limit * (1 + 1e-9):
            raise InputError(source, f"tubes[{i}].curvature",
                             f"tube {i + 1} (od {t.od:g} mm, curvature {t.curvature:g} 1/mm) is strained "
                             f"{100 * strain:.3g} % when straightened, beyond the strain limit "
                             f"{100 * b.strain_limit:.3g} %")
    if tubes < 1 or tubes > 3:
        raise InputError("--tubes", "", f"must be 1, 2 or 3, got {tubes}")
    k_max = tubes - len(fixed)
    if k_max < 0:
        raise InputError("--tubes", "", f"the --from robot already has {len(fixed)} tubes (> {tubes})")
    k_min = 0 if fixed else 1
    if k_max > 0:
        sizes = _fitting_sizes(stock, fixed, b.min_gap_mm)
        if len(sizes) == 0:
            raise InputError("bounds", "nesting",
                             f"infeasible bounds: no stock tube fits inside the --from robot's "
                             f"innermost tube (id {fixed[0].id:g} mm) with a radial gap of {b.min_gap_mm:g} mm")
    return Space(bounds=b, stock=tuple(stock), fixed=tuple(fixed), k_min=k_min, k_max=k_max,
                 derived=derived)


def _fitting_sizes(stock, fixed, gap: float) -> list[int]:
    """Indices of stock sizes that fit inside the innermost fixed tube (all without one)."""
    if not fixed:
        return list(range(len(stock)))
    return [j for j, (od, _) in enumerate(stock) if (fixed[0].id - od) / 2 >= gap - 1e-12]


def _ranges(space: Space, i: int):
    """(curvature, curved_length, straight_length, allowed stock indices) of designed tube i."""
    d = space.derived
    if d is None:
        b = space.bounds
        return b.curvature, b.curved_length, b.straight_length, tuple(range(len(space.stock)))
    r = d.ranges(i)
    return r.curvature, r.curved_length, r.straight_length, r.sizes


def _sizes(space: Space, k: int, u: np.ndarray, binding: list) -> list | None:
    """Stock sizes of the k designed tubes (innermost first): each the size its variable picks
    among the allowed ones, or the largest allowed that still nests inside the tube around it."""
    b = space.bounds
    stock = space.stock
    fits_fixed = set(_fitting_sizes(stock, space.fixed, b.min_gap_mm))
    sizes: list[tuple[float, float]] = [(0.0, 0.0)] * k
    limit_id = space.fixed[0].id if space.fixed else math.inf
    for i in range(k - 1, -1, -1):
        allowed = [j for j in _ranges(space, i)[3] if j in fits_fixed] or sorted(fits_fixed)
        fit = [j for j in allowed if (limit_id - stock[j][0]) / 2 >= b.min_gap_mm - 1e-12]
        if not fit:
            return None
        want = allowed[int(min(len(allowed) - 1, math.floor(u[PER_TUBE * i + 3] * len(allowed))))]
        j = want if want in fit else max((f for f in fit if f <= want), default=fit[0])
        if j != want:
            binding.append("nesting")
        sizes[i] = stock[j]
        limit_id = stock[j][1]
    return sizes


def decode(space: Space, k: int, u: np.ndarray, name: str = "design") -> Decoded:
    """The robot of ``k`` designed tubes (innermost first) from ``u`` (dim,) in [0, 1], plus
    the fixed tubes outside them; constraints repaired where possible and named. With derived
    ranges (``space.derived``) each variable spans its tube's derived range and the curved
    length at most the entry room at the tube's curvature."""
    b = space.bounds
    u = np.clip(np.asarray(u, dtype=float), 0.0, 1.0)
    binding: list[str] = []
    sizes = _sizes(space, k, u, binding)
    if sizes is None:
        return Decoded(None, ("nesting",), {"tubes": k})
    tubes: list[Tube] = []
    # lengths from the outermost designed tube inward (an inner tube is at least as long)
    outer_len = space.fixed[0].length if space.fixed else 0.0
    outer_straight = space.fixed[0].straight_length if space.fixed else 0.0
    for i in range(k - 1, -1, -1):
        od, id_ = sizes[i]
        kr, cr, sr, _ = _ranges(space, i)
        uk, uc, us = u[PER_TUBE * i: PER_TUBE * i + 3]
        kappa = kr[0] + uk * (kr[1] - kr[0])
        kmax = b.strain_limit / (od / 2)
        if kappa > kmax:
            kappa = kmax
            binding.append("strain")
        c_hi = cr[1]
        if space.derived is not None:
            c_hi = max(cr[0], min(c_hi, space.derived.curved_cap(od / 2, kappa)))
        curved = cr[0] + uc * (c_hi - cr[0])
        straight = sr[0] + us * (sr[1] - sr[0])
        if straight > b.max_stroke_mm:
            straight = b.max_stroke_mm
            binding.append("stroke")
        need = max(outer_len + 1.0 - curved, outer_straight)   # reach past the tube around it
        if straight < need:
            straight = need
            binding.append("joints")
            if straight > b.max_stroke_mm:
                return Decoded(None, ("joints", "stroke"), {"tubes": k})
        if straight + curved > b.max_length_mm:
            curved = b.max_length_mm - straight
            binding.append("length")
            if curved < b.curved_length[0]:
                return Decoded(None, ("joints", "length"), {"tubes": k})
        # values rounded for robot.yaml; curvature rounded down so the strain limit still holds
        tubes.insert(0, Tube(od=float(od), id=float(id_), straight_length=float(round(straight, 3)),
                             curved_length=float(round(curved, 3)), curvature=math.floor(kappa * 1e7) / 1e7,
                             youngs_modulus=NITINOL_E_MPA, poisson_ratio=NITINOL_POISSON))
        outer_len, outer_straight = tubes[0].length, tubes[0].straight_length
    all_tubes = tuple(tubes) + space.fixed
    try:
        robot = Robot(name=name, tubes=all_tubes)
        robot.retracted()
    except InputError:
        return Decoded(None, tuple(dict.fromkeys(binding + ["joints"])), {"tubes": k})
    params = {"tubes": k, "designed": [{"od": t.od, "id": t.id, "curvature": t.curvature,
                                        "curved_length": t.curved_length,
                                        "straight_length": t.straight_length} for t in tubes]}
    return Decoded(robot, tuple(dict.fromkeys(binding)), params)


def constraint_report(robot: Robot, bounds: Bounds, rtol: float = 0.02) -> dict[str, dict]:
    """Each hard constraint of ``robot`` (all its tubes): the worst value, the limit, whether
    it holds and whether it binds (within ``rtol`` of the limit)."""
    t = robot.tubes
    strain = max(0.5 * x.od * abs(x.curvature) for x in t)
    gaps = [(t[i + 1].id - t[i].od) / 2 for i in range(len(t) - 1)]
    length = max(x.length for x in t)
    stroke = max(x.straight_length for x in t)

    def row(value, limit, upper=True):
        ok = value <= limit * (1 + 1e-9) if upper else value >= limit - 1e-9
        binds = abs(value - limit) <= rtol * max(abs(limit), 1e-9)
        return {"value": float(value), "limit": float(limit), "satisfied": bool(ok), "binds": bool(binds)}

    out = {"strain": row(strain, bounds.strain_limit),
           "length": row(length, bounds.max_length_mm),
           "stroke": row(stroke, bounds.max_stroke_mm)}
    if gaps:
        out["nesting"] = row(min(gaps), bounds.min_gap_mm, upper=False)
    return out


def simplicity(robot: Robot) -> tuple[int, float, float]:
    """Simplicity cost, compared in order: tubes, total bending angle kappa x curved length
    (rad), total length (mm). Smaller is simpler."""
    t = robot.tubes
    return (len(t), float(sum(abs(x.curvature) * x.curved_length for x in t)),
            float(sum(x.length for x in t)))
