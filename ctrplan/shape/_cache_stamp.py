"""The numba cache stamp of the mechanics kernels.

numba caches a compiled kernel with every kernel it calls compiled in, and reuses the cache while
the source file of the cached function itself is unchanged: an edit of a callee in another module
would leave its callers' caches stale (they would run the old callee). So every kernel module
(:data:`KERNEL_MODULES`) ends with the line ``# numba cache stamp: <digest>``, the digest of all
kernel modules' sources with that line left out. After editing a kernel module, run::

    python -m ctrplan.shape._cache_stamp

which rewrites the stamp in every kernel module: each file's text changes, so numba recompiles
every kernel on its next call. ``tests/test_kernel_cache.py`` fails while a stamp is out of date
(and checks that every cached numba module that calls into a kernel module is one of them).
"""

from __future__ import annotations

import hashlib
import sys
from pathlib import Path

#: the numba modules whose kernels call each other (all in this folder)
KERNEL_MODULES = ("_ode", "_kernel", "_loaded", "_shooting", "_continuation")
PREFIX = "# numba cache stamp: "
HERE = Path(__file__).resolve().parent


def _body(text: str) -> str:
    """The source without its stamp line and trailing blank lines."""
    lines = text.splitlines(keepends=True)
    return "".join(line for line in lines if not line.startswith(PREFIX)).rstrip("\n")


def _stamp(text: str) -> str | None:
    for line in text.splitlines():
        if line.startswith(PREFIX):
            return line[len(PREFIX):].strip()
    return None


def digest(folder: Path = HERE) -> str:
    """sha256 of the kernel modules' sources (names and text, stamp lines left out)."""
    h = hashlib.sha256()
    for name in KERNEL_MODULES:
        h.update(name.encode() + b"\0")
        h.update(_body((folder / f"{name}.py").read_text(encoding="utf-8")).encode() + b"\0")
    return h.hexdigest()


def stale(folder: Path = HERE) -> list[str]:
    """The kernel modules whose stamp is missing or not :func:`digest`."""
    d = digest(folder)
    return [name for name in KERNEL_MODULES
            if _stamp((folder / f"{name}.py").read_text(encoding="utf-8")) != d]


def rewrite(folder: Path = HERE) -> list[str]:
    """Write the current digest into every stale kernel module (the stamp line at the end).
    Returns the modules rewritten."""
    d = digest(folder)
    out = []
    for name in stale(folder):
        path = folder / f"{name}.py"
        body = _body(path.read_text(encoding="utf-8"))
        path.write_text(f"{body}\n\n{PREFIX}{d}\n", encoding="utf-8")
        out.append(name)
    return out


if __name__ == "__main__":
    done = rewrite()
    sys.stdout.write(f"numba cache stamp {digest()[:12]}: rewrote {', '.join(done) or 'nothing'}\n")
