"""Walls whose inside is defined: holes filled or refused, declared open ends capped, STL
soups welded, orientation checked (ctrplan.collision.closure, via load_scene).

Oracles share no code with the closure: the intact mesh checked by FCL (a probe crossing the
surface collides), geometry by construction (a probe through an open end crosses the end's
disc), trimesh's own watertightness and volume on the result.
"""

from __future__ import annotations

import logging

import numpy as np
import pytest
import trimesh
import yaml

from ctrplan.collision.scene import SceneMesh, inside_walls, load_scene, replace
from ctrplan.collision.world import CollisionWorld
from ctrplan.errors import InputError
from ctrplan.shape.base import Shape


def write_scene(folder, meshes, position=(0.0, 0.0, 0.0), **extra):
    """A scene folder: meshes [(name, role, trimesh, file suffix)], base at ``position``."""
    folder.mkdir(parents=True, exist_ok=True)
    entries = []
    for name, role, mesh, suffix in meshes:
        mesh.export(folder / f"{name}.{suffix}")
        entries.append({"name": name, "file": f"{name}.{suffix}", "role": role})
    doc = {"name": "t", "units": "mm", "meshes": entries,
           "base_pose": {"position": list(position), "quaternion": [1.0, 0.0, 0.0, 0.0]}}
    doc.update(extra)
    (folder / "scene.yaml").write_text(yaml.safe_dump(doc))
    return folder


def lumen(radius=8.0, height=80.0, sections=48):
    """A closed cylinder around the z axis from z = -10 to height - 10 (the base at 0 inside)."""
    m = trimesh.creation.cylinder(radius=radius, height=height, sections=sections)
    m.apply_translation([0.0, 0.0, height / 2 - 10.0])
    v, f = trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=1.5)
    return trimesh.Trimesh(v, f, process=True)


def punch(mesh, centre, radius):
    """The mesh without the faces whose centroid lies within ``radius`` of ``centre``."""
    keep = np.linalg.norm(mesh.triangles_center - centre, axis=1) > radius
    return trimesh.Trimesh(mesh.vertices, mesh.faces[keep], process=False)


def probe(points, radius=0.3):
    """A one-configuration shape: the polyline ``points`` (robot base = scene frame here)."""
    p = np.asarray(points, dtype=float)[None]
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(p[0], axis=0), axis=1))])[None]
    return Shape(points=p, s=s, radius=np.full(p.shape[:2], radius), ok=np.array([True]))


def collides(scene, shape):
    return bool(CollisionWorld(scene, padding="none", prefilter=False).collides(shape)[0])


def test_a_small_hole_is_filled_and_a_probe_through_it_collides(tmp_path, caplog):
    """A 3 mm hole in the side of a closed lumen: filled with a warning naming where and how
    much; a probe from the base out through the hole collides, as with the intact mesh (and
    unlike the holed mesh taken as it is)."""
    intact = lumen()
    hole_at = np.array([8.0, 0.0, 30.0])
    holed = punch(intact, hole_at, 1.5)
    assert len(holed.faces) < len(intact.faces) and not holed.is_watertight
    with caplog.at_level(logging.WARNING, logger="ctrplan"):
        scene = load_scene(write_scene(tmp_path / "s", [("wall", "wall", holed, "ply")]))
    msg = " ".join(r.getMessage() for r in caplog.records)
    assert "filled a hole" in msg and "wall.ply" in msg and "mm^2" in msg
    (c,) = scene.mesh("wall").closures
    assert np.linalg.norm(c.centre - hole_at) < 1.5 and c.kind == "hole"
    assert scene.mesh("wall").closed and scene.mesh("wall").mesh.is_watertight
    through = probe([[0, 0, 0], [0.0, 0.0, 30.0], [12.0, 0.0, 30.0]])
    intact_scene = load_scene(write_scene(tmp_path / "i", [("wall", "wall", intact, "ply")]))
    assert collides(intact_scene, through)
    assert collides(scene, through)
    raw = replace(scene, meshes=(SceneMesh("wall", "wall", holed),))
    assert not collides(raw, through)          # the danger the fill removes


def test_a_large_hole_is_refused_with_its_location_and_size(tmp_path):
    holed = punch(lumen(), np.array([8.0, 0.0, 30.0]), 6.0)
    with pytest.raises(InputError) as err:
        load_scene(write_scene(tmp_path / "s", [("wall", "wall", holed, "ply")]))
    msg = str(err.value)
    assert "wall.ply" in msg and "hole" in msg and "open_ends" in msg
    at = np.array([float(x) for x in msg.split("at (")[1].split(")")[0].split(",")])
    size = float(msg.split("a hole ")[1].split(" mm")[0])
    assert np.linalg.norm(at - [8.0, 0.0, 30.0]) < 3.0 and 5.0 < size < 16.0


def test_max_hole_mm_lifts_the_limit(tmp_path):
    holed = punch(lumen(), np.array([8.0, 0.0, 30.0]), 4.0)
    with pytest.raises(InputError, match="a hole"):
        load_scene(write_scene(tmp_path / "a", [("wall", "wall", holed, "ply")]))
    scene = load_scene(write_scene(tmp_path / "b", [("wall", "wall", holed, "ply")], max_hole_mm=12.0))
    assert scene.mesh("wall").closed


def test_declared_open_ends_are_capped_and_a_probe_out_of_them_collides(tmp_path):
    """An open tube (the side only): refused as it is; with both ends declared it loads, and
    a probe leaving through an end collides with the cap (it crosses the end's disc)."""
    m = lumen()
    side = trimesh.Trimesh(m.vertices, m.faces[np.abs(m.face_normals[:, 2]) < 0.5], process=True)
    with pytest.raises(InputError, match="a hole 16"):
        load_scene(write_scene(tmp_path / "a", [("wall", "wall", side, "stl")]))
    ends = [{"mesh": "wall", "position": [0.0, 0.0, -10.0], "radius": 9.0},
            {"mesh": "wall", "position": [0.0, 0.0, 70.0], "radius": 9.0}]
    scene = load_scene(write_scene(tmp_path / "b", [("wall", "wall", side, "stl")], open_ends=ends))
    assert [c.kind for c in scene.mesh("wall").closures] == ["open end", "open end"]
    assert scene.mesh("wall").closed and scene.mesh("wall").mesh.is_watertight
    assert collides(scene, probe([[0, 0, 0], [0.0, 2.0, 60.0], [0.0, 2.0, 90.0]]))
    assert not collides(scene, probe([[0, 0, 0], [0.0, 2.0, 60.0]]))
    assert inside_walls(scene, np.array([[0.0, 0.0, 30.0]]))[0]
    assert not inside_walls(scene, np.array([[0.0, 0.0, 90.0], [20.0, 0.0, 30.0]])).any()


def test_an_open_end_that_matches_nothing_is_refused(tmp_path):
    ends = [{"mesh": "wall", "position": [50.0, 0.0, 0.0], "radius": 2.0}]
    with pytest.raises(InputError, match="open_ends: no open boundary of 'wall'"):
        load_scene(write_scene(tmp_path / "s", [("wall", "wall", lumen(), "ply")], open_ends=ends))
    with pytest.raises(InputError, match=r"open_ends\[0\].mesh"):
        load_scene(write_scene(tmp_path / "t", [("wall", "wall", lumen(), "ply")],
                               open_ends=[{"mesh": "nope", "position": [0, 0, 0], "radius": 1}]))


def test_a_ball_plug_seals_a_mouth_without_a_boundary_and_may_not_hold_the_base(tmp_path):
    """A double-walled cup (inner and outer surfaces joined at the rim: no boundary loop) is
    open at its mouth: the base inside sees a ray escape and is refused; a declared ball over
    the mouth plugs it; a ball around the base is refused."""
    # outer wall and bottom, inner wall and bottom, an annulus joining them at the rim z = 30
    k = 48
    t = np.linspace(0.0, 2 * np.pi, k, endpoint=False)
    ring = lambda r, z: np.stack([r * np.cos(t), r * np.sin(t), np.full(k, z)], axis=1)  # noqa: E731
    v = np.vstack([ring(10.0, -30.0), ring(10.0, 30.0), ring(8.0, 30.0), ring(8.0, -28.0),
                   [[0.0, 0.0, -30.0], [0.0, 0.0, -28.0]]])
    f = []
    for i in range(k):
        j = (i + 1) % k
        for a0, b0 in ((0, k), (k, 2 * k), (2 * k, 3 * k)):
            f += [[a0 + i, a0 + j, b0 + i], [a0 + j, b0 + j, b0 + i]]
        f += [[4 * k, 0 + j, 0 + i], [4 * k + 1, 3 * k + i, 3 * k + j]]
    cup = trimesh.Trimesh(v, np.array(f), process=True)
    assert cup.is_watertight
    with pytest.raises(InputError, match="lies outside the wall meshes"):
        load_scene(write_scene(tmp_path / "a", [("wall", "wall", cup, "ply")]))
    plug = [{"mesh": "wall", "position": [0.0, 0.0, 32.0], "radius": 9.5, "shape": "ball"}]
    scene = load_scene(write_scene(tmp_path / "b", [("wall", "wall", cup, "ply")], open_ends=plug))
    assert [c.kind for c in scene.mesh("wall").closures] == ["plug"]
    assert collides(scene, probe([[0, 0, 0], [0.0, 0.0, 50.0]]))
    with pytest.raises(InputError, match="inside the ball of open_ends"):
        load_scene(write_scene(tmp_path / "c", [("wall", "wall", cup, "ply")],
                               open_ends=[dict(plug[0], radius=40.0)]))


def test_stl_triangle_soup_is_welded_and_closed(tmp_path):
    """STL stores every triangle on its own; welded on load the box is closed (no holes)."""
    box = trimesh.creation.box(extents=(40.0, 40.0, 80.0))
    box.apply_translation([0.0, 0.0, 30.0])
    scene = load_scene(write_scene(tmp_path / "s", [("wall", "wall", box, "stl")]))
    m = scene.mesh("wall")
    assert m.closed and m.closures == () and m.mesh.is_watertight and len(m.mesh.vertices) == 8


def test_orientation_is_made_consistent_and_outward(tmp_path, caplog):
    m = lumen(sections=16)
    f = m.faces.copy()
    f[:5] = f[:5, ::-1]                            # five triangles wound the wrong way
    bad = trimesh.Trimesh(m.vertices, f, process=False)
    with caplog.at_level(logging.INFO, logger="ctrplan"):
        scene = load_scene(write_scene(tmp_path / "a", [("wall", "wall", bad, "ply")]))
    assert "inconsistent winding" in caplog.text
    got = scene.mesh("wall").mesh
    assert got.is_winding_consistent and got.volume > 0
    inverted = trimesh.Trimesh(m.vertices, m.faces[:, ::-1], process=False)
    assert inverted.volume < 0
    scene = load_scene(write_scene(tmp_path / "b", [("wall", "wall", inverted, "ply")]))
    assert scene.mesh("wall").mesh.volume > 0


def test_non_manifold_is_still_refused(tmp_path):
    m = lumen()
    extra = np.vstack([m.faces, [[m.faces[0][0], m.faces[0][1], 0]]])
    fan = trimesh.Trimesh(m.vertices, extra, process=False)
    with pytest.raises(InputError, match="non-manifold"):
        load_scene(write_scene(tmp_path / "s", [("wall", "wall", fan, "ply")]))


def test_shipped_airway_declares_its_three_open_ends():
    """The airway's bronchi leave the model (capped) and the trachea's double-walled upper end
    is plugged: the lumen is closed around the base, and a probe from the base out through a
    bronchus end collides."""
    scene = load_scene("airway")
    kinds = sorted((c.mesh, c.kind) for m in scene.meshes for c in m.closures)
    assert kinds == [("left_main_bronchus", "open end"), ("right_main_bronchus", "open end"),
                     ("trachea", "plug")]
    base = scene.base_pose[:3, 3]
    assert inside_walls(scene, base[None])[0]
    end = next(e for e in scene.open_ends if e.mesh == "left_main_bronchus")
    # from the base to the carina region, then out through the left bronchus's end cap
    carina = scene.targets[0].position
    inward = end.position + (carina - end.position) * 0.2
    outward = end.position + (end.position - carina) * 0.3
    path = scene.to_base(np.array([base, carina, inward, outward]))
    assert collides(scene, probe(path, radius=0.2))
