"""The distance-field cache verifies what it holds (ctrplan.collision.field_cache).

A tampered, truncated, empty or foreign cache file never changes a verdict: each is rebuilt
with a one-line warning, and the verdicts equal those of a world without any cache. Writes are
atomic, and two processes building the same entry leave one whole, valid file.
"""

from __future__ import annotations

import logging
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import trimesh

from ctrplan.collision.field import FieldConfig
from ctrplan.collision.field_cache import field_for, mesh_key
from ctrplan.collision.scene import Scene, SceneMesh
from ctrplan.collision.world import CollisionWorld
from ctrplan.shape.base import Shape

ROOT = Path(__file__).resolve().parents[1]
#: a coarse grid keeps the builds short
CFG = FieldConfig(h_mm=1.0, refine_mm=3.0)


def _lumen(radius=8.0):
    m = trimesh.creation.cylinder(radius=radius, height=60.0, sections=32)
    m.apply_translation([0.0, 0.0, 20.0])
    return m


def _scene(mesh) -> Scene:
    return Scene(name="t", path="", meshes=(SceneMesh("wall", "wall", mesh),), base_pose=np.eye(4),
                 targets=())


def _probes(n=400, seed=0) -> Shape:
    """Random 3-point chains from the base (radius 0.5 mm): many near and across the wall."""
    rng = np.random.default_rng(seed)
    p = np.zeros((n, 3, 3))
    p[:, 1] = rng.normal(0, 5.0, (n, 3)) + [0, 0, 20]
    p[:, 2] = p[:, 1] + rng.normal(0, 5.0, (n, 3))
    s = np.concatenate([np.zeros((n, 1)), np.cumsum(np.linalg.norm(np.diff(p, axis=1), axis=2), axis=1)], 1)
    return Shape(points=p, s=s, radius=np.full((n, 3), 0.5), ok=np.ones(n, bool))


def _entry(folder: Path, mesh) -> Path:
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.faces)
    return folder / f"field-{mesh_key(v, f, CFG, bool(mesh.is_watertight))}.npz"


@pytest.fixture(scope="module")
def reference():
    """Verdicts with no cache at all, and the two meshes' fields built once."""
    wide, narrow = _lumen(8.0), _lumen(6.0)
    want = CollisionWorld(_scene(narrow), cache=False, field_config=CFG).check(_probes())
    assert 50 < want.collides.sum() < 350
    return wide, narrow, want


def _damage(path: Path, how: str, other: Path) -> None:
    data = path.read_bytes()
    if how == "truncated":
        path.write_bytes(data[: len(data) // 2])
    elif how == "empty":
        path.write_bytes(b"")
    elif how == "flipped":
        b = bytearray(data)
        for k in range(len(b) // 3, len(b) // 3 + 64):
            b[k] ^= 0xFF
        path.write_bytes(bytes(b))
    elif how == "foreign":            # another mesh's entry under this mesh's name
        shutil.copyfile(other, path)
    elif how == "not-npz":
        path.write_bytes(b"PK\x03\x04 garbage" * 100)
    elif how == "edited":            # a whole, readable entry whose bounds were raised
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
        arrays["lb"] = arrays["lb"] + 5.0
        np.savez(path, **arrays)


@pytest.fixture(scope="module")
def filled_cache(tmp_path_factory, reference):
    """A cache folder holding both meshes' entries (built once; each test damages a copy)."""
    wide, narrow, _ = reference
    folder = tmp_path_factory.mktemp("cache")
    field_for(wide, CFG, cache=folder)
    field_for(narrow, CFG, cache=folder)
    return folder


@pytest.mark.parametrize("how", ["truncated", "empty", "flipped", "foreign", "not-npz", "edited"])
def test_a_bad_cache_entry_never_changes_a_verdict(tmp_path, caplog, reference, filled_cache, how):
    wide, narrow, want = reference
    tmp_path = tmp_path / "cache"
    shutil.copytree(filled_cache, tmp_path)
    entry, other = _entry(tmp_path, narrow), _entry(tmp_path, wide)
    assert entry.is_file() and other.is_file()
    _damage(entry, how, other)
    with caplog.at_level(logging.WARNING, logger="ctrplan"):
        got = CollisionWorld(_scene(narrow), cache=tmp_path, field_config=CFG).check(_probes())
    warnings = [r.getMessage() for r in caplog.records if r.levelno >= logging.WARNING]
    assert len(warnings) == 1 and "rebuilding" in warnings[0] and "\n" not in warnings[0]
    np.testing.assert_array_equal(got.collides, want.collides)
    np.testing.assert_allclose(got.clearance_mm, want.clearance_mm)
    # rebuilt in place: the next load is silent
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="ctrplan"):
        field_for(narrow, CFG, cache=tmp_path)
    assert not caplog.records
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([entry.name, other.name])


def test_the_entry_holds_the_mesh_and_parameter_hash(tmp_path):
    mesh = _lumen()
    field_for(mesh, CFG, cache=tmp_path)
    entry = _entry(tmp_path, mesh)
    with np.load(entry) as z:
        digest = str(z["mesh_digest"])
    assert entry.name == f"field-{digest[:32]}.npz" and len(digest) == 64
    # other parameters, other entry
    field_for(mesh, FieldConfig(h_mm=1.2, refine_mm=3.0), cache=tmp_path)
    assert len(list(tmp_path.glob("field-*.npz"))) == 2


_BUILD = """
import sys
import trimesh
from ctrplan.collision.field import FieldConfig
from ctrplan.collision.field_cache import field_for
m = trimesh.creation.cylinder(radius=8.0, height=60.0, sections=32)
m.apply_translation([0.0, 0.0, 20.0])
field_for(m, FieldConfig(h_mm=1.0, refine_mm=3.0), cache=sys.argv[1])
"""


def test_two_processes_building_the_same_entry_leave_one_valid_file(tmp_path, caplog):
    env_py = [sys.executable, "-c", _BUILD, str(tmp_path)]
    procs = [subprocess.Popen(env_py, cwd=ROOT, stderr=subprocess.PIPE) for _ in range(2)]
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err.decode()[-2000:]
    files = sorted(p.name for p in tmp_path.iterdir())
    assert len(files) == 1 and files[0].startswith("field-") and files[0].endswith(".npz")
    with caplog.at_level(logging.WARNING, logger="ctrplan"):
        f = field_for(_lumen(), CFG, cache=tmp_path)
    assert not caplog.records and f.build_s == 0.0
