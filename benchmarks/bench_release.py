"""Release checks that are about time, not correctness (never asserted by tests):

- ``field_prep``: distance-field preparation of a CAD-style cylinder wall (radius 20 mm,
  height 400 mm, 64 sections, 256 long thin triangles), in a fresh process with an empty field
  cache: wall time and peak memory (target < 30 s and < 2 GB; the sample count that bounds
  it is asserted by tests/test_field_sampling.py).
- ``demo``: wall time of ``ctrplan demo`` in a fresh process (README: about 23 s cold).

    .venv/bin/python benchmarks/bench_release.py [--quick] [--out release.json]

``run(quick) -> dict`` like the other suites.
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time

FIELD_PREP = r"""
import json, resource, sys, time
import numpy as np, trimesh
from ctrplan.collision.field import FieldConfig, surface_samples
from ctrplan.collision.field_cache import field_for
cyl = trimesh.creation.cylinder(radius=20.0, height=400.0, sections=64)
t0 = time.perf_counter()
f = field_for(cyl, FieldConfig(), cache=sys.argv[1])
wall = time.perf_counter() - t0
sv, _ = surface_samples(np.asarray(cyl.vertices, float), np.asarray(cyl.faces), f.h / 2)
print(json.dumps({"faces": int(len(cyl.faces)), "wall_s": wall, "build_s": f.build_s,
                  "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
                  "samples": int(len(sv)), "grid": list(f.lb.shape), "h_mm": f.h}))
"""


def field_prep() -> dict:
    with tempfile.TemporaryDirectory() as cache:
        # compile the kernels once (numba's cache) so the timed run measures the work
        proc = subprocess.run([sys.executable, "-c", FIELD_PREP, cache + "/warm"],
                              capture_output=True, text=True, check=True)
        proc = subprocess.run([sys.executable, "-c", FIELD_PREP, cache + "/cold"],
                              capture_output=True, text=True, check=True)
    return json.loads(proc.stdout.strip().splitlines()[-1])


def demo() -> dict:
    with tempfile.TemporaryDirectory() as out:
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-m", "ctrplan.cli", "-q", "demo", "--out", out],
                       capture_output=True, text=True, check=True)
        return {"wall_s": time.perf_counter() - t0}


def run(quick: bool = False) -> dict:
    res = {"field_prep": field_prep()}
    if not quick:
        res["demo"] = demo()
    return res


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true")
    p.add_argument("--out")
    args = p.parse_args(argv)
    res = run(args.quick)
    text = json.dumps(res, indent=2)
    print(text)
    if args.out:
        with open(args.out, "w") as fh:
            fh.write(text + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
