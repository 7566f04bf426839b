"""Benchmark: the diagnose workflow on simulated measurements (seed1, three tubes, one core).

Target (issues 6, 12): 1,000 samples in under two minutes on one core, with the default
settings (every effect form, the nuisances outside the vocabulary, the evidence and the learned
residual); the load case is the slowest (every solve after ``load`` is found is a loaded one). Reports the wall time of the
whole workflow, the number of batched kernel calls it made, and a baseline measured in the same
process — one rigid and one compliant solve of the same 1,000 configurations — so the ratio
"workflow / one compliant batch" is comparable across machines.
"""

from __future__ import annotations

import os
import time

import numpy as np

CASES = (
    ("clearance+friction+torsion", {"clearance": {"length": 8.0, "limit": 0.3},
                                    "friction": {"lost1": 0.1, "lost2": 0.08, "lost3": 0.05},
                                    "torsion": {"compliance": 1.0}}),
    ("none", {}),
    ("load (gravity, horizontal robot)", {"load": {"gx": 9.81}}),
)


def _one_core():
    try:
        before = os.sched_getaffinity(0)
        os.sched_setaffinity(0, {min(before)})
        return before
    except (AttributeError, OSError):  # pragma: no cover - non-Linux
        return None


def run(quick: bool = False) -> dict:
    from ctrplan.calibration.diagnose import diagnose
    from ctrplan.calibration.simulate import design, simulate
    from ctrplan.robot import load_robot
    from ctrplan.shape.physics import PhysicsModel

    rows = 200 if quick else 1000
    robot = load_robot("seed1")
    saved = _one_core()
    table = []
    try:
        q, sweep = design(robot, ["random_walk"], rows, sweeps=8, seed=1)
        base = {}
        for torsion in (False, True):
            m = PhysicsModel(robot, torsion=torsion)
            m.shape(q[:4], 2)
            t0 = time.perf_counter()
            m.shape(q, 2)
            base["compliant" if torsion else "rigid"] = time.perf_counter() - t0
        for name, effects in CASES[: 1 if quick else None]:
            data = simulate(robot, q, effects, sweep=sweep, noise_mm=0.2, seed=1, step_mm=5.0)
            t0 = time.perf_counter()
            rep = diagnose(robot, data, base="rigid", seed=1)
            dt = time.perf_counter() - t0
            table.append({
                "hidden": name, "rows": len(data), "found": ", ".join(rep.effects) or "none",
                "wall_s": dt, "under_2_min": bool(dt < 120.0),
                "kernel_calls": rep.settings["kernel_calls"],
                "error_before_mm": rep.error_before_mm, "error_after_mm": rep.error_after_mm,
                "baseline_rigid_batch_s": base["rigid"],
                "baseline_compliant_batch_s": base["compliant"],
                "ratio_vs_compliant_batch": dt / base["compliant"],
            })
    finally:
        if saved is not None:
            os.sched_setaffinity(0, saved)
    return {"table": table, "robot": "seed1", "cores": 1,
            "median_wall_s": float(np.median([r["wall_s"] for r in table]))}


if __name__ == "__main__":
    import json
    import sys

    print(json.dumps(run(quick="--quick" in sys.argv), indent=1))
