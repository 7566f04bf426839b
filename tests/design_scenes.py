"""Anatomies with a known answer for ``ctrplan design`` (imports nothing from ctrplan).

:func:`build` makes a tortuous lumen around the swept volume of a known two-tube robot's
motions to three known targets, so a feasible design (that robot, with that motion) is
guaranteed:

- the **known robot** (:func:`known_robot`): two nitinol tubes from the shipped stock sizes that
  nest with a radial gap, curvatures, curved and straight lengths drawn inside design's default
  space, every tube within the 6 % strain limit;
- its **motions**: from the retracted start (alpha 0, tubes pulled back as far as the joint
  constraints allow) along the straight line in joint space to three target configurations;
  the backbones come from the foreign generator's own mechanics
  (:func:`tests.foreign.recheck.backbone`, torsionally compliant Cosserat rods), densely enough
  that no backbone point moves more than :data:`STEP_MM` between consecutive states;
- the **lumen**: the union of balls around the backbone samples, each of the local tube radius
  plus a margin (:data:`MARGIN_MM`, narrowed to :data:`NARROW_MM` in one or two balls along the
  motions: the narrowings), plus an entry channel behind the base and two or three dead-end
  **side branches**; its signed distance is exact at the grid nodes near the surface (a KD-tree
  of the samples), meshed by marching cubes (scikit-image) and decimated (fast-simplification);
- the **targets**: the known robot's tip at the three target configurations;
- the scene frame is the base frame moved by a random rigid transform (``base_pose``).

The lumen contains every state of the known motions with at least ``MARGIN_MM`` less the mesh
error; ``tests/test_design_scenes.py`` confirms each known motion with the independent re-check
(``tests/foreign/recheck.py``: exact FCL cylinders). ``infeasible=True`` builds the same anatomy
with a **neck**: across a slab of the corridor at :attr:`KnownScene.neck_depth_mm` past the base
(base frame, along +z) the lumen is replaced by a thread of radius :data:`NECK_RADIUS_MM`, below
the radius of the smallest stock tube (0.51 mm od), so no design can pass it.

    from tests.design_scenes import build
    ks = build(seed, folder)                  # ks.folder has scene.yaml and lumen.ply
    ks.robot, ks.targets, ks.motions          # the known answer
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from tests.foreign.recheck import backbone
from tests.foreign.robot import load_spec

#: Stock pairs (inner od/id, outer od/id) that nest with >= 0.05 mm radial gap (shipped table).
PAIRS = (((0.81, 0.64), (1.30, 1.00)), ((1.00, 0.80), (1.60, 1.35)), ((1.30, 1.00), (1.90, 1.60)))
#: Margin (mm) of the lumen around the known robot's body, and inside the narrowings.
MARGIN_MM = (1.0, 1.6)
NARROW_MM = 0.7
#: Largest backbone displacement (mm) between consecutive states of a motion.
STEP_MM = 0.8
#: Grid spacing (mm) of the signed distance that is meshed.
GRID_MM = 0.4
#: Radius (mm) of the neck of an infeasible variant (the smallest stock tube has radius 0.255).
NECK_RADIUS_MM = 0.15
#: Backbone samples per mm.
SAMPLES_PER_MM = 4.0


@dataclass
class KnownScene:
    """A generated anatomy: its folder (``scene.yaml``, ``lumen.ply``), the known robot (a
    robot YAML dict), the targets (T, 3) scene frame and names, the known motions (each (K, 4)
    joint-space path from the retracted start), the base pose (4, 4), and for an infeasible
    variant the neck (depth along base +z, mm, and its centre, scene frame)."""

    folder: Path
    robot: dict
    targets: np.ndarray
    names: list
    motions: list
    pose: np.ndarray
    seed: int
    infeasible: bool = False
    neck_depth_mm: float | None = None
    neck_centre: np.ndarray | None = None
    info: dict = field(default_factory=dict)


def known_robot(rng: np.random.Generator) -> dict:
    """A random two-tube nitinol robot (innermost first) inside design's default space."""
    (i_od, i_id), (o_od, o_id) = PAIRS[int(rng.integers(len(PAIRS)))]
    k_out = rng.uniform(0.012, 0.03)
    k_in = rng.uniform(0.02, 0.045)
    c_out = rng.uniform(8.0, 16.0)
    c_in = rng.uniform(12.0, 24.0)
    s_out = rng.uniform(25.0, 45.0)
    s_in = s_out + c_out + rng.uniform(12.0, 28.0) - c_in
    tubes = [dict(od=i_od, id=i_id, straight_length=round(s_in, 2), curved_length=round(c_in, 2),
                  curvature=round(k_in, 5), youngs_modulus=60000.0, poisson_ratio=0.33),
             dict(od=o_od, id=o_id, straight_length=round(s_out, 2), curved_length=round(c_out, 2),
                  curvature=round(k_out, 5), youngs_modulus=60000.0, poisson_ratio=0.33)]
    for t in tubes:
        assert t["od"] / 2 * t["curvature"] <= 0.06
    return {"name": "known", "tubes": tubes}


def retracted(spec) -> np.ndarray:
    """Retracted start (2n,): alpha 0, the outer tube back to its curved section, each inner
    tube back as far as nesting allows (as DESIGN.md's constraints give it)."""
    n = spec.n
    b = np.zeros(n)
    b[-1] = -spec.straight[-1]
    for i in range(n - 2, -1, -1):
        b[i] = min(max(-spec.straight[i], b[i + 1] + spec.L[i + 1] - spec.L[i]), b[i + 1])
    return np.concatenate([np.zeros(n), b])


def _goal(spec, rng, alpha_out: float) -> np.ndarray:
    """A target configuration: both tubes inserted most of their stroke, rotated."""
    n = spec.n
    b = np.zeros(n)
    b[-1] = -spec.straight[-1] * rng.uniform(0.1, 0.5)
    lo = max(-spec.straight[0], b[-1] + spec.L[-1] - spec.L[0])
    b[0] = lo + rng.uniform(0.5, 1.0) * (b[-1] - lo)
    a = np.array([alpha_out + rng.uniform(-0.9, 0.9), alpha_out])
    return np.concatenate([a, b])


def _shapes(spec, q: np.ndarray, points: int):
    P, rad, ok = backbone(spec, q, points=points)
    if not ok.all():
        raise RuntimeError("foreign mechanics failed on the known motion")
    return P, rad


def motion(spec, goal: np.ndarray, points: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Straight line in joint space from the retracted start to ``goal``, refined until no
    backbone point moves more than STEP_MM between consecutive states. Returns the states
    (K, 2n), their backbones (K, P, 3) base frame and segment radii (K, P-1)."""
    q0 = retracted(spec)
    t = np.linspace(0.0, 1.0, 17)
    for _ in range(8):
        q = q0 + t[:, None] * (goal - q0)
        P, rad = _shapes(spec, q, points)
        move = np.linalg.norm(np.diff(P, axis=0), axis=2).max(axis=1)
        if move.max() <= STEP_MM:
            return q, P, rad
        extra = [0.5 * (t[i] + t[i + 1]) for i in np.flatnonzero(move > STEP_MM)]
        t = np.sort(np.concatenate([t, extra]))
    raise RuntimeError("motion did not refine")


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.standard_normal(4)
    w, x, y, z = q / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def quaternion(R: np.ndarray) -> list:
    """(w, x, y, z) of a rotation matrix (Shepperd)."""
    m = R
    tr = np.trace(m)
    if tr > 0:
        s = math.sqrt(tr + 1.0) * 2
        q = [0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s]
    else:
        i = int(np.argmax(np.diag(m)))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k]) * 2
        q = [0.0] * 4
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q = np.array(q) / np.linalg.norm(q)
    return [float(v) for v in (q if q[0] >= 0 else -q)]


# ----------------------------------------------------------------------------- the lumen
def _balls(motions, rng, margin: float, narrow: list) -> tuple[np.ndarray, np.ndarray]:
    """Ball centres (N, 3) and radii (N,) (base frame) of the swept body plus margin: every
    backbone sample with its segment's tube radius + margin (NARROW_MM within a narrowing)."""
    cs, rs = [], []
    for _, P, rad in motions:
        r = np.concatenate([rad, rad[:, -1:]], axis=1)      # per point: its segment's radius
        cs.append(P.reshape(-1, 3))
        rs.append(r.reshape(-1))
    c = np.concatenate(cs)
    r = np.concatenate(rs)
    m = np.full(len(c), margin)
    for centre, radius in narrow:
        m[np.linalg.norm(c - centre, axis=1) < radius] = NARROW_MM
    # entry channel behind the base (the base lies inside the lumen)
    z = np.arange(-8.0, 0.0, 0.25)
    entry = np.column_stack([np.zeros_like(z), np.zeros_like(z), z])
    c = np.concatenate([c, entry])
    r = np.concatenate([r + m, np.full(len(z), r.max() + margin)])
    return c, r


def _branches(motions, rng, count: int) -> tuple[np.ndarray, np.ndarray]:
    """Dead-end side branches: curved tubes of radius 1-2 mm, 8-18 mm long, leaving the final
    backbone of a random motion at 25-75 % of its length, sideways."""
    cs, rs = [], []
    for _ in range(count):
        _, P, _ = motions[int(rng.integers(len(motions)))]
        bb = P[-1]
        i = int(rng.uniform(0.25, 0.75) * (len(bb) - 1))
        t = bb[min(i + 1, len(bb) - 1)] - bb[max(i - 1, 0)]
        t /= np.linalg.norm(t)
        side = np.cross(t, rng.standard_normal(3))
        side /= np.linalg.norm(side)
        d = side + rng.uniform(-0.4, 0.6) * t
        d /= np.linalg.norm(d)
        bend = np.cross(d, rng.standard_normal(3))
        bend /= np.linalg.norm(bend)
        length = rng.uniform(8.0, 18.0)
        s = np.arange(0.0, length, 0.25)
        pts = bb[i] + s[:, None] * d + (0.01 * s**2)[:, None] * bend
        cs.append(pts)
        rs.append(np.full(len(s), rng.uniform(1.0, 2.0)))
    if not cs:
        return np.zeros((0, 3)), np.zeros(0)
    return np.concatenate(cs), np.concatenate(rs)


def signed_distance(centres: np.ndarray, radii: np.ndarray, h: float):
    """Signed distance (negative inside) of a union of balls on a grid of spacing ``h``:
    min over balls of |x - c| - r, exact (KD-tree per radius class) at every node within 2 h of
    the surface, a bound farther away. Returns (sdf (nx, ny, nz), origin (3,))."""
    from scipy import ndimage
    from scipy.spatial import cKDTree

    pad = radii.max() + 3 * h
    lo = centres.min(axis=0) - pad
    hi = centres.max(axis=0) + pad
    shape = tuple(int(math.ceil(e / h)) + 1 for e in hi - lo)
    sdf = np.full(shape, np.inf)
    levels = np.round(radii, 2)
    for r in np.unique(levels):
        c = centres[levels == r]
        node = np.clip(np.rint((c - lo) / h).astype(int), 0, np.array(shape) - 1)
        grid = np.ones(shape, dtype=bool)
        grid[tuple(node.T)] = False
        far = ndimage.distance_transform_edt(grid, sampling=h)
        approx = far - r
        near = np.flatnonzero(np.abs(approx.ravel()) < 2 * h + h * math.sqrt(3))
        pts = np.stack(np.unravel_index(near, shape), axis=1) * h + lo
        d, _ = cKDTree(c).query(pts)
        approx.ravel()[near] = d - r
        np.minimum(sdf, approx, out=sdf)
    return sdf, lo


def mesh_of(sdf: np.ndarray, lo: np.ndarray, h: float, faces: int = 40000):
    """Marching cubes of the zero level, decimated to about ``faces`` triangles (closed)."""
    import trimesh
    from skimage import measure

    padded = np.pad(sdf, 1, constant_values=h)
    v, f, _, _ = measure.marching_cubes(padded, level=0.0, spacing=(h, h, h))
    v = v + lo - h
    mesh = trimesh.Trimesh(v, f[:, ::-1], process=True)
    if len(mesh.faces) > faces:
        import fast_simplification

        vv, ff = fast_simplification.simplify(np.asarray(mesh.vertices, np.float32),
                                              np.asarray(mesh.faces, np.int32),
                                              target_reduction=1.0 - faces / len(mesh.faces))
        small = trimesh.Trimesh(vv.astype(float), ff, process=True)
        if small.is_watertight:
            mesh = small
    trimesh.repair.fix_normals(mesh)
    return mesh


# ----------------------------------------------------------------------------- build
def build(seed: int, folder: str | Path, infeasible: bool = False, faces: int = 40000) -> KnownScene:
    """Build anatomy ``seed`` into ``folder`` (the same seed gives the same anatomy; with
    ``infeasible`` the same anatomy with a neck below the smallest stock tube)."""
    rng = np.random.default_rng(seed)
    robot = known_robot(rng)
    spec = load_spec(robot)
    alpha0 = rng.uniform(-math.pi, math.pi)
    alphas = alpha0 + np.array([0.0, 2.0, 4.0]) + rng.uniform(-0.5, 0.5, 3)
    points = int(max(500, SAMPLES_PER_MM * spec.L[0]))
    motions = [motion(spec, _goal(spec, rng, a), points) for a in alphas]
    margin = rng.uniform(*MARGIN_MM)
    # one or two narrowings: balls of radius 3 mm around points of the final backbones
    narrow = []
    for _ in range(int(rng.integers(1, 3))):
        _, P, _ = motions[int(rng.integers(3))]
        narrow.append((P[-1][int(rng.uniform(0.3, 0.8) * (len(P[-1]) - 1))], 3.0))
    c, r = _balls(motions, rng, margin, narrow)
    bc, br = _branches(motions, rng, int(rng.integers(2, 4)))
    centres = np.concatenate([c, bc])
    radii = np.concatenate([r, br])
    neck_depth = None
    sdf, lo = signed_distance(centres, radii, GRID_MM)
    if infeasible:
        # a slab across every route (|z - z_n| <= NECK_HALF_MM, base frame) holds only a thread
        neck_depth = float(rng.uniform(4.0, 8.0))
        ncentre = np.array([0.0, 0.0, neck_depth])
        sdf = _with_neck(sdf, lo, GRID_MM, neck_depth)
    mesh = mesh_of(sdf, lo, GRID_MM, faces)
    R = random_rotation(rng)
    tr = rng.uniform(-50.0, 50.0, 3)
    pose = np.eye(4)
    pose[:3, :3] = R
    pose[:3, 3] = tr
    mesh.apply_transform(pose)
    tips = np.array([P[-1, -1] for _, P, _ in motions])
    targets = tips @ R.T + tr
    names = ["a", "b", "c"]
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    mesh.export(folder / "lumen.ply", file_type="ply", encoding="binary")
    doc = {"name": f"known_{seed}{'_neck' if infeasible else ''}", "units": "mm",
           "meshes": [{"name": "lumen", "file": "lumen.ply", "role": "wall"}],
           "base_pose": {"position": [float(v) for v in tr], "quaternion": quaternion(R)},
           "targets": [{"name": n, "position": [float(v) for v in p]} for n, p in zip(names, targets)],
           "source": "tests/design_scenes.py (known two-tube robot's swept volume)",
           "licence": "BSD-3-Clause"}
    (folder / "scene.yaml").write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    with open(folder / "known_robot.yaml", "w", encoding="utf-8") as f:
        yaml.safe_dump(robot, f, sort_keys=False)
    return KnownScene(folder=folder, robot=robot, targets=targets, names=names,
                      motions=[q for q, _, _ in motions], pose=pose, seed=seed,
                      infeasible=infeasible, neck_depth_mm=neck_depth,
                      neck_centre=None if neck_depth is None else pose[:3, :3] @ ncentre + tr,
                      info={"margin_mm": margin, "narrowings": len(narrow),
                            "branches": int(len(np.unique(br))) if len(br) else 0,
                            "faces": int(len(mesh.faces)), "watertight": bool(mesh.is_watertight)})


#: Half thickness (mm) of the neck's slab.
NECK_HALF_MM = 1.5


def _with_neck(sdf: np.ndarray, lo: np.ndarray, h: float, depth: float) -> np.ndarray:
    """The lumen with the slab |z - depth| <= NECK_HALF_MM (base frame) replaced by a thread
    of radius NECK_RADIUS_MM along the z axis (exact distance to that segment)."""
    nodes = np.stack(np.indices(sdf.shape), axis=-1).reshape(-1, 3) * h + lo
    z = nodes[:, 2]
    zc = np.clip(z, depth - NECK_HALF_MM, depth + NECK_HALF_MM)
    thread = np.sqrt(nodes[:, 0] ** 2 + nodes[:, 1] ** 2 + (z - zc) ** 2) - NECK_RADIUS_MM
    flat = sdf.ravel().copy()
    slab = np.abs(z - depth) <= NECK_HALF_MM
    flat[slab] = np.maximum(flat[slab], h)
    return np.minimum(flat, thread).reshape(sdf.shape)


# ----------------------------------------------------------------------------- analytic lumens
def write_scene(folder: str | Path, mesh, pose: np.ndarray, targets: dict, name: str) -> Path:
    """A scene folder: ``lumen.ply`` (the mesh, already in the scene frame), scene.yaml with
    ``base_pose`` and the named targets (scene frame)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    mesh.export(folder / "lumen.ply", file_type="ply", encoding="binary")
    doc = {"name": name, "units": "mm", "meshes": [{"name": "lumen", "file": "lumen.ply", "role": "wall"}],
           "base_pose": {"position": [float(v) for v in pose[:3, 3]], "quaternion": quaternion(pose[:3, :3])},
           "targets": [{"name": k, "position": [float(x) for x in v]} for k, v in targets.items()],
           "source": "tests/design_scenes.py", "licence": "BSD-3-Clause"}
    (folder / "scene.yaml").write_text(yaml.safe_dump(doc, sort_keys=False), encoding="utf-8")
    return folder


def bend_centreline(straight: float, radius: float, angle: float, tail: float,
                    step: float = 0.1) -> np.ndarray:
    """Centre line (N, 3) base frame: ``straight`` mm along +z from z = -8 (behind the base),
    an arc of ``radius`` turning by ``angle`` rad toward +x, then ``tail`` mm straight on."""
    z = np.arange(-8.0, straight, step)
    a = np.column_stack([np.zeros_like(z), np.zeros_like(z), z])
    t = np.arange(0.0, angle, step / radius)
    b = np.column_stack([radius * (1 - np.cos(t)), np.zeros_like(t), straight + radius * np.sin(t)])
    end = np.array([radius * (1 - math.cos(angle)), 0.0, straight + radius * math.sin(angle)])
    d = np.array([math.sin(angle), 0.0, math.cos(angle)])
    s = np.arange(0.0, tail + 1e-9, step)
    c = end + s[:, None] * d
    return np.vstack([a, b, c])


def tube_lumen(folder: str | Path, centre: np.ndarray, radii: np.ndarray, pose: np.ndarray,
               targets: dict, name: str = "tube", h: float = GRID_MM) -> Path:
    """A closed lumen: the union of balls of ``radii`` (N,) along ``centre`` (N, 3) base frame,
    meshed and moved into the scene frame by ``pose``; targets given in the base frame."""
    sdf, lo = signed_distance(np.asarray(centre, float), np.asarray(radii, float), h)
    mesh = mesh_of(sdf, lo, h)
    mesh.apply_transform(pose)
    R, t = pose[:3, :3], pose[:3, 3]
    return write_scene(folder, mesh, pose, {k: R @ np.asarray(v, float) + t for k, v in targets.items()}, name)
