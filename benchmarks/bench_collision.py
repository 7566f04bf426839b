"""Collision benchmark: configurations validated per second (shape + collision), per scene.

Batch of 10,000 configurations of the ``seed1`` robot, 21 backbone points (20 capsules), from
two distributions per scene: ``reach`` (uniform over the valid joint set restricted to tips
within the scene's reach: mostly colliding, what a sampling planner draws) and ``near_targets``
(the example targets' configurations perturbed by up to 0.3 rad and 5 mm: mostly free and close
to the walls, what an edge near a solution looks like). In the same run, per scene, distribution
and shape model:

- ``fcl``: every configuration checked by exact FCL alone
  (``CollisionWorld(scene, prefilter=False).collides``);
- ``prefilter``: the distance-field prefilter, the exact second stage for the capsule-mesh
  pairs its bounds cannot decide, and FCL for that stage's ties (``CollisionWorld.collides``),
  whose verdicts must equal FCL alone's (``verdicts_equal``, on the FCL subset).

Shape time is included in both. One core: numba and torch are limited to one thread.
Run: ``python benchmarks/bench_collision.py [--quick]`` or ``ctrplan bench collision``.
"""

from __future__ import annotations

import itertools
import json
import os
import sys
import time

for _v in ("OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_v, "1")

import numba  # noqa: E402
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


def near_targets(robot, scene, n: int, seed: int) -> np.ndarray:
    """n valid configurations near the scene's target configurations (mostly free)."""
    rng = np.random.default_rng(seed)
    base = np.array([t.config for t in scene.targets])
    out, have = [], 0
    k = robot.n
    while have < n:
        q = base[rng.integers(len(base), size=2 * n)].copy()
        q[:, :k] += rng.uniform(-0.3, 0.3, size=(len(q), k))
        q[:, k:] += rng.uniform(-5.0, 5.0, size=(len(q), k))
        q = q[robot.is_valid(q)]
        out.append(q)
        have += len(q)
    return np.concatenate(out)[:n]


def run(quick: bool = False) -> dict:
    """Measure; returns {'table': [...rows], 'notes': ...}."""
    # numba's pool through its API: NUMBA_NUM_THREADS set after numba is imported (as under
    # `ctrplan bench`) makes numba refuse every later compile in the process
    numba.set_num_threads(1)
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
        _ = world.geometry.second_stage  # and the second stage's triangle lists (~30 ms)
        from ctrplan.collision.scene import load_scene

        dists = {"reach": sample_reach(robot, batch, reach, seed=7),
                 "near_targets": near_targets(robot, load_scene(scene), batch, seed=8)}
        for (dist, q), (mname, model) in itertools.product(dists.items(), models.items()):
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
            fcl_calls, stage_calls = world.last_fcl_calls, world.last_stage_calls
            sub = slice(0, fcl_batch)
            sub_shape = shape[sub]  # the pad too: the same capsules as in the full batch
            t0 = time.perf_counter()
            exact = fcl_world.collides(sub_shape)
            t_fcl = (time.perf_counter() - t0) * batch / fcl_batch
            rate_pre = batch / (t_shape + t_pre)
            rate_fcl = batch / (t_shape + t_fcl)
            t0 = time.perf_counter()
            fcl_world.collides(sub_shape)
            t_fcl_only = (time.perf_counter() - t0) / fcl_batch
            rows.append({
                "scene": scene, "configs": dist, "model": mname, "batch": batch,
                "free_fraction": float(1 - verdict.mean()),
                "to_stage_fraction": stage_calls / batch,
                "to_fcl_fraction": fcl_calls / batch,
                "shape_us": 1e6 * t_shape / batch,
                "fcl_alone_per_s": rate_fcl,
                "prefilter_fcl_per_s": rate_pre,
                "speedup": rate_pre / rate_fcl,
                "collision_us_fcl": 1e6 * t_fcl_only,
                "collision_us_prefilter": 1e6 * t_pre / batch,
                "collision_speedup": t_fcl_only * batch / t_pre,
                "verdicts_equal": bool(np.array_equal(verdict[sub], exact)),
            })
    notes = {k: v for k, v in models.items() if isinstance(v, str)}
    return {"table": rows, "notes": notes}


if __name__ == "__main__":
    res = run(quick="--quick" in sys.argv)
    print(json.dumps(res, indent=1))
