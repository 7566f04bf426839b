"""Reading NIfTI label maps as untrusted input.

The header is checked before any voxel is read: not a NIfTI-1/2 file, a .hdr/.img pair, more
than three dimensions, a non-numeric data type, a volume over the memory budget. A gzip stream
is never decompressed beyond what the header declares plus 1 MiB (a gzip bomb stops there).
Float images are accepted only when every value is an integer. The affine is the sform when its
code is set, else the qform, else the voxel sizes alone; a singular or non-finite one is refused.
Coordinates are NIfTI's scanner frame, RAS+ (x right, y anterior, z superior), mm.
"""

from __future__ import annotations

import gzip
import io
import logging
import os
import struct
import zlib
from dataclasses import dataclass
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
