"""Branch tracking along a motion and the stability measure (ctrplan.shape.branches,
ctrplan.planning.tracking).

Oracles (no ctrplan code):
- a balanced pair (equal EI, curvature and EI/GJ, curved sections coinciding) reduces to one
  equation for the relative twist theta = psi_1 - psi_2 on the overlap,
  theta'' = (EI kappa^2 / GJ) sin(theta), with theta' = 0 at the tubes' common end and the
  straight transmission (length a) giving alpha = theta_c - a theta'_c at the curve start.
  Integrated here with scipy from the distal angle theta_e, it gives alpha(theta_e): its turning
  points are the folds, and (Wronskian of the Jacobi equation) det J = d alpha / d theta_e;
- the independently discretised elastic energy of tests/test_stability.py (its Hessian's
  smallest eigenvalue is > 0 exactly at stable equilibria);
- scipy's own continuation of the reduced problem (dense in theta_e) for the shapes' branch.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.integrate import solve_ivp

from ctrplan.errors import InputError
from ctrplan.planning.stability import Start, check_branch, resolve_start, start_from_plan
from ctrplan.planning.validator import BatchValidator, ValidatorConfig
from ctrplan.robot import load_robot
from ctrplan.shape import branches as br
from ctrplan.shape.physics import Loads, PhysicsModel
from tests.conftest import balanced_pair, open_scene, write_open_scene

BETA = -50.0                # balanced pair: curved overlap s in [50, 150], transmission 100 mm


def _alpha_of(theta_e: np.ndarray, c: float, a: float = 100.0, ell: float = 100.0) -> np.ndarray:
    """The oracle: actuator relative angle of the equilibrium with distal relative angle
    theta_e (backward integration of theta'' = c sin theta over the overlap)."""
    out = []
    for te in np.atleast_1d(theta_e):
        sol = solve_ivp(lambda x, y: [y[1], c * math.sin(y[0])], (ell, 0.0), [te, 0.0],
                        rtol=1e-12, atol=1e-14)
        thc, dthc = sol.y[:, -1]
        out.append(thc - a * dthc)
    return np.array(out)


@pytest.fixture(scope="module")
def pair():
    robot = balanced_pair()
    t = robot.tubes[0]
    c = t.bending_stiffness / t.torsional_stiffness * t.curvature ** 2
    return robot, PhysicsModel(robot), c


class _NoWorld:
    """A collision world with nothing in it that still answers (no anatomy to touch)."""

    def collides(self, shape):
        return ~np.asarray(shape.ok, dtype=bool)

    def first_collision(self, shape):
        bad = np.flatnonzero(~np.asarray(shape.ok, dtype=bool))
        return int(bad[0]) if len(bad) else -1

    def check_exact(self, shape):
        return self.check(shape)

    def check(self, shape):
        from types import SimpleNamespace

        hit = ~np.asarray(shape.ok, dtype=bool)
        return SimpleNamespace(collides=hit, clearance_mm=np.where(hit, -1.0, 50.0),
                               contact=np.where(hit, "model", ""))


def _sweep(robot, a0, a1, step=0.01):
    a = np.arange(a0, a1 + 1e-12, step)
    return a, np.stack([a, 0 * a, BETA + 0 * a, BETA + 0 * a], 1)


def test_continuation_follows_the_branch_to_the_oracle_fold(pair):
    """Rotating the inner tube of the balanced pair from 0 up (0.01 rad steps): the chained
    solve stays on the branch it started on until the oracle's fold and ends there (the next
    state lies beyond it), and its stability equals the oracle's d alpha / d theta_e on that
    branch (1e-3); the history-free solve jumps to the other branch before the fold."""
    robot, model, c = pair
    th = np.linspace(0.0, 2 * math.pi, 601)
    al = _alpha_of(th, c)
    slope = np.gradient(al, th)
    turn = np.flatnonzero((slope[:-1] > 0) & (slope[1:] <= 0))
    assert len(turn) == 1                       # the pair is bistable: one fold going up
    k = turn[0]
    fold = float(al[k])
    assert math.pi < fold < 2 * math.pi
    a, q = _sweep(robot, 0.0, fold + 0.3)
    t = br.solve(model, q, 12, chain=np.zeros(len(q), dtype=bool))
    last = int(np.flatnonzero(t.continued)[-1])
    assert a[last] <= fold < a[last] + 0.01 + 1e-9
    assert not t.continued[last + 1:].any() and not t.shape.ok[last + 1:].any()
    # stability on the branch against the oracle (lower branch: theta_e in [0, th[k]])
    lower = slice(0, k + 1)
    for i in range(0, last + 1, 10):
        te = np.interp(a[i], al[lower], th[lower])
        h = 1e-5
        s_oracle = float(np.diff(_alpha_of(np.array([te - h, te + h]), c))[0] / (2 * h))
        assert abs(t.stability[i] - s_oracle) <= 1e-3 * max(1.0, abs(s_oracle)), a[i]
    assert t.stability[last] < 0.1 * t.stability[0]
    # the history-free solve picks the other branch before the fold: a jump of the tip
    plain = model.shape(q[: last + 1], 12)
    jump = np.linalg.norm(np.diff(plain.tip, axis=0), axis=1).max()
    smooth = np.linalg.norm(np.diff(t.shape.tip[: last + 1], axis=0), axis=1).max()
    assert jump > 20 * smooth


def test_continued_states_are_minima_of_the_energy_oracle():
    """two_tube_nylon at full overlap, inner tube rotated through the bistable range on the
    branch it entered on: every continued equilibrium is a strict minimum of the
    independently discretised energy (and meets its boundary conditions), also where the
    history-free solve returns the other one."""
    from tests.foreign.core import load_spec
    from tests.test_stability import _hessian_min_eig

    sp = load_spec("two_tube_nylon")
    model = PhysicsModel("two_tube_nylon")
    a = np.linspace(2.4, 3.7, 27)
    q = np.stack([a, 0 * a, -160 + 0 * a, -100 + 0 * a], 1)
    t = br.solve(model, q, 2, chain=np.zeros(len(q), dtype=bool))
    assert t.continued.all()
    plain = br.solve(model, q, 2)
    other = ~br.same_equilibrium(t.uz0, plain.uz0, model.robot)
    assert other.sum() >= 5                     # beyond pi the two solves disagree
    for k in np.flatnonzero(other)[::2]:
        lam, res = _hessian_min_eig(sp, q[k, :2], q[k, 2:], t.uz0[k], h=2.0)
        assert lam > 0 and np.all(np.abs(res) < 1e-7), (a[k], lam)


def test_check_path_over_a_branch_switch_is_not_ok():
    """The issue's step: relative rotation through pi at full overlap, 0.0004 rad (0.012 mm of
    metric). The history-free shapes of its two states are 50 mm apart; as a motion the robot
    stays on its branch, so the path ends on another equilibrium than the model's shape at its
    end: not ok ('branch'). The same states reached the long way round are ok."""
    model = PhysicsModel("two_tube_nylon")
    robot = model.robot
    v = BatchValidator(robot, model, _NoWorld(), ValidatorConfig(motion_bound=False))
    qa = np.array([math.pi - 2e-4, 0, -160, -100])
    qb = np.array([math.pi + 2e-4, 0, -160, -100])
    tips = model.shape(np.stack([qa, qb]), 2).tip
    assert np.linalg.norm(tips[0] - tips[1]) > 40
    check = v.check_path(np.stack([qa, qb]), 0.5)
    assert not check.ok and check.contact[-1] == "branch"
    # arriving at the same end state from the other side: the robot is on the model's shape
    v2 = BatchValidator(robot, model, _NoWorld(), ValidatorConfig(motion_bound=False))
    assert v2.check_path(np.stack([qb + [1.0, 0, 0, 0], qb]), 0.5).ok
    assert not v2.check_path(np.stack([qb - [1.0, 0, 0, 0], qb]), 0.5).ok


def test_edges_through_a_fold_and_between_branches_are_invalid():
    """Edges as motions: through the fold (4.08 -> 2.33 at full overlap) invalid; the long way
    round valid; an edge between two states remembered on different equilibria invalid, on
    the same one valid; the state reached is remembered with the equilibrium it was reached on."""
    model = PhysicsModel("two_tube_nylon")
    robot = model.robot
    v = BatchValidator(robot, model, _NoWorld(), ValidatorConfig(motion_bound=False))
    s = np.array([4.08, 0, -160, -100])
    assert not v.edge_valid(s, np.array([2.33, 0, -160, -100]))
    assert v.tracker.counters.folds >= 1
    mid = np.array([5.9, 0, -160, -100])
    assert v.edge_valid(s, mid) and v.tracker.lookup(mid) is not None
    assert v.edge_valid(mid, np.array([2.33 + 2 * math.pi - 6.0, 0, -160, -100]))
    # two remembered states at pi -/+ 0.01: the branch continues across pi, but the default
    # equilibria of the two states are on different branches
    qa = np.array([math.pi - 0.01, 0, -160, -100])
    qb = np.array([math.pi + 0.01, 0, -160, -100])
    v.anchor(np.stack([qa, qb]))
    assert not v.edge_valid(qa, qb)
    assert v.tracker.counters.branch_mismatch >= 1
    # qa's equilibrium continued to qb, remembered there: the same edge is then valid
    t = br.solve(model, np.stack([qa, qb]), 2, chain=np.array([True, False]),
                 uz_init=np.stack([v.tracker.lookup(qa), np.full(2, np.nan)]))
    v.tracker.register(qb[None], t.uz0[1:])
    assert v.edge_valid(qa, qb)


def test_stability_margin_makes_states_invalid():
    """A state whose stability is below the margin is invalid; margin 0 keeps every stable one."""
    model = PhysicsModel("two_tube_nylon")
    q = np.array([[0.0, 0, -160, -100], [math.pi, 0, -160, -100]])
    stab = br.solve(model, q, 2).stability
    assert stab[0] > 2.0 > stab[1] > 0
    for margin, expect in ((0.0, [True, True]), (2.0, [True, False]), (100.0, [False, False])):
        v = BatchValidator(model.robot, model, _NoWorld(),
                           ValidatorConfig(motion_bound=False, stability_margin=margin))
        assert list(v.states_valid(q)) == expect, margin
    assert v.tracker.counters.below_margin >= 2


def test_tracking_is_off_where_the_model_cannot_snap_and_a_no_op_on_seed1():
    """Rigid and loaded models are not tracked; on seed1 the continued shapes of random edges
    equal the history-free ones (same equilibrium, to the solver's tolerance)."""
    from ctrplan.planning.validator import interpolate

    r = load_robot("seed1")
    assert not br.tracks_branches(PhysicsModel(r, torsion=False))
    assert not br.tracks_branches(PhysicsModel(r, loads=Loads(tip_force=(0.0, 0.1, 0.0))))
    assert br.tracks_branches(PhysicsModel(r))
    assert BatchValidator(r, PhysicsModel(r, torsion=False), _NoWorld()).tracker is None
    model = PhysicsModel(r)
    q0, q1 = r.sample(40, seed=5), r.sample(40, seed=6)
    rows, starts = [], []
    for a, b in zip(q0, q1):
        e = interpolate(a, a + 0.2 * (b - a), r.n, 30.0, 2.0)
        rows.append(e)
        starts.append(np.r_[True, np.zeros(len(e) - 1, dtype=bool)])
    q = np.concatenate(rows)
    t = br.solve(model, q, 16, chain=np.concatenate(starts))
    plain = model.shape(q, 16)
    assert t.continued.all() and t.shape.ok.all()
    assert np.abs(t.shape.points - plain.points).max() < 1e-6


def test_a_bistable_start_needs_its_branch():
    """At relative rotation pi with full overlap the nylon pair has two stable equilibria:
    without a branch the start is refused (one line naming --start); +1 and -1 pick the two,
    whose tips lie on opposite sides (y), and a non-bistable start refuses a nonzero branch."""
    model = PhysicsModel("two_tube_nylon")
    q = np.array([math.pi, 0.0, -160.0, -100.0])
    with pytest.raises(InputError, match="bistable") as exc:
        resolve_start(model, q, None)
    assert "\n" not in str(exc.value)
    up, down = resolve_start(model, q, 1), resolve_start(model, q, -1)
    assert up[0] > down[0]
    tips = br.settle(model, np.stack([q, q]), np.stack([up, down]), 2).shape.tip
    assert tips[0, 1] * tips[1, 1] < 0 and abs(tips[0, 1] - tips[1, 1]) > 40
    with pytest.raises(InputError, match="one stable"):
        resolve_start(model, np.array([0.0, 0.0, -160.0, -100.0]), 1)
    # the label of each is what plan.json would record there
    first, second = br.stable_equilibria(model, np.stack([q, q]))
    assert list(br.label_of(np.stack([up, down]), first, second, model.robot)) == [1, -1]
    assert check_branch("+1") == 1 and check_branch(-1) == -1 and check_branch(None) is None
    with pytest.raises(InputError):
        check_branch(2)


def test_start_from_plan_reads_the_last_state_and_its_branch(tmp_path):
    import json

    from ctrplan.robot import robot_record

    robot = load_robot("two_tube_nylon")
    plan = {"path": [[0.0, 0, -150, -100], [math.pi, 0, -160, -100]], "branch": [0, -1],
            **robot_record(robot)}
    p = tmp_path / "plan.json"
    p.write_text(json.dumps(plan))
    s = start_from_plan(p, robot)
    assert isinstance(s, Start) and s.branch == -1 and s.q[0] == math.pi
    with pytest.raises(InputError, match="another robot"):
        start_from_plan(p, balanced_pair())
    plan["branch"] = [0, 7]
    p.write_text(json.dumps(plan))
    with pytest.raises(InputError, match="branch"):
        start_from_plan(p, robot)


def test_the_issues_first_example_does_not_snap():
    """The issue's first example: two_tube_nylon from 4.08,0,-160,-100 to the tip of the
    configuration at relative rotation 2.33 (the other side of the bistable range), open
    scene. Before branch tracking this was a SUCCESS that snapped; now the plan, replayed by
    the foreign generator's continuation (the physical robot), never snaps and every path
    state's backbone is within 1 mm of the replayed one; branch and stability per state."""
    from ctrplan.planning.plan import PlanStatus, plan_to_target
    from tests.foreign.continuation import continue_path

    model = PhysicsModel("two_tube_nylon")
    target = model.shape(np.array([[2.33, 0.0, -160.0, -100.0]]), 2).tip[0]
    r = plan_to_target("two_tube_nylon", open_scene(), target, start=[4.08, 0, -160, -100], seed=0)
    assert r.status is PlanStatus.SUCCESS, r.message
    rep = continue_path("two_tube_nylon", r.path, points=r.backbones.shape[1])
    assert rep.snaps == []
    assert np.linalg.norm(rep.backbones - r.backbones, axis=2).max() < 1.0
    j = r.to_json()
    assert len(j["branch"]) == len(j["path"]) == len(j["stability"])
    assert set(j["branch"]) <= {-1, 0, 1} and min(j["stability"]) >= 0.1


def test_cli_start_from_an_earlier_plan_and_a_bistable_start(tmp_path, capsys):
    """`ctrplan plan --start plan.json` starts where the earlier plan ended, on its branch; a
    bistable --start without --branch is refused with one line (exit 2, nothing written); with
    --branch it is planned; a bad --branch or --stability-margin is refused."""
    import json

    from ctrplan.cli import main

    scene = write_open_scene(tmp_path / "open")
    first, second = tmp_path / "a.json", tmp_path / "b.json"
    model = PhysicsModel("two_tube_nylon")
    t1 = ",".join(map(str, model.shape(np.array([[math.pi, 0.0, -160.0, -100.0]]), 2).tip[0]))
    t2 = ",".join(map(str, model.shape(np.array([[0.5, 0.0, -150.0, -100.0]]), 2).tip[0]))

    def ctrplan(*args):
        return main(["-q", "plan", "--robot", "two_tube_nylon", "--scene", scene, *args])

    assert ctrplan("--target", t1, "--start", "0.3,0,-160,-100", "--out", str(first)) == 0
    p1 = json.loads(first.read_text())
    assert len(p1["branch"]) == len(p1["path"]) == len(p1["stability"])
    assert ctrplan("--target", t2, "--start", str(first), "--out", str(second)) == 0
    p2 = json.loads(second.read_text())
    assert np.allclose(p2["path"][0], p1["path"][-1], atol=1e-9)
    assert p2["branch"][0] == p1["branch"][-1]
    capsys.readouterr()
    bistable = "3.14159,0,-160,-100"
    assert ctrplan("--target", t2, "--start", bistable, "--out", str(tmp_path / "c.json")) == 2
    err = capsys.readouterr().err
    assert "bistable" in err and "--branch" in err and len(err.strip().splitlines()) == 1
    assert not (tmp_path / "c.json").exists()
    assert ctrplan("--target", t2, "--start", bistable, "--branch", "-1",
                   "--out", str(tmp_path / "d.json")) == 0
    assert json.loads((tmp_path / "d.json").read_text())["branch"][0] == -1
    for bad in (["--branch", "2"], ["--stability-margin", "-1"], ["--stability-margin", "x"]):
        assert ctrplan("--target", t2, "--start", bistable, *bad, "--out",
                       str(tmp_path / "e.json")) == 2, bad


def _fixed_pair():
    """The balanced pair with no straight sections: both translations fixed at 0 (a curved
    section may not start behind the plane), so only the rotations move; bistable for relative
    rotations of about 2.5-3.78 rad."""
    from ctrplan.robot import Robot
    from tests.conftest import nitinol

    inner = nitinol(1.0, 0.6, 0.0, 100.0, 0.02)
    od2, id2 = 1.6, 1.2
    e2 = inner.second_moment / (math.pi / 64.0 * (od2 ** 4 - id2 ** 4)) * inner.youngs_modulus
    return Robot(name="fixed_pair", tubes=(inner, nitinol(od2, id2, 0.0, 100.0, 0.02, E=e2)))


def test_unstable_only_when_only_a_fold_leads_to_the_goal():
    """The search stage: the fixed pair inside a cylinder (radius 67 mm) that the strongly bent
    shapes near relative rotation 0 touch. From relative rotation 4.3 to a goal at 2.0 the
    robot can only go down through the bistable range, where its branch ends (the way up
    through 0 is blocked): no stable path exists. The search with branch tracking finds none,
    the same search without it does (the history-free shapes jump past the fold), so the
    status is UNSTABLE_ONLY, not TIMEOUT. (Explicit goals: the IK would also offer the swapped
    tube rotations, the same shape on the start's side.)"""
    from types import SimpleNamespace

    import trimesh

    from ctrplan.collision.scene import Scene, SceneMesh
    from ctrplan.planning import stages
    from ctrplan.planning.planner import Planner, PlannerConfig
    from ctrplan.planning.result import PlanStatus
    from ctrplan.planning.run import Stop

    robot = _fixed_pair()
    model = PhysicsModel(robot)
    start = np.array([4.3, 0.0, 0.0, 0.0])
    goal = np.array([2.0, 0.0, 0.0, 0.0])
    cyl = trimesh.creation.cylinder(radius=67.0, segment=[(0, 0, -50), (0, 0, 150)], sections=96)
    scene = Scene(name="cylinder", path="<memory>", meshes=(SceneMesh("wall", "wall", cyl),),
                  base_pose=np.eye(4), targets=())
    planner = Planner(robot, scene, model, PlannerConfig(max_states=5_000))
    run = planner._run(model.shape(goal[None], 2).tip[0], 0, "rrtconnect", 60.0, 1.0, None)
    start = stages.checks(run, start)
    assert run.validator.states_valid(np.stack([start, goal])).all()
    assert not run.validator.states_valid(np.array([[0.0, 0.0, 0.0, 0.0]]))[0]   # the way up
    run.validator.anchor(goal[None])
    source = SimpleNamespace(goals=[goal], next=lambda: np.zeros((0, 4)), rounds=1, reaching=1,
                             evaluations=0)
    assert stages.relaxed(run).edge_valid(start, goal)
    with pytest.raises(Stop) as stop:
        stages.search(run, start, source, goal[None])
    res = stop.value.result
    assert res.status is PlanStatus.UNSTABLE_ONLY and "fold" in res.message
    assert run.validator.tracker.counters.folds > 0 and res.counts["unstable_only_check"] == 1


def test_unstable_only_when_every_goal_is_below_the_margin():
    """The IK stage: a target far out near the axis of two_tube_nylon is reached only with the
    tubes turned against each other (stability about 0.6); with --stability-margin 1 every
    reaching configuration is below it: UNSTABLE_ONLY; the default margin plans it."""
    from ctrplan.planning.plan import PlanConfig, PlanStatus, plan_to_target

    model = PhysicsModel("two_tube_nylon")
    q = np.array([[-2.12409384, 0.8099516, -3.70351066, -1.00144663]])
    target = model.shape(q, 2).tip[0]
    strict = PlanConfig(validator=ValidatorConfig(stability_margin=1.0))
    r = plan_to_target("two_tube_nylon", open_scene(), target, start=[0, 0, -160, -100],
                       seed=0, config=strict)
    assert r.status is PlanStatus.UNSTABLE_ONLY and "below the stability margin" in r.message
    ok = plan_to_target("two_tube_nylon", open_scene(), target, start=[0, 0, -160, -100], seed=0)
    assert ok.status is PlanStatus.SUCCESS and 0.1 <= min(ok.stability) < 1.0
    # a start below the margin is refused the same way
    r = plan_to_target("two_tube_nylon", open_scene(), target, start=[0, 0, -160, -100], seed=0,
                       config=PlanConfig(validator=ValidatorConfig(stability_margin=5.0)))
    assert r.status is PlanStatus.UNSTABLE_ONLY and "start" in r.message


def test_job_files_check_the_branch_fields():
    """plan-batch resume trusts a job file's per-state branch and stability only when they are
    lists as long as the path of -1 / 0 / +1 (or null) and of finite numbers (or null)."""
    from ctrplan.planning.jobfile import branch_fields_problem

    good = {"path": [[0, 0, -1, -1], [1, 0, -1, -1]], "branch": [0, -1], "stability": [1.5, None]}
    assert branch_fields_problem(good) is None
    assert branch_fields_problem({"path": []}) is None
    for key, value in (("branch", [0, 2]), ("branch", [0]), ("branch", [0, True]),
                       ("stability", [1.0, "x"]), ("stability", "1.0"), ("branch", [0, 1.0])):
        assert branch_fields_problem({**good, key: value})[0] == key, (key, value)
