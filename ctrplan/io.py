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


@contextlib.contextmanager
def scratch_files(beside: str | os.PathLike, count: int) -> Iterator[list[Path]]:
    """Yield ``count`` empty scratch files in the folder of ``beside`` (an output being built
    in parts); all are removed on exit, and by the Ctrl-C watchdog if it must kill us."""
    from ctrplan import interrupt

    folder = Path(beside).parent
    paths: list[Path] = []
    try:
        for _ in range(count):
            try:
                fd, tmp = tempfile.mkstemp(prefix=f".{Path(beside).name}.part.", dir=folder)
            except OSError as exc:
                raise _os_error(Path(beside), exc) from None
            os.close(fd)
            paths.append(Path(tmp))
            interrupt.pending_added(tmp)
        yield paths
    finally:
        for p in paths:
            with contextlib.suppress(OSError):
                p.unlink()
            interrupt.pending_removed(str(p))


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


# ---------------------------------------------------------------------------- bounded reading
#: Default size caps (MB) of input files, by kind, checked (``os.stat``) before anything is
#: read. ``--max-mb`` (every command) lifts them all: see :func:`set_max_input_mb`.
MAX_INPUT_MB: dict[str, float] = {
    "configs": 2048.0,   # configuration CSVs streamed in chunks (shape, check): memory stays flat
    "csv": 256.0,        # CSVs read whole (measured data, target lists): ~10x their size in memory
    "text": 64.0,        # YAML, JSON, plan.json, job and label tables
    "model": 512.0,      # trained model files
    "mesh": 1024.0,      # scene meshes
}
_override_mb: float | None = None


def set_max_input_mb(mb: float | None) -> None:
    """Set (``None``: reset to the defaults) the size cap of every input file, in MB."""
    global _override_mb
    if mb is not None and not (math.isfinite(mb) and mb > 0):
        raise InputError("--max-mb", "", f"must be a finite number > 0, got {excerpt(mb)}")
    _override_mb = None if mb is None else float(mb)


def max_input_bytes(kind: str = "text") -> int:
    """The size cap in bytes of an input file of ``kind`` (see :data:`MAX_INPUT_MB`)."""
    mb = _override_mb if _override_mb is not None else MAX_INPUT_MB.get(kind, MAX_INPUT_MB["text"])
    return int(min(mb, 2.0 ** 40) * 2 ** 20)


def excerpt(value: Any, n: int = 40) -> str:
    """``repr`` of a (possibly huge) bad value, cut to its first ``n`` characters plus
    ``...`` and its length: error messages quote a bad value, never all of it."""
    if isinstance(value, int) and not isinstance(value, bool) and value.bit_length() > 200:
        return f"<an integer of about {int(value.bit_length() * 0.30103) + 1} digits>"
    text = value if isinstance(value, str) else str(value) if isinstance(value, (int, float)) else repr(value)
    if len(text) <= n:
        return repr(text) if isinstance(value, str) else text
    cut = repr(text[:n])[:-1] + f"...' ({len(text)} characters)"
    return cut


def short_field(name: str, n: int = 40) -> str:
    """A field name (a CSV column, a key) as shown in an error: as it is when short, else an
    :func:`excerpt`."""
    return name if len(name) <= n else excerpt(name, n)


def check_input_file(path: str | os.PathLike, kind: str = "text") -> int:
    """Before reading: ``path`` must be a regular file (not a device such as /dev/zero, a
    pipe or a folder) no larger than the cap for ``kind``; returns its size in bytes.
    Raises InputError naming the file (and how to lift the cap)."""
    p = Path(path)
    try:
        st = p.stat()
    except FileNotFoundError:
        raise InputError(str(path), "", "file not found") from None
    except (OSError, ValueError) as exc:
        raise InputError(str(path), "", f"cannot read file ({exc.__class__.__name__})") from None
    import stat as _stat

    if _stat.S_ISDIR(st.st_mode):
        raise InputError(str(path), "", "is a folder, expected a file")
    if not _stat.S_ISREG(st.st_mode):
        raise InputError(str(path), "", "not a regular file (a device, pipe or socket has no "
                         "end to read to)")
    cap = max_input_bytes(kind)
    if st.st_size > cap:
        raise InputError(str(path), "", f"file is {st.st_size / 2 ** 20:.4g} MB, above the "
                         f"{cap / 2 ** 20:.4g} MB limit for {kind} files (lift with --max-mb)")
    return int(st.st_size)


def read_bytes(path: str | os.PathLike, kind: str = "text") -> bytes:
    """A file's bytes after :func:`check_input_file`; reads at most the cap (a file that grows
    while read is refused, not followed)."""
    check_input_file(path, kind)
    cap = max_input_bytes(kind)
    try:
        with open(path, "rb") as fh:
            # in blocks: read(cap + 1) would allocate the whole cap up front (a MemoryError
            # for --max-mb 1e6)
            blocks, total = [], 0
            while total <= cap:
                block = fh.read(min(1 << 24, cap + 1 - total))
                if not block:
                    break
                blocks.append(block)
                total += len(block)
            data = b"".join(blocks)
    except OSError as exc:
        raise InputError(str(path), "", f"cannot read file ({exc.strerror or exc.__class__.__name__})") from None
    if len(data) > cap:
        raise InputError(str(path), "", f"file grew beyond the {cap / 2 ** 20:.4g} MB limit while "
                         "read (lift with --max-mb)")
    return data


def read_text(path: str | os.PathLike, kind: str = "text") -> str:
    """A UTF-8 text file's contents (a leading byte-order mark is dropped; CRLF and CR line
    ends read as LF); a missing, unreadable, non-regular or over-cap file is an InputError
    naming it."""
    data = read_bytes(path, kind)
    try:
        text = data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise InputError(str(path), "", f"cannot read file ({exc.__class__.__name__})") from None
    return text.replace("\r\n", "\n").replace("\r", "\n")


def parse_json(text: str, source: str = "<string>") -> Any:
    """Parse JSON text; malformed JSON, huge integers and deep nesting are InputErrors naming
    ``source`` (never a traceback)."""
    try:
        return json.loads(text)
    except RecursionError:
        raise InputError(source, "", "malformed JSON: nested too deeply") from None
    except ValueError as exc:   # JSONDecodeError, and integers beyond Python's digit limit
        msg = str(exc)
        if "digits" in msg or "integer string conversion" in msg:
            msg = "a number with too many digits"
        raise InputError(source, "", f"malformed JSON: {msg[:120]}") from None


def load_json(path: str | os.PathLike, kind: str = "text") -> Any:
    """Read a JSON file (size-capped, see :func:`check_input_file`); errors name the file."""
    return parse_json(read_text(path, kind), str(path))


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
    except ValueError as exc:   # an integer beyond Python's digit limit, a bad timestamp, ...
        msg = str(exc)
        if "digits" in msg or "integer string conversion" in msg:
            msg = "a number with too many digits"
        raise InputError(source, "", f"malformed YAML: {msg[:120]}") from None


def load_yaml(path: str | os.PathLike) -> Any:
    """Read a YAML file safely (no Python objects, bounded aliases and nesting, no duplicate
    keys); errors name the file."""
    path = Path(path)
    return parse_yaml(read_text(path), str(path))


#: Rows per chunk when configuration files are streamed (memory per chunk: a few MB).
CHUNK_ROWS = 50_000

_TUBE_COLUMN = re.compile(r"^(alpha|beta)([0-9]+)$")


class _CappedReader(io.RawIOBase):
    """A raw reader that refuses to read past ``cap`` bytes (a file that grows while read)."""

    def __init__(self, raw: Any, cap: int, path: Path):
        self.raw, self.cap, self.path, self.done = raw, cap, path, 0

    def readable(self) -> bool:
        return True

    def readinto(self, b: Any) -> int:
        n = self.raw.readinto(b)
        self.done += n or 0
        if self.done > self.cap:
            raise InputError(str(self.path), "", f"file grew beyond the {self.cap / 2 ** 20:.4g} MB "
                             "limit while read (lift with --max-mb)")
        return n


def _csv_header(path: Path, row: list[str]) -> list[str]:
    header = [h.strip() for h in row]
    seen: set[str] = set()
    for h in header:
        if h in seen:
            raise InputError(str(path), short_field(h), "duplicate column in the header")
        seen.add(h)
    return header


def iter_csv_rows(path: str | os.PathLike, kind: str = "csv",
                  chunk_rows: int = CHUNK_ROWS) -> Iterator[tuple[list[str], int, list[list[str]]]]:
    """Stream a CSV file (size-capped, see :func:`check_input_file`) as chunks
    ``(header, first_row, rows)`` of at most ``chunk_rows`` rows of strings; ``first_row`` is
    the row number error messages use for the chunk's first row (the header is row 1; blank
    lines are skipped). Malformed CSV, a duplicate column and a row of the wrong length are
    InputErrors naming the file. Memory is bounded by the chunk, whatever the file's size."""
    path = Path(path)
    check_input_file(path, kind)
    cap = max_input_bytes(kind)
    header: list[str] | None = None
    rows: list[list[str]] = []
    first = 2
    try:
        with open(path, "rb") as raw, io.TextIOWrapper(
                io.BufferedReader(_CappedReader(raw, cap, path)), encoding="utf-8-sig", newline="") as fh:
            for r in csv.reader(fh):
                if not r or not any(c.strip() for c in r):
                    continue
                if header is None:
                    header = _csv_header(path, r)
                    continue
                if len(r) != len(header):
                    raise InputError(str(path), f"row {first + len(rows)}",
                                     f"has {len(r)} values but the header has {len(header)} columns")
                rows.append(r)
                if len(rows) >= chunk_rows:
                    yield header, first, rows
                    first += len(rows)
                    rows = []
    except csv.Error as exc:
        raise InputError(str(path), "", f"malformed CSV: {str(exc)[:120]}") from None
    except UnicodeDecodeError as exc:
        raise InputError(str(path), "", f"cannot read file ({exc.__class__.__name__})") from None
    except OSError as exc:
        raise InputError(str(path), "", f"cannot read file ({exc.strerror or exc.__class__.__name__})") from None
    if header is None:
        raise InputError(str(path), "header", "empty file (expected a header row)")
    if rows or first == 2:
        yield header, first, rows


def read_csv_table(path: str | os.PathLike, kind: str = "csv") -> tuple[list[str], list[list[str]]]:
    """Read a CSV file (size-capped) into (header, rows of strings). Errors name the file."""
    header: list[str] = []
    body: list[list[str]] = []
    for head, _, rows in iter_csv_rows(path, kind):
        header = head
        body.extend(rows)
    return header, body


def strict_float(text: Any) -> float:
    """``float(text)`` without what a number in a file or option should not be: digit
    separators (``1_0``) and non-ASCII digits raise ValueError (``nan``/``inf`` are returned
    for the caller's finiteness check)."""
    t = str(text)
    if "_" in t or not t.isascii():
        raise ValueError(f"not a number: {excerpt(t)}")
    return float(t)


def _not_strict(cells: list[str]) -> int | None:
    """Index of the first cell ``float`` would read but a strict number parser must refuse
    (underscores as in ``1_0``, non-ASCII digits), else None. Checked on the joined chunk
    first, so clean chunks cost one scan."""
    joined = "\x1f".join(cells)
    if "_" not in joined and joined.isascii():
        return None
    for k, c in enumerate(cells):
        if "_" in c or not c.isascii():
            return k
    return None


def parse_float_columns(
    path: str | os.PathLike, header: list[str], body: list[list[str]], columns: Sequence[str],
    first_row: int = 2,
) -> np.ndarray:
    """Parse the named columns as finite floats, ``(rows, len(columns))``. Numbers are read
    strictly: decimal ASCII (``1.5``, ``-2e3``), no digit separators (``1_0``) and no
    non-ASCII digits; ``first_row`` numbers the first row in error messages."""
    index = {h: i for i, h in enumerate(header)}
    out = np.empty((len(body), len(columns)), dtype=float)
    for j, col in enumerate(columns):
        if col not in index:
            raise InputError(str(path), col, "missing column")
        ci = index[col]
        cells = [r[ci] for r in body]
        bad = _not_strict(cells)
        if bad is not None:
            raise InputError(str(path), f"{col} (row {bad + first_row})",
                             f"not a number: {excerpt(cells[bad])}")
        try:
            out[:, j] = list(map(float, cells))
        except ValueError:
            for k, c in enumerate(cells):
                try:
                    float(c)
                except ValueError:
                    raise InputError(str(path), f"{col} (row {k + first_row})",
                                     f"not a number: {excerpt(c)}") from None
        fin = np.isfinite(out[:, j])
        if not fin.all():
            k = int(np.argmin(fin))
            raise InputError(str(path), f"{col} (row {k + first_row})", f"not finite: {excerpt(cells[k])}")
    return out


def check_tube_columns(path: str | os.PathLike, header: Sequence[str], robot: Any) -> None:
    """A configuration file's tube columns must match the robot: ``alphaK``/``betaK`` with K
    outside 1..n (tube-3 columns for a two-tube robot, say) are refused, not ignored."""
    for h in header:
        m = _TUBE_COLUMN.match(h)
        if m and not 1 <= int(m.group(2)) <= robot.n:
            k = m.group(2) if len(m.group(2)) <= 6 else excerpt(m.group(2), 6)
            raise InputError(str(path), short_field(h), f"is a column for tube {k} but "
                             f"robot {robot.name!r} has {robot.n} tube{'s' if robot.n != 1 else ''}")


def iter_configs(path: str | os.PathLike, robot: Any, check: bool = True, kind: str = "configs",
                 chunk_rows: int = CHUNK_ROWS, extra: Sequence[str] = ("sweep",),
                 ) -> Iterator[tuple[np.ndarray, dict[str, list[str]]]]:
    """Stream a configuration CSV (header ``alpha1..alphaN,beta1..betaN``, extra columns
    allowed) as chunks ``(q (k, 2n), {name: cells})`` for the ``extra`` columns present.

    Memory is bounded by the chunk whatever the file's size. With ``check`` every row must
    satisfy the robot's joint constraints. Errors name the file, column and row; a file
    without rows is refused. Between chunks a pending Ctrl-C is honoured (Python code runs)."""
    seen = False
    for header, first, rows in iter_csv_rows(path, kind, chunk_rows):
        if first == 2:
            check_tube_columns(path, header, robot)
        if not rows:
            break
        seen = True
        q = parse_float_columns(path, header, rows, robot.column_names, first_row=first)
        robot.check_plausible(q, str(path), row_offset=first)
        if check:
            ok = robot.is_valid(q)
            if not ok.all():
                k = int(np.argmin(ok))
                viol = robot.constraint_violations(q[k:k + 1])[0]
                raise InputError(
                    str(path), f"row {k + first}",
                    f"violates the joint constraints of robot {robot.name!r} "
                    f"(worst constraint off by {-viol.min():.6g} mm)",
                )
        cols = {}
        for name in extra:
            if name in header:
                ci = header.index(name)
                cols[name] = [r[ci].strip() for r in rows]
        yield q, cols
    if not seen:
        raise InputError(str(path), "rows", "no configurations (only a header)")
