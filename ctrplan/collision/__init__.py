"""Collision checking: backbone -> capsules; CollisionWorld over anatomy meshes (FCL); a
conservative distance-field prefilter in front of exact FCL; the anatomy scenes."""

from ctrplan.collision.scene import Scene, SceneMesh, Target, load_scene

__all__ = ["Scene", "SceneMesh", "Target", "load_scene", "CollisionWorld", "CollisionReport"]


def __getattr__(name: str):
    if name in ("CollisionWorld", "CollisionReport"):
        from ctrplan.collision import world

        return getattr(world, name)
    raise AttributeError(name)
