"""Progress bars that stay quiet when output is not a terminal (or with ``--quiet``)."""

from __future__ import annotations

import sys
from collections.abc import Iterable
from typing import Any

from tqdm.auto import tqdm

_enabled = True


def set_enabled(flag: bool) -> None:
    """Globally enable or disable progress bars (``ctrplan --quiet`` disables them)."""
    global _enabled
    _enabled = bool(flag)


def bar(iterable: Iterable[Any] | None = None, total: int | None = None, desc: str = "", **kw: Any) -> tqdm:
    """A tqdm bar on stderr, disabled when stderr is not a TTY or progress is off."""
    off = bool(kw.pop("disable", False))
    disable = off or (not _enabled) or not sys.stderr.isatty()
    return tqdm(iterable, total=total, desc=desc, disable=disable, file=sys.stderr, leave=False, **kw)
