"""Walks docs/bad-input.md: every row's input, run through the CLI, ends with exit code 2, one
line on stderr containing the row's message, no traceback, and nothing written. Also: every
command refuses an unwritable --out before doing any work, the inputs the table says are
accepted are accepted, and Ctrl-C stops a command inside compiled code within 3 s."""

from __future__ import annotations

import functools
import os
import re
import select
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

from ctrplan import cli

ROOT = Path(__file__).resolve().parents[1]
TABLE = ROOT / "docs" / "bad-input.md"
HEADER = "alpha1,alpha2,alpha3,beta1,beta2,beta3"
GOOD = "0.1,0.2,0.3,-150,-100,-50"
TUBE = ("{od: %s, id: %s, straight_length: 100, curved_length: 50, curvature: %s, "
        "youngs_modulus: 60000, poisson_ratio: 0.3}")
AIRWAY_TARGET = "--target=-8.216,544.457,-5.763"


def table_rows() -> dict[str, str]:
    rows = {}
    for line in TABLE.read_text(encoding="utf-8").splitlines():
        m = re.match(r"^\| ([a-z0-9-]+) \|.*\| `([^`]+)` \|$", line)
        if m:
            rows[m.group(1)] = m.group(2)
    return rows


# ---------------------------------------------------------------------------- input makers
def _w(path: Path, text: str | bytes) -> Path:
    path.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(text, bytes):
        path.write_bytes(text)
    else:
        path.write_text(text, encoding="utf-8")
    return path


def _shape(i: Path, o: Path, csv: str | bytes, *extra: str) -> list[str]:
    return ["shape", "--robot", "seed1", "--configs", str(_w(i / "c.csv", csv)), "--out", str(o / "s.npz"), *extra]


def _robot(i: Path, o: Path, yaml_text: str) -> list[str]:
    return ["shape", "--robot", str(_w(i / "r.yaml", yaml_text)), "--configs",
            str(_w(i / "c.csv", "alpha1,beta1\n0,-10\n")), "--out", str(o / "s.npz")]


def _one_tube(od="1.0", id_="0.8", kappa="0.01") -> str:
    return "name: r\ntubes:\n  - " + TUBE % (od, id_, kappa) + "\n"


def _scene(i: Path, o: Path, yaml_text: str, mesh=None) -> list[str]:
    folder = i / "scene"
    folder.mkdir(parents=True, exist_ok=True)
    (mesh if mesh is not None else trimesh.creation.cylinder(radius=10.0, height=100.0, sections=16)
     ).export(folder / "wall.stl")
    _w(folder / "scene.yaml", yaml_text)
    return ["check", "--scene", str(folder), "--robot", "seed1", "--configs",
            str(_w(i / "c.csv", f"{HEADER}\n{GOOD}\n")), "--out", str(o / "v.csv")]


def _holed_cylinder():
    """The scene's wall cylinder (radius 10 mm) with a hole about 12 mm across in its side."""
    m = trimesh.creation.cylinder(radius=10.0, height=100.0, sections=32)
    v, f = trimesh.remesh.subdivide_to_size(m.vertices, m.faces, max_edge=2.0)
    m = trimesh.Trimesh(v, f, process=True)
    keep = np.linalg.norm(m.triangles_center - [10.0, 0.0, 0.0], axis=1) > 6.0
    return trimesh.Trimesh(m.vertices, m.faces[keep], process=False)


def _cylinder_bytes(kind: str) -> bytes:
    m = trimesh.creation.cylinder(radius=10.0, height=100.0, sections=16)
    return m.export(file_type=kind)


def _cylinder_obj(zero: bool = False) -> str:
    """The wall cylinder as OBJ; ``zero``: its first face refers to vertex 0 (its own first
    vertex read 0-based, which OBJ does not allow)."""
    m = trimesh.creation.cylinder(radius=10.0, height=100.0, sections=16)
    faces = m.faces + 1
    if zero:
        faces = faces.copy()
        faces[0] = m.faces[0]
        faces[0, 0] = 0
    return ("".join(f"v {x:g} {y:g} {z:g}\n" for x, y, z in m.vertices)
            + "".join(f"f {a} {b} {c}\n" for a, b, c in faces))


def _mesh_file_scene(i: Path, o: Path, name: str, data: bytes) -> list[str]:
    argv = _scene(i, o, SCENE_OK % (name, ""))
    _w(i / "scene" / name, data)
    return argv


def _design(o: Path, *extra: str) -> list[str]:
    argv = {"--scene": "design_bend", "--targets": "t01"}
    for k, v in zip(extra[::2], extra[1::2]):
        argv[k] = v
    return ["design", *[x for kv in argv.items() for x in kv], "--budget", "1", "--out", str(o / "d")]


def _no_wall_scene(i: Path) -> Path:
    folder = i / "scene"
    folder.mkdir(parents=True, exist_ok=True)
    trimesh.creation.cylinder(radius=5.0, height=20.0, sections=16).apply_translation(
        [100.0, 0.0, 0.0]).export(folder / "vessel.stl")
    _w(folder / "scene.yaml", "name: s\nunits: mm\nmeshes:\n  - {name: vessel, file: vessel.stl, role: obstacle}\n"
       "base_pose: {position: [0, 0, 0], quaternion: [1, 0, 0, 0]}\n"
       "targets:\n  - {name: t01, position: [0, 0, 30]}\n")
    return folder


SCENE_OK = ("name: s\nunits: mm\nmeshes:\n  - {name: wall, file: %s, role: wall}\n"
            "base_pose: {position: [0, 0, -40], quaternion: [1, 0, 0, 0]}\n%s")


def _bomb(levels: int = 9, width: int = 9) -> str:
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for k in range(1, levels):
        lines.append(f"a{k}: &a{k} [" + ", ".join([f"*a{k - 1}"] * width) + "]")
    return "source:\n" + "".join(f"  {ln}\n" for ln in lines)


def _many_aliases() -> str:
    return "source:\n  base: &x lol\n  list: [" + ", ".join(["*x"] * 150) + "]\n"


def _nifti(path: Path, data: np.ndarray, affine: np.ndarray | None = None) -> Path:
    import nibabel as nib

    path.parent.mkdir(parents=True, exist_ok=True)
    nib.save(nib.Nifti1Image(data, np.eye(4) if affine is None else affine), str(path))
    return path


def _box_labels(dtype=np.uint8) -> np.ndarray:
    data = np.zeros((20, 20, 20), dtype)
    data[3:17, 3:17, 3:17] = 1
    return data


def _nifti_header(shape: tuple[int, int, int], dtype=np.uint8) -> bytes:
    import nibabel as nib

    h = nib.Nifti1Header()
    h.set_data_shape(shape)
    h.set_data_dtype(dtype)
    h.set_data_offset(352)
    return h.binaryblock + b"\x00" * 4


def _from_labels(i: Path, o: Path, image: Path, *extra: str, entry: str = "10,10,6") -> list[str]:
    return ["scene", "from-labels", str(image), "--wall", "1", f"--entry={entry}",
            "--toward=10,10,12", *extra, "--out", str(o / "scene")]


def _singular_affine(path: Path) -> Path:
    """A label map whose sform maps every voxel onto the plane z = 0."""
    import nibabel as nib

    data = _box_labels()
    h = nib.Nifti1Header()
    h.set_data_shape(data.shape)
    h.set_data_dtype(np.uint8)
    h.set_data_offset(352)
    h["sform_code"], h["qform_code"] = 1, 0
    h["srow_x"], h["srow_y"], h["srow_z"] = [1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 0, 0]
    return _w(path, h.binaryblock + b"\x00" * 4 + data.tobytes(order="F"))


def _gzip_bomb(path: Path) -> Path:
    import gzip

    path.parent.mkdir(parents=True, exist_ok=True)
    with gzip.open(path, "wb", compresslevel=1) as fh:
        fh.write(_nifti_header((20, 20, 20)))
        for _ in range(8):
            fh.write(b"\x00" * (1 << 22))
    return path


MAKERS = {
    "csv-not-a-number": lambda i, o: _shape(i, o, f"{HEADER}\n0.1,abc,0.3,-150,-100,-50\n"),
    "csv-not-finite": lambda i, o: _shape(i, o, f"{HEADER}\nnan,0.2,0.3,-150,-100,-50\n"),
    "csv-missing-column": lambda i, o: _shape(i, o, "alpha1,alpha2,alpha3,beta1,beta2\n0,0,0,-150,-100\n"),
    "csv-duplicate-column": lambda i, o: _shape(i, o, f"{HEADER},alpha1\n{GOOD},0.5\n"),
    "csv-row-length": lambda i, o: _shape(i, o, f"{HEADER}\n{GOOD}\n0.1,0.2,-150,-100,-50\n"),
    "csv-empty": lambda i, o: _shape(i, o, ""),
    "csv-header-only": lambda i, o: _shape(i, o, f"{HEADER}\n"),
    "csv-not-utf8": lambda i, o: _shape(i, o, b"\xff\xfe\x00a\x00l\x00p\x00h\x00a\x00"),
    "csv-constraint": lambda i, o: _shape(i, o, f"{HEADER}\n{GOOD}\n0,0,0,-50,-100,-150\n"),
    "file-missing": lambda i, o: ["shape", "--robot", "seed1", "--configs", str(i / "nope.csv"),
                                  "--out", str(o / "s.npz")],
    "measured-missing-tip": lambda i, o: [
        "diagnose", "--robot", "two_tube_nylon", "--data",
        str(_w(i / "m.csv", "alpha1,alpha2,beta1,beta2,tip_x,tip_y\n0,0,-10,0,1,2\n")), "--out", str(o / "rep")],
    "robot-unknown": lambda i, o: ["shape", "--robot", "nope", "--configs",
                                   str(_w(i / "c.csv", f"{HEADER}\n{GOOD}\n")), "--out", str(o / "s.npz")],
    "robot-unknown-key": lambda i, o: _robot(i, o, _one_tube().replace("poisson_ratio: 0.3", "poisson_ratio: 0.3, colour: red")),
    "robot-duplicate-key": lambda i, o: _robot(i, o, "name: r\nname: q\n" + _one_tube()[len("name: r\n"):]),
    "robot-malformed-yaml": lambda i, o: _robot(i, o, "name: r\ntubes: [ {od: 1\n"),
    "robot-deep-nesting": lambda i, o: _robot(i, o, "name: r\ntubes: " + "[" * 5000 + "]" * 5000 + "\n"),
    "robot-not-a-number": lambda i, o: _robot(i, o, _one_tube(od='"1,5"')),
    "robot-not-finite": lambda i, o: _robot(i, o, _one_tube(kappa=".nan")),
    "robot-id-od": lambda i, o: _robot(i, o, _one_tube(od="1.0", id_="1.2")),
    "robot-not-nested": lambda i, o: _robot(
        i, o, "name: r\ntubes:\n  - " + TUBE % ("1.0", "0.8", "0.01") + "\n  - " + TUBE % ("1.5", "0.9", "0.01") + "\n"),
    "robot-curvature-implausible": lambda i, o: _robot(i, o, _one_tube(kappa="5.0")),
    "design-unknown-target": lambda i, o: _design(o, "--targets", "t01,nope"),
    "design-scene-no-wall": lambda i, o: _design(o, "--scene", str(_no_wall_scene(i))),
    "design-infeasible-bounds": lambda i, o: _design(o, "--curvature", "0.5,0.6"),
    "design-from-strain": lambda i, o: _design(o, "--from", str(_w(i / "r.yaml", _one_tube(
        od="2.5", id_="2.2", kappa="0.05")))),
    "scene-alias-bomb": lambda i, o: _scene(i, o, SCENE_OK % ("wall.stl", _bomb())),
    "scene-too-many-aliases": lambda i, o: _scene(i, o, SCENE_OK % ("wall.stl", _many_aliases())),
    "scene-unknown-key": lambda i, o: _scene(i, o, SCENE_OK % ("wall.stl", "colour: red\n")),
    "scene-mesh-absolute": lambda i, o: _scene(i, o, SCENE_OK % (str(i / "scene" / "wall.stl"), "")),
    "scene-mesh-outside": lambda i, o: _scene(i, o, SCENE_OK % ("../scene/wall.stl", "")),
    "scene-mesh-missing": lambda i, o: _scene(i, o, SCENE_OK % ("other.stl", "")),
    "scene-mesh-units": lambda i, o: _scene(
        i, o, SCENE_OK % ("wall.stl", ""), trimesh.creation.cylinder(radius=0.01, height=0.1, sections=16)),
    "scene-base-outside": lambda i, o: _scene(
        i, o, (SCENE_OK % ("wall.stl", "")).replace("[0, 0, -40]", "[50, 0, -40]")),
    "scene-mesh-hole": lambda i, o: _scene(i, o, SCENE_OK % ("wall.stl", ""), _holed_cylinder()),
    "scene-open-end-unmatched": lambda i, o: _scene(i, o, SCENE_OK % (
        "wall.stl", "open_ends:\n  - {mesh: wall, position: [0, 0, 200], radius: 5}\n")),
    "mesh-obj-index-zero": lambda i, o: _mesh_file_scene(i, o, "wall.obj", _cylinder_obj(zero=True).encode()),
    "mesh-stl-size": lambda i, o: _mesh_file_scene(i, o, "wall.stl", _cylinder_bytes("stl")[:-7]),
    "mesh-ply-truncated": lambda i, o: _mesh_file_scene(i, o, "wall.ply", _cylinder_bytes("ply")[:-30]),
    "cost-mesh": lambda i, o: _scene(i, o, SCENE_OK % ("wall.stl", "")) + ["--max-mb", "100"],
    "labels-not-nifti": lambda i, o: _from_labels(i, o, _w(i / "seg.nii.gz", "not an image\n")),
    "labels-float": lambda i, o: _from_labels(
        i, o, _nifti(i / "ct.nii.gz", np.random.default_rng(0).normal(size=(20, 20, 20)).astype(np.float32))),
    "labels-missing-name": lambda i, o: [
        "scene", "from-labels", str(_nifti(i / "seg.nii.gz", _box_labels())), "--wall", "liver",
        "--entry=10,10,6", "--toward=10,10,12", "--label-table", str(_w(i / "t.json", '{"lumen": 1}')),
        "--out", str(o / "scene")],
    "labels-empty": lambda i, o: _from_labels(i, o, _nifti(i / "seg.nii.gz", _box_labels()), "--obstacle", "7"),
    "labels-singular-affine": lambda i, o: _from_labels(i, o, _singular_affine(i / "seg.nii")),
    "labels-over-budget": lambda i, o: _from_labels(
        i, o, _w(i / "big.nii", _nifti_header((1000, 1000, 1000), np.int16))),
    "labels-gzip-bomb": lambda i, o: _from_labels(i, o, _gzip_bomb(i / "bomb.nii.gz")),
    "labels-entry-outside": lambda i, o: _from_labels(
        i, o, _nifti(i / "seg.nii.gz", _box_labels()), entry="1,1,1"),
    "out-under-file": lambda i, o: ["simulate", "--robot", "seed1", "--n", "5",
                                    "--out", str(_w(o / "f.csv", "x\n") / "x.csv")],
    "out-unwritable": lambda i, o: ["simulate", "--robot", "seed1", "--n", "5",
                                    "--out", str(UNWRITABLE / "x.csv")],
    "out-suffix": lambda i, o: _shape(i, o, f"{HEADER}\n{GOOD}\n")[:-1] + [str(o / "s.txt")],
    "out-is-folder": lambda i, o: _shape(i, o, f"{HEADER}\n{GOOD}\n")[:-1] + [str(_mkdir(o / "d.npz"))],
    "seed-negative": lambda i, o: ["simulate", "--robot", "seed1", "--n", "5", "--seed", "-1",
                                   "--out", str(o / "m.csv")],
    "points-view": lambda i, o: ["view", str(_w(i / "plan.json", "{}")), "--points", "0",
                                 "--out", str(o / "v.html")],
    "points-shape": lambda i, o: _shape(i, o, f"{HEADER}\n{GOOD}\n", "--points", "1"),
    "target-implausible": lambda i, o: ["plan", "--scene", "airway", "--target", "1e200,0,0",
                                        "--out", str(o / "p.json")],
    "margin-implausible": lambda i, o: ["plan", "--scene", "airway", "--target", "carina",
                                        "--margin", "1e300", "--out", str(o / "p.json")],
    "target-malformed": lambda i, o: ["plan", "--scene", "airway", "--target", "1,2",
                                      "--out", str(o / "p.json")],
    "model-unknown": lambda i, o: _shape(i, o, f"{HEADER}\n{GOOD}\n", "--model", "nope"),
    "effect-unknown": lambda i, o: ["simulate", "--robot", "seed1", "--n", "5", "--effect", "magic:x=1",
                                    "--out", str(o / "m.csv")],
    # branch valid: plausibility ranges, model files, confined paths, honest train, job files
    "robot-implausible-modulus": lambda i, o: _robot(i, o, _one_tube().replace("60000", "1e300")),
    "robot-implausible-length": lambda i, o: _robot(i, o, _one_tube().replace("straight_length: 100",
                                                                              "straight_length: 1.0e12")),
    "config-implausible-angle": lambda i, o: _shape(i, o, f"{HEADER}\n1e20,0.2,0.3,-150,-100,-50\n"),
    "robot-not-regular-file": lambda i, o: ["shape", "--robot", "/dev/zero", "--configs",
                                            str(_w(i / "c.csv", f"{HEADER}\n{GOOD}\n")), "--out", str(o / "s.npz")],
    "model-not-regular-file": lambda i, o: _shape(i, o, f"{HEADER}\n{GOOD}\n", "--model", "/dev/zero"),
    "model-zero-span": lambda i, o: _shape(i, o, f"{HEADER}\n{GOOD}\n", "--model",
                                           str(_edited_model(i / "m.pt", zero_span=True))),
    "model-other-robot": lambda i, o: ["shape", "--robot", "two_tube_nylon", "--configs",
                                       str(_w(i / "c.csv", "alpha1,alpha2,beta1,beta2\n0,0,-20,-10\n")),
                                       "--model", str(_edited_model(i / "m.pt")), "--out", str(o / "s.npz")],
    "train-no-variety": lambda i, o: ["train", "--robot", "seed1", "--sim", "0", "--real",
                                      str(_identical_rows(i / "m.csv")), "--out", str(o / "m.pt")],
    "view-robot-edited": lambda i, o: _view(i, o, robot_spec="edited"),
    "view-robot-device": lambda i, o: _view(i, o, robot="/dev/zero"),
    "view-scene-arbitrary": lambda i, o: _view(i, o, scene=str(_w(i / "notes.txt", "hello\n"))),
    "view-target-malformed": lambda i, o: _view(i, o, target=[1.0, 2.0]),
    "robot-actuator-unknown-key": lambda i, o: _robot(
        i, o, _one_tube() + "actuators: {rotation: {max_sped: 1}}\n"),
    "robot-actuator-implausible": lambda i, o: _robot(
        i, o, _one_tube() + "actuators: {translation: {max_speed: 1.0e9}}\n"),
    "robot-actuator-count": lambda i, o: _robot(i, o, _one_tube() + "actuators: [{}, {}]\n"),
    "plan-rate": lambda i, o: ["plan", "--scene", "airway", "--target", "carina", "--rate", "0",
                               "--trajectory", str(o / "t.csv"), "--out", str(o / "p.json")],
    "plan-standoff": lambda i, o: ["plan", "--scene", "airway", "--target", "carina", "--standoff",
                                   "-1", "--out", str(o / "p.json")],
    "plan-approach": lambda i, o: ["plan", "--scene", "airway", "--target", "carina", "--approach",
                                   "0,0,0", "--out", str(o / "p.json")],
    "plan-cone": lambda i, o: ["plan", "--scene", "airway", "--target", "carina", "--approach",
                               "normal", "--cone", "120", "--out", str(o / "p.json")],
    "plan-cone-alone": lambda i, o: ["plan", "--scene", "airway", "--target", "carina", "--cone",
                                     "10", "--out", str(o / "p.json")],
    "plan-snap-far": lambda i, o: ["plan", "--scene", "neuro", "--target", "t01", "--standoff", "1",
                                   "--out", str(o / "p.json")],
    "view-trajectory-other-plan": lambda i, o: [*_view(i, o), "--trajectory", str(_w(
        i / "t.csv", f"t,{HEADER}\n0,0,0,0,-150,-100,-50\n0.01,0.1,0.2,0.3,-150,-100,-50\n"))],
    "view-trajectory-time": lambda i, o: [*_view(i, o), "--trajectory", str(_w(
        i / "t.csv", f"t,{HEADER}\n0,{GOOD}\n0,{GOOD}\n"))],
    "scene-mesh-symlink": lambda i, o: _symlinked_mesh_scene(i, o),
    "batch-job-edited": lambda i, o: _edited_job(i, o),
    # branch bound: bounded resources, strict numbers, options
    "input-not-regular": lambda i, o: ["shape", "--robot", "seed1", "--configs", "/dev/zero",
                                       "--out", str(o / "s.npz")],
    "input-too-large": lambda i, o: _shape(i, o, f"{HEADER}\n" + f"{GOOD}\n" * 100, "--max-mb", "0.001"),
    "csv-tube-columns": lambda i, o: ["shape", "--robot", "two_tube_nylon", "--configs", str(_w(
        i / "c.csv", f"{HEADER}\n0,0,0,-10,-5,0\n")), "--out", str(o / "s.npz")],
    "csv-digit-separator": lambda i, o: _shape(i, o, f"{HEADER}\n0.1,0.2,0.3,-1_50,-100,-50\n"),
    "option-not-finite": lambda i, o: ["diagnose", "--robot", "seed1", "--data", str(i / "m.csv"),
                                       "--bic-threshold", "nan", "--out", str(o / "rep")],
    "option-out-of-range": lambda i, o: ["train", "--robot", "seed1", "--sim", "20", "--points", "1",
                                         "--out", str(o / "m.pt")],
    "option-not-strict": lambda i, o: ["simulate", "--robot", "seed1", "--n", "1_0", "--out", str(o / "m.csv")],
    "option-long-value": lambda i, o: ["simulate", "--robot", "seed1", "--n", "9" * 100_000,
                                       "--out", str(o / "m.csv")],
    "yaml-huge-integer": lambda i, o: _robot(i, o, _one_tube().replace("youngs_modulus: 60000",
                                                                       "youngs_modulus: " + "7" * 100_000)),
    "json-huge-integer": lambda i, o: [
        "scene", "from-labels", str(_nifti(i / "seg.nii.gz", _box_labels())), "--wall", "lumen",
        "--entry=10,10,6", "--toward=10,10,12", "--label-table",
        str(_w(i / "t.json", '{"lumen": ' + "7" * 100_000 + "}")), "--out", str(o / "scene")],
    "cost-rows": lambda i, o: ["simulate", "--robot", "seed1", "--n", "100000000", "--out", str(o / "m.csv")],
    "cost-step": lambda i, o: ["simulate", "--robot", "seed1", "--step", "1e-9", "--out", str(o / "m.csv")],
}


def _edited_model(path: Path, zero_span: bool = False) -> Path:
    """The shipped seed1 network, copied (and with ``zero_span`` its beta spans set to 0)."""
    import json

    import torch

    obj = torch.load(ROOT / "ctrplan" / "data" / "models" / "seed1.pt", weights_only=True)
    if zero_span:
        meta = json.loads(obj["meta_json"])
        meta["normalisation"]["beta_span_mm"] = [0.0] * 3
        obj["meta_json"] = json.dumps(meta)
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save(obj, path)
    return path


def _identical_rows(path: Path, rows: int = 300) -> Path:
    """300 copies of one measured row (configuration, tip, 3 backbone points)."""
    cols = [*HEADER.split(","), "tip_x", "tip_y", "tip_z"] + [f"p{k}_{c}" for k in (1, 2, 3) for c in "xyz"]
    row = [*GOOD.split(","), "1", "2", "100", "0", "0", "0", "0.5", "1", "50", "1", "2", "100"]
    return _w(path, ",".join(cols) + "\n" + (",".join(row) + "\n") * rows)


def _view(i: Path, o: Path, **edit) -> list[str]:
    """``view`` of a plan.json (seed1, airway, one state) with fields replaced by ``edit``
    (``robot_spec="edited"``: the recorded robot changed after planning; ``robot=``: a plan
    without a recorded robot naming that robot)."""
    import json

    from ctrplan.robot import load_robot, robot_record

    plan = {"scene": "airway", "robot": "seed1", "model": "physics", "status": "SUCCESS",
            "path": [[0.1, 0.2, 0.3, -150, -100, -50]], "target": [0.0, 0.0, 0.0],
            **robot_record(load_robot("seed1"))}
    if edit.pop("robot_spec", "") == "edited":
        plan["robot_spec"]["tubes"][0]["curvature"] = 0.02
    if "robot" in edit:
        del plan["robot_spec"], plan["robot_sha256"]
    plan.update(edit)
    return ["view", str(_w(i / "plan.json", json.dumps(plan))), "--out", str(o / "v.html")]


def _symlinked_mesh_scene(i: Path, o: Path) -> list[str]:
    argv = _scene(i, o, SCENE_OK % ("link.stl", ""))
    trimesh.creation.cylinder(radius=10.0, height=100.0, sections=16).export(i / "elsewhere.stl")
    (i / "scene" / "link.stl").symlink_to(i / "elsewhere.stl")
    return argv


def _edited_job(i: Path, o: Path) -> list[str]:
    """A finished-looking job file for the job plan-batch will make, edited to an unknown status."""
    import json
    from dataclasses import asdict

    from ctrplan.planning.batch import make_jobs

    targets = _w(i / "t.csv", "scene,name,x,y,z\nairway,t,0,0,0\n")
    job = make_jobs([("airway", "t", (0.0, 0.0, 0.0))], seeds=(0,), robot="seed1", model="physics",
                    planner="rrtconnect", time_limit=5.0, tolerance_mm=1.0, margin="auto",
                    objective="clearance")[0]
    data = {"job_id": job.id, **asdict(job), "target": [0.0, 0.0, 0.0], "status": "GREAT",
            "success": True, "message": "", "planning_time_s": 1.0}
    _w(o / "b" / "jobs" / f"{job.id}.json", json.dumps(data))
    return ["plan-batch", "--targets", str(targets), "--out", str(o / "b")]


def _mkdir(p: Path) -> Path:
    p.mkdir(parents=True, exist_ok=True)
    return p


@functools.lru_cache(maxsize=1)
def _unwritable_folder() -> Path | None:
    """A folder this process cannot create files in (root ignores permission bits, so then a
    pseudo file system such as /sys)."""
    if os.geteuid() != 0:
        d = Path(tempfile.mkdtemp(prefix="ctrplan-ro-"))
        d.chmod(0o555)
        return d
    for cand in ("/sys", "/proc/sys"):
        try:
            fd, p = tempfile.mkstemp(dir=cand)
        except OSError:
            return Path(cand)
        os.close(fd)
        os.unlink(p)
    return None


UNWRITABLE = _unwritable_folder() or Path("/nonexistent-unwritable")


def _snapshot(folder: Path) -> set[str]:
    return {str(p.relative_to(folder)) for p in folder.rglob("*")}


def _run(capsys, argv: list[str]) -> tuple[int, str]:
    rc = cli.main(["-q", *argv])
    return rc, capsys.readouterr().err


def test_table_and_makers_match():
    assert set(table_rows()) == set(MAKERS)


@pytest.mark.parametrize("row", list(MAKERS))
def test_bad_input_row(tmp_path, capsys, row):
    if row == "out-unwritable" and _unwritable_folder() is None:
        pytest.skip("no unwritable folder on this machine")
    message = table_rows()[row]
    i, o = tmp_path / "in", tmp_path / "out"
    o.mkdir()
    argv = MAKERS[row](i, o)
    before = _snapshot(tmp_path)
    rc, err = _run(capsys, argv)
    lines = err.strip().splitlines()
    assert rc == 2, (row, rc, err)
    assert len(lines) == 1, (row, err)
    assert "Traceback" not in err
    assert lines[0].startswith(f"ctrplan {argv[0]}: error: "), lines[0]
    assert message in lines[0], (row, message, lines[0])
    assert _snapshot(tmp_path) == before, (row, _snapshot(tmp_path) - before)


# every command checks --out before any work
COMMANDS = {
    "shape": lambda i, out: ["shape", "--robot", "seed1", "--configs", str(i / "c.csv"), "--out", f"{out}.npz"],
    "simulate": lambda i, out: ["simulate", "--robot", "seed1", "--n", "5", "--out", f"{out}.csv"],
    "train": lambda i, out: ["train", "--robot", "seed1", "--sim", "20", "--out", f"{out}.pt"],
    "check": lambda i, out: ["check", "--scene", "airway", "--robot", "seed1", "--configs", str(i / "c.csv"),
                             "--out", f"{out}.csv"],
    "scene": lambda i, out: ["scene", "show", "airway", "--out", f"{out}.png"],
    "scene-from-labels": lambda i, out: ["scene", "from-labels", str(i / "seg.nii.gz"), "--wall", "1",
                                         "--entry=0,0,0", "--toward=0,0,1", "--out", out],
    "plan": lambda i, out: ["plan", "--scene", "airway", AIRWAY_TARGET, "--out", f"{out}.json"],
    "plan-batch": lambda i, out: ["plan-batch", "--targets", "examples", "--out", out],
    "scene-reach": lambda i, out: ["scene", "reach", "--scene", "skull_base", "--points", "5", "--out", out],
    "view": lambda i, out: ["view", str(i / "plan.json"), "--out", f"{out}.html"],
    "diagnose": lambda i, out: ["diagnose", "--robot", "seed1", "--data", str(i / "c.csv"), "--out", out],
    "demo": lambda i, out: ["demo", "--out", out],
    "design": lambda i, out: ["design", "--scene", "design_bend", "--targets", "t01", "--out", out],
    "bench": lambda i, out: ["bench", "shape", "--quick", "--out", out],
}


@pytest.mark.parametrize("kind", ["under-file", "unwritable"])
@pytest.mark.parametrize("command", list(COMMANDS))
def test_every_command_refuses_unwritable_out(tmp_path, capsys, command, kind):
    i = tmp_path / "in"
    _w(i / "c.csv", f"{HEADER}\n{GOOD}\n")
    _w(i / "plan.json", "{}")
    if kind == "under-file":
        base = str(_w(tmp_path / "afile.txt", "x\n") / "sub" / "o")
        message = "is a file, not a folder"
    else:
        if _unwritable_folder() is None:
            pytest.skip("no unwritable folder on this machine")
        base = str(UNWRITABLE / "ctrplan-o")
        message = "is not writable"
    before = _snapshot(tmp_path)
    t0 = time.perf_counter()
    rc, err = _run(capsys, COMMANDS[command](i, base))
    assert rc == 2, err
    assert len(err.strip().splitlines()) == 1 and message in err and "--out" in err, err
    assert _snapshot(tmp_path) == before
    assert time.perf_counter() - t0 < 60     # refused up front, not after the work


# ---------------------------------------------------------------------------- accepted inputs
def test_bom_and_crlf_csv_are_accepted(tmp_path, capsys):
    plain = _w(tmp_path / "plain.csv", f"{HEADER}\n{GOOD}\n0,0,0,-120,-90,-40\n")
    bom = _w(tmp_path / "bom.csv", b"\xef\xbb\xbf" + f"{HEADER}\r\n{GOOD}\r\n0,0,0,-120,-90,-40\r\n".encode())
    outs = []
    for src in (plain, bom):
        out = tmp_path / f"{src.stem}.npz"
        assert cli.main(["-q", "shape", "--robot", "seed1", "--configs", str(src), "--out", str(out)]) == 0
        with np.load(out) as z:
            outs.append(z["points"])
    np.testing.assert_array_equal(outs[0], outs[1])


def test_yaml_exponent_without_dot_is_a_number(tmp_path):
    from ctrplan.robot import load_robot

    seed1 = load_robot("seed1")
    text = "name: seed1\ntubes:\n" + "".join(
        f"  - {{od: {t.od}, id: {t.id}, straight_length: {t.straight_length}, curved_length: "
        f"{t.curved_length}, curvature: {t.curvature}, youngs_modulus: 6e4, poisson_ratio: {t.poisson_ratio}}}\n"
        for t in seed1.tubes)
    r = load_robot(_w(tmp_path / "r.yaml", text))
    assert r.tubes == seed1.tubes


def test_sample_counts_and_seeds():
    from ctrplan.errors import InputError
    from ctrplan.robot import load_robot

    r = load_robot("seed1")
    assert r.sample(0).shape == (0, 6)
    for bad in (-1, 2.5):
        with pytest.raises(InputError):
            r.sample(bad)
    with pytest.raises(InputError, match="seed"):
        r.sample(3, seed=-1)


def test_physics_never_vouches_for_a_backbone_longer_than_its_arc():
    """A robot past the plausibility check (forced, bypassing validation): whatever the solver
    returns, a shape marked ok has chords no longer than arcs and its tip within reach."""
    from ctrplan.robot import load_robot
    from ctrplan.shape.physics import PhysicsModel, chords_within_arc

    r = load_robot("seed1")
    for t, kappa in zip(r.tubes, (8.0, 3.0, 10.0)):
        object.__setattr__(t, "curvature", kappa)
    q = r.sample(300, seed=1)
    for torsion in (True, False):
        shape = PhysicsModel(r, torsion=torsion).shape(q, points=30)
        ok = shape.ok
        chord = np.linalg.norm(np.diff(shape.points[ok], axis=1), axis=2)
        assert np.all(chord <= np.diff(shape.s[ok], axis=1) * (1 + 1e-4) + 1e-6)
        assert np.all(np.linalg.norm(shape.points[ok][:, -1], axis=1) <= r.tip_length(q[ok]) + 1e-6)
    # the check itself on closed-form curves: a straight line passes, a stretched one does not
    s = np.linspace(0, 100, 11)[None]
    line = np.stack([0 * s, 0 * s, s], axis=-1)
    assert chords_within_arc(line, s).all()
    assert not chords_within_arc(line * 1.01, s).any()


# ---------------------------------------------------------------------------- Ctrl-C
def _cylinder_scene(folder: Path) -> Path:
    folder.mkdir(parents=True)
    trimesh.creation.cylinder(radius=20.0, height=400.0, sections=64).export(folder / "wall.stl")
    _w(folder / "scene.yaml", SCENE_OK.replace("[0, 0, -40]", "[0, 0, -190]") % ("wall.stl", ""))
    return folder


def test_ctrl_c_stops_a_command_inside_compiled_code_within_3_s(tmp_path):
    """SIGINT while `check` prepares the distance field of a large wall (numba and scipy code
    that does not return to Python for many seconds)."""
    scene = _cylinder_scene(tmp_path / "cyl")
    configs = _w(tmp_path / "c.csv", f"{HEADER}\n{GOOD}\n")
    out = tmp_path / "out"
    out.mkdir()
    env = dict(os.environ, CTRPLAN_CACHE=str(tmp_path / "cache"), PYTHONPATH=str(ROOT))
    proc = subprocess.Popen([sys.executable, "-m", "ctrplan.cli", "check", "--scene", str(scene),
                             "--robot", "seed1", "--configs", str(configs), "--out", str(out / "v.csv")],
                            stderr=subprocess.PIPE, env=env)
    deadline = time.monotonic() + 120
    seen = b""
    while b"preparing the distance field" not in seen:
        assert time.monotonic() < deadline and proc.poll() is None, seen.decode(errors="replace")
        r, _, _ = select.select([proc.stderr], [], [], 1.0)
        if r:
            seen += os.read(proc.stderr.fileno(), 4096)
    time.sleep(2.0)                       # well inside the build
    assert proc.poll() is None
    t0 = time.monotonic()
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=30)
    latency = time.monotonic() - t0
    err = (seen + proc.stderr.read()).decode(errors="replace")
    assert latency < 3.0, (latency, err)
    assert proc.returncode != 0
    assert "interrupted" in err and "Traceback" not in err
    assert list(out.iterdir()) == []      # nothing written, no temporary left


def test_ctrl_c_inside_a_c_callback_prints_no_traceback():
    """Ctrl-C while numba compiles can land inside llvmlite's ctypes callback, where Python
    reports the KeyboardInterrupt through sys.unraisablehook with a traceback (seen in a
    fresh-clone CI run); inside interrupt.guard() that report is silent and the interruption
    is recorded."""
    code = (
        "import ctypes, os, signal\n"
        "from ctrplan import interrupt\n"
        "with interrupt.guard():\n"
        "    cb = ctypes.CFUNCTYPE(None)(lambda: os.kill(os.getpid(), signal.SIGINT))\n"
        "    cb()\n"
        "    print('interrupted', interrupt.interrupted())\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60,
                       env=dict(os.environ, PYTHONPATH=str(ROOT)))
    assert "Traceback" not in r.stderr, r.stderr
    assert "interrupted True" in r.stdout
