"""Calibration where the compliant model has two stable equilibria: each measured row is compared
on the branch the robot was on.

Oracle: the foreign finite-element energy (tests/foreign/continuation.py, imports nothing from
ctrplan) finds every stable equilibrium of a configuration and its backbone; the "measurements"
put the robot on one branch in some rows and on the other in the rest, at the same
configurations. A prediction that picks one equilibrium per configuration is tens of mm off on
half of them.
"""

from __future__ import annotations

import numpy as np

from ctrplan.calibration.lsq import Problem
from ctrplan.measured import MeasuredData
from ctrplan.robot import load_robot
from ctrplan.shape.effects import EffectModel
from tests.foreign import continuation as C

ROBOT = "two_tube_nylon"


def _tips(q: np.ndarray) -> list[np.ndarray]:
    """Every configuration's stable equilibria's tips (foreign energy), mm."""
    out = []
    for row in q:
        eqs = C.equilibria(ROBOT, row)
        out.append(np.array([C.continue_path(ROBOT, row[None], uz0=e.uz0 + 1e-4, points=2).tips[0]
                             for e in eqs]))
    return out


def test_each_row_is_predicted_on_the_branch_it_was_measured_on():
    q = np.array([[np.pi + 0.3, 0.0, -60.0, 0.0],
                  [np.pi - 0.25, 0.0, -60.0, -3.0],
                  [np.pi + 0.1, 0.0, -80.0, -5.0],
                  [0.4, 0.0, -60.0, 0.0]])            # the last: one stable equilibrium
    tips = _tips(q)
    assert [len(t) for t in tips] == [2, 2, 2, 1]
    assert all(np.linalg.norm(t[0] - t[1]) > 20.0 for t in tips[:3])
    # each bistable configuration measured on both branches (in either order), the last once
    rows, meas = [], []
    for i, t in enumerate(tips):
        for k in ((0,) if len(t) == 1 else (0, 1) if i % 2 == 0 else (1, 0)):
            rows.append(q[i])
            meas.append(t[k])
    rows, meas = np.array(rows), np.array(meas)
    data = MeasuredData(q=rows, tip=meas)
    everything = np.ones(len(rows), dtype=bool)
    prob = Problem(EffectModel(load_robot(ROBOT), "compliant"), data, everything, everything)
    pred = prob.predict_many([{}])[0]
    assert np.max(np.linalg.norm(pred[:, -1] - meas, axis=1)) < 0.01
    assert list(prob.last_bistable) == [True] * 6 + [False]
    # the solve's first pick is one of the two at each configuration: the other rows of a pair
    # were predicted on the other branch
    assert prob.last_other_branch.sum() == 3
    assert all(prob.last_other_branch[2 * i] != prob.last_other_branch[2 * i + 1] for i in range(3))
