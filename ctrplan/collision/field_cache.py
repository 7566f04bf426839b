"""The distance-field cache: entries that verify what they hold.

Fields are cached on disk (``$CTRPLAN_CACHE`` or ``~/.cache/ctrplan``), named by a hash of the
mesh bytes (vertices and faces) and the field parameters. Each entry also stores that full hash
and a hash of its own arrays; on load both are checked, with the arrays' shapes, types and the
mesh's bounding box, and an entry that is unreadable, truncated, empty, tampered with or built
from another mesh is rebuilt with a one-line warning (and replaced). Entries are written to a
unique temporary file in the same folder, flushed and renamed into place (atomic): a reader
never sees a partial file, and two processes building the same entry each write a whole file
(the last rename wins, both are the same field).
"""

from __future__ import annotations

import contextlib
import hashlib
import logging
import math
import os
from pathlib import Path

import numpy as np

from ctrplan.collision.field import FIELD_VERSION, DistanceField, FieldConfig, build_field

log = logging.getLogger("ctrplan")


def cache_dir() -> Path:
    """Folder for cached fields: ``$CTRPLAN_CACHE`` or ``~/.cache/ctrplan``."""
    env = os.environ.get("CTRPLAN_CACHE")
    return Path(env) if env else Path.home() / ".cache" / "ctrplan"


def mesh_digest(vertices: np.ndarray, faces: np.ndarray, config: FieldConfig,
                watertight: bool) -> str:
    """sha256 (hex) of the mesh bytes and everything the field is built from."""
    h = hashlib.sha256()
    h.update(f"v{FIELD_VERSION}:{config}:{bool(watertight)}".encode())
    h.update(np.ascontiguousarray(vertices, dtype=np.float64).tobytes())
    h.update(np.ascontiguousarray(faces, dtype=np.int64).tobytes())
    return h.hexdigest()


def mesh_key(vertices: np.ndarray, faces: np.ndarray, config: FieldConfig,
             watertight: bool = False) -> str:
    """The cache entry's name: the first 32 hex digits of :func:`mesh_digest`."""
    return mesh_digest(vertices, faces, config, watertight)[:32]


_ARRAYS = ("origin", "h", "lb", "ub", "box_lo", "box_hi", "rho", "side", "watertight")


def _content_digest(arrays: dict) -> str:
    h = hashlib.sha256()
    for name in _ARRAYS:
        a = np.ascontiguousarray(arrays[name])
        h.update(f"{name}:{a.dtype.str}:{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _read_entry(path: Path, digest: str, v: np.ndarray, config: FieldConfig) -> DistanceField:
    """The field stored at ``path``; ValueError (with the reason) unless it is whole, made for
    this mesh and these parameters, and consistent."""
    with open(path, "rb") as fh, np.load(fh, allow_pickle=False) as z:
        if str(z["mesh_digest"]) != digest:
            raise ValueError("built from another mesh or other parameters")
        arrays = {name: np.array(z[name]) for name in _ARRAYS}
        if str(z["content_digest"]) != _content_digest(arrays):
            raise ValueError("its arrays do not match their recorded hash")
    lb, ub, side = arrays["lb"], arrays["ub"], arrays["side"]
    box_lo, box_hi = v.min(axis=0), v.max(axis=0)
    ok = (lb.dtype == np.float32 and ub.dtype == np.float32 and side.dtype == np.int8
          and lb.ndim == 3 and lb.shape == ub.shape == side.shape
          and np.array_equal(arrays["box_lo"], box_lo) and np.array_equal(arrays["box_hi"], box_hi)
          and float(arrays["h"]) >= config.h_mm and np.all(np.isfinite(arrays["origin"]))
          and math.isfinite(float(arrays["rho"])) and float(arrays["rho"]) >= 0)
    if not ok:
        raise ValueError("inconsistent arrays")
    return DistanceField(origin=arrays["origin"], h=float(arrays["h"]), lb=lb, ub=ub,
                         box_lo=box_lo, box_hi=box_hi, rho=float(arrays["rho"]), side=side,
                         watertight=bool(arrays["watertight"]))


def _write_entry(path: Path, field: DistanceField, digest: str) -> None:
    """Write atomically: a unique temporary file in the same folder, flushed, renamed."""
    import tempfile

    arrays = {"origin": field.origin, "h": np.float64(field.h), "lb": field.lb, "ub": field.ub,
              "box_lo": field.box_lo, "box_hi": field.box_hi, "rho": np.float64(field.rho),
              "side": field.side, "watertight": np.bool_(field.watertight)}
    fd, tmp = tempfile.mkstemp(prefix=path.name + ".", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as fh:
            np.savez(fh, mesh_digest=np.str_(digest), content_digest=np.str_(_content_digest(arrays)),
                     **arrays)
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def field_for(mesh, config: FieldConfig | None = None, cache: bool | Path = True,
              watertight: bool | None = None) -> DistanceField:
    """The distance field of a trimesh mesh, from the disk cache when a verified entry is there
    (module docstring). ``watertight``: whether the mesh is closed on its own (side
    information); None asks trimesh."""
    config = config or FieldConfig()
    v = np.asarray(mesh.vertices, dtype=float)
    f = np.asarray(mesh.faces, dtype=np.int64)
    closed = bool(mesh.is_watertight) if watertight is None else bool(watertight)
    folder = path = None
    digest = mesh_digest(v, f, config, closed)
    if cache:
        folder = cache_dir() if cache is True else Path(cache)
        path = folder / f"field-{digest[:32]}.npz"
        if path.is_file():
            try:
                return _read_entry(path, digest, v, config)
            except Exception as exc:  # noqa: BLE001 - any unreadable entry is rebuilt
                log.warning("distance-field cache %s is unusable (%s: %s); rebuilding it", path,
                            exc.__class__.__name__, str(exc)[:120].replace("\n", " "))
    log.info("preparing the distance field of a %d-triangle mesh (once; cached in %s)",
             len(f), folder if folder is not None else "memory only")
    field = build_field(v, f, config, watertight=closed, progress=True)
    if path is not None:
        try:
            folder.mkdir(parents=True, exist_ok=True)
            _write_entry(path, field, digest)
        except OSError as exc:  # a read-only cache only costs time
            log.warning("could not write field cache in %s (%s)", folder, exc)
    return field
