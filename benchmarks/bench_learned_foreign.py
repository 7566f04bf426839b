"""The learned model vs physics on the independent (foreign) generator's shape data, 10 seeds.

Runs :func:`tests.test_learned_foreign.experiment` (the statistical test's experiment, see its
docstring: seed1, clearance + precurvature error + end-moment friction, 0.3 mm noise, 1,050
fine-tuning shapes from back-and-forth sweeps, 3 whole held-out sweeps of 150 rows) for every
Sim+Real variant (pure, direction-aware, residual over the Sim model, residual + direction) and
reports the mean max deviation along the shaft per seed and over seeds, next to physics and the
Sim-only model. Usage (from the repository root)::

    python benchmarks/bench_learned_foreign.py [--seeds 10] [--out benchmarks/results/learned_foreign.json]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
sys.path.insert(0, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))

import numpy as np  # noqa: E402
import torch  # noqa: E402

from ctrplan.shape import training as T  # noqa: E402


def run(seeds: int = 10, variants=T.VARIANTS) -> dict:
    from tests.test_learned_foreign import EFFECTS, NOISE_MM, experiment

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    runs = [experiment(s, variants=variants) for s in range(seeds)]
    phys = np.array([r["physics"] for r in runs])
    summary = {"physics": float(phys.mean()), "sim_only": float(np.mean([r["sim"] for r in runs]))}
    for v in variants:
        a = np.array([r["variants"][v] for r in runs])
        summary[v] = {"mean_mm": float(a.mean()), "gain_vs_physics": float(1 - a.mean() / phys.mean()),
                      "per_seed_gain": (1 - a / phys).round(3).tolist(),
                      "seconds_per_seed": float(np.mean([r["seconds"][v] for r in runs]))}
    return {"effects": EFFECTS, "noise_mm": NOISE_MM, "seeds": seeds, "runs": runs,
            "summary": summary, "seconds": time.perf_counter() - t0,
            "torch": torch.__version__}


def markdown(res: dict) -> str:
    s = res["summary"]
    lines = [f"Foreign generator, seed1, {res['seeds']} seeds: mean max deviation along the shaft "
             "on held-out whole sweeps (mm), mean over seeds", "",
             "| model | mean max deviation (mm) | vs physics | per-seed gains |", "|---|---|---|---|",
             f"| physics (compliant) | {s['physics']:.3f} | - | - |",
             f"| Sim-only (shipped seed1.pt) | {s['sim_only']:.3f} | {100 * (1 - s['sim_only'] / s['physics']):+.1f} % | - |"]
    for v in T.VARIANTS:
        if v in s:
            g = s[v]
            lines.append(f"| Sim+Real {v} | {g['mean_mm']:.3f} | {100 * g['gain_vs_physics']:.1f} % better | "
                         f"{min(g['per_seed_gain']):.2f} .. {max(g['per_seed_gain']):.2f} |")
    lines.append(f"\n{res['seconds']:.0f} s in all.")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=int, default=10)
    ap.add_argument("--out", default=None)
    args = ap.parse_args(argv)
    res = run(args.seeds)
    md = markdown(res)
    print(md)
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(res, fh, indent=1)
        with open(os.path.splitext(args.out)[0] + ".md", "w") as fh:
            fh.write(md + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
