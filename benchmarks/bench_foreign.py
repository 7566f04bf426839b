"""Speed of the foreign measurement generator (tests/foreign): 1,000 configurations per call.

Noise-free truth (``tests.foreign.core.truth``) for the rows of one ``generate(robot, "sweeps",
n=1000)`` design on ``seed1`` and ``two_tube_nylon``: the rigid closed form (the baseline, same
process), the torsionally compliant Cosserat shooting, and compliant + loads (gravity and a tip
force). One thread; medians of the calling thread's CPU time over repeats (wall time beside it;
the machines are shared and noisy). Usage::

    python benchmarks/bench_foreign.py [--quick] [--out results.json]

``run(quick) -> dict``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from tests.foreign import generate, load_spec  # noqa: E402
from tests.foreign.core import truth  # noqa: E402

CASES = (("rigid", {}), ("compliant", {"torsion": {}}),
         ("compliant+loads", {"torsion": {}, "load": {}}))


def run(quick: bool = False) -> dict:
    reps = 1 if quick else 3
    rows = []
    for robot in ("seed1", "two_tube_nylon"):
        spec = load_spec(robot)
        d = generate(robot, "sweeps", n=1000, effects={}, seed=0)
        base = None
        for name, eff in CASES:
            cpu, wall = [], []
            for _ in range(reps):
                t0, w0 = time.thread_time(), time.perf_counter()
                truth(spec, d.q, eff, direction=d.direction)
                cpu.append(time.thread_time() - t0)
                wall.append(time.perf_counter() - w0)
            c = statistics.median(cpu)
            base = c if name == "rigid" else base
            rows.append({"robot": robot, "model": name, "rows": 1000, "cpu_s": c,
                         "wall_s": statistics.median(wall), "ratio_to_rigid": c / base})
    table = ["| robot | model | CPU s / 1,000 rows | wall s | x rigid |", "|---|---|---:|---:|---:|"]
    table += [f"| {r['robot']} | {r['model']} | {r['cpu_s']:.3f} | {r['wall_s']:.3f} | "
              f"{r['ratio_to_rigid']:.0f} |" for r in rows]
    return {"suite": "foreign", "results": rows, "table": table}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out")
    a = ap.parse_args()
    res = run(a.quick)
    print("\n".join(res["table"]))
    if a.out:
        Path(a.out).write_text(json.dumps(res, indent=2))


if __name__ == "__main__":
    main()
