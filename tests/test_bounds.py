"""Chord pads cover loaded robots, and the clearance gap form is continuous.

Oracles: the loaded rod integrated independently (scipy, ``tests/test_loads.py::Reference``:
global force and moment states, its own root finding) at 20 points per capsule, its distance to
the model's 24-point chords computed here; the gap form's window-averaged curvature against a
brute-force average of the rigid curvature written here.
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from ctrplan.robot import load_robot
from ctrplan.shape.effects import GAP_WINDOW_MM, EffectModel, window_curvature
from ctrplan.shape.physics import Loads, PhysicsModel
from tests.test_loads import Reference

G = 9.80665
SUB = 20


def _seg_dist(p, a, b):
    v = b - a
    t = np.clip((p - a) @ v / max(float(v @ v), 1e-30), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * v), axis=1)


def _excess(robot, q, loads, kink=None, torsion=True):
    """(largest distance of the independent dense backbone beyond the model's padded chords,
    the same beyond the precurvature sagitta alone), mm."""
    m = PhysicsModel(robot, torsion=torsion, loads=loads)
    p = m.base_params(1)
    if kink is not None:
        from dataclasses import replace

        p = replace(p, kink=np.asarray(kink, float)[None])
    sh = m.solve(q[None], 24, p)
    assert sh.ok.all()
    ref = Reference(robot, q, torsion, loads.gravity, loads.tip_force, loads.tip_moment, kink)
    s = sh.s[0]
    s_out = np.concatenate([np.linspace(s[k], s[k + 1], SUB + 1)[:-1] for k in range(23)] + [s[-1:]])
    dense = ref.solve(s_out, uz0=m.last_info.uz0[0], m0=m.last_info.moment0[0])
    worst = np.array([_seg_dist(dense[k * SUB:(k + 1) * SUB + 1], sh.points[0, k],
                                sh.points[0, k + 1]).max() for k in range(23)])
    kappa = np.max(np.abs(robot.array("curvature")))
    sagitta = kappa * np.diff(s) ** 2 / 8.0
    return float(np.max(worst - sh.pad[0])), float(np.max(worst - sagitta))


CASES = [
    ("seed1", [0.4, -1.2, 2.5, -60.0, -30.0, -10.0], Loads(tip_force=(0.0, 2.0, 0.0)), None),
    ("seed1", [1.0, 0.3, -2.0, -40.0, -25.0, -8.0], Loads(tip_force=(0.5, 0.0, 0.0),
                                                          gravity=(0.0, -G, 0.0)),
     [[0, 0], [0.05, -0.03], [0.02, 0.04]]),
    ("two_tube_nylon", [1.0, -2.0, -40.0, -30.0], Loads(tip_force=(0.5, 0.0, 0.0)), None),
    ("two_tube_nylon", [0.2, 2.0, -10.0, -5.0], Loads(gravity=(G, 0.0, 0.0),
                                                      tip_moment=(20.0, 0.0, 5.0)),
     [[0, 0], [0.04, 0.03]]),
]


@pytest.mark.parametrize("case", [0, 3])
def test_pad_covers_the_independently_integrated_loaded_rod(case):
    name, q, loads, kink = CASES[case]
    excess, beyond_sagitta = _excess(load_robot(name), np.array(q, float), loads, kink)
    assert excess <= 1e-4, excess          # the kernel agrees with scipy to ~1e-5 mm
    if case == 0:                          # a 2 N tip force: precurvature alone is not a bound
        assert beyond_sagitta > 0.02


@pytest.mark.statistical
@pytest.mark.parametrize("name,torsion", [("seed1", True), ("two_tube_nylon", False)])
def test_pad_covers_loaded_rods_many_configurations(name, torsion):
    """The cases above, then gravity, 0.5 N and 2 N tip forces and a tip moment on a random
    configuration each, with random kinks (about 5 s per independent solve)."""
    for case in (1, 2):
        assert _excess(load_robot(CASES[case][0]), np.array(CASES[case][1], float),
                       CASES[case][2], CASES[case][3], torsion)[0] <= 1e-4
    robot = load_robot(name)
    rng = np.random.default_rng(7)
    loads = [Loads(gravity=(0.0, -G, 0.0)), Loads(tip_force=(0.5, 0.0, 0.0)),
             Loads(tip_force=(0.0, -2.0, 0.5)), Loads(tip_moment=(10.0, -5.0, 2.0))]
    beyond = 0.0
    for ld in loads:
        for q in robot.sample(1, seed=rng):
            kink = rng.normal(0, 0.03, (robot.n, 2))
            kink[0] = 0.0
            excess, b = _excess(robot, q, ld, kink, torsion)
            assert excess <= 1e-4, (ld, q, excess)
            beyond = max(beyond, b)
    assert beyond > 0.01


def _brute_window(robot, q, a, b, samples=400_001):
    """Mean of the rigid curvature vector over [a, b] where some tube is present (written here)."""
    n = robot.n
    s = np.linspace(a, b, samples)
    ends = [q[n + i] + robot.tubes[i].straight_length + robot.tubes[i].curved_length for i in range(n)]
    starts = [q[n + i] + robot.tubes[i].straight_length for i in range(n)]
    num = np.zeros((samples, 2))
    den = np.zeros(samples)
    for i, t in enumerate(robot.tubes):
        ei = t.youngs_modulus * math.pi / 64 * (t.od ** 4 - t.id ** 4)
        here = s < ends[i]
        den += np.where(here, ei, 0.0)
        bent = here & (s >= starts[i])
        num[:, 0] += np.where(bent, -ei * t.curvature * math.sin(q[i]), 0.0)
        num[:, 1] += np.where(bent, ei * t.curvature * math.cos(q[i]), 0.0)
    some = den > 0
    return (num[some] / den[some, None]).mean(axis=0) if some.any() else np.zeros(2)


def test_window_curvature_is_the_mean_over_the_window():
    robot = load_robot("seed1")
    q = robot.sample(2, seed=4)
    n = robot.n
    kappa = np.tile(robot.array("curvature"), (len(q), 1))
    EI = np.tile(robot.array("bending_stiffness"), (len(q), 1))
    for j in range(1, n):
        e = q[:, n + j] + robot.lengths[j]
        for lo, hi in ((e - GAP_WINDOW_MM, e), (e, e + GAP_WINDOW_MM), (e - 40.0, e + 3.0)):
            got = window_curvature(robot, q, kappa, EI, lo, hi)
            for i in range(len(q)):
                want = _brute_window(robot, q[i], lo[i], hi[i])
                assert np.allclose(got[i], want, atol=1e-6), (j, i, got[i], want)


def test_gap_form_moves_the_backbone_continuously():
    """seed1, gap length 20 mm: inserting tube 1 so that its curved section's start crosses
    tube 2's end moved the tip 9.5 mm within 0.005 mm of insertion (a step) before the
    curvature was averaged; now each 0.005 mm step moves it at most 0.1 mm, and the tilt
    still changes the tip by several mm across the window."""
    robot = load_robot("seed1")
    m = EffectModel(robot, "compliant", {"clearance": {"length": 20.0}})
    b2, b3 = -40.0, -10.0
    c = b2 + robot.lengths[1] - robot.tubes[0].straight_length     # curve start at tube 2's end
    b1 = np.linspace(c - 1.5, c + 1.5, 601)
    q = np.array([[0.3, 2.0, -1.0, x, b2, b3] for x in b1])
    tip = m.shape(q, 24).points[:, -1]
    step = np.linalg.norm(np.diff(tip, axis=0), axis=1)
    assert step.max() < 0.1
    assert np.linalg.norm(tip[-1] - tip[0]) > 5.0


@pytest.mark.parametrize("effects", [{"clearance": {"c0": 0.1, "c1": 0.1}},
                                     {"clearance": {"c0": 0.1, "c1": 0.1}, "load": {"fx": 0.5}}])
def test_kinks_of_tubes_ending_together_compose_as_in_the_limit(effects):
    """Tubes 2 and 3 of seed1 ending at the same arc length (the constraint's edge): the tip is
    where it tends to as the ends come together (the kinks compose in the limit's order; the
    other order left a 1.8 um step)."""
    robot = load_robot("seed1")
    m = EffectModel(robot, "compliant", effects)
    b2 = -60.0
    b3 = b2 + robot.lengths[1] - robot.lengths[2]
    gap = np.array([1e-3, 1e-5, 1e-7, 0.0])
    tip = m.shape(np.array([[0.3, 2.0, -1.0, -100.0, b2, b3 - g] for g in gap]), 24).points[:, -1]
    move = np.linalg.norm(tip - tip[-1], axis=1)
    assert move[0] > 1e-5                              # the kinks matter here
    assert np.all(move[1:-1] <= 2.0 * move[0] * gap[1:-1] / gap[0] + 1e-9)
