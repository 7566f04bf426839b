"""Build hook: put the shipped scenes (top-level ``anatomy/``) into the wheel.

The repository keeps scenes in ``anatomy/<name>/`` (meshes, scene.yaml, NOTICE.md). A built wheel
(or a non-editable ``pip install .``) carries them as ``ctrplan/anatomy/<name>/``, where
:func:`ctrplan.collision.scene.anatomy_dir` finds them. Editable installs copy nothing and keep
reading ``anatomy/`` in the checkout. The source meshes in ``anatomy/sources/`` (only needed to
rebuild the scenes) stay out of the wheel.
"""

from __future__ import annotations

import shutil
from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

ROOT = Path(__file__).resolve().parent


class build_py_with_scenes(build_py):
    def run(self) -> None:
        super().run()
        if getattr(self, "editable_mode", False):
            return
        src = ROOT / "anatomy"
        dst = Path(self.build_lib) / "ctrplan" / "anatomy"
        if dst.exists():
            shutil.rmtree(dst)
        for scene in sorted(src.iterdir()) if src.is_dir() else []:
            if (scene / "scene.yaml").is_file():
                shutil.copytree(scene, dst / scene.name)


setup(cmdclass={"build_py": build_py_with_scenes})
