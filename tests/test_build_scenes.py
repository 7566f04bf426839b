"""The shipped scenes rebuild bit for bit from the repository alone.

``python -m ctrplan.collision.build_scenes`` reads the source meshes carried in
``anatomy/sources/`` (with their NOTICE files) and the procedural generators; every file it
writes (meshes, scene.yaml with the picked targets, NOTICE.md) must equal the committed one byte
for byte. About 70 s per scene on one core, so the full rebuild runs with the statistical suites
(``make test-stat``, ``.ci/run``); the default run checks that the sources are all there.
"""

from __future__ import annotations

import filecmp
from pathlib import Path

import pytest

from ctrplan.collision import build_scenes
from ctrplan.collision.scene import SHIPPED_SCENES

ROOT = Path(__file__).resolve().parents[1]
ANATOMY = ROOT / "anatomy"
SOURCES = ANATOMY / "sources"


def test_sources_are_in_the_repository_with_notices():
    assert build_scenes.default_sources() == SOURCES
    for rel in ("hra_ccf/3d-vh-m-trachea.glb", "hra_ccf/3d-vh-m-main-bronchus.glb",
                "hra_ccf/NOTICE.md", "mni152/brain_surface_mni152.ply",
                "mni152/lateral_ventricles_mni152.ply", "mni152/NOTICE.md"):
        assert (SOURCES / rel).is_file(), rel
    # every third-party scene keeps the NOTICE of its source, unchanged
    assert (ANATOMY / "airway" / "NOTICE.md").read_bytes() == (SOURCES / "hra_ccf" / "NOTICE.md").read_bytes()
    assert (ANATOMY / "neuro" / "NOTICE.md").read_bytes() == (SOURCES / "mni152" / "NOTICE.md").read_bytes()


@pytest.mark.statistical
@pytest.mark.parametrize("name", SHIPPED_SCENES)
def test_scene_rebuilds_bit_for_bit(tmp_path, name):
    assert build_scenes.main(["--out", str(tmp_path), name]) == 0
    built = sorted(p.name for p in (tmp_path / name).iterdir())
    shipped = sorted(p.name for p in (ANATOMY / name).iterdir())
    assert built == shipped
    match, mismatch, errors = filecmp.cmpfiles(ANATOMY / name, tmp_path / name, shipped, shallow=False)
    assert mismatch == [] and errors == [], (mismatch, errors)
