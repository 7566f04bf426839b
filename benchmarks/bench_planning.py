"""Planning benchmark: a Planner per scene and model plans to every example target of every shipped scene.

    .venv/bin/python benchmarks/bench_planning.py [--quick] [--out planning.json]

Full run: all example targets of every shipped scene, 5 seeds each, with the learned model
and with the physics model (RRTConnect, 5 s limit, tolerance 1 mm, seed1). Quick run: two
targets per scene, one seed. Reports per scene and model the success rate (every example target
is reachable: it is the tip of a collision-free configuration) and the median / 90th percentile
planning time per plan: wall time (what a user waits) and the calling thread's CPU time (its
cost on one core, steadier on a shared machine; OMPL, the models and FCL all run in that
thread), plus the median time of each stage. One warm-up plan per scene and model (preparing the
Planner: model, scene, collision world, workspace table, retracted start; and JIT caches) is
timed separately and not counted.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

# one thread for anything that might use a pool (torch intra-op, BLAS, numba); before imports
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import numba  # noqa: E402
import numpy as np  # noqa: E402

from ctrplan.collision.scene import list_scenes, load_scene  # noqa: E402
from ctrplan.planning.planner import Planner  # noqa: E402

ROBOT = "seed1"
MODELS = ("learned", "physics")
PLANNER = "rrtconnect"
TIME_LIMIT = 5.0
STAGES = ("checks", "ik", "planning", "simplification", "optimization", "verification")


def _robot():
    from ctrplan.robot import load_robot

    return load_robot(ROBOT)


def _pct(x: list[float], q: float) -> float:
    return float(np.percentile(x, q)) if x else float("nan")


def run(quick: bool = False, recheck: bool = False, models: tuple[str, ...] = MODELS) -> dict:
    # numba's pool through its API: NUMBA_NUM_THREADS set after numba is imported (as under
    # `ctrplan bench`) makes numba refuse every later compile in the process
    numba.set_num_threads(1)
    seeds = [0] if quick else [0, 1, 2, 3, 4]
    scenes = list_scenes()
    plans: list[dict] = []
    warmup: dict[str, float] = {}
    for scene_name in scenes:
        scene = load_scene(scene_name)
        targets = scene.targets[:2] if quick else scene.targets
        for model in models:
            t0 = time.perf_counter()
            planner = Planner(ROBOT, scene, model)
            planner.plan(targets[0].position, seed=99, planner=PLANNER, time_limit=TIME_LIMIT)
            warmup[f"{scene_name}/{model}"] = time.perf_counter() - t0
            for t in targets:
                for seed in seeds:
                    c0 = time.thread_time()
                    r = planner.plan(t.position, seed=seed, planner=PLANNER, time_limit=TIME_LIMIT)
                    cpu = time.thread_time() - c0
                    free = None
                    if recheck and r.success:
                        from hard_problems import verify_path

                        free = verify_path(_robot(), scene, r.path)[0]
                    plans.append({
                        "scene": scene_name, "target": t.name, "seed": seed, "model": model,
                        "status": r.status.value, "success": r.success,
                        "wall_s": r.planning_time_s, "cpu_s": cpu,
                        "tip_error_mm": r.tip_error_mm if r.success else None,
                        "tip_error_physics_mm": r.tip_error_physics_mm if r.success else None,
                        "direct": r.counts.get("direct", 0),
                        "recheck_free": free,
                        "min_clearance_reference_mm": r.min_clearance_reference_mm if r.success else None,
                        **{f"{s}_s": r.timings.get(s, 0.0) for s in STAGES},
                    })
    table = []
    groups = [(s, m) for m in models for s in scenes] + [("all", m) for m in models]
    for scene_name, model in groups:
        rs = [p for p in plans if p["model"] == model and scene_name in ("all", p["scene"])]
        if not rs:
            continue
        wall = [p["wall_s"] for p in rs]
        cpu = [p["cpu_s"] for p in rs]
        ok = [p for p in rs if p["success"]]
        row = {
            "scene": scene_name, "model": model, "plans": len(rs),
            "success_rate": len(ok) / len(rs),
            "median_s": statistics.median(wall), "p90_s": _pct(wall, 90),
            "median_cpu_s": statistics.median(cpu), "p90_cpu_s": _pct(cpu, 90),
        }
        for s in STAGES:
            row[f"{s}_median_s"] = statistics.median(p[f"{s}_s"] for p in rs)
        row["tip_error_physics_median_mm"] = (
            statistics.median(p["tip_error_physics_mm"] for p in ok) if ok else float("nan"))
        row["direct_fraction"] = sum(p["direct"] for p in rs) / len(rs)
        row["recheck_failures"] = sum(1 for p in ok if p["recheck_free"] is False)
        row["rechecked"] = sum(1 for p in ok if p["recheck_free"] is not None)
        statuses: dict[str, int] = {}
        for p in rs:
            statuses[p["status"]] = statuses.get(p["status"], 0) + 1
        row["statuses"] = ";".join(f"{k}:{v}" for k, v in sorted(statuses.items()))
        table.append(row)
    by = {(r["scene"], r["model"]): r for r in table}
    ratio = {}
    if ("all", "learned") in by and ("all", "physics") in by:
        ratio = {
            "physics_over_learned_median_wall": by[("all", "physics")]["median_s"] / by[("all", "learned")]["median_s"],
            "physics_over_learned_median_cpu": by[("all", "physics")]["median_cpu_s"] / by[("all", "learned")]["median_cpu_s"],
        }
    return {"robot": ROBOT, "planner": PLANNER, "time_limit_s": TIME_LIMIT, "seeds": seeds,
            "models": list(models), "recheck": bool(recheck),
            "scenes": scenes, "table": table, "ratios": ratio, "warmup_s": warmup, "plans": plans}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="two targets per scene, one seed")
    ap.add_argument("--out", default=None, help="write the results as JSON here")
    ap.add_argument("--recheck", action="store_true",
                    help="re-check every successful path independently (8x densified, physics, FCL)")
    ap.add_argument("--models", default=",".join(MODELS),
                    help=f"comma-separated planning models (default: {','.join(MODELS)})")
    args = ap.parse_args(argv)
    models = tuple(m.strip() for m in args.models.split(",") if m.strip())
    bad = [m for m in models if m not in MODELS]
    if bad or not models:
        ap.error(f"--models: expected some of {', '.join(MODELS)}, got {args.models!r}")
    res = run(quick=args.quick, recheck=args.recheck, models=models)
    for r in res["table"]:
        print(f"{r['scene']:>15} {r['model']:>8}: {r['plans']:4d} plans, success "
              f"{100 * r['success_rate']:5.1f}%, wall median {r['median_s']:.2f} s p90 {r['p90_s']:.2f} s, "
              f"cpu median {r['median_cpu_s']:.2f} s p90 {r['p90_cpu_s']:.2f} s  [{r['statuses']}]")
    print(json.dumps(res["ratios"]))
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(res, fh, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
