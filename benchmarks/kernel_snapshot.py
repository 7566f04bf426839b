"""Before/after check of the mechanics kernels: every output array of a fixed set of solves.

A refactoring of the numba kernels (``ctrplan/shape/_ode.py``, ``_kernel.py``, ``_loaded.py``,
``_shooting.py``, ``_continuation.py``) must give the same numbers bit for bit. Run this script in
the old tree and in the new one (each with its own ``PYTHONPATH`` and fresh numba caches), then
compare::

    PYTHONPATH=/old/tree python benchmarks/kernel_snapshot.py --out before.npz
    PYTHONPATH=$PWD      python benchmarks/kernel_snapshot.py --out after.npz
    python benchmarks/kernel_snapshot.py --compare before.npz after.npz

The cases: seed1, two_tube_nylon (snapping: stability search, compliance continuation) and
two_tube_wide, compliant and rigid, with the stability check off and with probing; loaded rows
(gravity, tip force and moment; a large tip force that needs the load ramp; rows mixed with
unloaded ones); random kinks and the clearance effect; chained solves (the balanced pair through
its fold, two_tube_nylon through its bistable range, seed1 motions, a NaN start); the loaded
batch kernel from a NaN first guess. ``--compare`` exits 1 unless every array is equal
(``np.array_equal`` with NaNs equal) and prints what each case exercised (branch codes,
iterations).
"""

from __future__ import annotations

import argparse
import os
import sys

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMBA_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

from dataclasses import replace  # noqa: E402

import numpy as np  # noqa: E402

LOADS = dict(gravity=(0.0, -9.81, 0.0), tip_force=(0.1, -0.05, 0.02), tip_moment=(2.0, -1.0, 0.5))


def _balanced_pair():
    sys.path.insert(0, os.path.join(os.path.dirname(__file__), ".."))
    from tests.conftest import balanced_pair

    return balanced_pair()


def _record(out: dict, name: str, shape, info) -> None:
    out[f"{name}/points"] = shape.points
    out[f"{name}/s"] = shape.s
    out[f"{name}/ok"] = shape.ok
    out[f"{name}/radius"] = shape.radius
    if shape.pad is not None:
        out[f"{name}/pad"] = shape.pad
    for key in ("uz0", "iterations", "residual", "moment0", "detj", "branch", "uz0_alt",
                "continued"):
        v = getattr(info, key)
        if v is not None:
            out[f"{name}/{key}"] = np.asarray(v)


def _motions(robot, k: int, steps: int, seed: int) -> tuple[np.ndarray, np.ndarray]:
    """k straight-line motions between random configurations, ``steps`` states each."""
    a = robot.sample(k, seed=seed)
    b = robot.sample(k, seed=seed + 1)
    t = np.linspace(0.0, 1.0, steps)[:, None]
    q = np.concatenate([a[i] + t * (b[i] - a[i]) for i in range(k)])
    start = np.zeros(len(q), dtype=bool)
    start[::steps] = True
    return q, start


def snapshot() -> dict[str, np.ndarray]:
    from ctrplan.robot import load_robot
    from ctrplan.shape import _loaded
    from ctrplan.shape.effects import EffectModel
    from ctrplan.shape.physics import Loads, PhysicsConfig, PhysicsModel

    out: dict[str, np.ndarray] = {}
    for name, B, seed in (("seed1", 300, 1), ("two_tube_nylon", 400, 5), ("two_tube_wide", 300, 3)):
        robot = load_robot(name)
        q = robot.sample(B, seed=seed)
        for label, model in (
                ("compliant", PhysicsModel(robot)),
                ("rigid", PhysicsModel(robot, torsion=False)),
                ("probe", PhysicsModel(robot, config=PhysicsConfig(probe_bistable=True))),
                ("nostab", PhysicsModel(robot, config=PhysicsConfig(stability=False)))):
            _record(out, f"{name}/{label}", model.shape(q, 20), model.last_info)
        for torsion in (True, False):
            model = PhysicsModel(robot, torsion=torsion, loads=Loads(**LOADS))
            ql = q[:80]
            _record(out, f"{name}/loaded_{torsion}", model.shape(ql, 15), model.last_info)
            # half the rows unloaded, random kinks everywhere
            p = model.base_params(len(ql))
            rng = np.random.default_rng(7)
            kink = rng.uniform(-0.03, 0.03, p.kink.shape)
            w = p.weight.copy()
            f = p.force.copy()
            mo = p.moment.copy()
            w[::2] = f[::2] = mo[::2] = 0.0
            p = replace(p, kink=kink, weight=w, force=f, moment=mo)
            _record(out, f"{name}/mixed_kink_{torsion}", model.solve(ql, 11, p), model.last_info)
            unl = PhysicsModel(robot, torsion=torsion)
            pu = replace(unl.base_params(len(q)), kink=rng.uniform(-0.03, 0.03, (len(q), robot.n, 2)))
            _record(out, f"{name}/kink_{torsion}", unl.solve(q, 11, pu), unl.last_info)
        big = PhysicsModel(robot, loads=Loads(tip_force=(1.5, 0.0, -0.5), tip_moment=(20.0, 0, 0)))
        _record(out, f"{name}/bigload", big.shape(q[:40], 9), big.last_info)
        # eight times the torsional compliance: unstable first roots whose stable one is found
        # by continuation (branch 3) or not at all (-1), also under loads
        qs = robot.sample(120, seed=98)
        for label, model in (("soft", PhysicsModel(robot, config=PhysicsConfig(probe_bistable=True))),
                             ("soft_loaded", PhysicsModel(robot, loads=Loads(**LOADS)))):
            p = model.base_params(len(qs))
            p = replace(p, ratio=8.0 * p.ratio)
            _record(out, f"{name}/{label}", model.solve(qs, 9, p), model.last_info)
    # the clearance effect (kinks from the model) on both bases
    seed1 = load_robot("seed1")
    q = seed1.sample(150, seed=11)
    for base in ("compliant", "rigid"):
        em = EffectModel(seed1, base=base, effects={"clearance": {"length": 4.0, "limit": 0.05}})
        out[f"effect_{base}/points"] = em.shape(q, 12).points
    # chained solves
    pair = _balanced_pair()
    a = np.arange(0.0, 4.6, 0.01)
    qp = np.stack([a, 0 * a, -50.0 + 0 * a, -50.0 + 0 * a], 1)
    model = PhysicsModel(pair)
    _record(out, "chain_pair", model.solve(qp, 12, model.base_params(len(qp)),
                                           chain=np.zeros(len(qp), dtype=bool)), model.last_info)
    nylon = load_robot("two_tube_nylon")
    a = np.linspace(2.4, 3.7, 27)
    qn = np.stack([a, 0 * a, -160 + 0 * a, -100 + 0 * a], 1)
    model = PhysicsModel(nylon)
    _record(out, "chain_nylon", model.solve(qn, 9, model.base_params(len(qn)),
                                            chain=np.zeros(len(qn), dtype=bool)), model.last_info)
    for name, seed in (("seed1", 2), ("two_tube_nylon", 4), ("two_tube_wide", 6)):
        robot = load_robot(name)
        qm, start = _motions(robot, 6, 25, seed)
        model = PhysicsModel(robot)
        x0 = np.full((len(qm), robot.n), np.nan)
        x0[25] = 0.0
        _record(out, f"chain_{name}", model.solve(qm, 10, model.base_params(len(qm)), uz_init=x0,
                                                  chain=start), model.last_info)
    # the loaded batch kernel from a first guess Newton cannot use
    r = seed1
    n = r.n
    q1 = seed1.sample(5, seed=21)
    m = PhysicsModel(r, loads=Loads(gravity=(0.0, -9.81, 0.0), tip_force=(0.2, 0.0, 0.0)))
    p = m.base_params(len(q1))
    res = _loaded.solve_loaded_batch(
        np.ascontiguousarray(q1[:, :n]), np.ascontiguousarray(q1[:, n:]), r.lengths,
        r.array("straight_length"), p.kappa, p.EI, p.ratio, p.kink, p.weight, p.force,
        np.zeros((len(q1), 3)), 9, 10.0, 1e-10, 30, np.full((len(q1), n + 2), np.nan),
        np.zeros((len(q1), n + 2)))
    for i, v in enumerate(res):
        out[f"loaded_nan/{i}"] = np.asarray(v)
    return out


def compare(a_path: str, b_path: str) -> int:
    a = np.load(a_path)
    b = np.load(b_path)
    bad = sorted(set(a.files) ^ set(b.files))
    for k in sorted(set(a.files) & set(b.files)):
        if a[k].shape != b[k].shape or a[k].dtype != b[k].dtype or not np.array_equal(
                a[k], b[k], equal_nan=a[k].dtype.kind == "f"):
            bad.append(k)
    n_vals = sum(a[k].size for k in a.files)
    print(f"{len(a.files)} arrays, {n_vals:,} values compared")
    for k in sorted(a.files):
        if k.endswith("/branch"):
            codes, counts = np.unique(a[k], return_counts=True)
            print(f"  {k}: branch codes {dict(zip(codes.tolist(), counts.tolist()))}")
        if k.endswith("/iterations"):
            print(f"  {k}: iterations max {a[k].max()}, total {a[k].sum()}")
        if k.endswith("/continued"):
            print(f"  {k}: continued {int(a[k].sum())} of {a[k].size}")
        if k.endswith("/ok"):
            print(f"  {k}: ok {int(a[k].sum())} of {a[k].size}")
    if bad:
        print("DIFFERENT:", ", ".join(bad))
        return 1
    print("all equal (bit for bit)")
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--out", help="write the snapshot (.npz)")
    ap.add_argument("--compare", nargs=2, metavar=("BEFORE", "AFTER"))
    args = ap.parse_args()
    if args.compare:
        return compare(*args.compare)
    if not args.out:
        ap.error("--out or --compare")
    np.savez_compressed(args.out, **snapshot())
    return 0


if __name__ == "__main__":
    sys.exit(main())
