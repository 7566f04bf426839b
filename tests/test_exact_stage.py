"""The exact second stage behind the prefilter (ctrplan/collision/_exact.py).

Oracles, none sharing code with the stage: the segment-triangle distance as the minimum over
the segment of trimesh's point-triangle closest point (the distance to a convex set is convex
along a line, so a golden-section search finds its minimum), with the three edges (point-segment
distance written here) for a triangle of zero area; FCL (python-fcl) for the verdicts of whole
worlds, alone (``prefilter=False``), on the shipped scenes.
"""

from __future__ import annotations

import numpy as np
import pytest
import trimesh

from ctrplan.collision._exact import FREE, TIE_MM, UNSURE, ExactStage, seg_tri_d2
from ctrplan.collision._fcl import FclMeshes
from ctrplan.collision.field import EPS_MM
from ctrplan.collision.scene import load_scene
from ctrplan.collision.world import CollisionWorld
from ctrplan.shape.physics import PhysicsModel

GOLD = (np.sqrt(5.0) - 1.0) / 2.0


def _point_seg(p, a, b):
    """(N,) distance from points p to segments a-b (N, 3), closed form."""
    d = b - a
    dd = np.einsum("ij,ij->i", d, d)
    t = np.where(dd > 0, np.einsum("ij,ij->i", p - a, d) / np.where(dd > 0, dd, 1.0), 0.0)
    return np.linalg.norm(a + np.clip(t, 0.0, 1.0)[:, None] * d - p, axis=1)


def _point_tri(x, tri):
    """(N,) distance from points x (N, 3) to triangles tri (N, 3, 3)."""
    area = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    flat = area < 1e-9 * (1.0 + np.abs(tri).max(axis=(1, 2)) ** 2)
    out = np.empty(len(x))
    if (~flat).any():
        cp = trimesh.triangles.closest_point(tri[~flat], x[~flat])
        out[~flat] = np.linalg.norm(cp - x[~flat], axis=1)
    if flat.any():
        t, p = tri[flat], x[flat]
        out[flat] = np.min([_point_seg(p, t[:, i], t[:, (i + 1) % 3]) for i in range(3)], axis=0)
    return out


def oracle(p, q, tri, iters: int = 90):
    """(N,) segment-triangle distance: golden-section minimum over the segment parameter."""
    lo, hi = np.zeros(len(p)), np.ones(len(p))

    def f(t):
        return _point_tri(p + t[:, None] * (q - p), tri)

    x1, x2 = hi - GOLD * (hi - lo), lo + GOLD * (hi - lo)
    f1, f2 = f(x1), f(x2)
    for _ in range(iters):
        left = f1 < f2
        hi = np.where(left, x2, hi)
        lo = np.where(left, lo, x1)
        x1n, x2n = hi - GOLD * (hi - lo), lo + GOLD * (hi - lo)
        x1, x2 = x1n, x2n
        f1, f2 = f(x1), f(x2)
    return np.minimum.reduce([f1, f2, _point_tri(p, tri), _point_tri(q, tri)])


def _cases(rng, n):
    """n (p, q, triangle) cases: generic, and the degenerate ones."""
    tri = rng.normal(0.0, 3.0, (n, 3, 3))
    p = rng.normal(0.0, 4.0, (n, 3))
    q = p + rng.normal(0.0, 4.0, (n, 3))
    kind = np.arange(n) % 8
    nrm = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    w = rng.dirichlet(np.ones(3), n)
    inside = np.einsum("ni,nij->nj", w, tri)
    inplane = np.cross(nrm, rng.normal(size=(n, 3)))
    s = rng.uniform(0.2, 6.0, (n, 1))
    off = rng.uniform(-0.5, 0.5, (n, 1))
    for k, (pk, qk) in enumerate([
            (inside - s * inplane, inside + s * inplane),                    # 1 in the plane, through
            (inside - s * inplane + off * nrm, inside + s * inplane + off * nrm),  # 2 parallel
            (tri[:, 0] - s * nrm, tri[:, 0] + s * nrm),                      # 3 through a vertex
            (p, p),                                                          # 4 zero length
            (inside + s * nrm, inside - 0.5 * s * nrm),                      # 5 crosses inside
            (tri[:, 1] + s * inplane, tri[:, 1] + 2 * s * inplane)]):        # 6 from a vertex
        m = kind == k + 1
        p[m], q[m] = pk[m], qk[m]
    flat = kind == 7                                                         # 7 zero-area triangle
    tri[flat, 2] = tri[flat, 0] + rng.uniform(-1, 2, (flat.sum(), 1)) * (tri[flat, 1] - tri[flat, 0])
    return p, q, tri


def _kernel(p, q, tri, above=np.inf):
    ab = np.broadcast_to(above, len(p))
    return np.array([seg_tri_d2(*p[i], *q[i], *tri[i, 0], *tri[i, 1], *tri[i, 2], ab[i])
                     for i in range(len(p))])


def test_segment_triangle_distance_against_golden_section_oracle():
    """1,600 cases (generic, segment in the triangle's plane through it, parallel to it,
    through a vertex, zero length, crossing the interior, starting at a vertex, zero-area
    triangle): the kernel's distance equals the oracle's within 1e-7 mm."""
    rng = np.random.default_rng(5)
    p, q, tri = _cases(rng, 1600)
    d = np.sqrt(_kernel(p, q, tri))
    ref = oracle(p, q, tri)
    np.testing.assert_allclose(d, ref, atol=1e-7, rtol=0)
    crossing = np.arange(1600) % 8 == 5
    assert np.all(d[crossing] == 0.0)
    assert np.all(d[np.arange(1600) % 8 == 1] <= 1e-12)      # in the plane, through it


def test_segment_triangle_distance_above_threshold():
    """With ``above``: exact where the squared distance is at most ``above``, larger
    than ``above`` where it is not (never a smaller value)."""
    rng = np.random.default_rng(6)
    p, q, tri = _cases(rng, 800)
    exact = _kernel(p, q, tri)
    above = exact * rng.uniform(0.3, 1.7, len(p))
    got = _kernel(p, q, tri, above)
    near = exact <= above
    np.testing.assert_array_equal(got[near], exact[near])
    assert np.all(got[~near] > above[~near])


def _meshes():
    ball = trimesh.creation.icosphere(subdivisions=1, radius=6.0)
    box = trimesh.creation.box(extents=[4.0, 3.0, 8.0])
    box.apply_translation([7.0, 0.0, 0.0])
    return [ball, box]


def _oracle_distance(a, b, mesh):
    """(N,) distance from segments a-b (N, 3) to a mesh: the oracle over all its triangles."""
    tri = mesh.triangles
    n, t = len(a), len(tri)
    d = oracle(np.repeat(a, t, axis=0), np.repeat(b, t, axis=0), np.tile(tri, (n, 1, 1)), 60)
    return d.reshape(n, t).min(axis=1)


@pytest.fixture(scope="module")
def capsule_cases():
    """Two meshes, 400 random capsules (some of zero length), the oracle's distance of each
    to each mesh (400, 2), radii (15 % exactly at the first mesh's distance: ties)."""
    rng = np.random.default_rng(7)
    meshes = _meshes()
    n = 400
    a = rng.uniform([-9, -8, -8], [11, 8, 8], (n, 3))
    b = a + rng.normal(0.0, 3.0, (n, 3)) * (rng.random((n, 1)) > 0.15)
    dist = np.stack([_oracle_distance(a, b, m) for m in meshes], axis=1)
    r = rng.uniform(0.1, 2.0, n)
    tie = rng.random(n) < 0.15
    r[tie] = np.maximum(dist[tie, 0], 1e-3)
    return meshes, a, b, dist, r, tie


@pytest.mark.parametrize("balls", [True, False])
def test_stage_verdicts_against_brute_force_over_all_triangles(balls, capsule_cases,
                                                                 monkeypatch):
    """400 random capsules (some of zero length) near two meshes: the stage's verdict is the
    brute-force one (the first mesh in order whose distance is below the radius) wherever the
    distance is farther than TIE_MM from the radius, and UNSURE on exact ties; with the
    triangles' balls kept and computed on the way (the large meshes' path)."""
    import ctrplan.collision._exact as exact

    monkeypatch.setattr(exact, "BALLS_UP_TO", 10**9 if balls else 0)
    meshes, a, b, dist, r, tie = capsule_cases
    n = len(a)
    stage = ExactStage.from_meshes(meshes)
    assert (stage.meshes[0].S.shape[0] > 0) == balls
    got = stage.decide(a[:, None], b[:, None], r[:, None], np.arange(n),
                       np.full((n, 1), 3, dtype=np.uint64))
    hit = dist < r[:, None]
    want = np.where(hit[:, 0], 0, np.where(hit[:, 1], 1, FREE))
    clear = np.abs(dist - r[:, None]) > 2 * TIE_MM
    decided = clear[:, 0] & (hit[:, 0] | clear[:, 1])
    np.testing.assert_array_equal(got[decided], want[decided])
    assert np.all((got[~decided] == UNSURE) | (got[~decided] == want[~decided]))
    assert np.all(got[tie & (dist[:, 0] > 1e-3)] == UNSURE)
    assert 40 < (want == 0).sum() and 15 < (want == 1).sum() and 40 < (want == FREE).sum()
    # only the pairs named by the masks: mesh 1 only
    only1 = stage.decide(a[:, None], b[:, None], r[:, None], np.arange(n),
                         np.full((n, 1), 2, dtype=np.uint64))
    sure = clear[:, 1]
    np.testing.assert_array_equal(only1[sure], np.where(hit[sure, 1], 1, FREE))


def test_stage_far_and_non_finite_capsules():
    """Capsules far outside the grids are free (no triangle is near), a long one through the
    ball hits it, and non-finite ones or ones beyond FAR_MM are left to FCL (UNSURE)."""
    from ctrplan.collision._exact import FAR_MM

    stage = ExactStage.from_meshes(_meshes())
    a = np.array([[500.0, 500.0, 500.0], [-1e5, 0.1, 0.2], [np.nan, 0, 0], [2 * FAR_MM, 0, 0],
                  [0.0, 0.0, 0.0], [-3e5, -3e5, 9e5]])
    b = np.array([[501.0, 500.0, 500.0], [1e5, 0.1, 0.2], [1.0, 0, 0], [2 * FAR_MM + 1, 0, 0],
                  [0.0, 0.0, 3.0], [-3e5, -3e5, 9e5 + 2.0]])
    r = np.array([1.0, 0.5, 1.0, 1.0, np.inf, 1.0])
    got = stage.decide(a[:, None], b[:, None], r[:, None], np.arange(len(a)),
                       np.full((len(a), 1), 3, dtype=np.uint64))
    np.testing.assert_array_equal(got, [FREE, 0, UNSURE, UNSURE, UNSURE, FREE])
    # a NaN anywhere (not only where a max() over the coordinates would meet it first)
    a = np.array([[0.0, 0.0, 0.0], [9.0, 0.0, 0.0], [20.0, 0.0, 0.0], [9.0, 0.0, 0.0]])
    b = np.array([[np.nan, 0.0, 3.0], [9.0, np.nan, 0.0], [20.0, 0.0, np.nan], [9.0, 0.0, 0.0]])
    r = np.array([1.0, 1.0, 1.0, np.nan])
    got = stage.decide(a[:, None], b[:, None], r[:, None], np.arange(len(a)),
                       np.full((len(a), 1), 3, dtype=np.uint64))
    np.testing.assert_array_equal(got, [UNSURE] * 4)


def test_fcl_contact_band_is_inside_the_tie_band():
    """FCL's verdict equals the exact one (distance < radius) for capsules 0.1 TIE_MM from
    contact, at vertices, edges and faces of a triangle far from the origin: the band left to
    FCL covers its tolerance."""
    rng = np.random.default_rng(8)
    off = np.array([180.0, -150.0, 220.0])
    tri = trimesh.Trimesh(vertices=np.array([[0, 0, 0], [3, 0, 0], [0, 3, 0.5]]) + off,
                          faces=[[0, 1, 2]])
    fcl = FclMeshes([tri])
    n = 300
    w = rng.dirichlet([1, 1, 1], n)
    w[::3] = [1.0, 0.0, 0.0]                                # at a vertex
    w[1::3, 2] = 0.0                                        # on an edge
    target = w @ tri.triangles[0] / w.sum(axis=1, keepdims=True)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    a = target + rng.uniform(0.5, 3.0, (n, 1)) * u
    b = a + np.cross(u, rng.normal(size=(n, 3)))
    d = oracle(a, b, np.repeat(tri.triangles[:1], n, axis=0))
    wrong = 0
    for i in np.flatnonzero(d > 0.01):
        for sign in (-1.0, 1.0):
            r = d[i] + sign * 0.1 * TIE_MM
            hit = fcl.first_hit(a[i][None], b[i][None], np.array([r])) >= 0
            wrong += hit != (sign > 0)
    assert (d > 0.01).sum() > 200
    assert wrong == 0


def _near_targets(robot, scene, n, seed):
    rng = np.random.default_rng(seed)
    base = np.array([t.config for t in scene.targets])
    out = []
    while sum(map(len, out)) < n:
        q = base[rng.integers(len(base), size=2 * n)].copy()
        q[:, :robot.n] += rng.uniform(-0.3, 0.3, (len(q), robot.n))
        q[:, robot.n:] += rng.uniform(-5.0, 5.0, (len(q), robot.n))
        out.append(q[robot.is_valid(q)])
    return np.concatenate(out)[:n]


@pytest.mark.parametrize("name", ["airway", "skull_base", "bronchial_tree", "neuro"])
def test_world_with_second_stage_equals_fcl_alone(name, seed1):
    """1,500 configurations near the scene's targets (mostly close to the walls), margins 0
    and 0.4 mm: verdicts with the second stage equal FCL alone's
    (``prefilter=False``), the stage decides what the bounds could not (almost nothing
    reaches FCL), and the first collision of the batch is FCL's."""
    scene = load_scene(name)
    physics = PhysicsModel(seed1)
    shape = physics.shape(_near_targets(seed1, scene, 1500, seed=21), points=21)
    for margin in (0.0, 0.4):
        world = CollisionWorld(scene, margin_mm=margin)
        alone = CollisionWorld(scene, margin_mm=margin, prefilter=False, geometry=world.geometry)
        fast, exact = world.check(shape), alone.check(shape)
        np.testing.assert_array_equal(fast.collides, exact.collides)
        assert np.all(fast.contact[fast.collides] != "")
        np.testing.assert_array_equal(world.collides(shape), exact.collides)
        assert world.last_stage_calls > 0
        assert world.last_fcl_calls <= 0.01 * len(shape)
        first = np.flatnonzero(exact.collides)
        assert world.first_collision(shape) == (int(first[0]) if len(first) else -1)
        free = np.flatnonzero(~exact.collides)
        assert world.first_collision(shape[free[:50]]) == -1
        # a collision the field's bounds do not prove (clearance not below -EPS_MM), after
        # 20 free states, before or after one they prove: FCL alone's first is index 20
        soft = np.flatnonzero(exact.collides & (fast.clearance_mm >= -EPS_MM))
        hard = np.flatnonzero(exact.collides & (fast.clearance_mm < -EPS_MM))
        assert len(soft) > 0 and len(hard) > 0 and len(free) >= 20
        for tail in ([soft[0], hard[0]], [hard[0], soft[0]]):
            batch = shape[np.concatenate([free[:20], tail, free[20:40]])]
            assert world.first_collision(batch) == 20
            assert alone.first_collision(batch) == 20


def test_pair_distance_against_brute_force_over_all_triangles(capsule_cases):
    """The stage's capsule-mesh distance (the clearance's exact measure) is the oracle's least
    segment-triangle distance minus the radius, -1 on overlap (FCL's convention), wherever the
    pair is not within TIE_MM of contact; with ``limit``, a pair farther than it gets a value
    at least ``limit`` and never more than the truth; far and non-finite capsules are left to
    FCL (NaN)."""
    meshes, a, b, dist, r, _ = capsule_cases
    stage = ExactStage.from_meshes(meshes)
    for j in range(len(meshes)):
        got = np.array([stage.pair_distance(a[i], b[i], r[i], j) for i in range(len(a))])
        want = dist[:, j] - r
        sure = np.abs(want) > TIE_MM
        over = sure & (want < 0)
        np.testing.assert_array_equal(got[over], -1.0)
        np.testing.assert_allclose(got[sure & ~over], want[sure & ~over], atol=1e-9)
        assert over.sum() > 40 and (sure & ~over).sum() > 40
        # a known lower bound (a tenth of the truth) only moves where the search starts
        lower = np.array([stage.pair_distance(a[i], b[i], r[i], j, lower=0.9 * want[i])
                          for i in np.flatnonzero(sure & ~over)])
        np.testing.assert_allclose(lower, want[sure & ~over], atol=1e-9)
        limit = 1.5
        capped = np.array([stage.pair_distance(a[i], b[i], r[i], j, limit=limit)
                           for i in range(len(a))])
        far = sure & (want > limit)
        assert far.sum() > 20
        assert np.all(capped[far] >= limit) and np.all(capped[far] <= want[far] + 1e-9)
        near = sure & ~over & (want < limit)
        np.testing.assert_allclose(capped[near], want[near], atol=1e-9)
    for p in np.array([[np.nan, 0, 0], [0, np.nan, 0], [0, 0, np.inf], [3e6, 0, 0]]):
        assert np.isnan(stage.pair_distance(p, np.zeros(3), 1.0, 0))
        assert np.isnan(stage.pair_distance(np.zeros(3), p, 1.0, 0))
    assert np.isnan(stage.pair_distance(np.zeros(3), np.ones(3), np.nan, 0))
    # far from the mesh (the search widens until it reaches it): the oracle's distance
    p, q = np.array([400.0, -300.0, 250.0]), np.array([401.0, -300.0, 252.0])
    want = _oracle_distance(p[None], q[None], meshes[0])[0] - 0.5
    assert abs(stage.pair_distance(p, q, 0.5, 0) - want) < 1e-9


@pytest.mark.parametrize("name", ["airway", "bronchial_tree"])
def test_world_clearance_with_exact_distances_equals_fcl_alone(name, seed1):
    """The world's exact clearance (branch and bound over capsule-mesh pairs, the pairs
    measured by the stage's segment-triangle distances) equals the one measured by FCL's
    distance queries (the stage off) within FCL's own tolerance, on 600 configurations near the
    targets, free ones and colliding ones (-1 both), with the same number of pairs measured."""
    scene = load_scene(name)
    physics = PhysicsModel(seed1)
    shape = physics.shape(_near_targets(seed1, scene, 600, seed=22), points=21)
    world = CollisionWorld(scene)
    fcl_world = CollisionWorld(scene, second_stage=False, geometry=world.geometry)
    ticks = int(world.geometry.second_stage._ticks[0])
    got, used = world.clearance_bounded(shape)
    assert world.geometry.second_stage._ticks[0] >= ticks + used    # the stage measured them
    want, used_fcl = fcl_world.clearance_bounded(shape)
    np.testing.assert_array_equal(got < 0, want < 0)
    free = want >= 0
    assert free.sum() > 50 and (~free).sum() > 50
    np.testing.assert_allclose(got[free], want[free], atol=1e-4)
    assert used == used_fcl
