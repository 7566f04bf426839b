"""Evaluation jobs of the design search: submitted now, collected later, on any backend.

:class:`Runner` runs :func:`ctrplan.design.evaluate.evaluate_job` in this process, on a spawned
process pool (``workers > 1``) or on Ray (``ray_address``: the same session as ``plan-batch
--ray``, :mod:`ctrplan.planning.ray_pool`). :meth:`Runner.submit` returns a ticket at once;
:meth:`Runner.result` waits for that ticket's result. What a caller gets never depends on
where, when or in which order the jobs ran: every job is a pure function of its input, and a
caller decides when it looks at a result (the design search does so at fixed generations,
:mod:`ctrplan.design.search`).

Dispatch: the runner keeps its own queue and starts a job only when a worker is free (at most
``workers`` jobs on the pool, the cluster's CPUs on Ray), lowest ``priority`` first, then in
submission order. So the search's short screens (priority 0) never wait behind plans queued
before them, only behind plans already running. Jobs are started whenever the caller is in
the runner (submitting or waiting), which is nearly always. In this process (one worker) a
job runs when its result is asked for.

Schedule log: every submission, every wait and the caller's own time in between, and each
job's seconds measured where it ran (scene loading apart), are kept in :meth:`Runner.schedule`:
enough to replay the search's schedule on any number of simulated workers
(``benchmarks/bench_design.py``).
"""

from __future__ import annotations

import contextlib
import heapq
import sys
import time
from collections.abc import Callable

from ctrplan.design.evaluate import EvalSettings, context, evaluate_job

#: Priority of the search's screens (run first) and of every other job (plans).
SCREEN, PLAN = 0, 1


def timed_job(job: dict, planners=None) -> tuple[dict, dict]:
    """:func:`evaluate_job` and its seconds: ``load_s`` (the scene and its collision world,
    once per process) and ``job_s`` (the evaluation itself), wall-clock; ``load_cpu_s`` and
    ``cpu_s``, the same in this process's CPU time (what the job costs on a core of its own,
    whatever else the machine runs)."""
    t0, c0 = time.perf_counter(), time.process_time()
    context(job["scene"], EvalSettings(**job["settings"]), planners)
    t1, c1 = time.perf_counter(), time.process_time()
    res = evaluate_job(job, planners)
    return res, {"load_s": t1 - t0, "job_s": time.perf_counter() - t1,
                 "load_cpu_s": c1 - c0, "cpu_s": time.process_time() - c1}


def warm_worker(scene_spec, settings: dict) -> None:
    """Load the scene and its collision world into this worker (what its first job would)."""
    context(scene_spec, EvalSettings(**settings))


class Runner:
    """Runs evaluation jobs in this process, on a spawned process pool (``workers > 1``) or on
    Ray (``ray_address``); see the module's docstring. ``fn(job, planners=None) -> (result,
    seconds)`` runs one job (:func:`timed_job`; a module-level function, for the pool)."""

    def __init__(self, workers: int, ray_address: str | None = None, fn: Callable = timed_job,
                 warm: tuple | None = None):
        from ctrplan.planning.planner import Planners

        self.fn = fn            # fn(job, planners=None) -> (result, seconds): timed_job
        #: (scene spec, settings dict): start the workers and load the scene in each on entry,
        #: so they get ready while the caller does its own work (reads the anatomy)
        self.warm = warm
        self._warming: list = []
        self.workers = int(workers)
        self.ray_address = ray_address
        self._ex = None
        self._ray = None
        self._ray_session = None
        self._remote = None
        self._capacity = 0
        #: the scenes of the jobs run in this process (the workers keep their own)
        self._planners = Planners()
        self._jobs: dict[int, dict] = {}          # ticket -> job not started yet
        self._queue: list[tuple[int, int]] = []   # (priority, ticket) not started yet
        self._running: dict = {}                  # backend handle -> ticket
        self._done: dict[int, dict] = {}          # ticket -> result not collected yet
        self._next = 0
        self._events: list[dict] = []
        self._seconds: dict[int, dict] = {}
        self._mark = self._entered = self._opened = time.perf_counter()
        self._head = 0.0

    # ------------------------------------------------------------------ lifetime
    def __enter__(self) -> Runner:
        self._opened = time.perf_counter()
        if self.ray_address:
            from ctrplan.planning.ray_pool import ray_session

            # a local instance gets every core Ray detects (--workers and --ray exclude each other)
            self._ray_session = ray_session(self.ray_address)
            self._ray = self._ray_session.__enter__()
            self._remote = self._ray.remote(num_cpus=1)(self.fn)
            self._capacity = max(1, int(self._ray.cluster_resources().get("CPU", 1)))
            if self.warm is not None:
                task = self._ray.remote(num_cpus=1)(warm_worker)
                self._warming = [task.remote(*self.warm) for _ in range(self._capacity)]
        elif self.workers > 1:
            from concurrent.futures import ProcessPoolExecutor

            from ctrplan import interrupt
            from ctrplan.planning.batch import _worker_init

            # spawn, not fork: numba, torch and OMPL threads do not survive a fork reliably;
            # workers start with SIGINT blocked (the parent stops them)
            self._ex = ProcessPoolExecutor(max_workers=self.workers, initializer=_worker_init,
                                           mp_context=interrupt.worker_context("spawn"))
            self._capacity = self.workers
            if self.warm is not None:
                try:
                    with interrupt.spawning():   # workers start on demand; a Ctrl-C is raised after
                        self._warming = [self._ex.submit(warm_worker, *self.warm)
                                         for _ in range(self.workers)]
                except BaseException:
                    self.__exit__(*sys.exc_info())
                    raise
        self.start_log()
        return self

    def __exit__(self, *exc) -> None:
        if self._ray is not None:
            ray, self._ray = self._ray, None
            if exc[0] is not None:
                for ref in [*self._running, *self._warming]:   # a cluster runs on what is not cancelled
                    with contextlib.suppress(Exception):
                        ray.cancel(ref, force=True)
            self._ray_session.__exit__(*exc)    # shuts down a local instance: its workers end with it
        if self._ex is not None:
            if exc[0] is not None:
                # Ctrl-C or an error: stop every worker now, not after its current design
                # (the executor keeps its processes in a private dict; nothing public does this)
                for proc in list(getattr(self._ex, "_processes", {}).values()):
                    proc.terminate()
            self._ex.shutdown(wait=exc[0] is None, cancel_futures=True)
            self._ex = None
        self._running.clear()

    # ------------------------------------------------------------------ the caller's side
    def submit(self, job: dict, priority: int = PLAN) -> int:
        """Queue ``job``; returns its ticket (for :meth:`result`). Starts it if a worker is free."""
        self._caller_time()
        t = self._next
        self._next += 1
        self._jobs[t] = job
        if self._capacity:          # in this process: run when asked for (:meth:`result`)
            heapq.heappush(self._queue, (int(priority), t))
        self._events.append({"event": "submit", "ticket": t, "stage": job["stage"],
                             "priority": int(priority)})
        self._dispatch()
        self._mark = time.perf_counter()
        return t

    def result(self, ticket: int) -> dict:
        """The result of ``ticket`` (waits for it; each ticket's result is collected once)."""
        self._caller_time()
        self._events.append({"event": "wait", "ticket": ticket})
        while ticket not in self._done:
            if self._capacity == 0:
                self._run_here(ticket)
            else:
                self._dispatch()
                self._collect()
        self._mark = time.perf_counter()
        return self._done.pop(ticket)

    def map(self, jobs: list[dict], priority: int = PLAN) -> list[dict]:
        """The results of ``jobs``, in their order."""
        return [self.result(t) for t in [self.submit(j, priority) for j in jobs]]

    def schedule(self) -> dict:
        """The log so far: ``events`` (submit: ticket, stage, priority; wait: ticket; caller:
        seconds the caller spent outside the runner), ``seconds`` (ticket -> :func:`timed_job`'s),
        ``wall_s`` (since the log started) and ``head_s`` (from entering the runner, when the
        workers started, to the log's start: the start-up the caller's own work hid)."""
        return {"events": list(self._events), "seconds": {t: dict(s) for t, s in self._seconds.items()},
                "wall_s": time.perf_counter() - self._entered, "head_s": self._head}

    def start_log(self) -> None:
        """Start the schedule log afresh (the caller's time counts from now)."""
        self._events.clear()
        self._seconds.clear()
        self._mark = self._entered = time.perf_counter()
        self._head = self._entered - self._opened

    def _caller_time(self) -> None:
        self._events.append({"event": "caller", "s": time.perf_counter() - self._mark})

    # ------------------------------------------------------------------ backends
    def _run_here(self, ticket: int) -> None:
        res, secs = self.fn(self._jobs.pop(ticket), self._planners)
        self._finished(ticket, res, secs)

    def _dispatch(self) -> None:
        """Start queued jobs, best priority first, while a worker is free."""
        while self._queue and len(self._running) < self._capacity:
            _, t = heapq.heappop(self._queue)
            job = self._jobs.pop(t)
            if self._ray is not None:
                self._running[self._remote.remote(job)] = t
            else:
                from ctrplan import interrupt

                with interrupt.spawning():   # workers start on demand; a Ctrl-C is raised after
                    self._running[self._ex.submit(self.fn, job)] = t

    def _collect(self) -> None:
        """Wait until at least one running job finishes; keep what finished."""
        if self._ray is not None:
            from ctrplan import interrupt

            done, _ = self._ray.wait(list(self._running), num_returns=1, timeout=0.5)
            interrupt.check()    # a pending Ctrl-C / SIGTERM ends the wait
            for ref in done:
                self._finished(self._running.pop(ref), *self._ray.get(ref))
            return
        from concurrent.futures import FIRST_COMPLETED, wait

        done, _ = wait(list(self._running), return_when=FIRST_COMPLETED)
        for fut in done:
            self._finished(self._running.pop(fut), *fut.result())

    def _finished(self, ticket: int, res: dict, secs: dict) -> None:
        self._done[ticket] = res
        self._seconds[ticket] = secs
