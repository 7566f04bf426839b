"""Time per shape of the learned model vs the batched physics model, batch 1 .. 100,000.

Both models run in the same process on ``seed1`` with 20 points per backbone and one thread
(``torch.set_num_threads(1)``; the numba kernel is serial): the public ``backbone(q)`` call,
conversion to float64 numpy included. The learned model is the shipped default
(``ctrplan/data/models/seed1.pt``; an untrained network of the same size if none is shipped:
timing does not depend on the weights). Reported per batch size: median thread-CPU time and
wall time per shape (us) over repeats, and the speed-up learned vs physics. Thread CPU time
is the cost on one core and does not count time the OS gives to other processes on a shared
machine; both are reported. Usage::

    python benchmarks/bench_learned.py [--quick] [--out results.json]
    python benchmarks/bench_learned.py --device cuda [--out results.json]   # GPU table

With ``--device cuda`` (``run_gpu``) the learned model is timed on the GPU: the public
``backbone(q)`` call from float64 numpy in to float64 numpy out (transfers included; batches
below ``GPU_MIN_BATCH`` run on the CPU paths by design), ``shape(q)`` (backbones, closed-form
rigid base and continuity pad on the device) and the network's forward pass on tensors already
on the device (synchronised), batch 1 .. 1,000,000, each next to the same model on one CPU core
in the same run (``cpu_us_per_shape``, ``speedup_vs_cpu``). ``--device auto`` runs it when torch
sees a GPU (else the CPU table) and ``--record`` writes the result to
``benchmarks/results/learned_gpu_<card>.json`` (the card's name in the file and its name).

``run(quick) -> dict`` is what ``ctrplan bench`` calls; ``table`` holds the markdown rows.
Targets (issue 3): at batch 100,000 at most 1 us per shape and at least 100x faster than the
batched physics model.

``variants`` (issue 14): the same public call as the table (``backbone(q)``, with
``direction=D`` for direction-aware models) at batch 100,000 for the pure
shipped model, a direction-aware one, a residual one over a learned base (the shipped
network; evaluated in the same pass, no physics call), and both, as medians and as ratios to
the pure model measured in the same run (target <= 2x). A residual model over the *physics*
base adds one physics call per shape: it is timed too, and its ratio is physics-sized.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

for _var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numba  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from ctrplan.robot import load_robot  # noqa: E402
from ctrplan.shape.learned import LearnedModel, shipped_model_path  # noqa: E402
from ctrplan.shape.physics import PhysicsModel  # noqa: E402

ROBOT = "seed1"
POINTS = 20
SEED = 1


def _rel(path) -> str:
    """The model file relative to the repository (results carry no machine paths)."""
    return os.path.relpath(path, os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


def _median_time(fn, repeats: int) -> tuple[float, float]:
    cpu: list[float] = []
    wall: list[float] = []
    for _ in range(repeats):
        c0 = time.thread_time()
        t0 = time.perf_counter()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.thread_time() - c0)
    return statistics.median(cpu), statistics.median(wall)


def _repeats(batch: int, quick: bool) -> int:
    if batch <= 10:
        return 50 if quick else 300
    if batch <= 1000:
        return 5 if quick else 20
    return 2 if quick else 3


def network_floor(learned: LearnedModel, B: int, repeats: int) -> dict:
    """Per-shape CPU time of the network's matrix products alone (hidden layers and the 3K
    outputs, torch ``addmm`` in the model's chunks, nothing else), and with the basis expansion
    to ``POINTS`` points: what no trimming of the public call can go below on this core."""
    from ctrplan.shape.learned import CHUNK

    hidden, Wl, bl, M, *_ = learned._cpu_weights(POINTS)
    X = torch.randn(B, hidden[0][0].shape[0], generator=torch.Generator().manual_seed(SEED))
    bufs = [torch.empty(CHUNK, W.shape[1]) for W, _, _ in hidden]
    cbuf, pbuf = torch.empty(CHUNK, Wl.shape[1]), torch.empty(CHUNK, M.shape[1])

    def products(expand: bool) -> None:
        with torch.inference_mode():
            for i in range(0, B, CHUNK):
                h = X[i:i + CHUNK]
                r = len(h)
                for (W, b, slope), buf in zip(hidden, bufs):
                    torch.addmm(b, h, W, out=buf[:r])
                    torch.nn.functional.leaky_relu_(buf[:r], float(slope.reshape(-1)[0]))
                    h = buf[:r]
                torch.addmm(bl, h, Wl, out=cbuf[:r])
                if expand:
                    torch.mm(cbuf[:r], M, out=pbuf[:r])

    mlp, _ = _median_time(lambda: products(False), repeats)
    full, _ = _median_time(lambda: products(True), repeats)
    return {"batch": B, "network_products_us_per_shape": 1e6 * mlp / B,
            "with_basis_expansion_us_per_shape": 1e6 * full / B}


def variants(learned: LearnedModel, quick: bool = False, batch: int = 100_000) -> dict:
    """Per-shape CPU time of the model variants at ``batch`` and their ratios to the pure model."""
    from ctrplan.shape import training as T

    robot = learned.robot
    q = robot.sample(batch, seed=SEED + 1)
    d = np.random.default_rng(SEED).choice([-1, 0, 1], size=q.shape).astype(np.int8)
    direction = T.with_direction_inputs(learned)
    pairs = learned.pair_inputs                               # same inputs: one pass
    residual = T.new_model(robot, learned.width, learned.depth, learned.terms, seed=1, base=learned,
                           pairs=pairs)
    both = T.new_model(robot, learned.width, learned.depth, learned.terms, seed=1, base=learned,
                       direction=True, pairs=pairs)
    phys_res = T.new_model(robot, learned.width, learned.depth, learned.terms, seed=1,
                           base=PhysicsModel(robot))
    calls = {
        "pure": lambda: learned.backbone(q, POINTS),
        "direction": lambda: direction.backbone(q, POINTS, direction=d),
        "residual (learned base)": lambda: residual.backbone(q, POINTS),
        "residual+direction (learned base)": lambda: both.backbone(q, POINTS, direction=d),
    }
    reps = 3 if quick else 7
    rows = {}
    for fn in calls.values():
        fn()                                                  # warm up
    for _ in range(2):                                        # interleave: same machine load
        for name, fn in calls.items():
            c, _ = _median_time(fn, reps)
            rows.setdefault(name, []).append(c)
    out = {name: 1e6 * min(v) / batch for name, v in rows.items()}
    pb = min(batch, 10_000) if quick else batch
    phys_res.backbone(q[:4], POINTS)                          # warm up (kernel load)
    c, _ = _median_time(lambda: phys_res.backbone(q[:pb], POINTS), 1)
    pc, _ = _median_time(lambda: PhysicsModel(robot).backbone(q[:pb], POINTS), 1)
    return {"batch": batch, "us_per_shape": out,
            "ratio_to_pure": {k: v / out["pure"] for k, v in out.items()},
            "residual_physics_base": {"batch": pb, "us_per_shape": 1e6 * c / pb,
                                      "physics_alone_us_per_shape": 1e6 * pc / pb,
                                      "note": "a residual over the physics base calls physics once per shape"}}


def run(quick: bool = False) -> dict:
    # numba's pool through its API: NUMBA_NUM_THREADS set after numba is imported (as under
    # `ctrplan bench`) makes numba refuse every later compile in the process
    numba.set_num_threads(1)
    torch.set_num_threads(1)
    robot = load_robot(ROBOT)
    path = shipped_model_path(ROBOT)
    learned = LearnedModel.load(path, robot=robot) if path else LearnedModel(robot)
    physics = PhysicsModel(robot)
    batches = [1, 100, 1000, 10_000] if quick else [1, 10, 100, 1000, 10_000, 100_000]
    q_all = robot.sample(max(batches), seed=SEED)
    learned.backbone(q_all[:2], POINTS)                      # warm up both paths / JIT
    learned.backbone(q_all[:1000], POINTS)
    physics.backbone(q_all[:2], POINTS)
    rows = []
    for B in batches:
        q = q_all[:B]
        reps = _repeats(B, quick)
        lc, lw = _median_time(lambda q=q: learned.backbone(q, POINTS), max(reps, 3))
        preps = max(1, reps // 3) if B >= 10_000 else reps
        pc, pw = _median_time(lambda q=q: physics.backbone(q, POINTS), preps)
        rows.append({
            "batch": B,
            "learned_us_per_shape": 1e6 * lc / B, "learned_wall_us_per_shape": 1e6 * lw / B,
            "physics_us_per_shape": 1e6 * pc / B, "physics_wall_us_per_shape": 1e6 * pw / B,
            "speedup": pc / lc if lc > 0 else float("inf"),
        })
    big = rows[-1]
    b1 = rows[0]
    floor = network_floor(learned, big["batch"], 3 if quick else 9)
    return {
        "robot": ROBOT, "points": POINTS, "threads": torch.get_num_threads(),
        "model": _rel(path) if path else "untrained network (no shipped model)",
        "architecture": f"{learned.depth}x{learned.width}, K={learned.terms}, frame={learned.frame}, "
                        f"pairs={learned.pair_inputs}, base={type(learned.base).__name__}",
        "table": rows,
        "batch1_latency_us": {"learned": b1["learned_us_per_shape"], "physics": b1["physics_us_per_shape"]},
        "largest_batch": big["batch"],
        "target_le_1us_at_100k": bool(big["batch"] >= 100_000 and big["learned_us_per_shape"] <= 1.0),
        "target_ge_100x_at_100k": bool(big["batch"] >= 100_000 and big["speedup"] >= 100.0),
        "floor": floor,
        "ratio_bound_from_floor": big["physics_us_per_shape"] / floor["with_basis_expansion_us_per_shape"],
        "variants": variants(learned, quick, batch=10_000 if quick else 100_000),
    }


def run_gpu(quick: bool = False, device: str = "cuda") -> dict:
    """Learned model on a CUDA device: wall time per shape vs batch size (median over repeats)."""
    robot = load_robot(ROBOT)
    path = shipped_model_path(ROBOT)
    learned = LearnedModel.load(path, robot=robot, device=device) if path else LearnedModel(robot, device=device)
    batches = [1, 100, 10_000, 100_000] if quick else [1, 10, 100, 1000, 10_000, 100_000, 1_000_000]
    q_all = robot.sample(max(batches), seed=SEED)

    def synced(fn):
        def call():
            fn()
            torch.cuda.synchronize(device)
        return call

    numba.set_num_threads(1)
    torch.set_num_threads(1)
    cpu = LearnedModel.load(path, robot=robot, device="cpu") if path else LearnedModel(robot)
    rows = []
    for B in batches:
        q = q_all[:B]
        qt = torch.as_tensor(q, dtype=torch.float32, device=device)
        public = synced(lambda q=q: learned.backbone(q, POINTS))
        shape = synced(lambda q=q: learned.shape(q, POINTS))

        def on_device(qt=qt):
            with torch.inference_mode():
                learned._fast_points(qt, POINTS)
        forward = synced(on_device)
        for fn in (public, shape, forward):   # warm up (kernels, allocator)
            fn()
            fn()
        reps = 200 if B <= 1000 else (20 if B <= 100_000 else 5)
        reps = max(3, reps // 4) if quick else reps
        _, pw = _median_time(public, reps)
        _, sw = _median_time(shape, reps)
        _, fw = _median_time(forward, reps)
        cpu.backbone(q[:2], POINTS)
        cc, _ = _median_time(lambda q=q: cpu.backbone(q, POINTS), max(3, reps // 4))
        cs, _ = _median_time(lambda q=q: cpu.shape(q, POINTS), max(3, reps // 4))
        rows.append({"batch": B, "backbone_us_per_shape": 1e6 * pw / B,
                     "shape_us_per_shape": 1e6 * sw / B,
                     "forward_on_device_us_per_shape": 1e6 * fw / B,
                     "backbone_call_ms": 1e3 * pw,
                     "cpu_us_per_shape": 1e6 * cc / B, "cpu_shape_us_per_shape": 1e6 * cs / B,
                     "speedup_vs_cpu": cc / pw if pw > 0 else float("inf"),
                     "shape_speedup_vs_cpu": cs / sw if sw > 0 else float("inf")})
    from ctrplan.shape.learned import GPU_MIN_BATCH

    return {"robot": ROBOT, "points": POINTS, "device": torch.cuda.get_device_name(device),
            "torch": torch.__version__, "model": _rel(path) if path else "untrained network",
            "architecture": f"{learned.depth}x{learned.width}, K={learned.terms}, "
                            f"pairs={learned.pair_inputs}, base={type(learned.base).__name__}",
            "gpu_min_batch": GPU_MIN_BATCH, "cpu": "one core, one thread (same run)",
            "table": rows}


def record_path(res: dict) -> str:
    """benchmarks/results/learned_gpu_<card>.json for a GPU result."""
    import re

    slug = re.sub(r"[^a-z0-9]+", "_", res["device"].lower()).strip("_")[:40] or "gpu"
    return os.path.join(os.path.dirname(os.path.abspath(__file__)), "results", f"learned_gpu_{slug}.json")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--quick", action="store_true")
    ap.add_argument("--out", default=None)
    ap.add_argument("--device", default="cpu",
                    help="cpu (learned vs physics), cuda (learned on the GPU vs one CPU core) or "
                         "auto (cuda when torch sees a GPU)")
    ap.add_argument("--record", action="store_true",
                    help="with a GPU: also write benchmarks/results/learned_gpu_<card>.json")
    args = ap.parse_args(argv)
    if args.device == "auto":
        args.device = "cuda" if torch.cuda.is_available() else "cpu"
    if args.device != "cpu" and not torch.cuda.is_available():
        print(f"bench_learned: --device {args.device}: torch sees no CUDA device", file=sys.stderr)
        return 2
    if args.device != "cpu":
        res = run_gpu(quick=args.quick, device=args.device)
        print(f"{res['device']}, torch {res['torch']}, {res['architecture']}")
        print(f"{'batch':>8} {'backbone us':>12} {'shape us':>9} {'forward us':>11} {'CPU us':>8} "
              f"{'x CPU':>7} {'shape x CPU':>12}")
        lines = [f"{r['batch']:>8} {r['backbone_us_per_shape']:>12.4f} {r['shape_us_per_shape']:>9.4f} "
                 f"{r['forward_on_device_us_per_shape']:>11.5f} {r['cpu_us_per_shape']:>8.3f} "
                 f"{r['speedup_vs_cpu']:>6.1f}x {r['shape_speedup_vs_cpu']:>11.1f}x"
                 for r in res["table"]]
        if args.record:
            with open(record_path(res), "w") as fh:
                json.dump(res, fh, indent=2)
    else:
        res = run(quick=args.quick)
        print(f"{'batch':>7} {'learned us':>11} {'(wall)':>8} {'physics us':>11} {'(wall)':>8} {'speed-up':>9}")
        lines = [f"{r['batch']:>7} {r['learned_us_per_shape']:>11.3f} {r['learned_wall_us_per_shape']:>8.3f} "
                 f"{r['physics_us_per_shape']:>11.2f} {r['physics_wall_us_per_shape']:>8.2f} {r['speedup']:>8.0f}x"
                 for r in res["table"]]
    print("\n".join(lines))
    if "floor" in res:
        f = res["floor"]
        print(f"network products alone at batch {f['batch']}: {f['network_products_us_per_shape']:.3f} us/shape, "
              f"{f['with_basis_expansion_us_per_shape']:.3f} with the basis expansion "
              f"(bound on the speed-up: {res['ratio_bound_from_floor']:.0f}x)")
    if "variants" in res:
        v = res["variants"]
        print(f"variants at batch {v['batch']} (backbone(), us/shape, ratio to pure in this run):")
        for k, t in v["us_per_shape"].items():
            print(f"  {k:<36} {t:8.3f}  {v['ratio_to_pure'][k]:5.2f}x")
        p = v["residual_physics_base"]
        print(f"  residual over physics (batch {p['batch']}): {p['us_per_shape']:.2f} us/shape "
              f"(physics alone {p['physics_alone_us_per_shape']:.2f}): {p['note']}")
    if args.out:
        with open(args.out, "w") as fh:
            json.dump(res, fh, indent=2)
    return 0


if __name__ == "__main__":
    sys.exit(main())
