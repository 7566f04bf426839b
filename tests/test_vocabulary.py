"""One vocabulary on the command line (issue 22 item 2).

- model names: ``physics``/``rigid`` everywhere; ``compliant`` and ``--base`` still work and
  print one deprecation line on stderr, with the same result as the current name;
- shipped targets have anatomical names and their ids ``t01``.. name the same target; the facts
  each anatomical name rests on are re-measured here from the meshes (trimesh distances, not
  the table under test);
- commands write to a default ``--out`` when none is given.
"""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from ctrplan.cli import build_parser, main


def _deprecations(err: str) -> list[str]:
    return [ln for ln in err.splitlines() if "deprecated" in ln]


# ----------------------------------------------------------------------------- model names
@pytest.mark.parametrize("cmd", ["diagnose", "simulate"])
def test_base_is_a_deprecated_alias_of_model(cmd, capsys):
    parser = build_parser()
    extra = ["--data", "m.csv"] if cmd == "diagnose" else []
    new = parser.parse_args([cmd, "--robot", "seed1", *extra, "--model", "physics"])
    assert capsys.readouterr().err == ""
    for old, want in (("compliant", "physics"), ("rigid", "rigid"), ("physics", "physics")):
        args = parser.parse_args([cmd, "--robot", "seed1", *extra, "--base", old])
        assert args.model == want
        lines = _deprecations(capsys.readouterr().err)
        assert len(lines) == 1 and "--base" in lines[0] and "--model" in lines[0], lines
    assert new.model == "physics"
    with pytest.raises(SystemExit):       # a model that is not a mechanics model is refused
        parser.parse_args([cmd, "--robot", "seed1", *extra, "--model", "learned"])


def test_simulate_base_compliant_equals_model_physics(tmp_path, capsys):
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    assert main(["-q", "simulate", "--robot", "seed1", "--n", "20", "--seed", "3",
                 "--base", "compliant", "--out", str(a)]) == 0
    assert len(_deprecations(capsys.readouterr().err)) == 1
    assert main(["-q", "simulate", "--robot", "seed1", "--n", "20", "--seed", "3",
                 "--model", "physics", "--out", str(b)]) == 0
    assert not _deprecations(capsys.readouterr().err)
    assert a.read_bytes() == b.read_bytes()
    c = tmp_path / "c.csv"            # and the rigid model gives other tips (the flag is used)
    assert main(["-q", "simulate", "--robot", "seed1", "--n", "20", "--seed", "3",
                 "--model", "rigid", "--out", str(c)]) == 0
    assert a.read_bytes() != c.read_bytes()


def test_shape_model_compliant_is_physics_with_a_deprecation(tmp_path, capsys):
    cfg = tmp_path / "q.csv"
    assert main(["-q", "simulate", "--robot", "seed1", "--n", "5", "--seed", "1",
                 "--out", str(tmp_path / "m.csv")]) == 0
    with open(tmp_path / "m.csv") as f:
        rows = list(csv.reader(f))
    cols = [i for i, h in enumerate(rows[0]) if h.startswith(("alpha", "beta"))]
    with open(cfg, "w", newline="") as f:
        csv.writer(f).writerows([[r[i] for i in cols] for r in rows])
    capsys.readouterr()
    for name in ("compliant", "physics"):
        assert main(["-q", "shape", "--robot", "seed1", "--configs", str(cfg), "--model", name,
                     "--out", str(tmp_path / f"{name}.npz")]) == 0
        err = capsys.readouterr().err
        assert len(_deprecations(err)) == (name == "compliant")
    a, b = np.load(tmp_path / "compliant.npz"), np.load(tmp_path / "physics.npz")
    np.testing.assert_array_equal(a["points"], b["points"])


# ----------------------------------------------------------------------------- target names
SHIPPED = ("airway", "neuro", "skull_base", "bronchial_tree")


@pytest.mark.parametrize("scene_name", SHIPPED)
def test_every_shipped_target_has_a_unique_anatomical_name_and_its_id_as_alias(scene_name):
    from ctrplan.collision.scene import load_scene
    from ctrplan.commands.plan import parse_target

    scene = load_scene(scene_name)
    labels = [t.label for t in scene.targets]
    assert all(labels) and len(set(labels)) == len(labels)
    assert not set(labels) & {t.name for t in scene.targets}
    for t in scene.targets:
        by_name, id_a = parse_target(t.label, scene)
        by_id, id_b = parse_target(t.name, scene)
        assert by_name == by_id == [float(v) for v in t.position] and id_a == id_b == t.name


def _sd(mesh, p) -> float:
    """Unsigned distance from ``p`` to ``mesh`` (trimesh's closest point, independent of the
    name table)."""
    import trimesh

    return float(abs(trimesh.proximity.signed_distance(mesh, np.atleast_2d(p))[0]))


def test_the_anatomical_names_rest_on_the_geometry():
    import trimesh

    from ctrplan.collision.scene import load_scene

    air = load_scene("airway")
    lb, rb = air.mesh("left_main_bronchus").mesh, air.mesh("right_main_bronchus").mesh
    summed = {t.label: _sd(lb, t.position) + _sd(rb, t.position) for t in air.targets}
    assert min(summed, key=summed.get) == "carina"
    for t in air.targets:
        near = min(_sd(lb, t.position), _sd(rb, t.position))
        assert (near < 15.0) == (t.label == "carina" or t.label.startswith("lower_trachea")), t

    sb = load_scene("skull_base")
    obst = [m for m in sb.meshes if m.role == "obstacle"]
    origin = {t.label: float(np.linalg.norm(t.position)) for t in sb.targets}
    assert min(origin, key=origin.get) == "near_sella"
    for label, mesh in (("near_left_carotid", "internal_carotid_left"),
                        ("near_right_carotid", "internal_carotid_right"),
                        ("near_left_optic_nerve", "optic_nerve_left")):
        p = sb.find_target(label).position
        d = {m.name: _sd(m.mesh, p) for m in obst}
        assert min(d, key=d.get) == mesh and d[mesh] < 6.5, (label, d)
    p = sb.find_target("below_optic_chiasm").position
    d = {m.name: _sd(m.mesh, p) for m in obst}
    assert abs(d["optic_nerve_left"] - d["optic_nerve_right"]) < 0.5 and max(
        d["optic_nerve_left"], d["optic_nerve_right"]) < min(d["internal_carotid_left"],
                                                              d["internal_carotid_right"])

    neuro = load_scene("neuro")
    vents = neuro.mesh("lateral_ventricles").mesh
    horn = neuro.find_target("left_frontal_horn").position
    assert trimesh.proximity.signed_distance(vents, [horn])[0] > 0 and horn[0] < 0 and horn[1] > 0
    for t in neuro.targets:
        assert _sd(vents, t.position) <= 12.0
        if t.label.startswith("periventricular_"):
            assert (t.position[0] > 0) == ("right" in t.label), t

    bt = load_scene("bronchial_tree")
    bif = np.array([0.0, 0.0, -100.0])     # the first bifurcation of the procedural tree
    dist = {t.label: float(np.linalg.norm(t.position - bif)) for t in bt.targets}
    assert min(dist, key=dist.get) == "carina"
    for t in bt.targets:
        if t.label.startswith("lower_trachea"):
            assert t.position[2] > -100.0
        if t.label.startswith("bronchus_x_"):
            assert t.position[2] < -100.0 and (t.position[0] > 0) == ("x_pos" in t.label), t


def test_plan_by_anatomical_name_equals_plan_by_id(tmp_path):
    outs = []
    for key in ("carina", "t01"):
        out = tmp_path / f"{key}.json"
        assert main(["-q", "plan", "--scene", "airway", "--target", key, "--time", "5",
                     "--seed", "0", "--out", str(out)]) == 0
        outs.append(json.loads(out.read_text()))
    a, b = outs
    assert a["path"] == b["path"] and a["target_name"] == b["target_name"] == "carina"
    assert a["target_id"] == b["target_id"] == "t01"


def test_unknown_target_lists_names_and_ids(capsys):
    assert main(["-q", "plan", "--scene", "airway", "--target", "nowhere", "--out", "x.json"]) == 2
    err = capsys.readouterr().err
    assert "carina (t01)" in err and err.count("\n") == 1


def test_design_accepts_anatomical_names_and_ids():
    from ctrplan.collision.scene import load_scene
    from ctrplan.design import resolve_targets

    scene = load_scene("airway")
    _, a = resolve_targets(scene, "carina,mid_trachea_2")
    _, b = resolve_targets(scene, "t01,t03")
    np.testing.assert_array_equal(a, b)


# ----------------------------------------------------------------------------- default --out
def test_default_outputs_are_written(tmp_path, monkeypatch, capsys):
    from ctrplan.commands._vocab import DEFAULT_OUT

    monkeypatch.chdir(tmp_path)
    assert main(["-q", "simulate", "--robot", "seed1", "--n", "10", "--seed", "1"]) == 0
    assert (tmp_path / DEFAULT_OUT["simulate"]).is_file()
    with open(DEFAULT_OUT["simulate"]) as f:
        rows = list(csv.reader(f))
    cols = [i for i, h in enumerate(rows[0]) if h.startswith(("alpha", "beta"))]
    with open("q.csv", "w", newline="") as f:
        csv.writer(f).writerows([[r[i] for i in cols] for r in rows])
    assert main(["-q", "shape", "--robot", "seed1", "--configs", "q.csv"]) == 0
    assert main(["-q", "check", "--scene", "airway", "--robot", "seed1", "--configs", "q.csv",
                 "--model", "physics"]) == 0
    assert main(["-q", "plan", "--scene", "airway", "--target", "carina", "--time", "5"]) == 0
    assert main(["-q", "view", DEFAULT_OUT["plan"]]) == 0
    for cmd in ("simulate", "shape", "check", "plan", "view"):
        assert (tmp_path / DEFAULT_OUT[cmd]).is_file() and (tmp_path / DEFAULT_OUT[cmd]).stat().st_size > 0, cmd
    summary = capsys.readouterr().out
    assert "SUCCESS" in summary and "closest approach" in summary and "nominal model" in summary


def test_documented_defaults_are_the_code_defaults():
    """docs/conventions.md's table of default outputs and the README's command table say what
    the parsers do."""
    import re
    from pathlib import Path

    from ctrplan.commands._vocab import DEFAULT_OUT

    root = Path(__file__).resolve().parents[1]
    conv = (root / "docs" / "conventions.md").read_text(encoding="utf-8")
    table = dict(re.findall(r"^\| `([a-z -]+)` \| `([^`]+)` \|$", conv, re.M))
    for cmd, out in DEFAULT_OUT.items():
        assert table.get(cmd, "").rstrip("/") == out, (cmd, table.get(cmd))
    parser = build_parser()
    for cmd in ("plan", "shape", "check", "simulate", "diagnose", "plan-batch", "design"):
        argv = {"plan": ["--scene", "a", "--target", "t01"], "shape": ["--robot", "r", "--configs", "c"],
                "check": ["--scene", "a", "--robot", "r", "--configs", "c"], "simulate": ["--robot", "r"],
                "diagnose": ["--robot", "r", "--data", "d"], "plan-batch": ["--targets", "t"],
                "design": ["--scene", "s", "--targets", "t"]}[cmd]
        assert parser.parse_args([cmd, *argv]).out == DEFAULT_OUT[cmd], cmd
