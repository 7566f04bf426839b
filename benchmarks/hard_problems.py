"""The fixed hard planning benchmark: problems whose target the straight edge cannot reach.

    .venv/bin/python benchmarks/hard_problems.py [--scenes S ...] [--count 5]   # (re)build the set

A problem is a start configuration (the retracted one, rotated out of contact where needed), a
target (mm, scene frame) and a known collision-free solution. Found by search, per scene, with
the seed1 robot and the physics model: random configurations (fixed seed) that are collision-free
with capsules padded by the sagitta bound are taken as goals; a goal qualifies when the straight
edge from the start to it collides, ``plan_to_target`` on its tip does not take the direct edge
(none of the 4 nearest IK goals is straight-line reachable), and a plan is found; that plan's
waypoints are stored as the known solution, re-checked here independently (:func:`verify_path`:
the foreign generator's mechanics, exact FCL cylinders, 8x the edge resolution; no ctrplan code). Problems are stored in ``benchmarks/hard/<scene>.json``.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from dataclasses import dataclass
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

_ROOT = str(Path(__file__).resolve().parents[1])
if _ROOT not in sys.path:          # tests.foreign (the independent re-check) from a checkout
    sys.path.insert(0, _ROOT)

HERE = Path(__file__).resolve().parent / "hard"
ROBOT = "seed1"


@dataclass(frozen=True)
class Problem:
    """One hard problem. start, goal : (2n,) rad and mm; target : (3,) mm scene frame;
    solution : (K, 2n) collision-free waypoints from start to a configuration reaching target."""

    scene: str
    name: str
    start: np.ndarray
    goal: np.ndarray
    target: np.ndarray
    solution: np.ndarray


def load_problems(scene: str) -> list[Problem]:
    data = json.loads((HERE / f"{scene}.json").read_text(encoding="utf-8"))
    return [Problem(scene, p["name"], np.array(p["start"]), np.array(p["goal"]),
                    np.array(p["target"]), np.array(p["solution"])) for p in data["problems"]]


def scenes() -> list[str]:
    return sorted(p.stem for p in HERE.glob("*.json"))


def verify_path(robot, scene, path: np.ndarray, factor: int = 8, clearance: bool = True,
                effects: dict | None = None) -> tuple[bool, float]:
    """Independent re-check (:mod:`tests.foreign.recheck`, no ctrplan code): the path
    densified linearly (rotations as stored, unwrapped; at least 10 states per edge and
    ``factor`` x the planner's 2 mm edge resolution), the backbone from the foreign generator's
    own compliant mechanics (600+ points; ``effects``: a foreign truth robot), exact FCL
    cylinders of each tube's outer radius against the scene's meshes read from its files.
    Returns (collision-free, smallest FCL distance; NaN with ``clearance=False``, where only
    the verdict is wanted and the check stops at the first contact)."""
    from tests.foreign.recheck import recheck_path

    spec = robot.to_dict() if hasattr(robot, "to_dict") else robot
    where = getattr(scene, "path", scene)
    rep = recheck_path(spec, where, np.asarray(path, dtype=float), effects=effects,
                       step_mm=2.0 / factor, distances=clearance, depths=clearance,
                       stop_at_first=not clearance)
    return rep.free, (rep.min_clearance_mm if clearance and rep.free else
                      (float("nan") if not clearance else -1.0))


def search(scene_name: str, count: int = 5, samples: int = 60000, seed: int = 0,
           have: list[dict] | None = None) -> dict:
    from ctrplan.collision.scene import load_scene
    from ctrplan.collision.world import world_for
    from ctrplan.planning import Planner, PlannerConfig
    from ctrplan.planning.validator import BatchValidator
    from ctrplan.robot import load_robot
    from ctrplan.shape.models import load_model
    from ctrplan.shape.planning_model import planning_model

    robot = load_robot(ROBOT)
    scene = load_scene(scene_name)
    physics = load_model("physics", robot)
    learned = load_model("learned", robot)
    planner = Planner(robot, scene, physics, PlannerConfig(max_states=1_000_000))
    v = BatchValidator(robot, planner.model, planner.world)
    start, _ = planner.retracted_start()
    rng = np.random.default_rng([seed, 99])
    q = robot.sample(samples, seed=rng)
    free = q[v.states_valid(q)]
    tips = physics.shape(free, points=2).tip
    # deepest first (farthest tips from the base), so the set is not only trivial near-base goals
    order = np.argsort(-np.linalg.norm(tips, axis=1), kind="stable")
    lv = BatchValidator(robot, learned, world_for(scene, 0.0, planning_model(learned).curvature_bound))
    problems, tried = list(have or []), 0
    for i in order:
        if len(problems) >= count:
            break
        goal = free[i]
        if v.edge_valid(start, goal) or not lv.states_valid(start[None])[0]:
            continue
        target = scene.to_scene(tips[i][None])[0]
        if any(np.linalg.norm(target - np.array(p["target"])) < 10.0 for p in problems):
            continue
        tried += 1
        r = planner.plan(target, seed=seed, start=start, time_limit=20.0)
        if not r.success or r.counts.get("direct", 0):
            continue
        ok, clearance = verify_path(robot, scene, r.path)
        if not ok:
            continue
        name = f"{scene_name}_h{len(problems) + 1:02d}"
        problems.append({"name": name, "start": start.tolist(), "goal": goal.tolist(),
                         "target": target.tolist(), "solution": r.path.tolist(),
                         "solution_min_clearance_mm": clearance})
        print(f"{name}: target {np.round(target, 2).tolist()}, solution {len(r.path)} states, "
              f"clearance {clearance:.3f} mm", flush=True)
    return {
        "scene": scene_name, "robot": ROBOT,
        "units": "configurations: alpha rad, beta mm; target mm",
        "frame": "targets in the scene frame; configurations per DESIGN (alpha1..n, beta1..n)",
        "source": f"found by benchmarks/hard_problems.py search(samples={samples}, seeds "
                  f"0..{seed} until {count} problems): "
                  "the straight edge from the start collides and plan_to_target does not take it; "
                  "solution = a physics-model plan that passes the independent re-check "
                  "(tests/foreign/recheck.py)",
        "licence": "CC0",
        "candidates_tried": tried,
        "problems": problems,
    }


def main(argv: list[str] | None = None) -> int:
    import numba

    numba.set_num_threads(1)
    from ctrplan.collision.scene import list_scenes

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=None)
    ap.add_argument("--count", type=int, default=5)
    ap.add_argument("--samples", type=int, default=60000)
    ap.add_argument("--seeds", type=int, default=3, help="search seeds tried until --count problems")
    args = ap.parse_args(argv)
    HERE.mkdir(exist_ok=True)
    for s in args.scenes or list_scenes():
        data = None
        for seed in range(args.seeds):
            data = search(s, args.count, args.samples, seed, data["problems"] if data else None)
            if len(data["problems"]) >= args.count:
                break
        (HERE / f"{s}.json").write_text(json.dumps(data, indent=1) + "\n", encoding="utf-8")
        print(f"{s}: {len(data['problems'])} problems ({data['candidates_tried']} candidates)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
