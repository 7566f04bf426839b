"""Robot model: shipped robots, YAML validation (errors name the field), constraints, sampling."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml
from scipy import stats

from ctrplan.errors import InputError
from ctrplan.robot import load_robot, read_configs, robot_from_dict, wrap_angle, write_configs

GOOD = {
    "name": "t",
    "tubes": [
        {"od": 1.3, "id": 1.0, "straight_length": 200.0, "curved_length": 60.0,
         "curvature": 0.01, "youngs_modulus": 60000, "poisson_ratio": 0.33},
        {"od": 1.9, "id": 1.6, "straight_length": 150.0, "curved_length": 40.0,
         "curvature": 0.005, "youngs_modulus": 60000, "poisson_ratio": 0.33},
    ],
}


def _write(tmp_path, data, name="r.yaml"):
    p = tmp_path / name
    p.write_text(data if isinstance(data, str) else yaml.safe_dump(data))
    return p


def _bad(tube: int, **change):
    d = {"name": "t", "tubes": [dict(t) for t in GOOD["tubes"]]}
    d["tubes"][tube].update(change)
    return d


def test_shipped_seed1_matches_the_issue(seed1):
    assert seed1.n == 3
    np.testing.assert_allclose(seed1.array("od"), [1.3, 1.9, 2.5])
    np.testing.assert_allclose(seed1.array("id"), [1.0, 1.6, 2.2])
    np.testing.assert_allclose(seed1.array("straight_length"), [245.9, 163.1, 95.2])
    np.testing.assert_allclose(seed1.array("curved_length"), [66.6, 45.6, 36.4])
    np.testing.assert_allclose(seed1.array("curvature") * 1000, [9.3354, 4.6270, 7.4184])
    np.testing.assert_allclose(seed1.array("youngs_modulus"), 60000.0)
    np.testing.assert_allclose(seed1.array("poisson_ratio"), 0.33)


def test_shipped_two_tube_nylon(nylon):
    assert nylon.n == 2
    assert nylon.tubes[0].od == 4.5 and nylon.tubes[1].od == 6.8 and nylon.tubes[1].id == 4.9
    np.testing.assert_allclose(1.0 / nylon.array("curvature"), [98.5, 97.0], rtol=1e-6)
    np.testing.assert_allclose(nylon.array("curved_length"), [114.0, 74.0])
    np.testing.assert_allclose(nylon.array("poisson_ratio"), 0.41)


def test_yaml_round_trip(tmp_path, seed1):
    p = tmp_path / "seed1.yaml"
    seed1.save(p)
    again = load_robot(p)
    assert again == seed1


@pytest.mark.parametrize("data,field", [
    (_bad(0, id=1.3), "tubes[0].id"),                       # id >= od
    (_bad(1, id=1.2), "tubes[1].id"),                       # not nested around tube 1
    (_bad(0, youngs_modulus=0), "tubes[0].youngs_modulus"),
    (_bad(1, youngs_modulus=-5), "tubes[1].youngs_modulus"),
    (_bad(0, poisson_ratio=0.5), "tubes[0].poisson_ratio"),
    (_bad(0, poisson_ratio=-0.1), "tubes[0].poisson_ratio"),
    (_bad(0, od=-1.0), "tubes[0].od"),
    (_bad(1, curved_length=-1.0), "tubes[1].curved_length"),
    (_bad(0, curvature=float("nan")), "tubes[0].curvature"),
    (_bad(1, straight_length=float("inf")), "tubes[1].straight_length"),
    (_bad(0, curvature="big"), "tubes[0].curvature"),
    (_bad(1, colour="red"), "tubes[1].colour"),              # unknown key
    ({**GOOD, "speed": 3}, "speed"),                         # unknown top-level key
    ({"name": "t", "tubes": []}, "tubes"),
    ({"name": "t", "tubes": [{k: v for k, v in GOOD["tubes"][0].items() if k != "id"}]}, "tubes[0].id"),
])
def test_yaml_validation_names_the_field(tmp_path, data, field):
    p = _write(tmp_path, data)
    with pytest.raises(InputError) as ei:
        load_robot(p)
    assert ei.value.field == field
    assert ei.value.source == str(p)
    assert str(p) in str(ei.value) and field in str(ei.value)
    assert "\n" not in str(ei.value)


def test_malformed_yaml_names_the_file_and_line(tmp_path):
    p = _write(tmp_path, "name: t\ntubes: [ {od: 1\n")
    with pytest.raises(InputError) as ei:
        load_robot(p)
    assert str(p) in str(ei.value) and "line" in ei.value.field


def test_unknown_robot_name():
    with pytest.raises(InputError, match="not a shipped robot"):
        load_robot("no_such_robot")


def test_constraints(seed1):
    n = seed1.n
    q = seed1.retracted()
    assert seed1.is_valid(q[None])[0]
    L = seed1.lengths
    beta = np.array([-100.0, -60.0, -20.0])
    ok = np.concatenate([np.zeros(n), beta])
    assert seed1.is_valid(ok[None])[0]

    def with_beta(b):
        return np.concatenate([np.full(n, 0.3), b])[None]

    assert not seed1.is_valid(with_beta([-100.0, -60.0, 1.0]))[0]          # beta_n <= 0
    assert not seed1.is_valid(with_beta([-50.0, -60.0, -20.0]))[0]         # beta_1 <= beta_2
    # inner tubes reach at least as far: tube 1 shorter than tube 2 beyond the plane
    b = np.array([-150.0, -60.0, -20.0])
    b[0] = -60.0 + L[1] - L[0] - 1.0
    assert not seed1.is_valid(with_beta(b))[0]
    # curved section behind the constraint plane
    assert not seed1.is_valid(with_beta([-250.0, -60.0, -20.0]))[0]
    assert not seed1.is_valid(np.full((1, 2 * n), np.nan))[0]
    # alpha is free
    assert seed1.is_valid(np.concatenate([[100.0, -7.0, 3.0], beta])[None])[0]
    with pytest.raises(ValueError):
        seed1.is_valid(np.zeros((1, 5)))


def test_retracted_is_valid_for_shipped_robots(seed1, nylon):
    for r in (seed1, nylon):
        q = r.retracted()
        assert q.shape == (r.dof,)
        assert r.is_valid(q[None])[0]
        np.testing.assert_array_equal(q[:r.n], 0.0)


def _valid_by_hand(robot, beta):
    """Independent transcription of the DESIGN.md constraints."""
    L = robot.lengths
    straight = robot.array("straight_length")
    ok = np.all(beta <= 0, axis=1)
    ok &= np.all(np.diff(beta, axis=1) >= 0, axis=1)
    ok &= np.all((beta[:, :-1] + L[:-1]) >= (beta[:, 1:] + L[1:]), axis=1)
    ok &= beta[:, -1] + L[-1] >= 0
    ok &= np.all(beta + straight >= 0, axis=1)
    return ok


def test_sample_is_valid_deterministic_and_uniform(seed1):
    """Uniform over the valid set: each beta marginal matches that of brute-force rejection
    from a box (independent code and seed) by a two-sample KS test; alphas are uniform on
    (-pi, pi]. n = 4000 each, reject at p < 1e-3 (a false alarm 1 in 1000 per test; the seeds
    are fixed so the outcome is deterministic)."""
    n = 4000
    q = seed1.sample(n, seed=123)
    assert q.shape == (n, seed1.dof)
    assert seed1.is_valid(q).all()
    np.testing.assert_array_equal(q, seed1.sample(n, seed=123))
    assert not np.array_equal(q, seed1.sample(n, seed=124))

    rng = np.random.default_rng(999)
    lo = -seed1.array("straight_length")
    ref = np.empty((0, seed1.n))
    while len(ref) < n:
        b = rng.uniform(lo, 0.0, size=(20000, seed1.n))
        ref = np.concatenate([ref, b[_valid_by_hand(seed1, b)]])
    ref = ref[:n]
    beta = q[:, seed1.n:]
    for i in range(seed1.n):
        p = stats.ks_2samp(beta[:, i], ref[:, i]).pvalue
        assert p > 1e-3, (i, p)
    alpha = q[:, :seed1.n]
    assert np.all(alpha > -math.pi) and np.all(alpha <= math.pi)
    for i in range(seed1.n):
        p = stats.kstest(alpha[:, i], stats.uniform(loc=-math.pi, scale=2 * math.pi).cdf).pvalue
        assert p > 1e-3, (i, p)


def test_wrap_angle():
    a = np.array([0.0, math.pi, -math.pi, 3 * math.pi, 7.0, -7.0])
    w = wrap_angle(a)
    assert np.all(w > -math.pi) and np.all(w <= math.pi)
    np.testing.assert_allclose(np.cos(w), np.cos(a), atol=1e-12)
    np.testing.assert_allclose(np.sin(w), np.sin(a), atol=1e-12)
    assert w[2] == pytest.approx(math.pi)


def test_config_csv_round_trip(tmp_path, seed1):
    q = seed1.sample(7, seed=1)
    p = tmp_path / "c.csv"
    write_configs(p, seed1, q)
    assert p.read_text().splitlines()[0] == "alpha1,alpha2,alpha3,beta1,beta2,beta3"
    np.testing.assert_array_equal(read_configs(p, seed1), q)


def test_robot_from_dict_rejects_non_mapping():
    with pytest.raises(InputError):
        robot_from_dict([1, 2], source="x.yaml")


def test_sampling_a_zero_volume_valid_set_raises_instead_of_looping():
    from tests.conftest import overlap_pair

    robot = overlap_pair()              # equal lengths force beta1 == beta2
    assert robot.is_valid(np.array([[0.0, 0.0, -50.0, -50.0]]))[0]
    with pytest.raises(InputError, match="sample"):
        robot.sample(3, seed=0)


def test_radius_along_is_the_outermost_tube_present():
    """radius_along (a compiled kernel) against a plain loop written here: at each arc length
    the outer radius of the outermost tube whose distal end is not before it (the innermost
    past the tip, and where an arc length is NaN), on configurations inside and outside the
    joint limits; the robot's cached per-tube arrays come back as fresh copies."""
    from ctrplan.shape.base import radius_along

    rng = np.random.default_rng(3)
    for name in ("seed1", "two_tube_nylon"):
        robot = load_robot(name)
        n = robot.n
        q = np.c_[rng.uniform(-3, 3, (200, n)), rng.uniform(-120, 5, (200, n))]
        s = rng.uniform(-5, 300, (200, 17))
        s[0, 3] = np.nan
        want = np.empty_like(s)
        for b in range(len(q)):
            for j in range(s.shape[1]):
                k = 0
                for i, tube in enumerate(robot.tubes):
                    if s[b, j] <= q[b, n + i] + tube.length + 1e-9:
                        k = i
                want[b, j] = robot.tubes[k].od / 2.0
        np.testing.assert_array_equal(radius_along(robot, q, s), want)
        a = robot.array("od")
        a[:] = -1.0
        assert np.all(robot.array("od") > 0)
