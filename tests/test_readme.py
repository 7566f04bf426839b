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
ROOT = README.parent
#: the documents whose every number must come from a generated block, with the blocks each
#: must hold (written by `ctrplan bench --readme README.md [--no-run]` from benchmarks/results/)
DOCS = {"README.md": ("glance", "fresh-summary"),
        "docs/performance.md": ("perf-summary", "bench", "hard", "hard-summary"),
        "docs/validation.md": ("validation", "real-robot", "fresh")}
#: numbers outside generated blocks, code and link targets that are names, versions, units or
#: citations, not measurements (each a phrase as it stands in the documents, with the reason)
NOT_MEASURED = (
    r"\bseed1\b",                 # the shipped robot's name
    r"\bt01\b",                   # the target-id alias named in the text
    r"Python >= 3\.10",            # supported versions
    r"CC BY 4\.0", r"BSD-3-Clause",  # licence names
    r"MNI152 ICBM 2009a", r"\bMNI152\b",  # the template's name
    r"IROS 2019",                  # a citation
    r"1/clearance", r"1/mm",       # a formula's name, a unit
    r"m/s\^2",                     # a unit
    r"\b3D Slicer\b",              # a program's name
)


def _block(text: str, name: str) -> str | None:
    m = re.search(rf"<!-- {re.escape(name)}:start -->\n(.*?)<!-- {re.escape(name)}:end -->", text, re.S)
    return None if m is None else m.group(1)


def _doc(rel: str) -> str:
    return (ROOT / rel).read_text(encoding="utf-8")


def hand_typed_numbers(text: str) -> list[str]:
    """Lines with a digit outside generated blocks, fenced code, code spans, link targets and
    HTML comments that is not part of a NOT_MEASURED phrase."""
    text = re.sub(r"<!-- ([\w-]+):start -->.*?<!-- \1:end -->", "", text, flags=re.S)
    text = re.sub(r"```.*?```", "", text, flags=re.S)
    text = re.sub(r"<!--.*?-->", "", text, flags=re.S)
    text = re.sub(r"`[^`]*`", "", text)
    text = re.sub(r"\]\([^)]*\)", "]", text)
    bad = []
    for line in text.splitlines():
        rest = line
        for pat in NOT_MEASURED:
            rest = re.sub(pat, "", rest)
        if re.search(r"\d", rest):
            bad.append(line)
    return bad


def stale_blocks(text: str, blocks: dict[str, str]) -> list[str]:
    """Names of the generated blocks in ``text`` that differ from what the generator writes."""
    return [name for name, md in blocks.items()
            if (got := _block(text, name)) is not None and got.strip() != md.strip()]


def test_generated_blocks_match_the_committed_json():
    """Every generated block of README.md, docs/performance.md and docs/validation.md is what
    the committed JSON in benchmarks/results/ (and docs/validation.yaml) gives now (the
    oracle: the JSON the benches wrote; the documents' text is not trusted)."""
    from ctrplan.commands.bench import readme_blocks

    blocks = readme_blocks(ROOT / "benchmarks" / "results")
    placed = set()
    for rel, required in DOCS.items():
        text = _doc(rel)
        for name in required:
            assert _block(text, name) is not None, f"{rel} lacks the generated block {name!r}"
        stale = stale_blocks(text, blocks)
        assert not stale, (f"{rel}: blocks {stale} differ from benchmarks/results/: run "
                           "`ctrplan bench --readme README.md --no-run`")
        placed |= {n for n in blocks if _block(text, n) is not None}
    assert placed == set(blocks), f"generated but in no document: {sorted(set(blocks) - placed)}"


@pytest.mark.parametrize("rel", list(DOCS))
def test_no_number_without_a_generated_source(rel):
    bad = hand_typed_numbers(_doc(rel))
    assert not bad, f"{rel}: hand-typed numbers (put them in a generated block):\n" + "\n".join(bad)


def test_the_number_checks_fail_on_a_hand_typed_number():
    """The two checks above catch a number typed into the text or into a block."""
    from ctrplan.commands.bench import readme_blocks

    text = _doc("docs/performance.md")
    assert hand_typed_numbers(text.replace("## Every suite\n", "## Every suite\n\nIt plans in 0.2 s.\n"))
    assert not hand_typed_numbers("Plans with `--time 5` to t01 on seed1.\n")
    blocks = readme_blocks(ROOT / "benchmarks" / "results")
    forged = text.replace("<!-- perf-summary:start -->\n", "<!-- perf-summary:start -->\nplans 240/240\n")
    assert stale_blocks(forged, blocks) == ["perf-summary"]
    assert stale_blocks(text, blocks) == []


# ----------------------------------------------------------------------------- docs/validation.md
def _claims() -> list[dict]:
    from ctrplan.commands.bench import load_claims

    return load_claims(ROOT / "docs" / "validation.yaml")


def _function_source(path: Path, name: str) -> str | None:
    import ast

    src = path.read_text(encoding="utf-8")
    for node in ast.walk(ast.parse(src)):
        if isinstance(node, ast.FunctionDef) and node.name == name:
            first = min([d.lineno for d in node.decorator_list] + [node.lineno])
            return "\n".join(src.splitlines()[first - 1:node.end_lineno])   # with decorators
    return None


def test_every_claim_names_a_test_that_exists_runs_in_ci_and_asserts_the_threshold():
    """Each claim of docs/validation.yaml names tests/<file>::<test> that exists, is collected by
    `make test` or `make test-stat` (both run by .ci/run), is not skipped outright, and whose
    source contains the claim's ``asserts`` text (the threshold as the test writes it)."""
    ci = (ROOT / ".ci" / "run").read_text(encoding="utf-8")
    assert "make test " in ci and "make test-stat " in ci
    make = (ROOT / "Makefile").read_text(encoding="utf-8")
    assert "$(PY) -m pytest -q $(PYTEST_ARGS)" in make and "-m statistical" in make
    claims = _claims()
    assert len(claims) >= 10
    for c in claims:
        path, _, name = c["test"].partition("::")
        f = ROOT / path
        assert f.is_file() and f.parent.name == "tests" and f.name.startswith("test_"), c["test"]
        body = _function_source(f, name)
        assert body is not None, f"{c['test']}: no such test"
        assert "pytest.mark.skip(" not in body and "@pytest.mark.skip\n" not in body, c["test"]
        assert c["asserts"] in body or any(re.search(rf"\b{re.escape(n)}\b", body)
                                          for n in _defined_with(f, c["asserts"])), (
            f"{c['test']}: {c['asserts']!r} is neither in the test nor in a helper or constant "
            "it uses")


def _defined_with(path: Path, text: str) -> list[str]:
    """Names of the top-level functions and constants of ``path`` whose source contains
    ``text`` (the helper or constant a test asserts its threshold through)."""
    import ast

    src = path.read_text(encoding="utf-8")
    out = []
    for node in ast.parse(src).body:
        seg = ast.get_source_segment(src, node) or ""
        if text not in seg:
            continue
        if isinstance(node, ast.FunctionDef):
            out.append(node.name)
        elif isinstance(node, (ast.Assign, ast.AnnAssign)):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            out += [t.id for t in targets if isinstance(t, ast.Name)]
    return out


def test_the_claim_check_fails_on_a_missing_test(tmp_path):
    body = _function_source(ROOT / "tests" / "test_physics.py", "test_no_such_test_in_this_file")
    assert body is None
    body = _function_source(ROOT / "tests" / "test_physics.py",
                            "test_compliant_model_matches_tight_scipy_solution_at_default_step")
    assert body is not None and "err < 1e-5" in body and "SIM_BOUND_MM" not in body
    assert _defined_with(ROOT / "tests" / "test_physics.py", "err < 7e-9") == []
    assert "SIM_BOUND_MM" in _defined_with(ROOT / "tests" / "test_learned.py", "SIM_BOUND_MM")
