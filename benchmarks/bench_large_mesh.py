"""Large meshes within a budget: ``ctrplan check`` on a closed wall of 0.3 to 5 million triangles.

The wall (made here, deterministic; not timed) is a fine segmentation's lumen: a tube of radius
about 9 mm (a slow wobble of 1 mm on it) along a gently curving centreline 220 mm long, closed
by fans at both ends, as a binary PLY; ``nt`` triangles around, ``ns`` rings along (the 5M case:
1,000 x 2,500, triangles about 0.09 x 0.06 mm). The seed1 robot's base sits on the axis 10 mm
inside one end. The timed step is the whole command in a fresh process, on one core
(``OMP_NUM_THREADS=1``, ``NUMBA_NUM_THREADS=1``):

    ctrplan check --scene DIR --robot seed1 --configs C.csv --out V.csv

with 1,000 configurations (``seed1.sample(1000, seed=0)``), once with an empty distance-field
cache (a first check: everything is built) and once with it filled. Measured with
``/usr/bin/time -v``: peak resident memory ("Maximum resident set size") and wall time; the
work estimate ``ctrplan.collision.budget.estimate`` is printed beside them. The budget's
default (2048 MB) must hold for 5 million triangles, or the command must refuse up front.
The two runs' verdicts must be equal (``same_verdicts``).

Run: ``python benchmarks/bench_large_mesh.py [--quick] [--sizes 0.3,1.25,5] [--baseline CHECKOUT]
[--out large.json]`` (``--quick``: 0.3 M only; ``--baseline``: also time another checkout's
``ctrplan check`` on the same scenes, e.g. the commit before this work).
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]


def tube_wall(nt: int, ns: int, length: float = 220.0, radius: float = 9.0) -> tuple[np.ndarray, np.ndarray]:
    """A closed tube (vertices (V, 3), faces (F, 3)): ``2 nt (ns - 1) + 2 nt`` triangles."""
    s = np.linspace(0.0, length, ns)
    centre = np.stack([0.0008 * s ** 2, 3.0 * np.sin(s / 40.0), s - 10.0], axis=1)
    tangent = np.gradient(centre, axis=0)
    tangent /= np.linalg.norm(tangent, axis=1, keepdims=True)
    normal = np.cross(tangent, [0.0, 1.0, 0.0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    binormal = np.cross(tangent, normal)
    phi = np.linspace(0.0, 2.0 * np.pi, nt, endpoint=False)
    r = radius + 1.0 * np.sin(3 * phi)[None, :] * np.cos(s / 25.0)[:, None]
    ring = (centre[:, None] + r[..., None] * (np.cos(phi)[None, :, None] * normal[:, None]
                                                + np.sin(phi)[None, :, None] * binormal[:, None]))
    v = np.concatenate([ring.reshape(-1, 3), centre[[0, -1]]])
    i, j = np.meshgrid(np.arange(ns - 1), np.arange(nt), indexing="ij")
    a = (i * nt + j).ravel()
    b = (i * nt + (j + 1) % nt).ravel()
    side = np.concatenate([np.stack([a, a + nt, b], 1), np.stack([b, a + nt, b + nt], 1)])
    k = np.arange(nt)
    c0, c1 = len(v) - 2, len(v) - 1
    cap0 = np.stack([np.full(nt, c0), k, (k + 1) % nt], 1)
    last = (ns - 1) * nt
    cap1 = np.stack([np.full(nt, c1), last + (k + 1) % nt, last + k], 1)
    f = np.concatenate([side, cap0, cap1]).astype(np.int64)
    return v, np.ascontiguousarray(f[:, ::-1])      # normals outward


def write_ply(path: Path, v: np.ndarray, f: np.ndarray) -> None:
    head = (f"ply\nformat binary_little_endian 1.0\nelement vertex {len(v)}\nproperty float x\n"
            f"property float y\nproperty float z\nelement face {len(f)}\n"
            "property list uchar int vertex_indices\nend_header\n").encode()
    rec = np.zeros(len(f), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    rec["n"] = 3
    rec["i"] = f
    with open(path, "wb") as fh:
        fh.write(head)
        fh.write(v.astype("<f4").tobytes())
        fh.write(rec.tobytes())


def make_scene(folder: Path, mtri: float) -> int:
    """A scene folder with the wall of about ``mtri`` million triangles; returns the count."""
    import yaml

    folder.mkdir(parents=True, exist_ok=True)
    nt = int(round(np.sqrt(mtri * 1e6 / 5.0)))     # ns = 2.5 nt
    v, f = tube_wall(nt, int(2.5 * nt))
    write_ply(folder / "wall.ply", v, f)
    (folder / "scene.yaml").write_text(yaml.safe_dump({
        "name": "large", "units": "mm", "meshes": [{"name": "wall", "file": "wall.ply", "role": "wall"}],
        "base_pose": {"position": [0.0, 0.0, 0.0], "quaternion": [1.0, 0.0, 0.0, 0.0]},
        "targets": [], "source": "benchmarks/bench_large_mesh.py", "licence": "CC0"}))
    return len(f)


def timed_check(scene: Path, configs: Path, out: Path, cache: Path, extra: list[str],
                root: Path = ROOT) -> dict:
    env = dict(os.environ, OMP_NUM_THREADS="1", MKL_NUM_THREADS="1", NUMBA_NUM_THREADS="1",
               CTRPLAN_CACHE=str(cache), PYTHONPATH=str(root))
    cmd = ["/usr/bin/time", "-v", str(Path(sys.executable).parent / "ctrplan"), "check", "--scene", str(scene),
           "--robot", "seed1", "--configs", str(configs), "--out", str(out), *extra]
    t0 = time.perf_counter()
    proc = subprocess.run(cmd, capture_output=True, text=True, env=env)
    wall = time.perf_counter() - t0
    rss = re.search(r"Maximum resident set size \(kbytes\): (\d+)", proc.stderr)
    return {"rc": proc.returncode, "wall_s": round(wall, 2),
            "peak_rss_mb": round(int(rss.group(1)) / 1024, 1) if rss else None,
            "stderr_tail": proc.stderr.split("\tCommand being timed")[0][-400:]}


def run(quick: bool = False, sizes: tuple[float, ...] | None = None, baseline: str = "") -> dict:
    from ctrplan.collision.budget import estimate
    from ctrplan.robot import load_robot

    sizes = sizes or ((0.3,) if quick else (0.3, 1.25, 5.0))
    out: dict = {"sizes": []}
    with tempfile.TemporaryDirectory(prefix="ctrplan-large-") as tmp:
        tmp = Path(tmp)
        q = load_robot("seed1").sample(1000, seed=0)
        configs = tmp / "configs.csv"
        np.savetxt(configs, q, delimiter=",", comments="",
                   header="alpha1,alpha2,alpha3,beta1,beta2,beta3")
        for mtri in sizes:
            folder = tmp / f"scene_{mtri}"
            tri = make_scene(folder, mtri)
            est_mb, est_s = estimate(tri)
            row = {"triangles": tri, "estimate_mb": round(est_mb), "estimate_s": round(est_s, 1)}
            cache = tmp / f"cache_{mtri}"
            row["first"] = timed_check(folder, configs, tmp / "v1.csv", cache, [])
            row["cached"] = timed_check(folder, configs, tmp / "v2.csv", cache, [])
            if baseline:       # another checkout (e.g. before this work), same scene, same run
                row["baseline_first"] = timed_check(folder, configs, tmp / "vb.csv",
                                                    tmp / f"cache_b{mtri}", ["--max-mb", "8000"],
                                                    Path(baseline))
            if row["first"]["rc"] == 0 and row["cached"]["rc"] == 0:
                row["same_verdicts"] = (tmp / "v1.csv").read_bytes() == (tmp / "v2.csv").read_bytes()
                if baseline and row["baseline_first"]["rc"] == 0:   # collides column
                    ours = np.loadtxt(tmp / "v1.csv", delimiter=",", skiprows=1, usecols=0)
                    theirs = np.loadtxt(tmp / "vb.csv", delimiter=",", skiprows=1, usecols=0)
                    row["baseline_same_collides"] = bool(np.array_equal(ours, theirs))
                row["collide"] = int(np.loadtxt(tmp / "v1.csv", delimiter=",", skiprows=1,
                                                usecols=0).sum())
            out["sizes"].append(row)
            print(json.dumps(row), flush=True)
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--quick", action="store_true")
    p.add_argument("--sizes", default="", help="million triangles, comma-separated")
    p.add_argument("--baseline", default="", help="another checkout to time on the same scenes")
    p.add_argument("--out", default="")
    a = p.parse_args()
    sizes = tuple(float(x) for x in a.sizes.split(",")) if a.sizes else None
    res = run(a.quick, sizes, a.baseline)
    if a.out:
        Path(a.out).write_text(json.dumps(res, indent=1))


if __name__ == "__main__":
    main()
