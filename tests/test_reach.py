"""Reachability maps (issue 39, item 3): surface sampling, the map, resume, interrupt, outputs.

Oracles: closed-form areas and normals of a box lumen with a ball obstacle; trimesh's own
containment test (not ctrplan's ray parity) for the side of the shipped meshes; numpy's least
squares for the barycentric coordinates of a point in its triangle; the file system and exit
statuses for resume and interrupt; a real headless browser for the HTML view.
"""

from __future__ import annotations

import csv
import json
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from tests.browser import colour_fraction, find_chromium, non_background_fraction, screenshot

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = find_chromium()


# ---------------------------------------------------------------------------- sampling
def box_scene(obstacle: bool = True):
    """A closed 40 x 20 x 10 mm box lumen (centre 0) with a ball obstacle (radius 2) inside."""
    import trimesh

    from ctrplan.collision.scene import Scene, SceneMesh

    box = trimesh.creation.box(extents=(40.0, 20.0, 10.0))
    meshes = [SceneMesh("box", "wall", box, closed=True)]
    if obstacle:
        ball = trimesh.creation.icosphere(subdivisions=3, radius=2.0)
        ball.apply_translation((8.0, 0.0, 0.0))
        meshes.append(SceneMesh("ball", "obstacle", ball, closed=True))
    return Scene(name="box", path="", meshes=tuple(meshes), base_pose=np.eye(4), targets=(),
                 walls_closed=True)


def test_samples_follow_area_and_lie_on_their_triangles_with_normals_into_the_lumen():
    from ctrplan.collision.surface import sample_surface

    scene = box_scene()
    n = 3000
    s = sample_surface(scene, n, seed=3)
    assert len(s) == n and s.points.shape == (n, 3) and s.normals.shape == (n, 3)
    # each point on its recorded triangle: barycentric coordinates by least squares
    for name in ("box", "ball"):
        m = scene.mesh(name).mesh
        sel = s.mesh == name
        tri = np.asarray(m.vertices)[np.asarray(m.faces)[s.face[sel]]]
        for p, t in zip(s.points[sel][:300], tri[:300]):
            A = np.vstack([t.T, np.ones(3)])
            lam, *_ = np.linalg.lstsq(A, np.append(p, 1.0), rcond=None)
            assert np.all(lam >= -1e-9) and np.allclose(A @ lam, np.append(p, 1.0), atol=1e-9)
    # area weights: the ball's share, and the box's faces by their closed-form areas
    ball_area = float(scene.mesh("ball").mesh.area)
    areas = {0: 2 * 20 * 10, 1: 2 * 40 * 10, 2: 2 * 40 * 20}       # faces normal to x, y, z
    total = sum(areas.values()) + ball_area
    on_ball = s.mesh == "ball"
    for k, count in [("ball", on_ball.sum())] + [
            (ax, np.sum(~on_ball & (np.abs(s.normals[:, ax]) > 0.999))) for ax in areas]:
        p = (ball_area if k == "ball" else areas[k]) / total
        sigma = np.sqrt(n * p * (1 - p))
        assert abs(count - n * p) < 4 * sigma, (k, count, n * p)
    # normals into the lumen: on the box, the inward face normal; on the ball, outward
    box = ~on_ball
    axis = np.argmax(np.abs(s.normals[box]), axis=1)
    inward = -np.sign(s.points[box][np.arange(box.sum()), axis])
    assert np.allclose(s.normals[box][np.arange(box.sum()), axis], inward)
    radial = s.points[on_ball] - np.array([8.0, 0.0, 0.0])
    radial /= np.linalg.norm(radial, axis=1, keepdims=True)
    assert np.all(np.sum(radial * s.normals[on_ball], axis=1) > 0.95)


def test_same_seed_same_points_and_a_region_stays_near_its_points():
    from ctrplan.collision.surface import sample_surface

    scene = box_scene(obstacle=False)
    a = sample_surface(scene, 50, seed=1)
    assert np.array_equal(a.points, sample_surface(scene, 50, seed=1).points)
    assert not np.allclose(a.points, sample_surface(scene, 50, seed=2).points)
    near = np.array([[20.0, 0.0, 0.0]])            # the centre of the box's +x face
    r = sample_surface(scene, 400, seed=0, near=near, radius_mm=6.0)
    d = np.linalg.norm(r.points - near, axis=1)
    assert np.all(d <= 6.0 + 1e-9)
    # within 5 mm of the centre of the face x = 20 (10 mm high) the region is a whole disc of
    # that face: uniform on it, the fraction within 2.5 mm is (2.5 / 5)^2
    whole = d < 5.0
    assert np.allclose(r.points[whole, 0], 20.0) and whole.sum() > 200
    frac = np.mean(d[whole] <= 2.5)                 # (2.5 / 5)^2 = 0.25 of the disc of radius 5
    assert abs(frac - 0.25) < 4 * np.sqrt(0.25 * 0.75 / whole.sum())


def test_shipped_normals_point_into_the_lumen_by_trimesh_containment():
    """skull_base: the corridor is one closed mesh, the vessels closed obstacles; trimesh's
    containment (not ctrplan's ray parity) says which side of each point is the lumen."""
    from ctrplan.collision.scene import load_scene
    from ctrplan.collision.surface import sample_surface

    scene = load_scene("skull_base")
    s = sample_surface(scene, 120, seed=0, near=scene.target_positions(), radius_mm=25.0)
    corridor = scene.mesh("nasal_corridor").mesh
    inside = corridor.contains(s.points + 0.3 * s.normals)
    outside = ~corridor.contains(s.points - 0.3 * s.normals)
    on_wall = s.mesh == "nasal_corridor"
    assert inside.all()
    assert outside[on_wall].all()
    for m in scene.meshes:
        if m.role == "obstacle":
            assert not m.mesh.contains(s.points + 0.3 * s.normals).any()


# ---------------------------------------------------------------------------- the map
def _settings(**kw):
    from ctrplan.planning.reach import ReachSettings

    # a time cap far above what these plans take: the search budget (a count) decides, so a
    # rerun decides a point as the first run did whatever the load
    return ReachSettings(**{"scene": "skull_base", "time_limit": 10.0, **kw})


@pytest.fixture(scope="module")
def small_map(tmp_path_factory):
    from ctrplan.collision.scene import load_scene
    from ctrplan.collision.surface import sample_surface
    from ctrplan.planning.reach import reach_map

    scene = load_scene("skull_base")
    samples = sample_surface(scene, 20, seed=0, near=scene.target_positions(), radius_mm=20.0)
    out = tmp_path_factory.mktemp("reach") / "map"
    return samples, out, reach_map(_settings(), samples, out)


def _csv(path: Path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def test_map_rows_are_the_plans_and_screen(small_map):
    from ctrplan.planning.reach import COLUMNS, NO_POSE

    samples, out, summary = small_map
    rows = _csv(out / "reach.csv")
    assert tuple(rows[0].keys()) == COLUMNS and len(rows) == 20
    assert summary.screened_out + summary.planned == 20 and summary.planned > 0
    for r, p, n in zip(rows, samples.points, samples.normals):
        assert np.allclose([float(r[c]) for c in "xyz"], p)
        goal = np.array([float(r[f"goal_{c}"]) for c in "xyz"])
        assert np.allclose(goal, p + 2.0 * n)                       # the standoff along the normal
        if r["reachable"] == "1":                                   # a plan that put the tip there
            assert r["status"] == "SUCCESS" and float(r["tip_error_mm"]) <= 1.0
            assert float(r["clearance_mm"]) >= 0.0
        if r["screen"] == "0":
            assert r["status"] == NO_POSE and r["reachable"] == "0" and r["tip_error_mm"] == ""


def test_a_reachable_point_is_reached_by_its_recorded_plan(small_map):
    """Re-plan one reachable point through the public API: the tip ends within the tolerance
    of the standoff point (measured here from the plan's own tip path)."""
    import ctrplan
    from ctrplan.planning.tipgoal import TipGoal

    samples, out, summary = small_map
    rows = [r for r in summary.rows if r["reachable"]]
    if not rows:
        pytest.skip("no reachable point in this sample")
    r = rows[0]
    k = r["point"]
    res = ctrplan.Planner("seed1", "skull_base").plan(
        TipGoal(position=samples.points[k], normal=samples.normals[k], standoff_mm=2.0),
        seed=0, time_limit=10.0)
    goal = samples.points[k] + 2.0 * samples.normals[k]
    assert res.status.value == "SUCCESS"
    assert np.linalg.norm(np.asarray(res.tip_path)[-1] - goal) <= 1.0


def test_rerun_resumes_only_what_is_left_and_refuses_an_edited_file(small_map, tmp_path):
    import shutil

    from ctrplan.errors import InputError
    from ctrplan.planning.reach import reach_map

    samples, out, first = small_map
    folder = tmp_path / "map"
    shutil.copytree(out, folder)
    before = (folder / "reach.csv").read_text()
    again = reach_map(_settings(), samples, folder)
    assert (again.skipped, again.screened_out, again.planned) == (20, 0, 0)
    files = sorted((folder / "points").iterdir())
    assert len(files) == 20
    gone = files[:3]
    for f in gone:
        f.unlink()
    (folder / "points" / ".p00001__x.json.abc.tmp").write_text("{")   # a killed run's temporary
    third = reach_map(_settings(), samples, folder)
    assert third.skipped == 17 and third.screened_out + third.planned == 3
    assert not any(p.name.startswith(".") for p in (folder / "points").iterdir())

    def strip(text):   # planning times differ between runs
        rows = list(csv.DictReader(text.splitlines()))
        return [{k: v for k, v in r.items() if k != "planning_time_s"} for r in rows]

    assert strip((folder / "reach.csv").read_text()) == strip(before)
    # another setting is another point id: a map with it decides every point again
    from ctrplan.planning.reach import point_id

    p, n = samples.points[0], samples.normals[0]
    ids = {point_id(s, 0, p, n) for s in (_settings(), _settings(standoff_mm=3.0),
                                          _settings(approach="normal", cone_deg=30.0), _settings(seed=1))}
    assert len(ids) == 4
    # an edited point file is refused, naming the file and field
    f = files[5]
    data = json.loads(f.read_text())
    data["reachable"] = not data["reachable"]
    f.write_text(json.dumps(data))
    with pytest.raises(InputError, match=r"reachable") as exc:
        reach_map(_settings(), samples, folder)
    assert f.name in str(exc.value)


def test_settings_are_checked():
    from ctrplan.errors import ArgumentError

    with pytest.raises(ArgumentError, match="cone_deg"):
        _settings(approach="normal")
    with pytest.raises(ArgumentError, match="cone_deg"):
        _settings(approach="normal", cone_deg=120.0)
    with pytest.raises(ArgumentError, match="approach"):
        _settings(approach="1,0", cone_deg=10.0)
    with pytest.raises(ArgumentError, match="standoff_mm"):
        _settings(standoff_mm=-1.0)


# ---------------------------------------------------------------------------- the command
def _cli(*args, cwd: Path, **kw):
    import os

    env = dict(os.environ, PYTHONPATH=str(ROOT), OMP_NUM_THREADS="1")
    env.pop("PYTEST_CURRENT_TEST", None)
    return subprocess.Popen([sys.executable, "-m", "ctrplan.cli", "-q", "scene", "reach", *args],
                            cwd=cwd, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            start_new_session=True, **kw)


@pytest.fixture(scope="module")
def cli_map(tmp_path_factory):
    cwd = tmp_path_factory.mktemp("cli")
    p = _cli("--scene", "skull_base", "--points", "12", "--near-targets", "--time", "1",
             "--out", "m", cwd=cwd)
    out, err = p.communicate(timeout=600)
    assert p.returncode == 0, err.decode()
    return cwd / "m", out.decode()


def test_command_writes_csv_html_png(cli_map):
    out, stdout = cli_map
    assert "points reachable" in stdout
    rows = _csv(out / "reach.csv")
    assert len(rows) == 12
    png = (out / "reach.png").read_bytes()
    assert png[:8] == b"\x89PNG\r\n\x1a\n"
    html = (out / "reach.html").read_text()
    assert "<script src=\"http" not in html and "plotly" in html.lower()


@pytest.mark.skipif(CHROMIUM is None, reason="no Chromium installed")
def test_reach_html_renders_offline_in_a_real_browser(cli_map, tmp_path):
    from ctrplan.commands.reach import NO_POSE_COLOUR

    out, _ = cli_map
    png = tmp_path / "shot.png"
    requests = screenshot(out / "reach.html", png, CHROMIUM)
    assert requests == [], f"the reach view tried to load external URLs: {requests}"
    assert non_background_fraction(png) > 0.05, "the 3-D view looks blank"
    rows = _csv(out / "reach.csv")
    if any(r["screen"] == "0" for r in rows):
        assert colour_fraction(png, NO_POSE_COLOUR, tol=30) > 1e-5, "the points are not drawn"


def test_command_bad_input_is_one_line_exit_2(tmp_path):
    for args, word in ((["--scene", "nowhere"], "nowhere"),
                       (["--scene", "skull_base", "--approach", "normal"], "--cone"),
                       (["--scene", "skull_base", "--region", "nosuch"], "--region")):
        p = _cli(*args, "--out", "x", cwd=tmp_path)
        _, err = p.communicate(timeout=120)
        err = err.decode()
        assert p.returncode == 2, err
        assert "Traceback" not in err and word in err
        assert len([ln for ln in err.splitlines() if ln.strip()]) == 1
    assert not (tmp_path / "x" / "reach.csv").exists()


def _interrupt_once(args, cwd: Path, sig: int, points: Path, after: int) -> set[str] | None:
    """Run the command, send ``sig`` to its process group once ``after`` more point files
    exist; None when it finished first. Checks exit 128 + sig, no traceback, no map."""
    import os
    import time

    def count() -> int:
        return len(list(points.glob("p*.json"))) if points.exists() else 0

    before = count()
    p = _cli(*args, cwd=cwd)
    deadline = time.monotonic() + 240
    while time.monotonic() < deadline and p.poll() is None and count() < before + after:
        time.sleep(0.05)
    # the screen writes the points it rules out in one burst, just before the pool starts; a
    # file after the burst comes from the pool, so the signal below lands while the pool plans
    # (a Ctrl-C while workers start is tested in test_interrupt.py)
    burst = count()
    while time.monotonic() < deadline and p.poll() is None and count() <= burst:
        time.sleep(0.05)
    if p.poll() is not None:
        p.communicate()
        return None
    os.killpg(p.pid, sig)
    _, err = p.communicate(timeout=120)
    err = err.decode()
    assert p.returncode == 128 + sig, err
    assert "Traceback" not in err
    from tests.test_interrupt import survivors

    assert survivors(p.pid) == []                               # no worker left behind
    for name in ("reach.csv", "reach.html", "reach.png"):
        assert not (cwd / "m" / name).exists()
    done = {f.name for f in points.iterdir()}
    assert not any(n.startswith(".") for n in done), done       # no temporary left
    for f in points.iterdir():
        json.loads(f.read_text())                               # complete files only
    return done


def test_interrupted_map_exits_130_or_143_leaves_no_map_and_resumes(tmp_path):
    """SIGINT (to the group, as Ctrl-C) while the pool plans, then SIGTERM on the resumed run,
    then a run that finishes with the points of the two before it already done."""
    args = ("--scene", "skull_base", "--points", "20", "--near-targets", "--time", "10",
            "--ik-seeds", "8", "--workers", "2", "--out", "m")
    points = tmp_path / "m" / "points"
    first = _interrupt_once(args, tmp_path, signal.SIGINT, points, after=2)
    if first is None:
        pytest.skip("the map finished before it could be interrupted")
    second = _interrupt_once(args, tmp_path, signal.SIGTERM, points, after=1)
    done = second if second is not None else {f.name for f in points.iterdir()}
    assert first <= done
    p = _cli(*args, cwd=tmp_path)
    out, err = p.communicate(timeout=600)
    assert p.returncode == 0, err.decode()
    if second is not None:
        assert f"{len(done)} were already done" in out.decode()
    assert len(_csv(tmp_path / "m" / "reach.csv")) == 20
