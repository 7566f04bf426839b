"""Every example in examples/ runs (quick mode) and prints what it promises."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"


def run_example(name: str, *args: str, timeout: int = 600) -> str:
    proc = subprocess.run([sys.executable, str(EXAMPLES / name), "--quick", *args],
                          capture_output=True, text=True, timeout=timeout)
    assert proc.returncode == 0, f"{name} failed:\n{proc.stderr[-3000:]}"
    return proc.stdout


def test_every_example_is_tested():
    here = Path(__file__).resolve().parent
    tested = set(re.findall(r'run_example\("([a-z_]+\.py)"', Path(__file__).read_text()))
    # examples run by the test module of their own feature (e.g. test_diagnose.py)
    others = "".join(p.read_text() for p in here.glob("test_*.py") if p.name != Path(__file__).name)
    tested |= {p.name for p in EXAMPLES.glob("*.py") if p.name in others}
    shipped = {p.name for p in EXAMPLES.glob("*.py")}
    assert shipped <= tested, f"examples without a test: {sorted(shipped - tested)}"


def test_plan_to_target(tmp_path):
    out = run_example("plan_to_target.py", "--out", str(tmp_path))
    assert re.search(r"SUCCESS, tip error 0\.\d+ mm", out), out
    assert (tmp_path / "plan.json").exists()


def test_learned_vs_physics():
    out = run_example("learned_vs_physics.py")
    m = re.search(r"\| learned \| ([\d.]+) \| ([\d.]+) \+- ([\d.]+) mm", out)
    assert m, out
    assert float(m.group(2)) < 3.0            # mean max deviation vs physics, mm
    speedup = float(re.search(r"speed-up of the learned model: (\d+)x", out).group(1))
    assert speedup >= 2


def test_calibrate_from_measurements(tmp_path):
    out = run_example("calibrate_from_measurements.py", "--out", str(tmp_path))
    assert "effects named: ['clearance']" in out, out
    before, after = map(float, re.search(r"error: ([\d.]+) mm -> ([\d.]+) mm", out).groups())
    assert after < 0.5 * before
    assert (tmp_path / "report.json").exists() and (tmp_path / "report.md").exists()


def test_custom_robot_and_mesh(tmp_path):
    out = run_example("custom_robot_and_mesh.py", "--out", str(tmp_path))
    assert (tmp_path / "lumen.stl").exists() and (tmp_path / "my_robot.yaml").exists()
    assert re.search(r"\d+ random configurations: \d+ collide", out), out
    assert "SUCCESS" in out, out


def test_offline_planning(tmp_path):
    out = run_example("offline_planning.py", "--out", str(tmp_path), "--workers", "2")
    assert re.search(r"\d+ jobs \(\d+ run now, 0 already done\)", out), out
    assert (tmp_path / "summary.csv").exists()
    again = run_example("offline_planning.py", "--out", str(tmp_path), "--workers", "2")
    assert re.search(r"(\d+) jobs \(0 run now, \1 already done\)", again), again
