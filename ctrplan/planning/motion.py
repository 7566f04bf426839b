"""The motion between checked states of a path: a cover derived from the model along each segment.

:meth:`BatchValidator.check_path <ctrplan.planning.validator.BatchValidator.check_path>` checks
the states of a path at a fine resolution; this module certifies the motion between consecutive
states. On each segment (two consecutive states, ``h`` mm of the joint metric apart, the motion
a straight line in joint space) the model's backbones at both ends and their velocities along
the segment (one-sided finite differences over ``h / 16``, :data:`~ctrplan.shape.bounds.FD_FRACTION`)
give a bound of how far each backbone point, and each capsule's chord pad, can move
(:func:`ctrplan.shape.bounds.motion_cover`, which also states the assumption the bound makes and
refuses a segment whose displacement the velocities do not explain: a jump). A segment is
certified

- at level 0, when the motion is resolved and both end states' conservative clearances are at
  least its largest capsule cover; otherwise
- it is split into :data:`SUBDIVISIONS` parts whose end states are checked with every capsule
  grown by its own cover (the larger of the two adjacent parts'); parts not covered are split
  again, :data:`LEVELS` levels deep (0.008 mm of metric for a 0.5 mm segment).

A state that really collides, a part still not covered at the last level, or a part whose
velocities reveal a jump or a speed above :data:`~ctrplan.shape.bounds.MAX_SPEED` fails its
segment. Evaluations run in path order with each finite-difference state right after its base
state (a model that warm-starts each state from the previous one stays on its branch).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ctrplan.robot import wrap_angle
from ctrplan.shape.bounds import FD_FRACTION, MotionCover, motion_cover

#: parts a segment that its end clearances do not certify is split into, and levels of splitting
SUBDIVISIONS = 8
LEVELS = 2


@dataclass
class Chains:
    """Runs of equally spaced states along straight joint-space lines, evaluated together.

    start : (C, 2n) first state of each chain; step : (C, 2n) joint step between its states
    (rotations unwrapped); parts : (C,) int, steps per chain (>= 1); direction : (C, 2n) int8
    direction of motion of each chain, or None (a model that does not take it);
    uz0 : (sum(parts + 1), n) 1/mm or None, the equilibrium (base torsions) each chain state is
    solved from, chains in order (branch tracking: the branch the robot is on there).
    """

    start: np.ndarray
    step: np.ndarray
    parts: np.ndarray
    direction: np.ndarray | None
    uz0: np.ndarray | None = None


def joint_delta(q0: np.ndarray, q1: np.ndarray, n: int) -> np.ndarray:
    """q1 - q0 with rotations along the shorter arc. q0, q1 : (..., 2n)."""
    d = np.asarray(q1, dtype=float) - np.asarray(q0, dtype=float)
    d[..., :n] = wrap_angle(d[..., :n])
    return d


def edge_direction(q0: np.ndarray, q1: np.ndarray, n: int) -> np.ndarray:
    """(2n,) int8 direction of motion along the edge q0 -> q1 (rotations along the shorter
    arc): +1, -1, or 0 where the joint does not move."""
    return np.sign(joint_delta(q0, q1, n)).astype(np.int8)


def _metric(dq: np.ndarray, n: int, w: float) -> np.ndarray:
    return w * np.abs(dq[..., :n]).sum(-1) + np.linalg.norm(dq[..., n:], axis=-1)


def _rows(ch: Chains, n: int, w: float):
    """The states to evaluate for chains: per chain its K + 1 states, each followed by a
    finite-difference state (forward along the chain; backward at its last state).
    Returns (rows (R, 2n), chain index (R,), eps (C,) metric mm, h (C,) metric mm)."""
    h = _metric(ch.step, n, w)
    eps = FD_FRACTION * h
    unit = ch.step / np.where(h > 0, h, 1.0)[:, None]
    out, owner = [], []
    for c in range(len(ch.start)):
        K = int(ch.parts[c])
        t = np.arange(K + 1)[:, None]
        base = ch.start[c][None] + t * ch.step[c][None]
        fd = base + eps[c] * unit[c][None]
        fd[-1] = base[-1] - eps[c] * unit[c]
        pair = np.empty((2 * (K + 1), base.shape[1]))
        pair[0::2], pair[1::2] = base, fd
        out.append(pair)
        owner.append(np.full(2 * (K + 1), c))
    rows = np.concatenate(out) if out else np.zeros((0, 2 * n))
    rows[:, :n] = wrap_angle(rows[:, :n])
    return rows, (np.concatenate(owner) if owner else np.zeros(0, int)), eps, h


@dataclass
class Evaluated:
    """Shapes of chain states (one per direction variant) and the covers of their parts.

    shapes : list over variants of Shapes of the states (S_total rows, in chain order);
    cover : MotionCover of every part, worst over the variants (P_total rows);
    part_chain : (P_total,) chain of each part.
    """

    shapes: list
    cover: MotionCover
    part_chain: np.ndarray


def evaluate_chains(validator, ch: Chains, points: int) -> Evaluated:
    """Shapes of the chains' states and the motion cover of every part (one shape call per
    direction variant)."""
    n, w = validator.n, validator.config.alpha_weight_mm
    rows, owner, eps, h = _rows(ch, n, w)
    dirs = None if ch.direction is None else ch.direction[owner]
    # each state and its finite-difference neighbour start from the state's equilibrium
    uz = None if ch.uz0 is None else np.repeat(np.asarray(ch.uz0, dtype=float), 2, axis=0)
    covers, shapes = [], []
    base = np.arange(0, len(rows), 2)
    K = ch.parts.astype(int)
    last = np.cumsum(K + 1) - 1                                   # last state of each chain
    is_last = np.zeros(len(base), dtype=bool)
    is_last[last] = True
    for d in validator.variants(rows, dirs):
        sh = validator.shapes(rows, points=points, direction=d) if uz is None else \
            validator.shapes(rows, points=points, direction=d, uz0=uz)
        P = sh.points
        pad = sh.pad
        ok = np.asarray(sh.ok, dtype=bool)
        pb, pf = P[base], P[base + 1]
        e = eps[owner[base]]
        sgn = np.where(is_last, -1.0, 1.0)
        vel = (pf - pb) * (sgn / np.where(e > 0, e, 1.0))[:, None, None]
        dpad = None if pad is None else (pad[base + 1] - pad[base]) * (sgn / np.where(e > 0, e, 1.0))[:, None]
        good = ok[base] & ok[base + 1]
        # parts: consecutive states of a chain; the velocity at a part's end is the next
        # state's forward difference inside the chain (same direction), the backward one at
        # the chain's last state
        a = np.concatenate([np.arange(s0, s0 + k) for s0, k in zip(last - K, K)]) if len(K) else \
            np.zeros(0, int)
        b = a + 1
        pc = owner[base[a]]
        cov = motion_cover(pb[a], pb[b], vel[a], vel[b], h[pc], eps[pc],
                           None if pad is None else pad[base[a]],
                           None if pad is None else pad[base[b]],
                           None if dpad is None else dpad[a], None if dpad is None else dpad[b])
        bad = ~(good[a] & good[b])
        cov = MotionCover(point_mm=cov.point_mm,
                          capsule_mm=np.where(bad[:, None], np.inf, cov.capsule_mm),
                          resolved=cov.resolved & ~bad, speed=np.where(bad, np.inf, cov.speed))
        covers.append(cov)
        shapes.append(_take(sh, base))
    cover = covers[0]
    for c in covers[1:]:
        cover = MotionCover(np.maximum(cover.point_mm, c.point_mm),
                            np.maximum(cover.capsule_mm, c.capsule_mm),
                            cover.resolved & c.resolved, np.maximum(cover.speed, c.speed))
    a_chain = np.repeat(np.arange(len(K)), K)
    return Evaluated(shapes, cover, a_chain)


def _take(shape, idx):
    """The rows ``idx`` of a Shape."""
    return replace(shape, points=shape.points[idx], s=shape.s[idx], radius=shape.radius[idx],
                   ok=np.asarray(shape.ok)[idx], pad=None if shape.pad is None else shape.pad[idx])


def grown(shape, world, capsule_mm: np.ndarray):
    """The shape with every capsule grown by ``capsule_mm`` (B, m - 1) mm in ``world``: through
    its pad (the world pads capsules by the larger of the shape's pad and its own sagitta
    bound), or, for a world that takes no pads, the world grown by the largest cover.
    Returns (shape, world)."""
    from ctrplan.collision.capsules import sagitta_bound

    cover = np.where(np.isfinite(capsule_mm), capsule_mm, np.inf)
    if getattr(world, "padding", "auto") != "auto" or not hasattr(world, "curvature_per_mm"):
        big = float(np.max(cover)) if cover.size else 0.0
        return shape, world.with_motion(big if np.isfinite(big) else 1e6)
    base = np.zeros(cover.shape) if shape.pad is None else np.asarray(shape.pad, dtype=float)
    kappa = float(world.curvature_per_mm)
    if kappa > 0:
        arc = np.maximum(np.abs(np.diff(shape.s, axis=1)),
                         np.linalg.norm(np.diff(shape.points, axis=1), axis=-1))
        base = np.maximum(base, sagitta_bound(arc, kappa))
    # an infinite cover (a shape that could not be bounded) is a shape that is not ok
    ok = np.asarray(shape.ok, dtype=bool) & np.all(np.isfinite(cover), axis=1)
    return replace(shape, pad=base + np.where(np.isfinite(cover), cover, 0.0), ok=ok), world


def path_chains(validator, states: np.ndarray, uz0: np.ndarray | None = None) -> Chains:
    """Chains of a path's checked states (S, 2n): one per run of consecutive pairs with the same
    joint step (an edge). uz0 : (S, n) each state's equilibrium, or None."""
    n = validator.n
    dq = joint_delta(states[:-1], states[1:], n)                        # (S - 1, 2n)
    scale = np.maximum(np.abs(dq), 1e-9)
    new = np.ones(len(dq), dtype=bool)
    new[1:] = np.any(np.abs(dq[1:] - dq[:-1]) > 1e-6 * scale[1:], axis=1)
    first = np.flatnonzero(new)
    parts = np.diff(np.r_[first, len(dq)])
    direction = None
    if validator.directional:
        direction = np.sign(dq[first]).astype(np.int8)
    chain_uz0 = None
    if uz0 is not None:
        chain_uz0 = np.concatenate([uz0[f:f + k + 1] for f, k in zip(first, parts)])
    return Chains(states[first], dq[first], parts, direction, chain_uz0)


def _sub_uz0(uz0: np.ndarray | None, owner: np.ndarray, f0: np.ndarray, fs: np.ndarray,
             k: int) -> np.ndarray | None:
    """Equilibria to start the states of sub-chains from (branch tracking), or None: linear in
    the fraction of the segment between the equilibria of its end states (the path was
    continued, so both are on the robot's branch). owner : (P,) segment of each sub-chain;
    f0, fs : (P,) fraction of the segment at its first state and per part; k parts each.
    Returns (P * (k + 1), n) 1/mm, in chain order."""
    if uz0 is None:
        return None
    fr = f0[:, None] + fs[:, None] * np.arange(k + 1)[None, :]             # (P, k + 1)
    a, b = uz0[owner][:, None, :], uz0[owner + 1][:, None, :]
    return ((1.0 - fr)[..., None] * a + fr[..., None] * b).reshape(-1, uz0.shape[1])


def check_motion(validator, states, clearance, collides, contact, points, uz0=None) -> None:
    """Cover the motion between consecutive checked states (module docstring); marks the first
    state of every segment that fails (``collides`` True, ``contact`` the mesh or "motion").
    uz0 : (S, n) each state's equilibrium reached by continuation (branch tracking), or None:
    the states between two checked states are solved from the equilibria of their ends."""
    world = validator.world
    S = len(states)
    ch = path_chains(validator, states, uz0)
    ev = evaluate_chains(validator, ch, points)
    cov = ev.cover
    need = np.max(cov.capsule_mm, axis=1)                                # (S - 1,)
    with np.errstate(invalid="ignore"):
        done = cov.certified & (np.minimum(clearance[:-1], clearance[1:]) >= need)
    failed = np.zeros(S, dtype=bool)
    why = np.full(S, "", dtype=object)
    fast = cov.resolved & ~cov.certified                                 # too fast: refused
    failed[:-1] |= fast
    why[:-1][fast] = "motion"
    owner = np.flatnonzero(~done & ~failed[:-1])
    validator.counters.motion_segments += len(owner)
    d = ch.direction[ev.part_chain[owner]] if ch.direction is not None else None
    qa, dq = states[owner], joint_delta(states[owner], states[owner + 1], validator.n)
    f0, fs = np.zeros(len(owner)), np.ones(len(owner))          # fractions of the segment
    for level in range(1, LEVELS + 1):
        if len(owner) == 0:
            break
        fs = fs / SUBDIVISIONS
        sub = Chains(qa, dq / SUBDIVISIONS, np.full(len(owner), SUBDIVISIONS), d,
                     _sub_uz0(uz0, owner, f0, fs, SUBDIVISIONS))
        ev = evaluate_chains(validator, sub, points)
        k = SUBDIVISIONS
        cap = ev.cover.capsule_mm.reshape(len(owner), k, -1)            # (P, k, m - 1)
        K1 = cap.shape[-1]
        pad = np.zeros((len(owner), k + 1, K1))
        pad[:, :-1] = cap
        pad[:, 1:] = np.maximum(pad[:, 1:], cap)
        hit = np.zeros((len(owner), k + 1), dtype=bool)
        for shape in ev.shapes:
            g, w = grown(shape, world, pad.reshape(-1, K1))
            hh = np.asarray(w.collides(g), dtype=bool).reshape(len(owner), k + 1)
            if hh.any():   # grown capsules touch: do the states themselves collide?
                rows = np.flatnonzero(hh.reshape(-1))
                rep = world.check(_take(shape, rows))
                for r, c, name in zip(rows, np.asarray(rep.collides, bool), rep.contact):
                    if c:
                        o = owner[r // (k + 1)]
                        failed[o] = True
                        why[o] = str(name) or "motion"
            hit |= hh
        cert = ev.cover.certified.reshape(len(owner), k)
        refused = (ev.cover.resolved & ~ev.cover.certified).reshape(len(owner), k).any(axis=1)
        failed[owner[refused]] = True
        for o in owner[refused]:
            why[o] = why[o] or "motion"
        todo = ~(cert & ~hit[:, :-1] & ~hit[:, 1:]) & ~failed[owner][:, None]
        if level == LEVELS:
            for o in owner[todo.any(axis=1)]:
                failed[o] = True
                why[o] = why[o] or "motion"
            break
        pi, pj = np.nonzero(todo)
        qa = qa[pi] + pj[:, None] * (dq[pi] / k)
        dq = dq[pi] / k
        f0, fs = f0[pi] + pj * fs[pi], fs[pi]
        d = None if d is None else d[pi]
        owner = owner[pi]
    for i in np.flatnonzero(failed):
        collides[i] = True
        contact[i] = why[i]
