"""Plan the seed1 robot to targets in the airway scene: the Python API in a dozen lines.

A Planner is prepared once (robot, scene, model, collision world, IK table) and plans to as many
targets as you like; ``ctrplan.plan_to_target`` does the same for one target in one call.

    python examples/plan_to_target.py [--quick] [--out DIR]
"""

import argparse

import ctrplan

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--quick", action="store_true", help="short time limit (used by the tests)")
parser.add_argument("--out", default=None, help="optional folder for plan.json (the first target's)")
args = parser.parse_args()

robot = ctrplan.load_robot("seed1")                      # three nitinol tubes (shipped)
scene = ctrplan.load_scene("airway")                     # trachea + main bronchi, mm
planner = ctrplan.Planner(robot, scene, "physics", ctrplan.PlannerConfig(objective="clearance"))
for target in scene.targets[:1 if args.quick else 3]:    # reachable example targets
    result = planner.plan(target.position, seed=0, time_limit=2.0 if args.quick else 5.0)
    print(f"{target.display}: {result.status.name}, tip error {result.tip_error_mm:.3f} mm, "
          f"min clearance {result.min_clearance_mm:.2f} mm, {len(result.path)} states")
    if args.out and target is scene.targets[0]:
        from pathlib import Path

        from ctrplan.io import write_json_atomic

        write_json_atomic(Path(args.out) / "plan.json", result.to_json())
