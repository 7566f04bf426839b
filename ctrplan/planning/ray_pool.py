"""Ray for every parallel command: one way to start or join a cluster and to run tasks on it.

``plan-batch --ray ADDRESS`` (:func:`ctrplan.planning.batch.run_batch`) and ``design --ray
ADDRESS`` (:class:`ctrplan.design.runner.Runner`) both run their work here:
:func:`ray_session` connects to the cluster at ADDRESS, or with ``"local"`` starts a private
Ray instance on this machine (shut down again on exit); :func:`ray_as_completed` submits one
task per argument (one CPU each, ``OMP_NUM_THREADS=1`` in every worker: the tasks are the
parallelism) and yields ``(index, result)`` as the tasks finish; plan-batch writes them as they
come. Design submits its own tasks on the session (a job when a CPU is free, collected by
ticket at fixed points of its search), so its outcome never depends on which worker finished
first.

Ray is optional (``pip install 'ctrplan[ray]'``); without it :func:`require_ray` raises
:class:`~ctrplan.errors.InputError` (one line on the command line, exit 2).
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterator, Sequence
from typing import Any

from ctrplan.errors import ArgumentError

#: ``--ray local``: start a Ray instance on this machine instead of joining a cluster.
LOCAL = "local"


def require_ray():
    """The ``ray`` module, or ArgumentError naming ``ray_address`` (``--ray`` on the command
    line) when it is not installed."""
    try:
        import ray
    except ImportError:
        raise ArgumentError("ray_address", "ray is not installed (pip install 'ctrplan[ray]')") from None
    return ray


@contextlib.contextmanager
def ray_session(address: str, num_cpus: int | None = None) -> Iterator[Any]:
    """Ray connected for the body: a cluster at ``address``, or a local instance for
    ``"local"`` (``num_cpus`` CPUs; None: every core Ray detects). A session this call started
    is shut down at exit (its workers end with it); an already initialised Ray is used as it is."""
    ray = require_ray()
    import signal
    import threading

    from ctrplan import interrupt

    # ray.init installs its own SIGTERM handling (a C++ handler that prints a stack and exits
    # 1; Python's default on shutdown): ours is put back after init and after shutdown, so
    # SIGINT / SIGTERM still end the command with one line and 130 / 143.
    ours = {s: signal.getsignal(s) for s in interrupt.SIGNALS}

    def restore() -> None:
        if threading.current_thread() is threading.main_thread():
            for s, h in ours.items():
                if h is not None:
                    signal.signal(s, h)

    started = False
    try:
        if not ray.is_initialized():
            env = {"env_vars": {"OMP_NUM_THREADS": "1"}}
            started = True     # from here on, shut down whatever init started
            if address == LOCAL:
                ray.init(num_cpus=num_cpus, include_dashboard=False, log_to_driver=False,
                         configure_logging=False, runtime_env=env)
            else:
                try:
                    ray.init(address=address, log_to_driver=False, configure_logging=False,
                             runtime_env=env)
                except Exception as exc:  # ray raises ConnectionError, RuntimeError, ValueError...
                    raise ArgumentError("ray_address", f"cannot connect to Ray at {address!r}: {exc}") from None
            restore()
            interrupt.check()
        yield ray
    finally:
        if started:
            with contextlib.suppress(Exception):
                ray.shutdown()     # stops the local instance and its workers
        restore()


def ray_as_completed(fn: Callable[[Any], Any], args: Sequence[Any]) -> Iterator[tuple[int, Any]]:
    """Run ``fn(a)`` for every ``a`` in ``args`` as Ray tasks (inside :func:`ray_session`);
    yield ``(index into args, result)`` as each finishes. Closing the iterator early (an
    error, Ctrl-C) cancels the tasks still pending."""
    ray = require_ray()
    from ctrplan import interrupt

    remote = ray.remote(num_cpus=1)(fn)
    refs = [remote.remote(a) for a in args]
    index = {ref: i for i, ref in enumerate(refs)}
    pending = list(refs)
    try:
        while pending:
            done, pending = ray.wait(pending, num_returns=1, timeout=0.5)
            interrupt.check()    # a pending Ctrl-C / SIGTERM ends the wait
            for ref in done:
                yield index[ref], ray.get(ref)
    finally:
        for ref in pending:
            with contextlib.suppress(Exception):
                ray.cancel(ref, force=True)

