"""The fixed hard benchmark and the independent re-check of plans.

Oracles: the re-check (``benchmarks/hard_problems.verify_path`` -> ``tests/foreign/recheck.py``)
shares no code with ctrplan (foreign mechanics, exact FCL cylinders, its own interpolation); it
is itself checked here against closed forms (a straight tube in a cylindrical wall: clearance and
penetration depth) and against ctrplan's physics backbone (two independent implementations of
the same equations); the benchmark logs are read back with OMPL's own log reader
(``ompl.tools.readBenchmarkLog``).
"""

from __future__ import annotations

import sqlite3
import sys
from pathlib import Path

import numpy as np
import pytest

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))

from bench_hard import PLANNERS, RUN_PROPERTIES, run, write_log  # noqa: E402
from hard_problems import load_problems, scenes, verify_path  # noqa: E402

from ctrplan.planning.plan import scene_by_name  # noqa: E402
from ctrplan.shape.physics import PhysicsModel  # noqa: E402


def test_every_scene_has_hard_problems():
    names = scenes()
    assert set(names) >= {"airway", "bronchial_tree", "neuro", "skull_base"}
    for s in names:
        assert len(load_problems(s)) >= 2, s


@pytest.mark.parametrize("scene", ["airway", "bronchial_tree", "neuro", "skull_base"])
def test_hard_problem_straight_edge_collides_and_known_solution_is_free(scene, seed1):
    prob = load_problems(scene)[0]
    sc = scene_by_name(scene)
    straight, _ = verify_path(seed1, sc, np.stack([prob.start, prob.goal]), clearance=False)
    assert not straight
    free, _ = verify_path(seed1, sc, prob.solution, factor=1, clearance=False)
    assert free
    assert np.allclose(prob.solution[0], prob.start)
    tip = PhysicsModel(seed1).shape(prob.solution[-1:], points=2).tip[0]
    assert np.linalg.norm(sc.to_scene(tip[None])[0] - prob.target) <= 1.0 + 1e-6


def test_benchmark_log_is_read_by_ompls_reader(tmp_path):
    import ompl.tools as ot

    recs = [{"problem": "p", "scene": "airway", "model": "physics", "planner": p, "seed": s,
             "status": "SUCCESS" if s == 0 else "TIMEOUT", "success": s == 0, "time": 1.5 + s,
             "states_validated": 1000, "time_cap_hit": s == 1, "direct": False,
             **({"length": 120.0, "segments": 3, "clearance": 0.4, "clearance_exact": True,
                 "clearance_physics": 0.3, "recheck_free": True, "recheck_clearance": 0.31,
                 "tip_error_physics": 0.5} if s == 0 else {})}
            for p in ("rrtconnect", "prm") for s in (0, 1)]
    log = tmp_path / "x.log"
    write_log(log, "ctrplan_test", recs, ["rrtconnect", "prm"], 10.0, 2, 3.0, "setup text")
    db = tmp_path / "x.db"
    ot.readBenchmarkLog(str(db), [str(log)], False)
    con = sqlite3.connect(db)
    assert con.execute("select count(*) from experiments").fetchone()[0] == 1
    rows = con.execute("select p.name, r.solved, r.time, r.solution_length, r.plan_status "
                       "from runs r join plannerConfigs p on r.plannerid = p.id order by r.id").fetchall()
    assert [r[0] for r in rows] == ["geometric_rrtconnect"] * 2 + ["geometric_prm"] * 2
    assert [r[1] for r in rows] == [1, 0, 1, 0] and rows[0][2] == 1.5 and rows[0][3] == 120.0
    assert rows[1][3] is None and rows[1][4] == 5           # TIMEOUT's enum index
    cols = {c[1] for c in con.execute("pragma table_info(runs)")}
    assert {"_".join(n.split()) for n, _ in RUN_PROPERTIES} <= cols


# ----------------------------------------------------------------------------- the re-check itself
def _straight_robot():
    tubes = [{"od": od, "id": od - 0.3, "straight_length": sl, "curved_length": 40.0, "curvature": 0.0,
              "youngs_modulus": 60000.0, "poisson_ratio": 0.33}
             for od, sl in ((1.3, 240.0), (1.9, 160.0), (2.5, 90.0))]
    return {"name": "straight", "tubes": tubes}


def _wall_scene(tmp_path, radius: float, dx: float):
    """A cylindrical wall (512 sides, open ends) of ``radius`` around the line x = dx, y = 0."""
    import trimesh
    import yaml

    m = trimesh.creation.cylinder(radius=radius, height=400.0, sections=512)
    keep = np.abs(m.face_normals[:, 2]) < 0.5                   # the side only
    side = trimesh.Trimesh(m.vertices, m.faces[keep], process=False)
    side.apply_translation([dx, 0.0, 150.0])
    side.export(tmp_path / "wall.ply")
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump({
        "name": "tube", "units": "mm", "meshes": [{"name": "wall", "file": "wall.ply", "role": "wall"}],
        "base_pose": {"position": [0.0, 0.0, 0.0], "quaternion": [1.0, 0.0, 0.0, 0.0]}}))
    return tmp_path


@pytest.mark.parametrize("dx, clearance", [(3.0, 0.75), (4.5, -0.75), (4.0, -0.25)])
def test_recheck_clearance_and_depth_match_closed_form(tmp_path, dx, clearance):
    """Straight tubes (outer radius 1.25 mm at the base) along the z axis inside a wall of radius
    5 mm whose axis is dx away: clearance 5 - dx - 1.25 (negative: penetration depth), within the
    polygon's sag (1e-4 mm) and the depth bisection's resolution."""
    from tests.foreign.recheck import DEPTH_TOL_MM, recheck_path

    scene = _wall_scene(tmp_path, 5.0, dx)
    q = np.array([[0.0, 0.0, 0.0, -200.0, -120.0, -50.0], [0.05, -0.05, 0.02, -199.0, -119.5, -49.5]])
    rep = recheck_path(_straight_robot(), str(scene), q)
    assert len(rep.edge) >= 11 and rep.states[0, 0] == 0.0
    assert rep.min_clearance_mm == pytest.approx(clearance, abs=DEPTH_TOL_MM + 2e-4)
    if clearance > 0:
        assert rep.free and rep.penetrating(0.0) == 0
    else:
        assert not rep.free and set(rep.contact) == {"wall"} and not rep.crosses.any()
        # every state is equally deep (straight tubes, the outer one always inside the wall)
        assert rep.penetrating(-clearance + 0.01) == 0
        assert rep.penetrating(-clearance - 0.01) == len(rep.edge)


def test_recheck_interpolates_unwrapped_rotations_densely():
    """plan.json rotations are unwrapped: from 3.0 to -3.0 rad the motion passes through 0."""
    from tests.foreign.recheck import densify, directions

    path = np.array([[3.0, 0.0, 0.0, -100.0, -60.0, -30.0], [-3.0, 0.0, 0.0, -100.0, -60.0, -30.0],
                     [-3.0, 0.0, 0.0, -99.9, -60.0, -30.0]])
    st, edge = densify(path, 3)
    assert np.sum(edge == 0) >= 10 and np.sum(edge == 1) >= 10
    assert np.min(np.abs(st[edge == 0, 0])) < 0.05              # passes alpha = 0, not pi
    assert np.max(np.abs(np.diff(st[:, 0]))) <= 0.25 / 30.0 + 1e-12
    d = directions(st, edge, path)
    assert (d[edge == 0, 0] == -1).all() and (d[edge == 1, 3] == 1).all()


def test_recheck_backbone_agrees_with_ctrplan_physics(seed1):
    """Two independent implementations of the compliant rod (foreign numpy shooting vs ctrplan's
    kernel): the re-check's backbone and ctrplan's agree to 1e-3 mm."""
    from tests.foreign.recheck import backbone
    from tests.foreign.robot import load_spec

    q = seed1.sample(20, seed=3)
    P, radius, ok = backbone(load_spec("seed1"), q, points=500)
    assert ok.all() and P.shape[1] == 502 and set(np.unique(radius)) <= {0.65, 0.95, 1.25}
    ref = PhysicsModel(seed1).shape(q, points=500).points
    assert np.max(np.linalg.norm(P[:, -1] - ref[:, -1], axis=1)) < 1e-3


@pytest.mark.statistical
def test_best_planner_solves_the_hard_set_and_every_plan_passes_the_recheck(tmp_path):
    """RRTConnect on the README's hard set (first 2 problems per scene), 10 s cap: with the
    physics planning model >= 95 % success (the README's threshold); with the learned planning
    model at margin 0 (the unsafe setting: only the physics re-check stands between it and the
    anatomy) any success is allowed, but every successful path of both must be collision-free
    in the independent re-check. About 4 min on one core."""
    phys = run(["physics"], ["rrtconnect"], 1, 10.0, 2, tmp_path / "physics")
    learned = run(["learned"], ["rrtconnect"], 1, 10.0, 2, tmp_path / "learned", margin=0.0)
    assert len(phys["problems"]) == 8
    assert phys["table"][0]["success_rate"] >= 0.95, phys["table"]
    for res in (phys, learned):
        ok = [r for r in res["records"] if r["success"]]
        assert all(r["recheck_free"] for r in ok)
        assert all(r["recheck_clearance"] >= 0 for r in ok)
    assert len(list((tmp_path / "physics").glob("*/*.log"))) == 8
    assert "rrtconnect" in PLANNERS


@pytest.mark.statistical
@pytest.mark.parametrize("model", ["learned", "physics"])
def test_shipped_targets_plans_pass_the_recheck(model, seed1):
    """Two shipped targets per scene (the shipped benchmark set), margin 0 (the setting that
    leans most on the re-check), every successful plan re-checked."""
    from ctrplan.collision.scene import list_scenes
    from ctrplan.planning import PlanConfig, plan_to_target

    done = 0
    for s in list_scenes():
        sc = scene_by_name(s)
        for t, seed in ((sc.targets[0], 0), (sc.targets[len(sc.targets) // 2], 1)):
            r = plan_to_target(seed1, sc, t.position, model=model, seed=seed, time_limit=10.0,
                               config=PlanConfig(margin_mm=0.0))
            if r.success:
                free, _ = verify_path(seed1, sc, r.path, clearance=False)
                assert free, (s, t.name, model)
                done += 1
    assert done >= 4


def test_recheck_smallest_clearance_is_the_brute_force_minimum(seed1):
    """The re-check asks FCL for every group of every state only on its anchors and elsewhere
    prunes groups by how far they can have moved: on a known solution's first edges (airway),
    its smallest clearance equals brute force (every fine cylinder group of every state asked),
    and each state's value is a lower bound of that state's brute-force distance."""
    import tests.foreign.recheck as R

    prob = load_problems("airway")[0]
    path = prob.solution[:4]
    rep = R.recheck_path(seed1.to_dict(), "airway", path)
    spec = R.load_spec(seed1.to_dict())
    sc = R.load_scene("airway")
    world = R._Scene(sc)
    P, rad, ok = R.backbone(spec, rep.states, None, None, 600)
    assert ok.all() and rep.free and len(rep.states) > 3 * R.STRIDE
    brute = np.array([min(world._dist_objs(R._tube_objects(sc.to_scene(P[k]), rad[k], 0.0, g))
                          for g in np.array_split(np.arange(len(rad[k])), len(rad[k]) // 40))
                      for k in range(len(P))])
    assert rep.min_clearance_mm == pytest.approx(brute.min(), abs=1e-9)
    assert np.all(rep.clearance_mm <= brute + 1e-9)
