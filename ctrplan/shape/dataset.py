"""Simulated shape data sets: large batches of backbones computed over all CPU cores.

:func:`simulate_shapes` cuts a batch of configurations into chunks, solves the chunks in a
process pool (each worker gets the model once, pickled) and returns one :class:`Shape` with the
rows in the input order. Small batches (one chunk) and ``workers=1`` run in this process.
"""

from __future__ import annotations

import multiprocessing as mp
import os
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np

from ctrplan.shape.base import Shape

_WORKER_MODEL: Any = None


def _init_worker(model: Any) -> None:
    global _WORKER_MODEL
    from ctrplan import interrupt

    interrupt.ignore_in_child()   # the parent stops the pool on Ctrl-C / SIGTERM
    _WORKER_MODEL = model
    try:  # keep each worker single-threaded: the pool already uses every core
        import torch

        torch.set_num_threads(1)
    except Exception:  # pragma: no cover - torch is a dependency
        pass


def _solve_chunk(args: tuple[int, np.ndarray, int]) -> tuple[int, tuple[np.ndarray, ...]]:
    k, q, points = args
    sh = _WORKER_MODEL.shape(q, points=points)
    return k, (sh.points, sh.s, sh.radius, sh.ok)


def _concat(parts: list[tuple[np.ndarray, ...]]) -> Shape:
    return Shape(
        points=np.concatenate([p[0] for p in parts], axis=0),
        s=np.concatenate([p[1] for p in parts], axis=0),
        radius=np.concatenate([p[2] for p in parts], axis=0),
        ok=np.concatenate([p[3] for p in parts], axis=0),
    )


def default_workers() -> int:
    """Worker processes used by default: every core this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except (AttributeError, OSError):  # pragma: no cover - non-Linux
        return max(1, os.cpu_count() or 1)


def simulate_shapes(model: Any, q: np.ndarray, points: int = 20, workers: int | None = None,
                    chunk: int = 2000, progress: bool = True) -> Shape:
    """Backbones of a (large) batch of configurations, computed in parallel.

    Parameters
    ----------
    model : ShapeModel
        Any picklable model with ``shape(q, points) -> Shape`` (e.g. :class:`PhysicsModel`).
    q : (B, 2n) float
        Configurations, rad and mm.
    points : int
        Backbone points per configuration (base to tip, inclusive).
    workers : int or None
        Processes to use; ``None`` means every available core, ``1`` runs in this process.
    chunk : int
        Configurations per task (also the progress-bar granularity).
    progress : bool
        Show a progress bar (only on a terminal, and not with ``ctrplan --quiet``).

    Returns
    -------
    Shape
        Rows in the order of ``q``. Rows the model could not solve have ``ok = False``.
    """
    from ctrplan.progress import bar

    q = np.ascontiguousarray(np.atleast_2d(np.asarray(q, dtype=float)))
    if chunk < 1:
        raise ValueError("chunk must be >= 1")
    if points < 2:
        raise ValueError("points must be >= 2 (base and tip)")
    B = len(q)
    workers = default_workers() if workers is None else int(workers)
    if workers < 1:
        raise ValueError("workers must be >= 1")
    starts = list(range(0, B, chunk)) or [0]
    tasks = [(k, q[a:a + chunk], points) for k, a in enumerate(starts)]
    parts: list[tuple[np.ndarray, ...] | None] = [None] * len(tasks)
    with bar(total=B, desc=f"simulate ({getattr(model, 'name', 'model')})", unit="shape") as pb:
        if not progress:
            pb.disable = True
        if workers == 1 or len(tasks) == 1:
            for k, qc, m in tasks:
                sh = model.shape(qc, points=m)
                parts[k] = (sh.points, sh.s, sh.radius, sh.ok)
                pb.update(len(qc))
        else:
            from ctrplan import interrupt

            # fork: workers inherit the compiled kernels and scripts need no __main__ guard;
            # they start with SIGINT blocked (their initializer ignores it; we stop them)
            ctx = interrupt.worker_context("fork" if "fork" in mp.get_all_start_methods() else "spawn")

            ex = ProcessPoolExecutor(max_workers=min(workers, len(tasks)), mp_context=ctx,
                                     initializer=_init_worker, initargs=(model,))
            try:
                with interrupt.spawning():    # the workers start in map(); a Ctrl-C is raised after it
                    results = ex.map(_solve_chunk, tasks)
                for k, res in results:
                    parts[k] = res
                    pb.update(len(res[0]))
            except BaseException:
                interrupt.stop_executor(ex)   # Ctrl-C or an error: no worker finishes its chunk
                raise
            ex.shutdown()
    return _concat(parts)  # type: ignore[arg-type]
