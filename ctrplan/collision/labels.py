"""Scenes from segmented medical images: a NIfTI label map to a planning scene.

    scene_from_labels("seg.nii.gz", "my_scene/", wall=["airway"], obstacle=[5, 6],
                      entry=(x, y, z), toward=(x, y, z), targets=["tumour"])

Coordinates are those of the image's scanner frame as NIfTI defines it (RAS+: +x toward the
subject's right... precisely, x increases to the Right, y to the Anterior, z to the Superior),
in mm: the sform when its code is set, else the qform, else the voxel sizes alone (a warning).
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
import gzip
import hashlib
import io
import json
import logging
import os
import re
import shutil
import struct
import tempfile
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")

#: Default memory budget (MB) for reading and meshing one label map.
DEFAULT_MAX_MB = 2048
#: Bytes per voxel the pipeline may hold beyond the stored data (a copy as int, two masks).
WORK_BYTES_PER_VOXEL = 6
#: A gzip stream may decompress to at most this much more than its header declares.
GZIP_SLACK_BYTES = 1 << 20
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


@dataclass(frozen=True)
class LabelImage:
    """A label map in memory: integer labels (I, J, K), the affine voxel -> scanner (mm), and
    which header field the affine came from (``sform``, ``qform`` or ``pixdim``)."""

    path: str
    data: np.ndarray
    affine: np.ndarray
    affine_source: str

    @property
    def voxel_size(self) -> np.ndarray:
        """(3,) mm: the length of each voxel axis in the scanner frame."""
        return np.linalg.norm(self.affine[:3, :3], axis=0)

    def to_scanner(self, ijk: np.ndarray) -> np.ndarray:
        """Voxel indices (..., 3) -> scanner coordinates (..., 3) mm."""
        return np.asarray(ijk, dtype=float) @ self.affine[:3, :3].T + self.affine[:3, 3]

    def to_voxel(self, xyz: np.ndarray) -> np.ndarray:
        """Scanner coordinates (..., 3) mm -> fractional voxel indices (..., 3)."""
        inv = np.linalg.inv(self.affine)
        return np.asarray(xyz, dtype=float) @ inv[:3, :3].T + inv[:3, 3]


# ---------------------------------------------------------------------------- NIfTI reading
@dataclass(frozen=True)
class NiftiHeader:
    """What the checks need from a header: version (1 or 2), shape (I, J, K), dtype, offset of
    the voxel data in bytes, and the parsed nibabel header."""

    version: int
    shape: tuple[int, int, int]
    dtype: np.dtype
    offset: int
    header: object

    @property
    def data_bytes(self) -> int:
        return int(np.prod(self.shape, dtype=np.int64)) * self.dtype.itemsize


def check_header(raw: bytes, src: str, max_mb: float = DEFAULT_MAX_MB) -> NiftiHeader:
    """Check a NIfTI-1/2 header (the first 348 or 540 bytes of the file, more is ignored)
    before any voxel is read; raises :class:`InputError` naming ``src`` and the field."""
    import nibabel as nib

    if len(raw) < 4:
        raise InputError(src, "", "not a NIfTI file (shorter than a header)")
    size_le, size_be = struct.unpack("<i", raw[:4])[0], struct.unpack(">i", raw[:4])[0]
    size = size_le if size_le in (348, 540) else size_be
    if size not in (348, 540):
        raise InputError(src, "sizeof_hdr", f"not a NIfTI file (header size {size_le}, expected "
                         "348 or 540)")
    if len(raw) < size:
        raise InputError(src, "", f"not a NIfTI file (truncated header: {len(raw)} of {size} bytes)")
    version = 1 if size == 348 else 2
    magic = raw[344:348] if version == 1 else raw[4:12]
    if version == 1 and magic == b"ni1\x00":
        raise InputError(src, "magic", "a .hdr/.img pair: save the label map as one .nii or .nii.gz")
    if (version == 1 and magic != b"n+1\x00") or (version == 2 and magic[:4] != b"n+2\x00"):
        raise InputError(src, "magic", f"not a NIfTI file (magic {bytes(magic[:4])!r})")
    cls = nib.Nifti1Header if version == 1 else nib.Nifti2Header
    try:
        hdr = cls.from_fileobj(io.BytesIO(raw[:size]), check=False)
        dims = [int(d) for d in hdr["dim"]]
        dtype = hdr.get_data_dtype()
        offset = int(hdr.get_data_offset())
    except Exception as exc:  # nibabel raises many types for malformed headers
        raise InputError(src, "", f"malformed NIfTI header ({exc.__class__.__name__})") from None
    ndim = dims[0]
    if not 1 <= ndim <= 7:
        raise InputError(src, "dim", f"dim[0] = {ndim}: not 1..7")
    shape = dims[1:1 + ndim]
    if any(d < 1 for d in shape):
        raise InputError(src, "dim", f"image size {'x'.join(map(str, shape))} has an empty or negative axis")
    if ndim > 3 and any(d != 1 for d in shape[3:]):
        raise InputError(src, "dim", f"a {ndim}-D image ({'x'.join(map(str, shape))}): pass one "
                         "3-D label volume")
    shape = (shape + [1, 1, 1])[:3]
    if dtype.kind not in "uif" or dtype.fields is not None:
        raise InputError(src, "datatype", f"a {dtype} image is not a label map (labels are integers)")
    if offset < size:
        raise InputError(src, "vox_offset", f"{offset} lies inside the {size}-byte header")
    nvox = int(np.prod(shape, dtype=np.int64))
    need = nvox * (dtype.itemsize + WORK_BYTES_PER_VOXEL) / 1e6
    if need > max_mb:
        raise InputError(src, "dim", f"a volume of {' x '.join(map(str, shape))} {dtype} voxels needs "
                         f"about {need:,.0f} MB, over the {max_mb:,.0f} MB memory budget (lift it "
                         "with --max-mb, or LabelSceneConfig(max_mb=...) in Python)")
    return NiftiHeader(version, tuple(shape), dtype, offset, hdr)


def _check_affine(hdr, src: str) -> tuple[np.ndarray, str]:
    sform, scode = hdr.get_sform(coded=True)
    qform, qcode = hdr.get_qform(coded=True)
    if scode and sform is not None:
        aff, name = np.asarray(sform, dtype=float), "sform"
    elif qcode and qform is not None:
        aff, name = np.asarray(qform, dtype=float), "qform"
    else:
        aff, name = np.asarray(hdr.get_base_affine(), dtype=float), "pixdim"
        log.warning("%s: no sform or qform: coordinates are voxel indices scaled by pixdim", src)
    if not np.all(np.isfinite(aff)):
        raise InputError(src, name, "the affine has non-finite entries")
    m = aff[:3, :3]
    cols = np.linalg.norm(m, axis=0)
    det = float(np.linalg.det(m))
    if cols.min() <= 0 or abs(det) <= 1e-9 * float(np.prod(cols)):
        raise InputError(src, name, f"singular affine (determinant {det:.3g}): the voxel axes do not "
                         "span 3-D space")
    return aff, name


def _read_bytes(path: Path, src: str, limit: int) -> bytes:
    """The file's contents, decompressed if gzip, never more than ``limit`` bytes."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(2)
            fh.seek(0)
            if head != b"\x1f\x8b":
                data = fh.read(limit + 1)
                return data
            out = bytearray()
            with gzip.GzipFile(fileobj=fh) as gz:
                while len(out) <= limit:
                    chunk = gz.read(min(1 << 22, limit + 1 - len(out)))
                    if not chunk:
                        break
                    out += chunk
            return bytes(out)
    except FileNotFoundError:
        raise InputError(src, "", "file not found") from None
    except (OSError, EOFError, zlib.error) as exc:
        raise InputError(src, "", f"not a NIfTI file (unreadable or corrupt gzip: "
                         f"{exc.__class__.__name__})") from None


def read_label_image(path: str | os.PathLike, max_mb: float = DEFAULT_MAX_MB) -> LabelImage:
    """Read and check a NIfTI-1/2 label map (.nii or .nii.gz)."""
    import nibabel as nib

    p = Path(path)
    src = str(path)
    if not p.is_file():
        raise InputError(src, "", "file not found" if not p.exists() else "not a file")
    first = _read_bytes(p, src, 540)
    hdr = check_header(first, src, max_mb)
    declared = hdr.offset + hdr.data_bytes
    gz = _is_gzip(p)
    raw = _read_bytes(p, src, declared + GZIP_SLACK_BYTES)
    if gz and len(raw) > declared + GZIP_SLACK_BYTES:
        raise InputError(src, "", f"decompresses to more than {(declared + GZIP_SLACK_BYTES) / 1e6:,.1f} "
                         f"MB, more than its header declares ({declared / 1e6:,.1f} MB): stopped "
                         "there (a gzip bomb?)")
    if len(raw) < declared:
        raise InputError(src, "", f"truncated: {max(len(raw) - hdr.offset, 0)} bytes of voxel data, "
                         f"the header declares {hdr.data_bytes}")
    cls = nib.Nifti1Image if hdr.version == 1 else nib.Nifti2Image
    try:
        img = cls.from_bytes(raw[:declared])
        data = np.asanyarray(img.dataobj)
    except Exception as exc:  # nibabel raises many types for malformed files
        raise InputError(src, "", f"unreadable NIfTI data ({exc.__class__.__name__})") from None
    del raw
    data = data.reshape(hdr.shape)
    if data.dtype.kind == "f":
        finite = np.isfinite(data)
        if not finite.all():
            raise InputError(src, "datatype", "a float image with NaN or infinite values is not a label map")
        frac = data != np.round(data)
        if frac.any():
            ex = float(data[frac].flat[0])
            raise InputError(src, "datatype", f"a float image ({hdr.dtype}) with non-integer values "
                             f"(e.g. {ex:.4g}) is not a label map: pass the segmentation")
        if data.size and max(abs(float(data.min())), abs(float(data.max()))) > 2**31:
            raise InputError(src, "datatype", "float labels beyond the int32 range")
        data = data.astype(np.int32)
    affine, name = _check_affine(img.header, src)
    return LabelImage(path=src, data=data, affine=affine, affine_source=name)


def _is_gzip(p: Path) -> bool:
    with open(p, "rb") as fh:
        return fh.read(2) == b"\x1f\x8b"


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


def scene_from_labels(image: str | os.PathLike, out: str | os.PathLike, *, wall, entry, toward,
                      obstacle=(), landmark=(), targets=(), name: str | None = None,
                      config: LabelSceneConfig | None = None, command: str = "") -> LabelSceneResult:
    """Make a scene folder ``out`` from a NIfTI label map.

    wall, obstacle, landmark : label values or names (a list, or one comma-separated string).
    entry, toward : (3,) mm, scanner frame: the robot base position and a point it points at.
    targets : each a point (3,) mm or label references (the label voxel nearest its centroid).
    command : the command that made the scene, written into scene.yaml (``generator``).
    Raises :class:`InputError` for bad input; nothing is written then.
    """
    from ctrplan import progress
    from ctrplan.collision.label_mesh import label_surface
    from ctrplan.collision.scene import matrix_to_quaternion

    config = config or LabelSceneConfig()
    out = Path(out)
    _check_out(out)
    entry_p, toward_p = _point(entry, "--entry"), _point(toward, "--toward")
    pose = pose_from_entry(entry_p, toward_p)
    img = read_label_image(image, config.max_mb)
    src = img.path
    table_path = Path(config.label_table) if config.label_table else find_label_table(image)
    table, table_src = None, "none beside the image"
    if table_path is not None:
        table, table_src = read_label_table(table_path), str(table_path)
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
    bound = config.max_shift_mm or 0.5 * float(img.voxel_size.min())
    # mesh jobs: all wall labels together, every other label alone
    jobs = [("wall", groups["wall"])] + [(role, [lab]) for role in ("obstacle", "landmark")
                                         for lab in groups.get(role, [])]
    with progress.bar(total=len(jobs) + 1, desc="from-labels", unit="mesh") as bar:
        meshes, built, used = [], [], set()
        for role, labs in jobs:
            values = [v for _, v in labs]
            for (lname, v) in labs:
                if not np.any(img.data == v):
                    raise InputError(src, f"--{role}", f"label {v} ({lname}) has no voxels")
            mask = np.isin(img.data, values)
            lo, hi = _bbox(mask)
            crop = np.ascontiguousarray(mask[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]])
            del mask
            mname = _safe_name("_".join(n for n, _ in labs) if role != "wall" or len(labs) == 1
                               else "lumen_" + "_".join(n for n, _ in labs))
            while mname in used:
                mname += "_"
            used.add(mname)
            mesh, stats = label_surface(crop, img.affine, lo, bound, config.smoothing_iterations)
            voxels = int(crop.sum())
            meshes.append(LabelMesh(mname, role, tuple(values), voxels, f"{mname}.ply", stats))
            built.append(mesh)
            log.info("%s (%s, labels %s): %d voxels -> %d triangles, within %.3f mm of the voxel "
                     "surface", mname, role, values, voxels, stats.faces, stats.max_shift_mm)
            bar.update(1)
        tgt = []
        for k, t in enumerate(targets or ()):
            if _is_point(t):
                tgt.append((f"t{k + 1:02d}", _point(t, "--targets")))
                continue
            for lname, v in resolve_labels(t, table, table_src, "--targets"):
                bb = _bbox(img.data == v)
                if bb is None:
                    raise InputError(src, "--targets", f"label {v} ({lname}) has no voxels")
                tgt.append((_safe_name(lname), _label_target(img, v, bb)))
        stem = Path(src).name
        digest = hashlib.sha256(Path(src).read_bytes()).hexdigest()[:16]
        vs = img.voxel_size
        doc = {
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
        scene = _write_scene(out, doc, meshes, built, pose)
        bar.update(1)
    return LabelSceneResult(success=True, path=str(out), scene=scene, meshes=tuple(meshes),
                            voxel_size_mm=tuple(float(x) for x in vs), max_shift_mm=float(bound),
                            targets=tuple((n, tuple(float(x) for x in p)) for n, p in tgt))


def _write_scene(out: Path, doc: dict, meshes: list[LabelMesh], built: list, pose: np.ndarray):
    """Write into a temporary folder beside ``out``, load it with the scene loader, then rename
    it into place (an existing scene folder is replaced only after the new one loaded)."""
    import yaml

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
                + yaml.safe_dump(doc, sort_keys=False, width=100))
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
