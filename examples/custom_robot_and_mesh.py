"""Bring your own robot (YAML) and anatomy (an STL mesh): build a scene folder, check
configurations against it and plan to a target.

The mesh here is a synthetic curved lumen written to STL, standing in for a user's segmentation.

    python examples/custom_robot_and_mesh.py [--quick] [--out DIR]
"""

import argparse
import tempfile
from pathlib import Path

import numpy as np
import trimesh
import yaml

import ctrplan

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--quick", action="store_true", help="short planning time (used by the tests)")
parser.add_argument("--out", default=None, help="working folder (default: a temporary folder)")
args = parser.parse_args()
work = Path(args.out or tempfile.mkdtemp(prefix="ctrplan_custom_"))
work.mkdir(parents=True, exist_ok=True)

# 1. The robot: two nitinol tubes, innermost first (lengths mm, curvature 1/mm, E in MPa).
robot_yaml = work / "my_robot.yaml"
robot_yaml.write_text(yaml.safe_dump({"name": "my_robot", "tubes": [
    {"od": 1.2, "id": 0.9, "straight_length": 150.0, "curved_length": 60.0, "curvature": 0.012,
     "youngs_modulus": 60000, "poisson_ratio": 0.33},
    {"od": 2.0, "id": 1.6, "straight_length": 100.0, "curved_length": 40.0, "curvature": 0.006,
     "youngs_modulus": 60000, "poisson_ratio": 0.33},
]}, sort_keys=False))
robot = ctrplan.load_robot(robot_yaml)

# 2. The anatomy: a lumen of radius 9 mm around a gently curving centreline, saved as STL (mm).
#    (Here a tube of rings swept along the centreline; yours would come from a segmentation.)
s = np.linspace(-20.0, 200.0, 111)
centre = np.stack([0.0015 * np.clip(s, 0, None) ** 2, np.zeros_like(s), s], axis=1)
tangent = np.gradient(centre, axis=0)
tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
normal = np.cross(tangent, [0.0, 1.0, 0.0])
normal /= np.linalg.norm(normal, axis=1, keepdims=True)
binormal = np.cross(tangent, normal)
phi = np.linspace(0, 2 * np.pi, 32, endpoint=False)
rings = centre[:, None] + 9.0 * (np.cos(phi)[None, :, None] * normal[:, None]
                                 + np.sin(phi)[None, :, None] * binormal[:, None])
i, j = np.meshgrid(np.arange(len(s) - 1), np.arange(len(phi)), indexing="ij")
a, b = i * len(phi) + j, i * len(phi) + (j + 1) % len(phi)
faces = np.concatenate([np.stack([a, b, a + len(phi)], -1).reshape(-1, 3),
                        np.stack([b, b + len(phi), a + len(phi)], -1).reshape(-1, 3)])
lumen = trimesh.Trimesh(rings.reshape(-1, 3), faces, process=True)
lumen.export(work / "lumen.stl")

# 3. The scene: the robot base at the lumen's entry, +z along it; one target. The tube is open
#    at both ends (where a segmentation would leave the image): declared under open_ends, the
#    openings are capped, so a backbone leaving through them collides instead of reading free.
(work / "scene.yaml").write_text(yaml.safe_dump({
    "name": "my_lumen", "units": "mm",
    "meshes": [{"name": "lumen", "file": "lumen.stl", "role": "wall"}],
    "open_ends": [{"mesh": "lumen", "position": centre[0].tolist(), "radius": 10.0},
                  {"mesh": "lumen", "position": centre[-1].tolist(), "radius": 10.0}],
    "base_pose": {"position": [0.0, 0.0, 0.0], "quaternion": [1.0, 0.0, 0.0, 0.0]},
    "targets": [],
    "source": "synthetic example lumen (examples/custom_robot_and_mesh.py)", "licence": "CC0",
}, sort_keys=False))
scene = ctrplan.load_scene(work)

# 4. Check random configurations against it (exact verdicts, clearances, which mesh is hit).
world = ctrplan.CollisionWorld(scene)
model = ctrplan.PhysicsModel(robot)
q = robot.sample(200 if args.quick else 2000, seed=0)
report = world.check(model.shape(q))
print(f"{len(q)} random configurations: {int(report.collides.sum())} collide, "
      f"median clearance {np.median(report.clearance_mm):.2f} mm")

# 5. Plan to the tip of a collision-free configuration (a target we know is reachable).
free = np.flatnonzero(~report.collides & (report.clearance_mm > 1.0))
target = scene.to_scene(model.backbone(q[free[:1]]))[0, -1]
result = ctrplan.plan_to_target(robot, scene, target, model=model,
                                time_limit=2.0 if args.quick else 5.0, seed=0)
print(f"plan to {target.round(1)} mm: {result.status.name}, tip error {result.tip_error_mm:.3f} mm, "
      f"min clearance {result.min_clearance_mm:.2f} mm")
