"""One vocabulary on the command line: model names, deprecated aliases, default outputs.

Model names are ``physics`` (torsionally compliant Cosserat rods) and ``rigid`` (torsionally
rigid, the "traditional" model) everywhere, plus ``learned`` or a model file where a command
takes one. The older name ``compliant`` (and ``diagnose``/``simulate``'s ``--base``, and
``diagnose``'s ``--test-fraction`` for ``--holdout``) still works and prints a one-line
deprecation message to stderr.
"""

from __future__ import annotations

import argparse
import sys

#: deprecated model name -> current name
MODEL_ALIASES = {"compliant": "physics"}

#: default ``--out`` of each command (docs/conventions.md, "Command line")
DEFAULT_OUT = {
    "plan": "plan.json", "shape": "shape.csv", "check": "verdicts.csv", "simulate": "measured.csv",
    "view": "plan.html", "diagnose": "report", "plan-batch": "batch", "design": "design",
    "scene show": "scene.png", "scene from-labels": "scene", "scene reach": "reach",
}


def deprecated(old: str, new: str) -> None:
    """One line on stderr: ``old`` still works, use ``new``."""
    print(f"ctrplan: {old} is deprecated; use {new}", file=sys.stderr)


def model_name(text: str) -> str:
    """A ``--model`` value with the deprecated names mapped to the current ones."""
    s = str(text)
    if s.strip().lower() in MODEL_ALIASES:
        new = MODEL_ALIASES[s.strip().lower()]
        deprecated(f"model name {s.strip()!r}", f"{new!r}")
        return new
    return s


def mechanics_model(text: str) -> str:
    """``--model`` of commands that take only a mechanics model: ``physics`` or ``rigid``."""
    s = model_name(text).strip().lower()
    if s not in ("physics", "rigid"):
        raise argparse.ArgumentTypeError(f"must be physics or rigid, got {text!r}")
    return s


class DeprecatedFlag(argparse.Action):
    """``--base X``: stores into the new option's ``dest`` and prints a deprecation line."""

    def __init__(self, option_strings, dest, new: str = "--model", **kw):
        self.new = new
        super().__init__(option_strings, dest, **kw)

    def __call__(self, parser, namespace, values, option_string=None):
        s = str(values).strip().lower()
        if s in MODEL_ALIASES:
            deprecated(f"{option_string} {values}", f"{self.new} {MODEL_ALIASES[s]}")
            s = MODEL_ALIASES[s]
        else:
            deprecated(option_string, self.new)
        setattr(namespace, self.dest, mechanics_model(s))


class DeprecatedAlias(argparse.Action):
    """An old spelling of an option (``--test-fraction`` for ``--holdout``): stores into the
    new option's ``dest`` (converted by its ``type``) and prints a deprecation line."""

    def __init__(self, option_strings, dest, new: str, **kw):
        self.new = new
        super().__init__(option_strings, dest, **kw)

    def __call__(self, parser, namespace, values, option_string=None):
        deprecated(option_string, self.new)
        setattr(namespace, self.dest, values)


def add_mechanics_model_arg(p: argparse.ArgumentParser, default: str, what: str) -> None:
    """``--model physics|rigid`` (default ``default``) and the deprecated ``--base``."""
    p.add_argument("--model", type=mechanics_model, default=default, metavar="physics|rigid",
                   help=f"{what}: physics (torsionally compliant) or rigid (torsionally rigid, the "
                        f"'traditional' model); default {default}")
    p.add_argument("--base", action=DeprecatedFlag, dest="model", help=argparse.SUPPRESS)


def base_of(model: str) -> str:
    """The calibration code's name of a mechanics model (``compliant`` / ``rigid``)."""
    return "compliant" if model == "physics" else "rigid"
