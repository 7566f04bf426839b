"""Make the example label map ``skull_base_labels.nii.gz`` from the shipped ``skull_base`` scene.

    python anatomy/example_labels/make_skull_base_labels.py

Voxelises the scene's meshes (procedural, BSD-3-Clause, see anatomy/skull_base/scene.yaml) the
way a segmentation would label a CT: voxels of 0.8 x 0.8 x 1.2 mm (anisotropic), stored
right-to-left along the first axis (an "LAS" image: x flipped, a left-handed voxel grid), with
the sform mapping voxels to the scene frame (x right, y anterior, z superior, mm: RAS+). A voxel
is labelled when its centre lies inside a mesh (ray parity along each voxel column: the number
of surface crossings below the centre is odd); obstacles are
written after the wall, so where they overlap the obstacle wins. Deterministic.
"""

from __future__ import annotations

from pathlib import Path

import nibabel as nib
import numpy as np
import trimesh

HERE = Path(__file__).resolve().parent
SCENE = HERE.parent / "skull_base"
LABELS = {  # name -> (value, mesh file)
    "nasal_corridor": (1, "nasal_corridor.ply"),
    "internal_carotid_right": (2, "internal_carotid_right.ply"),
    "internal_carotid_left": (3, "internal_carotid_left.ply"),
    "optic_nerve_right": (4, "optic_nerve_right.ply"),
    "optic_nerve_left": (5, "optic_nerve_left.ply"),
}
SPACING = np.array([0.8, 0.8, 1.2])
COLOURS = {1: (230, 220, 70), 2: (200, 30, 30), 3: (200, 30, 30), 4: (240, 200, 120), 5: (240, 200, 120)}


def inside_columns(mesh, x: np.ndarray, y: np.ndarray, z: np.ndarray) -> np.ndarray:
    """(len(x), len(y), len(z)) bool: voxel centres inside a closed mesh, by casting one ray
    per (x, y) column along +z and counting the crossings below each centre."""
    gx, gy = np.meshgrid(x, y, indexing="ij")
    # a tiny fixed offset keeps rays off mesh edges and vertices (no double counting)
    origins = np.stack([gx.ravel() + 1.1e-4, gy.ravel() + 1.7e-4,
                        np.full(gx.size, z.min() - 5.0)], axis=1)
    dirs = np.tile([0.0, 0.0, 1.0], (len(origins), 1))
    locs, ray, _ = mesh.ray.intersects_location(origins, dirs, multiple_hits=True)
    out = np.zeros((gx.size, len(z)), bool)
    for r in np.unique(ray):
        hz = np.sort(locs[ray == r, 2])
        out[r] = np.searchsorted(hz, z) % 2 == 1
    return out.reshape(len(x), len(y), len(z))


def main() -> None:
    meshes = {name: trimesh.load(SCENE / f, force="mesh", process=False) for name, (_, f) in LABELS.items()}
    lo = np.min([m.bounds[0] for m in meshes.values()], axis=0) - 3.0
    hi = np.max([m.bounds[1] for m in meshes.values()], axis=0) + 3.0
    dims = np.ceil((hi - lo) / SPACING).astype(int) + 1
    affine = np.diag([-SPACING[0], SPACING[1], SPACING[2], 1.0])      # LAS storage
    affine[:3, 3] = [hi[0], lo[1], lo[2]]
    data = np.zeros(dims, np.uint8)
    x = affine[0, 0] * np.arange(dims[0]) + affine[0, 3]
    y = affine[1, 1] * np.arange(dims[1]) + affine[1, 3]
    z = affine[2, 2] * np.arange(dims[2]) + affine[2, 3]
    for name, (value, _) in LABELS.items():
        data[inside_columns(meshes[name], x, y, z)] = value
    img = nib.Nifti1Image(data, affine)
    img.set_sform(affine, code=1)      # scanner-based anatomical coordinates
    img.set_qform(affine, code=1)
    img.header.set_xyzt_units("mm")
    nib.save(img, str(HERE / "skull_base_labels.nii.gz"))
    lines = ["# 3D Slicer colour table: value name r g b a (labels of skull_base_labels.nii.gz)"]
    lines += [f"{v} {name} {' '.join(map(str, COLOURS[v]))} 255" for name, (v, _) in LABELS.items()]
    (HERE / "skull_base_labels.ctbl").write_text("\n".join(lines) + "\n", encoding="utf-8")
    counts = {name: int((data == v).sum()) for name, (v, _) in LABELS.items()}
    print(f"{' x '.join(map(str, dims))} voxels of {SPACING.tolist()} mm; {counts}")  # noqa: T201


if __name__ == "__main__":
    main()
