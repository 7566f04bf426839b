"""Shape models: configuration -> whole backbone (physics or learned)."""

from ctrplan.shape.base import Shape, ShapeModel
from ctrplan.shape.physics import PhysicsConfig, PhysicsModel

__all__ = ["Shape", "ShapeModel", "PhysicsModel", "PhysicsConfig"]
