"""Friction named by its signature (``ctrplan.calibration.select.name_by_signature``).

Friction is the one vocabulary effect whose shapes depend on the direction of motion; a small
friction next to large effects fails the shares that guard against misfit absorbers, and is
then named only when the residual without it shows hysteresis that it removes. The cases build
residuals whose direction dependence is known by construction (no prediction of ctrplan's): a
back-and-forth walk of the joints, and tips off by a fixed vector that flips with the direction
of the last rotation of tube 1 (hysteresis) or does not (a configuration-dependent error).
"""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from ctrplan.calibration.result import Step
from ctrplan.calibration.select import SelectConfig, Selection, name_by_signature
from ctrplan.shape.base import direction_from_rows

B = 400


def _walk(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """(B, 4) rows of a two-tube back-and-forth walk (reversals every ~25 rows), 4 sweeps."""
    rng = np.random.default_rng(seed)
    q = np.zeros((B, 4))
    d = np.ones(4)
    for k in range(1, B):
        d = np.where(rng.random(4) < 0.04, -d, d)
        q[k] = q[k - 1] + d * np.array([0.05, 0.04, 0.3, 0.2]) * rng.uniform(0.5, 1.5, 4)
    q[:, 2:] = -np.abs(q[:, 2:]) % 40.0 - 10.0
    return q, np.repeat(np.array(["a", "b", "c", "d"], dtype=object), B // 4)


class _Prob:
    """The part of ``Problem`` the rule uses: data rows, measured tips, and predictions of an
    effect set (tip points (B, 2, 3)) given by the case: ``off`` without friction, ``on`` with."""

    def __init__(self, q, tip, on, off):
        self.data = SimpleNamespace(q=q)
        self.tip = tip
        self._on, self._off = on, off

    def predict_many(self, sets):
        return [np.stack([np.zeros_like(self.tip), self._on if "friction" in s else self._off],
                         axis=1) for s in sets]


def _step(effect, named, gain=0.2, dbic=-50.0):
    return Step(effect=effect, accepted=True, parameters={}, sigma={}, error_before_mm=1.0,
                error_after_mm=1.0 - gain, max_before_mm=2.0, max_after_mm=1.8,
                delta_bic=dbic, heldout_gain=gain, runner_up=None, runner_up_delta_bic=None,
                ambiguous=False, named=named)


def _case(off_hyst: float, on_hyst: float, gain=0.2, dbic=-50.0, seed=0):
    """Selection with torsion named and friction kept unnamed; the model without friction is
    off by ``off_hyst`` mm x (direction of tube 1's last rotation), with it by ``on_hyst``;
    both share a configuration-dependent error and 0.05 mm noise."""
    q, sw = _walk(seed)
    direction = direction_from_rows(q, sw)
    rng = np.random.default_rng(seed + 1)
    tip = rng.normal(0.0, 0.05, (B, 3))
    smooth = np.c_[np.cos(q[:, 0]), np.sin(q[:, 1]), 0.01 * q[:, 2]]   # same either way
    flip = direction[:, :1] * np.array([[1.0, 0.5, 0.0]])
    off = tip + smooth + off_hyst * flip
    on = tip + smooth + on_hyst * flip + rng.normal(0.0, 0.05, (B, 3))
    sel = Selection({"torsion": {}, "friction": {}}, None, {"torsion": [], "friction": []},
                    [_step("torsion", True), _step("friction", False, gain, dbic)], {})
    rows = np.ones(B, dtype=bool)
    return name_by_signature(_Prob(q, tip, on, off), sel, rows, direction, 0.05, SelectConfig())


def _friction(sel):
    return next(s for s in sel.steps if s.effect == "friction")


def test_friction_that_removes_the_hysteresis_is_named():
    st = _friction(_case(off_hyst=0.6, on_hyst=0.0))
    assert st.named and st.named_by.startswith("hysteresis")


@pytest.mark.parametrize("off_hyst,on_hyst", [(0.0, 0.0), (0.6, 0.5)])
def test_no_hysteresis_or_hysteresis_left_names_nothing(off_hyst, on_hyst):
    """No direction dependence without friction, or friction that leaves most of it: its
    signature is not in the evidence."""
    st = _friction(_case(off_hyst, on_hyst))
    assert not st.named and st.named_by == ""


@pytest.mark.parametrize("gain,dbic", [(0.01, -50.0), (0.2, 0.0)])
def test_friction_below_the_named_grade_gain_or_bic_is_not_named(gain, dbic):
    assert not _friction(_case(0.6, 0.0, gain=gain, dbic=dbic)).named


def test_only_friction_is_named_by_signature():
    """An unnamed non-friction effect stays unnamed whatever the hysteresis."""
    q, sw = _walk()
    direction = direction_from_rows(q, sw)
    tip = np.zeros((B, 3))
    off = direction[:, :1] * np.array([[0.6, 0.0, 0.0]])
    sel = Selection({"clearance": {}}, None, {"clearance": []}, [_step("clearance", False)], {})
    out = name_by_signature(_Prob(q, tip, off, off), sel, np.ones(B, bool), direction, 0.05,
                            SelectConfig())
    assert not out.steps[0].named
