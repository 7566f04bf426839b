"""Error types shared by every stage.

Bad user input raises :class:`InputError`, which always names the file (or "<argument>")
and the field that is wrong. The command line turns it into a one-line message and exit code 2.
"""

from __future__ import annotations

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
        self.source = excerpt(str(source).replace("\r", "\\r").replace("\n", "\\n"), 200)
        self.field = excerpt(" ".join(str(field).split()), 120)
        self.message = excerpt(" ".join(str(message).split()))
        where = self.source if not self.field else f"{self.source}: {self.field}"
        super().__init__(f"{where}: {self.message}")
