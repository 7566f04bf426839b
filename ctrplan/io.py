"""Small file helpers: atomic writes, safe YAML and CSV reading.

Everything read here is untrusted input: YAML goes through ``yaml.safe_load``, numbers are
checked for finiteness, and every failure becomes an :class:`~ctrplan.errors.InputError` naming
the file and field. Writes go to a temporary file in the same folder and are renamed into place,
so an interrupted command never leaves a half-written output.
"""

from __future__ import annotations

import contextlib
import csv
import enum
import io
import json
import math
import os
import tempfile
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ctrplan.errors import InputError


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(
        prefix=f".{path.name}.", suffix=suffix if suffix is not None else path.suffix,
        dir=path.parent,
    )
    os.close(fd)
    tmp_path = Path(tmp)
    try:
        yield tmp_path
        # mkstemp creates 0600 files; give the output the permissions a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp_path, 0o666 & ~umask)
        os.replace(tmp_path, path)
    finally:
        if tmp_path.exists():
            tmp_path.unlink()


def save_figure(fig: Any, path: str | os.PathLike, dpi: int | None = None) -> None:
    """Write a matplotlib figure to ``path`` as PNG atomically and close it."""
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_path(path) as tmp:
        tmp.write_text(text, encoding="utf-8")


def jsonable(obj: Any) -> Any:
    """JSON-safe copy: non-finite floats become None (JSON has no NaN), numpy scalars and
    arrays plain numbers and lists, enums their value."""
    if isinstance(obj, dict):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, (np.floating, float)):
        v = float(obj)
        return v if math.isfinite(v) else None
    if isinstance(obj, np.bool_):
        return bool(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, enum.Enum):
        return obj.value
    return obj


def write_json_atomic(path: str | os.PathLike, obj: Any) -> None:
    """Write ``obj`` as indented JSON atomically."""
    write_text_atomic(path, json.dumps(obj, indent=2, allow_nan=False) + "\n")


def write_csv_atomic(path: str | os.PathLike, header: Sequence[str], rows: Sequence[Sequence[Any]]) -> None:
    """Write a CSV with ``header`` and ``rows`` atomically."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(header)
    for row in rows:
        writer.writerow([_fmt(v) for v in row])
    write_text_atomic(path, buf.getvalue())


def _fmt(v: Any) -> Any:
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, (np.integer,)):
        return int(v)
    return v


def read_text(path: str | os.PathLike) -> str:
    """A UTF-8 text file's contents; a missing or unreadable file is an InputError naming it."""
    try:
        return Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError(str(path), "", "file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(str(path), "", f"cannot read file ({exc.__class__.__name__})") from None


def load_yaml(path: str | os.PathLike) -> Any:
    """Read a YAML file with ``yaml.safe_load``; errors name the file."""
    path = Path(path)
    text = read_text(path)
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or "malformed YAML"
        raise InputError(str(path), where, f"malformed YAML: {problem}") from None


def read_csv_table(path: str | os.PathLike) -> tuple[list[str], list[list[str]]]:
    """Read a CSV file into (header, rows of strings). Errors name the file."""
    path = Path(path)
    text = read_text(path)
    try:
        reader = csv.reader(io.StringIO(text))
        rows = [r for r in reader if r and any(c.strip() for c in r)]
    except csv.Error as exc:
        raise InputError(str(path), "", f"malformed CSV: {exc}") from None
    if not rows:
        raise InputError(str(path), "header", "empty file (expected a header row)")
    header = [h.strip() for h in rows[0]]
    body = rows[1:]
    for k, r in enumerate(body):
        if len(r) != len(header):
            raise InputError(
                str(path), f"row {k + 2}", f"has {len(r)} values but the header has {len(header)} columns"
            )
    return header, body


def parse_float_columns(
    path: str | os.PathLike, header: list[str], body: list[list[str]], columns: Sequence[str]
) -> np.ndarray:
    """Parse the named columns as finite floats, ``(rows, len(columns))``."""
    index = {h: i for i, h in enumerate(header)}
    out = np.empty((len(body), len(columns)), dtype=float)
    for j, col in enumerate(columns):
        if col not in index:
            raise InputError(str(path), col, "missing column")
        ci = index[col]
        for k, r in enumerate(body):
            try:
                v = float(r[ci])
            except ValueError:
                raise InputError(str(path), f"{col} (row {k + 2})", f"not a number: {r[ci]!r}") from None
            if not np.isfinite(v):
                raise InputError(str(path), f"{col} (row {k + 2})", f"not finite: {r[ci]!r}")
            out[k, j] = v
    return out
