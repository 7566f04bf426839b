"""Files validated as data (issue 24, items 3, 5, 6): plausibility ranges of robot and
configuration values, model files checked on load, non-finite shapes never ok (never free),
plan.json carrying its robot (robot_spec + robot_sha256), job files checked on resume, train
refusing data without variety, and outputs that a full disk (ENOSPC) leaves untouched.

Oracles are independent of the code under test: ranges are read from docs/conventions.md's
table, digests are recomputed here with hashlib, ENOSPC is raised by the operating system's
error code through a patched write, and "nothing written" is a directory listing."""

from __future__ import annotations

import errno
import hashlib
import json
import os
import re
from pathlib import Path

import numpy as np
import pytest
import yaml

from ctrplan import cli
from ctrplan.errors import InputError

ROOT = Path(__file__).resolve().parents[1]
SEED1_PT = ROOT / "ctrplan" / "data" / "models" / "seed1.pt"
GOOD_TUBE = {"od": 1.0, "id": 0.8, "straight_length": 100.0, "curved_length": 50.0,
             "curvature": 0.01, "youngs_modulus": 60000.0, "poisson_ratio": 0.3}


def _robot(**tube) -> dict:
    return {"name": "r", "tubes": [{**GOOD_TUBE, **tube}]}


def _enospc(*_a, **_k):
    raise OSError(errno.ENOSPC, "No space left on device")


def _files(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


# ---------------------------------------------------------------------------- ranges
def _doc_ranges() -> dict[str, tuple[float, float]]:
    """The 'Plausibility ranges' table of docs/conventions.md as {quantity: (lo, hi)}."""
    text = (ROOT / "docs" / "conventions.md").read_text(encoding="utf-8")
    section = text.split("### Plausibility ranges", 1)[1].split("###", 1)[0]
    out = {}
    for line in section.splitlines():
        m = re.match(r"^\| ([A-Za-z' ]+) \| .* \| (-?[\d.e]+) \.\. (-?[\d.e]+)", line)
        if m:
            out[m.group(1).strip()] = (float(m.group(2)), float(m.group(3)))
    return out


def test_the_documented_ranges_are_the_enforced_ones():
    from ctrplan.robot import PLAUSIBLE

    doc = _doc_ranges()
    names = {"diameter": "diameter", "length": "length", "curvature": "curvature",
             "Young's modulus": "youngs_modulus", "shear modulus": "shear_modulus",
             "Poisson ratio": "poisson_ratio", "density": "density", "angle": "angle",
             "rotation speed": "rotation_speed", "rotation acceleration": "rotation_accel",
             "translation speed": "translation_speed",
             "translation acceleration": "translation_accel"}
    assert set(doc) == set(names), doc
    for label, key in names.items():
        assert doc[label] == PLAUSIBLE[key], label


@pytest.mark.parametrize("field,value", [
    ("od", 51.0), ("straight_length", 1e12), ("curved_length", 5001.0), ("curvature", -10.5),
    ("youngs_modulus", 1e300), ("youngs_modulus", 0.5), ("density", 30000.0), ("density", 50.0),
])
def test_a_robot_value_outside_its_range_is_refused_naming_file_and_field(field, value):
    from ctrplan.robot import robot_from_dict

    with pytest.raises(InputError) as exc:
        robot_from_dict(_robot(**{field: value}), source="r.yaml")
    assert exc.value.source == "r.yaml" and exc.value.field == f"tubes[0].{field}"
    assert "plausible range" in str(exc.value) and "\n" not in str(exc.value)


def test_values_at_the_edges_of_the_ranges_are_accepted():
    from ctrplan.robot import robot_from_dict

    robot_from_dict(_robot(youngs_modulus=1.0, poisson_ratio=0.0, density=100.0), "r.yaml")
    robot_from_dict(_robot(youngs_modulus=2e6, density=25000.0, straight_length=5000.0,
                           curved_length=0.0, od=50.0, id=0.0, curvature=0.0), "r.yaml")
    for name in ("seed1", "two_tube_nylon"):        # the shipped robots pass
        from ctrplan.robot import load_robot

        load_robot(name)


def test_beta_min_and_configurations_are_range_checked(tmp_path):
    from ctrplan.robot import check_config_plausible, load_robot, read_configs, robot_from_dict

    with pytest.raises(InputError, match="plausible range") as exc:
        robot_from_dict({**_robot(), "beta_min": [-1e7]}, "r.yaml")
    assert exc.value.field == "beta_min[0]"
    r = load_robot("seed1")
    ok = np.array([[9999.0, -9999.0, 0.0, -150, -100, -50]])
    check_config_plausible(ok, r, "c.csv")
    for bad, col in ((1e20, "alpha1"), (-1.0001e4, "alpha1")):
        q = ok.copy()
        q[0, 0] = bad
        with pytest.raises(InputError) as exc:
            check_config_plausible(q, r, "c.csv")
        assert exc.value.field == f"row 2: {col}"
    csv = tmp_path / "c.csv"
    csv.write_text("alpha1,alpha2,alpha3,beta1,beta2,beta3\n0,0,0,-150,-100,-50\n0,1e20,0,-150,-100,-50\n")
    with pytest.raises(InputError) as exc:
        read_configs(csv, r)
    assert exc.value.field == "row 3: alpha2"


def test_only_regular_files_are_read_as_robots_and_models(tmp_path):
    from ctrplan.robot import load_robot
    from ctrplan.shape.models import load_model

    for path in ("/dev/zero", str(tmp_path)):
        with pytest.raises(InputError, match="not a regular file"):
            load_robot(path)
        with pytest.raises(InputError, match="not a regular file"):
            load_model(path, "seed1")
    other = tmp_path / "notes.txt"
    other.write_text("name: r\n")
    with pytest.raises(InputError, match="expected a robot YAML"):
        load_robot(other)
    with pytest.raises(InputError, match="expected a model file"):
        load_model(other, "seed1")


# ---------------------------------------------------------------------------- model files
def _pt(tmp_path: Path, edit) -> Path:
    import torch

    obj = torch.load(SEED1_PT, weights_only=True)
    meta = json.loads(obj["meta_json"])
    edit(meta)
    obj["meta_json"] = json.dumps(meta)
    path = tmp_path / "m.pt"
    torch.save(obj, path)
    return path


@pytest.mark.parametrize("edit,field", [
    (lambda m: m["normalisation"].update(beta_span_mm=[0.0, 0.0, 0.0]), "normalisation.beta_span_mm"),
    (lambda m: m["normalisation"].update(beta_span_mm=[-5.0, 100.0, 100.0]), "normalisation.beta_span_mm"),
    (lambda m: m["normalisation"].update(beta_lo_mm=[1e12, 0.0, 0.0]), "normalisation.beta_lo_mm"),
    (lambda m: m["domain"].update(beta_min_mm=[10.0, 10.0, 10.0]), "meta_json"),       # min > max
    (lambda m: m["domain"].update(alpha_arcs_rad=[[0.0, 4.0], None, None]), "meta_json"),
    (lambda m: m["robot"]["tubes"][0].update(youngs_modulus=1e300), "robot"),
])
def test_an_edited_learned_model_file_is_refused(tmp_path, edit, field):
    from ctrplan.shape.learned import LearnedModel

    with pytest.raises(InputError) as exc:
        LearnedModel.load(_pt(tmp_path, edit), robot="seed1")
    assert exc.value.field == field, str(exc.value)


def test_a_model_for_another_robot_is_refused(tmp_path):
    from ctrplan.shape.effects import EffectModel
    from ctrplan.shape.learned import LearnedModel
    from ctrplan.shape.models import load_model

    with pytest.raises(InputError, match="trained for robot"):
        LearnedModel.load(SEED1_PT, robot="two_tube_nylon")
    # a calibrated model whose robot has other tube diameters (same lengths)
    from ctrplan.robot import load_robot

    spec = load_robot("seed1").to_dict()
    spec["tubes"][0]["id"] = 0.9
    path = tmp_path / "calibrated.yaml"
    path.write_text(yaml.safe_dump({"kind": "ctrplan-effect-model", "base": "rigid", "robot": spec,
                                    "effects": {}}))
    assert isinstance(load_model(path, load_robot_spec(spec)), EffectModel)
    with pytest.raises(InputError, match="differ from"):
        load_model(path, "seed1")


def load_robot_spec(spec):
    from ctrplan.robot import robot_from_dict

    return robot_from_dict(spec, "spec")


# ---------------------------------------------------------------------------- non-finite shapes
def test_a_non_finite_shape_is_never_ok():
    from ctrplan.shape.base import Shape

    pts = np.zeros((4, 5, 3))
    pts[..., 2] = np.linspace(0, 10, 5)
    pts[1, 2, 0] = np.nan
    pts[2, 4, 1] = np.inf
    s = np.tile(np.linspace(0, 10, 5), (4, 1))
    pad = np.zeros((4, 4))
    pad[3, 0] = np.nan
    shape = Shape(points=pts, s=s, radius=np.ones((4, 5)), ok=np.ones(4, bool), pad=pad)
    assert shape.ok.tolist() == [True, False, False, False]


def test_a_zero_span_learned_model_gives_no_ok_shapes_and_collides(tmp_path):
    """The failure of issue 24: a zero span gave NaN shapes reported ok. Forced past the loader
    check, the model's NaN shapes are ok=False and a collision world calls them collisions."""
    import torch
    import trimesh

    from ctrplan.collision.world import CollisionWorld
    from ctrplan.shape.learned import LearnedModel

    model = LearnedModel.load(SEED1_PT, robot="seed1")
    q = model.robot.sample(20, seed=3)
    assert model.shape(q).ok.all()
    model.beta_span = torch.zeros(3)
    model.invalidate()
    with np.errstate(all="ignore"):
        shape = model.shape(q)
    assert not np.isfinite(shape.points).all()
    assert not shape.ok.any()
    folder = tmp_path / "scene"
    folder.mkdir()
    trimesh.creation.icosphere(subdivisions=1, radius=30.0).export(folder / "wall.stl")
    (folder / "scene.yaml").write_text(yaml.safe_dump({
        "name": "ball", "units": "mm", "meshes": [{"name": "wall", "file": "wall.stl", "role": "wall"}],
        "base_pose": {"position": [0, 0, 0], "quaternion": [1, 0, 0, 0]}}))
    world = CollisionWorld(folder, cache=tmp_path / "cache")
    assert world.check(shape).collides.all()
    assert world.check_exact(shape).collides.all()
    assert world.collides(shape).all()
    assert world.first_collision(shape) == 0
    # the field walk over NaN capsules never ended (check/plan/demo hung): now a proven hit
    assert (world.clearance_exact(shape) < 0).all()


def test_physics_and_calibrated_models_with_a_non_finite_tube_value_are_not_ok():
    from ctrplan.robot import load_robot
    from ctrplan.shape.effects import EffectModel
    from ctrplan.shape.physics import PhysicsModel

    r = load_robot("seed1")
    object.__setattr__(r.tubes[0], "curvature", float("nan"))   # bypasses the reader on purpose
    q = np.array([[0.1, 0.2, 0.3, -150, -100, -50], [0.0, 0.0, 0.0, -100, -80, -40]])
    for torsion in (False, True):
        shape = PhysicsModel(r, torsion=torsion).shape(q)
        assert not shape.ok.any()
    for base in ("rigid", "compliant"):
        shape = EffectModel(r, base, {"precurvature": {"scale1": 1.2}}).shape(q)
        assert not np.isfinite(shape.points).all() and not shape.ok.any()


# ---------------------------------------------------------------------------- symlinked meshes
def test_mesh_symlinks_inside_the_folder_are_fine_outside_refused(tmp_path):
    import trimesh

    from ctrplan.collision.scene import load_scene

    folder = tmp_path / "scene"
    (folder / "meshes").mkdir(parents=True)
    trimesh.creation.cylinder(radius=10.0, height=100.0, sections=16).export(folder / "meshes" / "w.stl")
    trimesh.creation.cylinder(radius=10.0, height=100.0, sections=16).export(tmp_path / "out.stl")
    (folder / "inside.stl").symlink_to(folder / "meshes" / "w.stl")
    (folder / "outside.stl").symlink_to(tmp_path / "out.stl")
    (folder / "dirlink").symlink_to(tmp_path)
    doc = ("name: s\nunits: mm\nmeshes:\n  - {name: wall, file: %s, role: wall}\n"
           "base_pose: {position: [0, 0, -40], quaternion: [1, 0, 0, 0]}\n")
    (folder / "scene.yaml").write_text(doc % "inside.stl")
    assert load_scene(folder).meshes[0].name == "wall"
    for name in ("outside.stl", "dirlink/out.stl"):
        (folder / "scene.yaml").write_text(doc % name)
        with pytest.raises(InputError, match="symlink that leaves the scene folder") as exc:
            load_scene(folder)
        assert exc.value.field == "meshes[0].file"


# ---------------------------------------------------------------------------- plan.json robot
def test_robot_record_is_the_spec_and_its_sha256():
    from ctrplan.robot import load_robot, robot_from_record, robot_record

    r = load_robot("two_tube_nylon")
    rec = robot_record(r)
    spec = yaml.safe_load(yaml.safe_dump(rec["robot_spec"]))     # what a file round trip gives
    digest = hashlib.sha256(json.dumps(spec, sort_keys=True, separators=(",", ":")).encode()).hexdigest()
    assert rec["robot_sha256"] == digest
    back = robot_from_record(json.loads(json.dumps(rec)), "plan.json")
    assert back.tubes == r.tubes and back.beta_min == r.beta_min
    edited = json.loads(json.dumps(rec))
    edited["robot_spec"]["tubes"][1]["curvature"] *= 1.01
    with pytest.raises(InputError, match="does not match robot_spec") as exc:
        robot_from_record(edited, "plan.json")
    assert exc.value.field == "robot_sha256"
    assert robot_from_record({"robot": "seed1"}, "plan.json") is None


def test_view_draws_the_recorded_robot_not_the_file_it_names(tmp_path):
    """plan.json names a robot file that has since changed: view uses robot_spec."""
    from ctrplan.commands.view import plan_robot
    from ctrplan.robot import load_robot, robot_from_dict, robot_record

    planned = robot_from_dict(_robot(curvature=0.01), "r.yaml")
    path = tmp_path / "r.yaml"
    path.write_text(yaml.safe_dump(_robot(curvature=0.02)))          # the file, edited later
    plan = {"robot": str(path), **robot_record(planned)}
    assert plan_robot(plan, "plan.json").tubes == planned.tubes
    assert load_robot(path).tubes != planned.tubes
    del plan["robot_spec"], plan["robot_sha256"]                    # an old plan: the file
    assert plan_robot(plan, "plan.json").tubes == load_robot(path).tubes


def test_plan_writes_robot_spec_of_a_yaml_robot(tmp_path, capsys):
    """End to end: `plan` with a robot YAML records the robot; `view` of it draws that robot."""
    from ctrplan.robot import load_robot, robot_record

    seed = load_robot("seed1").to_dict()
    seed["name"] = "seed1"                  # a YAML robot with a shipped robot's name
    robot = tmp_path / "r.yaml"
    robot.write_text(yaml.safe_dump(seed))
    out = tmp_path / "plan.json"
    rc = cli.main(["-q", "plan", "--scene", "airway", "--target", "t01", "--robot", str(robot),
                   "--objective", "first", "--time", "5", "--out", str(out)])
    assert rc in (0, 1), capsys.readouterr().err
    plan = json.loads(out.read_text())
    assert plan["robot"] == str(robot)
    assert plan["robot_spec"] == robot_record(load_robot(robot))["robot_spec"]
    assert plan["robot_sha256"] == robot_record(load_robot(robot))["robot_sha256"]


# ---------------------------------------------------------------------------- job files
def _job_and_result():
    from ctrplan.planning.batch import JobResult, make_jobs
    from ctrplan.planning.plan import PlanStatus
    from ctrplan.robot import load_robot, robot_record

    job = make_jobs([("airway", "t", (1.0, 2.0, 3.0))], seeds=(0,), robot="seed1")[0]
    plan = {"path": [[0.0, 0.0, 0.0, -150.0, -100.0, -50.0], [0.1, 0.2, 0.3, -140.0, -90.0, -40.0]],
            "planning_time_s": 0.5, "tip_error_mm": 0.2, "min_clearance_mm": 1.0,
            "planner": "direct", "requested_planner": "rrtconnect", "calibrated": False, **robot_record(load_robot("seed1"))}
    res = JobResult(job, PlanStatus.SUCCESS, "ok", plan).to_json()
    return job, json.loads(json.dumps(res))


@pytest.mark.parametrize("edit,field", [
    (lambda d: d.update(robot="two_tube_nylon"), "robot"),
    (lambda d: d.update(requested_planner="rrt"), "planner"),
    (lambda d: d.update(model="/dev/zero"), "model"),
    (lambda d: d.update(target=[1.0, 2.0, 4.0]), "target"),
    (lambda d: d.update(seed=True), "seed"),
    (lambda d: d.update(status="GREAT"), "status"),
    (lambda d: d.update(success=False), "success"),
    (lambda d: d.update(planning_time_s="fast"), "planning_time_s"),
    (lambda d: d.update(tip_error_mm=float("nan")), "tip_error_mm"),
    (lambda d: d.update(planning_time_s=-1.0), "planning_time_s"),
    (lambda d: d.update(calibrated="yes"), "calibrated"),
    (lambda d: d.update(start_rotated=1), "start_rotated"),
    (lambda d: d.update(goal_shift_mm="far"), "goal_shift_mm"),
    (lambda d: d.update(surrogate_error={"p99": 1.0}), "surrogate_error"),
    (lambda d: d.update(surrogate_error={"p50": 0.1, "p95": 0.2, "p99": -1.0, "max": 2.0}),
     "surrogate_error"),
    (lambda d: d.update(calibrated=True, surrogate_error={"p50": 0.1, "p95": 0.2, "p99": 0.3,
                                                          "max": 0.4}), "surrogate_error"),
    (lambda d: d.update(outside_measured_states="x"), "outside_measured_states"),
    (lambda d: d.update(outside_measured_states=-1), "outside_measured_states"),
    (lambda d: d.update(outside_measured_states=2.5), "outside_measured_states"),
    (lambda d: d.update(outside_measured_states=True), "outside_measured_states"),
    (lambda d: d["path"][1].__setitem__(0, 1e20), "path state 1: alpha1"),
    (lambda d: d.update(path=[[0.0, 0.0]]), "path"),
    (lambda d: d["robot_spec"]["tubes"][0].update(curvature=0.02), "robot_sha256"),
    (lambda d: d.update(scene="/etc"), "scene"),
    (lambda d: d.pop("path"), "path"),
])
def test_an_edited_job_file_is_refused(tmp_path, edit, field):
    from ctrplan.planning.jobfile import validate_job_file

    job, data = _job_and_result()
    assert validate_job_file(tmp_path / "j.json", data, job) is data
    edit(data)
    with pytest.raises(InputError) as exc:
        validate_job_file(tmp_path / "j.json", data, job)
    assert exc.value.field == field, str(exc.value)
    assert str(tmp_path / "j.json") in str(exc.value) and "delete the file" in str(exc.value)


def test_resume_with_a_valid_job_file_skips_the_job(tmp_path, monkeypatch):
    from ctrplan.planning import batch

    job, data = _job_and_result()
    (tmp_path / "jobs").mkdir()
    (tmp_path / "jobs" / f"{job.id}.json").write_text(json.dumps(data))
    monkeypatch.setattr(batch, "run_job", lambda j, *planners: pytest.fail("a done job ran again"))
    summary = batch.run_batch([job], tmp_path)
    assert (summary.skipped, summary.ran) == (1, 0)


# ---------------------------------------------------------------------------- honest train
def test_train_refuses_rows_without_variety_and_warns_on_little():
    from ctrplan.commands.train import MIN_DISTINCT, check_variety, quantile_summary

    cols = ["alpha1", "beta1"]
    rng = np.random.default_rng(0)
    q1 = np.tile([[0.1, -10.0]], (300, 1))
    pts = rng.normal(size=(300, 4, 3))
    with pytest.raises(InputError, match="only 1 distinct configurations in 300 rows"):
        check_variety(q1, np.tile(pts[:1], (300, 1, 1)), "m.csv", cols)
    q = np.column_stack([rng.uniform(-3, 3, 300), rng.uniform(-50, 0, 300)])
    with pytest.raises(InputError, match="distinct measured shapes"):
        check_variety(q, np.tile(pts[:1], (300, 1, 1)), "m.csv", cols)     # shapes all equal
    few = q[np.arange(300) % (MIN_DISTINCT - 1)]
    with pytest.raises(InputError, match=f"only {MIN_DISTINCT - 1} distinct"):
        check_variety(few, pts, "m.csv", cols)
    assert check_variety(q, pts, "m.csv", cols) == []
    warn = check_variety(q[np.arange(300) % 20], pts, "m.csv", cols)
    assert len(warn) == 1 and "only 20 distinct configurations in 300 rows" in warn[0]
    still = q.copy()
    still[:, 0] = 0.5
    assert any("alpha1 never move" in w for w in check_variety(still, pts, "m.csv", cols))
    eq = {"p50": 0.1, "p95": 0.2, "p99": 0.28, "max": 0.3}
    lines = quantile_summary(eq, {"rows": 30})
    assert "over 30 configurations" in lines[0] and "cannot support a p99" in lines[1]
    assert len(quantile_summary(eq, {"rows": 500})) == 1


# ---------------------------------------------------------------------------- full disk
def test_model_files_are_written_atomically_on_a_full_disk(tmp_path, monkeypatch):
    import builtins

    from ctrplan.shape import learned
    from ctrplan.shape.effects import EffectModel
    from ctrplan.shape.learned import LearnedModel

    model = LearnedModel.load(SEED1_PT, robot="seed1")
    out = tmp_path / "m.pt"
    model.save(out)
    before = out.read_bytes()
    real_open = builtins.open

    def full_open(file, mode="r", *a, **k):
        if "w" in mode:
            _enospc()
        return real_open(file, mode, *a, **k)

    monkeypatch.setattr(learned, "open", full_open, raising=False)
    with pytest.raises(OSError) as exc:
        model.save(out)
    assert exc.value.errno == errno.ENOSPC
    assert out.read_bytes() == before and _files(tmp_path) == ["m.pt"]   # old file kept, no temp
    monkeypatch.undo()
    cal = EffectModel(model.robot, "rigid", {})
    cal.save(tmp_path / "calibrated.yaml")
    old = (tmp_path / "calibrated.yaml").read_text()
    monkeypatch.setattr(Path, "write_text", _enospc)
    with pytest.raises(InputError, match="No space left on device"):
        cal.save(tmp_path / "calibrated.yaml")
    assert (tmp_path / "calibrated.yaml").read_text() == old
    assert _files(tmp_path) == ["calibrated.yaml", "m.pt"]


def test_train_on_a_full_disk_says_one_line_exit_2_nothing_written(tmp_path, monkeypatch, capsys):
    import builtins

    from ctrplan.shape import learned

    real_open = builtins.open

    def full_open(file, mode="r", *a, **k):
        if "w" in mode and str(file).startswith(str(tmp_path)):
            _enospc()
        return real_open(file, mode, *a, **k)

    monkeypatch.setattr(learned, "open", full_open, raising=False)
    out = tmp_path / "out"
    out.mkdir()
    rc = cli.main(["-q", "train", "--robot", "seed1", "--sim", "40", "--epochs", "1", "--workers", "1",
                   "--points", "5", "--out", str(out / "m.pt")])
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert "No space left on device" in err[0] and "Traceback" not in err[0]
    assert _files(out) == []


def test_plan_batch_on_a_full_disk_says_one_line_exit_2_nothing_written(tmp_path, monkeypatch, capsys):
    from ctrplan.planning import batch
    from ctrplan.planning.plan import PlanStatus

    monkeypatch.setattr(batch, "run_job", lambda job, *planners: batch.JobResult(job, PlanStatus.TIMEOUT, "t"))
    targets = tmp_path / "t.csv"
    targets.write_text("scene,name,x,y,z\nairway,a,0,0,0\nairway,b,1,0,0\n")
    out = tmp_path / "out"
    rc = cli.main(["-q", "plan-batch", "--targets", str(targets), "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    done = {p: p.read_bytes() for p in out.rglob("*") if p.is_file()}
    assert len([p for p in done if p.parent.name == "jobs"]) == 2
    for p in done:                                   # a new run: results to write again
        if p.parent.name == "jobs":
            p.unlink()
    capsys.readouterr()
    monkeypatch.setattr(os, "fsync", _enospc)          # the disk fills while a job file is written
    rc = cli.main(["-q", "plan-batch", "--targets", str(targets), "--out", str(out)])
    monkeypatch.undo()
    err = capsys.readouterr().err.strip().splitlines()
    assert rc == 2 and len(err) == 1, err
    assert "No space left on device" in err[0]
    left = sorted(str(p.relative_to(out)) for p in out.rglob("*"))
    # no job file, no temporary; the tables of the previous run were withdrawn when its results
    # went stale (they exist only after a run that finished every job), never half-written
    assert left == ["jobs"], left


def test_view_draws_the_planned_tip_after_the_robot_file_changed(tmp_path, monkeypatch, capsys):
    """Issue 24: view drew another robot (tip 3.7 mm from the planned one). Plan with a robot
    YAML, change the file, view: the drawn tips are the planned tip path."""
    from ctrplan import viz
    from ctrplan.robot import load_robot

    spec = load_robot("seed1").to_dict()
    robot = tmp_path / "r.yaml"
    robot.write_text(yaml.safe_dump(spec))
    out = tmp_path / "plan.json"
    rc = cli.main(["-q", "plan", "--scene", "airway", "--target", "t01", "--robot", str(robot),
                   "--objective", "first", "--time", "5", "--out", str(out)])
    assert rc == 0, capsys.readouterr().err
    spec["tubes"][2]["curvature"] *= 1.5
    robot.write_text(yaml.safe_dump(spec))                          # edited after planning
    drawn = {}
    monkeypatch.setattr(viz, "plan_html", lambda out, meshes, backbones, tip, target, title="", **kw:
                        drawn.update(backbones=backbones, tip=tip))
    rc = cli.main(["-q", "view", str(out), "--out", str(tmp_path / "v.html")])
    assert rc == 0, capsys.readouterr().err
    plan = json.loads(out.read_text())
    planned = np.asarray(plan["tip_path"])
    shown = viz.pick_frames(len(planned), viz.HTML_FRAMES)        # view draws these states only
    assert np.abs(drawn["backbones"][:, -1] - planned[shown]).max() < 1e-3
    # the test can fail: the edited file's robot puts the tip elsewhere (what view drew before)
    from ctrplan.collision.scene import load_scene
    from ctrplan.shape.physics import PhysicsModel

    wrong = load_scene("airway").to_scene(PhysicsModel(load_robot(robot)).backbone(np.asarray(plan["path"]),
                                                                                   points=40))
    assert np.linalg.norm(wrong[:, -1] - planned, axis=1).max() > 1.0
