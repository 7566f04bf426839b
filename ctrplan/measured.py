"""Measured (or simulated-measured) data: the CSV format of docs/conventions.md.

Columns: ``alpha1..alphaN, beta1..betaN`` (rad, mm), ``tip_x, tip_y, tip_z`` (mm, robot base
frame unless a registration is being calibrated), optionally ``time`` (s; row order is the order
of motion), ``sweep`` (an id grouping one continuous experiment) and backbone points
``p1_x, p1_y, p1_z, ..., pM_z`` (mm, evenly spaced in arc length from base to tip).
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass

import numpy as np

from ctrplan.errors import InputError
from ctrplan.io import (
    CHUNK_ROWS,
    check_tube_columns,
    iter_csv_rows,
    parse_float_columns,
    write_csv_atomic,
)
from ctrplan.robot import Robot

_POINT_RE = re.compile(r"^p(\d+)_([xyz])$")


@dataclass(frozen=True)
class MeasuredData:
    """A measured data set.

    q : (B, 2n) rad, mm. tip : (B, 3) mm. time : (B,) s or None. sweep : (B,) str or None.
    points : (B, M, 3) mm or None (backbone points base to tip).
    """

    q: np.ndarray
    tip: np.ndarray
    time: np.ndarray | None = None
    sweep: np.ndarray | None = None
    points: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.q.shape[0])

    def subset(self, idx: np.ndarray) -> MeasuredData:
        """Rows ``idx`` (index array or boolean mask), order kept."""
        def pick(a):
            return None if a is None else a[idx]

        return MeasuredData(q=self.q[idx], tip=self.tip[idx], time=pick(self.time),
                            sweep=pick(self.sweep), points=pick(self.points))

    def sweeps(self) -> np.ndarray:
        """Sweep id per row; rows without a sweep column form one sweep ``"0"``."""
        if self.sweep is None:
            return np.full(len(self), "0", dtype=object)
        return self.sweep


def read_measured(path: str | os.PathLike, robot: Robot, chunk_rows: int = CHUNK_ROWS) -> MeasuredData:
    """Read a measured-data CSV; errors name the file and the column/row. Parsed in chunks
    (:func:`ctrplan.io.iter_csv_rows`): only the numbers are held, never all rows as text;
    the file's size is capped before reading (see :func:`ctrplan.io.check_input_file`)."""
    parts: dict[str, list[np.ndarray]] = {"q": [], "tip": [], "time": [], "sweep": [], "points": []}
    header: list[str] = []
    m = 0
    for header, first, body in iter_csv_rows(path, chunk_rows=chunk_rows):
        if first == 2:
            check_tube_columns(path, header, robot)
            m = _point_count(path, header)
        if not body:
            break
        parts["q"].append(parse_float_columns(path, header, body, robot.column_names, first))
        parts["tip"].append(parse_float_columns(path, header, body, ["tip_x", "tip_y", "tip_z"], first))
        if "time" in header:
            parts["time"].append(parse_float_columns(path, header, body, ["time"], first)[:, 0])
        if "sweep" in header:
            ci = header.index("sweep")
            parts["sweep"].append(np.array([r[ci].strip() for r in body], dtype=object))
        if m:
            cols = [f"p{k}_{c}" for k in range(1, m + 1) for c in "xyz"]
            parts["points"].append(parse_float_columns(path, header, body, cols, first).reshape(len(body), m, 3))
    if not parts["q"]:
        raise InputError(str(path), "rows", "no data rows (only a header)")

    def cat(name: str) -> np.ndarray | None:
        return np.concatenate(parts[name]) if parts[name] else None

    return MeasuredData(q=cat("q"), tip=cat("tip"), time=cat("time"), sweep=cat("sweep"),
                        points=cat("points"))


def _point_count(path: str | os.PathLike, header: list[str]) -> int:
    """M for backbone point columns ``p1_x..pM_z`` (0 when there are none); incomplete sets
    are refused."""
    pcols: dict[int, set[str]] = {}
    for h in header:
        mt = _POINT_RE.match(h)
        if mt:
            pcols.setdefault(int(mt.group(1)), set()).add(mt.group(2))
    if not pcols:
        return 0
    m = max(pcols)
    for k in range(1, m + 1):
        if pcols.get(k) != {"x", "y", "z"}:
            raise InputError(str(path), f"p{k}_x/y/z", "backbone point columns must be complete p1..pM")
    if m < 2:
        raise InputError(str(path), "p1_x", "need at least 2 backbone points")
    return m


def write_measured(path: str | os.PathLike, robot: Robot, data: MeasuredData) -> None:
    """Write a measured-data CSV atomically (columns in the order of docs/conventions.md),
    streamed row by row."""
    header = list(robot.column_names) + ["tip_x", "tip_y", "tip_z"]
    parts = [data.q, data.tip]
    if data.time is not None:
        header.append("time")
        parts.append(np.asarray(data.time, dtype=float)[:, None])
    m = 0
    if data.sweep is not None:
        header.append("sweep")
    if data.points is not None:
        m = data.points.shape[1]
        header += [f"p{k}_{c}" for k in range(1, m + 1) for c in "xyz"]
    numbers = np.concatenate(parts, axis=1)

    def rows():
        for k in range(len(data)):
            row = numbers[k].tolist()
            if data.sweep is not None:
                row.append(str(data.sweep[k]))
            if data.points is not None:
                row.extend(np.asarray(data.points[k], dtype=float).reshape(-1).tolist())
            yield row

    write_csv_atomic(path, header, rows())
