"""Generated text of the fresh-seed calibration statistics (``benchmarks/bench_fresh.py``'s
``benchmarks/results/fresh.json``): docs/validation.md's table, the README's sentence and the
validation table's "last measured" of the calibration claims (``ctrplan bench --readme``)."""

from __future__ import annotations

import json
from pathlib import Path

#: what a case of benchmarks/bench_fresh.py must do on a seed, by kind
FRESH_PASS = {"single": "named alone, held-out error halved", "none": "nothing named",
              "outside": "nothing named, reported unexplained",
              "study": "clearance, friction and torsion named"}
FRESH_KINDS = {"single": "a single effect", "none": "no effect", "outside": "an effect outside "
               "the vocabulary", "study": "the three-effect study"}


def _pct(x: float) -> str:
    return f"{100 * x:.0f} %"


def _fresh_rate(c: dict) -> str:
    lo, hi = c["ci95"]
    return f"{c['passed']}/{c['n']} ({_pct(c['passed'] / c['n']) if c['n'] else 'n/a'}; 95 % interval {100 * lo:.0f}–{100 * hi:.0f} %)"


def _fresh_head(fr: dict) -> str:
    rev = fr["revisions"][0] if len(fr["revisions"]) == 1 else None
    code = (f"code revision `{(rev.get('commit') or 'unknown')[:10]}`"
            f"{' with local changes' if rev.get('dirty') else ''}" if rev else
            f"{len(fr['revisions'])} code revisions (resumed across commits)")
    done = sum(c["n"] for c in fr["cases"])
    total = sum(c["seeds"] for c in fr["cases"])
    return (f"{len(fr['seeds'])} fresh seeds per case (the study: its first "
            f"{min(c['seeds'] for c in fr['cases'] if c['kind'] == 'study') if any(c['kind'] == 'study' for c in fr['cases']) else 0}), "
            f"drawn from master seed {fr['master_seed']} (`CTRPLAN_FRESH_SEED={fr['master_seed']}`), "
            f"none of them a development seed; {code}; {fr['updated']}"
            + ("" if fr["complete"] else f"; INCOMPLETE: {done} of {total} results"))


def fresh_block(fr: dict) -> str:
    """docs/validation.md's fresh-seed table from benchmarks/results/fresh.json."""
    met = sum(c["met"] for c in fr["cases"])
    lines = [f"{_fresh_head(fr)}. Each rate with its exact (Clopper-Pearson) 95 % interval "
             f"and the threshold of issue 36; {met} of {len(fr['cases'])} cases meet it.", "",
             "| case | robot | passes a seed when | passed | rate | 95 % interval | needs | met |",
             "|---|---|---|---|---|---|---|---|"]
    for c in fr["cases"]:
        lo, hi = c["ci95"]
        rate = _pct(c["passed"] / c["n"]) if c["n"] else "n/a"
        lines.append(f"| {c['case'].split('/')[-1]} | {c['robot']} | {FRESH_PASS[c['kind']]} | "
                     f"{c['passed']}/{c['n']} | {rate} | {100 * lo:.0f}–{100 * hi:.0f} % | "
                     f"≥ {_pct(c['threshold'])} | {'yes' if c['met'] else '**no**'} |")
    return "\n".join(lines)


def _fresh_kind(fr: dict, kind: str) -> str | None:
    cs = [c for c in fr["cases"] if c["kind"] == kind and c["n"]]
    if not cs:
        return None
    low = min(cs, key=lambda c: (c["passed"] / c["n"], c["case"]))
    # below: the rate so far under the threshold; the others not met only wait for seeds
    short = [c["case"] for c in cs if c["passed"] < c["threshold"] * c["n"] - 1e-9]
    waiting = [c["case"] for c in cs if not c["met"] and c["case"] not in short]
    if len(cs) == 1:
        text = _fresh_rate(low)
    else:
        text = (f"{_pct(min(c['passed'] / c['n'] for c in cs))}–"
                f"{_pct(max(c['passed'] / c['n'] for c in cs))} of the seeds over {len(cs)} cases "
                f"(lowest {low['case']}: {_fresh_rate(low)})")
    return (text + (f"; below the threshold: {', '.join(short)}" if short else "")
            + (f"; at the threshold so far, not all seeds run: {', '.join(waiting)}" if waiting else ""))


def fresh_summary_block(fr: dict) -> str:
    """The README's sentence on the fresh-seed rates."""
    parts = []
    for kind, what in (("single", "a single effect named alone and its held-out error halved"),
                       ("none", "nothing named without an effect"),
                       ("outside", "an effect outside the vocabulary left unexplained and unnamed"),
                       ("study", "the study's three effects named")):
        t = _fresh_kind(fr, kind)
        if t:
            parts.append(f"{what}: {t}")
    return (f"Measured on data ctrplan did not make (the independent generator, "
            f"`benchmarks/bench_fresh.py`; {_fresh_head(fr)}): " + "; ".join(parts)
            + ". Per case in [docs/validation.md](docs/validation.md).")


def measured_fresh(kind: str):
    """The validation table's "last measured" of a claim: the fresh-seed rate of ``kind``."""
    def f(res: Path) -> str | None:
        try:
            fr = json.loads((res / "fresh.json").read_text(encoding="utf-8"))
        except (OSError, ValueError):
            fr = None
        t = _fresh_kind(fr, kind) if fr else None
        return None if t is None else f"fresh seeds: {t} (`fresh.json`)"
    return f
