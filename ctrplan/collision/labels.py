"""Scenes from segmented medical images: a NIfTI label map to a planning scene.

    scene_from_labels("seg.nii.gz", "my_scene/", wall=["airway"], obstacle=[5, 6],
                      entry=(x, y, z), toward=(x, y, z), targets=["tumour"])

Coordinates are those of the image's scanner frame as NIfTI defines it, RAS+ (x increases to
the subject's Right, y to Anterior, z to Superior), in mm: the sform when its code is set, else
the qform, else the voxel sizes alone (a warning).
A DICOM/ITK point in LPS is (-x, -y, z) here.

Roles: ``wall`` labels are the lumen the robot stays inside; they are meshed together as one
surface (adjacent wall labels such as trachea and bronchi would otherwise put a surface across
the lumen where they meet). ``obstacle`` and ``landmark`` labels get one mesh each. Surfaces are
made by :mod:`ctrplan.collision.label_mesh` within a stated bound on how far they may move from
the voxel (marching-cubes) surface: by default half the smallest voxel size.

Inputs are untrusted: the header is checked before any voxel is read (not NIfTI, 4-D, not
an integer image, singular affine, over the memory budget), a gzip stream is never
decompressed beyond what the header declares (plus 1 MiB), and a label table is read with caps.
The scene is written to a temporary folder beside ``out`` and renamed into place only once it
loads with :func:`ctrplan.collision.scene.load_scene`.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import logging
import os
import re
import shutil
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import yaml

from ctrplan.collision.nifti import DEFAULT_MAX_MB, LabelImage, read_label_image
from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")

#: Caps on a label table.
TABLE_MAX_BYTES = 4 << 20
TABLE_MAX_ENTRIES = 65536

_SUFFIXES = (".nii.gz", ".nii")
_TABLE_SUFFIXES = (".ctbl", ".txt", ".json")


# ---------------------------------------------------------------------------- configuration
@dataclass(frozen=True)
class LabelSceneConfig:
    """How a label map becomes a scene.

    max_shift_mm : how far (mm) a surface may move from the marching-cubes surface of its
        voxels, measured both ways (None: half the smallest voxel size).
    smoothing_iterations : Taubin lambda/mu pairs.
    max_mb : memory budget (MB) for the volume: stored voxels plus working copies.
    licence : written into scene.yaml (the terms of the image you segmented).
    label_table : a label table file (None: look beside the image).
    """

    max_shift_mm: float | None = None
    smoothing_iterations: int = 20
    max_mb: float = DEFAULT_MAX_MB
    licence: str = "as the source image (not stated)"
    label_table: str | None = None

    def __post_init__(self) -> None:
        if self.max_shift_mm is not None and not (np.isfinite(self.max_shift_mm) and self.max_shift_mm > 0):
            raise InputError("max_shift_mm", "", f"must be a number > 0, got {self.max_shift_mm!r}")
        if not (isinstance(self.smoothing_iterations, int) and 0 <= self.smoothing_iterations <= 1000):
            raise InputError("smoothing_iterations", "", "must be an integer in [0, 1000]")
        if not (np.isfinite(self.max_mb) and self.max_mb > 0):
            raise InputError("max_mb", "", f"must be a number > 0, got {self.max_mb!r}")


@dataclass(frozen=True)
class LabelMesh:
    """One mesh of the written scene: its name, role, the label values it was made from, the
    voxel count, and how its surface was made (:class:`~ctrplan.collision.label_mesh.SurfaceStats`)."""

    name: str
    role: str
    labels: tuple[int, ...]
    voxels: int
    file: str
    stats: object


@dataclass(frozen=True)
class LabelSceneResult:
    """What :func:`scene_from_labels` wrote: the folder, the loaded scene, one
    :class:`LabelMesh` per mesh, the voxel sizes (mm) and the bound the surfaces met."""

    success: bool
    path: str
    scene: object
    meshes: tuple[LabelMesh, ...]
    voxel_size_mm: tuple[float, float, float]
    max_shift_mm: float
    targets: tuple[tuple[str, tuple[float, float, float]], ...] = field(default=())


# ---------------------------------------------------------------------------- label tables
def find_label_table(image: str | os.PathLike) -> Path | None:
    """A label table beside the image: the same name with .ctbl, .txt or .json."""
    p = Path(image)
    stem = p.name
    for suf in _SUFFIXES:
        if stem.lower().endswith(suf):
            stem = stem[: -len(suf)]
            break
    for suf in _TABLE_SUFFIXES:
        cand = p.with_name(stem + suf)
        if cand.is_file():
            return cand
    return None


_LINE = re.compile(r'^\s*(-?\d+)\s+(?:(.*?)\s*"([^"]*)"\s*$|(\S+))')


def parse_label_table(text: str, src: str, json_format: bool) -> dict[str, int]:
    """Label names -> values from a label table's text.

    JSON: ``{"name": value, ...}`` (or nnU-Net's ``{"labels": {...}}``). Text (3D Slicer
    colour table ``.ctbl``/``.txt``: ``value name r g b a``; ITK-SNAP: ``value r g b a vis msh
    "name"``): one label a line, ``#`` comments. Names are unique; values are integers."""
    if len(text) > TABLE_MAX_BYTES:
        raise InputError(src, "", f"larger than {TABLE_MAX_BYTES >> 20} MB: not a label table")
    out: dict[str, int] = {}

    def add(name: object, value: object, where: str) -> None:
        if not isinstance(name, str) or not name.strip():
            raise InputError(src, where, "a label name must be a non-empty string")
        if isinstance(value, bool) or not isinstance(value, int):
            raise InputError(src, where, f"label value must be an integer, got {value!r}")
        if abs(value) > 2**63 - 1:
            raise InputError(src, where, "label value out of range")
        name = name.strip()
        if name in out:
            raise InputError(src, where, f"duplicate label name {name!r}")
        if len(out) >= TABLE_MAX_ENTRIES:
            raise InputError(src, where, f"more than {TABLE_MAX_ENTRIES} labels")
        out[name] = value

    if json_format:
        try:
            data = json.loads(text)
        except (ValueError, RecursionError) as exc:
            raise InputError(src, "", f"malformed JSON ({exc.__class__.__name__})") from None
        if isinstance(data, dict) and isinstance(data.get("labels"), dict):
            data = data["labels"]
        if not isinstance(data, dict):
            raise InputError(src, "", 'expected a mapping {"name": value, ...}')
        for k, v in data.items():
            add(k, v, str(k))
    else:
        for n, line in enumerate(text.splitlines(), 1):
            s = line.split("#", 1)[0] if not line.lstrip().startswith("#") else ""
            if not s.strip():
                continue
            m = _LINE.match(s)
            if not m:
                raise InputError(src, f"line {n}", "expected 'value name ...' (a Slicer colour table) "
                                 "or 'value r g b a vis msh \"name\"' (ITK-SNAP)")
            name = m.group(3) if m.group(3) is not None else m.group(4)
            add(name, int(m.group(1)), f"line {n}")
    if not out:
        raise InputError(src, "", "no labels in the table")
    return out


def read_label_table(path: str | os.PathLike) -> dict[str, int]:
    """Read a label table file (see :func:`parse_label_table`)."""
    from ctrplan.io import read_text

    p = Path(path)
    if p.is_file() and p.stat().st_size > TABLE_MAX_BYTES:
        raise InputError(str(p), "", f"larger than {TABLE_MAX_BYTES >> 20} MB: not a label table")
    return parse_label_table(read_text(p), str(p), p.suffix.lower() == ".json")


def resolve_labels(refs, table: dict[str, int] | None, table_src: str, field: str) -> list[tuple[str, int]]:
    """Label references (values or names; a string may hold several, comma-separated) ->
    [(name, value)]. Names come from the table; a value without a name is ``label_<v>``."""
    if isinstance(refs, (str, int)):
        refs = [refs]
    tokens: list[object] = []
    for r in refs:
        tokens += [t.strip() for t in r.split(",") if t.strip()] if isinstance(r, str) else [r]
    names_by_value = {v: k for k, v in (table or {}).items()}
    out = []
    for t in tokens:
        if isinstance(t, (int, np.integer)) or (isinstance(t, str) and re.fullmatch(r"-?\d+", t)):
            v = int(t)
            out.append((names_by_value.get(v, f"label_{v}"), v))
            continue
        if not isinstance(t, str):
            raise InputError(field, "", f"a label is a value or a name, got {t!r}")
        if table is None:
            raise InputError(field, "", f"{t!r} is a name but no label table was found ({table_src}); "
                             "give values, or a table with --label-table")
        if t in table:
            out.append((t, table[t]))
            continue
        folded = [k for k in table if k.lower() == t.lower()]
        if len(folded) == 1:
            out.append((folded[0], table[folded[0]]))
            continue
        shown = ", ".join(list(table)[:12]) + (" ..." if len(table) > 12 else "")
        raise InputError(field, "", f"no label named {t!r} in {table_src} (names: {shown})")
    if not out:
        raise InputError(field, "", "no labels given")
    return out


# ---------------------------------------------------------------------------- the scene
def _bbox(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray] | None:
    axes = [np.flatnonzero(mask.any(axis=tuple(a for a in range(3) if a != d))) for d in range(3)]
    if any(len(a) == 0 for a in axes):
        return None
    return np.array([a[0] for a in axes]), np.array([a[-1] + 1 for a in axes])


def _safe_name(name: str) -> str:
    s = re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("._") or "label"
    return s[:64]


def pose_from_entry(entry: np.ndarray, toward: np.ndarray) -> np.ndarray:
    """4x4 robot base pose: origin at ``entry``, +z toward ``toward``, +x the scanner axis
    most perpendicular to +z, projected (mm, scanner frame)."""
    z = np.asarray(toward, float) - np.asarray(entry, float)
    n = float(np.linalg.norm(z))
    if not n > 1e-9:
        raise InputError("--toward", "", "must differ from --entry (it sets the insertion direction)")
    z /= n
    hint = np.eye(3)[int(np.argmin(np.abs(z)))]
    x = hint - (hint @ z) * z
    x /= np.linalg.norm(x)
    T = np.eye(4)
    T[:3, :3] = np.column_stack([x, np.cross(z, x), z])
    T[:3, 3] = entry
    return T


def _point(raw, field: str) -> np.ndarray:
    if isinstance(raw, str):
        parts = [s for s in re.split(r"[,\s]+", raw.strip()) if s]
    else:
        parts = list(np.asarray(raw, dtype=object).ravel())
    try:
        v = np.array([float(s) for s in parts])
    except (TypeError, ValueError):
        raise InputError(field, "", f"must be X,Y,Z in mm, got {raw!r}") from None
    if v.shape != (3,) or not np.all(np.isfinite(v)):
        raise InputError(field, "", f"must be three finite numbers X,Y,Z in mm, got {raw!r}")
    return v


def _bare_target(targets) -> bool:
    """Whether ``targets`` is one target rather than a list of them: a name, a value, or three
    numbers."""
    if isinstance(targets, (str, int, np.integer)):
        return True
    if isinstance(targets, np.ndarray):
        return targets.ndim == 1 and targets.size == 3
    return (isinstance(targets, (list, tuple)) and len(targets) == 3
            and all(isinstance(t, (int, float, np.number)) for t in targets)
            and not all(isinstance(t, (int, np.integer)) for t in targets))


def _is_point(raw) -> bool:
    """A target given as a point: three numbers (a string ``X,Y,Z`` or a sequence)."""
    if isinstance(raw, str):
        parts = [s for s in re.split(r"[,\s]+", raw.strip()) if s]
        try:
            [float(s) for s in parts]
        except ValueError:
            return False
        return len(parts) == 3
    return not isinstance(raw, (int, np.integer)) and np.size(raw) == 3


def _label_target(img: LabelImage, value: int, bbox) -> np.ndarray:
    """The voxel of a label nearest its centroid (scanner frame, mm): inside the label even
    where the label is curved."""
    lo, hi = bbox
    crop = img.data[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] == value
    ijk = np.argwhere(crop) + lo
    xyz = img.to_scanner(ijk)
    c = xyz.mean(axis=0)
    return xyz[int(np.argmin(np.linalg.norm(xyz - c, axis=1)))]


def _given(refs) -> bool:
    if refs is None:
        return False
    if isinstance(refs, str):
        return bool(refs.strip())
    if isinstance(refs, (int, np.integer)):
        return True
    return len(refs) > 0


def _check_out(out: Path) -> None:
    if out.exists() and not out.is_dir():
        raise InputError("--out", "", f"{str(out)!r} is a file, expected a folder")
    if out.is_dir() and any(out.iterdir()) and not (out / "scene.yaml").is_file():
        raise InputError("--out", "", f"{str(out)!r} is a folder with other files in it (not a "
                         "scene folder): choose a new or empty folder")


def _label_groups(wall, obstacle, landmark, table: dict[str, int] | None,
                  table_src: str) -> dict[str, list[tuple[str, int]]]:
    """role -> (name, value) of its labels; a label may have one role only (InputError)."""
    groups = {"wall": resolve_labels(wall, table, table_src, "--wall")}
    for role, refs in (("obstacle", obstacle), ("landmark", landmark)):
        if _given(refs):
            groups[role] = resolve_labels(refs, table, table_src, f"--{role}")
    seen: dict[int, str] = {}
    for role, labs in groups.items():
        for _, v in labs:
            if v in seen and seen[v] != role:
                raise InputError(f"--{role}", "", f"label {v} is also given as {seen[v]}")
            seen[v] = role
    return groups


class _Boxes(dict):
    """label value -> voxel bounding box (lo, hi) of a label image, found once per label."""

    def __init__(self, img: LabelImage):
        super().__init__()
        self.img = img

    def of(self, v: int, lname: str, fieldname: str) -> tuple[np.ndarray, np.ndarray]:
        """The box of label ``v``; InputError naming ``fieldname`` when it has no voxels."""
        if v not in self:
            bb = _bbox(self.img.data == v)
            if bb is None:
                raise InputError(self.img.path, fieldname, f"label {v} ({lname}) has no voxels")
            self[v] = bb
        return self[v]


def _resolve_targets(targets, img: LabelImage, boxes: _Boxes, table: dict[str, int] | None,
                     table_src: str) -> list[tuple[str, np.ndarray]]:
    """(name, position mm) of every target: points as given (named t01, t02, ...), label
    references at the label voxel nearest its centroid."""
    if _bare_target(targets):
        targets = [targets]             # one target given bare: a name, a value or a point
    tgt = []
    for k, t in enumerate(targets or ()):
        if _is_point(t):
            tgt.append((f"t{k + 1:02d}", _point(t, "--targets")))
            continue
        for lname, v in resolve_labels(t, table, table_src, "--targets"):
            tgt.append((_safe_name(lname), _label_target(img, v, boxes.of(v, lname, "--targets"))))
    return tgt


def _mesh_job(img: LabelImage, role: str, labs: list[tuple[str, int]], boxes: _Boxes, used: set,
              bound: float, config: LabelSceneConfig, bar):
    """The surface mesh of one job (the wall labels together, or one other label): cropped to
    the labels' boxes, named uniquely (``used``), shown on the progress ``bar`` while it is
    meshed. Returns (LabelMesh, the mesh)."""
    from ctrplan.collision.label_mesh import label_surface

    values = [v for _, v in labs]
    lo = np.min([boxes[v][0] for v in values], axis=0)
    hi = np.max([boxes[v][1] for v in values], axis=0)
    sub = img.data[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]]
    crop = np.zeros(sub.shape, dtype=bool)
    for v in values:            # (a loop of == beats np.isin's sort here)
        crop |= sub == v
    mname = _safe_name("_".join(n for n, _ in labs) if role != "wall" or len(labs) == 1
                       else "lumen_" + "_".join(n for n, _ in labs))
    while mname in used:
        mname += "_"
    used.add(mname)
    bar.set_postfix_str(mname)
    mesh, stats = label_surface(crop, img.affine, lo, bound, config.smoothing_iterations)
    voxels = int(crop.sum())
    log.info("%s (%s, labels %s): %d voxels -> %d triangles, within %.3f mm of the voxel "
             "surface", mname, role, values, voxels, stats.faces, stats.max_shift_mm)
    return LabelMesh(mname, role, tuple(values), voxels, f"{mname}.ply", stats), mesh


def _scene_doc(img: LabelImage, meshes: list[LabelMesh], pose: np.ndarray, tgt: list, bound: float,
               name: str | None, table_src: str, config: LabelSceneConfig, command: str) -> dict:
    """The scene.yaml document: frame, provenance (the label map's digest), meshes, base pose
    and targets."""
    from ctrplan.collision.scene import matrix_to_quaternion

    src = img.path
    stem = Path(src).name
    digest = hashlib.sha256(Path(src).read_bytes()).hexdigest()[:16]
    vs = img.voxel_size
    return {
        "name": name or _safe_name(re.sub(r"\.nii(\.gz)?$", "", stem, flags=re.I)),
        "units": "mm",
        "frame": f"scanner frame of {stem} ({img.affine_source} affine; NIfTI RAS+: x right, "
                 "y anterior, z superior), mm",
        "description": f"from the label map {stem} ({' x '.join(map(str, img.data.shape))} voxels "
                       f"of {vs[0]:.4g} x {vs[1]:.4g} x {vs[2]:.4g} mm); surfaces within "
                       f"{bound:.4g} mm of the voxel surfaces",
        "meshes": [{"name": m.name, "file": m.file, "role": m.role,
                    "description": f"label(s) {', '.join(map(str, m.labels))}: {m.voxels} voxels, "
                                   f"{m.stats.faces} triangles, at most {m.stats.max_shift_mm:.3f} mm "
                                   f"from the marching-cubes surface (bound {m.stats.bound_mm:.3f} mm)"}
                   for m in meshes],
        "base_pose": {"position": [round(float(x), 6) for x in pose[:3, 3]],
                      "quaternion": [round(float(x), 10) for x in matrix_to_quaternion(pose[:3, :3])]},
        "targets": [{"name": n, "position": [round(float(x), 6) for x in p]} for n, p in tgt],
        "source": f"label map {stem} (sha256 {digest}...); label table: {table_src}",
        "licence": config.licence,
        "generator": command or "ctrplan.scene_from_labels",
    }


def scene_from_labels(image: str | os.PathLike, out: str | os.PathLike, *, wall, entry, toward,
                      obstacle=(), landmark=(), targets=(), name: str | None = None,
                      config: LabelSceneConfig | None = None, command: str = "") -> LabelSceneResult:
    """Make a scene folder ``out`` from a NIfTI label map.

    wall, obstacle, landmark : label values or names (a list, or one comma-separated string).
    entry, toward : (3,) mm, scanner frame: the robot base position and a point it points at.
    targets : a list, each a point (3,) mm or label references (the label voxel nearest its
        centroid); one target may be given bare (a name, a value, or a point with a non-integer
        coordinate or as an array: a list of three integers is three labels).
    command : the command that made the scene, written into scene.yaml (``generator``).
    Raises :class:`InputError` for bad input; nothing is written then.
    """
    from ctrplan import progress

    config = config or LabelSceneConfig()
    out = Path(out)
    _check_out(out)
    entry_p, toward_p = _point(entry, "--entry"), _point(toward, "--toward")
    pose = pose_from_entry(entry_p, toward_p)
    img = read_label_image(image, config.max_mb)
    table_path = Path(config.label_table) if config.label_table else find_label_table(image)
    table, table_src = None, "none beside the image"
    if table_path is not None:
        table, table_src = read_label_table(table_path), str(table_path)
    groups = _label_groups(wall, obstacle, landmark, table, table_src)
    bound = config.max_shift_mm or 0.5 * float(img.voxel_size.min())
    # mesh jobs: all wall labels together, every other label alone
    jobs = [("wall", groups["wall"])] + [(role, [lab]) for role in ("obstacle", "landmark")
                                         for lab in groups.get(role, [])]
    # every label and target is checked before the (slow) meshing starts
    boxes = _Boxes(img)
    for role, labs in jobs:
        for lname, v in labs:
            boxes.of(v, lname, f"--{role}")
    tgt = _resolve_targets(targets, img, boxes, table, table_src)
    with progress.bar(total=len(jobs) + 1, desc="from-labels", unit="mesh") as bar:
        meshes, built, used = [], [], set()
        for role, labs in jobs:
            lm, mesh = _mesh_job(img, role, labs, boxes, used, bound, config, bar)
            meshes.append(lm)
            built.append(mesh)
            bar.update(1)
        doc = _scene_doc(img, meshes, pose, tgt, bound, name, table_src, config, command)
        scene = _write_scene(out, doc, meshes, built, pose)
        bar.update(1)
    return LabelSceneResult(success=True, path=str(out), scene=scene, meshes=tuple(meshes),
                            voxel_size_mm=tuple(float(x) for x in img.voxel_size),
                            max_shift_mm=float(bound),
                            targets=tuple((n, tuple(float(x) for x in p)) for n, p in tgt))


class _FlowDumper(yaml.SafeDumper):
    """Writes lists of numbers inline ([x, y, z])."""


def _represent_list(dumper, data):
    flow = all(isinstance(x, (int, float)) for x in data)
    return dumper.represent_sequence("tag:yaml.org,2002:seq", data, flow_style=flow)


_FlowDumper.add_representer(list, _represent_list)


def _write_scene(out: Path, doc: dict, meshes: list[LabelMesh], built: list, pose: np.ndarray):
    """Write into a temporary folder beside ``out``, load it with the scene loader, then rename
    it into place (an existing scene folder is replaced only after the new one loaded)."""
    from ctrplan import interrupt
    from ctrplan.collision.scene import load_scene

    out = out.absolute()
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    written: list[str] = []
    try:
        for m, mesh in zip(meshes, built):
            f = tmp / m.file
            interrupt.pending_added(str(f))
            written.append(str(f))
            mesh.export(f, file_type="ply", encoding="binary")
        text = ("# Written by ctrplan scene from-labels (the command is in `generator`).\n"
                + yaml.dump(doc, Dumper=_FlowDumper, sort_keys=False, width=100))
        (tmp / "scene.yaml").write_text(text, encoding="utf-8")
        try:
            scene = load_scene(tmp)
        except InputError as exc:
            if exc.field.startswith("base_pose"):
                raise InputError("--entry", "", exc.message) from None
            raise
        if out.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{out.name}.old.", dir=out.parent))
            os.rename(out, old / "scene")
            os.rename(tmp, out)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.rename(tmp, out)
    finally:
        if tmp.exists():
            shutil.rmtree(tmp, ignore_errors=True)
        for f in written:
            interrupt.pending_removed(f)
    return dataclasses.replace(scene, path=str(out))
