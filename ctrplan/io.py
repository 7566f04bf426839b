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
import re
import tempfile
from collections.abc import Iterable, Iterator, Sequence
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from ctrplan.errors import InputError


def check_writable(path: str | os.PathLike, field: str = "--out", folder: bool = False) -> Path:
    """Check, before any work, that ``path`` (a file, or with ``folder`` a folder) can be
    written: its nearest existing ancestor must be a folder we can create files in (probed with
    a temporary file that is removed at once; nothing else is created). Raises InputError."""
    p = Path(path)
    if not folder and p.is_dir():
        raise InputError(field, "", f"{str(path)!r} is a folder, expected a file")
    if folder and p.exists() and not p.is_dir():
        raise InputError(field, "", f"{str(path)!r} is a file, expected a folder")
    anc = p if folder and p.is_dir() else p.parent
    anc = Path(os.path.abspath(anc))
    while not anc.exists():
        anc = anc.parent
    if not anc.is_dir():
        raise InputError(field, "", f"cannot write {str(path)!r}: {str(anc)!r} is a file, not a folder")
    try:
        fd, probe = tempfile.mkstemp(prefix=".ctrplan-write-test.", dir=anc)
        os.close(fd)
        os.unlink(probe)
    except OSError as exc:
        raise InputError(field, "", f"cannot write {str(path)!r}: folder {str(anc)!r} is not "
                         f"writable ({exc.strerror or exc.__class__.__name__})") from None
    return p


def _os_error(path: Path, exc: OSError) -> InputError:
    return InputError(str(path), "", f"cannot write ({exc.strerror or exc.__class__.__name__})")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike, suffix: str | None = None) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it onto ``path`` only on success.

    A folder that cannot be created or written raises InputError naming ``path``."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(
            prefix=f".{path.name}.", suffix=suffix if suffix is not None else path.suffix,
            dir=path.parent,
        )
        os.close(fd)
    except OSError as exc:
        raise _os_error(path, exc) from None
    tmp_path = Path(tmp)
    from ctrplan import interrupt

    interrupt.pending_added(str(tmp_path))   # the Ctrl-C watchdog removes it if it must kill us
    try:
        yield tmp_path
        # mkstemp creates 0600 files; give the output the permissions a plain open() would.
        umask = os.umask(0)
        os.umask(umask)
        try:
            os.chmod(tmp_path, 0o666 & ~umask)
            os.replace(tmp_path, path)
        except OSError as exc:
            raise _os_error(path, exc) from None
    finally:
        if tmp_path.exists():
            tmp_path.unlink()
        interrupt.pending_removed(str(tmp_path))


def save_figure(fig: Any, path: str | os.PathLike, dpi: int | None = None) -> None:
    """Write a matplotlib figure to ``path`` as PNG atomically and close it."""
    import matplotlib.pyplot as plt

    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    """Write ``text`` to ``path`` atomically (UTF-8)."""
    with atomic_path(path) as tmp:
        try:
            tmp.write_text(text, encoding="utf-8")
        except OSError as exc:
            raise _os_error(Path(path), exc) from None


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


def write_csv_atomic(path: str | os.PathLike, header: Sequence[str], rows: Iterable[Sequence[Any]]) -> None:
    """Write a CSV with ``header`` and ``rows`` atomically. Rows are streamed to the file (any
    iterable, e.g. a generator), so memory stays bounded for large outputs."""
    with atomic_path(path) as tmp:
        try:
            with open(tmp, "w", encoding="utf-8", newline="") as fh:
                writer = csv.writer(fh, lineterminator="\n")
                writer.writerow(header)
                for row in rows:
                    writer.writerow([_fmt(v) for v in row])
        except OSError as exc:
            raise _os_error(Path(path), exc) from None


def _fmt(v: Any) -> Any:
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, (np.integer,)):
        return int(v)
    return v


def read_text(path: str | os.PathLike) -> str:
    """A UTF-8 text file's contents (a leading byte-order mark is dropped; CRLF and CR line
    ends read as LF); a missing or unreadable file is an InputError naming it."""
    try:
        return Path(path).read_text(encoding="utf-8-sig")
    except FileNotFoundError:
        raise InputError(str(path), "", "file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(str(path), "", f"cannot read file ({exc.__class__.__name__})") from None


#: Limits applied while a YAML document is composed, before anything is expanded: a robot or
#: scene file needs none of them to be large (aliases are rare, nesting is 3-4 levels).
YAML_MAX_ALIASES = 100
YAML_MAX_DEPTH = 32
YAML_MAX_NODES = 1_000_000


class _LimitError(yaml.YAMLError):
    def __init__(self, problem: str, mark: Any):
        super().__init__(problem)
        self.problem = problem
        self.problem_mark = mark


class SafeLimitedLoader(yaml.SafeLoader):
    """``yaml.SafeLoader`` that refuses alias bombs and deep nesting while composing (before any
    expansion), refuses duplicate mapping keys, and reads ``6e4``-style numbers (YAML 1.2) as
    floats instead of strings."""

    def __init__(self, stream: Any):
        super().__init__(stream)
        self._aliases = 0
        self._depth = 0
        self._sizes: dict[int, int] = {}
        self._total = 0

    def compose_node(self, parent: Any, index: Any) -> Any:
        if self.check_event(yaml.AliasEvent):
            event = self.peek_event()
            self._aliases += 1
            if self._aliases > YAML_MAX_ALIASES:
                raise _LimitError(f"more than {YAML_MAX_ALIASES} aliases (*name)", event.start_mark)
            anchor = event.anchor
            node = self.anchors.get(anchor)
            if node is not None:
                # an alias expands to a copy of its anchor's whole subtree: count it again
                self._total += self._sizes.get(id(node), 1)
                if self._total > YAML_MAX_NODES:
                    raise _LimitError(f"expands to more than {YAML_MAX_NODES} values "
                                      "(aliases of aliases)", event.start_mark)
            return super().compose_node(parent, index)
        self._depth += 1
        if self._depth > YAML_MAX_DEPTH:
            raise _LimitError(f"nested deeper than {YAML_MAX_DEPTH} levels", self.peek_event().start_mark)
        before = self._total
        node = super().compose_node(parent, index)
        self._depth -= 1
        self._total += 1
        if self._total > YAML_MAX_NODES:
            raise _LimitError(f"more than {YAML_MAX_NODES} values", node.start_mark)
        self._sizes[id(node)] = self._total - before
        return node

    def construct_mapping(self, node: Any, deep: bool = False) -> Any:
        if isinstance(node, yaml.MappingNode):
            seen: set[Any] = set()
            for key_node, _ in node.value:
                if key_node.tag == "tag:yaml.org,2002:merge":
                    continue
                key = self.construct_object(key_node, deep=True)
                try:
                    dup = key in seen
                except TypeError:
                    continue    # unhashable keys are reported by the base class
                if dup:
                    raise _LimitError(f"duplicate key {key!r}", key_node.start_mark)
                seen.add(key)
        return super().construct_mapping(node, deep=deep)


SafeLimitedLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float",
    re.compile(r"^[-+]?(?:[0-9][0-9_]*)(?:\.[0-9_]*)?[eE][-+]?[0-9]+$"),
    list("-+0123456789"),
)


def parse_yaml(text: str, source: str = "<string>") -> Any:
    """Parse YAML text with :class:`SafeLimitedLoader`; errors are InputErrors naming ``source``."""
    try:
        loader = SafeLimitedLoader(text)
        try:
            return loader.get_single_data()
        finally:
            loader.dispose()
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}" if mark is not None else ""
        problem = getattr(exc, "problem", None) or "malformed YAML"
        raise InputError(source, where, f"malformed YAML: {problem}") from None
    except RecursionError:
        raise InputError(source, "", f"malformed YAML: nested deeper than {YAML_MAX_DEPTH} levels") from None


def load_yaml(path: str | os.PathLike) -> Any:
    """Read a YAML file safely (no Python objects, bounded aliases and nesting, no duplicate
    keys); errors name the file."""
    path = Path(path)
    return parse_yaml(read_text(path), str(path))


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
    seen: set[str] = set()
    for h in header:
        if h in seen:
            raise InputError(str(path), h, "duplicate column in the header")
        seen.add(h)
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
