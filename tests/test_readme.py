"""Every command in the README's command-line block runs, in order, in a fresh folder."""

from __future__ import annotations

import re
import shlex
import subprocess
import sys
from pathlib import Path

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
