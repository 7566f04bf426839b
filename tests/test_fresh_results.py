"""The committed fresh-seed results (``benchmarks/results/fresh.json``, written by
``benchmarks/bench_fresh.py``) against what the documents quote and what issue 36 asks.

Fast (it reads the results; the hours of diagnose runs are the benchmark's): every record's
verdict is re-derived from what it recorded (the effects named, the cut, ``unexplained``), the
counts, rates and exact binomial intervals are recomputed here with scipy's own
``binomtest`` (not the benchmark's code), the seeds are re-drawn from the printed master seed
and checked to be fresh, the cases cover the statistical suite, the design is the suite's, the
numbers the README and docs/validation.md quote are these, and every case meets its threshold.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import binomtest

ROOT = Path(__file__).resolve().parents[1]
RESULTS = ROOT / "benchmarks" / "results" / "fresh.json"
#: issue 36, "Done when": the share of fresh seeds each kind of case must reach, and how many
#: fresh seeds at least
THRESHOLDS = {"single": 0.85, "none": 0.95, "outside": 0.85, "study": 2 / 3}
MIN_SEEDS = {"single": 30, "none": 30, "outside": 30, "study": 3}


@pytest.fixture(scope="module")
def fresh() -> dict:
    assert RESULTS.is_file(), "benchmarks/results/fresh.json is missing: run benchmarks/bench_fresh.py"
    return json.loads(RESULTS.read_text(encoding="utf-8"))


def _passes(kind: str, rec: dict, case: dict) -> bool:
    """A record's verdict from what it recorded (the rules of the benchmark's docstring)."""
    if kind == "single":
        name = next(iter(case["effects"]))
        return rec["effects"] == [name] and rec["cut"] >= 0.5
    if kind == "none":
        return rec["effects"] == []
    if kind == "outside":
        return rec["effects"] == [] and bool(rec["unexplained"])
    return sorted(rec["effects"]) == ["clearance", "friction", "torsion"]


def test_seeds_are_fresh_and_drawn_from_the_printed_master_seed(fresh):
    seeds = fresh["seeds"]
    rng = np.random.default_rng(fresh["master_seed"])
    again: list[int] = []
    dev = set(fresh["development_seeds"])
    while len(again) < len(seeds):
        s = int(rng.integers(10_000, 2**31 - 1))
        if s not in again and s not in dev:
            again.append(s)
    assert seeds == again
    # the development seeds of the statistical suite and the generator's tests are all known
    for s in (*range(100, 110), *range(200, 220), 0, 1, 2, 3, 1000, 1001, 1002):
        assert s in dev
    assert not set(seeds) & dev and len(set(seeds)) == len(seeds)
    assert str(fresh["master_seed"]) in fresh["reproduce"]


def test_counts_rates_and_intervals_are_the_records(fresh):
    for c in fresh["cases"]:
        recs = c["records"]
        assert [r["seed"] for r in recs] == fresh["seeds"][:len(recs)], c["case"]
        for r in recs:
            assert r["ok"] == _passes(c["kind"], r, c), (c["case"], r["seed"])
        k = sum(r["ok"] for r in recs)
        assert (c["n"], c["passed"]) == (len(recs), k), c["case"]
        ci = binomtest(k, len(recs)).proportion_ci(0.95, method="exact")
        assert c["ci95"] == pytest.approx([ci.low, ci.high], abs=1e-9), c["case"]
        assert c["rate"] == pytest.approx(k / len(recs)), c["case"]
        assert c["threshold"] == pytest.approx(THRESHOLDS[c["kind"]]), c["case"]


def test_every_case_of_the_statistical_suite_is_measured_on_the_suites_design(fresh):
    import importlib.util

    from tests import foreign
    from tests import test_diagnose_foreign as suite

    spec = importlib.util.spec_from_file_location("bench_fresh", ROOT / "benchmarks" / "bench_fresh.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    assert (bench.ROBOT, bench.ROWS, bench.SWEEPS, bench.NOISE) == (suite.ROBOT, suite.ROWS,
                                                                     suite.SWEEPS, suite.NOISE)
    assert fresh["design"] == {"robot": suite.ROBOT, "rows": suite.ROWS, "sweeps": suite.SWEEPS,
                               "noise_mm": suite.NOISE}
    got = {(c["kind"], c["case"]) for c in fresh["cases"]}
    want = ({("single", c) for c in suite.SINGLE} | {("none", "none"), ("study", "study")}
            | {("outside", c) for c in foreign.OUTSIDE_EFFECTS})
    assert want <= got, sorted(want - got)
    assert {c["case"] for c in bench.CASES} == {c["case"] for c in fresh["cases"]}
    # every seed in the dev suite's lists is a development seed of the benchmark
    assert set(suite.SEEDS) <= set(fresh["development_seeds"])


#: Issue 36 is open: several cases are below their thresholds (docs/validation.md quotes the
#: counts). Strict: once they meet the thresholds this test fails as XPASS, and the marker goes.
OPEN = pytest.mark.xfail(strict=True, reason="issue 36 open: fresh-seed cases below threshold")


def test_results_are_complete_with_a_code_revision(fresh):
    assert fresh["complete"]
    for c in fresh["cases"]:
        assert c["n"] == c["seeds"] >= MIN_SEEDS[c["kind"]], c["case"]
    assert fresh["revisions"] and all(r.get("commit") for r in fresh["revisions"])


def test_every_result_has_a_code_revision(fresh):
    assert fresh["revisions"] and all(r.get("commit") for r in fresh["revisions"])
    assert all(c["n"] >= 1 for c in fresh["cases"])


@OPEN
def test_fresh_seed_rates_meet_the_thresholds(fresh):
    """Issue 36: each single effect named and its test error halved in >= 85 % of 30 fresh
    seeds, nothing named without an effect in >= 95 %, outside effects unexplained and unnamed
    in >= 85 %, the study's three effects named in >= 2 of 3 fresh seeds."""
    short = [f"{c['case']}: {c['passed']}/{c['n']} (needs {100 * THRESHOLDS[c['kind']]:.0f} %)"
             for c in fresh["cases"] if c["passed"] < THRESHOLDS[c["kind"]] * c["n"] - 1e-9]
    assert not short, "fresh-seed rates below issue 36's thresholds:\n" + "\n".join(short)


def _block(text: str, name: str) -> str:
    m = re.search(rf"<!-- {name}:start -->\n(.*?)<!-- {name}:end -->", text, re.S)
    assert m, name
    return m.group(1)


def test_the_documents_quote_these_rates(fresh):
    """docs/validation.md's table has one row per case with these counts and intervals; the
    README's sentence quotes the master seed and the lowest single-effect case's count."""
    table = _block((ROOT / "docs" / "validation.md").read_text(encoding="utf-8"), "fresh")
    rows = {}
    for line in table.splitlines():
        cells = [x.strip() for x in line.strip("|").split("|")]
        if len(cells) == 8 and re.fullmatch(r"\d+/\d+", cells[3]):
            rows[(cells[1], cells[0])] = cells
    assert len(rows) == len(fresh["cases"])
    for c in fresh["cases"]:
        cells = rows[(c["robot"], c["case"].split("/")[-1])]
        ci = binomtest(c["passed"], c["n"]).proportion_ci(0.95, method="exact")
        assert cells[3] == f"{c['passed']}/{c['n']}"
        assert cells[4] == f"{100 * c['passed'] / c['n']:.0f} %"
        assert cells[5] == f"{100 * ci.low:.0f}–{100 * ci.high:.0f} %"
        # met: every seed of the case measured and the rate at its threshold
        met = c["n"] == c["seeds"] and c["passed"] >= THRESHOLDS[c["kind"]] * c["n"] - 1e-9
        assert cells[7] == ("yes" if met else "**no**")
    readme = _block((ROOT / "README.md").read_text(encoding="utf-8"), "fresh-summary")
    assert f"CTRPLAN_FRESH_SEED={fresh['master_seed']}" in readme
    singles = [c for c in fresh["cases"] if c["kind"] == "single"]
    low = min(singles, key=lambda c: (c["passed"] / c["n"], c["case"]))
    assert f"lowest {low['case']}: {low['passed']}/{low['n']}" in readme
    study = next(c for c in fresh["cases"] if c["kind"] == "study")
    assert f"the study's three effects named: {study['passed']}/{study['n']}" in readme


def test_every_form_of_the_fresh_cases_is_checked_outside_the_joint_families():
    """Each single or outside case of the benchmark is a form tests/test_foreign_forms.py fits
    with every family at once (its data are evidence only if no combination reproduces it)."""
    import importlib.util

    from tests.test_foreign_forms import FORMS

    spec = importlib.util.spec_from_file_location("bench_fresh", ROOT / "benchmarks" / "bench_fresh.py")
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    cases = {(c["robot"], c["case"].split("/")[-1]) for c in bench.CASES
             if c["kind"] in ("single", "outside")}
    assert cases <= set(FORMS), sorted(cases - set(FORMS))
