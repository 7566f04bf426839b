"""One name per value: each value's command-line flag, Python argument and file key, side by side.

The library names a value as its Python caller writes it (``time_limit``); the command line
as its user types it (``--time``); a file by its key (``time_limit_s`` in plan.json). The
table here is the one place that says which names belong together, and docs/conventions.md
("Names") prints it (tests/test_names.py holds the two, the argument parsers, the Python
signatures and ``PlanResult.to_json()`` against each other).

Errors. A library error about an argument (:class:`~ctrplan.errors.ArgumentError`) names the
argument, and other arguments in its message between backticks; :func:`for_command_line`
gives the command line the same error with its flags, so a Python caller never reads about
``--seed`` and a command-line user never about ``seed``. An argument without a flag keeps its
Python name. To add the names of another file (report.json, ...), add its rows: the mapping,
the docs table and the test follow.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from ctrplan.errors import ArgumentError, InputError


@dataclass(frozen=True)
class Name:
    """One value's names.

    flag : the command-line flag ("" when the command line has none).
    commands : the commands that take the flag (comma-separated).
    argument : the Python argument (or config field) holding the value.
    where : where the argument is: ``module:Qualified.name`` of a function (a parameter) or of
        a dataclass (a field).
    key : the key of the value in ``file`` ("" when the file does not record it).
    file : the file the key is in (plan.json, ...).
    note : what differs between the names, if anything (units, a default).
    """

    flag: str
    commands: str
    argument: str
    where: str
    key: str
    file: str
    note: str = ""


_PLANNER = "ctrplan.planning.planner:Planner"
_PLAN = "ctrplan.planning.planner:Planner.plan"
_CONFIG = "ctrplan.planning.planner:PlannerConfig"
_TIPGOAL = "ctrplan.planning.tipgoal:TipGoal"

#: Planning (``plan``, ``plan-batch``): the Python side is ``Planner(robot, scene, model,
#: PlannerConfig(...)).plan(target, seed=..., ...)``; the file is plan.json.
PLANNING: tuple[Name, ...] = (
    Name("--robot", "plan, plan-batch", "robot", _PLANNER, "robot", "plan.json",
         "the tube values themselves: robot_spec"),
    Name("--scene", "plan", "scene", _PLANNER, "scene", "plan.json"),
    Name("--model", "plan, plan-batch", "model", _PLANNER, "model", "plan.json",
         "physics, rigid, learned or a model file"),
    Name("--margin", "plan, plan-batch", "margin_mm", _CONFIG, "margin_mm", "plan.json",
         "auto on the command line is None in Python; plan.json: the margin used and margin_auto; "
         "a plan-batch job's field margin (auto or mm, as text)"),
    Name("--stability-margin", "plan", "stability_margin",
         "ctrplan.planning.validator:ValidatorConfig", "", "plan.json",
         "PlannerConfig(validator=ValidatorConfig(stability_margin=...)); plan.json: stability per state"),
    Name("--target", "plan", "target", _PLAN, "target", "plan.json",
         "the command line also takes a target's name"),
    Name("--start", "plan", "start", _PLAN, "path", "plan.json",
         "plan.json: path[0], the start used"),
    Name("--branch", "plan", "branch", "ctrplan.planning.stability:Start", "branch", "plan.json",
         "Start(q, branch); plan.json: branch per path state"),
    Name("--standoff", "plan", "standoff_mm", _TIPGOAL, "standoff_requested_mm", "plan.json",
         "TipGoal(standoff_mm=...); plan.json: standoff_mm is the standoff achieved"),
    Name("--approach", "plan", "direction", _TIPGOAL, "approach_direction", "plan.json",
         "normal on the command line: minus the snapped surface's normal (TipGoal.normal)"),
    Name("--cone", "plan", "cone_deg", _TIPGOAL, "cone_deg", "plan.json",
         "degrees; plan.json: direction_error_deg is the angle achieved"),
    Name("--seed", "plan", "seed", _PLAN, "seed", "plan.json"),
    Name("--planner", "plan, plan-batch", "planner", _PLAN, "requested_planner", "plan.json",
         "plan.json's planner is what solved it (direct for the straight edge)"),
    Name("--time", "plan, plan-batch", "time_limit", _PLAN, "time_limit_s", "plan.json",
         "seconds"),
    Name("--tolerance", "plan, plan-batch", "tolerance_mm", _PLAN, "tolerance_mm", "plan.json", "mm"),
    Name("--objective", "plan, plan-batch", "objective", _PLAN, "objective", "plan.json"),
    Name("--targets", "plan-batch", "targets", "ctrplan.planning.batch:read_targets", "", "plan.json",
         "a CSV (x,y,z[,scene,name][,standoff_mm,approach,cone_deg]) or examples"),
    Name("--scene", "plan-batch", "scenes", "ctrplan.planning.batch:read_targets", "scene",
         "plan.json", "the scenes whose targets are planned"),
    Name("--seeds", "plan-batch", "seeds", "ctrplan.planning.batch:make_jobs", "seed", "plan.json",
         "K on the command line: seeds 0..K-1"),
    Name("--workers", "plan-batch", "workers", "ctrplan.planning.batch:run_batch", "", "plan.json"),
    Name("--ray", "plan-batch", "ray_address", "ctrplan.planning.batch:run_batch", "", "plan.json"),
    Name("--out", "plan, plan-batch", "out", "ctrplan.planning.batch:run_batch", "", "plan.json",
         "plan writes the file, plan-batch a folder"),
)

_REACH = "ctrplan.planning.reach:ReachSettings"
_SAMPLE = "ctrplan.collision.surface:sample_surface"
_REGION = "ctrplan.planning.reach:region_points"
_MAP = "ctrplan.planning.reach:reach_map"

#: Reachability maps (``scene reach``): ``reach_map(ReachSettings(...), sample_surface(...),
#: out)``; the file is reach.csv (the flags shared with plan, such as --time, are in PLANNING).
REACH: tuple[Name, ...] = (
    Name("--points", "scene reach", "count", _SAMPLE, "point", "reach.csv",
         "reach.csv: point is each row's index"),
    Name("--region", "scene reach", "region", _REGION, "", "reach.csv",
         "target names or ids, comma-separated"),
    Name("--near-targets", "scene reach", "near_targets", _REGION, "", "reach.csv"),
    Name("--radius", "scene reach", "radius_mm", _SAMPLE, "", "reach.csv", "mm"),
    Name("--standoff", "scene reach", "standoff_mm", _REACH, "standoff_mm", "reach.csv",
         "mm; TipGoal's standoff_mm"),
    Name("--approach", "scene reach", "approach", _REACH, "", "reach.csv",
         "normal or X,Y,Z (scene frame); TipGoal's direction"),
    Name("--cone", "scene reach", "cone_deg", _REACH, "cone_deg", "reach.csv", "deg"),
    Name("--ik-seeds", "scene reach", "ik_seeds", _REACH, "", "reach.csv"),
)

_JOB = "ctrplan.planning.batch:Job"

#: Tip pose goals in plan-batch's targets CSV (no flag: a column per row): the Job's fields,
#: the job file's keys; the key here is the targets CSV's column
TARGETS: tuple[Name, ...] = (
    Name("", "plan-batch", "goal_standoff_mm", _JOB, "standoff_mm", "targets CSV",
         "as plan --standoff (TipGoal's standoff_mm); in job files and jobs.csv standoff_mm is "
         "the standoff achieved"),
    Name("", "plan-batch", "goal_approach", _JOB, "approach", "targets CSV",
         "as plan --approach: normal or a direction (X Y Z in the CSV, x,y,z in the Job)"),
    Name("", "plan-batch", "goal_cone_deg", _JOB, "cone_deg", "targets CSV",
         "as plan --cone, deg; job files: direction_error_deg is the angle achieved"),
)

#: every table of names (another file's rows go here too)
TABLES: dict[str, tuple[Name, ...]] = {"planning": PLANNING, "reach": REACH, "targets": TARGETS}

#: Python argument -> command-line flag
FLAGS: dict[str, str] = {n.argument: n.flag for rows in TABLES.values() for n in rows if n.flag}

_TICKED = re.compile(r"`([A-Za-z_][A-Za-z0-9_]*)`")


def flag_of(argument: str) -> str:
    """The command-line flag of a Python argument (the argument itself when it has none)."""
    return FLAGS.get(argument, argument)


def for_command_line(exc: InputError) -> InputError:
    """The error as the command line shows it: an ArgumentError's argument and every
    backticked argument of its message as their flags (a name without a flag stays as it is);
    any other error as it is."""
    if not isinstance(exc, ArgumentError):
        return exc
    message = _TICKED.sub(lambda m: FLAGS.get(m.group(1), m.group(0)), exc.message)
    return InputError(flag_of(exc.argument), exc.field, message)


def markdown(rows: tuple[Name, ...]) -> list[str]:
    """The rows as the lines of docs/conventions.md's table (after its header)."""
    def cell(text: str) -> str:
        return f"`{text}`" if text else "—"

    return [f"| {cell(n.flag)} | {n.commands} | {cell(n.argument)} | "
            f"`{n.where.split(':')[1]}` | {cell(n.key)} | {n.note} |" for n in rows]
