"""Ctrl-C stops every command within seconds, even inside compiled code.

Python turns SIGINT into KeyboardInterrupt only when the main thread runs Python bytecode; a
long numba kernel, an FCL or scipy call, or numba compiling holds the interpreter for as long
as it runs, so Ctrl-C alone could wait minutes. The command line therefore starts a tiny
watchdog process (:func:`guard`): Python's C-level signal handler writes the signal number to a
wake-up pipe at once, whatever the main thread is doing; the watchdog reads it, gives the
command ``grace`` seconds to stop by itself (KeyboardInterrupt: temporary files removed, exit
130), and otherwise removes the temporary files of atomic writes in progress
(:func:`ctrplan.io.atomic_path` sends their names as it creates them) and ends the command with SIGKILL.
Either way nothing half-written is left behind and the shell gets control back within
``grace`` + ~0.1 s.
"""

from __future__ import annotations

import contextlib
import os
import signal
import subprocess
import sys
import threading
from collections.abc import Iterator

#: Seconds a command gets to stop by itself after Ctrl-C before the watchdog ends it.
GRACE_S = 1.5

_WATCHDOG = r"""
import os, select, signal, sys, time
signal.signal(signal.SIGINT, signal.SIG_IGN)
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
        if signal.SIGINT not in data:
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
            os.write(2, b"ctrplan: interrupted (stopped after %.0f s in compiled code)\n" % grace)
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


_interrupted = False


def interrupted() -> bool:
    """True once Ctrl-C (SIGINT) reached this process inside :func:`guard`. Code interrupted
    in a library (numba compiling, say) may surface as another exception; the command line
    reports it as an interruption, not as a failure."""
    return _interrupted


def _on_sigint(signum, frame) -> None:
    global _interrupted
    _interrupted = True
    raise KeyboardInterrupt


def _quiet_unraisable(hook):
    """An unraisable-exception hook that stays silent after Ctrl-C: a KeyboardInterrupt raised
    inside a C callback (llvmlite's object cache while numba compiles, say) is reported through
    this hook with a traceback, which a user who pressed Ctrl-C must not see."""
    def quiet(unraisable) -> None:
        if _interrupted or isinstance(unraisable.exc_value, KeyboardInterrupt):
            return
        hook(unraisable)
    return quiet


def pending_added(path: str) -> None:
    if _pipe is not None:
        _pipe.send("+" + path)


def pending_removed(path: str) -> None:
    if _pipe is not None:
        _pipe.send("-" + path)


@contextlib.contextmanager
def guard(grace: float = GRACE_S) -> Iterator[None]:
    """Run the body with the Ctrl-C watchdog (main thread only; elsewhere a no-op)."""
    global _pipe
    if threading.current_thread() is not threading.main_thread() or os.name != "posix":
        yield
        return
    wake_r, wake_w = os.pipe()
    path_r, path_w = os.pipe()
    os.set_blocking(wake_w, False)
    try:
        proc = subprocess.Popen(
            [sys.executable, "-S", "-c", _WATCHDOG, str(os.getpid()), str(grace), str(path_r)],
            stdin=wake_r, pass_fds=(path_r,), stdout=subprocess.DEVNULL,
            start_new_session=True, close_fds=True,
        )
    except OSError:
        for fd in (wake_r, wake_w, path_r, path_w):
            os.close(fd)
        yield
        return
    os.close(wake_r)
    os.close(path_r)
    try:
        old = signal.set_wakeup_fd(wake_w, warn_on_full_buffer=False)
    except ValueError:
        old = None
    _pipe = _PathPipe(path_w)
    old_handler = signal.signal(signal.SIGINT, _on_sigint)
    old_hook = sys.unraisablehook
    sys.unraisablehook = _quiet_unraisable(old_hook)
    try:
        yield
    finally:
        _pipe = None
        signal.signal(signal.SIGINT, old_handler)
        sys.unraisablehook = old_hook
        if old is not None:
            signal.set_wakeup_fd(old)
        os.close(wake_w)
        os.close(path_w)
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(timeout=5)
