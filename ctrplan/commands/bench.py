"""``ctrplan bench``: run the benchmark suites and write JSON plus a markdown table."""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import platform
import time
from pathlib import Path

from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")

SUITES = ("shape", "learned", "collision", "planning", "diagnose")
START, END = "<!-- bench:start -->", "<!-- bench:end -->"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run the benchmark suites (JSON + markdown out)",
                       description="Run benchmarks/bench_<suite>.py (shape models, learned model, "
                                   "collision, planning, diagnose) and write <out>/bench.json and "
                                   "<out>/bench.md with the machine they ran on.")
    p.add_argument("suites", nargs="*", default=list(SUITES), help=f"suites to run (default: all of {', '.join(SUITES)})")
    p.add_argument("--quick", action="store_true", help="small sizes (a smoke run)")
    p.add_argument("--out", default="benchmarks/results", help="output folder")
    p.add_argument("--readme", metavar="FILE",
                   help=f"also put the tables into FILE between the lines {START} and {END} "
                        "(how README.md's performance section is made)")
    p.set_defaults(func=run)


def benchmarks_dir() -> Path:
    """The repository's benchmarks/ folder (ctrplan is installed from a checkout)."""
    d = Path(__file__).resolve().parents[2] / "benchmarks"
    if not d.is_dir():
        raise InputError("benchmarks/", "", "not found: 'ctrplan bench' runs from a source checkout")
    return d


def load_suite(name: str):
    path = benchmarks_dir() / f"bench_{name}.py"
    if not path.exists():
        raise InputError(str(path), "", "benchmark script not found")
    spec = importlib.util.spec_from_file_location(f"ctrplan_bench_{name}", path)
    mod = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(mod)
    return mod


def machine() -> dict:
    import os

    import numpy
    try:
        import torch
        torch_v = torch.__version__
    except ImportError:  # pragma: no cover - torch is a dependency
        torch_v = None
    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"cpu": cpu, "cores": os.cpu_count(), "python": platform.python_version(),
            "numpy": numpy.__version__, "torch": torch_v, "platform": platform.platform(),
            "date": time.strftime("%Y-%m-%d %H:%M")}


def to_markdown(results: dict) -> str:
    """Render each suite's ``table`` (list of row dicts) as a markdown table."""
    m = results["machine"]
    lines = [f"Machine: {m['cpu']}, {m['cores']} cores, Python {m['python']}, torch {m['torch']}, {m['date']}", ""]
    for name, res in results["suites"].items():
        lines.append(f"### {name}")
        lines.append("")
        rows = res.get("table") if isinstance(res, dict) else None
        if not rows:
            lines.append("```\n" + json.dumps(res, indent=1)[:2000] + "\n```")
            lines.append("")
            continue
        cols = list(rows[0].keys())
        lines.append("| " + " | ".join(cols) + " |")
        lines.append("|" + "---|" * len(cols))
        for r in rows:
            lines.append("| " + " | ".join(_cell(r.get(c)) for c in cols) + " |")
        lines.append("")
    return "\n".join(lines)


def _cell(v) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    return "" if v is None else str(v)


def splice(text: str, md: str, source: str) -> str:
    """``text`` with the lines between the START and END markers replaced by ``md``."""
    lines = text.splitlines(keepends=True)
    try:
        i = next(k for k, ln in enumerate(lines) if ln.strip() == START)
        j = next(k for k, ln in enumerate(lines) if ln.strip() == END and k > i)
    except StopIteration:
        raise InputError(source, START, f"needs a line {START} followed by a line {END}") from None
    return "".join(lines[:i + 1]) + md.rstrip("\n") + "\n" + "".join(lines[j:])


def run(args: argparse.Namespace) -> int:
    from ctrplan.io import write_json_atomic, write_text_atomic

    unknown = [s for s in args.suites if s not in SUITES]
    if unknown:
        raise InputError("suites", unknown[0], f"unknown suite (choose from {', '.join(SUITES)})")
    readme = None
    if args.readme:  # check the target before spending minutes on benchmarks
        try:
            readme = Path(args.readme).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise InputError(args.readme, "", f"cannot read: {e}") from None
        splice(readme, "", args.readme)
    results = {"machine": machine(), "quick": bool(args.quick), "suites": {}}
    for name in args.suites:
        log.info("bench: running %s%s", name, " (quick)" if args.quick else "")
        t0 = time.perf_counter()
        res = load_suite(name).run(quick=args.quick)
        res["wall_s"] = time.perf_counter() - t0
        results["suites"][name] = res
    out = Path(args.out)
    write_json_atomic(out / "bench.json", results)
    md = to_markdown(results)
    write_text_atomic(out / "bench.md", md)
    if readme is not None:
        write_text_atomic(Path(args.readme), splice(readme, md, args.readme))
    print(md)
    return 0
