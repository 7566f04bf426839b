"""Reachability maps against full plan attempts (issue 39, item 3; docs/validation.md).

For each shipped scene: a map (:func:`ctrplan.planning.reach.reach_map`) of ``--points`` surface
points sampled near the scene's named targets (``--near-targets``, radius 20 mm, standoff 2 mm,
a 10 s time cap per plan, seed 0), then a full plan attempt to every point, the ones the screen turned away
included, with another seed (1): the verdicts agree where the map says reachable and the plan
succeeds, or neither. What disagrees is counted by kind: ``screen_missed`` (the screen found no
pose, the plan reached the point), ``plan_varies`` (planned in the map, another seed decided
otherwise). ``tests/test_reach_statistical.py`` runs the same comparison on fewer points in CI.

    python benchmarks/bench_reach.py [--points 200] [--scenes airway,...] [--out benchmarks/results/reach.json]
    python benchmarks/bench_reach.py --approach normal --cone 45 --out benchmarks/results/reach_cone.json
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from tempfile import TemporaryDirectory

SCENES = ("airway", "bronchial_tree", "neuro", "skull_base")


def compare(scene_name: str, points: int, out: Path, seed: int = 0, check_seed: int = 1,
            time_limit: float = 10.0, approach: str = "", cone_deg: float | None = None) -> dict:
    """The map of ``points`` points near the targets and a full plan to each with
    ``check_seed``: counts, agreement and seconds."""
    import numpy as np

    from ctrplan.collision.scene import load_scene
    from ctrplan.collision.surface import sample_surface
    from ctrplan.planning.planner import PlannerConfig, Planners
    from ctrplan.planning.reach import ReachSettings, approach_directions, reach_map
    from ctrplan.planning.tipgoal import TipGoal

    t0 = time.perf_counter()
    scene = load_scene(scene_name)
    samples = sample_surface(scene, points, seed=seed, near=scene.target_positions(), radius_mm=20.0)
    settings = ReachSettings(scene=scene_name, time_limit=time_limit, seed=seed, approach=approach,
                             cone_deg=cone_deg)
    planners = Planners()
    summary = reach_map(settings, samples, out, planners=planners)
    t_map = time.perf_counter() - t0
    planner = planners.get(settings.robot, scene_name, settings.model, PlannerConfig())
    dirs = approach_directions(settings, samples.normals)
    agree = missed = varies = 0
    t1 = time.perf_counter()
    for k, row in enumerate(summary.rows):
        goal = TipGoal(position=samples.points[k], normal=samples.normals[k],
                       standoff_mm=settings.standoff_mm,
                       direction=None if dirs is None else dirs[k], cone_deg=cone_deg)
        ok = planner.plan(goal, seed=check_seed, time_limit=time_limit).status.value == "SUCCESS"
        if ok == bool(row["reachable"]):
            agree += 1
        elif not row["screen"]:
            missed += 1
        else:
            varies += 1
    n = len(summary.rows)
    return {"scene": scene_name, "points": n, "screen_passed": summary.planned,
            "reachable": summary.reachable, "agree": agree, "agreement": agree / n,
            "screen_missed": missed, "plan_varies": varies,
            "map_s": round(t_map, 1), "check_s": round(time.perf_counter() - t1, 1),
            "reachable_fraction": float(np.mean([bool(r["reachable"]) for r in summary.rows]))}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=200)
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--out", default="benchmarks/results/reach.json")
    ap.add_argument("--approach", default="", help="'normal' or X,Y,Z (default: any direction)")
    ap.add_argument("--cone", type=float, default=None, help="cone half-angle, deg")
    ap.add_argument("--time", type=float, default=10.0,
                    help="each plan's time cap, s (default 10: the search budget decides)")
    args = ap.parse_args()
    import subprocess

    rev = subprocess.run(["git", "rev-parse", "--short=10", "HEAD"], capture_output=True,
                         text=True).stdout.strip()
    rows = []
    with TemporaryDirectory() as tmp:
        for s in args.scenes.split(","):
            rows.append(compare(s, args.points, Path(tmp) / s, approach=args.approach,
                                cone_deg=args.cone, time_limit=args.time))
            print(json.dumps(rows[-1]), flush=True)
    total = sum(r["points"] for r in rows)
    result = {"what": "reach map verdict vs a full plan attempt with another seed, points sampled "
                      "near the named targets (radius 20 mm), standoff 2 mm, seed1 "
                      f"robot, physics model, time cap {args.time:g} s per plan, one core" + (
                          f", approach {args.approach} within {args.cone:g} deg" if args.approach else ""),
              "revision": rev, "date": time.strftime("%Y-%m-%d %H:%M"), "points_per_scene": args.points,
              "scenes": rows, "agreement_all": sum(r["agree"] for r in rows) / total,
              "agreement_min": min(r["agreement"] for r in rows)}
    Path(args.out).write_text(json.dumps(result, indent=2) + "\n")
    print(f"agreement: all {result['agreement_all']:.3f}, lowest scene {result['agreement_min']:.3f}")


if __name__ == "__main__":
    main()
