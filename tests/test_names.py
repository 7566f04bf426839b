"""One name per value (issue 37, item 4): the table of names against the code and the docs.

``ctrplan/commands/_names.py`` says which command-line flag, Python argument and file key name the
same value. Checked here, each against its own source: every row's flag is an option of each
command's argparse parser, its argument a parameter (or dataclass field) of the Python object it
names, its key a key of ``PlanResult.to_json()``; docs/conventions.md prints the same rows. And
the errors: a Python caller reads the argument's name, never a flag; the command line reads the
flag, never the Python name.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import re
from pathlib import Path

import numpy as np
import pytest

from ctrplan.commands._names import FLAGS, TABLES, for_command_line, markdown
from ctrplan.errors import ArgumentError, InputError

DOCS = Path(__file__).resolve().parents[1] / "docs" / "conventions.md"


def _resolve(where: str):
    module, _, qual = where.partition(":")
    obj = importlib.import_module(module)
    for part in qual.split("."):
        obj = getattr(obj, part)
    return obj


def _options(command: str) -> set[str]:
    from ctrplan.cli import build_parser

    parser = build_parser()
    for word in command.split():      # "scene reach": a subcommand's subcommand
        sub = next(a for a in parser._actions if a.__class__.__name__ == "_SubParsersAction")
        parser = sub.choices[word]
    return set(parser._option_string_actions)


def _plan_json() -> dict:
    from ctrplan.planning.result import PlanResult, PlanStatus

    return PlanResult(success=False, status=PlanStatus.TIMEOUT, message="", path=np.zeros((0, 4)),
                      backbones=np.zeros((0, 2, 3)), tip_path=np.zeros((0, 3)),
                      target=np.zeros(3), tip_error_mm=np.nan, tip_error_physics_mm=np.nan,
                      min_clearance_mm=np.nan, planning_time_s=0.0, timings={}, counts={},
                      planner="rrtconnect", seed=0, robot="r", model="physics", scene="s",
                      tolerance_mm=1.0, time_limit_s=5.0).to_json()


@pytest.mark.parametrize("row", [r for rows in TABLES.values() for r in rows], ids=lambda r: r.flag or r.argument)
def test_each_row_names_what_exists(row):
    if row.flag:
        for command in row.commands.split(", "):
            assert row.flag in _options(command), (row.flag, command)
    target = _resolve(row.where)
    if dataclasses.is_dataclass(target):
        names = {f.name for f in dataclasses.fields(target)}
    else:
        names = set(inspect.signature(target).parameters)
    assert row.argument in names, (row.argument, row.where, sorted(names))
    if row.key and row.file == "plan.json":
        assert row.key in _plan_json(), row.key


def test_one_flag_per_argument():
    seen: dict[str, str] = {}
    for rows in TABLES.values():
        for r in rows:
            if r.flag:
                assert seen.setdefault(r.argument, r.flag) == r.flag, r
    assert FLAGS == seen


@pytest.mark.parametrize("table", sorted(TABLES))
def test_the_docs_print_the_table(table):
    text = DOCS.read_text(encoding="utf-8")
    block = re.search(rf"<!-- names:{table} -->\n(.*?)<!-- /names -->", text, re.S)
    assert block, f"docs/conventions.md has no names table {table}"
    lines = block.group(1).strip().splitlines()[2:]        # after the header and its rule
    assert lines == markdown(TABLES[table])


def test_errors_are_mapped_for_the_command_line():
    exc = ArgumentError("start", "the start is bistable: give its `branch`, or the `start` of a "
                                 "plan.json; `unknown_name` stays, and so does time_limit")
    assert str(exc).startswith("start: ") and "--" not in str(exc)
    cli = for_command_line(exc)
    assert str(cli) == ("--start: the start is bistable: give its --branch, or the --start of a "
                        "plan.json; `unknown_name` stays, and so does time_limit")
    plain = InputError("plan.json", "branch", "must be -1, 0 or +1")
    assert for_command_line(plain) is plain


@pytest.mark.parametrize("call,argument", [
    (dict(time_limit=0), "time_limit"),
    (dict(tolerance_mm=-1.0), "tolerance_mm"),
    (dict(seed=-3), "seed"),
    (dict(target=[0.0, 0.0]), "target"),
    (dict(objective="fast"), "objective"),
    (dict(planner="prm"), "planner"),
    (dict(model="no_such_model"), "model"),
])
def test_python_callers_read_the_argument_never_a_flag(call, argument):
    from ctrplan.planning.plan import plan_to_target

    kw = dict(robot="seed1", scene="airway", target=[0.0, 0.0, 100.0])
    kw.update(call)
    with pytest.raises(InputError) as exc:
        plan_to_target(**kw)
    assert str(exc.value).startswith(f"{argument}: ") and "--" not in str(exc.value), str(exc.value)


def test_config_and_start_errors_name_the_argument():
    from ctrplan.planning.arguments import check_start
    from ctrplan.planning.planner import PlannerConfig
    from ctrplan.planning.stability import check_branch
    from ctrplan.robot import load_robot

    for bad, argument in ((lambda: PlannerConfig(margin_mm=-1.0), "margin_mm"),
                          (lambda: PlannerConfig(max_states=0), "max_states"),
                          (lambda: check_start([0.0] * 5, load_robot("seed1")), "start"),
                          (lambda: check_branch(2), "branch")):
        with pytest.raises(InputError) as exc:
            bad()
        assert str(exc.value).startswith(f"{argument}: ") and "--" not in str(exc.value)


def test_the_command_line_reads_its_flags(tmp_path, capsys):
    """A library error reaches the command line with the flag: a start outside the joint
    constraints (checked by the planner, after parsing) and a target beyond the plausible range."""
    from ctrplan.cli import main

    out = tmp_path / "p.json"
    code = main(["-q", "plan", "--scene", "airway", "--target", "1e7,0,0", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and "--target: " in err and "target:" not in err.replace("--target:", ""), err
    code = main(["-q", "plan", "--scene", "airway", "--target", "t01", "--start",
                 "0,0,0,-50,-100,-150", "--out", str(out)])
    err = capsys.readouterr().err
    assert code == 2 and len(err.strip().splitlines()) == 1, err
    assert "--start" in err and "start:" not in err.replace("--start:", ""), err
