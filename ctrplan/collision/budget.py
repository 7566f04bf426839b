"""The work a scene's meshes need, estimated before anything is read.

Memory and time grow with the triangle count: reading and closing the meshes
(:mod:`ctrplan.collision.closure`), the exact-geometry index, and the distance fields (whose
grids are capped at ``FieldConfig.max_nodes``). The constants are measured
(``benchmarks/bench_large_mesh.py``: peak resident memory and wall time of ``ctrplan check``
on closed walls of 0.3 to 5 million triangles, one core) with a margin on top. A scene whose
estimate exceeds the memory budget (``--max-mb``, default 2048 MB; in Python
``ctrplan.io.set_max_input_mb``) is refused before any mesh is read, with the estimate and the
way to lift it; a large one gets a one-line notice with the estimate.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")

#: Peak memory (MB) of a check whatever the meshes (libraries, distance-field grids; measured
#: 560-610 MB for 0.3-2.5 million triangles).
BASE_MB = 600.0
#: Peak memory per million triangles (MB) on top of BASE_MB (measured about 55; 100 leaves room).
MB_PER_MTRI = 100.0
#: Wall time per million triangles (s, one core) to read, close, index and build the fields
#: (measured 7-11 on a busy 2-core machine).
S_PER_MTRI = 12.0
#: Meshes above this many triangles (all together) get a notice with the estimate.
NOTICE_TRIANGLES = 500_000


def estimate(triangles: int) -> tuple[float, float]:
    """(peak memory MB, seconds) to prepare meshes of ``triangles`` triangles in all."""
    mtri = triangles / 1e6
    return BASE_MB + MB_PER_MTRI * mtri, 5.0 + S_PER_MTRI * mtri


def memory_budget_mb() -> float:
    """The memory budget (MB): ``--max-mb`` when given, else 2048."""
    from ctrplan import io

    return io._override_mb if io._override_mb is not None else 2048.0


def check_scene_budget(files: list[tuple[Path, str]], src: str) -> None:
    """Refuse (InputError naming ``src``) meshes whose estimate exceeds the budget; log the
    estimate of large ones. ``files``: (mesh path, role)."""
    from ctrplan.collision.meshio import mesh_triangles

    total = 0
    for path, _ in files:
        try:
            found = Path(path).is_file()
        except OSError:
            found = False
        if found and os.access(path, os.R_OK):
            try:
                total += mesh_triangles(path)
            except OSError:     # the reader reports it
                pass
    if total == 0:
        return
    mb, secs = estimate(total)
    budget = memory_budget_mb()
    if mb > budget:
        raise InputError(src, "meshes", f"{total:,} triangles need about {mb:,.0f} MB of memory "
                         f"(and {secs:,.0f} s) to prepare, above the budget of {budget:,.0f} MB "
                         "(lift with --max-mb)")
    if total >= NOTICE_TRIANGLES:
        log.info("%s: %s triangles: preparing them takes about %.0f MB and %.0f s", src,
                 f"{total:,}", mb, secs)
