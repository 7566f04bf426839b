"""The shape-model protocol and the batched shape result shared by every model."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from ctrplan.robot import Robot


@dataclass(frozen=True)
class Shape:
    """Backbones of a batch of configurations, in the robot base frame.

    points : (B, m, 3) float, mm — evenly spaced in arc length from s = 0 (constraint plane)
        to the tip, inclusive.
    s : (B, m) float, mm — arc length of each point.
    radius : (B, m) float, mm — outer radius of the outermost tube present at each point.
    ok : (B,) bool — False where the model could not produce a trustworthy shape (the shooting
        did not converge); callers must treat such shapes as invalid.
    """

    points: np.ndarray
    s: np.ndarray
    radius: np.ndarray
    ok: np.ndarray

    @property
    def tip(self) -> np.ndarray:
        """(B, 3) tip positions, mm."""
        return self.points[:, -1, :]

    def __len__(self) -> int:
        return int(self.points.shape[0])


@runtime_checkable
class ShapeModel(Protocol):
    """Anything that turns configurations into backbones (physics or learned)."""

    robot: Robot
    name: str

    def shape(self, q: np.ndarray, points: int = 20) -> Shape:
        """Backbones with radii and status. q : (B, 2n) float, rad and mm."""
        ...

    def backbone(self, q: np.ndarray, points: int = 20) -> np.ndarray:
        """(B, points, 3) backbone points, mm, robot base frame."""
        ...


def radius_along(robot: Robot, q: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Outer radius (mm) of the outermost tube present at arc lengths ``s``.

    q : (B, 2n); s : (B, m) mm. Returns (B, m). A tube is present up to and including its
    distal end; past the tip the innermost tube's radius is used.
    """
    q = np.atleast_2d(np.asarray(q, dtype=float))
    n = robot.n
    ends = q[:, n:] + robot.lengths                       # (B, n)
    od = robot.array("od")
    present = s[:, :, None] <= ends[:, None, :] + 1e-9    # (B, m, n)
    # index of the outermost tube present (tubes are ordered innermost first)
    idx = np.where(present, np.arange(n)[None, None, :], 0).max(axis=2)
    return od[idx] / 2.0


def check_q(robot: Robot, q: np.ndarray) -> np.ndarray:
    """Coerce q to a finite float (B, 2n) array or raise ValueError."""
    q = np.asarray(q, dtype=float)
    if q.ndim == 1:
        q = q[None, :]
    if q.ndim != 2 or q.shape[1] != robot.dof:
        raise ValueError(f"q must have shape (B, {robot.dof}) for robot {robot.name!r}, got {q.shape}")
    if not np.all(np.isfinite(q)):
        raise ValueError("q contains NaN or infinite values")
    return q
