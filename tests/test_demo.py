"""The demo (`make demo` / `ctrplan demo`) and its views.

The demo runs once per module; its outputs are checked, and its interactive HTML view is opened
in a real browser: it must render and load nothing from the network.

Uses Debian's headless Chromium (``.ci/run`` installs it when missing); skipped only when no
browser is available. A recording proxy on loopback catches every URL the page tries to load.
"""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
import trimesh

from ctrplan import viz
from tests.browser import colour_fraction, find_chromium, non_background_fraction, screenshot

CHROMIUM = find_chromium()
needs_browser = pytest.mark.skipif(CHROMIUM is None, reason="no Chromium installed")


@pytest.fixture(scope="module")
def demo_outputs(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    # how long it takes is measured by benchmarks/bench_release.py, not asserted here
    proc = subprocess.run([sys.executable, "-m", "ctrplan.cli", "demo", "--out", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-2000:]
    return out, proc.stdout


def test_demo_writes_what_it_names(demo_outputs):
    out, stdout = demo_outputs
    for name in ("plan.json", "demo.png", "demo.html"):
        assert (out / name).exists() and (out / name).stat().st_size > 0, name
        assert str(out / name) in stdout
    plan = json.loads((out / "plan.json").read_text())
    for key in ("success", "status", "path", "tip_path", "tip_error_mm", "planning_time_s",
                "min_clearance_mm", "planner", "seed", "robot", "model", "scene"):
        assert key in plan, key
    assert plan["success"] is True and plan["status"] == "SUCCESS"
    assert plan["tip_error_mm"] <= 1.0
    assert plan["min_clearance_mm"] >= 0.0
    assert plan["robot"] == "seed1" and plan["model"] == "physics"
    assert "status SUCCESS" in stdout


def test_view_command_renders_the_plan(demo_outputs, tmp_path):
    from ctrplan.cli import main

    out, _ = demo_outputs
    assert main(["view", str(out / "plan.json"), "--out", str(tmp_path / "v.png")]) == 0
    assert non_background_fraction(tmp_path / "v.png") > 0.05
    assert main(["view", str(tmp_path / "missing.json"), "--out", str(tmp_path / "w.html")]) == 2
    assert not (tmp_path / "w.html").exists()


@needs_browser
def test_recording_proxy_catches_external_url(tmp_path):
    """Control: a page that references an external script IS caught by the proxy."""
    html = tmp_path / "ext.html"
    html.write_text('<html><body><h1>x</h1><script src="http://example.invalid/x.js"></script></body></html>')
    requests = screenshot(html, tmp_path / "ext.png", CHROMIUM, budget_ms=3000)
    assert any("example.invalid" in r for r in requests), requests


@needs_browser
def test_synthetic_view_renders_offline(tmp_path):
    tube = trimesh.creation.cylinder(radius=12.0, height=120.0, sections=24)
    meshes = [viz.ViewMesh("lumen", "wall", np.asarray(tube.vertices), np.asarray(tube.faces))]
    s = np.linspace(0, 1, 20)
    backbones = np.stack([np.stack([8 * k / 5 * s**2, 0 * s, -50 + 100 * s], axis=1) for k in range(6)])
    html = tmp_path / "view.html"
    viz.plan_html(html, meshes, backbones, backbones[:, -1], backbones[-1, -1], title="synthetic")
    png = tmp_path / "view.png"
    requests = screenshot(html, png, CHROMIUM)
    assert requests == []
    assert non_background_fraction(png) > 0.05
    # the robot (drawn in ROBOT_COLOUR) is visible in the WebGL canvas
    assert colour_fraction(png, viz.ROBOT_COLOUR, tol=45) > 1e-4


@needs_browser
def test_demo_html_renders_offline(demo_outputs, tmp_path):
    html = demo_outputs[0] / "demo.html"
    assert html.exists()
    png = tmp_path / "demo_shot.png"
    requests = screenshot(html, png, CHROMIUM)
    assert requests == [], f"the demo page tried to load external URLs: {requests}"
    assert non_background_fraction(png) > 0.05, "the 3-D view looks blank"
    assert colour_fraction(png, viz.ROBOT_COLOUR, tol=45) > 1e-4, "the robot is not visible"
