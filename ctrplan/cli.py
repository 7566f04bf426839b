"""The ``ctrplan`` command line.

Each sub-command lives in :mod:`ctrplan.commands` as a module with ``register(subparsers)``,
which adds its parser and sets ``func(args) -> int``. Bad input raises
:class:`~ctrplan.errors.InputError`; here it becomes one line on stderr and exit code 2.
"""

from __future__ import annotations

import argparse
import importlib
import importlib.util
import logging
import sys

from ctrplan import __version__
from ctrplan.errors import InputError

#: Sub-command modules in ``ctrplan.commands``, in the order shown by ``--help``.
COMMANDS = (
    "shape", "simulate", "train", "check", "scene", "plan", "plan_batch", "view",
    "diagnose", "design", "demo", "bench",
)

log = logging.getLogger("ctrplan")


class _Parser(argparse.ArgumentParser):
    """argparse's parser whose error line quotes a bad value as a short excerpt, never whole
    (sub-command parsers are of the same class)."""

    def error(self, message: str):  # type: ignore[override]
        from ctrplan.errors import excerpt

        super().error(excerpt(" ".join(message.split())))


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(
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
    return parser


def configure_logging(verbose: bool = False, quiet: bool = False) -> None:
    level = logging.DEBUG if verbose else logging.WARNING if quiet else logging.INFO
    logging.basicConfig(level=level, format="%(message)s", stream=sys.stderr, force=True)
    from ctrplan import progress

    progress.set_enabled(not quiet)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    configure_logging(args.verbose, args.quiet)
    from ctrplan import interrupt

    try:
        with interrupt.guard():
            check_common_args(args)
            return int(args.func(args) or 0)
    except InputError as exc:
        print(f"ctrplan {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except (MemoryError, RecursionError) as exc:
        print(f"ctrplan {args.command}: error: the input is too large or too deeply nested "
              f"({exc.__class__.__name__})", file=sys.stderr)
        return 2
    except OSError as exc:
        # an output that cannot be written (disk full, permissions changed mid-run, ...)
        where = f"{exc.filename}: " if getattr(exc, "filename", None) else ""
        print(f"ctrplan {args.command}: error: {where}{exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"ctrplan {args.command}: interrupted", file=sys.stderr)
        return 130
    except Exception:
        # Ctrl-C inside a library (numba compiling, say) can surface as another exception
        if interrupt.interrupted():
            print(f"ctrplan {args.command}: interrupted", file=sys.stderr)
            return 130
        raise


def check_common_args(args: argparse.Namespace) -> None:
    """Checks every command shares, before any work: ``--seed`` >= 0 (numpy's generators take
    no negative seeds); ``--out`` writable (a file when it has a suffix, else a folder)."""
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
