"""Effects on the mechanics model: exact "off", each effect's physics, composition, files."""

from __future__ import annotations

import math
import pickle

import numpy as np
import pytest

from ctrplan.errors import InputError
from ctrplan.robot import load_robot
from ctrplan.shape.base import ShapeModel
from ctrplan.shape.effects import (
    EFFECT_NAMES,
    EffectModel,
    clearance_kinks,
    complete_effects,
    effect_params,
    off_values,
    parse_effect_arg,
)
from ctrplan.shape.physics import PhysicsModel


def _q(robot, n=40, seed=3):
    return robot.sample(n, seed)


@pytest.mark.parametrize("robot", ["seed1", "two_tube_nylon"])
@pytest.mark.parametrize("base", ["rigid", "compliant"])
def test_all_effects_off_is_the_base_model_exactly(robot, base):
    phys = PhysicsModel(robot, torsion=base == "compliant")
    q = _q(phys.robot)
    ref = phys.shape(q, 12)
    for name in EFFECT_NAMES:
        one = EffectModel(robot, base, {name: {}}).shape(q, 12)
        assert np.array_equal(one.points, ref.points, equal_nan=True), name
    every = {e: off_values(e, phys.robot, base) for e in EFFECT_NAMES}
    allm = EffectModel(robot, base, every).shape(q, 12)
    assert np.array_equal(allm.points, ref.points, equal_nan=True)
    assert np.array_equal(allm.radius, ref.radius)
    assert np.array_equal(allm.ok, ref.ok)


def test_every_param_has_bounds_containing_off():
    r = load_robot("seed1")
    for name in EFFECT_NAMES:
        for base in ("rigid", "compliant"):
            for p in effect_params(name, r, base):
                assert p.lo <= p.off <= p.hi and p.unit, (name, p)


def test_each_effect_changes_the_shape():
    r = load_robot("seed1")
    q = _q(r)
    ref = EffectModel(r).shape(q, 2).tip
    on = {"torsion": {"compliance": 1.0}, "friction": {"lost1": 0.2},
          "clearance": {"length": 10.0}, "precurvature": {"scale1": 1.2},
          "stiffness": {"ratio1": 2.0}, "registration": {"tz": 1.0},
          "joint_offset": {"dbeta1": -2.0}, "load": {"gy": 9.81}}
    assert set(on) == set(EFFECT_NAMES)
    for name, vals in on.items():
        tip = EffectModel(r, "rigid", {name: vals}).shape(q, 2).tip
        assert np.max(np.linalg.norm(tip - ref, axis=1)) > 0.05, name


def test_torsion_turns_rigid_into_compliant():
    q = _q(load_robot("seed1"))
    a = EffectModel("seed1", "rigid", {"torsion": {"compliance": 1.0}}).shape(q, 8).points
    b = PhysicsModel("seed1", torsion=True).shape(q, 8).points
    assert np.array_equal(a, b)


def test_registration_is_a_rigid_transform():
    from scipy.spatial.transform import Rotation

    q = _q(load_robot("seed1"))
    r = np.array([0.02, -0.03, 0.1])
    t = np.array([1.0, -2.0, 3.0])
    reg = {"tx": t[0], "ty": t[1], "tz": t[2], "rx": r[0], "ry": r[1], "rz": r[2]}
    a = EffectModel("seed1", "rigid", {"registration": reg}).shape(q, 6).points
    b = PhysicsModel("seed1", torsion=False).shape(q, 6).points
    expect = Rotation.from_rotvec(r).apply(b.reshape(-1, 3)).reshape(b.shape) + t
    np.testing.assert_allclose(a, expect, atol=1e-9)


def test_joint_offset_shifts_the_configuration():
    r = load_robot("seed1")
    q = _q(r)
    off = np.array([0.1, -0.05, 0.02, -1.0, -0.5, 0.0])
    vals = {f"dalpha{i + 1}": off[i] for i in range(3)} | {f"dbeta{i + 1}": off[3 + i] for i in range(3)}
    a = EffectModel(r, "rigid", {"joint_offset": vals}).shape(q, 6).points
    b = PhysicsModel(r, torsion=False).shape(q + off, 6).points
    np.testing.assert_allclose(a, b, atol=1e-12)


def test_friction_is_a_backlash_that_depends_on_direction():
    r = load_robot("two_tube_nylon")
    lost = 0.2
    up = np.linspace(0, 1.0, 11)
    alpha = np.concatenate([up, up[::-1][1:]])              # forward then back
    q = np.zeros((len(alpha), 4))
    q[:, 0] = alpha
    q[:, 2] = -50.0
    m = EffectModel(r, "rigid", {"friction": {"lost1": lost}})
    phys = PhysicsModel(r, torsion=False)
    tips = m.shape(q, 2).tip
    # actual angle: lags by `lost` once moving up; after the reversal it stands still until the
    # command has come back by 2 * lost, then lags the other way
    actual = np.empty_like(alpha)
    e = 0.0
    for k in range(len(alpha)):
        if k:
            e = min(max(e + alpha[k] - alpha[k - 1], -lost), lost)
        actual[k] = alpha[k] - e
    qa = q.copy()
    qa[:, 0] = actual
    np.testing.assert_allclose(tips, phys.shape(qa, 2).tip, atol=1e-12)
    assert actual[10] == pytest.approx(1.0 - lost)            # lag moving up
    assert actual[12] == pytest.approx(actual[10])            # standing in the dead band
    assert actual[-1] == pytest.approx(0.0 + lost)            # lag moving down
    # a new sweep starts settled; same commanded angle, different direction -> different tip
    sweep = np.array(["a"] * 11 + ["b"] * 10, dtype=object)
    tips2 = m.shape(q, 2, sweep=sweep).tip
    np.testing.assert_allclose(tips2[11], phys.shape(q[11:12], 2).tip[0], atol=1e-12)
    assert np.linalg.norm(tips[5] - tips[15]) > 0.1         # alpha 0.5 up vs down


def test_friction_presliding_builds_up_gradually():
    r = load_robot("two_tube_nylon")
    q = np.zeros((30, 4))
    q[:, 0] = np.linspace(0, 1.5, 30)
    q[:, 2] = -50.0
    from ctrplan.shape.effects import prepare

    eff = complete_effects({"friction": {"lost1": 0.2, "presliding": 0.1}}, r, "rigid")
    lag = q[:, 0] - prepare(r, "rigid", eff, q).q[:, 0]
    assert lag[0] == 0 and np.all(np.diff(lag) >= -1e-12)
    assert 0.0 < lag[1] < 0.2 and lag[-1] == pytest.approx(0.2, abs=1e-6)


def test_clearance_tilt_depends_on_relative_rotation():
    r = load_robot("two_tube_nylon")
    n = r.n
    rel = np.linspace(-math.pi, math.pi, 25)
    q = np.zeros((len(rel), 4))
    q[:, 0] = rel
    q[:, 2] = -20.0
    kappa = np.broadcast_to(r.array("curvature"), (len(q), n)).copy()
    EI = np.broadcast_to(r.array("bending_stiffness"), (len(q), n)).copy()
    k = clearance_kinks(r, q, kappa, EI, 10.0)
    mag = np.hypot(k[:, 1, 0], k[:, 1, 1])
    assert np.all(k[:, 0] == 0.0)                  # nothing where the innermost tube ends
    assert mag[12] < mag[0] and mag.max() > 0.05   # opposed curvatures tilt most
    lim = clearance_kinks(r, q, kappa, EI, 10.0, limit=0.05)
    assert np.hypot(lim[:, 1, 0], lim[:, 1, 1]).max() <= 0.05 + 1e-12
    assert np.all(clearance_kinks(r, q, kappa, EI, 0.0) == 0.0)


def test_effects_compose():
    r = load_robot("seed1")
    q = _q(r)
    reg = {"tx": 2.0}
    a = EffectModel(r, "rigid", {"precurvature": {"scale2": 1.1}, "registration": reg}).shape(q, 4).points
    b = EffectModel(r, "rigid", {"precurvature": {"scale2": 1.1}}).shape(q, 4).points
    np.testing.assert_allclose(a, b + np.array([2.0, 0, 0]), atol=1e-12)


def test_effect_model_is_a_shape_model_picklable_and_saved(tmp_path):
    from ctrplan.shape.models import load_model

    eff = {"clearance": {"length": 5.0}, "friction": {"lost1": 0.1}, "stiffness": {"ratio2": 1.3}}
    m = EffectModel("seed1", "compliant", eff)
    assert isinstance(m, ShapeModel)
    q = _q(m.robot, 10)
    m2 = pickle.loads(pickle.dumps(m))
    np.testing.assert_array_equal(m2.backbone(q, 5), m.backbone(q, 5))
    path = tmp_path / "calibrated.yaml"
    m.save(path)
    m3 = load_model(str(path), "seed1")
    assert isinstance(m3, EffectModel) and m3.effects == m.effects and m3.base == "compliant"
    np.testing.assert_array_equal(m3.backbone(q, 5), m.backbone(q, 5))
    with pytest.raises(InputError, match="calibrated for robot"):
        load_model(str(path), "two_tube_nylon")


def test_bad_effects_are_input_errors():
    r = load_robot("seed1")
    with pytest.raises(InputError, match="unknown effect"):
        complete_effects({"gravity": {}}, r, "rigid")
    with pytest.raises(InputError, match="unknown parameter"):
        complete_effects({"clearance": {"gap": 1.0}}, r, "rigid")
    with pytest.raises(InputError, match="clearance.length"):
        complete_effects({"clearance": {"length": -1.0}}, r, "rigid")
    with pytest.raises(InputError):
        complete_effects({"clearance": {"length": float("nan")}}, r, "rigid")
    with pytest.raises(InputError):
        parse_effect_arg("friction:lost1")
    assert parse_effect_arg("friction:lost1=0.1, lost2=0.2") == ("friction", {"lost1": 0.1, "lost2": 0.2})
    assert parse_effect_arg("torsion") == ("torsion", {})


# ------------------------------------------------------------------ forms and contracts (issue 12)
def test_friction_with_direction_is_a_pure_function_of_q_and_direction():
    from ctrplan.shape.base import needs_direction

    r = load_robot("seed1")
    q = _q(r, 30, seed=5)
    rng = np.random.default_rng(0)
    D = rng.integers(-1, 2, size=q.shape).astype(np.int8)
    lost = {"lost1": 0.1, "lost2": 0.05, "lost3": 0.02}
    phys = PhysicsModel(r, torsion=False)
    for form in (0.0, 1.0):          # dead band and constant lag: settled lag against D
        m = EffectModel(r, "rigid", {"friction": {**lost, "form": form}})
        assert needs_direction(m)
        tips = m.shape(q, 2, direction=D).tip
        perm = rng.permutation(len(q))
        np.testing.assert_array_equal(m.shape(q[perm], 2, direction=D[perm]).tip, tips[perm])
        qa = q.copy()
        qa[:, :3] -= D[:, :3] * np.array([0.1, 0.05, 0.02])     # oracle: commanded - lost * D
        np.testing.assert_allclose(tips, phys.shape(qa, 2).tip, atol=1e-12)
    # relative form: a tube is dragged by a neighbour turning against it
    m = EffectModel(r, "rigid", {"friction": {"lost1": 0.1, "form": 2.0}})
    D2 = np.zeros((1, 6), dtype=np.int8)
    D2[0, 1] = 1                                                # tube 2 turns +, tube 1 held
    qa = q[:1].copy()
    qa[0, 0] += 0.1                                             # tube 1 is dragged along (+)
    np.testing.assert_allclose(m.shape(q[:1], 2, direction=D2).tip, phys.shape(qa, 2).tip,
                               atol=1e-12)
    assert not needs_direction(EffectModel(r, "rigid", {"friction": {}}))


def test_friction_windup_grows_the_lag_with_the_square_of_the_retracted_length():
    """windup: the lag is lost + wind (-beta / L)^2 (friction spread along the retracted
    length twists it by tau l^2 / 2 GJ). Oracle: the closed form applied to the joint values
    of the plain mechanics; a presliding build-up develops the same lag."""
    r = load_robot("seed1")
    q = _q(r, 30, seed=6)
    rng = np.random.default_rng(1)
    D = rng.choice([-1, 1], size=q.shape).astype(np.int8)
    lost = np.array([0.1, 0.05, 0.02])
    wind = np.array([0.04, 0.0, 0.03])
    fr = {f"lost{i + 1}": v for i, v in enumerate(lost)} | {f"wind{i + 1}": v
                                                           for i, v in enumerate(wind)}
    phys = PhysicsModel(r, torsion=False)
    frac = np.clip(-q[:, 3:] / r.lengths, 0, 1)
    assert np.ptp(frac) > 0.3
    for extra, lag in (({"windup": 1.0}, lost + wind * frac ** 2), ({}, lost + 0 * frac)):
        m = EffectModel(r, "rigid", {"friction": {**fr, "form": 1.0, **extra}})
        qa = q.copy()
        qa[:, :3] -= D[:, :3] * lag
        np.testing.assert_allclose(m.shape(q, 2, direction=D).tip, phys.shape(qa, 2).tip,
                                   atol=1e-12, err_msg=str(extra))
    # presliding with windup: a long monotone rotation at fixed beta develops
    # lost + wind (-beta / L)^2
    q2 = np.zeros((40, 6))
    q2[:, 0] = np.linspace(0, 2.0, 40)
    q2[:, 3:] = [-150.0, -100.0, -50.0]
    from ctrplan.shape.effects import prepare

    eff = complete_effects({"friction": {**fr, "presliding": 0.1, "windup": 1.0}}, r, "rigid")
    lag = q2[:, 0] - prepare(r, "rigid", eff, q2).q[:, 0]
    assert lag[0] == 0.0 and 0.0 < lag[1] < lag[-1]
    assert lag[-1] == pytest.approx(0.1 + 0.04 * (150.0 / r.lengths[0]) ** 2, rel=1e-6)


def test_planning_model_drops_registration_and_is_pure():
    r = load_robot("seed1")
    q = _q(r, 12)
    eff = {"registration": {"tx": 5.0}, "friction": {"lost1": 0.2},
           "clearance": {"c1": 0.05}}
    m = EffectModel(r, "rigid", eff, error_quantiles={"p50": 1, "p95": 2, "p99": 3, "max": 4})
    pm = m.planning_model()
    assert "registration" not in pm.effects and pm.error_quantiles == m.error_quantiles
    # no direction known: no lag; rows independent of their order
    ref = EffectModel(r, "rigid", {"clearance": {"c1": 0.05}}).shape(q, 4).points
    np.testing.assert_array_equal(pm.shape(q, 4).points, ref)
    np.testing.assert_array_equal(pm.shape(q[::-1], 4).points, ref[::-1])
    D = np.ones_like(q, dtype=np.int8)
    assert not np.allclose(pm.shape(q, 4, direction=D).points, ref)


def test_clearance_harmonic_tilts_towards_bending_direction_with_free_phase():
    from ctrplan.shape.effects import clearance_harmonic_kinks

    r = load_robot("two_tube_nylon")
    phi = np.linspace(-math.pi, math.pi, 73)
    q = np.zeros((len(phi), 4))
    q[:, 0] = phi - 0.4            # alpha1 - alpha2 = phi, alpha2 = -0.4
    q[:, 1] = -0.4
    q[:, 2:] = -10.0
    peak = math.radians(205.0)
    k = clearance_harmonic_kinks(r, q, [0.0, 0.1 * math.cos(peak), 0.1 * math.sin(peak), 0, 0])
    assert np.all(k[:, 0] == 0.0)
    # the rotation axis is tube 1's curvature axis (-sin a1, cos a1): tilt towards its bending
    axis = np.stack([-np.sin(q[:, 0]), np.cos(q[:, 0])], 1)
    t = (k[:, 1] * axis).sum(1)
    np.testing.assert_allclose(np.abs(t), np.hypot(k[:, 1, 0], k[:, 1, 1]), atol=1e-12)
    assert math.degrees(phi[np.argmax(t)]) % 360 == pytest.approx(205.0, abs=5.1)
    np.testing.assert_allclose(t, 0.1 * np.cos(phi - peak), atol=1e-12)
    # off is exact; the form changes the tip
    base = EffectModel(r).shape(q, 2).tip
    np.testing.assert_array_equal(EffectModel(r, "rigid", {"clearance": {"c0": 0.0}}).shape(q, 2).tip, base)
    assert np.max(np.linalg.norm(EffectModel(r, "rigid", {"clearance": {"c0": 0.05}}).shape(q, 2).tip
                                 - base, axis=1)) > 1.0


def test_error_quantiles_round_trip_through_calibrated_yaml(tmp_path):
    from ctrplan.shape.base import model_error_bound
    from ctrplan.shape.models import load_model

    eq = {"p50": 0.4, "p95": 1.1, "p99": 1.6, "max": 2.0}
    m = EffectModel("seed1", "rigid", {"torsion": {"compliance": 0.8}}, error_quantiles=eq)
    m.save(tmp_path / "calibrated.yaml")
    m2 = load_model(str(tmp_path / "calibrated.yaml"), "seed1")
    assert m2.error_quantiles == eq and model_error_bound(m2) == 1.6
    text = (tmp_path / "calibrated.yaml").read_text().replace("p99: 1.6", "p99: -1")
    (tmp_path / "bad.yaml").write_text(text)
    with pytest.raises(InputError, match="error_quantiles.p99"):
        load_model(str(tmp_path / "bad.yaml"), "seed1")


def test_end_moment_friction_twists_both_tubes_of_the_pair():
    # hand-computed oracle (two_tube_nylon): where the outer tube ends (s = 174 mm, both tubes
    # curved there) the torque mu |M| twists the inner tube by -T l_1/GJ_1 and the outer one by
    # +T l_2/GJ_2, the sign following the relative direction (inner turning +, outer held)
    r = load_robot("two_tube_nylon")
    a1, a2, b1, b2, mu = 0.3, -0.5, -50.0, 0.0, 0.02
    E, nu = 1700.0, 0.41
    inertia = [math.pi / 64 * (4.5 ** 4 - 3.0 ** 4), math.pi / 64 * (6.8 ** 4 - 4.9 ** 4)]
    EI = [E * i for i in inertia]
    GJ = [E / (2 * (1 + nu)) * 2 * i for i in inertia]
    k1, k2 = 0.010152284, 0.010309278
    ux = (EI[0] * k1 * -math.sin(a1) + EI[1] * k2 * -math.sin(a2)) / (EI[0] + EI[1])
    uy = (EI[0] * k1 * math.cos(a1) + EI[1] * k2 * math.cos(a2)) / (EI[0] + EI[1])
    M = EI[1] * math.hypot(ux + k2 * math.sin(a2), uy - k2 * math.cos(a2))
    expect = np.array([[a1 - mu * M * (174.0 - b1) / GJ[0], a2 + mu * M * (174.0 - b2) / GJ[1],
                        b1, b2]])
    q = np.array([[a1, a2, b1, b2]])
    D = np.array([[1, 0, 0, 0]], dtype=np.int8)
    m = EffectModel(r, "rigid", {"friction": {"form": 3.0, "mu": mu}})
    got = m.shape(q, 2, direction=D).tip
    np.testing.assert_allclose(got, PhysicsModel(r, torsion=False).shape(expect, 2).tip,
                               atol=1e-9)
    assert abs(expect[0, 0] - a1) > 1e-3                         # a visible twist
    # reversed relative direction: the opposite twist; both turning the same way: none
    np.testing.assert_allclose(m.shape(q, 2, direction=-D).tip, PhysicsModel(r, torsion=False).shape(
        np.array([[2 * a1 - expect[0, 0], 2 * a2 - expect[0, 1], b1, b2]]), 2).tip, atol=1e-9)
    np.testing.assert_array_equal(m.shape(q, 2, direction=np.array([[1, 1, 0, 0]])).tip,
                                  PhysicsModel(r, torsion=False).shape(q, 2).tip)
