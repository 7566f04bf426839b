"""Speed of ``ctrplan design`` on the ``design_bend`` scene.

Reports designs evaluated per second, the share of time in each stage (pre-screen: entry,
sampled workspace, IK; plans; stability; the final plans of the chosen design) and the scaling
from 1 to 2 workers: the same search (same seed, same budget, so the same evaluations and the
same design) run with ``workers=1`` and ``workers=2`` in this process, one after the other; the
ratio is the number to read (these machines are shared and noisy). The 2-worker run includes
starting the spawned workers (each imports ctrplan and loads the scene). Usage::

    python benchmarks/bench_design.py [--budget N] [--out benchmarks/results/design.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from ctrplan.design import Bounds, DesignConfig, design  # noqa: E402

TARGETS = "t01,t02,t03,t04,t05,t06"


def run(budget: int = 96) -> dict:
    cfg = DesignConfig(tubes=1, budget=budget, generation=8,
                       bounds=Bounds(curvature=(0.0, 0.06), curved_length=(10.0, 100.0),
                                     straight_length=(20.0, 120.0)))
    design("design_bend", "t01", DesignConfig(tubes=1, budget=1, generation=1), progress=False)  # warm-up
    out: dict = {"scene": "design_bend", "budget": budget, "runs": {}}
    robots = {}
    for workers in (1, 2):
        t0 = time.perf_counter()
        r = design("design_bend", TARGETS, DesignConfig(**{**cfg.__dict__, "workers": workers}), progress=False)
        wall = time.perf_counter() - t0
        stages = {k: v for k, v in r.timings.items() if k != "total"}
        total_stage = sum(stages.values())
        out["runs"][str(workers)] = {
            "wall_s": wall, "load_average_1min_after": os.getloadavg()[0], "evaluations": r.counts["evaluations"], "planned": r.counts["planned"],
            "evaluations_per_s": r.counts["evaluations"] / wall, "reached": r.reached,
            "stage_s": stages, "stage_share": {k: v / total_stage for k, v in stages.items()},
        }
        robots[workers] = r.robot.to_dict() if r.robot is not None else None
    out["speedup_2_over_1"] = out["runs"]["1"]["wall_s"] / out["runs"]["2"]["wall_s"]
    out["same_design_1_and_2_workers"] = robots[1] == robots[2]
    out["cpu_count"] = os.cpu_count()
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--budget", type=int, default=96)
    ap.add_argument("--out", default=str(Path(__file__).resolve().parent / "results" / "design.json"))
    args = ap.parse_args(argv)
    res = run(args.budget)
    Path(args.out).write_text(json.dumps(res, indent=1) + "\n", encoding="utf-8")
    for w, r in res["runs"].items():
        share = ", ".join(f"{k} {100 * v:.0f}%" for k, v in r["stage_share"].items())
        print(f"workers {w}: {r['evaluations']} designs in {r['wall_s']:.1f} s "
              f"({r['evaluations_per_s']:.2f}/s), {r['reached']} targets reached; {share}")
    print(f"2 workers / 1 worker speed-up: {res['speedup_2_over_1']:.2f}x; "
          f"same design: {res['same_design_1_and_2_workers']}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
