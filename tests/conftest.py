"""Shared fixtures: shipped robots, small synthetic robots with known answers, seeded RNGs.

Hypothesis runs derandomized with few examples (profile ``ctrplan``) so the suite is
deterministic and fast; ``HYPOTHESIS_PROFILE=thorough`` explores more.
"""

from __future__ import annotations

import math
import os

import numpy as np
import pytest
from hypothesis import HealthCheck, settings

from ctrplan.robot import Robot, Tube, load_robot

settings.register_profile(
    "ctrplan", derandomize=True, max_examples=12, deadline=None,
    suppress_health_check=[HealthCheck.too_slow],
)
settings.register_profile("thorough", derandomize=False, max_examples=200, deadline=None)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ctrplan"))


@pytest.fixture(scope="session")
def seed1() -> Robot:
    return load_robot("seed1")


@pytest.fixture(scope="session")
def nylon() -> Robot:
    return load_robot("two_tube_nylon")


@pytest.fixture
def rng() -> np.random.Generator:
    return np.random.default_rng(12345)


def nitinol(od: float, id: float, straight: float, curved: float, kappa: float,
            E: float = 60000.0, nu: float = 0.33) -> Tube:
    """A tube with nitinol defaults (lengths mm, kappa 1/mm, E MPa)."""
    return Tube(od=od, id=id, straight_length=straight, curved_length=curved, curvature=kappa,
                youngs_modulus=E, poisson_ratio=nu)


def balanced_pair(straight: float = 100.0, curved: float = 100.0, kappa: float = 0.01) -> Robot:
    """Two tubes with equal bending stiffness EI, curvature and EI/GJ (the outer tube's E is
    scaled so that E*I matches): at relative rotation pi their curvatures cancel exactly."""
    inner = nitinol(1.0, 0.6, straight, curved, kappa)
    od2, id2 = 1.6, 1.2
    e2 = inner.second_moment / (math.pi / 64.0 * (od2**4 - id2**4)) * inner.youngs_modulus
    outer = nitinol(od2, id2, straight, curved, kappa, E=e2)
    return Robot(name="balanced_pair", tubes=(inner, outer))


def open_scene():
    """An open scene (base frame = scene frame): one 10 mm box 400 mm behind the constraint
    plane, since a collision world needs a mesh. Where instability, not collision, decides."""
    import trimesh

    from ctrplan.collision.scene import Scene, SceneMesh

    box = trimesh.creation.box((10.0, 10.0, 10.0))
    box.apply_translation((0.0, 0.0, -400.0))
    return Scene(name="open", path="<memory>", meshes=(SceneMesh("box", "obstacle", box),),
                 base_pose=np.eye(4), targets=())


def write_open_scene(folder) -> str:
    """:func:`open_scene` as a scene folder (scene.yaml + box.ply) for the command line."""
    from pathlib import Path

    import trimesh

    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    box = trimesh.creation.box((10.0, 10.0, 10.0))
    box.apply_translation((0.0, 0.0, -400.0))
    box.export(folder / "box.ply")
    (folder / "scene.yaml").write_text(
        "name: open\nunits: mm\nmeshes:\n  - {name: box, file: box.ply, role: obstacle}\n"
        "base_pose: {position: [0, 0, 0], quaternion: [1, 0, 0, 0]}\n"
        "source: a box written by the tests\nlicence: CC0\n")
    return str(folder)


def overlap_pair() -> Robot:
    """Two strongly curved tubes of equal lengths whose curved sections coincide: at
    beta = (-50, -50) they overlap over exactly s in [50, 150] mm (a long RK4 interval)."""
    return Robot(name="overlap_pair", tubes=(
        nitinol(1.0, 0.6, 100.0, 100.0, 0.015),
        nitinol(1.6, 1.2, 100.0, 100.0, 0.010),
    ))


#: the longest statistical work units (one xdist group each, several minutes on one worker):
#: collected first, so `make test-stat`'s two workers do not end with one of them alone
_LONG_FIRST = ("tests/test_resources.py", "tests/test_real_robot.py")


def pytest_collection_modifyitems(config, items):
    """Move the long work units (``_LONG_FIRST``) to the front; the rest keep their order."""
    items.sort(key=lambda it: 0 if it.nodeid.startswith(_LONG_FIRST) else 1)
