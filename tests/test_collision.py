"""CollisionWorld: exact FCL verdicts against a brute-force oracle, the distance-field
prefilter against FCL on thousands of configurations per shipped scene, bounds of the field."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
import yaml

from ctrplan.collision.build_scenes import sample_reach
from ctrplan.collision.field import FieldConfig, build_field, point_bounds
from ctrplan.collision.field_cache import field_for
from ctrplan.collision.scene import SHIPPED_SCENES, Scene, load_scene
from ctrplan.collision.world import CollisionWorld
from ctrplan.errors import InputError
from ctrplan.shape.base import Shape
from ctrplan.shape.physics import PhysicsModel
from tests.test_capsules import shape_from_points

# one worker runs this file (`make test-stat` distributes by xdist group): its module fixtures
# are computed once
pytestmark = pytest.mark.xdist_group("collision")


def write_scene(folder, meshes, position=(0.0, 0.0, 0.0), quaternion=(1.0, 0.0, 0.0, 0.0), **extra):
    """A scene folder from [(name, role, trimesh)]; returns the folder."""
    folder.mkdir(parents=True, exist_ok=True)
    entries = []
    for name, role, mesh in meshes:
        mesh.export(folder / f"{name}.ply")
        entries.append({"name": name, "file": f"{name}.ply", "role": role})
    doc = {"name": folder.name, "units": "mm", "meshes": entries,
           "base_pose": {"position": list(position), "quaternion": list(quaternion)},
           "targets": [], "source": "test", "licence": "test"}
    doc.update(extra)
    (folder / "scene.yaml").write_text(yaml.safe_dump(doc))
    return folder


def synthetic_meshes():
    wall = trimesh.creation.icosphere(subdivisions=2, radius=40.0)
    post = trimesh.creation.cylinder(radius=3.0, height=30.0, sections=32)
    post.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    post.apply_translation([8.0, 0.0, 22.0])
    return [("shell", "wall", wall), ("post", "obstacle", post)]


@pytest.fixture(scope="module")
def synthetic(tmp_path_factory):
    folder = write_scene(tmp_path_factory.mktemp("scenes") / "synthetic", synthetic_meshes())
    return CollisionWorld(folder, cache=tmp_path_factory.mktemp("cache"))


def random_chains(n: int, seed: int, segments: int = 10, step: float = 5.0) -> np.ndarray:
    """Random-walk backbones (n, segments + 1, 3) from the base origin, mostly along +z."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, segments, 3)) * 0.6 + np.array([0.0, 0.0, 1.0])
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    pts = np.concatenate([np.zeros((n, 1, 3)), np.cumsum(d * step, axis=1)], axis=1)
    return pts


def brute_clearance(scene: Scene, points: np.ndarray, radius: float, spacing: float = 0.1) -> np.ndarray:
    """Oracle: dense points on every capsule axis, trimesh closest-point distances to every
    collision mesh, minus the radius. (B,) mm; within spacing / 2 above the true clearance."""
    out = np.empty(len(points))
    meshes = [m.mesh for m in scene.collision_meshes]
    for i, chain in enumerate(points):
        dense = []
        for a, b in zip(chain[:-1], chain[1:]):
            k = int(np.ceil(np.linalg.norm(b - a) / spacing)) + 1
            dense.append(a + np.linspace(0, 1, k)[:, None] * (b - a))
        dense = np.vstack(dense)
        out[i] = min(trimesh.proximity.closest_point(m, dense)[1].min() for m in meshes) - radius
    return out


def test_fcl_and_prefilter_against_brute_force(synthetic):
    pts = random_chains(40, seed=1)
    shape = shape_from_points(pts, 1.25)
    brute = brute_clearance(synthetic.scene, pts, 1.25)
    exact = synthetic.check_exact(shape)
    fast = synthetic.check(shape)
    clear = ~(np.abs(brute) < 0.06)   # skip cases the oracle's sampling cannot resolve
    assert clear.sum() > 30 and 8 < (brute[clear] < 0).sum() < clear.sum() - 8
    np.testing.assert_array_equal(exact.collides[clear], brute[clear] < 0)
    np.testing.assert_array_equal(fast.collides, exact.collides)
    np.testing.assert_array_equal(synthetic.collides(shape), exact.collides)
    # FCL distance for free chains equals the oracle (which overestimates by <= spacing / 2)
    free = np.flatnonzero(clear & (brute > 0))[:15]
    d = synthetic.clearance_exact(Shape(shape.points[free], shape.s[free], shape.radius[free], shape.ok[free]))
    np.testing.assert_allclose(d, brute[free], atol=0.06)
    # field clearances are conservative: never above the truth, and not far below it
    assert np.all(fast.clearance_mm[~fast.collides] <= brute[~fast.collides] + 1e-6)
    assert np.all(fast.clearance_mm[~fast.collides] >= brute[~fast.collides] - 3.0)
    assert np.all(fast.clearance_mm[fast.collides] <= 0.0)
    assert set(fast.contact[fast.collides]) <= {"shell", "post"}
    assert set(fast.contact[~fast.collides]) == {""}


def test_field_bounds_hold_at_random_points():
    mesh = synthetic_meshes()[1][2]
    field = build_field(mesh.vertices, mesh.faces, FieldConfig(h_mm=0.5), watertight=True)
    rng = np.random.default_rng(2)
    p = rng.uniform(mesh.bounds[0] - 8, mesh.bounds[1] + 8, size=(3000, 3))
    lo, up, side = point_bounds(field, p)
    true = trimesh.proximity.closest_point(mesh, p)[1]
    assert np.all(lo <= true + 1e-6) and np.all(true <= up + 1e-6)
    assert np.median(up - lo) < 2.0
    inside = mesh.contains(p)
    assert np.all(side[inside] != 1) and np.all(side[~inside] != -1)
    assert (side != 0).mean() > 0.5


def test_refinement_gives_the_nearest_sample_within_the_radius():
    """The band refinement (k-d tree over the samples) against brute force: every node within
    the radius of some sample gets the distance to its nearest sample; the others inf."""
    from ctrplan.collision.field import _nearest_sample

    rng = np.random.default_rng(5)
    samples = rng.uniform(0.0, 6.0, size=(400, 3))
    lo, h, radius, shape = np.array([-1.0, -0.5, -1.2]), 0.37, 1.3, (22, 21, 23)
    flat = np.arange(int(np.prod(shape)))
    near = _nearest_sample(samples, flat, shape, h, lo, radius).reshape(shape)
    nodes = np.stack(np.meshgrid(*[np.arange(k) for k in shape], indexing="ij"), axis=-1) * h + lo
    d2 = ((nodes.reshape(-1, 1, 3) - samples[None]) ** 2).sum(axis=2).min(axis=1).reshape(shape)
    within = d2 <= radius ** 2
    assert within.sum() > 1000 and (~within).sum() > 1000
    np.testing.assert_allclose(near[within] ** 2, d2[within], rtol=1e-12, atol=1e-12)
    assert np.all(np.isinf(near[~within]) | (near[~within] ** 2 > radius ** 2 - 1e-9))


def test_field_cache_roundtrip(tmp_path):
    mesh = synthetic_meshes()[1][2]
    a = field_for(mesh, cache=tmp_path)
    b = field_for(mesh, cache=tmp_path)
    assert a.build_s > 0 and b.build_s == 0
    np.testing.assert_array_equal(a.lb, b.lb)
    np.testing.assert_array_equal(a.side, b.side)
    assert len(list(tmp_path.glob("field-*.npz"))) == 1


@pytest.fixture(scope="module")
def physics(seed1):
    return PhysicsModel(seed1)


REACH = {"airway": 160.0, "neuro": 130.0, "skull_base": 140.0, "bronchial_tree": 260.0}


def _prefilter_against_fcl(name, seed1, physics, n: int, margins=(0.0,)):
    """n random configurations, half within the scene's reach, half anywhere in the joint
    space: the prefiltered verdicts equal exact FCL's, and no colliding state is called free."""
    q = np.vstack([sample_reach(seed1, n // 2, REACH[name], seed=11), seed1.sample(n - n // 2, seed=12)])
    shape = physics.shape(q, points=21)
    for margin in margins:
        world = CollisionWorld(name, margin_mm=margin)
        fast = world.check(shape)
        exact = world.check_exact(shape)
        called_free_but_colliding = int((~fast.collides & exact.collides).sum())
        assert called_free_but_colliding == 0
        np.testing.assert_array_equal(fast.collides, exact.collides)
        np.testing.assert_array_equal(world.collides(shape), exact.collides)   # traced walk
        assert np.all(fast.contact[fast.collides] != "")
        assert fast.fcl_calls < 0.5 * len(q)          # the prefilter decides most states
        if margin == 0.0:   # a mix of verdicts (with a wide margin a narrow scene may have no free state)
            assert 0 < (~fast.collides).sum() < len(q)
        else:
            assert exact.collides.any()
        assert world.first_collision(shape) == int(np.flatnonzero(exact.collides)[0])


@pytest.mark.parametrize("name", SHIPPED_SCENES)
def test_prefilter_never_calls_a_colliding_state_free(name, seed1, physics):
    _prefilter_against_fcl(name, seed1, physics, 2000)


@pytest.mark.statistical   # backs the README's "never calls a colliding shape free" (.ci/run)
@pytest.mark.parametrize("name", SHIPPED_SCENES)
def test_prefilter_never_calls_a_colliding_state_free_large(name, seed1, physics):
    _prefilter_against_fcl(name, seed1, physics, 10000, margins=(0.0, 0.5, 2.0))


def test_a_sub_batch_keeps_its_verdicts_and_capsules(seed1, physics):
    """A configuration's verdict does not depend on the batch it is checked in: selecting a
    sub-batch of a Shape keeps the model's pad (dropping it shrank the capsules, and the
    collision benchmark compared FCL on the smaller capsules with the prefilter on the full
    ones)."""
    world = CollisionWorld("airway")
    q = sample_reach(seed1, 300, 160.0, seed=3)
    shape = physics.shape(q, points=21)
    assert shape.pad is not None and shape.pad.max() > 0
    full = world.collides(shape)
    assert full.any() and not full[7::3].all()              # both verdicts in the sub-batch
    idx = np.arange(7, 300, 3)
    for sub in (shape[7:300:3], shape[idx], shape[np.isin(np.arange(300), idx)]):
        assert len(sub) == len(idx) and np.array_equal(sub.pad, shape.pad[idx])
        np.testing.assert_array_equal(world.collides(sub), full[idx])
        np.testing.assert_array_equal(world.check_exact(sub).collides, full[idx])
    one = shape[-1]
    assert len(one) == 1 and np.array_equal(one.points[0], shape.points[-1])


def test_prefilter_with_margin(seed1, physics):
    _prefilter_against_fcl("skull_base", seed1, physics, 600, margins=(0.5,))


def test_first_collision_and_model_failures(synthetic):
    pts = random_chains(30, seed=4)
    shape = shape_from_points(pts, 1.25)
    exact = synthetic.check_exact(shape).collides
    free = np.flatnonzero(~exact)
    sub = Shape(shape.points[free], shape.s[free], shape.radius[free], shape.ok[free].copy())
    assert synthetic.first_collision(sub) == -1
    ok = sub.ok.copy()
    ok[3] = False
    bad = Shape(sub.points, sub.s, sub.radius, ok)
    rep = synthetic.check(bad)
    assert rep.collides[3] and rep.contact[3] == "model" and synthetic.first_collision(bad) == 3
    assert rep.collides.sum() == 1


def test_margin_makes_more_collisions(synthetic):
    shape = shape_from_points(random_chains(60, seed=5), 1.0)
    thin = synthetic.collides(shape)
    fat = CollisionWorld(synthetic.scene, margin_mm=2.0).collides(shape)
    assert np.all(fat >= thin) and fat.sum() > thin.sum()


def test_empty_world_raises(tmp_path):
    folder = write_scene(tmp_path / "only_landmark", [("blob", "landmark", trimesh.creation.icosphere(radius=5.0))],
                         position=(0.0, 0.0, 50.0))
    with pytest.raises(InputError, match="nothing to check"):
        load_scene(folder)
    scene = load_scene(write_scene(tmp_path / "ok", synthetic_meshes()))
    empty = Scene(name="empty", path="<memory>", meshes=(), base_pose=np.eye(4), targets=())
    with pytest.raises(InputError, match="empty world"):
        CollisionWorld(empty)
    with pytest.raises(InputError):
        CollisionWorld(scene, margin_mm=-1.0)


@pytest.mark.parametrize("trace", [False, True])
def test_a_zero_length_capsule_is_bounded_as_a_sphere(trace):
    """Coinciding backbone points give a capsule of zero length (a sphere): its bounds come
    from the one point, against trimesh's exact closest point on the mesh (the walk divided
    by zero there). Inside an obstacle it is a proven collision; near the surface within its
    radius never free; far away free with a clearance no larger than the true one."""
    import trimesh

    from ctrplan.collision.field import build_field, capsule_bounds

    m = trimesh.creation.icosphere(subdivisions=3, radius=10.0)
    f = build_field(np.asarray(m.vertices), np.asarray(m.faces), watertight=True)
    pts = np.array([[0.0, 0.0, 0.0], [9.6, 0.0, 0.0], [30.0, 0.0, 0.0]])
    true = trimesh.proximity.closest_point(m, pts)[1]
    for p, d in zip(pts, true):
        a = p.reshape(1, 1, 3)
        clear, depth = np.full(1, np.inf), np.full(1, -np.inf)
        unsure = np.zeros((1, 1), np.uint64)
        capsule_bounds(f, a, a.copy(), np.ones((1, 1)), np.ones(1, bool), clear, depth, 1.0,
                       bad_side=-1, trace=trace, unsure=unsure)
        if p[0] == 0.0:
            assert depth[0] > 0                                 # inside the obstacle
        elif d < 1.0:
            assert depth[0] > 0 or unsure[0, 0]                 # within the radius: never free
        else:
            assert not unsure[0, 0] and 0 < clear[0] <= d - 1.0 + 1e-6
