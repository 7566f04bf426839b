"""Every command in the README's command-line block runs, in order, in a fresh folder."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

README = Path(__file__).resolve().parents[1] / "README.md"


def readme_commands() -> list[str]:
    text = README.read_text(encoding="utf-8")
    block = re.search(r"<!-- readme-commands -->\s*```bash\n(.*?)```", text, re.S)
    assert block, "README has no readme-commands block"
    return [ln.strip() for ln in block.group(1).splitlines() if ln.strip() and not ln.startswith("#")]


def test_readme_mentions_the_two_commands():
    text = README.read_text(encoding="utf-8")
    assert "make demo" in text and "make test" in text


def test_every_subcommand_appears_in_the_block():
    from ctrplan.cli import build_parser

    parser = build_parser()
    subs = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
    used = {shlex.split(c)[1] for c in readme_commands()}
    missing = set(subs.choices) - used - {"demo"}   # demo: run by test_demo.py (make demo)
    assert not missing, f"README block lacks: {sorted(missing)}"


def test_readme_commands_run(tmp_path):
    (tmp_path / "examples").symlink_to(README.parent / "examples")   # README paths are repo-relative
    (tmp_path / "anatomy").symlink_to(README.parent / "anatomy")
    for cmd in readme_commands():
        argv = shlex.split(cmd)
        assert argv[0] == "ctrplan"
        proc = subprocess.run([sys.executable, "-m", "ctrplan.cli", "--quiet", *argv[1:]], cwd=tmp_path,
                              capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, f"{cmd}\n{proc.stderr[-2000:]}"
    for name in ("sim.csv", "shapes.npz", "shapes.csv", "verdicts.csv", "airway.png", "plan.json",
                 "plan.html", "results/summary.csv", "measured.csv", "report/report.json",
                 "calibrated.npz", "model.pt", "learned.npz", "bench/bench.json", "labels_scene/scene.yaml"):
        assert (tmp_path / name).exists(), name


# ----------------------------------------------------------------------------- generated numbers
#: README sections whose measured numbers must all come from generated blocks
GENERATED_SECTIONS = ("## Planning safely", "## Performance")
#: blocks that must be present (written by `ctrplan bench --readme README.md [--no-run]`)
REQUIRED_BLOCKS = ("bench", "perf-summary", "hard", "hard-summary", "real-robot")
#: numbers outside generated blocks that are settings, names or references, not measurements
#: (each a phrase as it stands in the README)
NOT_MEASURED = (r"from 2 to 40 points", r"\bp99\b", r"0 for physics", r"margin 0\b", r"10 s cap",
                r"\bseed1\b", r"issue 18\b", r"2-vCPU", r"IROS 2019", r"1/clearance",
                r"500 points per shape, 10 states per edge", r"x1\.5")


def _section(text: str, title: str) -> str:
    a = text.index(title)
    b = text.find("\n## ", a + len(title))
    return text[a:b if b >= 0 else len(text)]


def _block(text: str, name: str) -> str | None:
    m = re.search(rf"<!-- {re.escape(name)}:start -->\n(.*?)<!-- {re.escape(name)}:end -->", text, re.S)
    return None if m is None else m.group(1)


def test_generated_blocks_match_the_committed_json():
    """Every generated block is what the committed JSON in benchmarks/results/ gives now (the
    oracle: the JSON the benches wrote; the README text is not trusted)."""
    from ctrplan.commands.bench import readme_blocks

    text = README.read_text(encoding="utf-8")
    blocks = readme_blocks(README.parent / "benchmarks" / "results")
    for name in REQUIRED_BLOCKS:
        assert _block(text, name) is not None, f"README lacks the generated block {name!r}"
    for name, md in blocks.items():
        got = _block(text, name)
        assert got is not None, f"README lacks <!-- {name}:start --> ... <!-- {name}:end -->"
        assert got.strip() == md.strip(), (
            f"README block {name!r} differs from benchmarks/results/: run "
            "`ctrplan bench --readme README.md --no-run`")
    assert set(REQUIRED_BLOCKS) - {"real-robot"} <= set(blocks), "committed benchmark JSON missing"


def test_no_number_in_the_planning_and_performance_sections_without_a_generated_source():
    """Outside generated blocks, code spans and link targets, a digit in these sections must be
    part of a listed setting/name phrase."""
    text = README.read_text(encoding="utf-8")
    bad = []
    for title in GENERATED_SECTIONS:
        sec = _section(text, title)
        sec = re.sub(r"<!-- ([\w-]+):start -->.*?<!-- \1:end -->", "", sec, flags=re.S)
        sec = re.sub(r"`[^`]*`", "", sec)
        sec = re.sub(r"\]\([^)]*\)", "]", sec)
        for line in sec.splitlines():
            rest = line
            for pat in NOT_MEASURED:
                rest = re.sub(pat, "", rest)
            if re.search(r"\d", rest):
                bad.append(line)
    assert not bad, "hand-typed numbers (put them in a generated block):\n" + "\n".join(bad)


def test_the_number_checks_fail_on_a_hand_typed_number(tmp_path):
    """The two checks above catch a number typed into the section or into a block."""
    global README
    text = README.read_text(encoding="utf-8")
    fake = tmp_path / "README.md"
    (tmp_path / "benchmarks").symlink_to(README.parent / "benchmarks")
    orig = README
    try:
        README = fake
        fake.write_text(text.replace("## Performance\n", "## Performance\n\nIt plans in 0.2 s.\n"),
                        encoding="utf-8")
        with pytest.raises(AssertionError, match="hand-typed"):
            test_no_number_in_the_planning_and_performance_sections_without_a_generated_source()
        fake.write_text(text.replace("<!-- perf-summary:start -->\n",
                                     "<!-- perf-summary:start -->\nplans 240/240\n"), encoding="utf-8")
        with pytest.raises(AssertionError, match="differs"):
            test_generated_blocks_match_the_committed_json()
    finally:
        README = orig
