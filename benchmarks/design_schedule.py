"""Replays a design search's job schedule on W simulated workers (used by bench_design.py).

The search's runner logs every submission (ticket, priority), every wait for a result, the
caller's own seconds in between, and each job's seconds measured where it ran
(:meth:`ctrplan.design.runner.Runner.schedule`). :func:`simulate` replays that log as list
scheduling on ``workers`` identical workers, with the runner's dispatch rule (a free worker
takes the queued job of best priority, then the earliest submitted; the caller blocks at a
wait until that job is done), and returns the makespan. The decisions of the search do not
depend on timing, so the same log holds for any number of workers: only when things run
changes. What it leaves out: the time to send jobs and results between processes, and cores
slowed by each other (memory, turbo); it is a prediction, to be checked by a real run.
"""

from __future__ import annotations

import heapq


def simulate(schedule: dict, workers: int, startup_s: float = 0.0, first_load: bool = True,
             clock: str = "cpu") -> float:
    """Makespan (s) of ``schedule`` (:meth:`Runner.schedule`, tickets as int or str keys) on
    ``workers`` workers, each ready ``startup_s`` after the start (process start, imports, the
    scene). ``first_load``: add the job's own recorded scene-loading seconds (the in-process
    run loads the scene in its first job) to every job's seconds. ``clock``: "cpu" takes each
    job's CPU seconds (what it costs on a core of its own: a run on a shared machine still
    predicts an unloaded one), "wall" its wall-clock seconds."""
    secs = {int(k): v for k, v in schedule["seconds"].items()}
    job, load = ("cpu_s", "load_cpu_s") if clock == "cpu" else ("job_s", "load_s")
    dur = {t: s[job] + (s[load] if first_load else 0.0) for t, s in secs.items()}
    free = [float(startup_s)] * int(workers)      # when each worker is next free
    queue: list[tuple[int, int]] = []             # (priority, ticket) queued
    end: dict[int, float] = {}
    t = 0.0

    def start_next(at: float) -> None:
        w = min(range(len(free)), key=free.__getitem__)
        _, k = heapq.heappop(queue)
        begin = max(free[w], at)
        free[w] = end[k] = begin + dur[k]

    def advance(to: float) -> None:
        # every worker that frees up before `to` takes the next queued job when it frees
        while queue and min(free) <= to:
            start_next(t)

    for ev in schedule["events"]:
        if ev["event"] == "caller":
            advance(t + ev["s"])
            t += ev["s"]
        elif ev["event"] == "submit":
            heapq.heappush(queue, (ev["priority"], int(ev["ticket"])))
            advance(t)
        else:                                      # wait for one ticket
            k = int(ev["ticket"])
            while k not in end:
                start_next(t)                      # the next worker to free up takes the next job
            advance(max(t, end[k]))
            t = max(t, end[k])
    return max([t, *end.values()])


def predict(schedule: dict, serial_s: float, worker_counts: list[int], startup_s: float,
            clock: str = "cpu") -> dict:
    """Predicted wall seconds and parallel efficiency per worker count: ``serial_s`` (the
    command's time outside the runner: anatomy, outputs) plus the simulated makespan; one
    worker runs in this process (no start-up), more on a pool that starts its workers while the
    command reads the anatomy (the log's ``head_s`` of the start-up is hidden)."""
    startup_s = max(0.0, startup_s - schedule.get("head_s", 0.0))
    t1 = serial_s + simulate(schedule, 1, clock=clock)
    out = {}
    for w in worker_counts:
        tw = t1 if w == 1 else serial_s + simulate(schedule, w, startup_s, first_load=False, clock=clock)
        out[str(w)] = {"wall_s": tw, "speedup": t1 / tw, "parallel_efficiency": t1 / (w * tw)}
    return out


def startup_probe(scene_spec, settings: dict) -> float:
    """In a fresh worker: load the scene as its first job would; returns the CPU seconds this
    process has used since it started (interpreter, imports, scene: a worker's start-up, on a
    core of its own)."""
    import time

    from ctrplan.design.runner import warm_worker

    warm_worker(scene_spec, settings)
    return time.process_time()
