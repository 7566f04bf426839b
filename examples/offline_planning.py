"""Offline planning over every shipped anatomy: many targets, a process pool, a summary table.

Jobs are resumable (finished ones are skipped when the script runs again on the same folder).
Scale to a Ray cluster with ``run_batch(..., ray_address="ray://head:10001")`` or
``ctrplan plan-batch --targets examples --ray ADDRESS --out results/``.

    python examples/offline_planning.py [--quick] [--workers K] [--out DIR]
"""

import argparse
import tempfile

from ctrplan.collision.scene import list_scenes, load_scene
from ctrplan.planning.batch import make_jobs, run_batch


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="2 targets per scene, short time limit (tests)")
    parser.add_argument("--workers", type=int, default=2, help="local worker processes")
    parser.add_argument("--out", default=None, help="results folder (default: a temporary folder)")
    args = parser.parse_args()

    targets = []
    for name in list_scenes():
        scene = load_scene(name)
        for t in scene.targets[: 2 if args.quick else None]:
            targets.append((name, t.name, tuple(float(v) for v in t.position)))

    jobs = make_jobs(targets, seeds=(0,), model="physics", time_limit=2.0 if args.quick else 5.0)
    summary = run_batch(jobs, args.out or tempfile.mkdtemp(prefix="ctrplan_offline_"), workers=args.workers)

    print(f"{summary.total} jobs ({summary.ran} run now, {summary.skipped} already done) -> {summary.out}")
    cols = list(summary.rows[0].keys())
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for row in summary.rows:
        print("| " + " | ".join(f"{v:.3g}" if isinstance(v, float) else str(v) for v in row.values()) + " |")


if __name__ == "__main__":  # process pools re-import this file
    main()
