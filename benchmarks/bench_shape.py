"""Time per shape of the mechanics models (rigid, torsionally compliant) on ``seed1``.

Batch sizes 1, 100 and 10,000, 20 points per backbone, one thread (the numba kernel is
serial), medians over repeats of ``PhysicsModel.shape`` (the public call, Python overhead
included). Baselines run in the same process, because these machines are shared and noisy:
the rigid model, and the tight scipy reference solver (:mod:`ctrplan.shape.reference`) one
configuration at a time on a few configurations, which also gives the accuracy of the default
step. Loads: the compliant and rigid models under gravity across the insertion axis
(``Loads(gravity=(0, -9.81, 0))``, nitinol density) at batch 10,000, timed interleaved with the
unloaded models in the same run (the ratio is the number to read). Usage::

    python benchmarks/bench_shape.py [--quick] [--out results.json]

``run(quick) -> dict`` is what ``ctrplan bench`` calls; ``table`` holds the markdown rows.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

# one thread for anything that might use a pool (numpy BLAS); set before numpy is imported
for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numba  # noqa: E402
import numpy as np  # noqa: E402

from ctrplan.robot import load_robot  # noqa: E402
from ctrplan.shape.physics import Loads, PhysicsConfig, PhysicsModel  # noqa: E402
from ctrplan.shape.reference import reference_shape  # noqa: E402

ROBOT = "seed1"
POINTS = 20
SEED = 1
#: A published time for the torsionally compliant model, one configuration at a time (the
#: foundation issue's anchor); measured elsewhere, so only indicative.
PUBLISHED_ANCHOR_S = 1.73e-3


def _median_time(fn, repeats: int) -> tuple[float, float]:
    """Median (thread CPU time, wall time) of ``fn()`` over ``repeats`` runs.

    The kernel is single-threaded, so the calling thread's CPU time is its cost on one core;
    unlike wall time it does not count the time the OS gives the core to other processes on
    a shared machine. Both are reported."""
    cpu: list[float] = []
    wall: list[float] = []
    for _ in range(repeats):
        c0 = time.thread_time()
        t0 = time.perf_counter()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.thread_time() - c0)
    return statistics.median(cpu), statistics.median(wall)


def run(quick: bool = False) -> dict:
    # numba's pool through its API: NUMBA_NUM_THREADS set after numba is imported (as under
    # `ctrplan bench`) makes numba refuse every later compile in the process
    numba.set_num_threads(1)
    robot = load_robot(ROBOT)
    batches = (1, 100, 10_000)
    repeats = {1: 50 if quick else 500, 100: 10 if quick else 50, 10_000: 2 if quick else 7}
    q_all = robot.sample(10_000, seed=SEED)
    models = {"rigid": PhysicsModel(robot, torsion=False), "compliant": PhysicsModel(robot, torsion=True)}
    for m in models.values():                     # compile (or load the numba cache) first
        m.shape(q_all[:2], POINTS)

    per_shape: dict[str, dict[int, float]] = {name: {} for name in models}
    per_shape_wall: dict[str, dict[int, float]] = {name: {} for name in models}
    for B in batches:
        q = q_all[:B]
        # interleave the models so that machine noise hits both alike
        for name, m in models.items():
            cpu, wall = _median_time(lambda m=m, q=q: m.shape(q, POINTS), repeats[B])
            per_shape[name][B] = cpu / B
            per_shape_wall[name][B] = wall / B

    # loads: loaded vs unloaded at batch 10,000, interleaved in this run
    gravity = Loads(gravity=(0.0, -9.80665, 0.0))
    loaded_models = {"rigid_loaded": PhysicsModel(robot, torsion=False, loads=gravity),
                     "compliant_loaded": PhysicsModel(robot, torsion=True, loads=gravity)}
    for m in loaded_models.values():
        m.shape(q_all[:2], POINTS)
    pair = {"rigid": [], "rigid_loaded": [], "compliant": [], "compliant_loaded": []}
    for _ in range(1 if quick else 3):
        for name in pair:
            m = loaded_models.get(name) or models[name]
            pair[name].append(_median_time(lambda m=m: m.shape(q_all, POINTS), 1)[0] / len(q_all))
    lp = {k: statistics.median(v) for k, v in pair.items()}
    lshape = loaded_models["compliant_loaded"].shape(q_all, POINTS)
    linfo = loaded_models["compliant_loaded"].last_info
    sag = np.linalg.norm(lshape.tip - models["compliant"].shape(q_all, POINTS).tip, axis=1)
    loads_res = {
        "loads": "gravity (0, -9.80665, 0) m/s^2, nitinol 6450 kg/m^3", "batch": len(q_all),
        "us_per_shape": {k: v * 1e6 for k, v in lp.items()},
        "compliant_loaded_over_compliant": lp["compliant_loaded"] / lp["compliant"],
        "rigid_loaded_over_rigid": lp["rigid_loaded"] / lp["rigid"],
        "newton_iterations_mean": float(linfo.iterations.mean()),
        "newton_iterations_max": int(linfo.iterations.max()),
        "converged_fraction": float(lshape.ok.mean()),
        "tip_sag_mm_median": float(np.median(sag)), "tip_sag_mm_max": float(sag.max()),
    }

    # elastic stability check (det of the shooting Jacobian, search for a stable root where it
    # is <= 0) vs the unchecked solve, interleaved in this run; seed1 (never unstable) and
    # two_tube_nylon (physical GJ: ~12 % of uniform configurations hit an unstable root)
    stab_res = {}
    for rname in (ROBOT, "two_tube_nylon"):
        rb = load_robot(rname)
        qs = rb.sample(2_000 if quick else 10_000, seed=SEED)
        sm = {"checked": PhysicsModel(rb, torsion=True),
              "unchecked": PhysicsModel(rb, torsion=True, config=PhysicsConfig(stability=False))}
        for m in sm.values():
            m.shape(qs[:2], POINTS)
        tv = {k: [] for k in sm}
        for _ in range(1 if quick else 3):
            for k, m in sm.items():
                tv[k].append(_median_time(lambda m=m, qs=qs: m.shape(qs, POINTS), 1)[0] / len(qs))
        sm["checked"].shape(qs, POINTS)
        br = sm["checked"].last_info.branch
        med = {k: statistics.median(v) for k, v in tv.items()}
        stab_res[rname] = {"batch": len(qs), "us_per_shape": {k: v * 1e6 for k, v in med.items()},
                           "checked_over_unchecked": med["checked"] / med["unchecked"],
                           "unstable_rejected_fraction": float((br != 0).mean()),
                           "bistable_fraction": float((br == 2).mean())}

    comp = models["compliant"]
    shape = comp.shape(q_all, POINTS)
    info = comp.last_info
    iterations = {"mean": float(info.iterations.mean()), "max": int(info.iterations.max()),
                  "converged_fraction": float(shape.ok.mean())}

    # baseline + accuracy: the scipy reference, one configuration at a time
    n_ref = 2 if quick else 5
    q_ref = q_all[:n_ref]
    ref_times, refs = [], []
    for k in range(n_ref):
        t0 = time.thread_time()
        refs.append(reference_shape(robot, q_ref[k], points=POINTS).points)
        ref_times.append(time.thread_time() - t0)
    refs_arr = np.stack(refs)
    ref_per_shape = statistics.median(ref_times)
    errors_by_step = {}
    for step in (5.0, 10.0, 20.0, 40.0):
        sh = comp.with_config(step_mm=step).shape(q_ref, POINTS)
        errors_by_step[step] = float(np.abs(sh.points - refs_arr).max())
    max_error = float(np.abs(shape.points[:n_ref] - refs_arr).max())

    table = []
    for B in batches:
        r, c = per_shape["rigid"][B], per_shape["compliant"][B]
        table.append({
            "batch": B,
            "rigid_us_per_shape": r * 1e6,
            "compliant_us_per_shape": c * 1e6,
            "compliant_over_rigid": c / r,
            "scipy_reference_over_compliant": ref_per_shape / c,
            "rigid_wall_us": per_shape_wall["rigid"][B] * 1e6,
            "compliant_wall_us": per_shape_wall["compliant"][B] * 1e6,
        })
    c10k = per_shape["compliant"][10_000]
    return {
        "robot": ROBOT, "points": POINTS, "seed": SEED, "threads": 1,
        "step_mm": comp.config.step_mm, "tol": comp.config.tol,
        "timer": "thread CPU time (wall time in *_wall_*)",
        "per_shape_s": {name: {str(B): v for B, v in d.items()} for name, d in per_shape.items()},
        "per_shape_wall_s": {name: {str(B): v for B, v in d.items()} for name, d in per_shape_wall.items()},
        "scipy_reference_s_per_shape": ref_per_shape,
        "max_error_vs_reference_mm": max_error,
        "max_error_vs_reference_mm_by_step": {str(k): v for k, v in errors_by_step.items()},
        "newton_iterations": iterations,
        "published_anchor_s_per_shape": PUBLISHED_ANCHOR_S,
        "anchor_over_compliant_10k": PUBLISHED_ANCHOR_S / c10k,
        "target_compliant_10k_s": 1e-4,
        "meets_target": bool(c10k <= 1e-4),
        "table": table,
        "loads": loads_res,
        "stability": stab_res,
    }


def to_markdown(res: dict) -> str:
    lines = [
        f"Robot {res['robot']}, {res['points']} points, one thread, step {res['step_mm']} mm, "
        f"tol {res['tol']:g}; medians of thread CPU time (wall time in brackets).",
        "",
        "| batch | rigid (us/shape) | compliant (us/shape) | compliant / rigid | scipy reference / compliant |",
        "|---:|---:|---:|---:|---:|",
    ]
    for r in res["table"]:
        lines.append(f"| {r['batch']:,} | {r['rigid_us_per_shape']:.1f} ({r['rigid_wall_us']:.1f}) | "
                     f"{r['compliant_us_per_shape']:.1f} ({r['compliant_wall_us']:.1f}) | "
                     f"{r['compliant_over_rigid']:.2f} | {r['scipy_reference_over_compliant']:,.0f} |")
    it = res["newton_iterations"]
    lines += [
        "",
        f"scipy reference (solve_ivp DOP853 rtol 1e-12 + root): {res['scipy_reference_s_per_shape'] * 1e3:.0f} ms/shape; "
        f"max |compliant - reference| = {res['max_error_vs_reference_mm']:.2e} mm at the default step "
        f"(by step: " + ", ".join(f"{k} mm: {v:.1e}" for k, v in res["max_error_vs_reference_mm_by_step"].items()) + ").",
        f"Newton iterations at batch 10,000: mean {it['mean']:.2f}, max {it['max']}, "
        f"converged {it['converged_fraction'] * 100:.2f} %. Target (compliant, batch 10,000) <= 100 us: "
        f"{'met' if res['meets_target'] else 'NOT met'} "
        f"({res['anchor_over_compliant_10k']:.0f}x below the published 1.73 ms/shape anchor).",
    ]
    ld = res.get("loads")
    if ld:
        us = ld["us_per_shape"]
        lines += [
            "",
            f"Loads ({ld['loads']}), batch {ld['batch']:,}: compliant {us['compliant_loaded']:.0f} "
            f"vs {us['compliant']:.1f} us/shape unloaded ({ld['compliant_loaded_over_compliant']:.1f}x), "
            f"rigid {us['rigid_loaded']:.0f} vs {us['rigid']:.1f} ({ld['rigid_loaded_over_rigid']:.1f}x); "
            f"Newton iterations mean {ld['newton_iterations_mean']:.2f}, max "
            f"{ld['newton_iterations_max']}, converged {ld['converged_fraction'] * 100:.2f} %; "
            f"tip sag median {ld['tip_sag_mm_median']:.2f} mm, max {ld['tip_sag_mm_max']:.2f} mm.",
        ]
    for rname, st in (res.get("stability") or {}).items():
        us = st["us_per_shape"]
        lines += [
            "",
            f"Stability check ({rname}, compliant, batch {st['batch']:,}): {us['checked']:.1f} vs "
            f"{us['unchecked']:.1f} us/shape unchecked ({st['checked_over_unchecked']:.3f}x); "
            f"unstable roots rejected in {st['unstable_rejected_fraction'] * 100:.1f} % of rows, "
            f"two stable found in {st['bistable_fraction'] * 100:.1f} %.",
        ]
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="fewer repeats (a smoke run)")
    ap.add_argument("--out", default=None, help="write the results as JSON here")
    args = ap.parse_args(argv)
    res = run(quick=args.quick)
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(res, fh, indent=2)
    print(to_markdown(res))
    return 0


if __name__ == "__main__":
    sys.exit(main())
