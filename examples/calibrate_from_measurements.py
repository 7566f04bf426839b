"""The sim-vs-measured workflow end to end on seed1.

Simulate "measurements" of the three-tube robot with a hidden effect (a clearance tilt where the
outer tubes end, plus sensor noise), run ``diagnose`` on them with the traditional (rigid) model,
and print which effect it names, the fitted parameter and how much the held-out error shrinks.
The calibrated model is written next to the report and works with every other command
(``ctrplan shape/check/plan --model <out>/calibrated.yaml``).

    python examples/calibrate_from_measurements.py [--quick] [--out DIR]
"""

import argparse
import tempfile
from pathlib import Path

import ctrplan
from ctrplan.calibration.simulate import design, simulate
from ctrplan.shape.models import load_model

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--quick", action="store_true", help="fewer rows (used by the tests)")
parser.add_argument("--out", default=None, help="report folder (default: a temporary folder)")
args = parser.parse_args()
out = Path(args.out or tempfile.mkdtemp(prefix="ctrplan_calibrate_"))

robot = ctrplan.load_robot("seed1")
# Random back-and-forth trajectories, 4 sweeps (fewer than 8: every sweep is cut into fit,
# validation and test blocks; with 8 or more, whole sweeps are held out).
q, sweep = design(robot, ["random_walk"], rows=160 if args.quick else 400, sweeps=4, seed=1)
hidden = {"clearance": {"length": 20.0, "limit": 0.05}}
data = simulate(robot, q, hidden, base="rigid", sweep=sweep, noise_mm=0.1, seed=1)

report = ctrplan.diagnose(robot, data, base="rigid", out=out)
print(f"hidden: {hidden}")
print(f"conclusion: {report.conclusion}")
print(f"effects named: {report.effects}  parameters: {report.parameters}")
print(f"held-out mean tip error: {report.error_before_mm:.2f} mm -> {report.error_after_mm:.2f} mm")
print(f"report: {out / 'report.md'}")

calibrated = [p for p in out.iterdir() if p.suffix == ".yaml"]
if calibrated:
    model = load_model(str(calibrated[0]), robot)
    print(f"calibrated model {calibrated[0].name}: {model.name}, tip of q[0] = {model.backbone(q[:1])[0, -1].round(2)} mm")
