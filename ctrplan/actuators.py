"""Actuator limits of a robot: the speed and acceleration each tube's rotation and translation
can make (the ``actuators`` block of a robot YAML, optional; docs/conventions.md).

Units: rotation rad/s and rad/s^2 (alpha), translation mm/s and mm/s^2 (beta). The defaults
(:data:`DEFAULT_ROTATION`, :data:`DEFAULT_TRANSLATION`) are conservative values for the
laboratory actuation units CTRs are built with (one carriage per tube on a lead screw, the
tube rotated through a gear on the carriage); docs/conventions.md says what they rest on.
This module is a leaf of the robot stage (it imports only the errors and io helpers).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

from ctrplan.errors import InputError
from ctrplan.io import excerpt


@dataclass(frozen=True)
class JointLimits:
    """The limits of one actuated joint: ``max_speed`` (rad/s or mm/s) and ``max_accel``
    (rad/s^2 or mm/s^2), both > 0."""

    max_speed: float
    max_accel: float


#: Default rotation limits of a tube (rad/s, rad/s^2): about 10 rpm, full speed in 0.2 s.
DEFAULT_ROTATION = JointLimits(max_speed=1.0, max_accel=5.0)
#: Default translation limits of a tube (mm/s, mm/s^2): full speed in 0.2 s.
DEFAULT_TRANSLATION = JointLimits(max_speed=10.0, max_accel=50.0)


@dataclass(frozen=True)
class Actuator:
    """The two actuated joints of one tube: its ``rotation`` (alpha, rad/s and rad/s^2) and
    its ``translation`` (beta, mm/s and mm/s^2)."""

    rotation: JointLimits = DEFAULT_ROTATION
    translation: JointLimits = DEFAULT_TRANSLATION


#: The actuator of a tube whose robot file has no ``actuators`` block.
DEFAULT_ACTUATOR = Actuator()

#: Plausibility ranges (inclusive) of the limits; merged into :data:`ctrplan.robot.PLAUSIBLE`.
#: Below the lower end a plan would take days (a typo: 1e-9); above the upper end no tube
#: carriage moves (1 m/s, ~1000 rpm, 10 g): a units mistake (m/s given as mm/s, deg as rad).
ACTUATOR_RANGES: dict[str, tuple[float, float]] = {
    "rotation_speed": (1e-3, 100.0),           # rad/s
    "rotation_accel": (1e-3, 1e4),             # rad/s^2
    "translation_speed": (1e-3, 1000.0),       # mm/s
    "translation_accel": (1e-3, 1e5),          # mm/s^2
}
_UNITS = {"rotation_speed": "rad/s", "rotation_accel": "rad/s^2",
          "translation_speed": "mm/s", "translation_accel": "mm/s^2"}
_JOINTS = {"rotation": DEFAULT_ROTATION, "translation": DEFAULT_TRANSLATION}
_FIELDS = {"max_speed": "speed", "max_accel": "accel"}


def _limit(value: Any, kind: str, source: str, where: str) -> float:
    """A limit value: a finite number inside :data:`ACTUATOR_RANGES` [kind]."""
    unit = _UNITS[kind]
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise InputError(source, where, f"must be a number ({unit}), got {excerpt(value)}")
    v = float(value)
    if not math.isfinite(v):
        raise InputError(source, where, f"must be a finite number ({unit}), got {v!r}")
    lo, hi = ACTUATOR_RANGES[kind]
    if not lo <= v <= hi:
        raise InputError(source, where, f"{v:.6g} is outside the plausible range [{lo:g}, {hi:g}] "
                                        f"{unit} (a typo or a units mistake?)")
    return v


def _joint(data: Any, joint: str, source: str, where: str) -> JointLimits:
    default = _JOINTS[joint]
    if not isinstance(data, dict):
        raise InputError(source, where, "must be a mapping with max_speed and/or max_accel")
    unknown = set(data) - set(_FIELDS)
    if unknown:
        raise InputError(source, f"{where}.{sorted(unknown, key=str)[0]}", "unknown key "
                         "(an actuated joint has max_speed and max_accel)")
    vals = {k: _limit(data[k], f"{joint}_{_FIELDS[k]}", source, f"{where}.{k}")
            if k in data else getattr(default, k) for k in _FIELDS}
    return JointLimits(**vals)


def _actuator(data: Any, source: str, where: str) -> Actuator:
    if not isinstance(data, dict):
        raise InputError(source, where, "must be a mapping with rotation and/or translation")
    unknown = set(data) - set(_JOINTS)
    if unknown:
        raise InputError(source, f"{where}.{sorted(unknown, key=str)[0]}", "unknown key "
                         "(a tube's actuator has rotation and translation)")
    return Actuator(**{j: _joint(data[j], j, source, f"{where}.{j}") if j in data else d
                       for j, d in _JOINTS.items()})


def actuators_from_yaml(data: Any, n: int, source: str) -> tuple[Actuator, ...]:
    """The ``actuators`` block of a robot file: one mapping for every tube, or a list of one
    per tube (innermost first); a field not given takes its default. ``(n,)`` actuators."""
    if isinstance(data, dict):
        return (_actuator(data, source, "actuators"),) * n
    if isinstance(data, list):
        if len(data) != n:
            raise InputError(source, "actuators", f"a list needs one entry per tube ({n}), got "
                                                  f"{len(data)} (or give one mapping for all)")
        return tuple(_actuator(d, source, f"actuators[{i}]") for i, d in enumerate(data))
    raise InputError(source, "actuators", "must be a mapping (rotation, translation) for every "
                                          "tube or a list of one per tube")


def actuators_to_yaml(actuators: tuple[Actuator, ...]) -> dict | list:
    """The ``actuators`` block for ``actuators`` (every field written): one mapping when all
    tubes share one actuator, else a list."""
    def one(a: Actuator) -> dict:
        return {j: {"max_speed": float(getattr(a, j).max_speed),
                    "max_accel": float(getattr(a, j).max_accel)} for j in _JOINTS}

    if len(set(actuators)) == 1:
        return one(actuators[0])
    return [one(a) for a in actuators]
