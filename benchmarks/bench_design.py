"""Speed of ``ctrplan design`` on the ``design_bend`` scene.

Reports designs evaluated per second, the share of time in each stage (pre-screen: entry,
sampled workspace, IK; plans; stability; the final plans of the chosen design; ``driver``: the
rest of the in-process run's wall time -- decoding, ranking, bookkeeping) and the scaling from 1
to 2 workers: the same search (same seed, same budget, so the same evaluations and the same
design) run with ``workers=1``, ``workers=2`` and, when ray is installed, ``ray_address="local"``
(a local Ray instance with every core: the plan-batch Ray path) in this process, one after the
other; the ratios are the numbers to read. The 2-worker and Ray runs include starting their
workers (each imports ctrplan and loads the scene; Ray also starts its own services).
Stage seconds are summed over the processes that ran them (CPU-side time per stage), so with
2 workers they can add up to more than the wall time. These machines are shared: the load
average before and after each run is recorded, and ratios measured under load are noisy.
Usage::

    python benchmarks/bench_design.py [--budget N] [--no-ray] [--out benchmarks/results/design.json]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import os
import sys
import time
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from ctrplan.design import Bounds, DesignConfig, design  # noqa: E402

TARGETS = "t01,t02,t03,t04,t05,t06"


def _one(cfg: DesignConfig, label: str) -> tuple[dict, dict | None]:
    load_before = os.getloadavg()[0]
    t0 = time.perf_counter()
    r = design("design_bend", TARGETS, cfg, progress=False)
    wall = time.perf_counter() - t0
    stages = {k: v for k, v in r.timings.items() if k != "total"}
    total_stage = sum(stages.values())
    row = {
        "label": label, "wall_s": wall, "evaluations": r.counts["evaluations"],
        "planned": r.counts["planned"], "evaluations_per_s": r.counts["evaluations"] / wall,
        "reached": r.reached, "stage_s": stages,
        "stage_share": {k: v / total_stage for k, v in stages.items()},
        "load_average_1min_before": load_before, "load_average_1min_after": os.getloadavg()[0],
    }
    if cfg.workers == 1 and cfg.ray_address is None:
        # in-process: the stages and the driver's own work add up to the wall time
        row["wall_share"] = {**{k: v / wall for k, v in stages.items()},
                             "driver": max(0.0, wall - total_stage) / wall}
    return row, (r.robot.to_dict() if r.robot is not None else None)


def run(budget: int = 96, use_ray: bool = True) -> dict:
    cfg = DesignConfig(tubes=1, budget=budget, generation=8,
                       bounds=Bounds(curvature=(0.0, 0.06), curved_length=(10.0, 100.0),
                                     straight_length=(20.0, 120.0)))
    design("design_bend", "t01", DesignConfig(tubes=1, budget=1, generation=1), progress=False)  # warm-up
    out: dict = {"scene": "design_bend", "targets": TARGETS, "budget": budget, "runs": {},
                 "cpu_count": os.cpu_count()}
    robots = {}
    variants = [("1", {"workers": 1}), ("2", {"workers": 2})]
    if use_ray and importlib.util.find_spec("ray") is not None:
        variants.append(("ray_local", {"ray_address": "local"}))
    for label, extra in variants:
        row, robots[label] = _one(DesignConfig(**{**cfg.__dict__, **extra}), label)
        out["runs"][label] = row
    wall1 = out["runs"]["1"]["wall_s"]
    out["speedup_2_over_1"] = wall1 / out["runs"]["2"]["wall_s"]
    if "ray_local" in out["runs"]:
        out["speedup_ray_local_over_1"] = wall1 / out["runs"]["ray_local"]["wall_s"]
    out["same_design_all_runs"] = all(r == robots["1"] for r in robots.values())
    out["notes"] = (
        "Measured on a shared machine (cpu_count cores, other jobs running: see the load "
        "averages); wall-time ratios between runs are noisy and say little beyond their sign at "
        "this budget. Parallel runs include starting their workers (spawned processes / a local "
        "Ray instance), which this small search does not amortise: each generation plans at most "
        "two designs, so the parallel share of the work is small. stage_s is summed over the "
        "processes that ran each stage. Budgets are counts, so every run evaluates the same "
        "designs and returns the same design (same_design_all_runs).")
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budget", type=int, default=96)
    ap.add_argument("--no-ray", action="store_true", help="skip the local Ray run")
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "design.json"))
    args = ap.parse_args(argv)
    res = run(args.budget, use_ray=not args.no_ray)
    Path(args.out).write_text(json.dumps(res, indent=1) + "\n", encoding="utf-8")
    for w, r in res["runs"].items():
        share = ", ".join(f"{k} {100 * v:.0f}%" for k, v in r["stage_share"].items())
        print(f"workers {w}: {r['evaluations']} designs in {r['wall_s']:.1f} s "
              f"({r['evaluations_per_s']:.2f}/s), {r['reached']} targets reached; {share}")
    ray = (f", Ray local / 1 worker: {res['speedup_ray_local_over_1']:.2f}x"
           if "speedup_ray_local_over_1" in res else "")
    print(f"2 workers / 1 worker speed-up: {res['speedup_2_over_1']:.2f}x{ray}; "
          f"same design in every run: {res['same_design_all_runs']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
