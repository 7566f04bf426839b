"""Error types shared by every stage.

Bad user input raises :class:`InputError`, which always names the file (or the argument) and
the field that is wrong; a bad value of a Python argument raises its subclass
:class:`ArgumentError`, named as the Python caller wrote it. The command line turns either into
a one-line message (with its own flag names) and exit code 2.
"""

from __future__ import annotations

import re

#: Longest run of non-blank characters an error message quotes whole (file paths fit); longer
#: runs (a 100,000-character bad value) are cut to their first 40 characters and their length.
MAX_TOKEN = 400
_LONG = re.compile(r"\S{" + str(MAX_TOKEN + 1) + ",}")


def shorten(text: str, max_token: int = MAX_TOKEN) -> str:
    """``text`` on one line with every run of non-blank characters longer than ``max_token``
    cut to its first 40 characters and its length."""
    long = _LONG if max_token == MAX_TOKEN else re.compile(r"\S{" + str(max_token + 1) + ",}")
    return " ".join(long.sub(lambda m: f"{m.group(0)[:40]}... ({len(m.group(0))} characters)",
                             str(text)).split())


#: longest message kept whole; longer ones (a bad value quoted whole) keep their start and end
MAX_MESSAGE = 300


def excerpt(text: str, limit: int = MAX_MESSAGE) -> str:
    """``text`` cut to at most ``limit`` characters, the middle replaced by `` ... ``."""
    if len(text) <= limit:
        return text
    head = limit * 3 // 4
    tail = limit - head - 5
    return f"{text[:head]} ... {text[-tail:]}"


class CtrplanError(Exception):
    """Base class for errors raised by ctrplan."""


class InputError(CtrplanError, ValueError):
    """Malformed or invalid user input (a file, a field, an argument).

    Parameters
    ----------
    source : str
        The file path (or a label such as ``"--target"``) that holds the bad value.
    field : str
        The field, column or key that is wrong (``""`` if the whole file is bad).
    message : str
        What is wrong, in one line.
    """

    def __init__(self, source: str, field: str, message: str):
        self.source = excerpt(str(source).replace("\r", "\\r").replace("\n", "\\n"), MAX_TOKEN)
        self.field = excerpt(shorten(field), 120)
        self.message = excerpt(shorten(message))
        where = self.source if not self.field else f"{self.source}: {self.field}"
        super().__init__(f"{where}: {self.message}")


class ArgumentError(InputError):
    """A bad value of a Python argument: the library's errors name the argument as the caller
    wrote it (``time_limit``, ``seed``, ``tolerance_mm``, ``start``, ...), never a command-line
    flag. Other arguments the message names are written between backticks (`` `branch` ``).

    The command line shows the same error with its own names (``--time``, ``--branch``):
    :func:`ctrplan.commands._names.for_command_line` maps ``argument`` and every backticked
    name through the table of names (docs/conventions.md, "Names").

    Parameters
    ----------
    argument : str
        The argument (or config field) whose value is bad.
    message : str
        What is wrong, in one line.
    """

    def __init__(self, argument: str, message: str):
        self.argument = str(argument)
        super().__init__(self.argument, "", message)
