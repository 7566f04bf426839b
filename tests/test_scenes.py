"""Shipped anatomy scenes (provenance, geometry, reachable targets) and bad scene input."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import yaml

from ctrplan.collision.scene import (
    SHIPPED_SCENES,
    anatomy_dir,
    inside_walls,
    list_scenes,
    load_scene,
    matrix_to_quaternion,
    quaternion_to_matrix,
)
from ctrplan.collision.world import CollisionWorld
from ctrplan.errors import InputError
from ctrplan.shape.physics import PhysicsModel
from tests.test_collision import synthetic_meshes, write_scene


def test_all_shipped_scenes_are_listed():
    assert set(SHIPPED_SCENES) <= set(list_scenes())


@pytest.mark.parametrize("name", SHIPPED_SCENES)
def test_shipped_scene_provenance_and_size(name):
    scene = load_scene(name)
    folder = anatomy_dir() / name
    doc = yaml.safe_load((folder / "scene.yaml").read_text())
    assert doc["units"] == "mm" and doc["source"] and doc["licence"] and doc["frame"]
    assert scene.source and scene.licence
    roles = {m.role for m in scene.meshes}
    assert "wall" in roles
    for m in scene.meshes:
        assert (folder / m.file).stat().st_size < 1_500_000
        assert 1.0 < np.ptp(m.mesh.vertices, axis=0).max() < 400.0   # mm, not metres
    if name in ("airway", "neuro"):   # third-party data keeps its notice
        assert "licen" in (folder / "NOTICE.md").read_text().lower()
    assert np.allclose(scene.base_pose[:3, :3] @ scene.base_pose[:3, :3].T, np.eye(3))


@pytest.mark.parametrize("name", SHIPPED_SCENES)
def test_targets_are_reached_collision_free_by_seed1(name, seed1):
    """Every example target has a seed1 configuration whose tip reaches it (physics model)
    and whose whole shape is free with a 0.5 mm margin, inside the walls."""
    scene = load_scene(name)
    assert len(scene.targets) >= 10
    q = np.array([t.config for t in scene.targets])
    assert np.all(seed1.is_valid(q))
    shape = PhysicsModel(seed1).shape(q, points=21)
    tips = scene.to_scene(shape.tip)
    np.testing.assert_allclose(tips, scene.target_positions(), atol=1e-3)
    world = CollisionWorld(scene, margin_mm=0.5, padding="none")
    assert not world.check_exact(shape).collides.any()
    # the continuous tube (capsules padded by the model's bound, which is < 0.5 mm) is free too
    assert np.all(shape.pad < 0.5)
    assert not CollisionWorld(scene).check_exact(shape).collides.any()
    assert inside_walls(scene, tips).all()
    # spread out: no two targets closer than 2 mm
    d = np.linalg.norm(tips[:, None] - tips[None], axis=2) + np.eye(len(tips)) * 1e9
    assert d.min() > 2.0


def test_frames_roundtrip():
    scene = load_scene("neuro")
    p = np.random.default_rng(0).normal(size=(5, 4, 3)) * 30
    np.testing.assert_allclose(scene.to_base(scene.to_scene(p)), p, atol=1e-9)
    np.testing.assert_allclose(scene.to_scene(np.zeros(3)), scene.base_pose[:3, 3])
    q = matrix_to_quaternion(scene.base_pose[:3, :3])
    np.testing.assert_allclose(quaternion_to_matrix(q), scene.base_pose[:3, :3], atol=1e-9)


def test_scene_by_folder_and_yaml_path(tmp_path):
    folder = write_scene(tmp_path / "synthetic", synthetic_meshes())
    assert load_scene(folder).name == "synthetic"
    assert load_scene(folder / "scene.yaml").name == "synthetic"


def _bad(tmp_path, meshes=None, **kw):
    return write_scene(tmp_path / "bad", meshes or synthetic_meshes(), **kw)


def test_unknown_scene():
    with pytest.raises(InputError, match="not a shipped scene"):
        load_scene("no_such_scene")


def test_unknown_role(tmp_path):
    meshes = synthetic_meshes()
    meshes[1] = ("post", "bone", meshes[1][2])
    with pytest.raises(InputError, match="unknown role 'bone'"):
        load_scene(_bad(tmp_path, meshes))


def test_absurd_scale(tmp_path):
    meshes = synthetic_meshes()
    m = meshes[1][2].copy()
    m.apply_scale(0.001)   # a mesh left in metres
    meshes[1] = ("post", "obstacle", m)
    with pytest.raises(InputError, match="is the mesh in mm"):
        load_scene(_bad(tmp_path, meshes))


def test_non_finite_mesh(tmp_path):
    folder = _bad(tmp_path)
    m = trimesh.creation.box(extents=(5, 5, 5))
    v = m.vertices.copy()
    v[0, 0] = np.nan
    (folder / "post.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 8\nproperty float x\nproperty float y\n"
        "property float z\nelement face 12\nproperty list uchar int vertex_indices\nend_header\n"
        + "".join(f"{a} {b} {c}\n" for a, b, c in v)
        + "".join(f"3 {a} {b} {c}\n" for a, b, c in m.faces))
    with pytest.raises(InputError, match="non-finite"):
        load_scene(folder)


def test_empty_and_unreadable_mesh(tmp_path):
    folder = _bad(tmp_path)
    (folder / "post.ply").write_bytes(b"this is not a mesh")
    with pytest.raises(InputError, match="post.ply"):
        load_scene(folder)
    (folder / "post.ply").unlink()
    with pytest.raises(InputError, match="mesh file not found"):
        load_scene(folder)


def test_base_pose_outside_wall_or_inside_obstacle(tmp_path):
    with pytest.raises(InputError, match="outside the wall"):
        load_scene(_bad(tmp_path, position=(0.0, 0.0, 60.0)))
    with pytest.raises(InputError, match="inside the obstacle"):
        load_scene(_bad(tmp_path, position=(8.0, 0.0, 22.0)))


def test_open_wall_inside_test():
    scene = load_scene("airway")
    base = scene.base_pose[:3, 3]
    assert inside_walls(scene, base[None])[0]
    assert not inside_walls(scene, (base + np.array([60.0, 0.0, 0.0]))[None])[0]


@pytest.mark.parametrize("field,value,match", [
    ("units", "m", "must be 'mm'"),
    ("colour", "red", "unknown key"),
    ("meshes", [], "empty scene"),
])
def test_bad_scene_fields(tmp_path, field, value, match):
    folder = _bad(tmp_path)
    doc = yaml.safe_load((folder / "scene.yaml").read_text())
    doc[field] = value
    (folder / "scene.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(InputError, match=match):
        load_scene(folder)


def test_bad_quaternion(tmp_path):
    with pytest.raises(InputError, match="unit quaternion"):
        load_scene(_bad(tmp_path, quaternion=(1.0, 1.0, 0.0, 0.0)))


def test_procedural_meshes_are_deterministic():
    pytest.importorskip("skimage")
    from ctrplan.collision import procedural

    a = procedural.branching_tree(seed=5, root=np.zeros(3), direction=np.array([0, 0, -1.0]),
                                  length=50.0, radius=5.0, generations=2)
    b = procedural.branching_tree(seed=5, root=np.zeros(3), direction=np.array([0, 0, -1.0]),
                                  length=50.0, radius=5.0, generations=2)
    assert len(a) == 7
    for (pa, ra), (pb, rb) in zip(a, b):
        np.testing.assert_array_equal(pa, pb)
        np.testing.assert_array_equal(ra, rb)
    path = procedural.smooth_path(np.array([[0, 0, 0], [0, 5, 10], [0, 0, 20.0]]), 20)
    m1 = procedural.tube_mesh(path, 2.0, h=0.5)
    m2 = procedural.tube_mesh(path, 2.0, h=0.5)
    assert m1.is_watertight
    np.testing.assert_array_equal(m1.vertices, m2.vertices)
    d = trimesh.proximity.closest_point(m1, path[5:15])[1]
    assert np.all(np.abs(d - 2.0) < 0.3)


@pytest.mark.parametrize("name", ["skull_base", "bronchial_tree"])
def test_procedural_scene_regenerates_from_its_command(name, tmp_path):
    """The committed procedural scene is what its generator command writes (the oracle is the
    committed file). Compared geometrically, so a newer scikit-image or decimator that moves
    vertices by rounding does not fail the test, while any real change does."""
    pytest.importorskip("skimage")
    pytest.importorskip("fast_simplification")
    from ctrplan.collision.build_scenes import main as build_main

    assert build_main([name, "--out", str(tmp_path)]) == 0
    shipped, rebuilt = load_scene(name), load_scene(tmp_path / name)
    assert [m.name for m in rebuilt.meshes] == [m.name for m in shipped.meshes]
    np.testing.assert_allclose(rebuilt.base_pose, shipped.base_pose, atol=1e-9)
    for a, b in zip(shipped.meshes, rebuilt.meshes):
        assert a.role == b.role
        np.testing.assert_allclose(b.mesh.bounds, a.mesh.bounds, atol=0.05)
        assert b.mesh.volume == pytest.approx(a.mesh.volume, rel=2e-3)
        pts = b.mesh.sample(2000, seed=0)
        d = trimesh.proximity.closest_point(a.mesh, pts)[1]
        assert d.max() < 0.1, f"{a.name}: regenerated surface {d.max():.3f} mm from the shipped one"
    # Targets are picked by sampling the physics model, so they match when the meshes do.
    tr, ts = rebuilt.target_positions(), shipped.target_positions()
    assert tr.shape == ts.shape
    np.testing.assert_allclose(tr, ts, atol=0.5)


def test_empty_mesh(tmp_path):
    folder = _bad(tmp_path)
    (folder / "post.ply").write_text(
        "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float y\n"
        "property float z\nelement face 0\nproperty list uchar int vertex_indices\nend_header\n")
    with pytest.raises(InputError, match="post.ply"):
        load_scene(folder)
