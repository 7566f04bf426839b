"""``ctrplan design``: scaling over workers, and success on anatomies it has never seen.

Two parts (each writes a JSON file into ``benchmarks/results/``):

``scaling`` -- one search (a generated anatomy, default settings, the same seed) run with 1, 2,
4 and 8 local workers and on a local Ray instance, one after the other in this process. Budgets
are counts, so every run evaluates the same designs and returns the same design
(``same_design_all_runs``). Reports the wall time, the speed-up and the parallel efficiency
``T1 / (w Tw)`` per worker count, the share of time per stage, and where it ran (CPU model,
cores, load averages before and after each run). Worker counts above the machine's cores are
skipped (and said so). Parallel runs include starting their workers.

``anatomies`` -- ``--count`` generated known-feasible anatomies (tests/design_scenes.py: a lumen
around a known two-tube robot's motions to three targets, fresh seeds from ``--first``) with
``ctrplan design`` at its defaults: targets reached, every reached plan replayed by the
independent re-check (tests/foreign/recheck.py: foreign mechanics, exact FCL cylinders), the
strain of every tube from robot.yaml; and the same anatomies narrowed below the smallest stock
tube (a neck): what the report names as blocking, and how far its place is from the neck.
Resumable: each anatomy's row goes to ``--work`` as it finishes; a rerun skips the rows there.

Usage::

    python benchmarks/bench_design.py scaling [--workers 1,2,4,8] [--no-ray] [--seed 2100]
    python benchmarks/bench_design.py anatomies [--count 10] [--first 2000] [--work DIR]
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import os
import platform
import sys
import time
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
sys.path.insert(0, str(Path(__file__).resolve().parent))

from ctrplan.design import DesignConfig, design  # noqa: E402

RESULTS = Path(__file__).resolve().parent / "results"
#: Strain limit the designs must keep (DEFAULT_STRAIN_LIMIT; restated, checked by hand).
STRAIN_LIMIT = 0.06
#: Smallest stock tube (od, mm) of the shipped table.
SMALLEST_OD = 0.51


def machine() -> dict:
    """Where it ran: CPU model, cores (logical and usable), OS, Python."""
    model = ""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        model = platform.processor()
    usable = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return {"cpu_model": model, "cpu_count": os.cpu_count(), "usable_cores": usable,
            "os": platform.platform(), "python": platform.python_version(),
            "date": time.strftime("%Y-%m-%d %H:%M")}


# ----------------------------------------------------------------------------- scaling
def _timed(folder: Path, cfg: DesignConfig, label: str, work: Path | None = None) -> tuple[dict, dict | None]:
    load_before = os.getloadavg()[0]
    t0, c0 = time.perf_counter(), time.process_time()
    r = design(folder, "a,b,c", cfg, progress=False)
    wall, cpu = time.perf_counter() - t0, time.process_time() - c0
    stages = {k: v for k, v in r.timings.items() if k != "total"}
    row = {"label": label, "wall_s": wall, "cpu_s": cpu, "evaluations": r.counts["evaluations"],
           "generations": r.counts.get("generations"), "planned": r.counts["planned"],
           "reached": r.reached, "stage_s": stages,
           "load_average_1min_before": load_before, "load_average_1min_after": os.getloadavg()[0]}
    if work is not None and r.schedule:      # the job log, for the schedule simulation
        row["schedule_file"] = str(work / f"schedule_{label}.json")
        row["runner_wall_s"] = r.schedule["wall_s"]
        Path(row["schedule_file"]).write_text(json.dumps(r.schedule) + "\n", encoding="utf-8")
    return row, (r.robot.to_dict() if r.robot is not None else None)


def _startup_s(folder: Path) -> float:
    """CPU seconds a fresh spawned worker spends before its first job (the process, the
    imports, the scene and its collision world): what each pool worker pays once."""
    import multiprocessing as mp
    from concurrent.futures import ProcessPoolExecutor

    from design_schedule import startup_probe

    from ctrplan.design.evaluate import EvalSettings
    from ctrplan.design.runner import _worker_init

    with ProcessPoolExecutor(1, mp_context=mp.get_context("spawn"), initializer=_worker_init) as ex:
        return ex.submit(startup_probe, str(folder), EvalSettings().__dict__).result()


def simulated(folder: Path, work: Path, workers: list[int], row_new: dict) -> dict:
    """Predicted efficiencies from the jobs' measured seconds: the 1-worker run's own log (this
    schedule) and a 1-worker run with PLAN_LAG = 1 (the old synchronous schedule), each
    replayed on W simulated workers (design_schedule.py)."""
    from design_schedule import predict

    import ctrplan.design.search as search

    lag = search.PLAN_LAG
    try:
        search.PLAN_LAG = 1
        row_old, _ = _timed(folder, DesignConfig(workers=1), "1_lag1", work)
    finally:
        search.PLAN_LAG = lag
    startup = _startup_s(folder)
    out = {"startup_s": startup, "plan_lag": lag}
    for name, row in ((f"lag{lag}", row_new), ("lag1_old", row_old)):
        sched = json.loads(Path(row["schedule_file"]).read_text())
        # this process's CPU outside the jobs (anatomy, CMA-ES, outputs), so that a run on a
        # shared machine still predicts an unloaded one
        serial = row["cpu_s"] - sum(v["cpu_s"] + v["load_cpu_s"] for v in sched["seconds"].values())
        out[name] = {"measured_1_worker_s": row["wall_s"], "generations": row["generations"],
                     "evaluations": row["evaluations"], "planned": row["planned"],
                     "reached": row["reached"], "serial_s": serial,
                     "predicted": predict(sched, serial, workers, startup),
                     "predicted_no_startup": predict(sched, serial, workers, 0.0),
                     "predicted_startup_not_hidden": predict({**sched, "head_s": 0.0}, serial, workers, startup)}
    return out


def scaling(workers: list[int], use_ray: bool, seed: int, work: Path, simulate: bool = True) -> dict:
    from tests.design_scenes import build

    folder = work / f"known_{seed}"
    build(seed, folder)
    design(folder, "a", DesignConfig(budget=2, generation=2), progress=False)     # warm-up: field, numba
    cores = machine()["usable_cores"] or 1
    out: dict = {"anatomy_seed": seed, "machine": machine(), "runs": {}, "skipped": []}
    robots = {}
    for w in workers:
        if w > cores:
            out["skipped"].append(f"{w} workers: only {cores} usable cores here")
            continue
        row, robots[str(w)] = _timed(folder, DesignConfig(workers=w), str(w), work)
        out["runs"][str(w)] = row
    if use_ray and importlib.util.find_spec("ray") is not None:
        row, robots["ray_local"] = _timed(folder, DesignConfig(ray_address="local"), "ray_local")
        out["runs"]["ray_local"] = row
    t1 = out["runs"].get("1", {}).get("wall_s")
    for key, row in out["runs"].items():
        w = cores if key == "ray_local" else int(key)
        if t1:
            row["speedup"] = t1 / row["wall_s"]
            row["parallel_efficiency"] = t1 / (w * row["wall_s"])
    out["same_design_all_runs"] = len({json.dumps(r, sort_keys=True) for r in robots.values()}) == 1
    if simulate and "1" in out["runs"]:
        out["simulated"] = simulated(folder, work, workers, out["runs"]["1"])
    return out


# ----------------------------------------------------------------------------- anatomies
def _recheck(out: Path, folder: Path, robot_yaml: Path) -> dict:
    """Every reached target's plan replayed by the independent re-check."""
    from tests.foreign.recheck import recheck_path

    doc = json.loads((out / "design.json").read_text())
    rows = {}
    for t in doc["targets"]:
        if not t["reached"]:
            continue
        plan = json.loads((out / t["path_file"]).read_text())
        rep = recheck_path(str(robot_yaml), str(folder), plan["path"], distances=False)
        rows[t["name"]] = {"free": rep.free, "states": int(len(rep.edge))}
    return rows


def _strain(robot_yaml: Path) -> float:
    import yaml

    tubes = yaml.safe_load(robot_yaml.read_text())["tubes"]
    return max(t["od"] / 2 * abs(t["curvature"]) for t in tubes)


def feasible_row(seed: int, work: Path) -> dict:
    """One known-feasible anatomy: ``ctrplan design`` at its defaults, plans re-checked."""
    from ctrplan.cli import main
    from tests.design_scenes import build

    folder = work / f"known_{seed}"
    t0 = time.perf_counter()
    ks = build(seed, folder)
    t_build = time.perf_counter() - t0
    out = work / f"design_{seed}"
    t0 = time.perf_counter()
    rc = main(["-q", "design", "--scene", str(folder), "--targets", ",".join(ks.names), "--out", str(out)])
    t_design = time.perf_counter() - t0
    doc = json.loads((out / "design.json").read_text())
    row = {"seed": seed, "rc": rc, "reached": doc["reached"], "targets": doc["targets_total"],
           "status": doc["status"], "build_s": t_build, "design_s": t_design,
           "evaluations": doc["counts"]["evaluations"], "planned": doc["counts"]["planned"],
           "known_robot": ks.robot["tubes"], "blocked": [(b["target"], b["blocking"]) for b in doc["blocked"]]}
    if doc["robot"] is not None:
        row["robot"] = doc["robot"]["tubes"]
        row["strain"] = _strain(out / "robot.yaml")
        row["recheck"] = _recheck(out, folder, out / "robot.yaml")
    row["ok"] = (doc["reached"] >= math.ceil(2 * doc["targets_total"] / 3)
                 and all(v["free"] for v in row.get("recheck", {}).values())
                 and row.get("strain", 0.0) <= STRAIN_LIMIT + 1e-12)
    return row


def infeasible_row(seed: int, work: Path) -> dict:
    """The same anatomy with a neck below the smallest stock tube: what blocks each target and
    how far the named place is from the neck (base frame)."""
    import numpy as np

    from ctrplan.cli import main
    from tests.design_scenes import build

    folder = work / f"neck_{seed}"
    ks = build(seed, folder, infeasible=True)
    out = work / f"design_neck_{seed}"
    t0 = time.perf_counter()
    rc = main(["-q", "design", "--scene", str(folder), "--targets", ",".join(ks.names), "--out", str(out)])
    t_design = time.perf_counter() - t0
    doc = json.loads((out / "design.json").read_text())
    named = []
    for b in doc["blocked"]:
        place = b.get("place") or {}
        dist = (float(np.linalg.norm(np.asarray(place["position"]) - ks.neck_centre))
                if place.get("position") is not None else None)
        named.append({"target": b["target"], "blocking": b["blocking"], "kind": b["kind"],
                      "width_mm": b["numbers"].get("width_mm"), "at_mm": place.get("at_mm"),
                      "distance_to_neck_mm": dist, "message": b["message"]})
    ok = (rc == 1 and len(named) == len(ks.names)
          and all(n["blocking"] == "corridor" and n["distance_to_neck_mm"] is not None
                  and n["distance_to_neck_mm"] <= 2.5 and (n["width_mm"] or 0.0) < SMALLEST_OD
                  for n in named))
    return {"seed": seed, "rc": rc, "status": doc["status"], "neck_depth_mm": ks.neck_depth_mm,
            "design_s": t_design, "named": named, "ok": ok}


def anatomies(count: int, first: int, work: Path) -> dict:
    work.mkdir(parents=True, exist_ok=True)
    rows = {"feasible": [], "infeasible": []}
    for seed in range(first, first + count):
        for kind, fn in (("feasible", feasible_row), ("infeasible", infeasible_row)):
            done = work / f"{kind}_{seed}.json"
            if done.is_file():
                rows[kind].append(json.loads(done.read_text()))
                continue
            row = fn(seed, work)
            done.write_text(json.dumps(row, indent=1, default=str) + "\n")
            rows[kind].append(row)
            print(f"{kind} {seed}: ok={row['ok']}", flush=True)
    f, n = rows["feasible"], rows["infeasible"]
    return {"machine": machine(), "seeds": [first, first + count - 1],
            "feasible_ok": sum(r["ok"] for r in f), "feasible_total": len(f),
            "feasible_share": sum(r["ok"] for r in f) / max(1, len(f)),
            "plans_rechecked": sum(len(r.get("recheck", {})) for r in f),
            "plans_free": sum(v["free"] for r in f for v in r.get("recheck", {}).values()),
            "infeasible_named": sum(r["ok"] for r in n), "infeasible_total": len(n),
            "design_s_median": sorted(r["design_s"] for r in f)[len(f) // 2] if f else None,
            "rows": rows}


def _print_simulated(sim: dict | None) -> None:
    if not sim:
        return
    print(f"simulated from the jobs' CPU seconds (worker start-up {sim['startup_s']:.1f} s each, "
          "hidden while the anatomy is read):")
    for name in (f"lag{sim['plan_lag']}", "lag1_old"):
        row = sim[name]
        pred = ", ".join(f"{w}: {p['wall_s']:.1f} s eff {p['parallel_efficiency']:.2f}"
                         for w, p in row["predicted"].items())
        print(f"  {name}: {row['generations']} generations, {row['evaluations']} designs, "
              f"{row['planned']} planned, measured 1 worker {row['measured_1_worker_s']:.1f} s; {pred}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="part", required=True)
    s = sub.add_parser("scaling")
    s.add_argument("--workers", default="1,2,4,8")
    s.add_argument("--no-ray", action="store_true")
    s.add_argument("--no-simulate", action="store_true",
                   help="skip the schedule simulation (a second 1-worker run with the old schedule)")
    s.add_argument("--seed", type=int, default=2100, help="the anatomy's seed")
    s.add_argument("--work", default="/tmp/ctrplan_bench_design")
    s.add_argument("--out", default=str(RESULTS / "design_scaling.json"))
    a = sub.add_parser("anatomies")
    a.add_argument("--count", type=int, default=10)
    a.add_argument("--first", type=int, default=2000)
    a.add_argument("--work", default="/tmp/ctrplan_bench_design")
    a.add_argument("--out", default=str(RESULTS / "design_generated.json"))
    args = ap.parse_args(argv)
    work = Path(args.work)
    work.mkdir(parents=True, exist_ok=True)
    if args.part == "scaling":
        res = scaling([int(w) for w in args.workers.split(",")], not args.no_ray, args.seed, work,
                      not args.no_simulate)
        for k, r in res["runs"].items():
            eff = f", efficiency {r['parallel_efficiency']:.2f}" if "parallel_efficiency" in r else ""
            print(f"{k}: {r['wall_s']:.1f} s, {r['evaluations']} designs, {r['reached']} reached{eff}")
        print(f"same design in every run: {res['same_design_all_runs']}; {res['machine']}")
        _print_simulated(res.get("simulated"))
    else:
        res = anatomies(args.count, args.first, work)
        print(f"known-feasible: {res['feasible_ok']}/{res['feasible_total']} reach >= 2/3 with every plan "
              f"free in the re-check ({res['plans_free']}/{res['plans_rechecked']} plans); infeasible: "
              f"{res['infeasible_named']}/{res['infeasible_total']} name the neck")
    Path(args.out).write_text(json.dumps(res, indent=1, default=str) + "\n", encoding="utf-8")
    return 0


if __name__ == "__main__":
    sys.exit(main())
