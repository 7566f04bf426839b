"""benchmarks/bench_fresh.py's machinery (fast: its diagnose runs replaced by a stand-in): the
seeds come from the printed master seed and are never development seeds, a killed run resumes
where it stopped, the summary counts what the records say, and ``ctrplan bench fresh`` runs it
into its own results file."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture()
def bench(monkeypatch):
    spec = importlib.util.spec_from_file_location("bench_fresh_t", ROOT / "benchmarks" / "bench_fresh.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    calls = []

    def fake(case, seed):                     # passes on even seeds, named as the case says
        calls.append((case["case"], seed))
        ok = seed % 2 == 0
        named = [case["named"]] if case["kind"] == "single" and ok else []
        if case["kind"] == "study":
            named = ["clearance", "friction", "torsion"] if ok else ["torsion"]
        return {"seed": seed, "ok": ok, "effects": named, "cut": 0.9 if ok else 0.1,
                "error_before_mm": 1.0, "error_after_mm": 0.1,
                "unexplained": case["kind"] == "outside" and ok, "elapsed_s": 0.0}
    monkeypatch.setattr(mod, "run_one", fake)
    monkeypatch.setenv(mod.ENV, "12345")
    mod.calls = calls
    return mod


def test_seeds_are_reproducible_and_never_development_seeds(bench, monkeypatch):
    a = bench.fresh_seeds(12345, 30)
    assert a == bench.fresh_seeds(12345, 30) and a != bench.fresh_seeds(12346, 30)
    assert len(set(a)) == 30 and not set(a) & set(bench.DEVELOPMENT_SEEDS)
    assert all(s >= 10_000 for s in a)
    assert bench.master_seed({bench.ENV: "77"}) == (77, True)
    drawn, given = bench.master_seed({})
    assert not given and 0 <= drawn < 2**31


def test_a_killed_run_resumes_where_it_stopped(bench, tmp_path, capsys):
    out = tmp_path / "fresh.json"
    cases = ["registration", "none", "study"]
    real = bench.run_one

    def dies_after_four(case, seed):
        if len(bench.calls) == 4:
            raise KeyboardInterrupt
        return real(case, seed)
    bench.run_one = dies_after_four
    with pytest.raises(KeyboardInterrupt):
        bench.run(seeds=5, cases=cases, out=out)
    assert "master seed 12345" in capsys.readouterr().out
    lines = (tmp_path / "fresh.journal.jsonl").read_text().splitlines()
    assert len(lines) == 4
    with open(tmp_path / "fresh.journal.jsonl", "a") as f:       # a torn last line
        f.write('{"master_seed": 12345, "case": "no')
    bench.run_one = real
    res = bench.run(seeds=5, cases=cases, out=out)
    assert len(bench.calls) == 5 + 5 + 3                          # 4 done before, 9 now
    assert len(set(bench.calls)) == len(bench.calls)             # nothing run twice
    assert res["complete"] and json.loads(out.read_text())["complete"]
    # the journal gone: the summary's own records resume a run
    (tmp_path / "fresh.journal.jsonl").unlink()
    bench.calls.clear()
    bench.run(seeds=5, cases=cases, out=out)
    assert bench.calls == []


def test_the_summary_counts_the_records(bench, tmp_path):
    res = bench.run(seeds=6, cases=["registration", "study"], out=tmp_path / "f.json")
    reg = next(c for c in res["cases"] if c["case"] == "registration")
    seeds = bench.fresh_seeds(12345, 6)
    assert [r["seed"] for r in reg["records"]] == seeds
    k = sum(s % 2 == 0 for s in seeds)
    assert (reg["n"], reg["passed"]) == (6, k)
    lo, hi = reg["ci95"]
    assert 0.0 <= lo <= k / 6 <= hi <= 1.0
    assert reg["met"] == (k >= 0.85 * 6)
    study = next(c for c in res["cases"] if c["case"] == "study")
    assert study["n"] == 3 and [r["seed"] for r in study["records"]] == seeds[:3]
    assert res["revisions"] and "commit" in res["revisions"][0]


def test_clopper_pearson_against_scipy(bench):
    from scipy.stats import binomtest

    for k, n in ((0, 30), (1, 30), (26, 30), (30, 30), (2, 3)):
        ci = binomtest(k, n).proportion_ci(0.95, method="exact")
        assert bench.clopper_pearson(k, n) == pytest.approx((ci.low, ci.high), abs=1e-12)


def test_ctrplan_bench_fresh_writes_its_own_results(bench, tmp_path, monkeypatch):
    from ctrplan import cli
    from ctrplan.commands import bench as cmd

    monkeypatch.setattr(cmd, "load_suite", lambda name: bench)
    assert cli.main(["-q", "bench", "fresh", "--quick", "--out", str(tmp_path)]) == 0
    got = json.loads((tmp_path / "fresh.json").read_text())
    assert got["master_seed"] == 12345 and len(got["seeds"]) == 2
    assert not (tmp_path / "bench.json").exists()                # not mixed into bench.json
