"""End-to-end real-robot scenario: measure a foreign "real" robot, calibrate, plan, replay on it.

    .venv/bin/python benchmarks/bench_real_robot.py [--seed 1] [--time 10] [--targets 3]
        [--out benchmarks/results/real_robot.json]

The truth robot is the foreign generator's (``tests/foreign``, no ctrplan code): seed1 with
effects outside ctrplan's fitted families (``tests.foreign.scenarios.real_robot(seed)``: curvature ramps, curved-section stiffness,
clearance lean and jump, presliding hysteresis, compliant drive couplings; without it the
vocabulary effects in ``FALLBACK_EFFECTS``), about 2 mm from the nominal robot (mean over random configurations of the max
deviation along the shaft; reported). The user's flows, each replayed on the truth with the
independent re-check (:mod:`tests.foreign.recheck`: foreign mechanics with the truth's effects,
600+ backbone points, exact FCL cylinders, >= 10 interpolated states per edge):

* **calibrate-then-plan**: ~320 rows of back-and-forth sweeps measured on the truth (noise
  0.08 mm), ``ctrplan diagnose --model physics`` (the CLI, as a user runs it), then
  a ``Planner`` with ``calibrated.yaml`` and ``--margin auto`` to the first ``--targets``
  example targets of each of the four shipped scenes;
* **default**: a ``Planner`` with the defaults (nominal physics model, no calibration).

Per plan: success, status, planning time, re-checked states, states in contact with the truth,
states penetrating deeper than 0.05 mm, deepest penetration, smallest clearance on the truth,
and the truth tip's distance to the target. Issue 18's thresholds are in ``THRESHOLDS``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import numpy as np  # noqa: E402

ROBOT = "seed1"
#: the nominal robot in foreign terms: compliant rods, physical GJ, no coupling (ctrplan physics)
NOMINAL = {"torsion": {"gj_scale": 1.0, "coupling": 0.0, "play": 0.0}}
SCENES = ("airway", "neuro", "skull_base", "bronchial_tree")
OUT = ROOT / "benchmarks" / "results" / "real_robot.json"
#: issue 18 "done when": calibrate-then-plan success share, penetration (mm) allowed on the
#: truth and states deeper than it, median truth tip error (mm); default flow: the share of
#: replayed states in contact with the truth at most (1 - 0.9) x that of the margin-0
#: first-solution plans (issue 18: 44 of 913 path states; a share, because this re-check
#: replays more states per path than the 913)
THRESHOLDS = {"calibrated_success_min": 0.75, "depth_mm": 0.05, "calibrated_penetrating_max": 0,
              "calibrated_tip_error_median_max_mm": 1.5, "default_baseline_states": [44, 913],
              "default_reduction_min": 0.9}
#: re-check density for this bench: >= 10 states per edge, at most 0.5 mm apart (metric mm)
STEP_MM = 0.5
#: FCL distances of free states (the truth clearance; the smallest per path is exact)
DISTANCES = True

#: the truth used while tests.foreign has no real_robot scenario: the issue's robot (middle
#: tube 10 % less curved, outer tube 25 % stiffer, a clearance tilt, an inner-tube rotation
#: lag, torsional compliance)
FALLBACK_EFFECTS = {
    "torsion": {"gj_scale": 1.0, "play": 0.0},
    "precurvature": {"scale": [1.0, 0.9, 1.0]},
    "stiffness": {"scale": [1.0, 1.0, 1.25]},
    "clearance": {"amplitude": 0.02, "phase_deg": 205.0, "harmonics": [0.5, 0.5]},
    "friction": {"form": "coulomb_lag", "lag": [0.03, 0.0, 0.0], "beta_lag": 0.0},
}


def truth_robot(seed: int = 1):
    """(foreign mechanics effects of the truth robot, where they come from, the scenario's
    RealRobot or None)."""
    try:
        from tests.foreign.scenarios import real_robot
    except ImportError:
        return dict(FALLBACK_EFFECTS), "bench_real_robot.FALLBACK_EFFECTS", None
    rr = real_robot(seed)
    return dict(rr.mechanics_effects), f"tests.foreign.scenarios.real_robot({seed})", rr


def deviation(effects: dict, n: int = 200, seed: int = 0, points: int = 50) -> dict:
    """Max deviation along the shaft (mm) of the truth from the nominal compliant robot over
    random valid configurations (random directions of motion): mean / p95 / max."""
    from tests.foreign import backbones
    from tests.foreign.robot import beta_from_unit, load_spec

    spec = load_spec(ROBOT)
    rng = np.random.default_rng([seed, 18])
    q = np.concatenate([rng.uniform(-np.pi, np.pi, (n, spec.n)),
                        beta_from_unit(spec, rng.uniform(0, 1, (n, spec.n)))], axis=1)
    d = rng.choice([-1, 1], size=q.shape)
    a = backbones(ROBOT, q, effects, points=points, direction=d)
    b = backbones(ROBOT, q, NOMINAL, points=points, direction=d)
    m = np.linalg.norm(a - b, axis=2).max(axis=1)
    m = m[np.isfinite(m)]
    return {"mean_mm": float(m.mean()), "p95_mm": float(np.percentile(m, 95)),
            "max_mm": float(m.max()), "configurations": int(m.size)}


def calibrate(effects: dict, work: Path, seed: int, rr=None, rows: int = 320,
              noise_mm: float = 0.08) -> dict:
    """Measure the truth (back-and-forth sweeps, rows in order of motion) and run
    ``ctrplan diagnose --model physics`` on the CSV."""
    from tests.foreign import generate

    if rr is not None:
        data = rr.measure(n=rows, sweeps=4, seed=seed)
        noise_mm = rr.noise_mm
    else:
        data = generate(ROBOT, design="sweeps", n=rows, effects=effects, noise_mm=noise_mm, seed=seed)
    csv = work / "measured.csv"
    data.write_csv(csv)
    t0 = time.perf_counter()
    proc = subprocess.run([sys.executable, "-m", "ctrplan.cli", "--quiet", "diagnose", "--robot", ROBOT,
                           "--data", str(csv), "--model", "physics", "--out", str(work / "report")],
                          capture_output=True, text=True, cwd=ROOT, timeout=900)
    if proc.returncode != 0:
        raise RuntimeError(f"ctrplan diagnose failed: {proc.stderr[-2000:]}")
    rep = json.loads((work / "report" / "report.json").read_text(encoding="utf-8"))
    return {"rows": len(data), "noise_mm": noise_mm, "wall_s": time.perf_counter() - t0,
            "model": str(work / "report" / "calibrated.yaml"),
            "effects": rep.get("effects"), "error_before_mm": rep.get("error_before_mm"),
            "error_after_mm": rep.get("error_after_mm"),
            "max_error_after_mm": rep.get("max_error_after_mm")}


def replay(scene: str, path: np.ndarray, target: np.ndarray, effects: dict) -> dict:
    """The path on the truth robot, independent re-check."""
    from tests.foreign.recheck import recheck_path

    rep = recheck_path(ROBOT, scene, path, effects=effects, step_mm=STEP_MM, distances=DISTANCES)
    s = rep.summary()
    contact = rep.contact != ""
    return {"states": s["states"], "contact_states": s["contact_states"],
            "penetrating_states": rep.penetrating(THRESHOLDS["depth_mm"]),
            "max_depth_mm": float(np.nanmax(rep.depth_mm)) if contact.any() else 0.0,
            "centreline_crossings": s["centreline_crossings"],
            "min_clearance_truth_mm": rep.min_clearance_mm,
            "tip_error_truth_mm": float(np.linalg.norm(rep.tip[-1] - target))}


def plan_flow(flow: str, model, margin, targets: int, time_limit: float, effects: dict,
              objective: str | None = None) -> list[dict]:
    from ctrplan.collision.scene import load_scene
    from ctrplan.planning import Planner, PlannerConfig

    cfg = PlannerConfig() if margin == "default" else PlannerConfig(margin_mm=margin)
    if objective is not None:
        cfg = replace(cfg, objective=objective)
    rows = []
    for s in SCENES:
        sc = load_scene(s)
        planner = Planner(ROBOT, sc, model, cfg)     # one per scene: prepared once
        for t in sc.targets[:targets]:
            r = planner.plan(t.position, seed=0, time_limit=time_limit)
            row = {"flow": flow, "scene": s, "target": t.name, "success": bool(r.success),
                   "status": r.status.value, "planning_time_s": r.planning_time_s,
                   "time_cap_hit": bool(r.time_cap_hit), "margin_mm": r.margin_mm,
                   "min_clearance_planning_mm": r.min_clearance_mm if r.success else None,
                   "goal_shift_mm": float(r.goal_shift_mm),
                   "outside_measured_states": r.outside_measured_states}
            if r.success:
                row.update(replay(s, r.path, np.asarray(t.position, float), effects))
            rows.append(row)
            print(f"{flow} {s}/{t.name}: {row['status']} "
                  + (f"states {row['states']} penetrating {row['penetrating_states']} "
                     f"depth {row['max_depth_mm']:.3f} tip {row['tip_error_truth_mm']:.2f} mm"
                     if r.success else ""), flush=True)
    return rows


def summary(rows: list[dict]) -> dict:
    ok = [r for r in rows if r["success"]]
    return {"plans": len(rows), "success": len(ok),
            "success_rate": len(ok) / len(rows) if rows else float("nan"),
            "states": sum(r["states"] for r in ok),
            "contact_states": sum(r["contact_states"] for r in ok),
            "contact_fraction": (sum(r["contact_states"] for r in ok) / max(1, sum(r["states"] for r in ok))),
            "penetrating_states": sum(r["penetrating_states"] for r in ok),
            "max_depth_mm": max((r["max_depth_mm"] for r in ok), default=0.0),
            "tip_error_truth_median_mm": statistics.median(r["tip_error_truth_mm"] for r in ok) if ok else None,
            "planning_time_median_s": statistics.median(r["planning_time_s"] for r in rows) if rows else None}


def default_allowed() -> float:
    """Largest share of replayed states in contact allowed to the default flow."""
    k, n = THRESHOLDS["default_baseline_states"]
    return (1 - THRESHOLDS["default_reduction_min"]) * k / n


def verdicts(res: dict) -> dict:
    th = THRESHOLDS
    c = res["calibrated"]["summary"]
    med = c["tip_error_truth_median_mm"]
    return {
        "calibrated_success": c["success_rate"] >= th["calibrated_success_min"],
        "calibrated_no_penetration": c["penetrating_states"] <= th["calibrated_penetrating_max"],
        "calibrated_tip_error": med is not None and med <= th["calibrated_tip_error_median_max_mm"],
        "default_penetration_reduced": default_reduced(res),
    }


def default_reduced(res: dict) -> bool:
    """The default flow's states in contact with the truth are at most (1 - 0.9) x those of the
    margin-0 first-solution plans to the same targets in the same run (``first`` flow); without
    that flow, against the issue's measured share (44 of 913)."""
    d = res["default"]["summary"]
    if "first" in res:
        return d["contact_states"] <= (1 - THRESHOLDS["default_reduction_min"]) * \
            res["first"]["summary"]["contact_states"]
    return d["contact_fraction"] <= default_allowed()


def run(seed: int = 1, time_limit: float = 10.0, targets: int = 3, flows=("calibrated", "default", "first"),
        out: Path | None = OUT) -> dict:
    import numba

    numba.set_num_threads(1)
    t0 = time.perf_counter()
    effects, source, rr = truth_robot(seed)
    res: dict = {"robot": ROBOT, "seed": seed, "time_limit_s": time_limit, "targets_per_scene": targets,
                 "scenes": list(SCENES), "truth": {"effects": effects, "source": source},
                 "thresholds": THRESHOLDS, "recheck": {"step_mm": STEP_MM, "per_edge": 10, "points": 600}}
    res["truth"]["deviation_from_nominal"] = deviation(effects)
    print(f"truth {source}: {res['truth']['deviation_from_nominal']}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        if "calibrated" in flows:
            cal = calibrate(effects, Path(tmp), seed, rr)
            print(f"calibration: {cal}", flush=True)
            rows = plan_flow("calibrated", cal["model"], None, targets, time_limit, effects)
            cal["model"] = "calibrated.yaml (diagnose output)"
            res["calibrated"] = {"calibration": cal, "plans": rows, "summary": summary(rows)}
        if "default" in flows:
            rows = plan_flow("default", "physics", "default", targets, time_limit, effects)
            res["default"] = {"plans": rows, "summary": summary(rows)}
        if "first" in flows:   # the baseline: margin 0, first solution (before issue 18)
            rows = plan_flow("first", "physics", 0.0, targets, time_limit, effects, objective="first")
            res["first"] = {"plans": rows, "summary": summary(rows)}
    if "calibrated" in res and "default" in res:
        res["verdicts"] = verdicts(res)
    res["wall_s"] = time.perf_counter() - t0
    if out is not None:
        out.parent.mkdir(parents=True, exist_ok=True)
        tmpf = out.with_suffix(".json.tmp")
        tmpf.write_text(json.dumps(res, indent=1) + "\n", encoding="utf-8")
        os.replace(tmpf, out)
    return res


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--time", type=float, default=10.0, help="time cap per plan (s)")
    ap.add_argument("--targets", type=int, default=3, help="first K targets per scene")
    ap.add_argument("--flows", nargs="+", default=["calibrated", "default", "first"])
    ap.add_argument("--out", default=str(OUT))
    args = ap.parse_args(argv)
    res = run(args.seed, args.time, args.targets, tuple(args.flows), Path(args.out))
    for f in ("calibrated", "default"):
        if f in res:
            print(f, json.dumps(res[f]["summary"]))
    print(json.dumps(res.get("verdicts", {})), f"{res['wall_s']:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
