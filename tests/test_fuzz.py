"""Property-based fuzzing of every reader of user files and of the command line's numeric options.

Property (docs/bad-input.md): a reader given any bytes either returns a valid object or raises
:class:`~ctrplan.errors.InputError` with one line of bounded length that names the file; never
another exception, never a hang. The command line, given any value of a numeric option, never
prints a traceback: it exits 2 with one bounded error line (or 0 when the value is fine).

Inputs come from two kinds of strategies: byte-level mutations (flips, insertions of tokens that
break parsers, deletions, duplications, truncation) of valid files (the shipped robots, a scene,
a small CSV, a plan.json, a trained model), and structured generation (valid YAML/JSON/CSV whose
values and keys are drawn from huge integers, NaN, deep nesting, unicode, aliases, BOM, CRLF).

Budgets are Hypothesis settings profiles, chosen with ``CTRPLAN_FUZZ``: ``dev`` (default, a few
dozen examples per reader, part of ``make test``), ``ci`` (10,000 examples per reader, run by
``make fuzz-ci`` in ``.ci/run``) and ``long`` (100,000, ``make fuzz``). Every profile is
derandomized (a fixed seed): the same examples on every run.
"""

from __future__ import annotations

import contextlib
import copy
import functools
import io
import json
import math
import os
import signal
import tempfile
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ctrplan import cli
from ctrplan.errors import InputError

# ---------------------------------------------------------------------- budgets
settings.register_profile(
    "fuzz-dev", max_examples=40, derandomize=True, database=None, deadline=None,
    suppress_health_check=list(HealthCheck), print_blob=True)
settings.register_profile(
    "fuzz-ci", max_examples=10_000, derandomize=True, database=None, deadline=None,
    suppress_health_check=list(HealthCheck), print_blob=True)
settings.register_profile(
    "fuzz-long", max_examples=100_000, derandomize=True, database=None, deadline=None,
    suppress_health_check=list(HealthCheck), print_blob=True)
PROFILE = os.environ.get("CTRPLAN_FUZZ", "dev")
if PROFILE not in ("dev", "ci", "long"):
    raise RuntimeError(f"CTRPLAN_FUZZ must be dev, ci or long, got {PROFILE!r}")
FUZZ = settings(settings.get_profile(f"fuzz-{PROFILE}"))
if os.environ.get("CTRPLAN_FUZZ_EXAMPLES"):     # measuring: another count, same seed
    FUZZ = settings(FUZZ, max_examples=int(os.environ["CTRPLAN_FUZZ_EXAMPLES"]))
#: seconds one example may take before it counts as a hang
HANG_S = 10.0
#: longest error message accepted (the bad value is quoted as an excerpt, never whole)
MAX_MESSAGE = 1000   # source (paths whole up to 400) + field + message (300)

REPO = Path(__file__).resolve().parents[1]
DATA = REPO / "ctrplan" / "data"


class Hang(AssertionError):
    """An example ran longer than HANG_S."""


@contextlib.contextmanager
def no_hang(seconds: float = HANG_S):
    """Fail the example (a hang) when it runs longer than ``seconds``."""
    def _alarm(signum, frame):
        raise Hang(f"example ran longer than {seconds} s")

    old = signal.signal(signal.SIGALRM, _alarm)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)


def check_reader(fn, path: Path | str):
    """Run ``fn()``; it returns or raises a one-line, bounded InputError naming ``path``."""
    with no_hang():
        try:
            return fn()
        except InputError as exc:
            msg = str(exc)
            assert "\n" not in msg and "\r" not in msg, f"multi-line message: {msg!r}"
            assert len(msg) <= MAX_MESSAGE, f"message of {len(msg)} characters: {msg[:200]!r}..."
            assert str(path) in msg, f"message does not name {path}: {msg!r}"
            return None


# ---------------------------------------------------------------------- strategies
#: byte strings that break parsers (YAML/CSV/JSON syntax, numbers at the edges, encodings)
TOKENS = [
    b"nan", b"NaN", b".nan", b"inf", b"-inf", b".inf", b"-.inf", b"1e309", b"-1e309", b"1e-320",
    b"9" * 400, b"-" + b"9" * 30, b"1_0", b"0x10", b"0o7", b"1e400", b"+", b"-", b".", b"e5",
    b"\x00", b"\xff", b"\xfe", b"\xef\xbb\xbf", b"\xc3\x28", b"\xe2\x82", "\u00e9\u2603\U0001f600".encode(),
    b"\r\n", b"\r", b"\n", b"\t", b" ", b",", b",,", b";", b'"', b"'", b"#",
    b":", b": ", b"- ", b"[", b"]", b"{", b"}", b"[[[[[[[[", b"&a ", b"*a", b"&a [1, 2]", b"<<: *a",
    b"!!python/object:os.system", b"!!binary", b"!!float", b"!!int", b"~", b"null", b"true", b"yes",
    b"---\n", b"...\n", b"%YAML 1.1\n", b"? ", b"|", b">", b"0", b"-0", b"1", b"1e5", b"6e4",
    b"[]", b"{}", b'{"a": 1}', b"[1, 2, 3]",
]


@st.composite
def mutated(draw, seeds: list[bytes]) -> bytes:
    """A valid file after 1-8 byte-level edits (or the valid file itself)."""
    b = bytearray(draw(st.sampled_from(seeds)))
    for _ in range(draw(st.integers(0, 8))):
        op = draw(st.sampled_from(["flip", "insert", "token", "delete", "dup", "truncate", "byte"]))
        pos = draw(st.integers(0, len(b)))
        if op == "flip" and b:
            i = min(pos, len(b) - 1)
            b[i] ^= 1 << draw(st.integers(0, 7))
        elif op == "byte" and b:
            b[min(pos, len(b) - 1)] = draw(st.integers(0, 255))
        elif op == "insert":
            b[pos:pos] = draw(st.binary(min_size=1, max_size=8))
        elif op == "token":
            b[pos:pos] = draw(st.sampled_from(TOKENS))
        elif op == "delete":
            del b[pos:pos + draw(st.integers(1, 40))]
        elif op == "dup":
            n = draw(st.integers(1, 200))
            b[pos:pos] = b[pos:pos + n] * draw(st.integers(1, 4))
        elif op == "truncate":
            del b[pos:]
    return bytes(b)


@functools.cache   # a strategy is built (and validated) once
def numberish() -> st.SearchStrategy:
    """Text that is, or is close to, a number."""
    return st.one_of(
        st.floats(allow_nan=True, allow_infinity=True).map(repr),
        st.integers().map(str),
        st.integers(min_value=10 ** 20, max_value=10 ** 400).map(str),
        st.sampled_from(["", " ", "nan", "inf", "-inf", "1_0", "0x10", "1e400", "1,5", "--1",
                         "+-1", "1e", ".", "٣", "１", "1.5.2", "0" * 300, "1" * 5000]),
        st.text(max_size=12),
    )


@functools.cache   # a strategy is built (and validated) once
def scalars() -> st.SearchStrategy:
    """YAML/JSON leaf values: huge ints, non-finite floats, unicode, booleans, null."""
    return st.one_of(
        st.none(), st.booleans(), st.integers(), st.integers(min_value=10 ** 18, max_value=10 ** 200),
        st.floats(allow_nan=True, allow_infinity=True), st.text(max_size=20),
        st.sampled_from(["nan", ".inf", "1_0", "", "0", "-1", "\ufeff", "a" * 300]),
    )


@functools.cache   # a strategy is built (and validated) once
def trees(leaves: st.SearchStrategy | None = None) -> st.SearchStrategy:
    """Nested lists and mappings (depth up to ~40, beyond the YAML reader's limit of 32)."""
    leaves = scalars() if leaves is None else leaves
    return st.recursive(
        leaves,
        lambda kids: st.one_of(st.lists(kids, max_size=5),
                               st.dictionaries(st.one_of(st.text(max_size=10), st.integers()), kids, max_size=5)),
        max_leaves=40)


@st.composite
def edited(draw, base: object, keys: list[str]) -> object:
    """``base`` (a JSON-like tree) with 1-4 edits at random places: a value replaced by a random
    tree, a key deleted, a key added (a known or a random one)."""
    data = copy.deepcopy(base)
    for _ in range(draw(st.integers(1, 4))):
        # walk down to a random container
        node = data
        for _ in range(draw(st.integers(0, 4))):
            kids = list(node.values()) if isinstance(node, dict) else node if isinstance(node, list) else []
            kids = [k for k in kids if isinstance(k, (dict, list))]
            if not kids:
                break
            node = draw(st.sampled_from(kids))
        if isinstance(node, dict) and node:
            key = draw(st.sampled_from(sorted(node, key=str)))
            op = draw(st.sampled_from(["replace", "replace", "delete", "add"]))
            if op == "replace":
                node[key] = draw(trees())
            elif op == "delete":
                del node[key]
            else:
                node[draw(st.one_of(st.sampled_from(keys), st.text(max_size=8)))] = draw(trees())
        elif isinstance(node, list) and node:
            i = draw(st.integers(0, len(node) - 1))
            op = draw(st.sampled_from(["replace", "delete", "dup"]))
            if op == "replace":
                node[i] = draw(trees())
            elif op == "delete":
                del node[i]
            else:
                node.append(copy.deepcopy(node[i]))
        elif draw(st.booleans()):
            return draw(trees())
    return data


def yaml_text(tree: object) -> st.SearchStrategy:
    """A tree as YAML text, in block or flow style, optionally with a BOM and CRLF line ends."""
    @st.composite
    def _s(draw):
        try:
            text = yaml.safe_dump(tree, default_flow_style=draw(st.sampled_from([None, True, False])),
                                  allow_unicode=draw(st.booleans()), width=draw(st.sampled_from([80, 10 ** 6])))
        except (yaml.YAMLError, RecursionError):
            text = repr(tree)
        if draw(st.booleans()):
            text = text.replace("\n", "\r\n")
        if draw(st.booleans()):
            text = "\ufeff" + text
        return text.encode("utf-8", "surrogatepass")
    return _s()


class Files:
    """One scratch folder per test; each example overwrites the same files."""

    def __init__(self):
        self.dir = Path(tempfile.mkdtemp(prefix="ctrplan-fuzz-"))

    def write(self, name: str, data: bytes) -> Path:
        p = self.dir / name
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_bytes(data)
        return p


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    f = Files()
    f.dir = tmp_path_factory.mktemp("fuzz")
    return f


# ---------------------------------------------------------------------- seeds (valid files)
def _robot():
    from ctrplan.robot import load_robot

    return load_robot("seed1")


ROBOT_SEEDS = [p.read_bytes() for p in sorted((DATA / "robots").glob("*.yaml"))]
# robots with actuator limits: one block for every tube, and a list of one per tube
ROBOT_SEEDS += [
    ROBOT_SEEDS[0] + b"actuators:\n  rotation: {max_speed: 1.5, max_accel: 6}\n"
                     b"  translation: {max_speed: 8, max_accel: 40}\n",
    ROBOT_SEEDS[0] + b"actuators:\n  - {rotation: {max_speed: 2}}\n  - {}\n"
                     b"  - translation: {max_accel: 30.5}\n",
]
ROBOT_DICTS = [yaml.safe_load(b) for b in ROBOT_SEEDS]
ROBOT_KEYS = ["name", "tubes", "beta_min", "units", "notes", "source", "od", "id", "straight_length",
              "curved_length", "curvature", "youngs_modulus", "poisson_ratio", "density",
              "actuators", "rotation", "translation", "max_speed", "max_accel"]


def _config_csv() -> bytes:
    r = _robot()
    rows = [",".join(r.column_names)]
    q = [[0.1, -2.0, 3.0, -60.0, -40.0, -20.0], [0.0, 0.0, 0.0, -1.0, -0.5, 0.0],
         [3.1, 1.0, -1.0, -100.0, -60.0, -10.0]]
    rows += [",".join(repr(v) for v in row) for row in q]
    return ("\n".join(rows) + "\n").encode()


def _measured_csv(points: bool) -> bytes:
    r = _robot()
    cols = ["time", "sweep", *r.column_names, "tip_x", "tip_y", "tip_z"]
    if points:
        cols += [f"p{k}_{c}" for k in (1, 2) for c in "xyz"]
    rows = [",".join(cols)]
    for k in range(3):
        vals = [str(0.1 * k), f"s{k % 2}", "0.1", "0.2", "0.3", str(-10.0 - k), "-5", "-1",
                "1.5", "-2.5", str(100.0 + k)]
        if points:
            vals += ["0", "0", "0", "1", "2", "50"]
        rows.append(",".join(vals))
    return ("\r\n".join(rows) + "\r\n").encode()


@st.composite
def csv_structured(draw, columns: list[str]) -> bytes:
    """A CSV whose header is drawn from the right columns (some missing, duplicated, extra,
    reordered) and whose cells are number-like text; random line ends, quoting and BOM."""
    header = draw(st.lists(st.one_of(st.sampled_from(columns), st.text(max_size=6)),
                           min_size=0, max_size=len(columns) + 3))
    if draw(st.booleans()):
        header = list(columns)
    ncols = len(header)
    rows = draw(st.lists(st.lists(numberish(), min_size=max(ncols - 1, 0), max_size=ncols + 1),
                         max_size=4))
    w = io.StringIO()
    import csv

    writer = csv.writer(w, lineterminator=draw(st.sampled_from(["\n", "\r\n", "\r"])))
    writer.writerow(header)
    writer.writerows(rows)
    text = w.getvalue()
    if draw(st.booleans()):
        text = "\ufeff" + text
    return text.encode("utf-8", "surrogatepass")


# ---------------------------------------------------------------------- CSV readers
CONFIG_SEEDS = [_config_csv()]
MEASURED_SEEDS = [_measured_csv(False), _measured_csv(True)]
ROBOT = _robot()
MEASURED_COLUMNS = ["time", "sweep", *ROBOT.column_names, "tip_x", "tip_y", "tip_z",
                    "p1_x", "p1_y", "p1_z", "p2_x", "p2_y", "p2_z", "p3_x"]


@FUZZ
@given(data=st.one_of(mutated(CONFIG_SEEDS), csv_structured(list(ROBOT.column_names))),
       check=st.booleans())
def test_fuzz_config_csv(files, data, check):
    """Configuration CSV (`shape/check --configs`): read_configs."""
    from ctrplan.robot import read_configs

    path = files.write("configs.csv", data)
    q = check_reader(lambda: read_configs(path, ROBOT, check=check), path)
    if q is not None:
        assert q.ndim == 2 and q.shape[1] == 2 * ROBOT.n and len(q) >= 1
        assert np.all(np.isfinite(q))
        if check:
            assert ROBOT.is_valid(q).all()


@FUZZ
@given(data=st.one_of(mutated(MEASURED_SEEDS), csv_structured(MEASURED_COLUMNS)))
def test_fuzz_measured_csv(files, data):
    """Measured-data CSV (`diagnose/train --data`): read_measured."""
    from ctrplan.measured import read_measured

    path = files.write("measured.csv", data)
    m = check_reader(lambda: read_measured(path, ROBOT), path)
    if m is not None:
        assert m.q.shape == (len(m), 2 * ROBOT.n) and m.tip.shape == (len(m), 3)
        assert np.all(np.isfinite(m.q)) and np.all(np.isfinite(m.tip))
        if m.points is not None:
            assert m.points.shape[0] == len(m) and np.all(np.isfinite(m.points))


# ---------------------------------------------------------------------- robot YAML
def _valid_robot(robot) -> None:
    for t in robot.tubes:
        for k in ("od", "id", "straight_length", "curved_length", "curvature",
                  "youngs_modulus", "poisson_ratio"):
            assert math.isfinite(getattr(t, k)), k
        assert 0 <= t.id < t.od
    assert robot.n >= 1
    speed, accel = robot.joint_limits()
    assert speed.shape == accel.shape == (robot.dof,)
    assert np.all(np.isfinite(speed) & (speed > 0)) and np.all(np.isfinite(accel) & (accel > 0))


@FUZZ
@given(data=st.one_of(mutated(ROBOT_SEEDS),
                      st.sampled_from(ROBOT_DICTS).flatmap(lambda d: edited(d, ROBOT_KEYS)).flatmap(yaml_text),
                      trees().flatmap(yaml_text)))
def test_fuzz_robot_yaml(files, data):
    """Robot YAML (`--robot r.yaml`): load_robot."""
    from ctrplan.robot import load_robot

    path = files.write("robot.yaml", data)
    r = check_reader(lambda: load_robot(path), path)
    if r is not None:
        _valid_robot(r)


# ---------------------------------------------------------------------- scene YAML + folder
def _scene_files(folder: Path) -> tuple[bytes, bytes]:
    """A small valid scene: a closed 40 mm box around the base (ASCII PLY) and its scene.yaml."""
    import trimesh

    box = trimesh.creation.box(extents=(40.0, 40.0, 80.0))
    box.apply_translation((0.0, 0.0, 30.0))
    ply = trimesh.exchange.ply.export_ply(box, encoding="ascii")
    scene = {
        "name": "fuzzbox", "units": "mm", "frame": "robot base frame",
        "meshes": [{"name": "wall", "file": "box.ply", "role": "wall", "description": "a box"}],
        "base_pose": {"position": [0.0, 0.0, 0.0], "quaternion": [1.0, 0.0, 0.0, 0.0]},
        "targets": [{"name": "t01", "position": [1.0, 2.0, 30.0]},
                    {"name": "t02", "position": [-1.0, 0.0, 40.0], "config": [0, 0, 0, -50, -30, -10]}],
        "source": "test", "licence": "CC0",
    }
    return yaml.safe_dump(scene, sort_keys=False).encode(), ply


SCENE_YAML, SCENE_PLY = _scene_files(Path("."))
SCENE_DICT = yaml.safe_load(SCENE_YAML)
SCENE_SEEDS = [SCENE_YAML, (REPO / "ctrplan/data/scenes/design_bend/scene.yaml").read_bytes().replace(
    b"lumen.ply", b"box.ply")]
SCENE_KEYS = ["name", "units", "frame", "meshes", "base_pose", "targets", "source", "licence",
              "description", "file", "role", "position", "quaternion", "config"]


@FUZZ
@given(yml=st.one_of(mutated(SCENE_SEEDS), edited(SCENE_DICT, SCENE_KEYS).flatmap(yaml_text),
                     st.sampled_from(SCENE_SEEDS)),
       ply=st.one_of(st.just(SCENE_PLY), mutated([SCENE_PLY])),
       how=st.sampled_from(["folder", "yaml"]))
def test_fuzz_scene(files, yml, ply, how):
    """Scene folder / scene.yaml with its mesh (`--scene DIR`): load_scene."""
    from ctrplan.collision.scene import load_scene

    path = files.write("scene/scene.yaml", yml)
    files.write("scene/box.ply", ply)
    target = path.parent if how == "folder" else path
    s = check_reader(lambda: load_scene(target), path.parent)
    if s is not None:
        assert s.collision_meshes
        assert np.all(np.isfinite(s.base_pose)) and s.base_pose.shape == (4, 4)
        assert np.all(np.isfinite(s.target_positions()))


# ---------------------------------------------------------------------- mesh files
def _mesh_seeds() -> dict[str, list[bytes]]:
    """Valid files of each format: a closed box (OBJ, ASCII and binary PLY and STL)."""
    import trimesh

    box = trimesh.creation.box(extents=(40.0, 40.0, 80.0))
    obj = "".join(f"v {x:g} {y:g} {z:g}\n" for x, y, z in box.vertices)
    obj += "".join(f"f {a + 1} {b + 1} {c + 1}\n" for a, b, c in box.faces)
    rel = obj.split("f ")[0] + "".join(f"f {a - 8} {b - 8} {c - 8}\n" for a, b, c in box.faces)
    return {
        ".obj": [obj.encode(), rel.encode()],
        ".ply": [trimesh.exchange.ply.export_ply(box, encoding="ascii"),
                 trimesh.exchange.ply.export_ply(box, encoding="binary")],
        ".stl": [trimesh.exchange.stl.export_stl(box), trimesh.exchange.stl.export_stl_ascii(box).encode()],
    }


MESH_SEEDS = _mesh_seeds()


@st.composite
def obj_edits(draw) -> bytes:
    """An OBJ with its statements edited by the format's rules: face indices replaced (0,
    negative within and beyond the vertices, past the end, huge, not integers, v/vt/vn forms),
    polygons of 1-6 vertices, vertex lines with missing or odd coordinates, lines dropped or
    repeated."""
    lines = draw(st.sampled_from(MESH_SEEDS[".obj"])).decode().splitlines()
    idx = st.one_of(st.integers(-12, 12), st.sampled_from([0, 2 ** 63, -(2 ** 40), 10 ** 30]))
    for _ in range(draw(st.integers(1, 6))):
        if not lines:
            break
        k = draw(st.integers(0, len(lines) - 1))
        op = draw(st.sampled_from(["index", "polygon", "vertex", "drop", "dup", "form"]))
        if op == "index" and lines[k].startswith("f ") and len(lines[k].split()) > 1:
            tok = lines[k].split()
            tok[draw(st.integers(1, len(tok) - 1))] = str(draw(idx))
            lines[k] = " ".join(tok)
        elif op == "polygon":
            lines.insert(k, "f " + " ".join(str(draw(idx)) for _ in range(draw(st.integers(1, 6)))))
        elif op == "vertex":
            lines.insert(k, "v " + " ".join(draw(st.lists(numberish(), min_size=0, max_size=5))))
        elif op == "drop":
            del lines[k]
        elif op == "dup":
            lines.insert(k, lines[k])
        elif op == "form" and lines[k].startswith("f "):
            tok = lines[k].split()
            lines[k] = " ".join([tok[0]] + [t + draw(st.sampled_from(["/1", "//1", "/1/1", "/", "/x"]))
                                            for t in tok[1:]])
    return ("\n".join(lines) + "\n").encode()


@st.composite
def ply_edits(draw) -> bytes:
    """A PLY with its header edited (element counts off by a little or a lot, the format,
    property types and names, lines dropped) and/or its body cut or extended."""
    data = draw(st.sampled_from(MESH_SEEDS[".ply"]))
    end = data.index(b"end_header")
    head, body = data[:end].decode().splitlines(), data[end:]
    for _ in range(draw(st.integers(1, 4))):
        k = draw(st.integers(1, len(head) - 1))
        tok = head[k].split()
        op = draw(st.sampled_from(["count", "format", "type", "drop", "dup"]))
        if len(tok) < 3 and op in ("count", "format", "type"):
            continue
        if op == "count" and tok[0] == "element":
            tok[2] = str(draw(st.one_of(st.integers(-2, 40), st.sampled_from([2 ** 31, 2 ** 40, 10 ** 20]))))
        elif op == "format" and tok[0] == "format":
            tok[1] = draw(st.sampled_from(["ascii", "binary_little_endian", "binary_big_endian", "text"]))
        elif op == "type" and tok[0] == "property":
            tok[1 if tok[1] != "list" else draw(st.integers(2, 3))] = draw(
                st.sampled_from(["uchar", "int", "float", "double", "int64", "list"]))
        elif op == "drop":
            tok = []
        elif op == "dup":
            tok = tok + ["\n" + head[k]]
        head[k] = " ".join(tok)
    if draw(st.booleans()):
        cut = draw(st.integers(0, len(body)))
        body = body[:cut] + draw(st.binary(max_size=64))
    return ("\n".join(h for h in head if h) + "\n").encode() + body


@st.composite
def stl_edits(draw) -> bytes:
    """A binary STL with its triangle count replaced and/or its body cut at triangle
    boundaries or anywhere; or an ASCII STL with its keywords mutated."""
    data = bytearray(draw(st.sampled_from(MESH_SEEDS[".stl"])))
    if data.startswith(b"solid") and draw(st.booleans()):
        return draw(mutated([bytes(data)]))
    if draw(st.booleans()) and len(data) >= 84:
        data[80:84] = draw(st.integers(0, 2 ** 32 - 1)).to_bytes(4, "little")
    if draw(st.booleans()):
        n = draw(st.integers(0, len(data) // 50 + 1))
        data = data[:draw(st.sampled_from([84 + 50 * n, draw(st.integers(0, len(data)))]))]
    return bytes(data)


@FUZZ
@given(kind_data=st.one_of(
    st.tuples(st.just(".obj"), st.one_of(obj_edits(), mutated(MESH_SEEDS[".obj"]))),
    st.tuples(st.just(".ply"), st.one_of(ply_edits(), mutated(MESH_SEEDS[".ply"]))),
    st.tuples(st.just(".stl"), st.one_of(stl_edits(), mutated(MESH_SEEDS[".stl"])))))
def test_fuzz_mesh_files(files, kind_data):
    """Mesh files (OBJ, PLY, STL; format-aware edits and byte mutations): load_mesh returns
    finite vertices and in-range triangles, or one line naming the file."""
    from ctrplan.collision.scene import load_mesh

    kind, data = kind_data
    path = files.write("mesh" + kind, data)
    m = check_reader(lambda: load_mesh(path), path)
    if m is not None:
        v, f = np.asarray(m.vertices), np.asarray(m.faces)
        assert v.ndim == 2 and v.shape[1] == 3 and np.all(np.isfinite(v))
        assert f.ndim == 2 and f.shape[1] == 3 and len(f) and f.min() >= 0 and f.max() < len(v)


# ---------------------------------------------------------------------- calibrated model YAML
def _calibrated_yaml() -> bytes:
    from ctrplan.shape.effects import MODEL_KIND, EffectModel

    m = EffectModel.from_dict({"kind": MODEL_KIND, "base": "rigid", "robot": ROBOT.to_dict(),
                               "effects": {}, "error_quantiles": {"p50": 0.1, "p95": 0.2, "p99": 0.3, "max": 0.4}})
    p = Path(tempfile.mkdtemp(prefix="ctrplan-fuzz-")) / "calibrated.yaml"
    m.save(p)
    data = p.read_bytes()
    p.unlink()
    p.parent.rmdir()
    return data


CALIBRATED = _calibrated_yaml()
CALIBRATED_DICT = yaml.safe_load(CALIBRATED)
CALIBRATED_KEYS = ["kind", "base", "robot", "effects", "units", "notes", "error_quantiles",
                   "error_profile", "p50", "p95", "p99", "max", "joint_offset", "registration",
                   "tubes", "od", "curvature"]


@FUZZ
@given(data=st.one_of(mutated([CALIBRATED]),
                      edited(CALIBRATED_DICT, CALIBRATED_KEYS).flatmap(yaml_text)))
def test_fuzz_calibrated_model(files, data):
    """Calibrated model (`--model calibrated.yaml`, written by diagnose): load_model."""
    from ctrplan.shape.models import load_model

    path = files.write("calibrated.yaml", data)
    m = check_reader(lambda: load_model(path, ROBOT), path)
    if m is not None:
        assert m.robot.n == ROBOT.n


# ---------------------------------------------------------------------- learned model (.pt)
LEARNED_BYTES = (DATA / "models" / "seed1.pt").read_bytes()
LEARNED_OBJ = torch.load(io.BytesIO(LEARNED_BYTES), map_location="cpu", weights_only=True)
LEARNED_META = json.loads(LEARNED_OBJ["meta_json"])
LEARNED_KEYS = ["architecture", "basis", "normalisation", "width", "depth", "terms", "frame",
                "inputs", "direction", "residual", "kind", "error_quantiles", "error_profile",
                "domain", "beta_min_mm", "beta_max_mm", "alpha_arcs_rad", "robot", "coef_mean",
                "coef_std", "beta_lo_mm", "beta_span_mm"]
Q_PROBE = np.array([[0.0, 0.0, 0.0, -60.0, -40.0, -20.0], [1.0, -1.0, 2.0, -5.0, -3.0, -1.0]])


def _tensor_like() -> st.SearchStrategy:
    return st.one_of(
        st.builds(lambda s, v: torch.full(s, v), st.lists(st.integers(0, 4), max_size=3).map(tuple),
                  st.floats(width=32, allow_nan=True, allow_infinity=True)),
        scalars(), st.lists(st.floats(), max_size=3))


@st.composite
def learned_objects(draw) -> dict:
    """The shipped model's file object with its metadata edited and/or its top level changed."""
    obj = dict(LEARNED_OBJ)
    obj["state"] = dict(LEARNED_OBJ["state"])
    if draw(st.booleans()):
        meta = draw(edited(LEARNED_META, LEARNED_KEYS))
        obj["meta_json"] = draw(st.one_of(st.just(json.dumps(meta, allow_nan=True)),
                                          mutated([json.dumps(meta).encode()]).map(lambda b: b.decode("utf-8", "replace"))))
    for _ in range(draw(st.integers(0 if "meta_json" in obj else 1, 3))):
        op = draw(st.sampled_from(["top", "state", "drop"]))
        if op == "top":
            obj[draw(st.sampled_from(["format", "version", "meta_json", "state", "base", "x"]))] = draw(
                st.one_of(scalars(), trees(), _tensor_like()))
        elif op == "state" and isinstance(obj.get("state"), dict) and obj["state"]:
            k = draw(st.sampled_from(sorted(obj["state"], key=str)))
            obj["state"][k] = draw(_tensor_like())
        elif op == "drop":
            obj.pop(draw(st.sampled_from(sorted(obj, key=str))), None)
    return obj


def _valid_learned(m) -> None:
    assert m.robot.n >= 1
    with no_hang():
        shp = m.shape(Q_PROBE[:, : 2 * m.robot.n] if m.robot.n == 3 else
                      np.zeros((1, 2 * m.robot.n)), points=8)
    # a shape it cannot trust is marked, never reported ok
    bad = ~np.all(np.isfinite(shp.points.reshape(len(shp.ok), -1)), axis=1)
    assert not np.any(shp.ok & bad), "non-finite shape reported ok"


@FUZZ
@given(obj=learned_objects())
def test_fuzz_learned_metadata(obj):
    """Learned model file contents (after torch.load(weights_only=True)): the metadata dict,
    the weights and the top-level keys."""
    from ctrplan.shape.learned import LearnedModel

    src = "fuzz.pt"
    m = check_reader(lambda: LearnedModel._from_object(obj, src, None), src)
    if m is not None:
        _valid_learned(m)


@FUZZ
@given(data=mutated([LEARNED_BYTES]))
def test_fuzz_learned_bytes(files, data):
    """Learned model file bytes (`--model m.pt`): load_model reads it with weights_only."""
    from ctrplan.shape.models import load_model

    path = files.write("model.pt", data)
    m = check_reader(lambda: load_model(path, ROBOT), path)
    if m is not None:
        _valid_learned(m)


# ---------------------------------------------------------------------- plan.json
PLAN = {"scene": "airway", "robot": "seed1", "model": "physics", "planner": "rrtconnect",
        "status": "SUCCESS", "target": [1.0, 2.0, 3.0], "tip_path": [[0, 0, 0], [1, 2, 3]],
        "path": [[0.0, 0.0, 0.0, -60.0, -40.0, -20.0], [0.1, 0.2, 0.3, -50.0, -30.0, -10.0]]}
PLAN_KEYS = ["scene", "robot", "model", "path", "target", "tip_path", "status", "planner"]


def _json_bytes(tree) -> st.SearchStrategy:
    return st.sampled_from([0, 1, None]).map(
        lambda indent: json.dumps(tree, indent=indent, allow_nan=True).encode())


@FUZZ
@given(data=st.one_of(mutated([json.dumps(PLAN, indent=1).encode()]),
                      edited(PLAN, PLAN_KEYS).flatmap(_json_bytes),
                      trees().flatmap(_json_bytes)))
def test_fuzz_plan_json(files, data):
    """plan.json (`view --plan`): read_plan."""
    from ctrplan.commands.view import read_plan

    path = files.write("plan.json", data)
    plan = check_reader(lambda: read_plan(path), path)
    if plan is not None:
        assert plan["_q"].ndim == 2 and np.all(np.isfinite(plan["_q"]))


# ---------------------------------------------------------------------- plan-batch inputs
TARGETS_CSV = b"scene,name,x,y,z\nairway,a,1,2,3\nneuro,b,30,0,40\n"
#: with tip pose goals (standoff, approach normal / a direction, cone) and a point row
GOAL_TARGETS_CSV = (b"scene,name,x,y,z,standoff_mm,approach,cone_deg\nairway,a,1,2,3,2,normal,15\n"
                    b"airway,b,1,2,3,,0 0 -1,\nairway,c,1,2,3,0.5,\"1,0,0\",30\nairway,d,1,2,3,,,\n")


@FUZZ
@given(data=st.one_of(mutated([TARGETS_CSV, b"x,y,z\n1,2,3\n", GOAL_TARGETS_CSV]),
                      csv_structured(["scene", "name", "x", "y", "z"]),
                      csv_structured(["scene", "name", "x", "y", "z", "standoff_mm", "approach",
                                      "cone_deg"])),
       scenes=st.sampled_from([(), ("airway",)]))
def test_fuzz_batch_targets(files, data, scenes):
    """plan-batch targets CSV (`plan-batch --targets t.csv`, tip goal columns too): read_targets."""
    from ctrplan.planning.batch import GOAL_FIELDS, Job, read_targets
    from ctrplan.planning.tipgoal import MAX_STANDOFF_MM

    path = files.write("targets.csv", data)
    out = check_reader(lambda: read_targets(str(path), scenes), path)
    if out is not None:
        assert out and all(len(t[2]) == 3 and all(math.isfinite(v) for v in t[2]) for t in out)
        for t in out:
            if len(t) == 3:
                continue
            standoff, approach, cone = (t[3][k] for k in GOAL_FIELDS)
            assert standoff is None or 0 <= standoff <= MAX_STANDOFF_MM
            assert cone is None or (0 < cone <= 90 and approach is not None)
            if approach not in (None, "normal"):
                v = [float(x) for x in approach.split(",")]
                assert len(v) == 3 and all(math.isfinite(x) for x in v) and any(v)
            assert Job(t[0], t[1], t[2], **t[3]).has_tip_goal


def _job():
    from ctrplan.planning.batch import Job

    return Job(scene="airway", target_name="a", target=(1.0, 2.0, 3.0), seed=0)


JOB = _job()
JOB_JSON = {"job_id": JOB.id, "scene": "airway", "target_name": "a", "target": [1.0, 2.0, 3.0],
            "seed": 0, "robot": "seed1", "model": "physics", "planner": "rrtconnect",
            "time_limit": 5.0, "tolerance_mm": 1.0, "margin": "auto", "objective": "clearance",
            "success": True, "status": "SUCCESS", "message": "", "planning_time_s": 0.5,
            "path": PLAN["path"]}
JOB_KEYS = list(JOB_JSON)


@FUZZ
@given(data=st.one_of(mutated([json.dumps(JOB_JSON).encode()]),
                      edited(JOB_JSON, JOB_KEYS).flatmap(_json_bytes)))
def test_fuzz_batch_job_file(files, data):
    """plan-batch job result file read on `--resume`: a finished job is recognised or re-run,
    and the summary tables are written either way (an edited file never crashes the batch)."""
    from ctrplan.planning import batch

    path = files.write("jobs/job.json", data)

    def resume():
        done = batch._done(path, JOB)
        results = [done] if done is not None else []
        rows = batch.summarize(results)
        batch.write_tables(files.dir / "out", results, rows)
        return rows

    (files.dir / "out").mkdir(exist_ok=True)
    check_reader(resume, path)


# ---------------------------------------------------------------------- numeric CLI options
#: (command argv with a missing input that stops any real work, numeric options)
MISSING = "{out}/missing/ctrplan-fuzz"
COMMANDS = [
    (["shape", "--robot", "seed1", "--configs", f"{MISSING}.csv", "--out", "{out}/s.csv"], ["--points"]),
    (["check", "--robot", "seed1", "--scene", "airway", "--configs", f"{MISSING}.csv",
      "--out", "{out}/c.csv"], ["--points", "--margin"]),
    (["simulate", "--robot", f"{MISSING}.yaml", "--out", "{out}/m.csv"],
     ["--n", "--sweeps", "--noise", "--points", "--step", "--seed"]),
    (["train", "--robot", f"{MISSING}.yaml", "--out", "{out}/m.pt"],
     ["--sim", "--real-sim", "--width", "--depth", "--terms", "--epochs", "--fine-epochs",
      "--patience", "--lr", "--batch-size", "--points", "--seed", "--workers", "--threads"]),
    (["plan", "--robot", f"{MISSING}.yaml", "--scene", "airway", "--target", "1,2,3",
      "--out", "{out}/p.json"], ["--time", "--tolerance", "--seed", "--margin", "--rate",
                                   "--standoff", "--approach", "--cone"]),
    (["plan-batch", "--robot", f"{MISSING}.yaml", "--targets", f"{MISSING}.csv", "--out", "{out}/b"],
     ["--seeds", "--workers", "--time", "--tolerance", "--margin"]),
    (["view", f"{MISSING}.json", "--out", "{out}/v.html"], ["--points"]),
    (["diagnose", "--robot", f"{MISSING}.yaml", "--data", f"{MISSING}.csv", "--out", "{out}/d"],
     ["--holdout", "--bic-threshold", "--min-gain", "--seed", "--test-fraction"]),
    (["design", "--scene", f"{MISSING}", "--targets", "t01", "--out", "{out}/g"],
     ["--tubes", "--seed", "--budget", "--time", "--workers", "--strain-limit", "--min-gap",
      "--max-length", "--max-stroke"]),
    (["scene", "from-labels", f"{MISSING}.nii.gz", "--wall", "1", "--entry", "0,0,0",
      "--toward", "0,0,1", "--out", "{out}/sc"], ["--max-shift", "--max-mb"]),
    (["demo", "--out", "{out}/afile/demo"], ["--time", "--seed"]),   # afile: a file
]


def _option_cases():
    return st.sampled_from([(argv, opt) for argv, opts in COMMANDS for opt in opts])


@pytest.fixture(scope="module")
def fast_cli():
    """main() as the command line runs it, less two fixed costs per call that have nothing to
    do with the options: the parser is built once, and the interrupt guard (signal handlers and
    a watchdog process) is left out."""
    parser = cli.build_parser()
    mp = pytest.MonkeyPatch()
    mp.setattr(cli, "build_parser", lambda: parser)
    from ctrplan import interrupt

    mp.setattr(interrupt, "guard", contextlib.nullcontext)
    yield
    mp.undo()


@FUZZ
@given(case=_option_cases(), value=numberish(), equals=st.booleans())
def test_fuzz_cli_numeric_options(files, capsys, fast_cli, case, value, equals):
    """Every numeric option, any value: exit 2 with one bounded error line, never a traceback
    (the inputs named are missing, so a value that is accepted ends at the missing file)."""
    argv, opt = case
    argv = [a.replace("{out}", str(files.dir)) for a in argv]
    files.write("afile", b"")
    extra = [f"{opt}={value}"] if equals or value.startswith("-") else [opt, value]
    capsys.readouterr()
    threads = torch.get_num_threads()
    with no_hang():
        try:
            rc = cli.main(["-q", *argv, *extra])
        except SystemExit as exc:   # argparse refuses the value before main's handler
            rc = exc.code
        finally:
            torch.set_num_threads(threads)   # `train --threads` sets it for the process
    out, err = capsys.readouterr()
    assert "Traceback" not in err
    assert rc == 2, f"exit {rc} for {opt} {value[:80]!r}: {err[-300:]!r}"
    lines = [ln for ln in err.splitlines() if ln.strip()]
    errors = [ln for ln in lines if "error:" in ln]
    assert len(errors) == 1, f"expected one error line for {opt} {value[:80]!r}: {err[-600:]!r}"
    assert "unrecognized arguments" not in err and "arguments are required" not in err, err[-300:]
    assert len(errors[0]) <= MAX_MESSAGE, f"error line of {len(errors[0])} characters for {opt}"
