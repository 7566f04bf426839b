"""diagnose writes its report as a set (issue 24 item 6): on a full disk the output folder holds
either the previous report, complete and unchanged, or the new one, never a mix, and nothing
else is left behind; the command line says so in one line and exits 2.

A full disk is simulated by making the k-th file write raise ``OSError(ENOSPC)`` part-way (after
some bytes of that file), for a first, middle and last k, and by making a rename of the final swap fail. The
previous report's files are compared byte for byte with what was there before.
"""

from __future__ import annotations

import contextlib
import errno
import os
from pathlib import Path

import pytest

import ctrplan.calibration.report as report_mod
import ctrplan.io as io_mod
from ctrplan.calibration.diagnose import diagnose
from ctrplan.calibration.report import REPORT_FILES, write_report
from ctrplan.calibration.simulate import design, simulate
from ctrplan.cli import main
from ctrplan.errors import InputError
from ctrplan.robot import load_robot

#: report files every run writes (tip-only data: no residuals_arclength.png)
EXPECTED = {"report.json", "report.md", "calibrated.yaml", "calibrated_robot.yaml",
            "residuals_rotation.png", "residuals_insertion.png", "errors_by_step.png",
            "tip_paths.png"}


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """One small diagnosis (registration hidden); the arguments write_report got."""
    r = load_robot("seed1")
    q, sw = design(r, ["random_walk"], 64, sweeps=8, seed=3)
    data = simulate(r, q, {"registration": {"tx": 2.0, "ty": -1.0}}, sweep=sw, noise_mm=0.1,
                    seed=3)
    got = {}
    real = report_mod.write_report

    def capture(rep, data, out, **kw):
        got.update(rep=rep, data=data, **kw)
        return real(rep, data, out, **kw)

    mp = pytest.MonkeyPatch()
    mp.setattr(report_mod, "write_report", capture)
    try:
        out = tmp_path_factory.mktemp("first") / "report"
        diagnose(r, data, candidates=["registration"], learned_residual=False, nuisances=False,
                 out=out)
    finally:
        mp.undo()
    got["first"] = out
    return got


def _snapshot(folder: Path) -> dict[str, bytes]:
    """Every file under ``folder`` (relative path -> bytes)."""
    return {str(p.relative_to(folder)): p.read_bytes() for p in sorted(folder.rglob("*"))
            if p.is_file()}


def _write(run, out: Path) -> Path:
    return write_report(run["rep"], run["data"], out, base_pred=run["base_pred"],
                        final_pred=run["final_pred"], test=run["test"])


def _other_report(run):
    """The same report with another conclusion (so its files differ from the first run's)."""
    from dataclasses import replace

    return {**run, "rep": replace(run["rep"], conclusion="a different conclusion",
                                  error_after_mm=run["rep"].error_after_mm + 1.0)}


@contextlib.contextmanager
def _disk_full_at(k: int, name: str | None = None):
    """The k-th atomic file write (1-based; of files called ``name`` when given) fails with
    ENOSPC after writing part of its file."""
    real = io_mod.atomic_path
    count = {"n": 0}

    @contextlib.contextmanager
    def failing(path, suffix=None):
        with real(path, suffix) as tmp:
            count["n"] += name is None or Path(path).name == name
            if count["n"] == k:
                tmp.write_bytes(b"partial")
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(tmp))
            yield tmp

    mp = pytest.MonkeyPatch()
    mp.setattr(io_mod, "atomic_path", failing)
    try:
        yield count
    finally:
        mp.undo()


def test_first_run_writes_the_whole_set(run):
    out = run["first"]
    assert set(os.listdir(out)) == EXPECTED
    assert os.listdir(out.parent) == ["report"]          # no temporary folder left
    assert (out / "report.md").read_text().startswith("Held-out tip error")


#: the k-th write: report.json (1), calibrated.yaml (3), the first plot (5), the last plot (8)
@pytest.mark.parametrize("k", [1, 3, 5, len(EXPECTED)])
def test_full_disk_keeps_the_previous_report_complete(run, tmp_path, k):
    out = tmp_path / "report"
    _write(run, out)
    (out / "notes.txt").write_text("the user's own file")
    before = _snapshot(out)
    with _disk_full_at(k) as count, pytest.raises(InputError) as exc:
        _write(_other_report(run), out)
    assert count["n"] == k                               # it failed where we made it fail
    assert "No space left on device" in str(exc.value) and "--out" in str(exc.value)
    assert _snapshot(out) == before                      # old report, complete, unchanged
    assert sorted(os.listdir(tmp_path)) == ["report"]    # nothing new next to it


@pytest.mark.parametrize("k", [2, len(EXPECTED)])
def test_full_disk_on_a_first_run_leaves_nothing(run, tmp_path, k):
    out = tmp_path / "new" / "deeper" / "report"
    with _disk_full_at(k), pytest.raises(InputError):
        _write(run, out)
    assert os.listdir(tmp_path) == []


def test_failure_during_the_swap_rolls_back(run, tmp_path, monkeypatch):
    out = tmp_path / "report"
    _write(run, out)
    before = _snapshot(out)
    real = os.replace
    calls = {"n": 0}

    def replace(src, dst):
        if ".diagnose-" in str(Path(src).parent.name):   # moving a new file in
            calls["n"] += 1
            if calls["n"] == 3:
                raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(dst))
        return real(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    with pytest.raises(InputError):
        _write(_other_report(run), out)
    monkeypatch.undo()
    assert calls["n"] == 3
    assert _snapshot(out) == before
    assert os.listdir(tmp_path) == ["report"]


def test_new_report_replaces_the_whole_previous_set(run, tmp_path):
    out = tmp_path / "report"
    _write(run, out)
    (out / "residuals_arclength.png").write_bytes(b"from a run with measured shapes")
    (out / "notes.txt").write_text("kept")
    new = _other_report(run)
    _write(new, out)
    assert set(os.listdir(out)) == EXPECTED | {"notes.txt"}   # stale plot gone, user file kept
    assert "a different conclusion" in (out / "report.md").read_text()
    assert set(REPORT_FILES) >= EXPECTED
    assert os.listdir(tmp_path) == ["report"]


def test_cli_full_disk_one_line_exit_2(run, tmp_path, capsys):
    csv = tmp_path / "m.csv"
    assert main(["-q", "simulate", "--robot", "seed1", "--experiment", "random_walk", "--n", "64",
                 "--effect", "registration:tx=2", "--noise", "0.1", "--seed", "3",
                 "--out", str(csv)]) == 0
    out = tmp_path / "out"
    _write(run, out)
    before = _snapshot(out)
    capsys.readouterr()
    with _disk_full_at(3):
        code = main(["-q", "diagnose", "--robot", "seed1", "--data", str(csv), "--effects",
                     "registration", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2
    assert err.count("\n") == 1 and "No space left on device" in err and "Traceback" not in err
    assert _snapshot(out) == before
    assert sorted(os.listdir(tmp_path)) == ["m.csv", "out"]


def test_best_report_and_comparison_are_one_set(run, tmp_path):
    """``diagnose --best``: diagnose's report and best_model.* are replaced together."""
    from ctrplan.calibration.best import best_model

    out = tmp_path / "best"
    best_model("seed1", run["data"], out=out, learned=False,
               diagnose_kwargs=dict(candidates=["registration"], nuisances=False))
    names = set(os.listdir(out))
    assert names >= EXPECTED | {"best_model.json", "best_model.md", "best_candidates"}
    before = _snapshot(out)
    assert "best_candidates/calibrated.yaml" in before
    with _disk_full_at(1, "best_model.json"), pytest.raises(InputError):
        best_model("seed1", run["data"], out=out, learned=False, seed=1,
                   diagnose_kwargs=dict(candidates=["registration"], nuisances=False))
    assert _snapshot(out) == before
    assert os.listdir(tmp_path) == ["best"]


#: SIGKILL at the i-th rename of the swap: moving the previous set out (1st, 4th of 8) or the
#: new set in (9th: first new file, 12th, 16th: the last)
@pytest.mark.parametrize("kill_at", [1, 4, 9, 12, 16])
def test_sigkill_during_the_swap_is_recovered_on_the_next_write(run, tmp_path, kill_at):
    """A real SIGKILL (no finally block runs) part-way through the swap leaves the previous set
    split between `out` and the hidden backup folder; the next write into `out` (here: its
    recovery step alone, then a whole write) puts the previous set back, complete and byte for
    byte, removes the hidden folders, and then writes the new set."""
    import signal

    out = tmp_path / "report"
    _write(run, out)
    (out / "notes.txt").write_text("the user's own file")
    before = _snapshot(out)
    pid = os.fork()
    if pid == 0:                                   # the run that is killed
        try:
            real, n = os.replace, [0]

            def replace(src, dst):
                d, s = Path(dst).parent, Path(src).parent
                if ".previous-" in d.name or (d == out and ".diagnose-" in s.name):
                    n[0] += 1
                    if n[0] == kill_at:
                        os.kill(os.getpid(), signal.SIGKILL)
                return real(src, dst)

            os.replace = replace
            _write(_other_report(run), out)
        finally:
            os._exit(3)                            # not reached when killed
    import time

    deadline = time.monotonic() + 120.0            # a child stuck after fork fails, never hangs
    while True:
        done_pid, status = os.waitpid(pid, os.WNOHANG)
        if done_pid or time.monotonic() > deadline:
            break
        time.sleep(0.05)
    if not done_pid:
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        pytest.fail("the forked writer did not finish within 120 s")
    assert os.WIFSIGNALED(status) and os.WTERMSIG(status) == signal.SIGKILL
    assert len(os.listdir(tmp_path)) >= 2          # the hidden folders the killed run left
    done = report_mod.recover(out, REPORT_FILES)
    assert len(done) == 1 and "restored the previous report set" in done[0]
    assert _snapshot(out) == before                # the previous set, complete, unchanged
    assert os.listdir(tmp_path) == ["report"]
    _write(_other_report(run), out)                # and the next write goes through
    assert "a different conclusion" in (out / "report.md").read_text()
    assert os.listdir(tmp_path) == ["report"]


def test_recovery_leaves_a_live_runs_folders_alone(tmp_path):
    """Hidden folders whose pid runs now belong to a diagnose still writing: left alone."""
    out = tmp_path / "report"
    out.mkdir()
    live = tmp_path / f".report.previous-{os.getppid()}-abc"
    live.mkdir()
    (live / "report.json").write_text("{}")
    assert report_mod.recover(out, REPORT_FILES) == []
    assert (live / "report.json").exists() and not (out / "report.json").exists()
