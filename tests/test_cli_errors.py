"""Bad input to ``ctrplan shape``: exit code 2, one line on stderr naming the file and the
field, no traceback, no output file."""

from __future__ import annotations

import subprocess
import sys

import pytest

from ctrplan import cli

HEADER = "alpha1,alpha2,alpha3,beta1,beta2,beta3"
GOOD_ROW = "0.1,0.2,0.3,-150,-100,-50"


def _run(capsys, args):
    rc = cli.main(args)
    err = capsys.readouterr().err
    return rc, err


CASES = {
    # name: (configs text or None, robot, extra args, words the message must contain)
    "non-number": (f"{HEADER}\n0.1,abc,0.3,-150,-100,-50\n", "seed1", [], ["alpha2", "row 2"]),
    "wrong-column-count": (f"{HEADER}\n{GOOD_ROW}\n0.1,0.2,-150,-100,-50\n", "seed1", [], ["row 3"]),
    "missing-column": ("alpha1,alpha2,alpha3,beta1,beta2\n0,0,0,-150,-100\n", "seed1", [], ["beta3"]),
    "nan": (f"{HEADER}\n{GOOD_ROW}\nnan,0.2,0.3,-150,-100,-50\n", "seed1", [], ["alpha1", "row 3"]),
    "inf": (f"{HEADER}\n0.1,0.2,0.3,-inf,-100,-50\n", "seed1", [], ["beta1", "row 2"]),
    "constraint": (f"{HEADER}\n{GOOD_ROW}\n0,0,0,-50,-100,-150\n", "seed1", [], ["row 3", "constraint"]),
    "empty": ("", "seed1", [], ["header"]),
    "header-only": (f"{HEADER}\n", "seed1", [], ["rows"]),
    "unknown-robot": (f"{HEADER}\n{GOOD_ROW}\n", "no_such_robot", [], ["no_such_robot"]),
    "bad-points": (f"{HEADER}\n{GOOD_ROW}\n", "seed1", ["--points", "1"], ["--points"]),
}


@pytest.mark.parametrize("name", list(CASES))
def test_bad_input_exits_2_with_one_line(tmp_path, capsys, name):
    text, robot, extra, words = CASES[name]
    cfg = tmp_path / "c.csv"
    cfg.write_text(text)
    out = tmp_path / "out.npz"
    rc, err = _run(capsys, ["-q", "shape", "--robot", robot, "--configs", str(cfg), "--out", str(out), *extra])
    assert rc == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1, err
    assert "Traceback" not in err
    if name not in ("unknown-robot", "bad-points"):
        assert str(cfg) in lines[0]
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert not out.exists()
    assert [p.name for p in tmp_path.iterdir()] == ["c.csv"]      # no temporary left behind


@pytest.mark.parametrize("yaml_text,field", [
    ("name: r\ntubes: [ {od: 1\n", "line"),
    ("name: r\ntubes:\n  - {od: 1.0, id: 1.2, straight_length: 100, curved_length: 50, curvature: 0.01, "
     "youngs_modulus: 60000, poisson_ratio: 0.3}\n", "tubes[0].id"),
    ("name: r\ntubes:\n  - {od: 1.0, id: 0.8, straight_length: 100, curved_length: 50, curvature: 0.01, "
     "youngs_modulus: 60000, poisson_ratio: 0.3, colour: red}\n", "tubes[0].colour"),
])
def test_bad_robot_yaml(tmp_path, capsys, yaml_text, field):
    rp = tmp_path / "robot.yaml"
    rp.write_text(yaml_text)
    cfg = tmp_path / "c.csv"
    cfg.write_text("alpha1,beta1\n0,-10\n")
    out = tmp_path / "o.csv"
    rc, err = _run(capsys, ["-q", "shape", "--robot", str(rp), "--configs", str(cfg), "--out", str(out)])
    assert rc == 2
    assert len(err.strip().splitlines()) == 1 and str(rp) in err and field in err
    assert not out.exists()


def test_bad_output_suffix_and_missing_file(tmp_path, capsys):
    rc, err = _run(capsys, ["-q", "shape", "--robot", "seed1", "--configs", str(tmp_path / "nope.csv"),
                            "--out", str(tmp_path / "o.npz")])
    assert rc == 2 and "nope.csv" in err and "not found" in err
    cfg = tmp_path / "c.csv"
    cfg.write_text(f"{HEADER}\n{GOOD_ROW}\n")
    rc, err = _run(capsys, ["-q", "shape", "--robot", "seed1", "--configs", str(cfg),
                            "--out", str(tmp_path / "o.txt")])
    assert rc == 2 and "--out" in err
    assert not (tmp_path / "o.txt").exists() and not (tmp_path / "o.npz").exists()


def test_real_process_prints_no_traceback(tmp_path):
    """The same through a real process: exit status 2 and a single stderr line."""
    cfg = tmp_path / "c.csv"
    cfg.write_text(f"{HEADER}\n0.1,0.2,0.3,-150,-100\n")
    out = tmp_path / "o.npz"
    proc = subprocess.run([sys.executable, "-m", "ctrplan.cli", "shape", "--robot", "seed1",
                           "--configs", str(cfg), "--out", str(out)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert str(cfg) in proc.stderr and "row 2" in proc.stderr
    assert not out.exists()
