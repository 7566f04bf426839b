"""Mesh readers follow each format's rules (ctrplan.collision.meshio via load_mesh).

Oracles: the formats' specifications, written out by hand here (OBJ vertex references are
1-based, negative ones count back from the last vertex defined; a binary STL is an 80-byte
header, a uint32 count and 50 bytes per triangle; a PLY header declares its element counts),
and trimesh reading the same valid files.
"""

from __future__ import annotations

import struct

import numpy as np
import pytest
import trimesh

from ctrplan.collision.meshio import mesh_triangles, ply_header
from ctrplan.collision.scene import load_mesh
from ctrplan.errors import InputError

TET = "v 0 0 0\nv 10 0 0\nv 0 10 0\nv 0 0 10\n"


def _obj(tmp_path, text, name="m.obj"):
    p = tmp_path / name
    p.write_text(text)
    return p


def test_obj_indices_are_one_based_and_negative_ones_relative(tmp_path):
    a = load_mesh(_obj(tmp_path, TET + "f 1 3 2\nf 1 2 4\nf 1 4 3\nf 2 3 4\n", "a.obj"))
    b = load_mesh(_obj(tmp_path, TET + "f -4 -2 -3\nf -4 -3 -1\nf -4 -1 -2\nf -3 -2 -1\n", "b.obj"))
    want = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
    np.testing.assert_array_equal(a.faces, want)
    np.testing.assert_array_equal(b.faces, want)
    np.testing.assert_array_equal(a.vertices, [[0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])
    # relative to the vertices defined so far, not to the file's end
    c = load_mesh(_obj(tmp_path, "v 0 0 0\nv 10 0 0\nv 0 10 0\nf -3 -2 -1\nv 0 0 10\nf -4 -3 -1\n", "c.obj"))
    np.testing.assert_array_equal(c.faces, [[0, 1, 2], [0, 1, 3]])


def test_obj_face_forms_polygons_comments_and_other_statements(tmp_path):
    text = ("# a quad in v/vt/vn form\nmtllib x.mtl\no quad\nv 0 0 0 1.0\nv 10 0 0\nv 10 10 0\n"
            "v 0 10 0\nvt 0 0\nvn 0 0 1\ns off\nusemtl m\nf 1/1/1 2/1/1 3//1 4/1 # fan\nl 1 2\n")
    m = load_mesh(_obj(tmp_path, text))
    np.testing.assert_array_equal(m.faces, [[0, 1, 2], [0, 2, 3]])


@pytest.mark.parametrize("face, match", [
    ("f 0 1 2", "index 0: OBJ indices start at 1"),
    ("f 1 2 5", "refers to vertex 5"),
    ("f -5 1 2", "reaches before the first vertex"),
    ("f 1 2", "at least 3 vertices"),
    ("f 1 x 2", "is not an index"),
    ("f 1.5 2 3", "is not an index"),
])
def test_obj_bad_indices_are_refused_naming_the_line(tmp_path, face, match):
    p = _obj(tmp_path, TET + face + "\n")
    with pytest.raises(InputError, match=match) as err:
        load_mesh(p)
    assert str(p) in str(err.value) and ("line 5" in str(err.value) or "refers to" in match)


def test_obj_bad_vertex_is_refused(tmp_path):
    with pytest.raises(InputError, match="line 2: vertex coordinate 'nan'"):
        load_mesh(_obj(tmp_path, "v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n"))
    with pytest.raises(InputError, match="a vertex needs x y z"):
        load_mesh(_obj(tmp_path, "v 0 0\nf 1 1 1\n", "b.obj"))
    with pytest.raises(InputError, match="no faces"):
        load_mesh(_obj(tmp_path, "v 0 0 0\n", "c.obj"))


def _box(tmp_path, name, **kw):
    box = trimesh.creation.box(extents=(10.0, 20.0, 30.0))
    p = tmp_path / name
    box.export(p, **kw)
    return p, box


def test_binary_stl_follows_its_header(tmp_path):
    p, box = _box(tmp_path, "b.stl")
    data = p.read_bytes()
    n = struct.unpack("<I", data[80:84])[0]
    assert n == len(box.faces) and len(data) == 84 + 50 * n
    assert mesh_triangles(p) == n
    m = load_mesh(p)
    np.testing.assert_allclose(np.sort(m.triangles.reshape(-1, 9), axis=0),
                               np.sort(box.triangles.reshape(-1, 9), axis=0), atol=1e-5)
    p.write_bytes(data[:-50])                       # one triangle short
    with pytest.raises(InputError, match=r"neither a binary STL \(its header declares 12 triangles"):
        load_mesh(p)
    p.write_bytes(data[:80] + struct.pack("<I", 10 ** 9) + data[84:])   # a lying count
    with pytest.raises(InputError, match="declares 1000000000 triangles"):
        load_mesh(p)


def test_ascii_stl_and_ascii_ply(tmp_path):
    p, box = _box(tmp_path, "a.stl", file_type="stl_ascii")
    assert p.read_bytes().startswith(b"solid")
    assert len(load_mesh(p).faces) == len(box.faces)
    q, _ = _box(tmp_path, "a.ply", encoding="ascii")
    assert len(load_mesh(q).faces) == len(box.faces)


def test_ply_header_rules(tmp_path):
    p, box = _box(tmp_path, "b.ply", encoding="binary")
    data = p.read_bytes()
    h = ply_header(data, str(p))
    assert h["vertex"] == len(box.vertices) and h["face"] == len(box.faces)
    assert mesh_triangles(p) == len(box.faces)
    cases = [
        (data[:len(data) - 20], "truncated: the header declares"),
        (data.replace(b"format binary_little_endian 1.0", b"format binary_little_endian 2.0"), "format must be"),
        (data.replace(b"element vertex 8", b"element vertex -8"), "an element needs a name and a count"),
        (data.replace(b"element vertex 8", b"element vertex 99999999999"), "an element needs a name and a count"),
        (data.replace(b"end_header", b"end_headxx"), "no 'end_header'"),
        (data.replace(b"property float x", b"property quad x"), "malformed property"),
        (b"plx" + data[3:], "not a PLY file"),
        (data.replace(b"element face", b"element fase"), "element face: missing"),
    ]
    for k, (bad, match) in enumerate(cases):
        q = tmp_path / f"bad{k}.ply"
        q.write_bytes(bad)
        with pytest.raises(InputError, match=match) as err:
            load_mesh(q)
        assert str(q) in str(err.value) and "\n" not in str(err.value)


def test_ply_vertex_count_must_match_the_body(tmp_path):
    """An ASCII PLY that declares more vertices than it holds is refused (trimesh alone would
    shift the face lines into the vertex list)."""
    p, box = _box(tmp_path, "a.ply", encoding="ascii")
    text = p.read_text().replace("element vertex 8", "element vertex 7")
    p.write_text(text)
    with pytest.raises(InputError):
        load_mesh(p)
