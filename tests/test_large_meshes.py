"""Large meshes within a budget: the lean exact backend agrees with FCL; the work estimate
refuses up front what exceeds the budget, naming --max-mb.

Oracles: FCL (python-fcl, a separate implementation) for verdicts and distances; brute-force
sampling of the segment and triangle for the closed-form segment-triangle distance. The
5-million-triangle measurement (time and peak memory of ``ctrplan check``) lives in
benchmarks/bench_large_mesh.py, not here.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import yaml

from ctrplan import cli
from ctrplan.collision._fcl import FclMeshes
from ctrplan.collision._grid import GridMeshes, seg_tri_d2
from ctrplan.collision.scene import load_scene
from ctrplan.collision.world import CollisionWorld
from ctrplan.shape.physics import PhysicsModel


def test_segment_triangle_distance_against_brute_force():
    """Closed-form distance vs a dense sampling of segment x triangle (which can only
    overstate it, by at most the sampling's covering radius)."""
    rng = np.random.default_rng(3)
    u = np.linspace(0.0, 1.0, 41)
    a_, b_ = np.meshgrid(u, u, indexing="ij")
    keep = a_ + b_ <= 1.0
    bary = np.stack([a_[keep], b_[keep]], axis=1)
    for _ in range(300):
        tri = rng.normal(0, 3.0, (3, 3))
        p, q = rng.normal(0, 4.0, (2, 3))
        if rng.random() < 0.2:
            q = p.copy()
        d = np.sqrt(seg_tri_d2(p, q, tri[0], tri[1], tri[2]))
        tp = tri[0] + bary[:, :1] * (tri[1] - tri[0]) + bary[:, 1:] * (tri[2] - tri[0])
        sp = p + u[:, None] * (q - p)
        brute = np.sqrt(((sp[:, None] - tp[None]) ** 2).sum(-1).min())
        edge = max(np.linalg.norm(tri[i] - tri[(i + 1) % 3]) for i in range(3)) / 40
        assert d <= brute + 1e-9
        assert brute - d <= edge + np.linalg.norm(q - p) / 40 + 1e-9


def test_grid_backend_agrees_with_fcl_on_random_capsules():
    """1,800 random capsules (and spheres) in and around the airway's trachea and a sphere:
    the same first hit; distances within FCL's GJK tolerance (1e-3 mm, EPS_MM, plus 0.3 % of
    the distance far away: measured 0.011 mm at 5 mm, where the grid's value equals the
    minimum over all triangles)."""
    m = trimesh.load(str(load_scene("airway").path) + "/trachea.ply", process=False)
    ball = trimesh.creation.icosphere(subdivisions=2, radius=5.0)
    ball.apply_translation([0.0, 600.0, 20.0])
    grid, fcl = GridMeshes([m, ball]), FclMeshes([m, ball])
    rng = np.random.default_rng(0)
    lo, hi = m.bounds
    hits = 0
    for _ in range(600):
        a = rng.uniform(lo, hi, (3, 3))
        b = a + rng.normal(0, 5.0, (3, 3))
        if rng.random() < 0.3:
            b = a.copy()
        r = rng.uniform(0.2, 2.0, 3)
        h = grid.first_hit(a, b, r)
        assert h == fcl.first_hit(a, b, r)
        hits += h >= 0
        for k in range(3):
            dg = grid.pair_distance(a[k], b[k], r[k], 0)
            df = fcl.pair_distance(a[k], b[k], r[k], 0)
            assert (dg < 0) == (df < 0)
            if dg >= 0:     # FCL's GJK distance is approximate: 1e-3 mm near, 0.3 % far
                assert abs(dg - df) < 1e-3 + 3e-3 * dg
    assert 120 < hits < 540


def test_grid_backend_distance_far_from_a_small_mesh():
    """A capsule hundreds of mm from a small mesh (farther than the mesh's diagonal plus the
    capsule's length): the grid backend's widening search still reaches it, the distance FCL's
    (it used to stop and report inf, a clearance above the truth)."""
    ball = trimesh.creation.icosphere(subdivisions=2, radius=5.0)
    grid, fcl = GridMeshes([ball]), FclMeshes([ball])
    for p, q in [([400.0, -300.0, 250.0], [401.0, -300.0, 252.0]),
                 ([0.0, 0.0, 90.0], [0.0, 0.0, 90.0])]:
        p, q = np.array(p), np.array(q)
        got = grid.pair_distance(p, q, 0.5, 0)
        want = fcl.pair_distance(p, q, 0.5, 0)
        assert np.isfinite(got) and abs(got - want) <= 1e-3 + 3e-3 * want, (got, want)


def test_grid_backend_never_calls_a_huge_or_non_finite_capsule_free():
    """A capsule whose axis reaches an enormous coordinate still crosses the mesh near the
    origin: the grid's cell range must not overflow (it did: int64 of 1e30 / cell came out
    negative and the capsule was reported free). A non-finite capsule is unsure: touching."""
    box = trimesh.creation.box(extents=(10.0, 10.0, 10.0))
    g = GridMeshes([box])
    a = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, -1e30], [np.nan, 0.0, 0.0]])
    b = np.array([[0.0, 0.0, 1e30], [1e300, 0.0, 0.0], [0.0, 0.0, 1e30], [1.0, 0.0, 0.0]])
    for k in range(len(a)):      # each axis crosses the box's wall at 5 mm (or is NaN)
        assert g.first_hit(a[k:k + 1], b[k:k + 1], np.array([0.1])) == 0, k
    # a short capsule in the middle of the box stays free (the clamp changes nothing there)
    assert g.first_hit(np.array([[0.0, 0.0, -1.0]]), np.array([[0.0, 0.0, 1.0]]),
                       np.array([0.1])) == -1


def test_worlds_on_either_backend_give_the_same_verdicts(seed1):
    """seed1 configurations in the neuro scene (6 meshes): verdicts, contacts and exact
    clearances equal with exact="grid" and exact="fcl"."""
    scene = load_scene("neuro")
    shape = PhysicsModel(seed1).shape(seed1.sample(300, seed=4), points=21)
    a = CollisionWorld(scene, exact="fcl", prefilter=False).check_exact(shape)
    b = CollisionWorld(scene, exact="grid", prefilter=False).check_exact(shape)
    assert 20 < a.collides.sum() < 290
    np.testing.assert_array_equal(a.collides, b.collides)
    np.testing.assert_array_equal(a.contact, b.contact)
    wa, wb = CollisionWorld(scene, exact="fcl"), CollisionWorld(scene, exact="grid")
    assert wa.geometry.backend == "fcl" and wb.geometry.backend == "grid"
    np.testing.assert_allclose(wa.clearance_exact(shape[:40]), wb.clearance_exact(shape[:40]),
                               atol=1e-3)


def _big_scene(tmp_path, subdivisions=7):
    """A closed sphere of 20 * 4^subdivisions triangles (327,680) around the base (binary PLY)."""
    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=60.0)
    m.export(tmp_path / "wall.ply")
    (tmp_path / "scene.yaml").write_text(yaml.safe_dump({
        "name": "big", "units": "mm", "meshes": [{"name": "wall", "file": "wall.ply", "role": "wall"}],
        "base_pose": {"position": [0.0, 0.0, 0.0], "quaternion": [1.0, 0.0, 0.0, 0.0]}}))
    return tmp_path, len(m.faces)


def test_the_budget_refuses_up_front_naming_max_mb(tmp_path, capsys):
    """A 327,680-triangle wall under a budget just below its estimate: one line with the
    triangle count and the estimate, naming --max-mb, before any mesh is read; lifted, the
    scene loads, on the grid backend."""
    from ctrplan.collision.budget import estimate

    folder, tri = _big_scene(tmp_path)
    need = estimate(tri)[0]
    (tmp_path / "c.csv").write_text("alpha1,alpha2,alpha3,beta1,beta2,beta3\n0,0,0,-200,-150,-90\n")
    rc = cli.main(["check", "--scene", str(folder), "--robot", "seed1", "--configs",
                   str(tmp_path / "c.csv"), "--out", str(tmp_path / "v.csv"),
                   "--max-mb", f"{need - 1:.0f}"])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert f"{tri:,} triangles need about" in err[0] and "lift with --max-mb" in err[0]
    assert not (tmp_path / "v.csv").exists()
    from ctrplan.io import set_max_input_mb

    try:
        set_max_input_mb(need + 1)
        scene = load_scene(folder)
        assert CollisionWorld(scene, prefilter=False).geometry.backend == "grid"
    finally:
        set_max_input_mb(None)


@pytest.mark.parametrize("subdivisions", [3])
def test_estimate_grows_with_triangles(subdivisions):
    from ctrplan.collision.budget import estimate

    mb1, s1 = estimate(20 * 4 ** subdivisions)
    mb2, s2 = estimate(5_000_000)
    assert mb1 < mb2 <= 2048 and s1 < s2 <= 120
