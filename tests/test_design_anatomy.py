"""The anatomy ``ctrplan design`` reads before it samples, the space it derives, and what it says
when a target cannot be reached.

Oracles that share no code with ctrplan:

- an analytic lumen (tests/design_scenes.py: a union of balls along a centre line we write down,
  meshed by scikit-image, placed by a random rigid transform): a straight stretch, a 60 degree
  bend of radius 25 mm, a straight tail, a narrowing to radius 1.2 mm; its depth, bend, width
  and the straight protrusion at the entry in closed form;
- the same lumen with a neck closed below the smallest stock tube: the place is where we put it;
- the generated known-feasible anatomies (tests/design_scenes.py: around a known robot's
  motions computed by the foreign mechanics): each known motion is free in the independent
  re-check (tests/foreign/recheck.py, exact FCL cylinders);
- CMA-ES's candidates do not depend on what else uses numpy's global generator (replayed with
  and without interference).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from tests.design_scenes import bend_centreline, build, random_rotation, tube_lumen

pytestmark = pytest.mark.xdist_group("design_anatomy")

STRAIGHT, BEND_R, BEND_DEG, TAIL, LUMEN_R = 20.0, 25.0, 60.0, 15.0, 2.5
NARROW = (6.0, 16.0, 1.2)     # z from, z to (base frame), radius: the narrowing
NECK = (8.0, 16.0, 0.15)      # the closed variant's neck: closed for z in [10.4, 13.6]


def _pose(seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    pose = np.eye(4)
    pose[:3, :3] = random_rotation(rng)
    pose[:3, 3] = rng.uniform(-40, 40, 3)
    return pose


def _radii(c: np.ndarray, narrow) -> np.ndarray:
    r = np.full(len(c), LUMEN_R)
    r[(c[:, 2] >= narrow[0]) & (c[:, 2] <= narrow[1]) & (c[:, 0] < 1e-9)] = narrow[2]
    return r


def _end(c: np.ndarray) -> np.ndarray:
    return c[-1]


@pytest.fixture(scope="module")
def bend(tmp_path_factory):
    c = bend_centreline(STRAIGHT, BEND_R, math.radians(BEND_DEG), TAIL)
    pose = _pose(3)
    folder = tube_lumen(tmp_path_factory.mktemp("bend"), c, _radii(c, NARROW), pose, {"end": _end(c)},
                        name="analytic_bend")
    return folder, pose


@pytest.fixture(scope="module")
def neck(tmp_path_factory):
    c = bend_centreline(STRAIGHT, BEND_R, math.radians(BEND_DEG), TAIL)
    pose = _pose(4)
    folder = tube_lumen(tmp_path_factory.mktemp("neck"), c, _radii(c, NECK), pose, {"end": _end(c)},
                        name="analytic_neck")
    return folder, pose


def _analyse(folder, tolerance=1.0, extra=None):
    from ctrplan.design import resolve_scene, resolve_targets
    from ctrplan.design.anatomy import analyse
    from ctrplan.design.space import load_stock
    from ctrplan.planning.plan import world_for

    sc = resolve_scene(folder)
    names, pts = resolve_targets(sc, [t.name for t in sc.targets])
    if extra is not None:                       # more targets (scene frame)
        names, pts = names + [f"x{i}" for i in range(len(extra))], np.vstack([pts, extra])
    radii = np.array([od / 2 for od, _ in load_stock()])
    return analyse(sc, world_for(sc, 0.0, 0.08), names, pts, radii, tolerance_mm=tolerance), sc


def test_corridor_of_an_analytic_bend(bend):
    """Depth, bend, narrowest width and place, and the straight protrusion at the entry, against
    the lumen's construction (closed form)."""
    folder, pose = bend
    an, _ = _analyse(folder)
    (r,) = an.routes
    assert r.connected and r.target_gap_mm == 0.0
    depth = STRAIGHT + BEND_R * math.radians(BEND_DEG) + TAIL
    assert abs(r.depth_mm - depth) < 1.5, r.depth_mm
    main = max(r.bends, key=lambda b: b.angle_deg)
    assert abs(main.angle_deg - BEND_DEG) < 8.0, r.bends
    assert STRAIGHT - 5.0 < main.at_mm < STRAIGHT + 3.0
    assert 18.0 < main.radius_mm < 35.0
    # the narrowing: radius 1.2 mm for z in [8.5, 13.5] (wider balls reach 2.5 mm into it)
    n = r.narrowest
    assert abs(n.width_mm - 2 * NARROW[2]) < 0.45, n
    assert 8.0 < n.at_mm < 14.5
    base = pose[:3, :3].T @ (n.position - pose[:3, 3])       # the place, base frame
    assert np.hypot(base[0], base[1]) < 0.8 and 8.0 < base[2] < 14.5
    # a straight tube of radius 0.5 leaves the lumen where the axis is 2 mm from the arc's wall:
    # sqrt(R^2 + (z - S)^2) - R = 2.5 - 0.5
    e = an.entry
    z_half = STRAIGHT + math.sqrt((BEND_R + LUMEN_R - 0.5) ** 2 - BEND_R**2)
    i = int(np.flatnonzero(np.isclose(e.radii, 0.5))[0])
    assert abs(e.straight_mm[i] - z_half) < 0.8, (e.straight_mm[i], z_half)
    # a tube of radius 1.5 does not pass the narrowing (it starts where the wide balls end)
    j = int(np.flatnonzero(np.isclose(e.radii, 1.5))[0])
    assert 5.5 < e.straight_mm[j] < 8.0, e.straight_mm[j]
    # an arc of curvature 1/R from the base leaves the lumen where its offset R (1 - cos(s / R))
    # exceeds the room: 2.0 mm before the narrowing (s = 10.1 mm at R = 25), 0.7 mm inside it
    # (s = 5.9 mm); a gentle arc bending the lumen's way goes farther than the straight line
    assert 5.5 < e.longest(0.5, 1 / BEND_R) < 10.6
    assert e.longest(0.5, 0.005) > e.straight_mm[i] + 2.0


def test_derived_space_contains_what_the_bend_needs(bend):
    """Stock that passes the narrowing, curvatures up to the bend's, curved lengths that fit the
    entry, straight lengths that reach the target."""
    from ctrplan.design.derive import derive
    from ctrplan.design.space import Bounds, load_stock

    an, _ = _analyse(bend[0])
    stock = load_stock()
    d = derive(an, Bounds(), stock)
    ods = [stock[i][0] for i in d.inner.sizes]
    assert 2.2 in ods and 3.0 not in ods and 3.5 not in ods     # 2.4 mm wide + half the grid
    assert d.inner.curvature[0] == 0.0 and d.inner.curvature[1] >= 1 / BEND_R
    assert d.inner.curvature[1] <= Bounds().curvature[1]
    depth = STRAIGHT + BEND_R * math.radians(BEND_DEG) + TAIL
    assert d.inner.straight_length[0] + d.inner.curved_length[1] <= depth
    assert d.inner.straight_length[1] + d.inner.curved_length[0] >= depth
    # the curved-length cap follows the entry room: a gentle arc bending the lumen's way
    # protrudes farther than a straight one, the bend's own curvature (from the base, where the
    # lumen is still straight for 20 mm) much less
    assert d.curved_cap(0.5, 0.005) > d.curved_cap(0.5, 0.0) > d.curved_cap(0.5, 1 / BEND_R) + 10.0


def test_blocks_are_named_with_numbers_and_places(bend):
    """Each check of the explanation, provoked by one limit at a time on the analytic bend."""
    from ctrplan.design.explain import explain
    from ctrplan.design.space import Bounds, load_stock

    an, sc = _analyse(bend[0])
    stock = load_stock()

    def why(b=None, st=stock, margin=0.0):
        (ans,) = explain(an, b or Bounds(), st, (), 1, margin, 1.0, [], None)
        return ans

    assert why()["blocking"] == "search"
    # a target 6 mm beside the tail's end, outside the lumen of radius 2.5 mm
    pose = bend[1]
    c = bend_centreline(STRAIGHT, BEND_R, math.radians(BEND_DEG), TAIL)
    out = pose[:3, :3] @ (c[-1] + [0.0, 6.0, 0.0]) + pose[:3, 3]
    an2, _ = _analyse(bend[0], extra=out[None])
    (tg,) = [a for a in explain(an2, Bounds(), stock, (), 1, 0.0, 1.0, [], None) if a["target"] == "x0"]
    assert tg["blocking"] == "target" and 3.0 < tg["numbers"]["gap_mm"] < 4.2, tg
    wide = ((3.0, 2.6), (3.5, 3.1))                          # only tubes wider than the narrowing
    a = why(st=wide)
    assert a["blocking"] == "corridor" and a["kind"] == "necessary"
    assert abs(a["numbers"]["width_mm"] - 2.4) < 0.45 and a["numbers"]["needs_mm"] == 3.0
    assert a["relax"]["constraint"] == "stock" and a["relax"]["to"] < 3.0
    assert "wide" in a["message"] and "past the entry" in a["message"]
    m = why(margin=0.9)                                       # 0.51 + 1.8 > 2.4
    assert m["blocking"] == "corridor" and m["relax"]["constraint"] == "margin_mm"
    far = math.dist(sc.to_base(sc.targets[0].position[None])[0], (0, 0, 0))
    ln = why(Bounds(max_length_mm=30.0, curved_length=(5.0, 20.0), straight_length=(10.0, 25.0)))
    assert ln["blocking"] == "length" and ln["relax"]["to"] == math.ceil(far)
    st = why(Bounds(max_stroke_mm=20.0, curved_length=(5.0, 20.0), straight_length=(10.0, 20.0)))
    assert st["blocking"] == "stroke" and st["relax"]["constraint"] == "max_stroke_mm"
    en = why(Bounds(curved_length=(60.0, 150.0)))             # no arc of 60 mm fits at the entry
    assert en["blocking"] == "entry" and en["numbers"]["room_mm"] < 60.0
    assert en["relax"]["constraint"] == "curved_length" and en["relax"]["to"][0] < 60.0
    cu = why(Bounds(curvature=(0.0, 0.01)))
    assert cu["blocking"] == "curvature" and cu["numbers"]["needs_per_mm"] > 0.01
    # cutting the corner (room 2.5 - 0.255 mm either side) a tube needs 1 / (25 + 2 x 2.245 /
    # (1 - cos 30 deg)) = 0.0173 1/mm: 0.44 % strain on the thinnest tube (od 0.51 mm)
    sn = why(Bounds(strain_limit=0.003))
    assert sn["blocking"] == "strain" and 0.003 < sn["numbers"]["strain"] < 0.006
    assert why(Bounds(strain_limit=0.006))["blocking"] == "search"


def test_a_closed_neck_is_named_where_it_is(neck, tmp_path, capsys):
    """The lumen closed by a neck of radius 0.15 mm (below every stock tube; the balls of the
    wide lumen on either side reach z = 10.4 and 13.6): the command exits 1 and says, for the
    target, that the corridor is closed there, and that no design constraint admits a design;
    the search runs one generation only (to show the closest design)."""
    import json

    from ctrplan.cli import main

    folder, pose = neck
    out = tmp_path / "d"
    rc = main(["-q", "design", "--scene", str(folder), "--targets", "end", "--out", str(out)])
    text = capsys.readouterr().out
    assert rc == 1
    line = next(ln for ln in text.splitlines() if ln.strip().startswith("end:") and "corridor" in ln)
    assert "past the entry" in line and "no design constraint" in line
    doc = json.loads((out / "design.json").read_text())
    assert doc["status"] == "NONE_REACHED" and doc["reached"] == 0
    (b,) = doc["blocked"]
    assert b["blocking"] == "corridor" and b["kind"] == "necessary"
    assert b["numbers"]["width_mm"] < 0.51
    p = pose[:3, :3].T @ (np.array(b["place"]["position"]) - pose[:3, 3])
    assert np.hypot(p[0], p[1]) < 1.0 and 9.9 < p[2] < 14.1, p
    assert 9.9 < b["place"]["at_mm"] < 14.1
    assert doc["closest"] is not None and doc["counts"]["evaluations"] == 16
    assert doc["anatomy"]["routes"][0]["narrowest"]["width_mm"] < 0.51
    assert "Why targets are not reached" in (out / "report.md").read_text()


def test_strategy_candidates_ignore_other_users_of_numpy_random():
    """Two strategies with the same seed and fitness: one with numpy's global generator used (and
    reseeded) between every call, one without; the same candidates, generation after generation."""
    from ctrplan.design.strategy import Strategy

    def run(interfere: bool) -> list:
        st = Strategy(2, 8, 8, seed=5, x0=np.full(8, 0.5))
        seen = []
        for g in range(6):
            if interfere:
                np.random.seed(g)
                np.random.rand(17)
            xs = st.ask()
            if interfere:
                np.random.randn(5)
            seen.append(np.array(xs))
            st.tell(xs, [float(np.sum((x - 0.3) ** 2)) for x in xs])
        return seen

    a, b = run(False), run(True)
    assert all(np.array_equal(x, y) for x, y in zip(a, b))
    assert len(a) == 6 and a[0].shape == (8, 8)
    # and it converges toward the minimum of the sphere function at 0.3
    late = run(False)[-1]
    assert np.abs(late.mean(axis=0) - 0.3).max() < np.abs(a[0].mean(axis=0) - 0.3).max()


def test_generated_anatomy_holds_the_known_motions(tmp_path):
    """Seed 0: the lumen is closed, the base lies inside it, the targets are the known robot's
    tips, and every state of every known motion is free in the independent re-check."""
    import trimesh

    from tests.foreign.recheck import check_states

    ks = build(0, tmp_path / "k0")
    mesh = trimesh.load(ks.folder / "lumen.ply", force="mesh")
    assert mesh.is_watertight
    assert mesh.contains(ks.pose[:3, 3][None])[0]
    assert len(ks.motions) == 3 and ks.info["branches"] >= 2 and ks.info["narrowings"] >= 1
    for q in ks.motions:
        rep = check_states(ks.robot, ks.folder, q[::4], points=500, distances=False)
        assert rep.free
