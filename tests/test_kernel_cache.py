"""The numba cache stamp of the mechanics kernels (:mod:`ctrplan.shape._cache_stamp`).

numba reuses a cached kernel while the source file of the cached function is unchanged, though
the kernels it calls (compiled into the cache) live in other files. Every kernel module carries a
digest of all of them; these tests fail while a stamp is out of date, check that an edit of one
kernel module changes the text of every one of them once restamped (so that numba recompiles
every caller), and that no cached numba module outside the list calls into a kernel module.
"""

from __future__ import annotations

import ast
import shutil
from pathlib import Path

from ctrplan.shape import _cache_stamp as cs

ROOT = Path(cs.__file__).resolve().parents[1]


def test_kernel_cache_stamps_are_current():
    assert cs.stale() == [], "a kernel module changed: run python -m ctrplan.shape._cache_stamp"


def test_an_edit_of_one_kernel_restamps_every_kernel(tmp_path):
    for name in cs.KERNEL_MODULES:
        shutil.copy(cs.HERE / f"{name}.py", tmp_path)
    assert cs.stale(tmp_path) == []
    before = {n: (tmp_path / f"{n}.py").read_text() for n in cs.KERNEL_MODULES}
    with open(tmp_path / "_kernel.py", "a", encoding="utf-8") as f:
        f.write("# an edit of one kernel module\n")
    assert cs.stale(tmp_path) == list(cs.KERNEL_MODULES)
    assert cs.rewrite(tmp_path) == list(cs.KERNEL_MODULES)
    assert cs.stale(tmp_path) == []
    for n in cs.KERNEL_MODULES:
        text = (tmp_path / f"{n}.py").read_text()
        assert text != before[n], n
        assert text.rstrip("\n").splitlines()[-1] == cs.PREFIX + cs.digest(tmp_path)


def _imports(path: Path) -> set[str]:
    out: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.ImportFrom) and node.module:
            out.add(node.module)
            out.update(f"{node.module}.{a.name}" for a in node.names)
        elif isinstance(node, ast.Import):
            out.update(a.name for a in node.names)
    return out


def test_every_cached_module_calling_a_kernel_module_is_stamped():
    kernels = {f"ctrplan.shape.{n}" for n in cs.KERNEL_MODULES}
    cached = [f for f in ROOT.rglob("*.py") if "cache=True" in f.read_text(encoding="utf-8")]
    assert len(cached) >= len(cs.KERNEL_MODULES)
    for f in cached:
        if _imports(f) & kernels:
            assert f.parent == cs.HERE and f.stem in cs.KERNEL_MODULES, f
    for n in cs.KERNEL_MODULES:
        assert cs.HERE / f"{n}.py" in cached
