"""ctrplan: motion planning for concentric tube robots inside anatomy.

The public API is the handful of names below; they are imported lazily so that
``import ctrplan`` stays fast and does not load torch, FCL or OMPL until they are used.

Units (mm, rad, 1/mm, MPa), frames, the configuration vector ``q = [alpha_1..alpha_n,
beta_1..beta_n]`` and every file format are described in the repository's
``docs/conventions.md``; bad inputs and their messages in ``docs/bad-input.md``.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

_EXPORTS = {
    "Tube": "ctrplan.robot",
    "Robot": "ctrplan.robot",
    "load_robot": "ctrplan.robot",
    "read_configs": "ctrplan.robot",
    "write_configs": "ctrplan.robot",
    "InputError": "ctrplan.errors",
    "Shape": "ctrplan.shape.base",
    "ShapeModel": "ctrplan.shape.base",
    "PhysicsModel": "ctrplan.shape.physics",
    "PhysicsConfig": "ctrplan.shape.physics",
    "Loads": "ctrplan.shape.physics",
    "LearnedModel": "ctrplan.shape.learned",
    "load_model": "ctrplan.shape.models",
    "load_scene": "ctrplan.collision.scene",
    "Scene": "ctrplan.collision.scene",
    "scene_from_labels": "ctrplan.collision.labels",
    "LabelSceneConfig": "ctrplan.collision.labels",
    "CollisionWorld": "ctrplan.collision.world",
    "Planner": "ctrplan.planning.planner",
    "PlannerConfig": "ctrplan.planning.planner",
    "plan_to_target": "ctrplan.planning.plan",
    "PlanResult": "ctrplan.planning.result",
    "PlanStatus": "ctrplan.planning.result",
    "PlanConfig": "ctrplan.planning.planner",
    "TipGoal": "ctrplan.planning.tipgoal",
    "plan_trajectory": "ctrplan.planning.trajectory",
    "Trajectory": "ctrplan.planning.trajectory",
    "diagnose": "ctrplan.calibration.diagnose",
    "design": "ctrplan.design",
    "DesignConfig": "ctrplan.design",
    "DesignResult": "ctrplan.design",
}

__all__ = sorted(_EXPORTS) + ["__version__"]


def __getattr__(name: str) -> Any:
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'ctrplan' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return __all__
