"""Same plans before and after a refactoring: plan a fixed set, write each plan.json, compare.

    python benchmarks/same_plans.py plan OUT/            # plan the set with the ctrplan on the path
    python benchmarks/same_plans.py compare A/ B/        # byte for byte, except the timings

The set: the seed1 robot in the 4 shipped scenes (2 example targets, seeds 0 and 1, the physics
and the learned model; the ``first`` objective on airway too; the rigid model once),
two_tube_nylon fold-crossing pairs from the foreign generator (tests/foreign/folds.py) in an
open scene, the issue's start at relative rotation 4.08 rad, a bistable start with its branch
(+1 and -1), a calibrated model file (an effect model with registration, measured error bound,
error profile and measured insertions: ``--model calibrated.yaml``), a friction model (direction
of motion), the rigid model, and a small in-process ``plan-batch``.

Every plan has a state budget of 40,000 and a time cap of 120 s, so that the budget (a count),
never the cap (the machine's load), is what stops a search. Plans are grouped by what a
:class:`ctrplan.Planner` prepares (robot, scene, model, config) and
made in a fixed order with one planner per group (``plan_to_target`` where ``ctrplan`` has no
``Planner``, e.g. before it existed; there the first plan of every group is made twice and the
first result dropped, so that no recorded plan pays for the process-wide caches of that code:
its counts then describe the plan alone, as a Planner's do).

``compare`` reads every ``*.json`` of A and B and compares them after dropping ``timings`` and
``planning_time_s`` (wall-clock); it prints one line per difference and exits 1 if any.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
from pathlib import Path

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

ROOT = Path(__file__).resolve().parents[1]
#: plan.json keys that hold wall-clock time
TIMES = ("timings", "planning_time_s")
#: every plan's state budget and time cap: the cap is never what stops a plan (a plan stopped by
#: it depends on the machine's load, ``time_cap_hit``), the budget is (a count: deterministic)
MAX_STATES = 40_000
TIME_LIMIT_S = 120.0
#: the calibrated model file (the same path in every run: plan.json records the model's path)
CALIBRATED = Path(os.environ.get("TMPDIR", "/tmp")) / "ctrplan-same-plans" / "calibrated.yaml"


def _calibrated_file() -> str:
    """A calibrated model file as ``diagnose`` writes one (seed1, compliant base)."""
    from ctrplan.shape.effects import EffectModel
    from ctrplan.shape.error_bounds import extend_tip_bound

    eq = {"p50": 0.3, "p95": 0.6, "p99": 0.8, "max": 1.1}
    model = EffectModel("seed1", "compliant",
                        {"precurvature": {"scale1": 1.02, "scale2": 0.99, "scale3": 1.0},
                         "registration": {"tx": 0.4, "ty": -0.2, "tz": 0.1, "rx": 0.0, "ry": 0.0,
                                          "rz": 0.01}},
                        error_quantiles=eq, error_profile=extend_tip_bound(eq).to_dict(),
                        measured_insertion={"min": [-120.0, -100.0, -80.0], "max": [0.0, 0.0, 0.0]},
                        error_bound="measured")
    CALIBRATED.parent.mkdir(parents=True, exist_ok=True)
    model.save(CALIBRATED)
    return str(CALIBRATED)


def cases() -> list[dict]:
    """The fixed set: dicts with group (what a planner prepares) and the plan's request."""
    import numpy as np

    from ctrplan.collision.scene import list_scenes, load_scene
    from ctrplan.shape.effects import EffectModel
    from ctrplan.shape.physics import PhysicsModel
    from tests.conftest import open_scene
    from tests.foreign.folds import fold_crossing_pairs

    out = []
    scenes = {name: load_scene(name) for name in list_scenes()}
    for name, scene in scenes.items():
        for model in ("physics", "learned"):
            for t in scene.targets[:2]:
                for seed in (0, 1):
                    out.append(dict(id=f"{name}-{model}-{t.name}-s{seed}", robot="seed1",
                                    scene=scene, model=model, target=list(t.position), seed=seed))
    air = scenes["airway"]
    for t in air.targets[:3]:
        out.append(dict(id=f"airway-first-{t.name}", robot="seed1", scene=air, model="physics",
                        target=list(t.position), seed=0, objective="first"))
    out.append(dict(id="airway-rigid", robot="seed1", scene=air, model="rigid",
                    target=list(air.targets[1].position), seed=0))
    cal = _calibrated_file()
    for t in air.targets[:3]:
        out.append(dict(id=f"airway-calibrated-{t.name}", robot="seed1", scene=air, model=cal,
                        target=list(t.position), seed=0))
    friction = EffectModel("seed1", "compliant", {"friction": {"lost1": 0.3, "lost2": 0.2, "lost3": 0.1}})
    for t in air.targets[1:3]:
        out.append(dict(id=f"airway-friction-{t.name}", robot="seed1", scene=air, model=friction,
                        target=list(t.position), seed=0))
    opened = open_scene()
    for k, (start, target) in enumerate(fold_crossing_pairs("two_tube_nylon", 4, 3501)):
        out.append(dict(id=f"nylon-fold-{k}", robot="two_tube_nylon", scene=opened, model="physics",
                        target=[float(v) for v in target], seed=k, start=[float(v) for v in start]))
    nylon = PhysicsModel("two_tube_nylon")
    t233 = nylon.shape(np.array([[2.33, 0.0, -160.0, -100.0]]), 2).tip[0]
    out.append(dict(id="nylon-issue", robot="two_tube_nylon", scene=opened, model="physics",
                    target=[float(v) for v in t233], seed=0, start=[4.08, 0.0, -160.0, -100.0]))
    t05 = nylon.shape(np.array([[0.5, 0.0, -150.0, -100.0]]), 2).tip[0]
    for branch in (1, -1):
        out.append(dict(id=f"nylon-bistable-{branch:+d}", robot="two_tube_nylon", scene=opened,
                        model="physics", target=[float(v) for v in t05], seed=0,
                        start=[math.pi, 0.0, -160.0, -100.0], branch=branch))
    return out


def _key(case: dict) -> tuple:
    model = case["model"]
    return (case["robot"], id(case["scene"]), model if isinstance(model, str) else id(model))


def plan_all(out: Path) -> None:
    import numba

    numba.set_num_threads(1)
    import ctrplan
    from ctrplan.io import write_json_atomic
    from ctrplan.planning.stability import Start

    out.mkdir(parents=True, exist_ok=True)
    work = out / "_work"
    work.mkdir(exist_ok=True)
    todo = cases()
    has_planner = hasattr(ctrplan, "Planner")
    planners: dict = {}
    seen: set = set()
    for case in todo:
        start = case.get("start")
        if start is not None and "branch" in case:
            start = Start(__import__("numpy").asarray(start), case["branch"])
        objective = case.get("objective", "clearance")
        if has_planner:
            key = _key(case)
            if key not in planners:
                planners[key] = ctrplan.Planner(case["robot"], case["scene"], case["model"],
                                                ctrplan.PlannerConfig(max_states=MAX_STATES))
            result = planners[key].plan(case["target"], seed=case["seed"], start=start,
                                        objective=objective, time_limit=TIME_LIMIT_S)
        else:
            if _key(case) not in seen:      # pay the process-wide caches with a dropped plan
                seen.add(_key(case))
                _plan_once(case, start, objective)
            result = _plan_once(case, start, objective)
        write_json_atomic(out / f"{case['id']}.json", result.to_json())
        print(f"{case['id']}: {result.status.value} {result.planner} "
              f"{result.planning_time_s:.2f} s", flush=True)
    _batch(out)


def _plan_once(case: dict, start, objective: str):
    """One plan with ``plan_to_target`` (a ctrplan without Planner)."""
    import ctrplan

    return ctrplan.plan_to_target(case["robot"], case["scene"], case["target"], model=case["model"],
                                  seed=case["seed"], start=start, objective=objective,
                                  time_limit=TIME_LIMIT_S,
                                  config=ctrplan.PlanConfig(max_states=MAX_STATES))


def _batch(out: Path) -> None:
    """A small in-process plan-batch (its job files are compared too)."""
    from ctrplan.collision.scene import load_scene
    from ctrplan.planning.batch import make_jobs, run_batch

    targets = []
    for name in ("airway", "neuro"):
        t = load_scene(name).targets[0]
        targets.append((name, t.name, list(t.position)))
    jobs = make_jobs(targets, seeds=[0, 1], time_limit=TIME_LIMIT_S)
    # (twice, the first dropped: as for the plans, no recorded job pays for process-wide caches)
    run_batch(jobs, out / "_work" / "batch", workers=1)
    folder = out / "_batch"
    run_batch(jobs, folder, workers=1)
    for f in sorted((folder / "jobs").glob("*.json")):
        (out / f"batch-{f.name}").write_text(f.read_text())


def _strip(d):
    if isinstance(d, dict):
        return {k: _strip(v) for k, v in d.items() if k not in TIMES}
    if isinstance(d, list):
        return [_strip(v) for v in d]
    return d


def _diff(a, b, where: str, out: list[str]) -> None:
    if isinstance(a, dict) and isinstance(b, dict):
        for k in sorted(set(a) | set(b)):
            if k not in a or k not in b:
                out.append(f"{where}.{k}: only in {'B' if k not in a else 'A'}")
            else:
                _diff(a[k], b[k], f"{where}.{k}", out)
    elif isinstance(a, list) and isinstance(b, list) and len(a) == len(b):
        for i, (x, y) in enumerate(zip(a, b)):
            _diff(x, y, f"{where}[{i}]", out)
    elif json.dumps(a) != json.dumps(b):
        out.append(f"{where}: {json.dumps(a)[:80]} != {json.dumps(b)[:80]}")


def compare(a: Path, b: Path) -> int:
    names = sorted({p.name for p in a.glob("*.json")} | {p.name for p in b.glob("*.json")})
    bad = 0
    for name in names:
        pa, pb = a / name, b / name
        if not (pa.exists() and pb.exists()):
            print(f"{name}: only in {'A' if pa.exists() else 'B'}")
            bad += 1
            continue
        da, db = _strip(json.loads(pa.read_text())), _strip(json.loads(pb.read_text()))
        same = json.dumps(da, sort_keys=False) == json.dumps(db, sort_keys=False)
        if not same:
            lines: list[str] = []
            _diff(da, db, name, lines)
            bad += 1
            print("\n".join(lines[:20]) or f"{name}: key order differs")
    print(f"{len(names)} plans compared, {bad} differ (timings and planning_time_s excluded)")
    return 1 if bad else 0


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="cmd", required=True)
    sp = sub.add_parser("plan")
    sp.add_argument("out")
    sc = sub.add_parser("compare")
    sc.add_argument("a")
    sc.add_argument("b")
    args = p.parse_args(argv)
    if str(ROOT) not in sys.path:      # tests/ (the foreign generator); ctrplan from PYTHONPATH
        sys.path.append(str(ROOT))
    if args.cmd == "plan":
        plan_all(Path(args.out))
        return 0
    return compare(Path(args.a), Path(args.b))


if __name__ == "__main__":
    sys.exit(main())
