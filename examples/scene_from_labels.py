"""A planning scene from a segmented image: a NIfTI label map -> meshes + scene.yaml -> a plan.

The label map is the shipped example ``anatomy/example_labels/skull_base_labels.nii.gz`` (the
skull_base scene voxelised at 0.8 x 0.8 x 1.2 mm, stored left-handed like many CT exports) with
its 3D Slicer colour table beside it, so labels can be named. Coordinates are the image's
scanner frame (NIfTI RAS+), mm. The same in one command:

    ctrplan scene from-labels anatomy/example_labels/skull_base_labels.nii.gz \\
        --wall nasal_corridor --obstacle internal_carotid_right,internal_carotid_left,optic_nerve_right,optic_nerve_left \\
        --entry 6.147,95.132,-29.134 --toward 7.422,76.073,-23.205 --targets 2.15,29.24,-10.37 --out my_scene/

    python examples/scene_from_labels.py [--quick] [--out DIR]
"""

import argparse
import tempfile
from pathlib import Path

import numpy as np
import trimesh

import ctrplan

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--quick", action="store_true", help="short planning time (used by the tests)")
parser.add_argument("--out", default=None, help="working folder (default: a temporary folder)")
args = parser.parse_args()
work = Path(args.out or tempfile.mkdtemp(prefix="ctrplan_labels_"))
repo = Path(__file__).resolve().parents[1]
image = repo / "anatomy" / "example_labels" / "skull_base_labels.nii.gz"

# 1. Label map -> scene folder. Wall labels are the lumen; each obstacle label gets its own mesh.
result = ctrplan.scene_from_labels(
    image, work / "skull_base_from_labels",
    wall="nasal_corridor",
    obstacle=["internal_carotid_right", "internal_carotid_left", "optic_nerve_right", "optic_nerve_left"],
    entry=(6.147, 95.132, -29.134), toward=(7.422, 76.073, -23.205),
    targets=[(2.15, 29.24, -10.37)])
print(f"voxels {np.round(result.voxel_size_mm, 3).tolist()} mm; surfaces may move at most "
      f"{result.max_shift_mm:.2f} mm from the voxel surface")
for m in result.meshes:
    print(f"  {m.name} ({m.role}): {m.voxels} voxels -> {m.stats.faces} triangles, "
          f"{m.stats.max_shift_mm:.3f} mm from the voxel surface")

# 2. How close is each surface to the meshes the label map was voxelised from? (The wall's
#    surface also runs around the obstacles that bulge into the lumen, whose voxels are theirs.)
original = ctrplan.load_scene("skull_base")
everything = trimesh.util.concatenate([m.mesh for m in original.meshes])
worst = 0.0
for m in result.scene.meshes:
    ref = everything if m.role == "wall" else original.mesh(m.name).mesh
    pts = np.asarray(m.mesh.vertices)[:: 4 if args.quick else 1]
    _, d, _ = trimesh.proximity.closest_point(ref, pts)
    worst = max(worst, float(d.max()))
print(f"largest distance from a label surface to the original mesh: {worst:.2f} mm")

# 3. Plan in it, exactly as in any other scene.
robot = ctrplan.load_robot("seed1")
scene = ctrplan.load_scene(result.path)
plan = ctrplan.plan_to_target(robot, scene, scene.targets[0].position, model=ctrplan.PhysicsModel(robot),
                              time_limit=3.0 if args.quick else 10.0, seed=0)
print(f"plan to {scene.targets[0].position.round(1)} mm: {plan.status.name}, tip error "
      f"{plan.tip_error_mm:.3f} mm, min clearance {plan.min_clearance_mm:.2f} mm")
