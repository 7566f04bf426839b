"""Resolve a model name (``physics``, ``rigid``, ``learned`` or a file path) to a shape model."""

from __future__ import annotations

import os
from pathlib import Path

from ctrplan.errors import ArgumentError
from ctrplan.robot import Robot, load_robot
from ctrplan.shape.base import ShapeModel
from ctrplan.shape.physics import PhysicsModel

MODEL_NAMES = ("physics", "rigid", "learned")


def load_model(spec: str | os.PathLike | ShapeModel, robot: Robot | str,
               device: str | None = None) -> ShapeModel:
    """Return a shape model for ``robot``.

    spec : ``"physics"`` (torsionally compliant), ``"rigid"``, ``"learned"`` (the shipped
        default network of the robot) or the path of a model file written by ``ctrplan train``;
        an object with ``shape``/``backbone`` is returned unchanged.
    device : where a learned model evaluates (``cpu``, ``cuda[:N]``, ``auto``; None: the CPU
        unless inside :class:`ctrplan.shape.learned.using_device`); other models ignore it.
    """
    if not isinstance(spec, (str, os.PathLike)):
        return spec
    robot = load_robot(robot)
    s = str(spec)
    if s == "physics":
        return PhysicsModel(robot, torsion=True)
    if s == "rigid":
        return PhysicsModel(robot, torsion=False)
    if s == "learned":
        from ctrplan.shape.learned import default_model_for

        return default_model_for(robot, device=device)
    path = Path(s)
    if not path.exists():
        raise ArgumentError("model", f"{s!r} is not a model name ({', '.join(MODEL_NAMES)}) or an existing file")
    check_model_file(path)
    from ctrplan.shape.effects import EffectModel, is_effect_model_file

    if is_effect_model_file(path):  # a calibrated model written by `ctrplan diagnose`
        return EffectModel.load(path, robot=robot)
    from ctrplan.shape.learned import LearnedModel

    return LearnedModel.load(path, robot=robot, device=device)


#: Largest model file read (bytes): trained networks are a few MB, calibrated YAML about 2 kB.
MAX_MODEL_BYTES = 256 << 20


def check_model_file(path: str | os.PathLike) -> Path:
    """``path`` when it is a regular ``.pt`` / ``.yaml`` / ``.yml`` file of a plausible size
    (devices, FIFOs and arbitrary files are refused before anything is read)."""
    from ctrplan.robot import check_regular_file

    return check_regular_file(path, (".pt", ".yaml", ".yml"),
                              "a model file (.pt from ctrplan train, calibrated .yaml)",
                              max_bytes=MAX_MODEL_BYTES)
