"""Statistical: plans on bistable robots never rely on a shape the robot cannot be in.

Problems from the foreign generator (tests/foreign/folds.py, which imports nothing from
ctrplan): start and target configurations on opposite sides of the bistable range of relative
rotation, each monostable, whose shortest joint motion crosses a fold (the oracle's own
continuation snaps on it); the target is the target configuration's tip. Each plan is replayed
by the oracle's continuation (tests/foreign/continuation.py: an independently discretised
elastic energy, followed quasi-statically, snapping where its branch ends): the physical
robot's motion. Asserted per robot (two_tube_nylon; two_tube_wide, bistable over a wider range):
>= 90 % of 20 fresh pairs planned, every planned path replayed with 0 snaps and every path
state's backbone within 1 mm of the replayed one, every other plan refused as UNSTABLE_ONLY.

The scene is open (one small box far behind the base): what decides is instability, not
collision. One case in a shipped scene (neuro, two_tube_wide, the first fold-crossing case of a
fixed seed whose start and target are collision-free there) checks the same with anatomy.
Measured before this test was written (seeds 11, 12 of the generator, not asserted here):
20 / 20 planned on each robot, 0 snaps, largest deviation 0.0006 mm. On the asserted seeds
(2026-11-27): 20 / 20 and 20 / 20 planned (nylon 12 by the straight edge, 8 by RRTConnect; wide
10 and 10), 0 snaps, largest deviation 0.0006 and 0.0004 mm, about 110 s on one core. The
planner without branch tracking (main before it) on nylon's asserted seed: 20 / 20 SUCCESS, of
which 7 snap on replay and 13 have a path state farther than 1 mm from the robot's shape.
"""

from __future__ import annotations

import numpy as np
import pytest

from ctrplan.planning.plan import PlanStatus, plan_to_target, scene_by_name
from tests.conftest import open_scene
from tests.foreign.continuation import continue_path
from tests.foreign.folds import fold_crossing_cases, fold_crossing_pairs

pytestmark = pytest.mark.statistical

#: robot -> the generator's seed for its pairs (fresh: not used while developing)
ROBOTS = {"two_tube_nylon": 3501, "two_tube_wide": 3502}
PAIRS = 20
MIN_PLANNED = 0.9
MAX_DEV_MM = 1.0
#: a cap only: the search budget is a count of states (a seed's result does not depend on load)
TIME_CAP_S = 120.0


def _replay(robot: str, result, to_base=None) -> tuple[list, float, np.ndarray]:
    """(snaps, largest backbone deviation mm, the oracle's stability per state)."""
    rep = continue_path(robot, result.path, points=result.backbones.shape[1])
    bb = result.backbones
    if to_base is not None:
        bb = to_base(bb.reshape(-1, 3)).reshape(bb.shape)
    return list(rep.snaps), float(np.linalg.norm(rep.backbones - bb, axis=2).max()), rep.stability


@pytest.mark.parametrize("robot", sorted(ROBOTS))
def test_fold_crossing_pairs_are_planned_without_snaps(robot):
    scene = open_scene()
    pairs = fold_crossing_pairs(robot, PAIRS, ROBOTS[robot])
    assert len(pairs) == PAIRS
    planned, refused = 0, []
    for k, (start, target) in enumerate(pairs):
        r = plan_to_target(robot, scene, target, start=start, seed=k, time_limit=TIME_CAP_S)
        if r.status is not PlanStatus.SUCCESS:
            refused.append((k, r.status.value, r.message))
            continue
        planned += 1
        snaps, dev, mu = _replay(robot, r)
        assert snaps == [], (k, snaps)
        assert dev <= MAX_DEV_MM, (k, dev)
        assert np.all(mu > 0), (k, float(mu.min()))     # every state a minimum of the oracle
        assert len(r.branch) == len(r.path) and min(r.stability) >= 0.1, k
    assert planned >= MIN_PLANNED * PAIRS, refused
    assert all(status == PlanStatus.UNSTABLE_ONLY.value for _, status, _ in refused), refused


def test_fold_crossing_case_in_a_shipped_scene():
    """neuro, two_tube_wide: the first fold-crossing case (seed 7) whose start and target are
    collision-free in the scene is planned with clearance, and replayed without a snap."""
    from ctrplan.collision.capsules import curvature_bound
    from ctrplan.planning.plan import world_for
    from ctrplan.planning.validator import BatchValidator
    from ctrplan.shape.physics import PhysicsModel

    robot = "two_tube_wide"
    scene = scene_by_name("neuro")
    model = PhysicsModel(robot)
    v = BatchValidator(model.robot, model, world_for(scene, 0.0, curvature_bound(model)))
    case = None
    for c in fold_crossing_cases(robot, 12, 7):
        if v.states_valid(np.stack([c.start_q, c.target_q])).all():
            case = c
            break
    assert case is not None and case.snaps >= 1
    r = plan_to_target(robot, scene, scene.to_scene(case.target[None])[0], start=case.start_q,
                       seed=0, time_limit=TIME_CAP_S)
    assert r.status is PlanStatus.SUCCESS, r.message
    assert r.min_clearance_mm > 0
    snaps, dev, mu = _replay(robot, r, scene.to_base)
    assert snaps == [] and dev <= MAX_DEV_MM and np.all(mu > 0), (snaps, dev)
