"""Helpers shared by the sub-commands: argument types, model resolution, output checks."""

from __future__ import annotations

import argparse
from pathlib import Path

from ctrplan.errors import InputError


def add_robot_arg(p: argparse.ArgumentParser, required: bool = True) -> None:
    p.add_argument("--robot", required=required, default=None if required else "seed1",
                   help="shipped robot name (seed1, two_tube_nylon) or robot YAML path")


def add_model_arg(p: argparse.ArgumentParser, default: str = "physics") -> None:
    from ctrplan.commands._vocab import model_name

    p.add_argument("--model", default=default, type=model_name,
                   help="physics (torsionally compliant), rigid, learned (shipped default network) "
                        "or a model file written by 'ctrplan train'")


def output_path(path: str, suffixes: tuple[str, ...], field: str = "--out") -> Path:
    """Check an output path's suffix and that it can be written (its folder exists or can be
    created, and accepts files)."""
    from ctrplan.io import check_writable

    p = Path(path)
    if suffixes and p.suffix.lower() not in suffixes:
        raise InputError(field, "", f"{path!r} must end in one of {', '.join(suffixes)}")
    return check_writable(p, field)
