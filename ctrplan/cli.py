"""The ``ctrplan`` command line.

Each sub-command lives in :mod:`ctrplan.commands` as a module with ``register(subparsers)``,
which adds its parser and sets ``func(args) -> int``. Bad input raises
:class:`~ctrplan.errors.InputError`; here it becomes one line on stderr and exit code 2 (an
error about a Python argument named with its flag: :mod:`ctrplan.commands._names`).
SIGINT / SIGTERM end any command with one line on stderr and exit 130 / 143
(:mod:`ctrplan.interrupt`).
"""

from __future__ import annotations

from ctrplan import interrupt

if __name__ == "__main__":
    interrupt.record_signals()   # from the first moment: a signal is recorded, never a traceback

import argparse  # noqa: E402
import importlib  # noqa: E402
import importlib.util  # noqa: E402
import logging  # noqa: E402
import sys  # noqa: E402

from ctrplan import __version__  # noqa: E402
from ctrplan.errors import InputError  # noqa: E402

#: Sub-command modules in ``ctrplan.commands``, in the order shown by ``--help``.
COMMANDS = (
    "shape", "simulate", "train", "check", "scene", "plan", "plan_batch", "view",
    "diagnose", "design", "demo", "bench",
)

log = logging.getLogger("ctrplan")


def build_parser() -> argparse.ArgumentParser:
    from ctrplan.commands._common import OneLineParser, add_max_mb_everywhere

    parser = OneLineParser(
        prog="ctrplan",
        description="Motion planning for concentric tube robots inside anatomy.",
    )
    parser.add_argument("--version", action="version", version=f"ctrplan {__version__}")
    verbosity = parser.add_mutually_exclusive_group()
    verbosity.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    verbosity.add_argument("-q", "--quiet", action="store_true", help="warnings and errors only, no progress bars")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in COMMANDS:
        modname = f"ctrplan.commands.{name}"
        if importlib.util.find_spec(modname) is None:
            continue
        importlib.import_module(modname).register(sub)
    add_max_mb_everywhere(parser)
    return parser


def configure_logging(verbose: bool = False, quiet: bool = False) -> None:
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    logging.basicConfig(level=level, format="%(message)s", stream=sys.stderr, force=True)
    from ctrplan import progress

    progress.set_enabled(not quiet)


def main(argv: list[str] | None = None) -> int:
    """Run the command line. ``argv`` None: the process's own arguments (the ``ctrplan``
    command): SIGINT / SIGTERM stay recorded, never raised, until the process ends, and the
    process ends here (:func:`_finish`); a list: an in-process call, which returns the exit code
    and restores the signal handlers."""
    old = interrupt.record_signals()
    try:
        code = _main(argv)
    finally:
        if argv is not None:
            interrupt.restore_signals(old)
    code = _exit_code(code)
    if argv is not None:
        interrupt.reset()
    # A KeyboardInterrupt that escaped a string exec() (dataclasses build methods that way
    # while a module is imported) leaves CPython's "unhandled KeyboardInterrupt" flag set, and
    # the interpreter would then end itself with SIGINT (status -2) instead of exiting with
    # ``code``. Each string exec() resets that flag first; this one is the last.
    exec("pass", {})
    if argv is None:
        _finish(code)
    return code


def _finish(code: int) -> None:
    """End the process with ``code``: the exit handlers run here, while SIGINT / SIGTERM are
    still only recorded, then ``os._exit``. (Interpreter finalisation puts the default signal
    handlers back, and a signal arriving then would end the process with -2 / -15 instead.)"""
    import atexit
    import os

    try:
        if interrupt.signalled():
            # after a signal no exit handler may keep the process alive: 5 s at most
            import threading

            t = threading.Thread(target=atexit._run_exitfuncs, daemon=True)
            t.start()
            t.join(5)
        else:
            atexit._run_exitfuncs()
    finally:
        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        if interrupt.signalled() and code not in (130, 143):
            code = interrupt.exit_code()
        os._exit(code)


def _exit_code(code: int) -> int:
    if interrupt.signalled() and code != interrupt.exit_code():
        # the signal came after the command finished its work (its outputs are complete) or
        # while it was already ending: still report it the way a shell expects
        if code not in (130, 143):
            print(f"ctrplan: {interrupt.describe()}", file=sys.stderr)
        code = interrupt.exit_code()
    return code


def _main(argv: list[str] | None = None) -> int:
    try:
        parser = build_parser()
        try:
            args = parser.parse_args(argv)
        except SystemExit as exc:  # --help, --version, or a bad option (one line, see OneLineParser)
            return exc.code if isinstance(exc.code, int) else 0 if exc.code is None else 2
    except KeyboardInterrupt:
        return _stopped("")
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    configure_logging(args.verbose, args.quiet)
    try:
        try:
            with interrupt.guard():
                check_common_args(args)
                code = int(args.func(args) or 0)
        finally:
            _stop_children()
        return code
    except KeyboardInterrupt:
        return _stopped(args.command)
    except InputError as exc:
        if interrupt.signalled():
            return _stopped(args.command)
        from ctrplan.commands._names import for_command_line  # the library's names -> flags

        print(f"ctrplan {args.command}: error: {for_command_line(exc)}", file=sys.stderr)
        return 2
    except (MemoryError, RecursionError) as exc:
        print(f"ctrplan {args.command}: error: the input is too large or too deeply nested "
              f"({exc.__class__.__name__})", file=sys.stderr)
        return 2
    except OSError as exc:
        if interrupt.signalled():
            return _stopped(args.command)
        # an output that cannot be written (disk full, permissions changed mid-run, ...)
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"ctrplan {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except Exception:
        # a signal inside a library (numba compiling, say) can surface as another exception
        if interrupt.signalled():
            return _stopped(args.command)
        raise


def _stopped(command: str) -> int:
    """One line on stderr; the exit code of the signal (130 SIGINT, 143 SIGTERM)."""
    name = f"ctrplan {command}" if command else "ctrplan"
    print(f"{name}: {interrupt.describe()}", file=sys.stderr)
    return interrupt.exit_code() or 130


def _stop_children() -> None:
    """End the child processes a command may have started and not reaped (the mechanics
    kernel's background compile, say): none outlives the command."""
    import multiprocessing

    for child in multiprocessing.active_children():
        child.kill()
        child.join(timeout=5)
    physics = sys.modules.get("ctrplan.shape.physics")     # demo's background numba compile
    warmup = getattr(physics, "_warmup", None)
    if warmup is not None and warmup.poll() is None:
        warmup.kill()
        warmup.wait(timeout=5)
    if interrupt.signalled():
        interrupt.kill_descendants()    # anything else a library started and left (Ray)


def check_common_args(args: argparse.Namespace) -> None:
    """Checks every command shares, before any work: ``--max-mb`` (the input size cap) set;
    ``--seed`` >= 0 (numpy's generators take
    no negative seeds); ``--out`` writable (a file when it has a suffix, else a folder)."""
    from ctrplan.io import set_max_input_mb

    set_max_input_mb(getattr(args, "max_mb", None))
    seed = getattr(args, "seed", None)
    if isinstance(seed, int) and seed < 0:
        raise InputError("--seed", "", f"must be >= 0, got {seed}")
    out = getattr(args, "out", None)
    if not out:
        return
    from pathlib import Path

    from ctrplan.io import check_writable

    p = Path(out)
    check_writable(p, "--out", folder=p.is_dir() or not p.suffix)


if __name__ == "__main__":
    sys.exit(main())
