"""``ctrplan design`` on anatomies it has never seen, with a known answer (statistical suite).

Each anatomy is generated at test time from a fresh seed (never used while developing design:
those were 0-5) by tests/design_scenes.py: a tortuous lumen around the swept volume of a known
two-tube robot's motions to three targets (margin, narrowings, dead-end side branches), so a
feasible design is guaranteed. Oracles that share no code with ctrplan:

- the independent re-check (tests/foreign/recheck.py: the foreign generator's mechanics, exact
  FCL cylinders of every tube, the scene read from its files) replays every reached plan;
- the strain of every tube, computed here from robot.yaml;
- for the infeasible variant (the same anatomy with a neck below the smallest stock tube, put
  there by the generator), the place the report names against where the neck is.

The full ten-anatomy run is ``benchmarks/bench_design.py anatomies`` (resumable, several
minutes per anatomy on a shared core); this test runs a sample of the same kind within the
statistical suite's budget.
"""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
import yaml

from tests.design_scenes import build

pytestmark = [pytest.mark.statistical, pytest.mark.xdist_group("design_generated")]

#: Fresh seeds (not used while developing design) and the share that must reach >= 2/3.
FRESH = (1000, 1001, 1002)
MIN_SHARE = 0.8
STRAIN_LIMIT = 0.06
SMALLEST_OD = 0.51


def _design(folder, names, out):
    from ctrplan.cli import main

    rc = main(["-q", "design", "--scene", str(folder), "--targets", ",".join(names), "--out", str(out)])
    return rc, json.loads((out / "design.json").read_text())


def test_design_reaches_generated_anatomies(tmp_path):
    """Default settings: >= 2/3 of the targets in >= 80 % of the anatomies, every reached plan
    free in the independent re-check, every tube within the strain limit."""
    from tests.foreign.recheck import recheck_path

    good = []
    for seed in FRESH:
        ks = build(seed, tmp_path / f"k{seed}")
        out = tmp_path / f"d{seed}"
        rc, doc = _design(ks.folder, ks.names, out)
        assert rc == (0 if doc["status"] == "ALL_REACHED" else 1)
        if doc["robot"] is None:
            good.append(False)
            continue
        tubes = yaml.safe_load((out / "robot.yaml").read_text())["tubes"]
        assert max(t["od"] / 2 * abs(t["curvature"]) for t in tubes) <= STRAIN_LIMIT + 1e-12
        for t in doc["targets"]:
            if t["reached"]:
                plan = json.loads((out / t["path_file"]).read_text())
                rep = recheck_path(str(out / "robot.yaml"), str(ks.folder), plan["path"], distances=False)
                assert rep.free, (seed, t["name"])
        good.append(doc["reached"] >= math.ceil(2 * len(ks.names) / 3))
    assert sum(good) >= math.ceil(MIN_SHARE * len(FRESH)), good


def test_infeasible_variants_name_the_neck(tmp_path, capsys):
    """The same anatomies narrowed below the smallest stock tube: exit 1, NONE_REACHED, and for
    every target the report names the corridor (a necessary condition), narrower than the
    smallest stock tube, at the neck (within 2.5 mm of where the generator put it), on the
    command line too."""
    for seed in FRESH:
        ks = build(seed, tmp_path / f"n{seed}", infeasible=True)
        rc, doc = _design(ks.folder, ks.names, tmp_path / f"dn{seed}")
        text = capsys.readouterr().out
        assert rc == 1 and doc["status"] == "NONE_REACHED"
        assert {b["target"] for b in doc["blocked"]} == set(ks.names)
        for b in doc["blocked"]:
            assert b["blocking"] == "corridor" and b["kind"] == "necessary", b
            assert b["numbers"]["width_mm"] < SMALLEST_OD
            assert np.linalg.norm(np.asarray(b["place"]["position"]) - ks.neck_centre) <= 2.5, b
            assert any(ln.strip().startswith(f"{b['target']}: corridor") and "past the entry" in ln
                       for ln in text.splitlines())
