"""Helpers shared by the sub-commands: argument types, model resolution, output checks."""

from __future__ import annotations

import argparse
import math
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import NoReturn

from ctrplan.errors import InputError

# ---------------------------------------------------------------------------- numeric options
_INT = re.compile(r"^[+-]?[0-9]{1,18}$")
_FLOAT = re.compile(r"^[+-]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)(?:[eE][+-]?[0-9]{1,4})?$")


def excerpt(text: object, n: int = 40) -> str:
    """A bad value as quoted in an error message: at most ``n`` characters, then ``...``."""
    from ctrplan.io import excerpt as _excerpt

    return _excerpt(text, n)


def _num(x: float) -> str:
    return f"{x:g}" if isinstance(x, float) else str(x)


def _bounds_text(lo, hi, lo_open: bool, hi_open: bool) -> str:
    if lo is not None and hi is not None:
        return f"{'>' if lo_open else '>='} {_num(lo)} and {'<' if hi_open else '<='} {_num(hi)}"
    if lo is not None:
        return f"{'>' if lo_open else '>='} {_num(lo)}"
    if hi is not None:
        return f"{'<' if hi_open else '<='} {_num(hi)}"
    return "finite"


def parse_int(text: str, lo: int | None = None, hi: int | None = None) -> int:
    """Strictly parse a decimal integer option value (no ``1_0``, no ``1e3``, no ``2.0``) in
    ``[lo, hi]``; raises ValueError with a one-line message quoting at most an excerpt."""
    t = str(text).strip()
    if not _INT.match(t):
        raise ValueError(f"expected an integer, got {excerpt(text)}")
    v = int(t)
    if (lo is not None and v < lo) or (hi is not None and v > hi):
        raise ValueError(f"must be {_bounds_text(lo, hi, False, False)} (an integer), got {v}")
    return v


def parse_float(text: str, lo: float | None = None, hi: float | None = None,
                lo_open: bool = False, hi_open: bool = False) -> float:
    """Strictly parse a finite decimal number (ASCII, no ``1_0``, no ``nan``/``inf``) in the
    given range; raises ValueError with a one-line message quoting at most an excerpt."""
    t = str(text).strip()
    if not _FLOAT.match(t):
        what = "not finite" if t.lower().lstrip("+-") in ("nan", "inf", "infinity") else "expected a number"
        raise ValueError(f"{what}, got {excerpt(text)}")
    v = float(t)
    if not math.isfinite(v):
        raise ValueError(f"not finite, got {excerpt(text)}")
    if ((lo is not None and (v < lo or (lo_open and v == lo)))
            or (hi is not None and (v > hi or (hi_open and v == hi)))):
        raise ValueError(f"must be {_bounds_text(lo, hi, lo_open, hi_open)}, got {v:g}")
    return v


def int_arg(lo: int | None = None, hi: int | None = None) -> Callable[[str], int]:
    """An argparse ``type`` for an integer option in ``[lo, hi]`` (strict, see :func:`parse_int`)."""
    def conv(text: str) -> int:
        try:
            return parse_int(text, lo, hi)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    conv.__name__ = "integer"
    return conv


def float_arg(lo: float | None = None, hi: float | None = None, lo_open: bool = False,
              hi_open: bool = False) -> Callable[[str], float]:
    """An argparse ``type`` for a finite number option in a range (strict, see :func:`parse_float`)."""
    def conv(text: str) -> float:
        try:
            return parse_float(text, lo, hi, lo_open, hi_open)
        except ValueError as exc:
            raise argparse.ArgumentTypeError(str(exc)) from None
    conv.__name__ = "number"
    return conv


#: Common option types. Counts have ceilings so that a typo cannot ask for years of work;
#: requests whose cost is known up front are also refused with their estimate by the command.
SEED = int_arg(0)
WORKERS = int_arg(1, 1024)
POINTS = int_arg(2, 100_000)
POSITIVE = float_arg(0.0, lo_open=True)
NONNEGATIVE = float_arg(0.0)
FRACTION = float_arg(0.0, 1.0, lo_open=True, hi_open=True)
MAX_MB = float_arg(0.0, 2.0 ** 40, lo_open=True)

#: an option's value is quoted whole up to this many characters (then 40 and its length)
OPTION_TOKEN = 60


class OneLineParser(argparse.ArgumentParser):
    """``ArgumentParser`` whose errors are one line (``ctrplan CMD: error: ...``, exit 2, no
    usage block) and quote at most a short excerpt of an over-long value."""

    def error(self, message: str) -> NoReturn:
        from ctrplan.errors import excerpt, shorten

        print(f"{self.prog}: error: {excerpt(shorten(message, OPTION_TOKEN))} (see {self.prog} --help)",
              file=sys.stderr)
        raise SystemExit(2)


def add_max_mb_arg(p: argparse.ArgumentParser) -> None:
    """``--max-mb``: lift (or lower) the size cap of every input file."""
    p.add_argument("--max-mb", type=MAX_MB, default=None, metavar="MB",
                   help="size cap of each input file, MB (default: per kind, e.g. 2048 for "
                        "configuration CSVs, 64 for YAML/JSON); files are checked before reading")


#: Default memory budget (MB) of a command whose memory use is known up front.
MEMORY_BUDGET_MB = 2048.0


def refuse_costly(field: str, request: str, estimate: float, limit: float, unit: str,
                  lift: str) -> None:
    """Refuse, before any work, a request whose cost is known up front to exceed ``limit``:
    one line with the request, the estimate and how to lift the limit."""
    def fmt(x: float) -> str:
        return f"{x:,.0f}" if x < 1e7 else f"{x:.2e}"

    if not estimate <= limit:
        raise InputError(field, "", f"{request} needs about {fmt(estimate)} {unit}, above the "
                         f"limit of {fmt(limit)} (lift with {lift})")


def add_max_mb_everywhere(parser: argparse.ArgumentParser) -> None:
    """Give every (sub-)command that lacks it the ``--max-mb`` option."""
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        if "--max-mb" not in parser._option_string_actions:
            add_max_mb_arg(parser)
        return
    for sub in subs:
        for child in set(sub.choices.values()):
            add_max_mb_everywhere(child)


def add_robot_arg(p: argparse.ArgumentParser, required: bool = True) -> None:
    p.add_argument("--robot", required=required, default=None if required else "seed1",
                   help="shipped robot name (seed1, two_tube_nylon, two_tube_wide) or robot YAML path")


def add_model_arg(p: argparse.ArgumentParser, default: str = "physics") -> None:
    from ctrplan.commands._vocab import model_name

    p.add_argument("--model", default=default, type=model_name,
                   help="physics (torsionally compliant), rigid, learned (shipped default network) "
                        "or a model file written by 'ctrplan train'")


def add_device_arg(p: argparse.ArgumentParser) -> None:
    """``--device cpu|cuda[:N]|auto``: where a learned model's network runs."""
    p.add_argument("--device", default="cpu",
                   help="where a learned model evaluates its network (and closed-form base) for "
                        "a batch: cpu (default), cuda[:N] or auto (cuda when torch sees a GPU, "
                        "else cpu); other models ignore it")


def device_arg(text: str) -> str:
    """A ``--device`` value resolved (``auto``) and checked: the device's name, or InputError
    naming ``--device`` when torch cannot use it."""
    if text == "cpu":
        return "cpu"
    from ctrplan.shape.learned import resolve_device

    try:
        return str(resolve_device(text))
    except ValueError as exc:
        raise InputError("--device", "", str(exc)) from None


def output_path(path: str, suffixes: tuple[str, ...], field: str = "--out") -> Path:
    """Check an output path's suffix and that it can be written (its folder exists or can be
    created, and accepts files)."""
    from ctrplan.io import check_writable

    p = Path(path)
    if suffixes and p.suffix.lower() not in suffixes:
        raise InputError(field, "", f"{path!r} must end in one of {', '.join(suffixes)}")
    return check_writable(p, field)
