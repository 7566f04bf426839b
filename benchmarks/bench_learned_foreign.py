"""The learned model vs physics on the independent (foreign) generator's shape data, 10 seeds.

Runs :func:`tests.test_learned_foreign.experiment` (the statistical test's experiment, see its
docstring: seed1, clearance + precurvature error + end-moment friction, 0.3 mm noise, 1,050
fine-tuning shapes from back-and-forth sweeps, 3 whole held-out sweeps of 150 rows) for every
Sim+Real variant (pure, direction-aware, residual over the Sim model, residual + direction) and
reports the mean max deviation along the shaft per seed and over seeds, next to physics and the
Sim-only model. ``--auto`` runs :func:`tests.test_learned_foreign.auto_experiment` instead: what
``ctrplan train`` does without variant flags (the variant chosen on the validation sweep) next to
each variant given explicitly, on the same held-out test sweep. Usage (from the repository root)::

    python benchmarks/bench_learned_foreign.py [--seeds 10] [--auto] [--out benchmarks/results/learned_foreign.json]
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


def run_auto(seeds: int = 5) -> dict:
    """The automatic variant choice vs each explicit variant, per seed and in the mean."""
    from tests.test_learned_foreign import auto_experiment

    torch.set_num_threads(1)
    t0 = time.perf_counter()
    runs = [auto_experiment(s) for s in range(seeds)]
    auto = np.array([r["auto"] for r in runs])
    per = {v: float(np.mean([r["variants"][v] for r in runs])) for v in T.VARIANTS}
    best = min(per, key=per.get)
    return {"seeds": seeds, "runs": runs, "physics": float(np.mean([r["physics"] for r in runs])),
            "auto": float(auto.mean()), "variants": per, "best_variant": best,
            "auto_over_best": float(auto.mean() / per[best]), "seconds": time.perf_counter() - t0}


def markdown_auto(res: dict) -> str:
    lines = [f"Foreign generator, seed1, {res['seeds']} seeds: `train` without variant flags vs each "
             "variant given explicitly, mean max deviation on the held-out test sweep (mm)", "",
             "| model | mean (mm) |", "|---|---|", f"| physics | {res['physics']:.3f} |",
             f"| automatic choice (chose {', '.join(r['chosen'] for r in res['runs'])}) | {res['auto']:.3f} |"]
    lines += [f"| {v} | {m:.3f} |" for v, m in res["variants"].items()]
    lines.append(f"\nautomatic / best ({res['best_variant']}): {res['auto_over_best']:.3f}; "
                 f"{res['seconds']:.0f} s in all.")
    return "\n".join(lines)


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
    ap.add_argument("--auto", action="store_true", help="the automatic variant choice vs each variant")
    args = ap.parse_args(argv)
    if args.auto:
        res = run_auto(args.seeds)
        md = markdown_auto(res)
    else:
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
