"""SIGINT (Ctrl-C) and SIGTERM stop every command promptly, with one line and exit 130 / 143.

How a command stops
-------------------
Inside :func:`guard` (the command line runs every command in it) SIGINT and SIGTERM get one
Python handler. The first signal is recorded (:func:`signalled`) and, unless the code is in a
:func:`deferred` region, raised as :class:`KeyboardInterrupt` at once. The exception unwinds
the command: atomic writes remove their temporary files (:func:`ctrplan.io.atomic_path`), a
process pool kills its workers (:mod:`ctrplan.planning.batch`), and :func:`ctrplan.cli.main`
prints one line and returns ``128 + signal`` (130 for SIGINT, 143 for SIGTERM). A second signal
while the command unwinds is recorded but not raised, so the clean-up itself is never cut short.

Python runs a signal handler only between bytecodes of the main thread, so compiled code must
come back to Python often: the long kernels run in chunks (the mechanics kernel on a few
thousand configurations at a time, :data:`CHUNK`) and call :func:`check` in between, so a
signal is acted on within a fraction of a second. Code that hands Python callbacks to C++ (the
OMPL planners) runs in a :func:`deferred` region: the callbacks and the planner's termination
condition poll :func:`requested` and the interruption is raised once control is back in Python
(an exception thrown through C++ frames is never relied on).

Last resort
-----------
A C call that never returns (a library hanging in native code) cannot be stopped from Python.
For that case only, :func:`guard` starts a tiny watchdog process: Python's C-level signal
handler writes the signal number to a wake-up pipe at once, whatever the main thread is doing;
if the command has not ended :data:`GRACE_S` seconds later, the watchdog removes the temporary
files of atomic writes in progress (:func:`ctrplan.io.atomic_path` sends their names as it
creates them) and ends the command with SIGKILL. The tests check that no command needs it.
"""

from __future__ import annotations

import builtins
import contextlib
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator

#: Seconds a command gets to stop by itself after a signal before the last-resort watchdog ends
#: it (no command needs it: the tests measure stops well under a second or two).
GRACE_S = 20.0

#: Rows per call of a long compiled kernel: small enough that a kernel call returns within a
#: fraction of a second (the signal is acted on in between), large enough that the Python
#: overhead per call is negligible.
CHUNK = 4096

#: The signals a command stops on, and their exit codes (128 + signal number).
SIGNALS = (signal.SIGINT, signal.SIGTERM)

_WATCHDOG = r"""
import os, select, signal, sys, time
signal.signal(signal.SIGINT, signal.SIG_IGN)
signal.signal(signal.SIGTERM, signal.SIG_IGN)
pid, grace, paths = int(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
wake = 0
pending, buf = set(), b""
def read_paths():
    global buf
    while True:
        r, _, _ = select.select([paths], [], [], 0)
        if not r:
            return True
        chunk = os.read(paths, 65536)
        if not chunk:
            return False
        buf += chunk
        *lines, buf = buf.split(b"\n")
        for line in lines:
            if line[:1] == b"+":
                pending.add(line[1:].decode())
            elif line[:1] == b"-":
                pending.discard(line[1:].decode())
while True:
    r, _, _ = select.select([wake, paths], [], [])
    if paths in r and not read_paths():
        sys.exit(0)
    if wake in r:
        data = os.read(wake, 64)
        if not data:
            sys.exit(0)
        if signal.SIGINT not in data and signal.SIGTERM not in data:
            continue
        deadline = time.monotonic() + grace
        alive = True
        while time.monotonic() < deadline:
            r, _, _ = select.select([wake, paths], [], [], max(deadline - time.monotonic(), 0))
            if paths in r and not read_paths():
                alive = False
                break
            if wake in r and not os.read(wake, 64):
                alive = False
                break
        if not alive:
            sys.exit(0)
        read_paths()
        for p in pending:
            try:
                os.unlink(p)
            except OSError:
                pass
        try:
            os.write(2, b"ctrplan: interrupted (killed after %.0f s in native code)\n" % grace)
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
        sys.exit(0)
"""



class _PathPipe:
    """Sends the temporary paths of atomic writes to the watchdog (+path / -path lines)."""

    def __init__(self, fd: int):
        self.fd = fd

    def send(self, line: str) -> None:
        with contextlib.suppress(OSError):
            os.write(self.fd, (line + "\n").encode())


_pipe: _PathPipe | None = None
_signal = 0        # the first signal received inside guard(), 0 for none
_raised = False    # whether it has been raised as KeyboardInterrupt yet
_defer = 0         # depth of deferred() regions
_active = False    # inside guard()


def signalled() -> int:
    """The first signal (SIGINT or SIGTERM) received inside :func:`guard`, or 0."""
    return _signal


def interrupted() -> bool:
    """True once SIGINT or SIGTERM reached this process inside :func:`guard`. Code interrupted
    in a library (numba compiling, say) may surface as another exception; the command line
    reports it as an interruption, not as a failure."""
    return _signal != 0


def requested() -> bool:
    """Whether the command should stop (cheap; for callbacks inside :func:`deferred` regions)."""
    return _signal != 0


def exit_code() -> int:
    """``128 + signal`` once a signal was received (130 SIGINT, 143 SIGTERM), else 0."""
    return 128 + int(_signal) if _signal else 0


def describe() -> str:
    """A few words for the one-line message: ``interrupted`` or ``terminated (SIGTERM)``."""
    return "terminated (SIGTERM)" if _signal == signal.SIGTERM else "interrupted"


def check() -> None:
    """Raise KeyboardInterrupt if a signal arrived. Long loops call it between chunks of
    compiled work; it raises again on every call, so an interruption that a library swallowed
    (a bare ``except:``) still stops the command at the next check."""
    global _raised
    if _signal:
        _raised = True
        raise KeyboardInterrupt


@contextlib.contextmanager
def deferred() -> Iterator[None]:
    """A region where a signal is only recorded, never raised (code that runs Python callbacks
    from C++); the caller's callbacks poll :func:`requested`. Leaving the region raises a
    pending interruption."""
    global _defer
    _defer += 1
    try:
        yield
    finally:
        _defer -= 1
    check()


def _checked_import(*args, **kwargs):
    """``__import__`` that stops after an import a signal came during: some libraries import
    their optional parts inside ``except BaseException`` (trimesh does), which swallows the
    KeyboardInterrupt; the check when the import returns raises it again."""
    module = _import(*args, **kwargs)
    if _signal and _defer == 0 and threading.current_thread() is threading.main_thread():
        check()      # only the main thread stops the command (a pool's feeder thread imports too)
    return module


_import = builtins.__import__


def _on_signal(signum, frame) -> None:
    global _signal, _raised
    if _signal:
        return          # already stopping: a second signal does not cut the clean-up short
    _signal = signum
    if _defer == 0:
        _raised = True
        raise KeyboardInterrupt


def _quiet_unraisable(hook):
    """An unraisable-exception hook that stays silent after a signal: a KeyboardInterrupt
    raised inside a C callback (llvmlite's object cache while numba compiles, say) is reported
    through this hook with a traceback, which a user who pressed Ctrl-C must not see."""
    def quiet(unraisable) -> None:
        if _signal or isinstance(unraisable.exc_value, KeyboardInterrupt):
            return
        hook(unraisable)
    return quiet


def pending_added(path: str) -> None:
    """Tell the last-resort watchdog about a temporary file being written."""
    if _pipe is not None:
        _pipe.send("+" + path)


def pending_removed(path: str) -> None:
    """Tell the last-resort watchdog that a temporary file is gone (renamed or removed)."""
    if _pipe is not None:
        _pipe.send("-" + path)


def ignore_in_child() -> None:
    """For worker processes: ignore SIGINT (a terminal's Ctrl-C reaches the whole process
    group; the parent stops its workers itself), restore SIGTERM's default, and die with the
    parent (Linux ``PR_SET_PDEATHSIG``) so that no worker outlives a parent killed with SIGKILL."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    # a worker starts with SIGINT blocked (worker_context): a Ctrl-C pending since then was
    # discarded by ignoring it above; unblock so that the worker's own children start plainly
    if os.name == "posix":
        signal.pthread_sigmask(signal.SIG_UNBLOCK, {signal.SIGINT})
    # tqdm guards its bars with a multiprocessing RLock, a named semaphore registered with the
    # parent's resource tracker; a worker killed mid-job never unregisters it, and the tracker
    # then prints "leaked semaphore objects" after the command's last line. A worker's bars (all
    # disabled) need only a thread lock.
    with contextlib.suppress(ImportError):
        from tqdm import tqdm

        tqdm.set_lock(threading.RLock())
    if sys.platform.startswith("linux"):
        import ctypes

        parent = os.getppid()
        with contextlib.suppress(OSError, AttributeError):
            libc = ctypes.CDLL(None, use_errno=True)
            libc.prctl(1, int(signal.SIGKILL), 0, 0, 0)   # PR_SET_PDEATHSIG
        if os.getppid() != parent:     # the parent died before prctl took effect
            os._exit(1)


def descendants(pid: int | None = None) -> list[int]:
    """Process ids of every live descendant of ``pid`` (default: this process), from /proc
    (Linux; elsewhere an empty list)."""
    root = os.getpid() if pid is None else int(pid)
    children: dict[int, list[int]] = {}
    try:
        entries = os.listdir("/proc")
    except OSError:
        return []
    for d in entries:
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat", "rb") as fh:
                stat = fh.read().decode(errors="replace")
        except OSError:
            continue
        fields = stat[stat.rindex(")") + 2:].split()
        if fields[0] in ("Z", "X"):
            continue
        children.setdefault(int(fields[1]), []).append(int(d))
    out, todo = [], [root]
    while todo:
        for c in children.get(todo.pop(), []):
            out.append(c)
            todo.append(c)
    return out


def kill_descendants() -> None:
    """SIGKILL every process this one started, directly or not, that is still running (the
    processes a Ray instance starts, say, when an interruption cut its start short). The
    multiprocessing resource tracker is spared: it still has semaphores to unregister, and it
    ends by itself when this process exits."""
    keep = set()
    tracker = sys.modules.get("multiprocessing.resource_tracker")
    if tracker is not None:
        keep.add(getattr(getattr(tracker, "_resource_tracker", None), "_pid", None))
    for pid in descendants():
        if pid in keep:
            continue
        with contextlib.suppress(OSError):
            os.kill(pid, signal.SIGKILL)


def _stop_workers(procs: list, shutdown) -> None:
    """Kill the worker processes ``procs``, run the pool's ``shutdown()`` in a daemon thread
    waited for a few seconds at most (it takes locks a killed worker, or an interruption in the
    pool's own code, may have left held), and reap the workers."""
    for proc in procs:
        with contextlib.suppress(Exception):
            proc.kill()
    t = threading.Thread(target=shutdown, daemon=True)
    t.start()
    t.join(5)
    for proc in procs:
        with contextlib.suppress(Exception):
            proc.join(5)


def stop_executor(ex) -> None:
    """Stop a ``concurrent.futures.ProcessPoolExecutor`` now: kill its workers (a task in
    progress is not waited for), cancel what is queued, and reap them. (Its shutdown takes the
    executor's lock, which an interruption inside submit() may have left in an odd state.)"""
    procs = list((getattr(ex, "_processes", None) or {}).values())   # no public way to do this
    _stop_workers(procs, lambda: ex.shutdown(wait=False, cancel_futures=True))


def stop_pool(pool) -> None:
    """Stop a ``multiprocessing.Pool`` now: kill its workers (a job in progress is not waited
    for) and reap them. ``Pool.terminate`` first takes the task queue's read lock, which an idle
    worker holds while it waits for a task: a worker killed there (SIGTERM to the process group
    kills the workers too) never releases it, and terminate, then join, would wait for ever
    (the watchdog then killed the command: exit 137 instead of 143)."""
    _stop_workers(list(getattr(pool, "_pool", None) or []), pool.terminate)   # no public way


@contextlib.contextmanager
def spawning() -> Iterator[None]:
    """Create a worker pool or submit to one (which may start workers) in the body: a signal
    that comes meanwhile is recorded and raised when the body ends, never inside the library's
    process bookkeeping (a pool half-built by an exception would lose track of a started
    worker). Pools must use :func:`worker_context`, whose workers start with SIGINT blocked."""
    with deferred():
        yield


def _start_blocked(start, tracker: bool) -> None:
    """Run ``Process.start`` with SIGINT blocked in this thread. The signal mask is inherited
    through fork and ``exec``, so the worker's interpreter starts with SIGINT blocked: a
    terminal's Ctrl-C (sent to the whole process group) stays pending in it, and its
    initializer (:func:`ignore_in_child`) discards it by ignoring SIGINT. Here the signal is
    not lost: it is delivered when the mask is restored, or meanwhile to another thread
    (Python's handler then runs in the main thread as usual). Ignoring SIGINT instead would
    lose a Ctrl-C that comes while a worker starts (an ignored signal is discarded)."""
    if os.name != "posix":
        start()
        return
    if tracker:
        # the resource tracker unblocks SIGINT (in this thread) after it first starts: start it
        # before blocking, or a spawned worker would inherit an unblocked mask
        from multiprocessing import resource_tracker

        resource_tracker.ensure_running()
    old = signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT})
    try:
        start()
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, old)


if os.name == "posix":
    from multiprocessing import context as _mpc

    class _SpawnProcess(_mpc.SpawnProcess):
        """A spawned worker that starts with SIGINT blocked (:func:`_start_blocked`)."""

        def start(self) -> None:
            _start_blocked(super().start, tracker=True)

    class _ForkProcess(_mpc.ForkProcess):
        """A forked worker that starts with SIGINT blocked (:func:`_start_blocked`)."""

        def start(self) -> None:
            _start_blocked(super().start, tracker=False)

    class _SpawnContext(_mpc.SpawnContext):
        Process = _SpawnProcess

    class _ForkContext(_mpc.ForkContext):
        Process = _ForkProcess


def worker_context(method: str = "spawn"):
    """A ``multiprocessing`` context (``"spawn"`` or ``"fork"``) for worker pools whose workers
    cannot be hit by a Ctrl-C before their initializer calls :func:`ignore_in_child`, and
    whose start never drops a Ctrl-C meant for this process (:func:`_start_blocked`). Use it as
    ``ctx.Pool(...)`` or ``ProcessPoolExecutor(mp_context=ctx)``, and create the pool or submit
    to it inside :func:`spawning`."""
    import multiprocessing as mp

    if os.name != "posix":
        return mp.get_context(method)
    if method == "spawn":
        return _SpawnContext()
    if method == "fork":
        return _ForkContext()
    raise ValueError(f"worker_context: unknown start method {method!r}")


def reset() -> None:
    """Forget a recorded signal (tests that run several commands in one process)."""
    global _signal, _raised
    _signal, _raised = 0, False


@contextlib.contextmanager
def guard(grace: float = GRACE_S) -> Iterator[None]:
    """Run the body with the SIGINT/SIGTERM handler and the last-resort watchdog (main thread
    only; elsewhere a no-op)."""
    global _pipe, _active
    if threading.current_thread() is not threading.main_thread() or os.name != "posix":
        yield
        return
    wake_r, wake_w = os.pipe()
    path_r, path_w = os.pipe()
    os.set_blocking(wake_w, False)
    try:
        proc = subprocess.Popen(     # its own session: a terminal's Ctrl-C does not reach it
            [sys.executable, "-S", "-c", _WATCHDOG, str(os.getpid()), str(grace), str(path_r)],
            stdin=wake_r, pass_fds=(path_r,), stdout=subprocess.DEVNULL,
            start_new_session=True, close_fds=True,
        )
    except OSError:
        for fd in (wake_r, wake_w, path_r, path_w):
            os.close(fd)
        proc = None
        wake_w = path_w = -1
    else:
        os.close(wake_r)
        os.close(path_r)
    old = None
    if wake_w >= 0:
        try:
            old = signal.set_wakeup_fd(wake_w, warn_on_full_buffer=False)
        except ValueError:
            old = None
        _pipe = _PathPipe(path_w)
    old_handlers = {s: signal.signal(s, _on_signal) for s in SIGNALS}
    old_hook = sys.unraisablehook
    sys.unraisablehook = _quiet_unraisable(old_hook)
    old_import = builtins.__import__
    builtins.__import__ = _checked_import
    _active = True
    try:
        check()      # a signal that came before (recorded by record_signals) stops it here
        yield
    finally:
        _active = False
        _pipe = None
        for s, h in old_handlers.items():
            signal.signal(s, h)
        builtins.__import__ = old_import
        sys.unraisablehook = old_hook
        if old is not None:
            signal.set_wakeup_fd(old)
        for fd in (wake_w, path_w):
            if fd >= 0:
                os.close(fd)
        if proc is not None:
            with contextlib.suppress(subprocess.TimeoutExpired):
                proc.wait(timeout=5)


def _record_only(signum, frame) -> None:
    global _signal
    if not _signal:
        _signal = signum


def record_signals() -> dict:
    """Outside :func:`guard` (before and after the command proper), record SIGINT and SIGTERM
    instead of raising: the command line starts and ends without a traceback whenever the
    signal comes, and still exits 130 / 143. Returns the previous handlers (main thread only;
    elsewhere nothing changes)."""
    if threading.current_thread() is not threading.main_thread():
        return {}
    return {s: signal.signal(s, _record_only) for s in SIGNALS}


def restore_signals(old: dict) -> None:
    """Put back handlers returned by :func:`record_signals`."""
    for s, h in old.items():
        signal.signal(s, h)
