"""Tip pose goals (issue 39, item 1): TipGoal, the tip tangent, the snap onto the anatomy, IK
with a cone, the command line.

Oracles: the foreign generator's own mechanics (``tests/foreign``, nothing of ctrplan) for the
tip tangent (a finite difference of its backbone at 0.05 mm spacing) and the tip position;
brute force over every triangle of the scene (Ericson's closest point on a triangle, written
here) for the snap; the scene's own ``scene.yaml`` base pose (read by the foreign re-check) for
frames.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from ctrplan.errors import ArgumentError, InputError
from ctrplan.planning.tipgoal import TipGoal, snap_to_surface, tip_frames
from tests.foreign.core import backbones
from tests.foreign.recheck import NOMINAL
from tests.foreign.recheck import load_scene as foreign_scene

#: foreign backbone points for its tip tangent: spacing <= 0.06 mm on seed1, so the last chord
#: is within kappa h / 2 < 0.002 deg of the tangent
FOREIGN_POINTS = 6001


def foreign_tip_frame(robot: str, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(tips (B, 3), unit tangents (B, 3)) in the robot base frame from the foreign generator:
    its tip point and the direction of its last chord."""
    pts = backbones(robot, np.atleast_2d(q), effects=NOMINAL, points=FOREIGN_POINTS)
    d = pts[:, -1] - pts[:, -2]
    return pts[:, -1], d / np.linalg.norm(d, axis=1, keepdims=True)


def angle(u, v) -> np.ndarray:
    u, v = np.atleast_2d(u), np.atleast_2d(v)
    c = np.sum(u * v, axis=1) / (np.linalg.norm(u, axis=1) * np.linalg.norm(v, axis=1))
    return np.degrees(np.arccos(np.clip(c, -1.0, 1.0)))


# ------------------------------------------------------------------ brute-force closest point
def closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """(T, 3) the closest point to p (3,) on each triangle (a, b, c) (T, 3) (Ericson, Real-Time
    Collision Detection, 5.1.5), vectorised over the triangles."""
    ab, ac, ap = b - a, c - a, p[None] - a
    d1, d2 = np.sum(ab * ap, 1), np.sum(ac * ap, 1)
    bp = p[None] - b
    d3, d4 = np.sum(ab * bp, 1), np.sum(ac * bp, 1)
    cp = p[None] - c
    d5, d6 = np.sum(ab * cp, 1), np.sum(ac * cp, 1)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        out = a + ab * (vb * denom)[:, None] + ac * (vc * denom)[:, None]          # inside
        t_ab = d1 / (d1 - d3)
        t_ac = d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    on_bc = (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0)
    out = np.where(on_bc[:, None], b + (c - b) * t_bc[:, None], out)
    on_ac = (vb <= 0) & (d2 >= 0) & (d6 <= 0)
    out = np.where(on_ac[:, None], a + ac * t_ac[:, None], out)
    on_ab = (vc <= 0) & (d1 >= 0) & (d3 <= 0)
    out = np.where(on_ab[:, None], a + ab * t_ab[:, None], out)
    out = np.where(((d6 >= 0) & (d5 <= d6))[:, None], c, out)
    out = np.where(((d3 >= 0) & (d4 <= d3))[:, None], b, out)
    out = np.where(((d1 <= 0) & (d2 <= 0))[:, None], a, out)
    return out


def brute_snap(scene, p: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """(distance, point, unit normal of the triangle up to sign) over every triangle."""
    best = (np.inf, None, None)
    for m in scene.collision_meshes:
        v, f = np.asarray(m.mesh.vertices, float), np.asarray(m.mesh.faces)
        a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
        q = closest_on_triangles(p, a, b, c)
        d = np.linalg.norm(q - p[None], axis=1)
        k = int(np.argmin(d))
        if d[k] < best[0]:
            n = np.cross(b[k] - a[k], c[k] - a[k])
            best = (float(d[k]), q[k], n / np.linalg.norm(n))
    return best


@pytest.mark.parametrize("name", ["airway", "skull_base"])
def test_snap_is_the_nearest_surface_point_by_brute_force(name):
    """trimesh's closest point equals brute force over all triangles (distance and point), its
    normal is the closest triangle's, and it points into the lumen: toward every named target
    (all inside the lumen), and the snapped point is where the target's ray meets the surface."""
    from ctrplan.collision.scene import load_scene

    scene = load_scene(name)
    rng = np.random.default_rng(7)
    for t in scene.targets[:4]:
        for p in (t.position, t.position + rng.normal(0, 1.5, 3)):
            snap = snap_to_surface(scene, p)
            d, q, n = brute_snap(scene, np.asarray(p, float))
            assert snap.distance_mm == pytest.approx(d, abs=1e-6)
            if d > 1e-6:    # the nearest point is unique away from the surface
                assert np.linalg.norm(snap.point - q) < 1e-5
            assert abs(abs(float(np.dot(snap.normal, n))) - 1.0) < 1e-6 or \
                np.linalg.norm(snap.point - q) < 1e-5      # an edge: either adjacent triangle
        snap = snap_to_surface(scene, t.position)
        toward = (t.position - snap.point) / snap.distance_mm
        assert float(np.dot(snap.normal, toward)) > 0.5, (name, t.name)


def test_tip_tangent_against_the_foreign_generator():
    """The tip tangent (second-order difference of 161 backbone points) agrees with the
    foreign mechanics' last chord at 0.05 mm spacing, within 0.1 deg on seed1."""
    from ctrplan.robot import load_robot
    from ctrplan.shape.models import load_model

    robot = load_robot("seed1")
    model = load_model("physics", robot)
    q = robot.sample(12, seed=3)
    tip, t, ok = tip_frames(model, q)
    ftip, ft = foreign_tip_frame("seed1", q)
    assert ok.all()
    assert np.max(np.linalg.norm(tip - ftip, axis=1)) < 0.05
    err = angle(t, ft)
    assert np.max(err) < 0.1, err
    # and the tangent is not trivially +z: the sample bends the tips by tens of degrees
    assert np.max(angle(t, np.array([0.0, 0.0, 1.0]))) > 10.0


def test_cone_ik_goals_point_within_the_cone():
    """Every IK solution solve_ik_cone reports within the cone points within it by the foreign
    generator's tip frame too, and reaches the target by its tip."""
    from ctrplan.planning import ik as _ik
    from ctrplan.robot import load_robot
    from ctrplan.shape.models import load_model

    robot = load_robot("seed1")
    model = load_model("physics", robot)
    q_true = robot.sample(6, seed=11)
    tips, tangents, _ = tip_frames(model, q_true)
    table = _ik.workspace_table(model, 2048)
    rng = np.random.default_rng(0)
    checked = 0
    for tip, tan in zip(tips, tangents):
        axis = tan + rng.normal(0, 0.15, 3)            # an axis ~10 deg off a reachable tangent
        axis /= np.linalg.norm(axis)
        cone = float(np.radians(15.0))
        res = _ik.solve_ik_cone(model, robot, tip, table.nearest(tip, 16), axis, cone)
        good = (res.error_mm <= 0.5) & (res.angle_deg <= 15.0)
        if not good.any():
            continue
        ftip, ft = foreign_tip_frame("seed1", res.q[good])
        assert np.all(np.linalg.norm(ftip - tip[None], axis=1) < 0.6)
        assert np.all(angle(ft, axis) <= 15.0 + 0.1), angle(ft, axis)
        checked += int(good.sum())
    assert checked >= 10


def test_tipgoal_checks_its_fields():
    g = TipGoal([1, 2, 3], direction=[0, 0, 2], standoff_mm=1.5)
    assert g.direction == (0.0, 0.0, 1.0) and g.cone_deg == 10.0
    assert np.allclose(g.point(), [1, 2, 1.5])          # back along the direction
    g = TipGoal([1, 2, 3], standoff_mm=2, normal=[1, 0, 0], direction=[0, 0, 1], cone_deg=20)
    assert np.allclose(g.point(), [3, 2, 3])            # along the normal when given
    for kw, field in ((dict(direction=[0, 0, 0]), "direction"), (dict(cone_deg=10), "cone_deg"),
                      (dict(direction=[0, 0, 1], cone_deg=95), "cone_deg"),
                      (dict(standoff_mm=-1, normal=[1, 0, 0]), "standoff_mm"),
                      (dict(standoff_mm=1.0), "standoff_mm"), (dict(normal=[np.nan, 0, 1]), "normal")):
        with pytest.raises(ArgumentError) as exc:
            TipGoal([0, 0, 100], **kw)
        assert exc.value.argument == field and "--" not in str(exc.value)
    with pytest.raises(ArgumentError) as exc:
        TipGoal([0, np.inf, 0])
    assert exc.value.argument == "position"
    from ctrplan.commands._names import for_command_line

    assert str(for_command_line(ArgumentError("direction", "x"))).startswith("--approach: ")
    assert isinstance(exc.value, InputError)


def test_a_goal_without_direction_or_standoff_is_the_point():
    """TipGoal(position) plans exactly what the point plans (the same path)."""
    import ctrplan

    scene = ctrplan.load_scene("airway")
    planner = ctrplan.Planner("seed1", scene, "physics")
    p = scene.find_target("t03").position
    a = planner.plan(p, seed=2, time_limit=10.0)
    b = planner.plan(TipGoal(p), seed=2, time_limit=10.0)
    assert a.status.value == "SUCCESS" and np.array_equal(a.path, b.path)
    assert a.to_json()["tip_goal"] is None and b.to_json()["tip_goal"]["position"] == list(map(float, p))


def test_cli_round_trip(tmp_path, capsys):
    """plan --target carina --standoff 2 --approach normal --cone 15: the snap is brute force's,
    the plan reaches the standoff point with its tip in the cone by the foreign generator's tip
    frame, and plan.json and the summary line say so."""
    from ctrplan.cli import main
    from ctrplan.collision.scene import load_scene

    out = tmp_path / "p.json"
    rc = main(["-q", "plan", "--scene", "airway", "--target", "carina", "--standoff", "2",
               "--approach", "normal", "--cone", "15", "--out", str(out)])
    line = capsys.readouterr().out
    plan = json.loads(out.read_text())
    assert rc == 0 and plan["status"] == "SUCCESS", line
    scene = load_scene("airway")
    d, q, n = brute_snap(scene, scene.find_target("carina").position)
    assert plan["snap_distance_mm"] == pytest.approx(d, abs=1e-6)
    assert plan["snap_mesh"] == "trachea" and "snapped" in line and "standoff 2.00 mm" in line
    normal = np.asarray(plan["tip_goal"]["normal"])
    assert np.allclose(plan["approach_direction"], -normal)
    assert np.allclose(plan["target"], q + 2.0 * normal, atol=1e-6)   # the standoff point
    fs = foreign_scene("airway")
    ftip, ft = foreign_tip_frame("seed1", np.asarray(plan["path"][-1]))
    R, o = fs.pose[:3, :3], fs.pose[:3, 3]
    tip_scene, t_scene = R @ ftip[0] + o, R @ ft[0]
    assert np.linalg.norm(tip_scene - np.asarray(plan["target"])) <= plan["tolerance_mm"]
    assert angle(t_scene, plan["approach_direction"])[0] <= 15.0
    assert abs(float(np.dot(tip_scene - q, normal)) - 2.0) < 0.2
    assert plan["direction_error_deg"] <= 15.0 and abs(plan["standoff_mm"] - 2.0) < 0.2
    assert angle(plan["tip_direction"], t_scene)[0] < 0.1
