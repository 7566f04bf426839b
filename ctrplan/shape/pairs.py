"""Pair inputs of the learned model: what the twist of a CTR depends on, given directly.

See :func:`pair_list`; :func:`pair_features` computes them in numpy (the CPU inference path),
``LearnedModel._pair_features_t`` in torch and ``ctrplan.shape._learned_kernel`` in the
compiled kernels (with their derivatives).
"""

from __future__ import annotations

from typing import Any

import numpy as np

DEFAULT_FRAME = "outer"


def pair_list(n_or_robot: Any, frame: str = DEFAULT_FRAME):
    """The pair inputs of a model. With a robot: (angle pairs, overlap pairs, 1 / scale of
    each overlap), else (n tubes) the angle pairs alone.

    Angle pairs (i, j), i < j: tubes whose relative rotation alpha_i - alpha_j enters as cos,
    sin: with frame ``outer`` the pairs without the outermost tube (the angles relative to it
    are inputs already), with ``base`` every pair. Overlap pairs: every pair of tubes, the
    length over which their curved sections overlap beyond the constraint plane (mm; piecewise
    linear in the translations), divided by the shorter of the two curved lengths, and that
    times cos and sin of alpha_i - alpha_j. The twist of a CTR comes from the torque between
    the curved sections of two tubes, about ``EI kappa_i kappa_j sin(alpha_i - alpha_j)`` per
    length of overlap: products of per-tube inputs that a PReLU network can only approximate
    piecewise (given directly they cut the surrogate's held-out p99 by about a quarter at the
    same width; ctrplan/data/models/README.md)."""
    if isinstance(n_or_robot, (int, np.integer)):
        n = int(n_or_robot)
        last = n - 1 if frame == "outer" else n
        return [(i, j) for i in range(last) for j in range(i + 1, last)]
    robot = n_or_robot
    n = robot.n
    curved = robot.array("curved_length")
    opairs = [(i, j) for i in range(n) for j in range(i + 1, n)]
    oinv = [1.0 / max(min(curved[i], curved[j]), 1e-9) for i, j in opairs]
    return pair_list(n, frame), opairs, oinv


def pair_features(model: Any, q: np.ndarray) -> np.ndarray:
    """The pair inputs (B, 2P + 3O) of q (B, 2n) in q's float dtype (:func:`pair_list`)."""
    n, B = model.robot.n, len(q)
    dt = q.dtype
    P, OP = model._pairs, model._opairs
    rel = q[:, P[:, 0]] - q[:, P[:, 1]]
    pa = np.stack([np.cos(rel), np.sin(rel)], axis=2).reshape(B, -1)
    b = q[:, n:]
    L, S = model.robot.lengths.astype(dt), model._straight.astype(dt)
    i, j = OP[:, 0], OP[:, 1]
    end = np.minimum(b[:, i] + L[i], b[:, j] + L[j])
    start = np.maximum(np.maximum(b[:, i] + S[i], b[:, j] + S[j]), dt.type(0))
    ov = np.maximum(end - start, dt.type(0)) * model._oinv.astype(dt)
    rel = q[:, i] - q[:, j]
    po = np.stack([ov, ov * np.cos(rel), ov * np.sin(rel)], axis=2).reshape(B, -1)
    return np.concatenate([pa, po], axis=1).astype(dt, copy=False)
