"""Bounds that make sampled backbones cover the continuous robot: the distance between a
backbone and its chords (curvature and tangent jumps, external loads included), and the motion
of the backbone between two checked states of a motion (derived from the model along it).

Chord bounds (``Shape.pad``). For a curve parameterised by arc length whose curvature is at most
``kappa`` on a segment of arc length ``h``, the error ``e(s) = c(s) - chord(s)`` vanishes at both
ends and ``|e''| <= kappa``, so ``|e(s)| <= kappa s (h - s) / 2 <= kappa h^2 / 8``
(:func:`sagitta_pad`). A tangent jump adds :func:`kink_pad`.

Curvature of the mechanics models (:func:`segment_curvature`). The backbone curvature is
``|u_xy|`` with (see :mod:`ctrplan.shape._loaded`)

    u_xy = (mb_xy + sum_j EI_j Rz(psi_j) uhat_j) / sum_j EI_j            (tubes present at s)

so ``|u_xy| <= max_j |kappa_j| + |m(s)| / sum_j EI_j``: the stiffness-weighted mean of the
rotated precurvatures never exceeds the largest one, and ``|mb_xy| <= |m(s)|``, the internal
moment. Unloaded, ``m = 0``. Loaded, the moment balance of the part distal of ``s`` (no
distributed moments; tip force ``F`` and moment ``M`` fixed in the base frame, weight ``W_i``
per unit length of tube i up to its end ``l_i``) gives

    m(s) = M + (p(l) - p(s)) x F + sum_i int_s^l_i (p(sigma) - p(s)) x W_i dsigma,

and since ``|p(sigma) - p(s)| <= sigma - s`` (arc length),
``|m(s)| <= |M| + |(p_tip - p_a) x F| + |F| (s - s_a) + sum_i |W_i| (l_i - s)^2 / 2`` for any
sample ``p_a`` at ``s_a <= s``. Where the clearance effect turns the frame by ``theta`` (a kink)
the kernel carries the bending moment with the frame and the twisting moment over, which can
grow ``|m|`` proximal of the kink by at most ``(1 + sin theta) / cos theta``; the bound takes
the product over the row's kinks. On each segment ``[s_a, s_b]`` the stiffness sum is at least
that of the tubes reaching ``s_b``.

Motion between checked states (:func:`motion_cover`): see its docstring.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: second derivative of the motion allowed on a segment, as a multiple of the largest value
#: its samples imply (see :func:`motion_cover`)
MOTION_SAFETY = 2.0
#: one-sided finite-difference step of the velocities, as a fraction of the segment
FD_FRACTION = 1.0 / 16.0
#: displacement (mm) the velocities need not explain (round-off of float32 backbones)
MOTION_SLACK_MM = 1e-3
#: fastest backbone motion (mm per mm of the joint metric) a segment may have: faster is the
#: signature of a fold or of a jump inside a finite-difference window, refused. About 3x the
#: steepest motion the models make: seed1's tip moves 81 mm per mm of insertion where the
#: clearance gap form at its fit bound (length 100 mm) turns over its 1 mm window (typical
#: motions: about 1 mm per mm).
MAX_SPEED = 250.0


def sagitta_pad(s: np.ndarray, curvature_per_mm: np.ndarray | float) -> np.ndarray:
    """(B, m - 1) sagitta bound ``kappa h^2 / 8`` of each segment of backbones sampled at arc
    lengths ``s`` (B, m); ``curvature_per_mm`` a number, (B,) per configuration or (B, m - 1)
    per segment."""
    s = np.asarray(s, dtype=float)
    k = np.asarray(curvature_per_mm, dtype=float)
    k = k[:, None] if k.ndim == 1 else k
    return k * np.square(np.diff(s, axis=1)) / 8.0


def kink_pad(s: np.ndarray, where: np.ndarray, angle: np.ndarray) -> np.ndarray:
    """(B, m - 1) bound (mm) of the distance between a backbone and its chords caused by
    tangent jumps: a jump of ``angle`` (rad) at arc length ``where`` inside the segment
    ``[s_a, s_b]`` (length ``h``) adds ``2 sin(angle / 2) (where - s_a) (s_b - where) / h``.

    Derivation: the chord error ``e(s)`` vanishes at both ends of the segment and ``e''`` is the
    curvature plus an impulse ``dt`` (the tangent jump, ``|dt| = 2 sin(angle/2)``) at the kink;
    with the Green's function of ``d^2/ds^2`` on ``[0, h]`` (zero at both ends),
    ``|G(s, w)| <= w (h - w) / h``, so the impulse moves ``u . e`` by at most
    ``|dt| w (h - w) / h`` for every unit ``u`` (``h sin(angle / 2) / 2`` for a kink in the
    middle: exactly the corner of two straight halves). It adds to the sagitta bound.

    s : (B, m) arc lengths of the samples; where, angle : (B, J) kinks (angle 0 = none).
    """
    s = np.asarray(s, dtype=float)
    where = np.asarray(where, dtype=float)
    angle = np.abs(np.asarray(angle, dtype=float))
    sa, sb = s[:, :-1, None], s[:, 1:, None]                  # (B, K, 1)
    w = where[:, None, :]                                     # (B, 1, J)
    h = sb - sa
    inside = (w > sa) & (w < sb) & (h > 0)
    with np.errstate(invalid="ignore", divide="ignore"):
        g = np.where(inside, (w - sa) * (sb - w) / np.where(h > 0, h, 1.0), 0.0)
    return (2.0 * np.sin(np.minimum(angle, np.pi) / 2.0)[:, None, :] * g).sum(axis=-1)


def kink_moment_factor(kink: np.ndarray) -> np.ndarray:
    """(B,) growth of the internal moment's magnitude across a row's kinks (module docstring):
    the product of ``(1 + sin theta) / cos theta``. kink : (B, n, 2) rad."""
    th = np.minimum(np.linalg.norm(np.asarray(kink, dtype=float), axis=-1), 1.5)
    return np.prod((1.0 + np.sin(th)) / np.cos(th), axis=1)


def segment_curvature(s: np.ndarray, points: np.ndarray, ends: np.ndarray, kappa: np.ndarray,
                      EI: np.ndarray, kink: np.ndarray, weight: np.ndarray | None = None,
                      force: np.ndarray | None = None,
                      moment: np.ndarray | None = None) -> np.ndarray:
    """(B, m - 1) bound (1/mm) of the backbone curvature on each segment of the mechanics
    models, external loads included (module docstring).

    s : (B, m) mm; points : (B, m, 3) mm (the solved backbone, base frame); ends : (B, n) mm,
    each tube's distal arc length; kappa, EI : (B, n) 1/mm and N mm^2; kink : (B, n, 2) rad;
    weight : (B, n, 3) N/mm, force : (B, 3) N, moment : (B, 3) N mm, or None (no load).
    """
    s = np.asarray(s, dtype=float)
    B, m = s.shape
    pre = np.max(np.abs(kappa), axis=1)[:, None] * np.ones((1, m - 1))
    if weight is None and force is None and moment is None:
        return pre
    sa, sb = s[:, :-1], s[:, 1:]
    mom = np.zeros((B, m - 1))
    if moment is not None:
        mom += np.linalg.norm(moment, axis=1)[:, None]
    if force is not None:
        F = np.asarray(force, dtype=float)
        lever = points[:, -1:, :] - points[:, :-1, :]                     # (B, m-1, 3)
        mom += np.linalg.norm(np.cross(lever, F[:, None, :]), axis=-1)
        mom += np.linalg.norm(F, axis=1)[:, None] * (sb - sa)
    if weight is not None:
        w = np.linalg.norm(weight, axis=-1)                                # (B, n)
        reach = np.maximum(ends[:, None, :] - sa[:, :, None], 0.0)         # (B, m-1, n)
        mom += np.sum(w[:, None, :] * reach ** 2 / 2.0, axis=-1)
    mom *= kink_moment_factor(kink)[:, None]
    # stiffness present on the whole segment: the tubes reaching its far end (the innermost
    # always reaches the tip; the tolerance covers round-off of s)
    through = ends[:, None, :] >= sb[:, :, None] - 1e-6                    # (B, m-1, n)
    eis = np.sum(np.where(through, EI[:, None, :], 0.0), axis=-1)
    eis = np.where(eis > 0, eis, EI[:, :1])
    return pre + mom / eis


def continuity_pad(q: np.ndarray, lengths: np.ndarray, s: np.ndarray, points: np.ndarray,
                   kappa: np.ndarray, EI: np.ndarray, kink: np.ndarray,
                   weight: np.ndarray | None = None, force: np.ndarray | None = None,
                   moment: np.ndarray | None = None) -> np.ndarray:
    """(B, m - 1) bound (mm) of the distance between the mechanics models' continuous backbone
    and the chord of each segment: the sagitta of :func:`segment_curvature` (precurvature and
    external loads) plus the offset of the tangent jumps the clearance kinks cause where tubes
    end (:func:`kink_pad`). q : (B, 2n); lengths : (n,) mm; other arrays as in
    :func:`segment_curvature`."""
    n = len(lengths)
    ends = np.asarray(q, dtype=float)[:, n:] + np.asarray(lengths, dtype=float)
    kappa_seg = segment_curvature(s, points, ends, kappa, EI, kink, weight, force, moment)
    pad = sagitta_pad(s, kappa_seg)
    angle = np.linalg.norm(kink, axis=-1)                 # (B, n)
    if np.any(angle > 0):
        pad = pad + kink_pad(s, ends, angle)
    return pad


def curvature_bound(model_or_robot) -> float:
    """Upper bound (1/mm) of the backbone curvature of a shape model without external loads,
    for shapes that carry no ``pad`` of their own.

    A model may state its own bound as ``max_curvature`` (1/mm). Otherwise: the largest
    precurvature of the robot's tubes (times the ``precurvature`` effect's scales for a
    calibrated model), which bounds the curvature of the unloaded physics models (torsionally
    rigid or compliant): their bending curvature is the EI-weighted mean of the tubes' rotated
    precurvature vectors. The loads' share is per configuration and segment
    (:func:`segment_curvature`): the mechanics models' shapes carry it in ``Shape.pad``, which
    capsules use besides this bound.
    """
    own = getattr(model_or_robot, "max_curvature", None)
    if own is not None:
        v = float(own)
        if not (np.isfinite(v) and v >= 0):
            raise ValueError(f"max_curvature must be a finite number >= 0, got {own!r}")
        return v
    robot = getattr(model_or_robot, "robot", model_or_robot)
    kappa = np.abs(np.asarray(robot.array("curvature"), dtype=float))
    effects = getattr(model_or_robot, "effects", None) or {}
    pc = effects.get("precurvature") if isinstance(effects, dict) else None
    if pc:
        scale = np.array([abs(float(pc.get(f"scale{i + 1}", 1.0))) for i in range(len(kappa))])
        kappa = kappa * np.maximum(scale, 1.0)
    return float(kappa.max()) if kappa.size else 0.0


# ---------------------------------------------------------------------------- motion cover
@dataclass(frozen=True)
class MotionCover:
    """How far the backbone can move on each segment of a motion (from its end states).

    point_mm : (P, m) bound (mm) of the distance of each backbone point (fixed arc-length
        fraction) at any state of the segment from the same point at either end state.
    capsule_mm : (P, m - 1) how much each capsule of either end state must grow to cover the
        continuous tube at any state of the segment: the larger of its two points' bounds plus
        the bound of the change of its chord pad.
    resolved : (P,) bool, the end velocities explain the displacement (no jump detected).
    speed : (P,) largest measured speed (mm of backbone per mm of the joint metric).
    """

    point_mm: np.ndarray
    capsule_mm: np.ndarray
    resolved: np.ndarray
    speed: np.ndarray

    @property
    def certified(self) -> np.ndarray:
        """(P,) bool: resolved and no faster than :data:`MAX_SPEED`."""
        return self.resolved & (self.speed <= MAX_SPEED) & np.all(np.isfinite(self.capsule_mm), axis=1)


def _channel_bound(x0, x1, w0, w1, h, eps, vector: bool):
    """One channel's trapezoid defect allowance, cover, defect and largest end speed, each
    (P, K). x0, x1 : values at the ends, w0, w1 : velocities, (P, K, 3) if ``vector`` else
    (P, K); h, eps : (P,) mm of metric."""
    nrm = (lambda v: np.linalg.norm(v, axis=-1)) if vector else np.abs
    h = np.maximum(h, 1e-12)              # a zero-length segment: any displacement is a jump
    hh, ee = h[:, None], eps[:, None]
    hv = h[:, None, None] if vector else hh
    disp = nrm(x1 - x0)
    sec = (x1 - x0) / hv
    vmax = np.maximum(nrm(w0), nrm(w1))
    dv = nrm(w1 - w0)
    m2 = np.maximum(dv / hh, 2.0 * np.maximum(nrm(sec - w0), nrm(sec - w1)) / np.maximum(hh - ee, hh / 2))
    # the displacement the velocities do not explain (trapezoid rule), and what a motion whose
    # velocity changes by |w1 - w0| once (a kink) may leave unexplained
    defect = nrm(x1 - x0 - hv * (w0 + w1) / 2.0)
    allow = MOTION_SAFETY / 4.0 * dv * (hh + 2.0 * ee)
    # the cover: the displacement plus the largest distance from the straight motion
    cover = disp + MOTION_SAFETY * m2 * hh * hh / 8.0
    return allow, cover, defect, vmax


def motion_cover(p0: np.ndarray, p1: np.ndarray, v0: np.ndarray, v1: np.ndarray,
                 h: np.ndarray, eps: np.ndarray, pad0: np.ndarray | None = None,
                 pad1: np.ndarray | None = None, dpad0: np.ndarray | None = None,
                 dpad1: np.ndarray | None = None) -> MotionCover:
    """Bound of the backbone motion on each segment of a straight joint-space motion, from the
    model's backbones at the segment's ends and their velocities along it.

    p0, p1 : (P, m, 3) mm, backbones at the ends (t = 0 and t = h, t the joint metric in mm);
    v0, v1 : (P, m, 3) velocities dP/dt there, measured by one-sided finite differences over
    ``eps`` (the mean velocity over a window of that length at each end);
    h, eps : (P,) mm of metric; pad0, pad1, dpad0, dpad1 : (P, m - 1) chord pads
    (``Shape.pad``) at the ends and their velocities (None: the model has none).

    Derivation. With ``M2`` a bound of ``|P''|`` on the segment, the motion is within
    ``M2 t (h - t) / 2 <= M2 h^2 / 8`` of the straight motion between its ends (the linear
    interpolation error), so every point is within ``|P(h) - P(0)| + M2 h^2 / 8`` of the same
    point at either end. The samples imply lower bounds of ``M2``: ``|v1 - v0| / h`` and
    ``2 |S - v| / (h - eps)`` (S the secant; the velocities are window means); the bound takes
    ``M2`` = :data:`MOTION_SAFETY` times the largest of them, i.e. it assumes that the second
    derivative of the motion on one segment is at most twice what its four samples show (the
    factor to spare for a quadratic motion, exact for a kink between two straight motions, as
    the learned network's activations make). A jump (a branch switch, a discontinuous model) is
    refused: the displacement must be explained by the velocities (trapezoid rule):
    ``|P(h) - P(0) - h (v0 + v1) / 2| <= SAFETY / 4 |v1 - v0| (h + 2 eps)`` +
    :data:`MOTION_SLACK_MM` at every point. A smooth motion leaves ``h^3 |P'''| / 12`` (it
    passes once the segment is short enough: split it), a kink between two straight motions at
    most ``h |v1 - v0| / 2`` (it passes), a jump its whole size (it fails once the segment is
    short enough: near a fold, where the speed grows, a segment split twice refuses a snap
    larger than about ``|v1 - v0| h / 128``). No point may move faster than
    :data:`MAX_SPEED` (a jump inside a finite-difference window: one smaller than
    ``MAX_SPEED eps`` there is not seen, which the planner's stability margin, keeping states
    away from folds, is left to exclude).

    The pad channel gets the same bound (``|pad(t) - pad(end)|``): a capsule at t lies within
    ``pad(t)`` of its chord, and its chord within the larger of its end points' bounds of the
    end state's chord, so ``capsule_mm`` grows that capsule of either end state to cover it.
    """
    h = np.asarray(h, dtype=float)
    eps = np.asarray(eps, dtype=float)
    allow, full, defect, vmax = _channel_bound(p0, p1, v0, v1, h, eps, vector=True)
    slack = MOTION_SLACK_MM
    resolved = np.all(defect <= allow + slack, axis=1)
    point = full + slack
    cap = np.maximum(point[:, :-1], point[:, 1:])
    if pad0 is not None and pad1 is not None:
        d0 = np.zeros_like(pad0) if dpad0 is None else dpad0
        d1 = np.zeros_like(pad1) if dpad1 is None else dpad1
        cap = cap + _channel_bound(pad0, pad1, d0, d1, h, eps, vector=False)[1]
    speed = np.max(vmax, axis=1)
    bad = ~np.all(np.isfinite(point), axis=1)
    return MotionCover(point_mm=point, capsule_mm=np.where(bad[:, None], np.inf, cap),
                       resolved=resolved & ~bad, speed=np.where(bad, np.inf, speed))
