"""``Robot.retracted()`` finds a valid start for every robot whose joint constraints admit one.

Oracle: the constraints as docs/conventions.md states them, written out here as a linear
program (scipy's HiGHS), sharing no code with ``Robot``: feasibility, and the smallest value
each beta can take. Random valid robots of 2-4 tubes with lengths drawn from 5 to 500 mm
(straight and curved independently, so outer tubes often have the longer straight section,
the case the old outermost-first rule got wrong), with and without ``beta_min``.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.optimize import linprog

from ctrplan.errors import InputError
from ctrplan.robot import Robot, Tube

TOL = 1e-6


def _lp_constraints(straight, curved, beta_min):
    """A_ub beta <= b_ub and bounds, from docs/conventions.md."""
    n = len(straight)
    L = np.asarray(straight) + np.asarray(curved)
    A, b = [], []
    for i in range(n - 1):
        row = np.zeros(n)
        row[i], row[i + 1] = 1.0, -1.0          # beta_i <= beta_(i+1)
        A.append(row)
        b.append(0.0)
        row = np.zeros(n)
        row[i], row[i + 1] = -1.0, 1.0          # beta_(i+1) + L_(i+1) <= beta_i + L_i
        A.append(row)
        b.append(L[i] - L[i + 1])
    row = np.zeros(n)
    row[-1] = -1.0                              # beta_n + L_n >= 0
    A.append(row)
    b.append(L[-1])
    lo = [max(-s, m) for s, m in zip(straight, beta_min)]   # curved section never behind the plane
    return np.array(A), np.array(b), [(lo_i, 0.0) for lo_i in lo]


def _lp_least(straight, curved, beta_min):
    """(feasible, smallest feasible value of each beta) by linear programming."""
    A, b, bounds = _lp_constraints(straight, curved, beta_min)
    n = len(straight)
    least = np.empty(n)
    for i in range(n):
        c = np.zeros(n)
        c[i] = 1.0
        res = linprog(c, A_ub=A, b_ub=b, bounds=bounds, method="highs")
        if res.status == 2:
            return False, None
        assert res.status == 0
        least[i] = res.fun
    return True, least


def _valid(straight, curved, beta_min, beta):
    A, b, bounds = _lp_constraints(straight, curved, beta_min)
    lo = np.array([x[0] for x in bounds])
    return bool(np.all(A @ beta <= b + TOL) and np.all(beta >= lo - TOL) and np.all(beta <= TOL))


def _random_robot(rng):
    n = int(rng.integers(2, 5))
    od = np.cumsum(rng.uniform(0.3, 0.8, n)) + 0.5
    straight = rng.uniform(5.0, 500.0, n)
    curved = rng.uniform(0.0, 200.0, n) * (rng.random(n) < 0.8)
    beta_min = (-rng.uniform(0.0, 500.0, n)) if rng.random() < 0.3 else np.full(n, -np.inf)
    tubes = tuple(Tube(od=float(od[i]), id=float(od[i] - 0.2), straight_length=float(straight[i]),
                       curved_length=float(curved[i]), curvature=float(rng.uniform(0.0, 0.02)),
                       youngs_modulus=60000.0, poisson_ratio=0.33) for i in range(n))
    bm = None if np.all(np.isinf(beta_min)) else tuple(float(x) for x in beta_min)
    return Robot(name="random", tubes=tubes, beta_min=bm), straight, curved, beta_min


def test_retracted_on_random_robots_matches_the_linear_program():
    """400 random robots (about a quarter feasible): retracted() succeeds exactly when the LP is
    feasible, and returns a valid configuration with every beta at its least feasible value
    and all rotations 0."""
    rng = np.random.default_rng(41)
    feasible_seen = infeasible_seen = 0
    for _ in range(400):
        robot, straight, curved, beta_min = _random_robot(rng)
        feasible, least = _lp_least(straight, curved, beta_min)
        if not feasible:
            infeasible_seen += 1
            with pytest.raises(InputError, match="admit no configuration"):
                robot.retracted()
            continue
        feasible_seen += 1
        q = robot.retracted()
        n = robot.n
        assert np.all(q[:n] == 0.0)
        assert _valid(straight, curved, beta_min, q[n:]), (straight, curved, beta_min, q)
        np.testing.assert_allclose(q[n:], least, atol=1e-6)
        assert robot.is_valid(q[None])[0]
    assert feasible_seen >= 80 and infeasible_seen >= 20, (feasible_seen, infeasible_seen)


def test_issue_robot_inner_tube_long_outer_straight_longer():
    """The robot of the report: inner tube straight 160 mm, curved 100 mm; the outer tube is
    shorter overall but its straight section (170 mm) is longer than the inner one's. Valid
    configurations exist (both betas -160); the old rule refused it."""
    tubes = (Tube(1.0, 0.8, 160.0, 100.0, 0.01, 60000.0, 0.33),
             Tube(1.6, 1.2, 170.0, 0.0, 0.0, 60000.0, 0.33))
    robot = Robot("issue", tubes)
    q = robot.retracted()
    np.testing.assert_allclose(q, [0.0, 0.0, -160.0, -160.0])
    assert robot.is_valid(q[None])[0]
