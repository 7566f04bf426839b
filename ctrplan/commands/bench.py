"""``ctrplan bench``: run the benchmark suites and write JSON plus a markdown table."""

from __future__ import annotations

import argparse
import importlib.util
import json
import logging
import platform
import time
from pathlib import Path

from ctrplan.commands._fresh import fresh_block, fresh_summary_block, measured_fresh
from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")

SUITES = ("shape", "learned", "collision", "planning", "diagnose")
#: suites run only when named (hours long) that keep their own results file <out>/<suite>.json
#: (resumable) instead of a part of bench.json: ``fresh``, the fresh-seed calibration statistics
OWN_RESULTS = ("fresh",)
START, END = "<!-- bench:start -->", "<!-- bench:end -->"


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("bench", help="run the benchmark suites (JSON + markdown out)",
                       description="Run benchmarks/bench_<suite>.py (shape models, learned model, "
                                   "collision, planning, diagnose) and write <out>/bench.json and "
                                   "<out>/bench.md with the machine they ran on.")
    p.add_argument("suites", nargs="*", default=list(SUITES),
                   help=f"suites to run (default: all of {', '.join(SUITES)}; also "
                        f"{', '.join(OWN_RESULTS)}: the fresh-seed calibration statistics, hours, "
                        "resumable, written to <out>/fresh.json)")
    p.add_argument("--quick", action="store_true", help="small sizes (a smoke run)")
    p.add_argument("--out", default="benchmarks/results", help="output folder")
    p.add_argument("--readme", metavar="FILE",
                   help=f"also put the tables into FILE between the lines {START} and {END}, and "
                        "rewrite FILE's other generated blocks (<!-- NAME:start --> ... "
                        "<!-- NAME:end -->: glance, perf-summary, hard, hard-summary, real-robot, "
                        "validation) from the JSON in --out, and the same blocks of "
                        "docs/performance.md and docs/validation.md beside FILE (how every "
                        "number of the README and those docs is made)")
    p.add_argument("--no-run", action="store_true",
                   help="run no suite: only rewrite --readme's blocks from the JSON already in --out")
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


def splice(text: str, md: str, source: str, block: str = "bench") -> str:
    """``text`` with the lines between the ``<!-- block:start -->`` and ``<!-- block:end -->``
    markers replaced by ``md``."""
    start, end = f"<!-- {block}:start -->", f"<!-- {block}:end -->"
    lines = text.splitlines(keepends=True)
    try:
        i = next(k for k, ln in enumerate(lines) if ln.strip() == start)
        j = next(k for k, ln in enumerate(lines) if ln.strip() == end and k > i)
    except StopIteration:
        raise InputError(source, start, f"needs a line {start} followed by a line {end}") from None
    return "".join(lines[:i + 1]) + md.rstrip("\n") + "\n" + "".join(lines[j:])


# ----------------------------------------------------------------------------- README blocks
# Every measured number of the README's planning and performance sections is written here from
# the committed JSON in benchmarks/results/ (tests/test_readme.py regenerates and compares).

def _load(path: Path):
    try:
        return json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None


def _rng(vals, fmt: str) -> str:
    vals = [v for v in vals if v is not None]
    if not vals:
        return "n/a"
    lo, hi = min(vals), max(vals)
    a, b = format(lo, fmt), format(hi, fmt)
    return a if a == b else f"{a}–{b}"


def _k(x: float) -> str:
    return f"{x / 1000:.0f}k"


def _gpu_result(results: Path) -> dict | None:
    """The GPU table of the learned model: the newest ``learned_gpu_<card>.json`` written by
    ``bench_learned.py --device cuda --record`` (it names the architecture), else the older
    ``learned_gpu_h100.json`` (the previous 3 x 30 network's)."""
    new = sorted((p for p in results.glob("learned_gpu_*.json") if p.name != "learned_gpu_h100.json"),
                 key=lambda p: p.stat().st_mtime)
    for p in reversed(new):
        got = _load(p)
        if got and "architecture" in got:
            return {**got, "_file": p.name}
    old = _load(results / "learned_gpu_h100.json")
    return None if old is None else {**old, "_file": "learned_gpu_h100.json"}


def _shape_rows(sh: dict) -> list[str]:
    """The mechanics row (suite ``shape``)."""
    ps = sh["per_shape_s"]
    return [f"| compliant mechanics, batch 10,000 ({sh['robot']}, {sh['points']} points) | "
            f"{ps['compliant']['10000'] * 1e6:.1f} µs per shape (rigid "
            f"{ps['rigid']['10000'] * 1e6:.1f} µs); published anchor "
            f"{sh['published_anchor_s_per_shape'] * 1e3:.2f} ms | "
            f"≤ {sh['target_compliant_10k_s'] * 1e6:.0f} µs |"]


def _learned_rows(le: dict) -> list[str]:
    """The learned model rows: time per shape and the ratio to physics (suite ``learned``)."""
    rows: list[str] = []
    by = {r["batch"]: r for r in le["table"]}
    big = by[le["largest_batch"]]
    rows.append(f"| learned model, batch {le['largest_batch']:,} | "
                f"{big['learned_us_per_shape']:.2f} µs per shape; batch-1 latency "
                f"{le['batch1_latency_us']['learned']:.0f} µs | ≤ 1 µs |")
    sp = [by[b]["speedup"] for b in sorted(by) if b >= 10000]
    met = "met" if le.get("target_ge_100x_at_100k") else (
        f"**not met**: the network's matrix products alone "
        f"({le['floor']['network_products_us_per_shape']:.2f} µs per shape at batch "
        f"{le['floor']['batch']:,}) cap the ratio at {le['ratio_bound_from_floor']:.0f}x")
    rows.append(f"| learned vs batched compliant physics, same run | {_rng(sp, '.0f')}x at "
                f"batch 10^4–10^5 | ≥ 100x — {met} |")
    return rows


def _gpu_rows(gpu: dict) -> list[str]:
    """The learned model on a GPU row (the GPU JSON)."""
    g = {r["batch"]: r for r in gpu["table"]}
    which = "" if "architecture" in gpu else ", the previous 3 x 30 network"
    return [f"| learned model on a GPU ({gpu['device']}{which}), forward pass on the device | "
            f"{g[100000]['forward_on_device_us_per_shape']:.3f} µs per shape at 10^5; "
            f"`backbone()` with numpy in/out {g[100000]['backbone_us_per_shape']:.2f} µs at "
            f"10^5; batch 1: {g[1]['backbone_call_ms']:.2f} ms | – |"]


def _collision_rows(co: dict) -> list[str]:
    """The shape + collision rows, random and near the targets (suite ``collision``)."""
    rows: list[str] = []
    for kind, what, tgt in (("reach", "shape + collision, learned model, random reachable "
                             "configurations", "≥ 50k/s, ≥ 20x"),
                            ("near_targets", "the same near the targets (tight lumens)", "–")):
        rs = [r for r in co["table"] if r["configs"] == kind and r["model"] == "learned"]
        if rs:
            if tgt != "–":
                short = [f"{r['scene']} {r['prefilter_fcl_per_s'] / 1000:.0f}k/s, "
                         f"{r['speedup']:.0f}x" for r in rs
                         if r["prefilter_fcl_per_s"] < 50_000 or r["speedup"] < 20]
                tgt += " — met" if not short else f" — **not met**: {'; '.join(short)}"
            cs = [r["collision_speedup"] for r in rs if "collision_speedup" in r]
            alone = f" (collision alone {_rng(cs, '.0f')}x)" if cs else ""
            rows.append(f"| {what} | {_rng([r['prefilter_fcl_per_s'] / 1000 for r in rs], '.0f')}k "
                        f"configurations/s per scene; {_rng([r['speedup'] for r in rs], '.0f')}x "
                        f"shape + FCL alone{alone}; "
                        f"{_rng([100 * r['to_fcl_fraction'] for r in rs], '.1f')} % of "
                        f"states need FCL | {tgt} |")
    return rows


def _planning_rows(pl: dict) -> list[str]:
    """The planning row (suite ``planning``)."""
    rows: list[str] = []
    by = {(r["scene"], r["model"]): r for r in pl["table"]}
    parts = []
    for m in ("physics", "learned"):
        r = by.get(("all", m))
        if r is None:
            continue
        ok = round(r["success_rate"] * r["plans"])
        txt = (f"{m}{' (the default)' if m == 'physics' else ''}: {ok}/{r['plans']} success, "
               f"median {r['median_s']:.2f} s, p90 {r['p90_s']:.2f} s per plan")
        if r.get("rechecked"):
            txt += (f"; {r['rechecked'] - r['recheck_failures']}/{r['rechecked']} successful "
                    "paths free in the independent re-check")
        parts.append(txt)
    if ("all", "physics") in by:
        parts.append(f"{100 * by[('all', 'physics')]['direct_fraction']:.0f} % of the physics "
                     "plans are a single direct joint-space edge")
    n_t = len({p["target"] for p in pl["plans"]})
    short = [f"{m} {100 * r['success_rate']:.0f} %, median {r['median_s']:.2f} s "
             f"({r['statuses']})" for (sc, m), r in sorted(by.items())
             if sc == "all" and (r["success_rate"] < 0.95 or r["median_s"] >= 1.0)]
    met = "met" if not short else f"**not met**: {'; '.join(short)}"
    rows.append(f"| planning, {len(pl['scenes'])} scenes x {n_t} targets x {len(pl['seeds'])} seeds "
                f"(`bench_planning.py`) | {'; '.join(parts)} | "
                f"≥ 95 %, median < 1 s — {met} |")
    return rows


def _diagnose_rows(dg: dict) -> list[str]:
    """The diagnose rows: the simulated case and the 5,000-row recording (suite ``diagnose``)."""
    rows: list[str] = []
    r = next((r for r in dg["table"] if r["hidden"] != "none"), None)
    if r:
        rows.append(f"| diagnose, {r['rows']:,} samples, hidden {r['hidden']}, {dg['robot']} | "
                    f"{r['wall_s']:.1f} s; found {r['found']}; held-out error "
                    f"{r['error_before_mm']:.2f} → {r['error_after_mm']:.2f} mm | < 2 min |")
    rr = dg.get("real_5000")
    if rr:
        met = "met" if rr["under_2_min"] else "**not met**"
        rows.append(f"| diagnose, {rr['rows']:,}-row continuous recording ({rr['hidden']}), "
                    f"{dg['robot']} | {rr['wall_s']:.0f} s ({rr['cpu_s']:.0f} s CPU); "
                    f"held-out error {rr['error_before_mm']:.2f} → "
                    f"{rr['error_after_mm']:.2f} mm ({rr['percent_of_length']:.2f} % of the "
                    f"length) on {rr['independent_test_blocks']} test blocks | < 2 min — "
                    f"{met} |")
    return rows


def summary_block(bench: dict, gpu: dict | None) -> str:
    """The performance summary table (what | measured | target) from bench.json (one run) and
    the GPU JSON."""
    su = bench["suites"]
    rows = ["| what | measured | target |", "|---|---|---|"]
    for name, part in (("shape", _shape_rows), ("learned", _learned_rows)):
        if su.get(name):
            rows += part(su[name])
    if gpu:
        rows += _gpu_rows(gpu)
    for name, part in (("collision", _collision_rows), ("planning", _planning_rows),
                       ("diagnose", _diagnose_rows)):
        if su.get(name):
            rows += part(su[name])
    m = bench["machine"]
    rows += ["", f"Measured {m['date']} on {m['cpu']}, {m['cores']} cores (`benchmarks/results/bench.json`"
             + (f", `benchmarks/results/{gpu.get('_file', 'learned_gpu_h100.json')}`" if gpu else "") + ")."]
    return "\n".join(rows)


def hard_summary_block(hard: dict) -> str:
    """The measured sentence of the hard benchmark from benchmarks/results/hard/summary.json."""
    recs = hard["records"]
    ok = [r for r in recs if r["success"]]
    phys = {r["planner"]: r for r in hard["table"] if r["model"] == "physics"}
    how = hard.get("recheck", "the planner's own physics model and FCL, written before the "
                              "independent re-check existed: rerun `bench_hard.py` to refresh")
    rc = [r["recheck_clearance"] for r in ok if r.get("recheck_clearance") is not None]
    fails = sum(1 for r in ok if r.get("recheck_free") is False)
    out = [f"Measured on all {len(hard['problems'])} problems ({hard['runs']} seed each, "
           f"{hard['time_limit_s']:g} s cap): "]
    if phys:
        good = [p for p, r in phys.items() if r["success_rate"] >= 0.95]
        first = phys.get("rrtconnect") or next(iter(phys.values()))
        out.append(f"with the physics planning model {first['planner']} solves "
                   f"{first['success']}/{first['plans']} (at least 95 %: {', '.join(good) or 'none'}); ")
    out.append(f"{len(ok) - fails} of the {len(ok)} successful plans (of {len(recs)} runs) are "
               f"collision-free in the re-check ({how}), smallest clearance "
               f"{min(rc):.3f} mm." if rc else "no successful plans.")
    return "".join(out)


def real_robot_block(rr: dict) -> str:
    """The end-to-end real-robot scenario from benchmarks/results/real_robot.json."""
    dev = rr["truth"]["deviation_from_nominal"]
    th = rr["thresholds"]
    lines = [f"Truth robot `{rr['truth']['source']}`: {dev['mean_mm']:.2f} mm mean (max "
             f"{dev['max_mm']:.2f} mm) of the max deviation along the shaft from the nominal "
             f"compliant {rr['robot']}. First {rr['targets_per_scene']} targets of each of the "
             f"{len(rr['scenes'])} shipped scenes, {rr['time_limit_s']:g} s cap, replayed on the "
             "truth with the independent re-check (`tests/foreign/recheck.py`).", "",
             "| flow | planned | states replayed | in contact | deeper than "
             f"{th['depth_mm']:g} mm | centreline crosses the wall | deepest (mm; at least the "
             "tube radius where the centreline crosses) | truth tip error median (mm) |",
             "|---|---|---|---|---|---|---|---|"]
    names = {"calibrated": "measure, `diagnose --model physics`, plan with the calibrated "
                           "model and `--margin auto`",
             "default": "default `ctrplan plan` (nominal physics model, no calibration)",
             "first": "before: nominal physics model, margin 0, first solution "
                      "(`--objective first`)"}
    for f in ("calibrated", "default", "first"):
        if f not in rr:
            continue
        s = rr[f]["summary"]
        tip = s["tip_error_truth_median_mm"]
        cross = sum(p.get("centreline_crossings", 0) for p in rr[f]["plans"] if p["success"])
        lines.append(f"| {names[f]} | {s['success']}/{s['plans']} | {s['states']} | "
                     f"{s['contact_states']} | {s['penetrating_states']} | {cross} | "
                     f"{s['max_depth_mm']:.2f} | "
                     f"{'n/a' if tip is None else format(tip, '.2f')} |")
    if "calibrated" in rr:
        c = rr["calibrated"]["calibration"]
        lines += ["", f"Calibration: {c['rows']} rows, found {', '.join(c['effects'] or []) or 'nothing'}, "
                  f"held-out error {c['error_before_mm']:.2f} → {c['error_after_mm']:.2f} mm."]
    return "\n".join(lines)


# ----------------------------------------------------------------------------- docs/validation.md
def _m_learned_foreign_best_gain(res: Path) -> str | None:
    d = _load(res / "learned_foreign.json")
    if not d:
        return None
    best = max((k for k in d["summary"] if isinstance(d["summary"][k], dict)),
               key=lambda k: d["summary"][k]["gain_vs_physics"])
    g = d["summary"][best]
    return (f"{best}: {100 * g['gain_vs_physics']:.0f} % ({g['mean_mm']:.2f} vs physics "
            f"{d['summary']['physics']:.2f} mm, {d['seeds']} seeds; `learned_foreign.json`)")


def _m_learned_foreign_auto_ratio(res: Path) -> str | None:
    d = _load(res / "learned_foreign_auto.json")
    if not d:
        return None
    return (f"{d['auto_over_best']:.3f}x the best ({d['best_variant']}), {d['seeds']} seeds "
            "(`learned_foreign_auto.json`)")


def _m_hard_rrtconnect_success(res: Path) -> str | None:
    d = _load(res / "hard" / "summary.json")
    if not d:
        return None
    r = next((r for r in d["table"] if r["model"] == "physics" and r["planner"] == "rrtconnect"), None)
    if r is None:
        return None
    fails = sum(1 for x in d["records"] if x["success"] and x.get("recheck_free") is False)
    return (f"{r['success']}/{r['plans']}; {fails} re-check failures "
            "(`hard/summary.json`)")


def _m_hard_clearance_ratio(res: Path) -> str | None:
    d = _load(res / "hard" / "summary.json")
    if not d:
        return None
    rows = {r["objective"]: r for r in d["table"]
            if r["model"] == "physics" and r["planner"] == "rrtconnect"}
    c, f = rows.get("clearance"), rows.get("first")
    if not c or not f or not f.get("clearance_median_mm") or not f.get("recheck_clearance_median_mm"):
        return None
    return (f"{c['clearance_median_mm']:.2f} vs {f['clearance_median_mm']:.2f} mm "
            f"({c['clearance_median_mm'] / f['clearance_median_mm']:.1f}x); re-check "
            f"{c['recheck_clearance_median_mm']:.2f} vs {f['recheck_clearance_median_mm']:.2f} mm "
            f"({c['recheck_clearance_median_mm'] / f['recheck_clearance_median_mm']:.1f}x); "
            f"{c['success']}/{c['plans']} (`hard/summary.json`)")


def _m_real_robot(flow: str):
    def f(res: Path) -> str | None:
        d = _load(res / "real_robot.json")
        if not d or flow not in d:
            return None
        s = d[flow]["summary"]
        if flow == "calibrated":
            return (f"{s['success']}/{s['plans']} planned, {s['penetrating_states']} states deeper, "
                    f"tip error median {s['tip_error_truth_median_mm']:.2f} mm (`real_robot.json`)")
        b = d["first"]["summary"]
        return (f"{s['contact_states']} vs {b['contact_states']} contact states "
                "(`real_robot.json`)")
    return f


def _m_design_generated(res: Path) -> str | None:
    d = _load(res / "design_generated.json")
    if not d:
        return None
    return (f"{d['feasible_ok']}/{d['feasible_total']} anatomies (seeds {d['seeds'][0]}-{d['seeds'][1]}); "
            f"{d['plans_free']}/{d['plans_rechecked']} plans free in the re-check "
            "(`design_generated.json`)")


def _m_design_infeasible(res: Path) -> str | None:
    d = _load(res / "design_generated.json")
    if not d:
        return None
    return f"{d['infeasible_named']}/{d['infeasible_total']} anatomies (`design_generated.json`)"


def _m_reach_agreement(res: Path) -> str | None:
    d = _load(res / "reach.json")
    if not d:
        return None
    per = ", ".join(f"{r['scene']} {r['agree']}/{r['points']}" for r in d["scenes"])
    return (f"{100 * d['agreement_min']:.1f} % on the lowest scene ({per}; "
            f"{d['points_per_scene']} points per scene, {d['date']}, `reach.json`)")


#: claim ``measured`` key -> its value as text, computed from the JSON in benchmarks/results/
MEASURED = {
    "reach_agreement": _m_reach_agreement,
    "design_generated": _m_design_generated,
    "design_infeasible": _m_design_infeasible,
    "fresh_single": measured_fresh("single"),
    "fresh_none": measured_fresh("none"),
    "fresh_outside": measured_fresh("outside"),
    "fresh_study": measured_fresh("study"),
    "learned_foreign_best_gain": _m_learned_foreign_best_gain,
    "learned_foreign_auto_ratio": _m_learned_foreign_auto_ratio,
    "hard_rrtconnect_success": _m_hard_rrtconnect_success,
    "hard_clearance_ratio": _m_hard_clearance_ratio,
    "real_robot_calibrated": _m_real_robot("calibrated"),
    "real_robot_default": _m_real_robot("default"),
}


def load_claims(path: Path) -> list[dict]:
    """The claims registry (docs/validation.yaml): a list of {area, claim, test, threshold,
    asserts, measured?}."""
    import yaml

    try:
        data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as e:
        raise InputError(str(path), "", f"cannot read: {e}") from None
    if not isinstance(data, list):
        raise InputError(str(path), "", "expected a list of claims")
    for k, c in enumerate(data):
        for key in ("area", "claim", "test", "threshold", "asserts"):
            if not isinstance(c, dict) or not c.get(key):
                raise InputError(str(path), f"[{k}].{key}", "missing")
        if c.get("measured") and c["measured"] not in MEASURED:
            raise InputError(str(path), f"[{k}].measured", f"unknown key {c['measured']!r}")
    return data


def validation_block(claims: list[dict], results: Path) -> str:
    """docs/validation.md's claims table from the registry and the committed JSON."""
    rows = ["| area | claim | enforced by | threshold | last measured |", "|---|---|---|---|---|"]
    for c in claims:
        m = MEASURED[c["measured"]](results) if c.get("measured") else None
        path, _, name = c["test"].partition("::")
        rows.append(f"| {c['area']} | {c['claim']} | `{path}::{name}` | {c['threshold']} | "
                    f"{m or 'each CI run (asserted; no separate record)'} |")
    return "\n".join(rows)


def glance_block(bench: dict) -> str:
    """The README's few numbers (from bench.json)."""
    su = bench["suites"]
    parts = []
    sh = su.get("shape")
    if sh:
        parts.append(f"compliant mechanics {sh['per_shape_s']['compliant']['10000'] * 1e6:.0f} µs "
                     "per shape (batch 10,000)")
    le = su.get("learned")
    if le:
        big = {r["batch"]: r for r in le["table"]}[le["largest_batch"]]
        parts.append(f"the learned model {big['learned_us_per_shape']:.2f} µs per shape")
    pl = su.get("planning")
    if pl:
        r = next((r for r in pl["table"] if r["scene"] == "all" and r["model"] == "physics"), None)
        if r:
            parts.append(f"planning to the shipped targets {round(r['success_rate'] * r['plans'])}"
                         f"/{r['plans']} plans found (targets x seeds), median {r['median_s']:.2f} s "
                         "per plan")
    m = bench["machine"]
    return (f"On one core of a shared {m['cores']}-core VM ({m['date']}): " + "; ".join(parts)
            + ". Details in [docs/performance.md](docs/performance.md).")


def readme_blocks(results: Path) -> dict[str, str]:
    """Marker name -> generated markdown, for every block whose JSON is in ``results``
    (the blocks of README.md, docs/performance.md and docs/validation.md; names are unique
    across the three)."""
    results = Path(results)
    out: dict[str, str] = {}
    bench = _load(results / "bench.json")
    if bench:
        out["bench"] = to_markdown(bench)
        out["perf-summary"] = summary_block(bench, _gpu_result(results))
        out["glance"] = glance_block(bench)
    claims = results.resolve().parents[1] / "docs" / "validation.yaml"
    if claims.is_file():
        out["validation"] = validation_block(load_claims(claims), results)
    hard = _load(results / "hard" / "summary.json")
    if hard:
        out["hard"] = load_suite("hard").markdown(hard["table"])
        out["hard-summary"] = hard_summary_block(hard)
    rr = _load(results / "real_robot.json")
    if rr:
        out["real-robot"] = real_robot_block(rr)
    fr = _load(results / "fresh.json")
    if fr:
        out["fresh"] = fresh_block(fr)
        out["fresh-summary"] = fresh_summary_block(fr)
    return out


def refresh_readme(text: str, results: Path, source: str) -> str:
    """``text`` with every generated block present in it rewritten from ``results``."""
    for name, md in readme_blocks(results).items():
        if f"<!-- {name}:start -->" in text:
            text = splice(text, md, source, name)
    return text


#: the documents beside README.md whose generated blocks ``--readme`` also rewrites
DOCS = ("docs/performance.md", "docs/validation.md")


def refresh_docs(readme: Path, results: Path) -> None:
    """Rewrite the generated blocks of docs/performance.md and docs/validation.md beside
    ``readme`` (where they exist)."""
    from ctrplan.io import write_text_atomic

    for rel in DOCS:
        doc = readme.resolve().parent / rel
        if doc.is_file():
            text = doc.read_text(encoding="utf-8")
            write_text_atomic(doc, refresh_readme(text, results, str(doc)))


def run(args: argparse.Namespace) -> int:
    from ctrplan.io import jsonable, write_json_atomic, write_text_atomic

    unknown = [s for s in args.suites if s not in SUITES + OWN_RESULTS]
    if unknown:
        raise InputError("suites", unknown[0],
                         f"unknown suite (choose from {', '.join(SUITES + OWN_RESULTS)})")
    readme = None
    if args.readme:  # check the target before spending minutes on benchmarks
        try:
            readme = Path(args.readme).read_text(encoding="utf-8")
        except (OSError, UnicodeDecodeError) as e:
            raise InputError(args.readme, "", f"cannot read: {e}") from None
        docs = [Path(args.readme).resolve().parent / d for d in DOCS]
        texts = [readme] + [d.read_text(encoding="utf-8") for d in docs if d.is_file()]
        if not any(START in t for t in texts):   # the tables must have somewhere to go
            splice(readme, "", args.readme)
    if getattr(args, "no_run", False):
        if readme is None:
            raise InputError("--no-run", "", "needs --readme FILE")
        write_text_atomic(Path(args.readme), refresh_readme(readme, Path(args.out), args.readme))
        refresh_docs(Path(args.readme), Path(args.out))
        return 0
    for name in [s for s in args.suites if s in OWN_RESULTS]:
        log.info("bench: running %s%s", name, " (quick)" if args.quick else "")
        res = load_suite(name).run(quick=args.quick, out=Path(args.out) / f"{name}.json")
        print(to_markdown({"machine": res["machine"], "suites": {name: res}}))
    regular = [s for s in args.suites if s not in OWN_RESULTS]
    if not regular:
        if readme is not None:
            write_text_atomic(Path(args.readme), refresh_readme(readme, Path(args.out), args.readme))
            refresh_docs(Path(args.readme), Path(args.out))
        return 0
    results = {"machine": machine(), "quick": bool(args.quick), "suites": {}}
    for name in regular:
        log.info("bench: running %s%s", name, " (quick)" if args.quick else "")
        t0 = time.perf_counter()
        res = load_suite(name).run(quick=args.quick)
        res["wall_s"] = time.perf_counter() - t0
        results["suites"][name] = jsonable(res)   # a NaN a suite measured: null
    out = Path(args.out)
    write_json_atomic(out / "bench.json", results)
    md = to_markdown(results)
    write_text_atomic(out / "bench.md", md)
    if readme is not None:
        if START in readme:
            readme = splice(readme, md, args.readme)
        write_text_atomic(Path(args.readme), refresh_readme(readme, out, args.readme))
        refresh_docs(Path(args.readme), out)
    print(md)
    return 0
