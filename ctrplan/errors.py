"""Error types shared by every stage.

Bad user input raises :class:`InputError`, which always names the file (or "<argument>")
and the field that is wrong. The command line turns it into a one-line message and exit code 2.
"""

from __future__ import annotations

import re

#: Longest run of non-blank characters an error message quotes whole (file paths fit); longer
#: runs (a 100,000-character bad value) are cut to their first 40 characters and their length.
MAX_TOKEN = 400
_LONG = re.compile(r"\S{" + str(MAX_TOKEN + 1) + ",}")


def shorten(text: str) -> str:
    """``text`` on one line with every over-long run of non-blank characters cut to an excerpt."""
    return " ".join(_LONG.sub(lambda m: f"{m.group(0)[:40]}... ({len(m.group(0))} characters)",
                              str(text)).split())


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
        self.source = str(source)
        self.field = shorten(field)
        self.message = shorten(message)
        where = self.source if not self.field else f"{self.source}: {self.field}"
        super().__init__(f"{where}: {self.message}")
