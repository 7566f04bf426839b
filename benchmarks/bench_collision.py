"""Collision benchmark: configurations validated per second (shape + collision), per scene.

Batch of 10,000 configurations of the ``seed1`` robot, 21 backbone points (20 capsules),
uniform over the valid joint set restricted to tips within the scene's reach (the range a
planner explores there). In the same run, per scene and shape model:

- ``fcl``: every configuration checked by exact FCL alone
  (``CollisionWorld(scene, prefilter=False).collides``);
- ``prefilter``: the distance-field prefilter with FCL for what it cannot decide
  (``CollisionWorld.collides``), whose verdicts must equal FCL's.

Shape time is included in both. One core: numba and torch are limited to one thread.
Run: ``python benchmarks/bench_collision.py [--quick]`` or ``ctrplan bench collision``.
"""

from __future__ import annotations

import json
import os
import sys
import time

for _v in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numpy as np  # noqa: E402

#: tip reach (mm) sampled per scene: about the depth of each scene's lumen from the base
REACH_MM = {"airway": 160.0, "neuro": 130.0, "skull_base": 140.0, "bronchial_tree": 260.0}


def _models(robot):
    from ctrplan.shape.physics import PhysicsModel

    models = {"physics": PhysicsModel(robot)}
    try:
        from ctrplan.shape.learned import default_model_for

        models["learned"] = default_model_for(robot)
    except Exception as exc:  # noqa: BLE001 - the learned model is optional here
        models["learned_unavailable"] = repr(exc)
    return models


def run(quick: bool = False) -> dict:
    """Measure; returns {'table': [...rows], 'notes': ...}."""
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover
        pass
    from ctrplan.collision.build_scenes import sample_reach
    from ctrplan.collision.world import CollisionWorld
    from ctrplan.robot import load_robot

    robot = load_robot("seed1")
    models = _models(robot)
    batch = 1000 if quick else 10_000
    fcl_batch = 200 if quick else 1000  # FCL alone is slow: timed on a subset, rate extrapolated
    rows = []
    for scene, reach in REACH_MM.items():
        world = CollisionWorld(scene)
        fcl_world = CollisionWorld(scene, prefilter=False)
        _ = world.fields  # build or load the distance fields outside the timing
        q = sample_reach(robot, batch, reach, seed=7)
        for mname, model in models.items():
            if isinstance(model, str):
                continue
            model.shape(q[:10], points=21)  # warm-up (compilation)
            world.collides(model.shape(q[:10], points=21))
            t0 = time.perf_counter()
            shape = model.shape(q, points=21)
            t_shape = time.perf_counter() - t0
            t0 = time.perf_counter()
            verdict = world.collides(shape)
            t_pre = time.perf_counter() - t0
            sub = slice(0, fcl_batch)
            sub_shape = type(shape)(points=shape.points[sub], s=shape.s[sub],
                                    radius=shape.radius[sub], ok=shape.ok[sub])
            t0 = time.perf_counter()
            exact = fcl_world.collides(sub_shape)
            t_fcl = (time.perf_counter() - t0) * batch / fcl_batch
            fcl_calls = world.check(shape).fcl_calls
            rate_pre = batch / (t_shape + t_pre)
            rate_fcl = batch / (t_shape + t_fcl)
            rows.append({
                "scene": scene, "model": mname, "batch": batch,
                "free_fraction": float(1 - verdict.mean()),
                "to_fcl_fraction": fcl_calls / batch,
                "shape_us": 1e6 * t_shape / batch,
                "fcl_alone_per_s": rate_fcl,
                "prefilter_fcl_per_s": rate_pre,
                "speedup": rate_pre / rate_fcl,
                "verdicts_equal": bool(np.array_equal(verdict[sub], exact)),
            })
    notes = {k: v for k, v in models.items() if isinstance(v, str)}
    return {"table": rows, "notes": notes}


if __name__ == "__main__":
    res = run(quick="--quick" in sys.argv)
    print(json.dumps(res, indent=1))
