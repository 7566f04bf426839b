"""Every numeric command-line option is typed centrally (ctrplan/commands/_common.py): NaN,
infinities, digit separators and out-of-range values end with exit 2 and one short line, no
traceback, whatever the command; a huge bad value is quoted as an excerpt, never whole."""

from __future__ import annotations

import argparse
import re

import pytest

from ctrplan import cli
from ctrplan.commands import _common


def _subparsers(parser: argparse.ArgumentParser, prefix: tuple[str, ...] = ()):
    subs = [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]
    if not subs:
        yield prefix, parser
        return
    for sub in subs:
        for name, child in sub.choices.items():
            yield from _subparsers(child, (*prefix, name))


def _numeric_options():
    """(command words, option string, converter) for every numeric option of every command."""
    out = []
    for words, p in _subparsers(cli.build_parser()):
        for a in p._actions:
            if a.option_strings and a.type is not None and getattr(a.type, "__name__", "") in ("integer", "number"):
                out.append((words, a.option_strings[0], a.type))
    return out


NUMERIC = _numeric_options()


def test_no_bare_int_or_float_option():
    """No option is typed with Python's int/float (which read 'nan', 'inf' and '1_0')."""
    bare = [(w, a.option_strings) for w, p in _subparsers(cli.build_parser()) for a in p._actions
            if a.type in (int, float)]
    assert bare == []
    assert len(NUMERIC) >= 40     # the options of every command are covered


@pytest.mark.parametrize("bad", ["nan", "NaN", "inf", "-inf", "+Infinity", "1_0", "1e999",
                                 "\u0661", "0x10", "", "1,5", "9" * 100_000])
def test_every_numeric_option_refuses(capsys, bad):
    for words, opt, _conv in NUMERIC:
        rc = cli.main(["-q", *words, f"{opt}={bad}"])
        err = capsys.readouterr().err
        lines = err.strip().splitlines()
        assert rc == 2, (words, opt, bad, err)
        assert len(lines) == 1 and "Traceback" not in err, (words, opt, err)
        assert lines[0].startswith(f"ctrplan {' '.join(words)}: error: argument {opt}"), lines[0]
        assert len(lines[0]) < 400, (words, opt, len(lines[0]))


def test_strict_parsers_against_reference_grammar():
    """parse_float / parse_int accept exactly the decimal ASCII grammar (an independent regular
    expression written here) and finite values; everything float()/int() would also read beyond
    it is refused."""
    ref_float = re.compile(r"\A[+-]?(\d+(\.\d*)?|\.\d+)([eE][+-]?\d+)?\Z", re.ASCII)
    ref_int = re.compile(r"\A[+-]?\d+\Z", re.ASCII)
    samples = ["1", "-2", "+3", "1.5", ".5", "5.", "-2e3", "2E-3", "1e999", "1_0", "1__0", "nan",
               "inf", "-Infinity", "\u0661\u0662", "\uff11", "0x1f", "1e", "e1", "--1", "1.2.3",
               " 7 ", "\t8\n", "1 0", "", " ", "1,5", "١"]
    for s in samples:
        t = s.strip()
        want_f = bool(ref_float.match(t)) and abs(float(t)) < float("inf")
        try:
            got = _common.parse_float(s)
            assert want_f, s
            assert got == float(t)
        except ValueError:
            assert not want_f, s
        want_i = bool(ref_int.match(t))
        try:
            got_i = _common.parse_int(s)
            assert want_i, s
            assert got_i == int(t)
        except ValueError:
            assert not want_i, s


def test_ranges_are_enforced():
    conv = _common.float_arg(0.0, 1.0, lo_open=True, hi_open=True)
    for v in ("0", "1", "-0.1", "1.0000001"):
        with pytest.raises(argparse.ArgumentTypeError, match="must be > 0 and < 1"):
            conv(v)
    assert conv("0.5") == 0.5
    with pytest.raises(argparse.ArgumentTypeError, match="must be >= 2"):
        _common.POINTS("1")
    assert _common.POINTS("2") == 2


@pytest.mark.parametrize("argv, message", [
    (["diagnose", "--robot", "seed1", "--data", "x.csv", "--out", "o", "--bic-threshold", "nan"], "not finite"),
    (["diagnose", "--robot", "seed1", "--data", "x.csv", "--out", "o", "--min-gain", "nan"], "not finite"),
    (["diagnose", "--robot", "seed1", "--data", "x.csv", "--out", "o", "--holdout", "1.5"], "must be > 0 and < 1"),
    (["train", "--robot", "seed1", "--points", "1", "--out", "m.pt"], "must be >= 2"),
    (["simulate", "--robot", "seed1", "--noise", "-1", "--out", "m.csv"], "must be >= 0"),
    (["plan", "--scene", "airway", "--time", "0", "--out", "p.json"], "must be > 0"),
    (["plan-batch", "--targets", "examples", "--workers", "0", "--out", "o"], "must be >= 1"),
    (["scene", "from-labels", "x.nii", "--max-mb", "inf", "--out", "o"], "not finite"),
    (["shape", "--robot", "seed1", "--configs", "c.csv", "--out", "s.npz", "--max-mb", "-1"], "must be > 0"),
])
def test_named_options(capsys, argv, message):
    rc = cli.main(["-q", *argv])
    err = capsys.readouterr().err
    assert rc == 2 and len(err.strip().splitlines()) == 1 and message in err, err


def test_long_value_quoted_as_excerpt(capsys):
    value = "x" * 100_000
    rc = cli.main(["-q", "simulate", "--robot", "seed1", "--n", value, "--out", "m.csv"])
    err = capsys.readouterr().err
    assert rc == 2 and "(100000 characters)" in err and len(err) < 300, err[:500]
    # an invalid choice echoes a long token as an excerpt too
    rc = cli.main(["-q", "simulate", "--robot", "seed1", "--experiment", value, "--out", "m.csv"])
    err = capsys.readouterr().err
    assert rc == 2 and len(err) < 600 and "characters" in err, err[:700]


def test_excerpt():
    from ctrplan.io import excerpt

    assert excerpt("abc") == "'abc'"
    e = excerpt("y" * 1000)
    assert e.startswith("'" + "y" * 40 + "...") and "(1000 characters)" in e and len(e) < 80
    assert "digits" in excerpt(10 ** 5000)


def test_numbers_inside_string_options_are_strict(capsys):
    """Options that carry numbers in text (--margin, --target, --start, --effect, design's
    MIN,MAX pairs) read them strictly too, and quote an excerpt of a bad value."""
    from ctrplan.commands.design import _pair
    from ctrplan.commands.plan import parse_margin
    from ctrplan.errors import InputError
    from ctrplan.shape.effects import parse_effect_arg

    assert parse_margin("0.5") == 0.5 and parse_margin("auto") is None
    assert parse_effect_arg("clearance:length=8")[1] == {"length": 8.0}
    for call in (lambda: parse_margin("1_0"), lambda: parse_margin("\u0661"),
                 lambda: parse_effect_arg("clearance:length=1_0"),
                 lambda: _pair("0_1,0.2", "--curvature", (0.0, 0.08))):
        with pytest.raises(InputError):
            call()
    with pytest.raises(InputError) as exc:
        parse_margin("m" * 100_000)
    assert len(str(exc.value)) < 200
    rc = cli.main(["-q", "simulate", "--robot", "seed1", "--n", "5", "--effect", "clearance:length=1_0",
                   "--out", "m.csv"])
    err = capsys.readouterr().err
    assert rc == 2 and "not a number: '1_0'" in err, err


def test_every_error_message_quotes_an_excerpt(tmp_path, capsys):
    """InputError itself cuts any over-long run of characters (a 100,000-character key or value
    from a file), so no reader can echo a huge value whole; file paths stay whole."""
    from ctrplan.errors import InputError

    e = InputError("r.yaml", "k" * 1000, "unknown key " + "v" * 100_000)
    assert len(str(e)) < 250 and "(1000 characters)" in str(e) and "(100000 characters)" in str(e)
    path = "/tmp/" + "d" * 300 + "/x.csv"
    assert path in str(InputError(path, "", f"cannot write {path}"))
    robot = tmp_path / "r.yaml"
    robot.write_text("name: r\ntubes:\n  - {od: " + "z" * 100_000 + ", id: 0.8, straight_length: 100, "
                     "curved_length: 50, curvature: 0.01, youngs_modulus: 60000, poisson_ratio: 0.3}\n")
    rc = cli.main(["-q", "shape", "--robot", str(robot), "--configs", str(tmp_path / "c.csv"),
                   "--out", str(tmp_path / "s.npz")])
    err = capsys.readouterr().err
    assert rc == 2 and len(err) < 300 + len(str(robot)) and "characters)" in err, err[:400]
