"""``ctrplan bench --readme``: the README's performance section is written by the benchmark."""

from __future__ import annotations

import pytest

from ctrplan import cli
from ctrplan.commands.bench import END, START, splice
from ctrplan.errors import InputError


def test_splice_replaces_only_between_the_markers():
    text = f"# T\nbefore\n{START}\nold 1\nold 2\n{END}\nafter\n"
    out = splice(text, "| a |\n|---|\n| 1 |\n", "R.md")
    assert out == f"# T\nbefore\n{START}\n| a |\n|---|\n| 1 |\n{END}\nafter\n"
    assert splice(out, "x", "R.md") == f"# T\nbefore\n{START}\nx\n{END}\nafter\n"


@pytest.mark.parametrize("text", ["no markers\n", f"{END}\n{START}\n", f"{START}\nonly start\n"])
def test_splice_without_markers_names_the_file(text):
    with pytest.raises(InputError, match="R.md"):
        splice(text, "x", "R.md")


def test_bench_refuses_a_readme_without_markers_before_running(tmp_path, capsys):
    readme = tmp_path / "R.md"
    readme.write_text("# nothing to replace\n")
    rc = cli.main(["bench", "shape", "--quick", "--out", str(tmp_path / "b"), "--readme", str(readme)])
    err = capsys.readouterr().err.strip()
    assert rc == 2 and len(err.splitlines()) == 1 and "R.md" in err
    assert not (tmp_path / "b").exists()          # nothing ran, nothing half-written
    assert readme.read_text() == "# nothing to replace\n"


def test_bench_writes_its_tables_into_the_readme(tmp_path, capsys):
    readme = tmp_path / "R.md"
    readme.write_text(f"## Performance\n{START}\nstale\n{END}\n## Next\n")
    rc = cli.main(["bench", "shape", "--quick", "--out", str(tmp_path / "b"), "--readme", str(readme)])
    assert rc == 0
    text = readme.read_text()
    md = (tmp_path / "b" / "bench.md").read_text()
    assert "stale" not in text and md.strip() in text and text.endswith(f"{END}\n## Next\n")
    assert "Machine:" in text and "### shape" in text
