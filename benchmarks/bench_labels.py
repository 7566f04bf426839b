"""Label map -> scene benchmark: a 256 x 256 x 256 NIfTI label map becomes a scene folder.

The label map (made here, deterministic; not timed): a branching lumen (a trachea-like tube of
radius 9 mm splitting twice, down to 4 mm) as the wall label, four vessels of radius 2-4 mm
running beside and across it as obstacle labels, and a 6 mm "tumour" sphere as a landmark, on
0.7 x 0.7 x 0.8 mm voxels (int16, gzip). The timed step is the whole command,
``ctrplan scene from-labels`` in a fresh process (reading, checks, marching cubes, smoothing,
bounded decimation, writing, loading the written scene back): wall time, CPU time and the peak
resident memory of that process (``ru_maxrss`` of the child). numba and BLAS may use the two
cores of the reference machine.

Run: ``python benchmarks/bench_labels.py [--quick] [--out labels.json]`` (``--quick``: 128^3).
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
SPACING = (0.7, 0.7, 0.8)


def _segments_label(data: np.ndarray, affine: np.ndarray, segs, value: int) -> None:
    """Set ``value`` in voxels whose centre lies within radius of a segment (a, b, r)."""
    inv = np.linalg.inv(affine)
    for a, b, r in segs:
        a, b = np.asarray(a, float), np.asarray(b, float)
        lo = np.floor((np.minimum(a, b) - r) @ inv[:3, :3].T + inv[:3, 3]).astype(int) - 1
        hi = np.ceil((np.maximum(a, b) + r) @ inv[:3, :3].T + inv[:3, 3]).astype(int) + 2
        lo, hi = np.clip(lo, 0, data.shape), np.clip(hi, 0, data.shape)
        if np.any(hi <= lo):
            continue
        ax = [np.arange(lo[d], hi[d]) for d in range(3)]
        ijk = np.stack(np.meshgrid(*ax, indexing="ij"), -1).reshape(-1, 3)
        x = ijk @ affine[:3, :3].T + affine[:3, 3]
        t = np.clip((x - a) @ (b - a) / max((b - a) @ (b - a), 1e-12), 0, 1)
        d = np.linalg.norm(x - a - t[:, None] * (b - a), axis=1)
        sub = data[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]].reshape(-1)
        sub[d <= r] = value
        data[lo[0]:hi[0], lo[1]:hi[1], lo[2]:hi[2]] = sub.reshape(hi - lo)


def make_label_map(path: Path, n: int) -> dict:
    """Write the synthetic label map (n^3 voxels); return entry, toward and a target (mm)."""
    import nibabel as nib

    s = n / 256.0
    affine = np.diag([*SPACING, 1.0])
    size = np.array(SPACING) * n
    c = size / 2
    data = np.zeros((n, n, n), np.int16)
    top = c + [0, 0, 0.42 * size[2]]
    carina = c + [0, 0, 0.05 * size[2]]
    lumen = [(top, carina, 9 * s)]
    for sx in (-1, 1):
        b1 = carina + [sx * 0.18 * size[0], 0.02 * size[1], -0.16 * size[2]]
        lumen.append((carina, b1, 6.5 * s))
        for sy in (-1, 1):
            b2 = b1 + [sx * 0.12 * size[0], sy * 0.14 * size[1], -0.18 * size[2]]
            lumen.append((b1, b2, 4.5 * s))
    _segments_label(data, affine, lumen, 1)
    vessels = [
        [(c + [14 * s, 12 * s, 70 * s], c + [16 * s, 14 * s, -60 * s], 4 * s)],
        [(c + [-15 * s, 13 * s, 70 * s], c + [-17 * s, 15 * s, -60 * s], 3.5 * s)],
        [(c + [-60 * s, -20 * s, 5 * s], c + [60 * s, -22 * s, 8 * s], 3 * s)],
        [(c + [-40 * s, 30 * s, -30 * s], c + [40 * s, 28 * s, -25 * s], 2 * s)],
    ]
    for k, segs in enumerate(vessels):
        _segments_label(data, affine, segs, 10 + k)
    tumour = carina + [0.35 * size[0], 0.1 * size[1], -0.3 * size[2]]
    _segments_label(data, affine, [(tumour, tumour, 6 * s)], 20)
    img = nib.Nifti1Image(data, affine)
    img.set_sform(affine, code=1)
    nib.save(img, str(path))
    return {"entry": top - [0, 0, 8 * s], "toward": carina, "target": tumour}


def run(quick: bool = False) -> dict:
    n = 128 if quick else 256
    with tempfile.TemporaryDirectory(prefix="ctrplan-bench-labels-") as tmp:
        tmp = Path(tmp)
        seg = tmp / "seg.nii.gz"
        t0 = time.perf_counter()
        where = make_label_map(seg, n)
        made_s = time.perf_counter() - t0
        fmt = ",".join
        cmd = [sys.executable, "-m", "ctrplan.cli", "scene", "from-labels", str(seg),
               "--wall", "1", "--obstacle", "10,11,12,13", "--landmark", "20",
               "--entry=" + fmt(f"{v:.3f}" for v in where["entry"]),
               "--toward=" + fmt(f"{v:.3f}" for v in where["toward"]),
               "--targets", "20", "--out", str(tmp / "scene")]
        env = dict(os.environ, PYTHONPATH=str(ROOT), CTRPLAN_CACHE=str(tmp / "cache"))
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
        wall = time.perf_counter() - t0
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        if proc.returncode != 0:
            raise RuntimeError(proc.stderr[-3000:])
        lines = [ln for ln in proc.stdout.splitlines() if "triangles" in ln]
        meshes = len(list((tmp / "scene").glob("*.ply")))
        return {
            "suite": "labels",
            "voxels": [n, n, n],
            "voxel_size_mm": list(SPACING),
            "file_mb": round(seg.stat().st_size / 1e6, 3),
            "make_label_map_s": round(made_s, 2),
            "wall_s": round(wall, 2),
            "cpu_s": round((after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime), 2),
            "peak_rss_mb": round(after.ru_maxrss / 1024, 1),
            "meshes": meshes,
            "mesh_report": lines,
            "cpus": os.cpu_count(),
            "load_average": [round(x, 2) for x in os.getloadavg()],
            "targets_s": {"wall": 60, "peak_rss_mb": 4096},
        }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--quick", action="store_true", help="128^3 instead of 256^3")
    ap.add_argument("--out", default=None, help="results JSON (default: print)")
    args = ap.parse_args(argv)
    res = run(args.quick)
    text = json.dumps(res, indent=2)
    if args.out:
        Path(args.out).write_text(text + "\n", encoding="utf-8")
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
