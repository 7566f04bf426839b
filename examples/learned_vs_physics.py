"""Learned vs physics shape model on seed1: accuracy against the physics model and speed.

    python examples/learned_vs_physics.py [--quick]
"""

import argparse
import time

import numpy as np
import torch

import ctrplan

torch.set_num_threads(1)                                 # compare both models on one core

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--quick", action="store_true", help="small batch (used by the tests)")
args = parser.parse_args()

robot = ctrplan.load_robot("seed1")
physics = ctrplan.PhysicsModel(robot)                    # torsionally compliant, batched (numba)
learned = ctrplan.load_model("learned", robot)           # shipped default network
q = robot.sample(10_000 if args.quick else 100_000, seed=7)

physics.backbone(q[:2]), learned.backbone(q[:2])         # warm up (JIT, torch)
rows = []
for name, model in (("physics", physics), ("learned", learned)):
    times = []
    for _ in range(3):                                   # median of 3 (shared machines are noisy)
        t0 = time.perf_counter()
        shape = model.shape(q, points=20)
        times.append(time.perf_counter() - t0)
    rows.append((name, shape.points, float(np.median(times)) / len(q) * 1e6))

ref = rows[0][1]
dev = np.linalg.norm(rows[1][1] - ref, axis=2)           # (B, 20) point deviations, mm
print(f"{len(q)} random seed1 configurations, 20 points per backbone")
print("| model | us per shape | max deviation vs physics (mean +- std) | tip deviation (mean) |")
print("|---|---|---|---|")
print(f"| physics | {rows[0][2]:.2f} | 0 (reference) | 0 |")
print(f"| learned | {rows[1][2]:.2f} | {dev.max(1).mean():.3f} +- {dev.max(1).std():.3f} mm "
      f"| {dev[:, -1].mean():.3f} mm |")
print(f"speed-up of the learned model: {rows[0][2] / rows[1][2]:.0f}x")
