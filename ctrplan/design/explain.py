"""Why a target is not reached: what blocks it, where, by how much, and what to relax.

For every target the chosen design does not reach, the anatomy read before the search
(:mod:`ctrplan.design.anatomy`) is checked against the design's limits in this order; the
first that fails is the answer (``blocking``), with its numbers and place:

1. ``target`` -- the target lies outside the lumen, farther than the tolerance from any free
   point (*necessary*: no tip can get there);
2. ``corridor`` -- the corridor is narrower than the thinnest tube the design may use (the
   smallest stock size, inside the ``--from`` tubes if given) plus twice the margin, or closed
   (*necessary*, up to the distance field's resolution; the width is measured on the mesh at
   0.1 mm where it decides this);
3. ``length`` / ``stroke`` -- the target is farther from the base (straight line) than the
   longest tube, or than the stroke plus the longest curved section (*necessary*);
4. ``entry`` -- no arc of any allowed curvature, as long as the shortest curved section, fits
   the lumen at the entry with the thinnest tube (*estimate*: one arc stands for the retracted
   robot, whose tubes bend each other);
5. ``curvature`` / ``strain`` -- a bend of the corridor needs more curvature than the bounds
   allow, or than the thinnest fitting tube can have within the strain limit, even cutting the
   corner as far as the corridor's width allows (:func:`needed_curvature`; *estimate*);
6. ``search`` -- nothing the anatomy shows rules the target out; the search did not find a
   design within its budget.

Each answer names the one constraint whose relaxation alone would remove that block
(``relax``; for ``corridor``, a thinner stock tube -- unless the lumen is closed, when no design
constraint can) and the closest design found for the target (the best screen tip error over
all designs evaluated, and the chosen design's plan status).
"""

from __future__ import annotations

import math

import numpy as np


def _fmt_pos(p) -> str:
    return "(" + ", ".join(f"{float(v):.1f}" for v in p) + ")"


def thinnest_od(stock, fixed, min_gap: float, designed: int) -> float:
    """The smallest outer diameter (mm) the innermost tube of a design may have."""
    if designed <= 0 and fixed:
        return float(fixed[0].od)
    limit = fixed[0].id if fixed else math.inf
    fits = [od for od, _ in stock if (limit - od) / 2 >= min_gap - 1e-12]
    return float(min(fits)) if fits else float(min(od for od, _ in stock))


def _corridor(route, od: float, margin: float, h: float) -> dict | None:
    n = route.narrowest
    need = od + 2 * margin
    width = n.width_mm if n is not None else 0.0
    if route.connected and (n is None or width >= need):
        return None
    if n is None:
        return {"blocking": "corridor", "kind": "necessary",
                "message": "no free corridor from the entry reaches the target",
                "place": None, "numbers": {"width_mm": 0.0, "needs_mm": need},
                "relax": {"constraint": None, "to": None,
                          "why": "the lumen is closed: no design constraint admits a design"}}
    closed = width <= 1e-9
    msg = (f"the corridor is {'closed' if closed else f'{width:.2f} mm wide'} {n.at_mm:.1f} mm past "
           f"the entry (at {_fmt_pos(n.position)}); the thinnest tube the design may use "
           f"(od {od:g} mm) needs {need:.2f} mm"
           + (f" with the {margin:g} mm margin" if margin > 0 else "")
           + ("" if n.refined else f" (distance field estimate, resolution {h:g} mm)"))
    if closed:
        relax = {"constraint": None, "to": None,
                 "why": "the lumen is closed there: no design constraint admits a design"}
    elif margin > 0 and width >= od:
        relax = {"constraint": "margin_mm", "to": round((width - od) / 2, 3),
                 "why": f"a margin of at most {(width - od) / 2:.2f} mm"}
    else:
        relax = {"constraint": "stock", "to": round(width - 2 * margin, 3),
                 "why": f"a stock tube of od below {width - 2 * margin:.2f} mm (--stock)"}
    return {"blocking": "corridor", "kind": "necessary", "message": msg,
            "place": {"at_mm": round(n.at_mm, 2), "position": [round(float(v), 3) for v in n.position]},
            "numbers": {"width_mm": round(width, 3), "needs_mm": round(need, 3)}, "relax": relax}


def _reach(route, bounds) -> dict | None:
    d = route.straight_mm
    if d > bounds.max_length_mm:
        return {"blocking": "length", "kind": "necessary",
                "message": f"the target is {d:.1f} mm from the base in a straight line; the longest "
                           f"tube may be {bounds.max_length_mm:g} mm",
                "place": None, "numbers": {"distance_mm": round(d, 2), "limit_mm": bounds.max_length_mm},
                "relax": {"constraint": "max_length_mm", "to": math.ceil(d),
                          "why": f"--max-length {math.ceil(d)}"}}
    need = d - bounds.curved_length[1]
    if need > bounds.max_stroke_mm:
        return {"blocking": "stroke", "kind": "necessary",
                "message": f"the target is {d:.1f} mm from the base; with curved sections of at most "
                           f"{bounds.curved_length[1]:g} mm a tube needs a stroke of {need:.1f} mm "
                           f"(limit {bounds.max_stroke_mm:g} mm)",
                "place": None, "numbers": {"needs_mm": round(need, 2), "limit_mm": bounds.max_stroke_mm},
                "relax": {"constraint": "max_stroke_mm", "to": math.ceil(need),
                          "why": f"--max-stroke {math.ceil(need)}"}}
    return None


def _entry(anatomy, bounds, od: float) -> dict | None:
    e = anatomy.entry
    r = od / 2
    ks = [k for k in e.kappa if bounds.curvature[0] - 1e-12 <= k <= bounds.curvature[1] + 1e-12] \
        or [bounds.curvature[0]]
    room = max(e.longest(r, float(k)) for k in ks)
    if room >= bounds.curved_length[0]:
        return None
    i = min(int(np.searchsorted(e.radii, r - 1e-9)), len(e.radii) - 1)
    straight = float(e.straight_mm[i])
    return {"blocking": "entry", "kind": "estimate",
            "message": f"the retracted robot protrudes its curved sections (at least "
                       f"{bounds.curved_length[0]:g} mm); at the entry the lumen leaves room for "
                       f"{room:.1f} mm of any allowed arc for a tube of od {od:g} mm (the straight line "
                       f"runs out of room {straight:.1f} mm past the entry, at {_fmt_pos(e.exit[i])})",
            "place": {"at_mm": round(straight, 2), "position": [round(float(v), 3) for v in e.exit[i]]},
            "numbers": {"room_mm": round(room, 2), "needs_mm": bounds.curved_length[0]},
            "relax": {"constraint": "curved_length", "to": [round(room, 1), bounds.curved_length[1]],
                      "why": f"--curved-length {max(room, 0.1):.1f},{bounds.curved_length[1]:g}"}}


def needed_curvature(route, bend, radius: float) -> float:
    """Curvature (1/mm) a tube of ``radius`` needs at least to follow ``bend``: an arc may cut
    the corner by the room the corridor leaves it (``a``: the least clearance along the bend
    less the radius, on either side), so its radius can grow from the bend's ``R`` to about
    ``R + 2 a / (1 - cos(angle / 2))`` (the sagitta of the turn)."""
    sel = (route.s >= bend.at_mm) & (route.s <= bend.at_mm + bend.length_mm)
    clr = float(route.clearance[sel].min()) if sel.any() else 0.0
    a = max(clr - radius, 0.0)
    half = math.radians(bend.angle_deg) / 2
    return 1.0 / (bend.radius_mm + 2 * a / max(1 - math.cos(half), 1e-9))


def _bend(route, bounds, od: float) -> dict | None:
    if not route.bends:
        return None
    b, k = max(((x, needed_curvature(route, x, od / 2)) for x in route.bends), key=lambda t: t[1])
    place = {"at_mm": round(b.at_mm, 2), "position": [round(float(v), 3) for v in route.place(b.at_mm)]}
    where = (f"the corridor turns by {b.angle_deg:.0f} degrees over {b.length_mm:.1f} mm {b.at_mm:.1f} mm "
             f"past the entry (at {_fmt_pos(place['position'])}); cutting the corner as far as its width "
             f"allows, a tube needs a curvature of {k:.4f} 1/mm")
    if k > bounds.curvature[1]:
        return {"blocking": "curvature", "kind": "estimate",
                "message": f"{where}; curvatures are bounded by {bounds.curvature[1]:g} 1/mm",
                "place": place, "numbers": {"needs_per_mm": round(k, 5), "limit_per_mm": bounds.curvature[1]},
                "relax": {"constraint": "curvature", "to": [bounds.curvature[0], round(k * 1.2, 4)],
                          "why": f"--curvature {bounds.curvature[0]:g},{k * 1.2:.4f}"}}
    strain = od / 2 * k
    if strain > bounds.strain_limit:
        return {"blocking": "strain", "kind": "estimate",
                "message": f"{where}; the thinnest tube the design may use (od {od:g} mm) is strained "
                           f"{100 * strain:.1f} % at that curvature, beyond the {100 * bounds.strain_limit:g} % limit",
                "place": place, "numbers": {"strain": round(strain, 4), "limit": bounds.strain_limit},
                "relax": {"constraint": "strain_limit", "to": round(strain, 4),
                          "why": f"--strain-limit {strain:.3f}" if strain < 0.1 else
                                 f"a stock tube of od below {2 * bounds.strain_limit / k:.2f} mm"}}
    return None


def _search(route, h: float) -> dict:
    n = route.narrowest
    bits = [f"{route.depth_mm:.1f} mm deep"]
    if n is not None:
        bits.append(f"{n.width_mm:.2f} mm wide at its narrowest, {n.at_mm:.1f} mm past the entry "
                    f"(at {_fmt_pos(n.position)})")
    if route.bends:
        b = max(route.bends, key=lambda x: x.angle_deg)
        bits.append(f"its sharpest turn {b.angle_deg:.0f} degrees over {b.length_mm:.1f} mm "
                    f"{b.at_mm:.1f} mm past the entry")
    return {"blocking": "search", "kind": "search",
            "message": "nothing the anatomy shows rules it out (the corridor is " + ", ".join(bits)
                       + "); no design within the budget reached it",
            "place": None if n is None else {"at_mm": round(n.at_mm, 2),
                                              "position": [round(float(v), 3) for v in n.position]},
            "numbers": {"depth_mm": round(route.depth_mm, 2)},
            "relax": {"constraint": "budget", "to": None,
                      "why": "a larger --budget, more --tubes, or a start from a design of your own (--from)"}}


def _closest(j: int, evaluations, outcome) -> dict:
    """The closest any evaluated design came to target j (screen IK tip error) and the chosen
    design's plan status for it."""
    best = None
    for e in evaluations:
        errs = e.get("screen_errors") or []
        if j < len(errs) and errs[j] is not None and (best is None or errs[j] < best[0]):
            best = (float(errs[j]), e["index"], e.get("parameters"))
    out = {"chosen_design_status": None if outcome is None else outcome.status}
    if best is not None:
        out.update({"tip_error_mm": round(best[0], 3), "design_index": best[1], "parameters": best[2]})
    return out


def explain(anatomy, bounds, stock, fixed, designed: int, margin_mm: float, tolerance_mm: float,
            evaluations, outcomes) -> list[dict]:
    """One answer per target not reached (module docstring); ``outcomes``: the chosen design's
    per-target outcomes (None when no design was chosen)."""
    od = thinnest_od(stock, fixed, bounds.min_gap_mm, designed)
    h = anatomy.resolution_mm
    out = []
    for j, route in enumerate(anatomy.routes):
        oc = outcomes[j] if outcomes else None
        if oc is not None and oc.reached:
            continue
        if route.target_gap_mm > tolerance_mm:
            ans = {"blocking": "target", "kind": "necessary",
                   "message": f"the target lies {route.target_gap_mm:.2f} mm from the nearest free point "
                              f"of the lumen, beyond the {tolerance_mm:g} mm tolerance",
                   "place": {"at_mm": None, "position": [round(float(v), 3) for v in route.target]},
                   "numbers": {"gap_mm": round(route.target_gap_mm, 3), "tolerance_mm": tolerance_mm},
                   "relax": {"constraint": "tolerance_mm", "to": round(route.target_gap_mm + 0.1, 2),
                             "why": "a target inside the lumen (or a larger tolerance)"}}
        else:
            ans = (_corridor(route, od, margin_mm, h) or _reach(route, bounds) or _entry(anatomy, bounds, od)
                   or _bend(route, bounds, od) or _search(route, h))
        ans = {"target": route.name, **ans, "closest": _closest(j, evaluations, oc)}
        out.append(ans)
    return out


def summary_line(ans: dict) -> str:
    """One line for the command line: the target, what blocks it and what to relax."""
    relax = ans["relax"]
    tail = f"; relax: {relax['why']}" if relax.get("why") else ""
    return f"{ans['target']}: {ans['blocking']}: {ans['message']}{tail}"
