"""``ctrplan shape``: backbones of configurations from a CSV."""

from __future__ import annotations

import argparse

import numpy as np

from ctrplan.commands._common import (
    POINTS,
    add_device_arg,
    add_model_arg,
    add_robot_arg,
    device_arg,
    output_path,
)
from ctrplan.commands._vocab import DEFAULT_OUT


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("shape", help="compute backbones of configurations",
                       description="Compute the backbone of each configuration in a CSV. "
                                   "Writes NPZ (points (B,M,3) mm, s (B,M) mm, ok (B,)) or CSV "
                                   "(one row per configuration: ok, p1_x..pM_z).")
    add_robot_arg(p)
    p.add_argument("--configs", required=True, help="configuration CSV (alpha1..alphaN,beta1..betaN)")
    add_model_arg(p)
    add_device_arg(p)
    p.add_argument("--points", type=POINTS, default=20, help="points per backbone, base to tip (default 20)")
    p.add_argument("--out", default=DEFAULT_OUT["shape"], help=f"output .npz or .csv (default {DEFAULT_OUT['shape']})")
    p.set_defaults(func=run)


#: Configurations per chunk: memory is bounded by one chunk whatever the file's size.
CHUNK = 20_000


class DirectionStream:
    """The direction of the last motion of each joint (:func:`direction_from_rows`) over a
    file read in chunks: the last row, its sweep and its direction carry over, so the result
    equals ``direction_from_rows`` on the whole file."""

    def __init__(self) -> None:
        self.prev_q: np.ndarray | None = None
        self.prev_sweep: object = None
        self.last: np.ndarray | None = None

    def __call__(self, q: np.ndarray, sweep: list[str] | None) -> np.ndarray:
        from ctrplan.shape.base import direction_from_rows

        sw = None if sweep is None else np.asarray(sweep, dtype=object)
        if self.prev_q is None:
            d = direction_from_rows(q, sw)
        else:
            qq = np.concatenate([self.prev_q[None], q])
            ss = None if sw is None else np.concatenate([np.array([self.prev_sweep], dtype=object), sw])
            d = direction_from_rows(qq, ss)[1:]
            # rows still in the carried row's sweep keep its direction until a joint moves
            same = len(q) if ss is None else int(np.argmax(np.append(ss[1:] != ss[:-1], True)))
            d[:same] = np.where(d[:same] != 0, d[:same], self.last)
        self.prev_q, self.last = q[-1].copy(), d[-1].copy()
        self.prev_sweep = None if sw is None else sw[-1]
        return d


def shape_chunks(model, robot, path: str, points: int, kind: str = "configs"):
    """Backbones of the configurations of the CSV ``path``, chunk by chunk (memory bounded by
    one chunk). Models that need the direction of the last motion get it from the row order
    (within each ``sweep`` when the file has that column), carried across chunks."""
    from ctrplan.io import iter_configs
    from ctrplan.shape.base import needs_direction

    directions = DirectionStream() if needs_direction(model) else None
    for q, cols in iter_configs(path, robot, chunk_rows=CHUNK, kind=kind):
        if directions is None:
            yield q, model.shape(q, points=points)
        else:
            yield q, model.shape(q, points=points, direction=directions(q, cols.get("sweep")))


def _write_npz_streamed(out, chunks) -> tuple[int, int]:
    """Write an NPZ (points, s, ok, radius) from chunks of Shapes without holding them all:
    each array goes to a scratch file beside ``out``, then into the archive. Atomic."""
    import shutil
    import zipfile

    from ctrplan.io import atomic_path, scratch_files

    names = ("points", "s", "ok", "radius")
    n = bad = 0
    tails: dict[str, tuple[tuple[int, ...], np.dtype]] = {}
    with scratch_files(out, len(names)) as parts:
        fhs = [open(pth, "wb") for pth in parts]
        try:
            for _, shape in chunks:
                for name, fh in zip(names, fhs):
                    a = np.ascontiguousarray(getattr(shape, name))
                    tails.setdefault(name, (a.shape[1:], a.dtype))
                    fh.write(a.tobytes())
                n += len(shape)
                bad += int((~shape.ok).sum())
        finally:
            for fh in fhs:
                fh.close()
        with atomic_path(out) as tmp, zipfile.ZipFile(tmp, "w", zipfile.ZIP_STORED, allowZip64=True) as zf:
            for name, pth in zip(names, parts):
                tail, dtype = tails[name]
                header = {"descr": np.lib.format.dtype_to_descr(dtype), "fortran_order": False,
                          "shape": (n, *tail)}
                with zf.open(f"{name}.npy", "w", force_zip64=True) as zfh, open(pth, "rb") as src:
                    np.lib.format.write_array_header_2_0(zfh, header)
                    shutil.copyfileobj(src, zfh, 1 << 20)
    return n, bad


def run(args: argparse.Namespace) -> int:
    from ctrplan.io import write_csv_atomic
    from ctrplan.robot import load_robot
    from ctrplan.shape.models import load_model

    out = output_path(args.out, (".npz", ".csv"))
    robot = load_robot(args.robot)
    model = load_model(args.model, robot, device=device_arg(args.device))
    chunks = shape_chunks(model, robot, args.configs, args.points)
    if out.suffix.lower() == ".npz":
        n, bad = _write_npz_streamed(out, chunks)
    else:
        m = args.points
        header = ["ok"] + [f"p{k + 1}_{c}" for k in range(m) for c in "xyz"]
        counts = [0, 0]

        def rows():
            for _, shape in chunks:
                counts[0] += len(shape)
                counts[1] += int((~shape.ok).sum())
                yield from ([int(ok)] + pts.reshape(-1).tolist() for ok, pts in zip(shape.ok, shape.points))

        write_csv_atomic(out, header, rows())   # streamed chunk by chunk, row by row
        n, bad = counts
    import logging

    logging.getLogger("ctrplan").info(
        "wrote %d backbones (%d points each, model %s) to %s%s", n, args.points,
        model.name, out, f"; {bad} did not converge (ok=0)" if bad else "")
    return 0
