"""Physical effects that extend the mechanics model, and :class:`EffectModel` that composes them.

Every effect has named physical parameters with bounds and an *off* value; with all parameters
off an :class:`EffectModel` returns exactly the base model's shapes (same kernel call, same
inputs). Effects act at three stages of one batched :meth:`PhysicsModel.solve` call:

1. joint space (``joint_offset``, ``friction``): the configuration the tubes really reach;
2. mechanics (``precurvature``, ``stiffness``, ``torsion``, ``clearance``): per-configuration
   :class:`~ctrplan.shape.physics.MechanicsParams` handed to the kernel;
3. sensor (``registration``): the rigid transform from the robot base to the sensor frame.

The vocabulary (docs/conventions.md):

``torsion``
    Torsional compliance of the tubes. ``compliance`` scales every tube's EI/GJ; 0 is the
    torsionally rigid ("traditional") model, 1 the nominal material (compliant model). Off: 0 on
    a rigid base, 1 on a compliant base. Form parameter ``inner_factor`` (not fitted) scales
    the innermost tube's compliance further.
``friction``
    Rotation lost in transmission, depending on the direction of motion; a family of forms
    (form parameter ``form``, not fitted; :data:`FRICTION_FORMS`), chosen by diagnose like any
    effect. ``dead_band`` (0): each tube's actual base angle follows the commanded one through a
    backlash of half-width ``lost<i>`` rad (moving up it lags by ``lost<i>``; after a reversal it
    stands still until the command has crossed the dead band); with ``presliding`` > 0 (rad) the
    lag builds up exponentially over that much rotation instead (Dahl-type). ``lag`` (1): a
    constant lag ``lost<i>`` against each tube's own direction of motion. ``relative`` (2): a lag
    ``lost<i>`` against the direction of rotation relative to the adjacent tubes (a tube is
    dragged along by a neighbour turning against it). ``end_moment`` (3): ``relative`` plus the
    study's concentrated end moment: where outer tube o ends a torque ``mu |M|`` (``|M|`` its
    bending moment there) twists tube o by ``+T l_o / GJ_o`` and tube o-1 by ``-T l / GJ``
    (l: each tube's length from its base to that point), its sign following the direction of
    relative rotation (the study's ``dtheta``); ``mu`` fitted. ``windup`` 1 (a form
    parameter, not fitted; diagnose screens ``lag`` and ``presliding`` with it): friction
    distributed along the part of each tube behind the base plane (its guide or support tube)
    winds the tube up over that length: a torque ``tau`` per unit length over the retracted
    length ``l`` twists the tube by ``tau l^2 / (2 GJ)``, so the lag is
    ``lost<i> + wind<i> (-beta_i / L_i)^2`` (both fitted; the retracted fraction is clipped to
    [0, 1]). The direction of motion: given as
    ``direction`` (B, 2n) in {-1, 0, +1} every row is a pure function of (q, direction) (the
    settled lag); without it, rows are taken in order as one continuous motion per sweep (the
    ``time``/row order of measured data), each sweep starting settled.
``clearance``
    Where outer tube j ends, the tubes inside it tilt within the radial gap (a kink
    R <- R Exp([kx, ky, 0]) of the backbone frame). Harmonic form (fitted ``c0, c1, s1, c2,
    s2``, rad): the tilt ``c0 + c1 cos phi + s1 sin phi + c2 cos 2phi + s2 sin 2phi`` of the
    relative rotation phi = alpha_(j-1) - alpha_j, about tube j-1's curvature axis, i.e. towards
    its bending direction (as in the study); its peak may sit at any relative rotation (the
    study found 205 deg). Gap form (fitted ``length``, mm): the frame rotates by
    ``length * du``, where ``du`` is the jump of the (torsionally rigid) curvature vector across
    the tube's end (largest when the curvatures oppose); form parameter ``limit`` (rad, not
    fitted; 0 = none) saturates that tilt: ``theta -> limit * tanh(theta / limit)``. The
    curvature on each side of the end is averaged over :data:`GAP_WINDOW_MM` (1 mm), so the
    tilt changes continuously (steeply) where a curved section starts or another tube ends
    near the end, instead of stepping.
``precurvature``
    Per-tube scale ``scale<i>`` of the precurvature (off 1).
``stiffness``
    Bending stiffness of tube i relative to the outermost tube, ``ratio<i>`` for i < n (off 1;
    only ratios change the unloaded shape).
``registration``
    Rigid transform sensor <- robot base: ``p_sensor = Rot(rx, ry, rz) p + (tx, ty, tz)``
    (rotation vector in rad, translation in mm; off 0).
``joint_offset``
    Zero offsets of the joints: the tubes are at ``alpha_i + dalpha<i>``, ``beta_i + dbeta<i>``
    (rad, mm; off 0).
``load``
    External loads (:class:`~ctrplan.shape.physics.Loads`, base frame). Fitted: gravity
    ``gx, gy`` (m/s^2; the component across the insertion axis, i.e. direction and magnitude
    of the sag of a robot that is not vertical; weight per length from each tube's ``density``,
    nitinol's where none is given, so a wrong density shows as a scaled g) and a tip force
    ``fx, fy, fz`` (N; the axial one too: a pull along the axis, such as a tracker sensor's lead
    tensioned through the lumen, bends a curved robot by the tip's lateral offset). Set by hand
    (not fitted: an axial weight barely bends the robot): ``gz`` (m/s^2). Off: all 0 (the
    unloaded kernel runs). On a rigid base the
    loaded model is torsionally rigid (see :class:`~ctrplan.shape.physics.PhysicsModel`).

A caveat written down once: on a compliant base the clearance tilt direction uses the base
angles alpha (the rigid model's tube angles), not the twisted angles at the tube's end.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numba import njit

from ctrplan.errors import InputError
from ctrplan.robot import Robot, load_robot
from ctrplan.shape.base import Shape, check_q, direction_from_rows, radius_along
from ctrplan.shape.physics import MechanicsParams, PhysicsConfig, PhysicsModel, tube_weights

EFFECT_NAMES = ("torsion", "friction", "clearance", "precurvature", "stiffness", "registration",
                "joint_offset", "load")
BASES = ("rigid", "compliant")

#: Friction forms (the ``form`` code of the friction effect is the index):
#: ``dead_band`` a backlash taken in row order (Dahl-type with ``presliding`` > 0);
#: ``lag`` a constant lag against each tube's own direction of motion;
#: ``relative`` a constant lag against the direction of rotation relative to the adjacent tubes
#: (a tube is dragged along by a neighbour turning against it; the study's ``dtheta``);
#: ``end_moment`` ``relative`` plus the twist of a torque ``mu |M|`` where each outer tube ends
#: (the study's concentrated end moment, ``beta'(L) = mu' |M| (1/k2z - 1/k1z)``; see
#: :func:`end_moment_twist`).
FRICTION_FORMS = ("dead_band", "lag", "relative", "end_moment")

#: Harmonic coefficients of the clearance tilt in the relative rotation phi of the tube that ends
#: and the next tube inside it: tilt(phi) = c0 + c1 cos phi + s1 sin phi + c2 cos 2phi + s2 sin 2phi
#: (rad), about the inner tube's curvature axis (towards its bending direction).
CLEARANCE_HARMONICS = (("c0", "constant tilt towards the inner tube's bending direction"),
                       ("c1", "tilt, cos(relative rotation) term"),
                       ("s1", "tilt, sin(relative rotation) term"),
                       ("c2", "tilt, cos(2 relative rotation) term"),
                       ("s2", "tilt, sin(2 relative rotation) term"))

#: File kind written by :meth:`EffectModel.save` and recognised by ``load_model``.
MODEL_KIND = "ctrplan-effect-model"


@dataclass(frozen=True)
class Param:
    """One effect parameter: name, off value, bounds, unit, meaning; ``fit`` False for form
    parameters that describe the effect's shape and are held fixed when fitting."""

    name: str
    off: float
    lo: float
    hi: float
    unit: str
    doc: str
    fit: bool = True
    typical: float | None = None   # a typical magnitude (the fit's step unit); None: by unit


def effect_params(name: str, robot: Robot, base: str = "rigid") -> tuple[Param, ...]:
    """The parameters of effect ``name`` for ``robot`` on ``base`` (``rigid``/``compliant``)."""
    n = robot.n
    if name == "torsion":
        off = 1.0 if base == "compliant" else 0.0
        return (Param("compliance", off, 0.0, 5.0, "1", "scale of EI/GJ (0 rigid, 1 nominal)"),
                Param("inner_factor", 1.0, 0.2, 5.0, "1", "extra scale of tube 1's compliance",
                      fit=False))
    if name == "friction":
        return tuple(Param(f"lost{i + 1}", 0.0, 0.0, 1.0, "rad",
                           f"rotation lost in transmission of tube {i + 1} (lag / dead-band "
                           "half-width)") for i in range(n)) + (
            Param("mu", 0.0, 0.0, 1.0, "1", "end-moment friction: a torque mu |M| where an "
                  "outer tube ends (|M| its bending moment there) twists both tubes of the pair "
                  "(end_moment form)", fit=False, typical=0.01),
            Param("presliding", 0.0, 0.0, 1.0, "rad", "rotation over which the lag builds up "
                  "(0 = ideal backlash; dead_band form)", fit=False)) + tuple(
            Param(f"wind{i + 1}", 0.0, 0.0, 1.0, "rad", f"lag of tube {i + 1} at full "
                  f"retraction, times (-beta{i + 1} / L{i + 1})^2 (windup forms)", fit=False)
            for i in range(n)) + (
            Param("windup", 0.0, 0.0, 1.0, "1", "1: the lags grow with the square of the "
                  "retracted length, lost<i> + wind<i> (-beta<i> / L<i>)^2; 0: constant lags",
                  fit=False),
            Param("form", 0.0, 0.0, float(len(FRICTION_FORMS) - 1), "1",
                  "friction form: " + ", ".join(f"{k} {f}" for k, f in enumerate(FRICTION_FORMS)),
                  fit=False))
    if name == "clearance":
        return (Param("length", 0.0, 0.0, 100.0, "mm",
                      "tilt per unit curvature jump where an outer tube ends"),
                Param("limit", 0.0, 0.0, 1.0, "rad", "largest tilt the gap allows (0 = none)",
                      fit=False)) + tuple(
            Param(h, 0.0, -0.2, 0.2, "rad", doc) for h, doc in CLEARANCE_HARMONICS)
    if name == "precurvature":
        return tuple(Param(f"scale{i + 1}", 1.0, 0.3, 3.0, "1", f"precurvature scale of tube {i + 1}")
                     for i in range(n))
    if name == "stiffness":
        return tuple(Param(f"ratio{i + 1}", 1.0, 0.2, 5.0, "1",
                           f"bending stiffness of tube {i + 1} relative to tube {n} (nominal 1)")
                     for i in range(n - 1))
    if name == "registration":
        return tuple(Param(f"t{c}", 0.0, -50.0, 50.0, "mm", f"sensor-frame translation {c}")
                     for c in "xyz") + tuple(
            Param(f"r{c}", 0.0, -0.5, 0.5, "rad", f"rotation vector component {c}") for c in "xyz")
    if name == "joint_offset":
        return tuple(Param(f"dalpha{i + 1}", 0.0, -0.5, 0.5, "rad", f"zero offset of alpha{i + 1}")
                     for i in range(n)) + tuple(
            Param(f"dbeta{i + 1}", 0.0, -10.0, 10.0, "mm", f"zero offset of beta{i + 1}")
            for i in range(n))
    if name == "load":
        return tuple(Param(f"g{c}", 0.0, -30.0, 30.0, "m/s^2", f"gravity component {c} (base frame)",
                           fit=c != "z") for c in "xyz") + tuple(
            Param(f"f{c}", 0.0, -5.0, 5.0, "N", f"tip force component {c} (base frame)")
            for c in "xyz")
    raise InputError("<effect>", name, f"unknown effect; known: {', '.join(EFFECT_NAMES)}")


def off_values(name: str, robot: Robot, base: str = "rigid") -> dict[str, float]:
    """All parameters of an effect at their off values."""
    return {p.name: p.off for p in effect_params(name, robot, base)}


def effect_variants(name: str, robot: Robot, base: str = "rigid") -> list[tuple[str, dict[str, float], list[str]]]:
    """The forms of effect ``name`` that diagnose screens: ``(form label, fixed form parameter
    values, names of the fitted parameters)``. An effect with one form has a single variant
    (label ``""``) fitting every parameter marked ``fit``."""
    n = robot.n
    if name == "friction":
        lost = [f"lost{i + 1}" for i in range(n)]
        wind = [f"wind{i + 1}" for i in range(n)]
        return [("dead_band", {"form": 0.0, "presliding": 0.0}, lost),
                ("presliding", {"form": 0.0}, [*lost, "presliding"]),
                ("lag", {"form": 1.0, "presliding": 0.0}, lost),
                ("relative", {"form": 2.0, "presliding": 0.0}, lost),
                ("end_moment", {"form": 3.0, "presliding": 0.0}, ["mu"]),
                ("end_moment+lag", {"form": 3.0, "presliding": 0.0}, ["mu", *lost]),
                ("lag/windup", {"form": 1.0, "presliding": 0.0, "windup": 1.0}, [*lost, *wind]),
                ("presliding/windup", {"form": 0.0, "windup": 1.0},
                 [*lost, *wind, "presliding"])]
    if name == "clearance":
        harm = [h for h, _ in CLEARANCE_HARMONICS]
        return [("harmonic", {"length": 0.0, "limit": 0.0}, harm[:3]),
                ("harmonic2", {"length": 0.0, "limit": 0.0}, harm),
                ("gap", {"limit": 0.0}, ["length"])]
    return [("", {}, [p.name for p in effect_params(name, robot, base) if p.fit])]


def effect_form(name: str, values: Mapping[str, float]) -> str:
    """A short label of the form of a fitted effect (for reports)."""
    if name == "friction":
        f = FRICTION_FORMS[int(round(values.get("form", 0.0)))]
        if f == "dead_band" and values.get("presliding", 0.0) > 0:
            f = "presliding"
        return f + "/windup" if values.get("windup", 0.0) > 0 else f
    if name == "clearance":
        harm = any(values.get(h, 0.0) != 0.0 for h, _ in CLEARANCE_HARMONICS)
        gap = values.get("length", 0.0) != 0.0
        return "harmonic+gap" if harm and gap else ("harmonic" if harm else "gap")
    return ""


def complete_effects(effects: Mapping[str, Mapping[str, float]] | None, robot: Robot, base: str,
                     source: str = "<effects>") -> dict[str, dict[str, float]]:
    """Validate effect names/parameters and fill missing parameters with their off values.

    Unknown effects or parameters, non-finite values and values outside the bounds raise
    :class:`InputError` naming ``source`` and the field.
    """
    if base not in BASES:
        raise InputError(source, "base", f"must be one of {', '.join(BASES)}, got {base!r}")
    out: dict[str, dict[str, float]] = {}
    for name in (effects or {}):
        if name not in EFFECT_NAMES:
            raise InputError(source, name, f"unknown effect; known: {', '.join(EFFECT_NAMES)}")
        params = {p.name: p for p in effect_params(name, robot, base)}
        vals = {k: p.off for k, p in params.items()}
        given = effects[name] or {}
        if not isinstance(given, Mapping):
            raise InputError(source, name, "parameters must be a mapping NAME: VALUE")
        for k, v in given.items():
            if k not in params:
                raise InputError(source, f"{name}.{k}",
                                 f"unknown parameter; {name} has {', '.join(params) or 'none'}")
            if isinstance(v, bool) or not isinstance(v, (int, float, np.floating, np.integer)):
                raise InputError(source, f"{name}.{k}", f"must be a number, got {v!r}")
            v = float(v)
            p = params[k]
            if not math.isfinite(v) or not p.lo - 1e-12 <= v <= p.hi + 1e-12:
                raise InputError(source, f"{name}.{k}",
                                 f"must be finite and in [{p.lo}, {p.hi}] {p.unit}, got {v!r}")
            vals[k] = v
        out[name] = vals
    return out


def parse_effect_arg(text: str, source: str = "--effect") -> tuple[str, dict[str, float]]:
    """Parse ``NAME`` or ``NAME:PARAM=VALUE[,PARAM=VALUE...]`` (command-line form)."""
    name, _, rest = text.partition(":")
    name = name.strip()
    if name not in EFFECT_NAMES:
        raise InputError(source, name or text, f"unknown effect; known: {', '.join(EFFECT_NAMES)}")
    vals: dict[str, float] = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        k, eq, v = item.partition("=")
        if not eq:
            raise InputError(source, f"{name}.{item}", "expected PARAM=VALUE")
        try:
            from ctrplan.io import strict_float

            vals[k.strip()] = strict_float(v)
        except ValueError:
            from ctrplan.io import excerpt

            raise InputError(source, f"{name}.{k.strip()}", f"not a number: {excerpt(v)}") from None
    return name, vals


# ---------------------------------------------------------------------------- stage functions
@njit(cache=True)
def _backlash(x, start, lost, presliding):
    """Actual angles (B, n) from commanded ``x`` (B, n) in row order, ``lost`` (B, n) the lag of
    each row; a new sweep starts where ``start`` is True (settled, actual = commanded)."""
    B, n = x.shape
    y = np.empty_like(x)
    for i in range(n):
        e = 0.0  # lag: commanded - actual
        for k in range(B):
            d = lost[k, i]
            if start[k]:
                e = 0.0
            else:
                dx = x[k, i] - x[k - 1, i]
                if presliding > 0.0:
                    if dx != 0.0:
                        target = d if dx > 0.0 else -d
                        e = target + (e - target) * math.exp(-abs(dx) / presliding)
                else:
                    e = min(max(e + dx, -d), d)
            y[k, i] = x[k, i] - e
    return y


def sweep_starts(B: int, sweep: np.ndarray | None) -> np.ndarray:
    """(B,) bool: True at the first row of each sweep (rows are in order of motion)."""
    start = np.zeros(B, dtype=bool)
    if B:
        start[0] = True
    if sweep is not None and B > 1:
        sw = np.asarray(sweep)
        start[1:] = sw[1:] != sw[:-1]
    return start


def _rotvec_matrix(r: np.ndarray) -> np.ndarray:
    th = float(np.linalg.norm(r))
    if th == 0.0:
        return np.eye(3)
    k = r / th
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1.0 - math.cos(th)) * K @ K


#: width (mm) of the windows on either side of a tube's end over which the gap form of the
#: clearance effect averages the (torsionally rigid) curvature whose jump tilts the tubes. The
#: inner tube meets the outer tube's lip over a contact region about a tube diameter long, so
#: the tilt responds to the curvature mismatch over that length, not at one point: a curved
#: section's start or another tube's end crossing the end changes the tilt continuously over
#: this much insertion (a point evaluation stepped there: 9.5 mm of tip motion over 0.005 mm of
#: insertion on seed1 with ``length`` 20 mm).
GAP_WINDOW_MM = 1.0


def window_curvature(robot: Robot, q: np.ndarray, kappa: np.ndarray, EI: np.ndarray,
                     lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """(B, 2) mean over arc lengths [lo, hi] (B,) mm of the torsionally rigid curvature vector
    ``sum EI_i uhat_i(alpha_i) / sum EI_i`` (tubes present, curved ones contributing), taken
    over the part of the window where some tube is present (zero where none is).

    q : (B, 2n); kappa, EI : (B, n). The curvature is piecewise constant between curve starts
    and tube ends, so the mean is exact: a sum over the pieces."""
    n = robot.n
    alpha, beta = q[:, :n], q[:, n:]
    end = beta + robot.lengths
    curve = beta + robot.array("straight_length")
    ux = -np.sin(alpha) * kappa * EI
    uy = np.cos(alpha) * kappa * EI
    cuts = np.sort(np.concatenate([lo[:, None], hi[:, None],
                                   np.clip(np.concatenate([end, curve], axis=1),
                                           lo[:, None], hi[:, None])], axis=1), axis=1)
    mid = 0.5 * (cuts[:, 1:] + cuts[:, :-1])                          # (B, P)
    width = np.diff(cuts, axis=1)
    present = mid[:, :, None] < end[:, None, :]                         # (B, P, n)
    curved = present & (mid[:, :, None] >= curve[:, None, :])
    eis = np.sum(np.where(present, EI[:, None, :], 0.0), axis=-1)
    some = eis > 0
    safe = np.where(some, eis, 1.0)
    u = np.stack([np.sum(np.where(curved, ux[:, None, :], 0.0), axis=-1) / safe,
                  np.sum(np.where(curved, uy[:, None, :], 0.0), axis=-1) / safe], axis=-1)
    w = np.where(some, width, 0.0)
    tot = w.sum(axis=1)
    mean = np.sum(u * w[:, :, None], axis=1) / np.where(tot > 0, tot, 1.0)[:, None]
    return np.where((tot > 0)[:, None], mean, 0.0)


def clearance_kinks(robot: Robot, q: np.ndarray, kappa: np.ndarray, EI: np.ndarray,
                    length: float, limit: float = 0.0) -> np.ndarray:
    """Kink rotation vectors (B, n, 2) rad at each tube's distal end (gap form, see the module
    docstring): ``length`` times the jump of the rigid curvature across the end, each side's
    curvature averaged over :data:`GAP_WINDOW_MM` (so the tilt is continuous in q).

    q : (B, 2n) actual configurations; kappa, EI : (B, n) effective precurvature and stiffness.
    """
    n = robot.n
    B = len(q)
    kink = np.zeros((B, n, 2))
    if length == 0.0 or n < 2:
        return kink
    end = q[:, n:] + robot.lengths                               # (B, n)
    w = GAP_WINDOW_MM
    for j in range(1, n):
        sj = end[:, j]
        du = (window_curvature(robot, q, kappa, EI, sj, sj + w)
              - window_curvature(robot, q, kappa, EI, sj - w, sj))
        kx = length * du[:, 0]
        ky = length * du[:, 1]
        if limit > 0.0:
            th = np.hypot(kx, ky)
            with np.errstate(invalid="ignore", divide="ignore"):
                f = np.where(th > 0, limit * np.tanh(th / limit) / th, 1.0)
            kx, ky = kx * f, ky * f
        kink[:, j, 0] = kx
        kink[:, j, 1] = ky
    return kink


def clearance_harmonic_kinks(robot: Robot, q: np.ndarray, coef) -> np.ndarray:
    """Kink rotation vectors (B, n, 2) rad of the harmonic clearance form.

    Where outer tube j (j >= 2) ends, the tubes inside tilt by
    ``t(phi) = c0 + c1 cos phi + s1 sin phi + c2 cos 2phi + s2 sin 2phi`` towards the bending
    direction of tube j-1 (rotation about its curvature axis), phi = alpha_(j-1) - alpha_j.
    """
    n = robot.n
    B = len(q)
    kink = np.zeros((B, n, 2))
    c0, c1, s1, c2, s2 = (float(c) for c in coef)
    for j in range(1, n):
        a_in = q[:, j - 1]
        phi = a_in - q[:, j]
        t = c0 + c1 * np.cos(phi) + s1 * np.sin(phi) + c2 * np.cos(2 * phi) + s2 * np.sin(2 * phi)
        kink[:, j, 0] = -np.sin(a_in) * t
        kink[:, j, 1] = np.cos(a_in) * t
    return kink


@dataclass(frozen=True)
class Prepared:
    """What goes into one kernel call: actual configurations and mechanics parameters."""

    q: np.ndarray
    params: MechanicsParams
    torsion: bool


def relative_direction(robot: Robot, d: np.ndarray) -> np.ndarray:
    """(B, n) direction of each tube's rotation relative to its adjacent tubes, from (B, n)
    directions of the relative angles alpha_i - alpha_(i+1) (pairs, (B, n-1))."""
    B = len(d)
    n = robot.n
    out = np.zeros((B, n))
    for i in range(n - 1):
        out[:, i] += d[:, i]
        out[:, i + 1] -= d[:, i]
    return np.clip(out, -1.0, 1.0)


def _row_directions(angles: np.ndarray, sweep: np.ndarray | None) -> np.ndarray:
    """(B, k) direction of the last motion of each angle column (rows in order of motion)."""
    B, k = angles.shape
    if k == 0:
        return np.zeros((B, 0))
    padded = np.hstack([angles, np.zeros((B, k))])      # direction_from_rows wraps the first half
    return direction_from_rows(padded, sweep)[:, :k].astype(float)


def friction_on(fr: Mapping[str, float]) -> bool:
    """True when friction parameters ``fr`` change any shape: a lag (``lost<i>``), a windup lag
    (``wind<i>`` with ``windup``) or the end-moment form's torque (``mu``)."""
    lags = any(v > 0.0 for k, v in fr.items() if k.startswith("lost"))
    wound = fr.get("windup", 0.0) > 0.0 and any(
        v > 0.0 for k, v in fr.items() if k.startswith("wind") and k != "windup")
    end_moment = (fr.get("mu", 0.0) > 0.0
                  and round(fr.get("form", 0.0)) == FRICTION_FORMS.index("end_moment"))
    return lags or wound or end_moment


def friction_angles(robot: Robot, fr: Mapping[str, float], alpha: np.ndarray,
                    sweep: np.ndarray | None = None, direction: np.ndarray | None = None,
                    pure: bool = False, beta: np.ndarray | None = None) -> np.ndarray:
    """Actual tube angles (B, n) from commanded ``alpha`` (B, n) under friction ``fr``.

    With ``direction`` (B, 2n) in {-1, 0, 1} every row is a pure function of (alpha, direction)
    (the settled state after moving that way: a lag of ``lost``); without it the rows are one
    motion in order per sweep (``dead_band`` is then a backlash with its transients). ``pure``
    without ``direction``: no direction known, no lag. ``beta`` (B, n) is needed by the
    end-moment and windup forms.
    """
    n = robot.n
    B = len(alpha)
    if not friction_on(fr) or (direction is None and pure):
        return alpha
    lost = np.array([fr[f"lost{i + 1}"] for i in range(n)])
    mu = float(fr.get("mu", 0.0))
    form = FRICTION_FORMS[int(round(fr.get("form", 0.0)))]
    wind = np.array([fr.get(f"wind{i + 1}", 0.0) for i in range(n)])
    if fr.get("windup", 0.0) > 0.0 and np.any(wind > 0.0):
        if beta is None:
            raise ValueError("the windup friction lag needs beta")
        lost = lost[None, :] + wind[None, :] * np.clip(-beta / robot.lengths[None, :], 0.0,
                                                       1.0) ** 2
    else:
        lost = np.broadcast_to(lost[None, :], (B, n))
    if direction is None and form == "dead_band":
        return _backlash(np.ascontiguousarray(alpha), sweep_starts(B, sweep),
                         np.ascontiguousarray(lost), float(fr["presliding"]))
    dj = (np.asarray(direction, dtype=float)[:, :n] if direction is not None
          else _row_directions(alpha, sweep))
    if form in ("dead_band", "lag"):
        return alpha - dj * lost
    pair = np.sign(dj[:, :-1] - dj[:, 1:])                    # inner minus outer, (B, n-1)
    out = alpha - relative_direction(robot, pair) * lost
    if form == "end_moment" and mu > 0.0 and n > 1:
        if beta is None:
            raise ValueError("the end-moment friction form needs beta")
        out = out + mu * end_moment_twist(robot, alpha, beta, pair)
    return out


def end_moment_twist(robot: Robot, alpha: np.ndarray, beta: np.ndarray,
                     pair: np.ndarray) -> np.ndarray:
    """(B, n) rotation (rad) per unit friction coefficient of the end-moment form (the study's
    concentrated moment): where outer tube o ends, a torque T = s |M| (|M| the outer tube's
    bending moment there in the rigid model, s = ``pair[:, o-1]`` the direction of the relative
    rotation inner minus outer) twists tube o by +T l_o / GJ_o and tube o-1 by
    -T l_(o-1) / GJ_(o-1), l being each tube's length from its base to that point."""
    n = robot.n
    kap = robot.array("curvature")
    EI = robot.array("bending_stiffness")
    GJ = robot.array("torsional_stiffness")
    L = robot.lengths
    straight = robot.array("straight_length")
    out = np.zeros_like(alpha)
    for o in range(1, n):
        s_end = beta[:, o] + L[o]
        s_in = s_end - 1e-6                                   # just inside the outer tube's end
        present = s_in[:, None] < beta + L[None, :]
        curved = s_in[:, None] >= beta + straight[None, :]
        k = np.where(curved, kap[None, :], 0.0)
        w = np.where(present, EI[None, :], 0.0)
        tot = np.where(w.sum(1) > 0, w.sum(1), 1.0)
        ux = -(w * k * np.sin(alpha)).sum(1) / tot
        uy = (w * k * np.cos(alpha)).sum(1) / tot
        M = EI[o] * np.hypot(ux + k[:, o] * np.sin(alpha[:, o]), uy - k[:, o] * np.cos(alpha[:, o]))
        T = pair[:, o - 1] * M
        out[:, o] += T * (s_end - beta[:, o]) / GJ[o]
        out[:, o - 1] -= T * (s_end - beta[:, o - 1]) / GJ[o - 1]
    return out


def prepare(robot: Robot, base: str, effects: Mapping[str, Mapping[str, float]], q: np.ndarray,
            sweep: np.ndarray | None = None, direction: np.ndarray | None = None,
            pure: bool = False) -> Prepared:
    """Joint-space and mechanics stages of the effects (complete parameter dicts expected).

    ``direction`` / ``pure``: see :func:`friction_angles`."""
    n = robot.n
    q = np.array(q, dtype=float)
    B = len(q)
    jo = effects.get("joint_offset")
    if jo is not None:
        off = np.array([jo[f"dalpha{i + 1}"] for i in range(n)] + [jo[f"dbeta{i + 1}"] for i in range(n)])
        if np.any(off != 0.0):
            q = q + off
    fr = effects.get("friction")
    if fr is not None:
        q[:, :n] = friction_angles(robot, fr, q[:, :n], sweep, direction, pure, q[:, n:])
    kappa = np.broadcast_to(robot.array("curvature"), (B, n)).copy()
    EI = np.broadcast_to(robot.array("bending_stiffness"), (B, n)).copy()
    ratio = np.broadcast_to(robot.array("bending_stiffness") / robot.array("torsional_stiffness"),
                            (B, n)).copy()
    pc = effects.get("precurvature")
    if pc is not None:
        kappa *= np.array([pc[f"scale{i + 1}"] for i in range(n)])
    st = effects.get("stiffness")
    if st is not None and n > 1:
        sc = np.array([st[f"ratio{i + 1}"] for i in range(n - 1)] + [1.0])
        EI *= sc             # a modulus change scales GJ alike, so EI/GJ stays
    torsion = base == "compliant"
    tor = effects.get("torsion")
    if tor is not None:
        c = float(tor["compliance"])
        f = np.ones(n)
        f[0] = float(tor["inner_factor"])
        ratio *= c * f
        torsion = c > 0.0
    kink = np.zeros((B, n, 2))
    cl = effects.get("clearance")
    if cl is not None and cl["length"] != 0.0:
        kink = clearance_kinks(robot, q, kappa, EI, float(cl["length"]), float(cl["limit"]))
    if cl is not None and any(cl.get(h, 0.0) != 0.0 for h, _ in CLEARANCE_HARMONICS):
        kink = kink + clearance_harmonic_kinks(robot, q, [cl.get(h, 0.0) for h, _ in
                                                          CLEARANCE_HARMONICS])
    params = MechanicsParams(kappa=kappa, EI=EI, ratio=ratio, kink=kink)
    ld = effects.get("load")
    if ld is not None:
        g = np.array([ld["gx"], ld["gy"], ld["gz"]])
        f = np.array([ld["fx"], ld["fy"], ld["fz"]])
        if np.any(g != 0.0) or np.any(f != 0.0):
            params = replace(params, weight=np.tile(tube_weights(robot, g), (B, 1, 1)),
                             force=np.tile(f, (B, 1)))
    return Prepared(q=q, params=params, torsion=torsion)


def to_sensor(effects: Mapping[str, Mapping[str, float]], points: np.ndarray) -> np.ndarray:
    """Registration stage: robot-base points (..., 3) -> sensor frame."""
    rg = effects.get("registration")
    if rg is None:
        return points
    t = np.array([rg["tx"], rg["ty"], rg["tz"]])
    r = np.array([rg["rx"], rg["ry"], rg["rz"]])
    if not np.any(t != 0.0) and not np.any(r != 0.0):
        return points
    return points @ _rotvec_matrix(r).T + t


class EffectModel:
    """A mechanics shape model with effects; implements the ShapeModel protocol.

    Parameters
    ----------
    robot : Robot or shipped name / YAML path.
    base : ``"rigid"`` (torsionally rigid, "traditional") or ``"compliant"``.
    effects : ``{effect name: {param: value}}``; missing parameters take their off values.
    config : PhysicsConfig of the kernel.

    ``shape(q, points, sweep=None)`` treats the rows of ``q`` as one continuous motion in order
    (per sweep when ``sweep`` ids are given); only ``friction`` depends on that order.
    Shapes are in the sensor frame when ``registration`` is on (the robot base frame otherwise).
    """

    def __init__(self, robot: Robot | str, base: str = "rigid",
                 effects: Mapping[str, Mapping[str, float]] | None = None,
                 config: PhysicsConfig | None = None,
                 error_quantiles: Mapping[str, float] | None = None, pure: bool = False,
                 error_profile: Mapping[str, Any] | None = None,
                 measured_insertion: Mapping[str, Any] | None = None,
                 error_bound: str = "measured"):
        self.robot = load_robot(robot)
        self.base = base
        self.effects = complete_effects(effects, self.robot, base)
        self.config = config or PhysicsConfig()
        self._rigid = PhysicsModel(self.robot, torsion=False, config=self.config)
        self._compliant = PhysicsModel(self.robot, torsion=True, config=self.config)
        self.name = base + "".join(f"+{e}" for e in self.effects)
        #: held-out tip residual norm quantiles (mm) of a calibrated model, or None
        self.error_quantiles = dict(error_quantiles) if error_quantiles else None
        #: held-out deviation quantiles along the shaft (``error_profile`` mapping of
        #: :mod:`ctrplan.shape.error_bounds`), or None
        self.error_profile = dict(error_profile) if error_profile else None
        #: where the bound was measured (:mod:`ctrplan.shape.error_bounds`): "measured" (the
        #: rows ``diagnose`` held out of a measured CSV; the default) or "surrogate"
        self.error_bound = error_bound
        #: {"min": [n], "max": [n]} mm: the insertions (beta) of the rows the error bound was
        #: measured on, or None; outside them the bound is extrapolated
        self.measured_insertion = ({k: [float(v) for v in measured_insertion[k]]
                                    for k in ("min", "max")} if measured_insertion else None)
        #: True: friction is a pure function of (q, direction) even without direction
        #: (no direction known = no lag); False: direction=None takes rows in order
        self.pure = bool(pure)

    @property
    def needs_direction(self) -> bool:
        """True when friction is on: shapes depend on the direction of the last motion."""
        fr = self.effects.get("friction")
        return bool(fr) and friction_on(fr)

    def __repr__(self) -> str:
        return f"EffectModel(robot={self.robot.name!r}, base={self.base!r}, effects={self.effects!r})"

    def with_effects(self, effects: Mapping[str, Mapping[str, float]]) -> EffectModel:
        """A copy with other effects (same robot, base and config)."""
        return EffectModel(self.robot, self.base, effects, self.config, pure=self.pure)

    def planning_model(self) -> EffectModel:
        """The model for collision checking: no sensor registration (points in the robot base
        frame) and friction a pure function of (q, direction) (no lag where none is given)."""
        eff = {k: v for k, v in self.effects.items() if k != "registration"}
        return EffectModel(self.robot, self.base, eff, self.config, self.error_quantiles,
                           pure=True, error_profile=self.error_profile,
                           measured_insertion=self.measured_insertion,
                           error_bound=self.error_bound)

    def shape(self, q: np.ndarray, points: int = 20, sweep: np.ndarray | None = None,
              direction: np.ndarray | None = None) -> Shape:
        """Backbones of a batch (one kernel call). q : (B, 2n) rad and mm.

        direction : (B, 2n) in {-1, 0, +1}, the direction of each joint's last motion; with it
        every row is a pure function of (q, direction). Without it rows are one motion in order
        (per ``sweep``), unless the model is ``pure``.
        """
        q = check_q(self.robot, q)
        if direction is not None:
            direction = np.asarray(direction)
            if direction.shape != q.shape:
                raise ValueError(f"direction must have shape {q.shape}, got {direction.shape}")
        return evaluate(self, q, points, sweep, direction=direction)

    def backbone(self, q: np.ndarray, points: int = 20) -> np.ndarray:
        """(B, points, 3) backbone points, mm (sensor frame with registration, else base frame)."""
        return self.shape(q, points).points

    # ------------------------------------------------------------------ files
    def to_dict(self) -> dict[str, Any]:
        d = {"kind": MODEL_KIND, "base": self.base, "robot": self.robot.to_dict(),
             "effects": {k: dict(v) for k, v in self.effects.items()},
             "units": "mm, rad; see ctrplan.shape.effects"}
        if self.error_quantiles:
            d["error_quantiles"] = {k: float(v) for k, v in self.error_quantiles.items()}
        if self.error_profile:
            from ctrplan.shape.error_bounds import profile_from_dict

            d["error_profile"] = profile_from_dict(self.error_profile).to_dict()
        if self.error_quantiles or self.error_profile:
            d["error_bound"] = self.error_bound
        if self.measured_insertion:
            d["measured_insertion"] = dict(self.measured_insertion)
        return d

    def save(self, path: str | os.PathLike) -> None:
        """Write the model as YAML (robot + base + effects with parameters)."""
        import yaml

        from ctrplan.io import write_text_atomic

        text = ("# ctrplan calibrated model: robot, base mechanics model and effects "
                "(lengths mm, angles rad)\n" + yaml.safe_dump(self.to_dict(), sort_keys=False))
        write_text_atomic(path, text)

    @classmethod
    def from_dict(cls, data: Any, source: str = "<memory>") -> EffectModel:
        from ctrplan.robot import robot_from_dict

        if not isinstance(data, dict) or data.get("kind") != MODEL_KIND:
            raise InputError(source, "kind", f"not a {MODEL_KIND} file")
        unknown = set(data) - {"kind", "base", "robot", "effects", "units", "notes",
                               "error_quantiles", "error_profile", "measured_insertion",
                               "error_bound"}
        if unknown:
            raise InputError(source, sorted(unknown, key=str)[0], "unknown key")
        robot = robot_from_dict(data.get("robot"), source=source)
        effects = data.get("effects") or {}
        if not isinstance(effects, dict):
            raise InputError(source, "effects", "must be a mapping")
        eq = data.get("error_quantiles")
        if eq is not None:
            if not isinstance(eq, dict) or set(eq) - {"p50", "p95", "p99", "max"}:
                raise InputError(source, "error_quantiles", "must be a mapping with keys "
                                 "p50, p95, p99, max (mm)")
            for k, v in eq.items():
                if isinstance(v, bool) or not isinstance(v, (int, float)) or not \
                        math.isfinite(v) or v < 0:
                    raise InputError(source, f"error_quantiles.{k}",
                                     f"must be a finite number >= 0 (mm), got {v!r}")
        prof = data.get("error_profile")
        if prof is not None:
            from ctrplan.shape.error_bounds import profile_from_dict

            try:
                prof = profile_from_dict(prof).to_dict()
            except ValueError as exc:
                field_, _, msg = str(exc).partition(": ")
                raise InputError(source, field_, msg) from None
        from ctrplan.shape.error_bounds import MEASURED, check_error_bound_kind

        try:   # absent (files written before the field): diagnose's bounds are measured
            kind = check_error_bound_kind(data.get("error_bound"), "error_bound") or MEASURED
        except ValueError as exc:
            raise InputError(source, "error_bound", str(exc).partition(": ")[2]) from None
        return cls(robot, str(data.get("base", "rigid")),
                   complete_effects(effects, robot, str(data.get("base", "rigid")), source),
                   error_quantiles=eq, error_profile=prof, error_bound=kind,
                   measured_insertion=_measured_insertion(data.get("measured_insertion"),
                                                          robot.n, source))

    @classmethod
    def load(cls, path: str | os.PathLike, robot: Robot | str | None = None) -> EffectModel:
        """Read a model file; with ``robot``, check that the file is for a robot with the same
        tubes (the calibrated file's own tube parameters are used)."""
        from ctrplan.io import load_yaml

        model = cls.from_dict(load_yaml(path), source=str(path))
        if robot is not None:
            r = load_robot(robot)
            same = r.n == model.robot.n and all(
                np.allclose(r.array(k), model.robot.array(k), rtol=1e-9, atol=1e-9)
                for k in ("straight_length", "curved_length", "od", "id"))
            if not same:
                raise InputError(str(path), "robot", f"calibrated for robot {model.robot.name!r} "
                                 f"({model.robot.n} tubes), whose tubes (lengths, diameters) "
                                 f"differ from {r.name!r} ({r.n} tubes)")
        return model


def _measured_insertion(value: Any, n: int, source: str) -> dict | None:
    """Check a file's ``measured_insertion`` ({"min": [n], "max": [n]} mm, min <= max)."""
    if value is None:
        return None
    if not isinstance(value, dict) or set(value) != {"min", "max"}:
        raise InputError(source, "measured_insertion", "must be a mapping with keys min, max "
                         "(mm per tube)")
    out = {}
    for k in ("min", "max"):
        v = value[k]
        if not isinstance(v, list) or len(v) != n or any(
                isinstance(x, bool) or not isinstance(x, (int, float)) or not math.isfinite(x)
                for x in v):
            raise InputError(source, f"measured_insertion.{k}",
                             f"must be a list of {n} finite numbers (mm)")
        out[k] = [float(x) for x in v]
    if any(a > b for a, b in zip(out["min"], out["max"])):
        raise InputError(source, "measured_insertion", "min must not exceed max")
    return out


def is_effect_model_file(path: str | os.PathLike) -> bool:
    """True when ``path`` is a YAML file written by :meth:`EffectModel.save`."""
    p = str(path)
    if not p.lower().endswith((".yaml", ".yml")):
        return False
    if not os.path.isfile(p):      # a pipe or device would block open() or never end
        return False
    try:
        with open(p, "rb") as fh:    # bytes: a file that is not UTF-8 is reported by load_yaml
            return MODEL_KIND.encode() in fh.read(4096)
    except OSError:
        return False


def evaluate(model: EffectModel, q: np.ndarray, points: int, sweep: np.ndarray | None = None,
             effects: Mapping[str, Mapping[str, float]] | None = None,
             direction: np.ndarray | None = None, uz_init: np.ndarray | None = None,
             chain: np.ndarray | None = None) -> Shape:
    """Shapes of ``q`` under ``model``'s robot/base with ``effects`` (default: the model's).

    One kernel call for the whole batch; ``effects`` must be complete (see
    :func:`complete_effects`). ``uz_init``, ``chain`` : passed to
    :meth:`~ctrplan.shape.physics.PhysicsModel.solve` (``chain``: compliant base only; branch
    tracking, :mod:`ctrplan.shape.branches`).
    """
    eff = model.effects if effects is None else effects
    prep = prepare(model.robot, model.base, eff, q, sweep, direction,
                   pure=getattr(model, "pure", False))
    phys = model._compliant if prep.torsion else model._rigid
    shp = phys.solve(prep.q, points, prep.params, uz_init=uz_init, chain=chain)
    if "registration" in eff:
        shp = replace(shp, points=to_sensor(eff, shp.points))
    if prep.q is not q and "joint_offset" in eff:
        shp = replace(shp, radius=radius_along(model.robot, prep.q, shp.s))
    return shp
