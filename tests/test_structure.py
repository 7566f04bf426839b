"""What planning needs is owned, not cached by the process; the layers depend one way (issue 37).

Read from the source with ``ast`` (nothing is imported):

- no process-wide cache in ``ctrplan/``: no module-level container that a function fills (a
  subscript store, a mutating method, ``global`` rebinding), no cache-type container at module
  level (``WeakKeyDictionary``, ``OrderedDict``, ``Bounded``, ...), no ``functools.cache`` /
  ``lru_cache`` on a module-level function. Module-level tables that no function changes are
  constants. :data:`PROCESS_STATE` is the short list of what a process really has once (each
  with the reason); a cache belongs to the object it is derived from (:mod:`ctrplan.objcache`)
  or to whoever plans (:class:`ctrplan.planning.planner.Planner`, ``Planners``);
- no ``getattr`` / ``hasattr`` probe of a model in ``ctrplan/planning/``: what planning needs
  from a model is the typed :class:`~ctrplan.shape.planning_model.PlanningModel`;
- shape imports neither collision nor planning; collision does not import planning; planning
  imports neither design nor the command line (at any depth, function-level imports included);
- ``ctrplan/planning/plan.py`` is at most 650 lines.

Each scanner is run on a small synthetic package with known violations first, so none can pass
by finding nothing.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1] / "ctrplan"

#: Module-level state that is the process's by nature, with the reason (module, name).
PROCESS_STATE = {
    ("ctrplan.interrupt", "_raised"): "whether a signal was turned into an exception (per process)",
    ("ctrplan.interrupt", "_defer"): "signals deferred while C++ runs Python callbacks (per process)",
    ("ctrplan.interrupt", "_signal"): "the signal received (per process)",
    ("ctrplan.interrupt", "_pipe"): "the self-pipe of the signal handler (per process)",
    ("ctrplan.interrupt", "_active"): "whether the handlers are installed (per process)",
    ("ctrplan.progress", "_enabled"): "progress bars on or off: the command line's -q (a setting)",
    ("ctrplan.io", "_override_mb"): "the input size cap: the command line's --max-mb (a setting)",
    ("ctrplan.shape.physics", "_warmup"): "the background compile helper process (demo), reaped once",
    ("ctrplan.shape.dataset", "_WORKER_MODEL"): "a simulate_shapes pool worker's model, set by the "
                                                "pool initializer in the spawned worker only (the "
                                                "model crosses the process boundary once, not per chunk)",
    ("ctrplan.planning.planner", "_WORKER_PLANNERS"): "a plan-batch/design worker's Planners, made by "
                                                      "its first job in the worker process only (the "
                                                      "command's own process owns its Planners)",
}
#: Module-level functions whose results are memoised: constants, keyed by a bounded integer.
MEMOISED = {
    ("ctrplan.shape.basis", "_coefficients"): "the orthonormal basis's exact coefficients, one per "
                                               "basis size (at most MAX_TERMS): constants of mathematics",
}

CACHE_TYPES = {"WeakKeyDictionary", "WeakValueDictionary", "OrderedDict", "Bounded", "defaultdict",
               "ChainMap", "Counter", "deque", "WeakSet"}
MUTATORS = {"append", "extend", "insert", "add", "update", "setdefault", "pop", "popitem", "clear",
            "remove", "discard", "move_to_end", "appendleft", "__setitem__"}
MEMO_DECORATORS = {"cache", "lru_cache", "cached_property"}


def _modules(root: Path) -> dict[str, Path]:
    out = {}
    for f in sorted(root.rglob("*.py")):
        parts = list(f.relative_to(root.parent).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts = parts[:-1]
        out[".".join(parts)] = f
    return out


def _root_name(node: ast.AST) -> str | None:
    while isinstance(node, (ast.Attribute, ast.Subscript)):
        node = node.value
    return node.id if isinstance(node, ast.Name) else None


def _call_name(node: ast.AST) -> str:
    f = node.func if isinstance(node, ast.Call) else node
    return f.attr if isinstance(f, ast.Attribute) else f.id if isinstance(f, ast.Name) else ""


def process_caches(root: Path) -> list[str]:
    """``module:name: why`` for every process-wide cache (module docstring)."""
    found = []
    for mod, path in _modules(root).items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        names: set[str] = set()
        for node in tree.body:
            targets = node.targets if isinstance(node, ast.Assign) else \
                [node.target] if isinstance(node, ast.AnnAssign) and node.value is not None else []
            for t in targets:
                if isinstance(t, ast.Name):
                    names.add(t.id)
                    if isinstance(node.value, ast.Call) and _call_name(node.value) in CACHE_TYPES:
                        found.append(f"{mod}:{t.id}: a {_call_name(node.value)} at module level")
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
                for d in node.decorator_list:
                    if _call_name(d) in MEMO_DECORATORS:
                        found.append(f"{mod}:{node.name}: memoised with {_call_name(d)}")
        for fn in ast.walk(tree):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)):
                continue
            local = {a.arg for a in ast.walk(fn) if isinstance(a, ast.arg)}
            for node in ast.walk(fn):
                if isinstance(node, ast.Global):
                    found += [f"{mod}:{n}: rebound through global" for n in node.names]
                elif isinstance(node, (ast.Assign, ast.AugAssign, ast.Delete)):
                    targets = node.targets if isinstance(node, (ast.Assign, ast.Delete)) else [node.target]
                    for t in targets:
                        r = _root_name(t)
                        if isinstance(t, ast.Subscript) and r in names and r not in local:
                            found.append(f"{mod}:{r}: filled by a function")
                elif isinstance(node, ast.Call) and isinstance(node.func, ast.Attribute) \
                        and node.func.attr in MUTATORS and isinstance(node.func.value, ast.Name) \
                        and node.func.value.id in names and node.func.value.id not in local:
                    found.append(f"{mod}:{node.func.value.id}: filled by a function ({node.func.attr})")
    return sorted(set(found))


def _allowed(entry: str) -> bool:
    mod, _, rest = entry.partition(":")
    name = rest.partition(":")[0]
    return (mod, name) in PROCESS_STATE or (mod, name) in MEMOISED


MODEL_ATTRS = {"effects", "error_quantiles", "error_profile", "error_bound", "measured_insertion",
               "planning_model", "tip_and_jacobian", "needs_direction", "max_curvature",
               "with_effects", "meta", "base", "torsion", "loads", "last_info"}
MODELISH = {"pm", "pmodel", "given", "ref", "reference", "inner", "m", "sm"}


def model_probes(root: Path) -> list[str]:
    """``file:line`` of every getattr/hasattr on a model-like object, or for a model attribute."""
    found = []
    for path in sorted(root.rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
            if not (isinstance(node, ast.Call) and _call_name(node) in ("getattr", "hasattr")
                    and isinstance(node.func, ast.Name) and len(node.args) >= 2):
                continue
            obj, attr = node.args[0], node.args[1]
            name = obj.attr if isinstance(obj, ast.Attribute) else obj.id if isinstance(obj, ast.Name) else ""
            modelish = "model" in name.lower() or name in MODELISH
            about_model = isinstance(attr, ast.Constant) and attr.value in MODEL_ATTRS
            if modelish or about_model:
                found.append(f"{path.relative_to(root.parent)}:{node.lineno}")
    return found


def _imports(path: Path) -> set[str]:
    out = set()
    for node in ast.walk(ast.parse(path.read_text(encoding="utf-8"))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and not node.level:
            out.add(node.module)
            out |= {f"{node.module}.{a.name}" for a in node.names}
    return out


#: layer -> what it must never import (robot -> shape -> collision -> planning -> design -> CLI)
NEVER = {
    "shape": ("ctrplan.collision", "ctrplan.planning", "ctrplan.design", "ctrplan.commands", "ctrplan.cli"),
    "collision": ("ctrplan.planning", "ctrplan.design", "ctrplan.commands", "ctrplan.cli"),
    "planning": ("ctrplan.design", "ctrplan.commands", "ctrplan.cli"),
}


def upward_imports(root: Path) -> list[str]:
    found = []
    for layer, banned in NEVER.items():
        for path in sorted((root / layer).rglob("*.py")):
            for name in sorted(_imports(path)):
                if name.startswith(banned):
                    found.append(f"{path.relative_to(root.parent)} imports {name}")
    return found


# ------------------------------------------------------------------------ the scanners' own test
def _package(tmp_path: Path) -> Path:
    root = tmp_path / "ctrplan"
    for layer in ("shape", "collision", "planning"):
        (root / layer).mkdir(parents=True)
        (root / layer / "__init__.py").write_text("")
    (root / "__init__.py").write_text("")
    (root / "shape" / "cached.py").write_text(
        "import functools\nimport weakref\nfrom collections import OrderedDict\n"
        "TABLE = {'a': 1}\n_MEMO = {}\n_SEEN = []\n_W = weakref.WeakKeyDictionary()\n"
        "_LRU = OrderedDict()\n_STATE = None\n"
        "def get(k):\n    if k not in _MEMO:\n        _MEMO[k] = TABLE['a'] + k\n    return _MEMO[k]\n"
        "def note(x):\n    _SEEN.append(x)\n"
        "def local(d):\n    d['x'] = 1\n    TABLE2 = {}\n    TABLE2['y'] = 2\n"
        "def swap():\n    global _STATE\n    _STATE = 1\n"
        "@functools.lru_cache(maxsize=8)\ndef slow(n):\n    return n\n"
        "from ctrplan.planning import plan\n")
    (root / "planning" / "probe.py").write_text(
        "def f(model, world, run):\n    a = getattr(model, 'effects', None)\n"
        "    b = hasattr(run.model, 'x')\n    c = getattr(world, 'margin_mm', 0.0)\n"
        "    d = getattr(world, 'error_quantiles', None)\n    return a, b, c, d\n")
    return root


def test_the_scanners_find_known_violations(tmp_path):
    root = _package(tmp_path)
    found = process_caches(root)
    names = {e.split(":")[1] for e in found}
    assert names == {"_MEMO", "_SEEN", "_W", "_LRU", "_STATE", "slow"}, found
    assert model_probes(root) == ["ctrplan/planning/probe.py:2", "ctrplan/planning/probe.py:3",
                                  "ctrplan/planning/probe.py:5"]
    assert upward_imports(root) == ["ctrplan/shape/cached.py imports ctrplan.planning",
                                    "ctrplan/shape/cached.py imports ctrplan.planning.plan"]


# ------------------------------------------------------------------------ the package
def test_no_process_wide_cache_in_the_package():
    found = [e for e in process_caches(ROOT) if not _allowed(e)]
    assert found == [], "module-level caches (keep them on their object or with their owner):\n" + \
        "\n".join(found)


def test_the_allow_lists_name_what_exists():
    """Every allow-listed name is still there (a list that outlives its entries hides nothing)."""
    entries = {tuple(e.split(":")[:2]) for e in process_caches(ROOT)}
    stale = [k for k in list(PROCESS_STATE) + list(MEMOISED) if k not in entries]
    assert stale == [], stale


def test_planning_asks_the_planning_model_not_the_model():
    assert model_probes(ROOT / "planning") == []


def test_no_import_runs_back_up_a_layer():
    assert upward_imports(ROOT) == []


def test_plan_py_stays_small():
    lines = (ROOT / "planning" / "plan.py").read_text(encoding="utf-8").count("\n")
    assert lines <= 650, lines


@pytest.mark.parametrize("name", ["plan_to_target", "PlanConfig", "PlanResult", "PlanStatus",
                                  "planning_model_of", "scene_by_name", "resolve_model", "world_for",
                                  "path_min_clearance", "check_objective", "check_target",
                                  "check_start", "robot_record_of", "MAX_TARGET_MM",
                                  "Planner", "PlannerConfig"])
def test_the_import_paths_of_plan_py_keep_working(name):
    import ctrplan
    import ctrplan.planning as planning
    import ctrplan.planning.plan as plan

    assert getattr(plan, name) is not None
    if name in ("plan_to_target", "PlanConfig", "PlanResult", "PlanStatus", "Planner", "PlannerConfig"):
        assert getattr(planning, name) is getattr(plan, name) is getattr(ctrplan, name)
