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


def test_bench_in_process_leaves_numba_usable(tmp_path):
    """`ctrplan bench` imports the suites into a process where numba is already loaded: pinning
    threads through NUMBA_NUM_THREADS there made numba refuse every later compile."""
    import numba
    import numpy as np

    from ctrplan.collision.field import FieldConfig, build_field

    threads = numba.get_num_threads()
    try:
        assert cli.main(["-q", "bench", "shape", "--quick", "--out", str(tmp_path)]) == 0
        assert numba.get_num_threads() == 1
        v = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])
        f = np.array([[0, 2, 1], [0, 1, 3], [0, 3, 2], [1, 2, 3]])
        field = build_field(v, f, FieldConfig(h_mm=0.5), watertight=True)   # the parallel splat
        assert np.isfinite(field.lb).all()

        @numba.njit
        def fresh(x):
            return x + 1

        assert fresh(1) == 2                                                 # a new compile
    finally:
        numba.set_num_threads(threads)


def test_a_suite_that_measures_nan_still_writes_strict_json(tmp_path, monkeypatch):
    """A value a suite could not measure (NaN) is written as null; the run's results are not
    lost to a traceback (strict JSON has no NaN)."""
    import json
    import types

    from ctrplan.commands import bench

    fake = types.SimpleNamespace(run=lambda quick=False: {
        "table": [{"case": "x", "ratio": float("nan"), "ok": 1.5}], "extra": [float("inf")]})
    monkeypatch.setattr(bench, "load_suite", lambda name: fake)
    assert cli.main(["-q", "bench", "shape", "--quick", "--out", str(tmp_path)]) == 0
    data = json.loads((tmp_path / "bench.json").read_text())
    suite = data["suites"]["shape"]
    assert suite["table"] == [{"case": "x", "ratio": None, "ok": 1.5}] and suite["extra"] == [None]
