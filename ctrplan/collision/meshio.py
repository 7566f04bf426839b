"""Mesh file readers that follow each format's rules.

- **OBJ** (read here): ``v x y z [w | r g b]`` and ``f`` lines whose vertex references are
  1-based (``1`` is the first vertex of the file) or negative (relative: ``-1`` is the vertex
  defined last before that line), in the forms ``i``, ``i/t``, ``i//n``, ``i/t/n``. Index ``0``
  is refused (OBJ has no vertex 0), so is a reference past the vertices defined. Polygons are
  split into a fan of triangles; other statements (``vt``, ``vn``, ``o``, ``g``, ``s``,
  ``usemtl``, ``l``, ...) are ignored, ``#`` starts a comment, ``\\`` joins lines.
- **PLY**: the header is checked here (``ply``, a ``format`` line, ``element`` counts that are
  non-negative integers, a ``vertex`` element with ``x``, ``y``, ``z`` and a ``face`` element with
  a ``vertex_indices`` list, ``end_header``; a binary body at least as long as the header
  declares), then trimesh reads the body; the vertex count read must equal the declared one.
- **STL**: binary when the 80-byte header's triangle count ``n`` gives exactly ``84 + 50 n``
  bytes (read here), else ASCII when it begins with ``solid`` (read by trimesh); anything else
  is refused with both sizes.
- Other formats (glTF, OFF, ...): trimesh.

:func:`mesh_triangles` reads only a header (or the file size) to say how many triangles a file
holds, for the work estimate made before anything is read (:mod:`ctrplan.collision.budget`).
Every error is an :class:`~ctrplan.errors.InputError` naming the file (and the line or header
field).
"""

from __future__ import annotations

import os
import re
from pathlib import Path

import numpy as np

from ctrplan.errors import InputError

#: Longest PLY header read (bytes).
MAX_PLY_HEADER = 64 << 10
_PLY_TYPES = {"char": 1, "uchar": 1, "short": 2, "ushort": 2, "int": 4, "uint": 4, "float": 4,
              "double": 8, "int8": 1, "uint8": 1, "int16": 2, "uint16": 2, "int32": 4,
              "uint32": 4, "float32": 4, "float64": 8}
_PLY_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")
_INT = re.compile(rb"[-+]?[0-9]+\Z")
_NUM = re.compile(rb"[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][-+]?[0-9]+)?\Z")
#: bytes per triangle of an ASCII STL (for the estimate; a facet is 6-7 lines)
_ASCII_STL_BYTES = 200
#: bytes per triangle of an OBJ (a face line and half a vertex line)
_OBJ_BYTES = 40


def read_mesh(path: str | os.PathLike, data: bytes) -> tuple[np.ndarray, np.ndarray]:
    """(vertices (V, 3) float64 mm, faces (F, 3) int64) of a mesh file whose bytes are ``data``.
    Raises :class:`InputError` naming ``path``."""
    src = str(path)
    kind = Path(src).suffix.lower()
    if kind == ".obj":
        return read_obj(data, src)
    if kind == ".stl":
        binary = _stl_binary_count(data, src)
        if binary is not None:
            return _read_binary_stl(data, binary)
        return _trimesh_arrays(data, "stl", src)
    if kind == ".ply":
        header = ply_header(data, src)
        fast = _binary_triangles(data, header, src)
        if fast is not None:
            return fast
        v, f = _trimesh_arrays(data, "ply", src)
        if len(v) != header["vertex"]:
            raise InputError(src, "element vertex", f"the header declares {header['vertex']} "
                             f"vertices, the body holds {len(v)}")
        return v, f
    return _trimesh_arrays(data, kind.lstrip(".") or None, src)


def mesh_triangles(path: str | os.PathLike) -> int:
    """How many triangles a mesh file holds, from its header (PLY, binary STL) or, where the
    format has none, an estimate from its size (OBJ, ASCII STL, others). Reads at most the
    first 64 KiB; raises :class:`InputError` for a header that breaks its format's rules."""
    src = str(path)
    size = os.path.getsize(src)
    kind = Path(src).suffix.lower()
    with open(src, "rb") as fh:
        head = fh.read(MAX_PLY_HEADER)
    if kind == ".ply":
        return int(ply_header(head, src, size)["face"])
    if kind == ".stl":
        if len(head) >= 84:
            n = int(np.frombuffer(head[80:84], dtype="<u4")[0])
            if 84 + 50 * n == size:
                return n
        return max(1, size // _ASCII_STL_BYTES)
    return max(1, size // _OBJ_BYTES)


# ---------------------------------------------------------------------------- OBJ
def read_obj(data: bytes, src: str) -> tuple[np.ndarray, np.ndarray]:
    """Vertices and triangles of a Wavefront OBJ (rules in the module docstring)."""
    text = data.replace(b"\\\r\n", b" ").replace(b"\\\n", b" ")
    verts: list[list[float]] = []
    faces: list[tuple[int, int, int]] = []
    for lineno, raw in enumerate(text.splitlines(), 1):
        line = raw.split(b"#", 1)[0]
        tok = line.split()
        if not tok:
            continue
        if tok[0] == b"v":
            verts.append(_obj_vertex(tok, src, lineno))
        elif tok[0] == b"f":
            idx = [_obj_index(t, len(verts), src, lineno) for t in tok[1:]]
            if len(idx) < 3:
                raise InputError(src, f"line {lineno}", f"a face needs at least 3 vertices, got {len(idx)}")
            faces.extend((idx[0], idx[k], idx[k + 1]) for k in range(1, len(idx) - 1))
    if not faces:
        raise InputError(src, "f", "no faces (an OBJ mesh needs 'f' lines)")
    v = np.array(verts, dtype=float).reshape(-1, 3)
    f = np.array(faces, dtype=np.int64).reshape(-1, 3)
    if f.max() >= len(v):
        bad = int(np.argmax(f.max(axis=1) >= len(v)))
        raise InputError(src, "f", f"face {bad + 1} refers to vertex {int(f[bad].max()) + 1}, "
                         f"but the file defines {len(v)} vertices")
    return v, f


def _obj_vertex(tok: list[bytes], src: str, lineno: int) -> list[float]:
    if len(tok) < 4:
        raise InputError(src, f"line {lineno}", f"a vertex needs x y z, got {len(tok) - 1} numbers")
    out = []
    for t in tok[1:4]:
        if not _NUM.match(t):
            raise InputError(src, f"line {lineno}", f"vertex coordinate {_show(t)} is not a number")
        out.append(float(t))
    return out


def _obj_index(token: bytes, defined: int, src: str, lineno: int) -> int:
    """0-based vertex index of one face token ``i[/t[/n]]``; ``defined`` vertices precede it."""
    head = token.split(b"/", 1)[0]
    if not _INT.match(head):
        raise InputError(src, f"line {lineno}", f"face vertex {_show(token)} is not an index")
    i = int(head)
    if i == 0:
        raise InputError(src, f"line {lineno}", "face vertex index 0: OBJ indices start at 1 "
                         "(negative ones count back from the last vertex)")
    if i < 0:
        if -i > defined:
            raise InputError(src, f"line {lineno}", f"relative index {i} reaches before the "
                             f"first vertex ({defined} defined so far)")
        return defined + i
    if i > 2 ** 62:
        raise InputError(src, f"line {lineno}", f"face vertex index {_show(head)} is out of range")
    return i - 1


def _show(token: bytes) -> str:
    text = token[:40].decode("utf-8", "replace")
    return repr(text) + ("..." if len(token) > 40 else "")


# ---------------------------------------------------------------------------- PLY
def ply_header(data: bytes, src: str, size: int | None = None) -> dict:
    """Check a PLY header (rules in the module docstring). Returns ``{"format", "vertex",
    "face", "length"}`` (counts, header length in bytes). ``size``: the file's size when
    ``data`` holds only its start."""
    size = len(data) if size is None else size
    if not (data.startswith(b"ply\n") or data.startswith(b"ply\r\n")):
        raise InputError(src, "header", "not a PLY file (it must start with the line 'ply')")
    end = data.find(b"end_header", 0, MAX_PLY_HEADER)
    if end < 0:
        raise InputError(src, "header", f"no 'end_header' in the first {MAX_PLY_HEADER // 1024} KiB")
    stop = data.find(b"\n", end)
    if stop < 0:
        raise InputError(src, "header", "the file ends inside its header")
    try:
        lines = data[:end].decode("ascii").splitlines()[1:]
    except UnicodeDecodeError:
        raise InputError(src, "header", "the header is not ASCII text") from None
    fmt, elements = _ply_elements(lines, src)
    names = [e[0] for e in elements]
    for need in ("vertex", "face"):
        if need not in names:
            raise InputError(src, f"element {need}", "missing from the header")
    vert = elements[names.index("vertex")]
    if not {"x", "y", "z"} <= {p[0] for p in vert[2]}:
        raise InputError(src, "element vertex", "needs properties x, y and z")
    face = elements[names.index("face")]
    if not any(p[0] in ("vertex_indices", "vertex_index") and p[1] == "list" for p in face[2]):
        raise InputError(src, "element face", "needs a list property vertex_indices")
    if fmt != "ascii":
        # lists at their shortest (length 0): a body shorter than this is truncated
        least = sum(count * sum(_PLY_TYPES[p[2]] for p in props) for _, count, props in elements)
        if size - (stop + 1) < least:
            raise InputError(src, "", f"truncated: the header declares {vert[1]} vertices and "
                             f"{face[1]} faces (at least {least + stop + 1} bytes), the file has {size}")
    return {"format": fmt, "vertex": vert[1], "face": face[1], "length": stop + 1,
            "elements": elements}


def _ply_elements(lines: list[str], src: str) -> tuple[str, list]:
    fmt = ""
    elements: list = []     # (name, count, [(property, type or "list", size type, item type)])
    for k, line in enumerate(lines, 2):
        tok = line.split()
        if not tok or tok[0] in ("comment", "obj_info"):
            continue
        where = f"header line {k}"
        if tok[0] == "format":
            if len(tok) != 3 or tok[1] not in _PLY_FORMATS or tok[2] != "1.0":
                raise InputError(src, where, f"format must be one of {', '.join(_PLY_FORMATS)} 1.0")
            fmt = tok[1]
        elif tok[0] == "element":
            if len(tok) != 3 or not tok[2].isdigit() or not tok[2].isascii() or int(tok[2]) > 2 ** 31:
                raise InputError(src, where, "an element needs a name and a count (an integer "
                                 "0 .. 2^31)")
            if tok[1] in {e[0] for e in elements}:
                raise InputError(src, where, f"element {tok[1][:40]!r} declared twice")
            elements.append((tok[1], int(tok[2]), []))
        elif tok[0] == "property":
            if not elements:
                raise InputError(src, where, "a property before any element")
            ok = (len(tok) == 3 and tok[1] in _PLY_TYPES) or (
                len(tok) == 5 and tok[1] == "list" and tok[2] in _PLY_TYPES and tok[3] in _PLY_TYPES)
            if not ok:
                raise InputError(src, where, f"malformed property ({line[:60]!r})")
            if tok[-1] in {p[0] for p in elements[-1][2]}:
                raise InputError(src, where, f"property {tok[-1][:40]!r} declared twice")
            # (name, type or "list", the type whose size a record takes at the least: a
            # list's count type, as a list may be empty; the item type)
            elements[-1][2].append((tok[-1], tok[1], tok[2] if tok[1] == "list" else tok[1],
                                    tok[3] if tok[1] == "list" else tok[1]))
        else:
            raise InputError(src, where, f"unknown header keyword {tok[0][:40]!r}")
    if not fmt:
        raise InputError(src, "header", "no format line")
    return fmt, elements


_NUMPY_TYPES = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4",
                "uint": "u4", "float": "f4", "double": "f8", "int8": "i1", "uint8": "u1",
                "int16": "i2", "uint16": "u2", "int32": "i4", "uint32": "u4", "float32": "f4",
                "float64": "f8"}


def _binary_triangles(data: bytes, header: dict, src: str):
    """(vertices, faces) of a binary PLY holding only a vertex and a face element, the faces
    all triangles (read straight into numpy: a fine segmentation has millions); None for any
    other layout (trimesh reads those)."""
    elements = header["elements"]
    if header["format"] == "ascii" or [e[0] for e in elements] != ["vertex", "face"]:
        return None
    (_, nv, vprops), (_, nf, fprops) = elements
    if len(fprops) != 1 or fprops[0][1] != "list" or any(p[1] == "list" for p in vprops):
        return None
    end = "<" if header["format"] == "binary_little_endian" else ">"
    vdt = np.dtype([(p[0], end + _NUMPY_TYPES[p[1]]) for p in vprops])
    _, _, count_type, item = fprops[0]
    fdt = np.dtype([("n", end + _NUMPY_TYPES[count_type]), ("i", end + _NUMPY_TYPES[item], (3,))])
    start = header["length"]
    need = start + vdt.itemsize * nv + fdt.itemsize * nf
    if len(data) < need:            # every face has at least 3 vertices: cut short
        raise InputError(src, "", f"truncated: the header declares {nv} vertices and {nf} faces "
                         f"(at least {need} bytes), the file has {len(data)}")
    if len(data) != need:
        return None                 # polygons other than triangles, or extra bytes: trimesh
    vert = np.frombuffer(data, dtype=vdt, count=nv, offset=start)
    face = np.frombuffer(data, dtype=fdt, count=nf, offset=start + vdt.itemsize * nv)
    if nf and not np.all(face["n"] == 3):
        return None
    v = np.stack([vert["x"], vert["y"], vert["z"]], axis=1).astype(np.float64)
    f = face["i"].astype(np.int64)
    if len(f) and (f.min() < 0 or f.max() >= len(v)):
        raise InputError(src, "element face", "face indices out of range")
    return v, f


# ---------------------------------------------------------------------------- STL
def _stl_binary_count(data: bytes, src: str) -> int | None:
    """Triangle count of a binary STL, None for an ASCII one; refuses anything else."""
    if len(data) >= 84:
        n = int(np.frombuffer(data[80:84], dtype="<u4")[0])
        if 84 + 50 * n == len(data):
            return n
    if data.lstrip()[:5].lower() == b"solid":
        return None
    declared = (f"its header declares {int(np.frombuffer(data[80:84], dtype='<u4')[0])} triangles "
                f"({84 + 50 * int(np.frombuffer(data[80:84], dtype='<u4')[0])} bytes)"
                if len(data) >= 84 else "it is shorter than the 84-byte header")
    raise InputError(src, "", f"neither a binary STL ({declared}, the file has {len(data)} bytes) "
                     "nor an ASCII STL (starting with 'solid')")


def _read_binary_stl(data: bytes, n: int) -> tuple[np.ndarray, np.ndarray]:
    rec = np.dtype([("normal", "<f4", (3,)), ("v", "<f4", (3, 3)), ("attr", "<u2")])
    tri = np.frombuffer(data, dtype=rec, count=n, offset=84)["v"]
    v = tri.reshape(-1, 3).astype(np.float64)
    return v, np.arange(len(v), dtype=np.int64).reshape(-1, 3)


# ---------------------------------------------------------------------------- others
def _trimesh_arrays(data: bytes, file_type: str | None, src: str) -> tuple[np.ndarray, np.ndarray]:
    import io

    import trimesh

    try:
        mesh = trimesh.load(io.BytesIO(data), file_type=file_type, force="mesh", process=False)
    except Exception as exc:  # trimesh raises many types for unreadable files
        raise InputError(src, "", f"unreadable mesh ({exc.__class__.__name__}: {exc})") from None
    if not isinstance(mesh, trimesh.Trimesh):
        raise InputError(src, "", "not a triangle mesh")
    return np.asarray(mesh.vertices, dtype=np.float64), np.asarray(mesh.faces, dtype=np.int64)
