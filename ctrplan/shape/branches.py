"""Which equilibrium a compliant robot is on: branch tracking along a motion, stability, labels.

Concentric tubes whose curved sections overlap far enough have, over a range of relative
rotation, two stable equilibria at the same configuration (bistable). The physical robot stays
on the one it is on as it moves (its equilibrium is continued: deformed continuously with the
configuration) until that branch ends at a fold, where it snaps to the other. A shape model that
picks an equilibrium per configuration cannot say which one the robot is in; this module is the
small interface through which the model is asked about motions instead. Planning asks it
through :class:`~ctrplan.shape.planning_model.PlanningModel` (``tracks_branches``, ``solve``,
``settle``, ``stable_equilibria``, ``branch_labels``), which calls the functions here.

- :func:`tracks_branches` : whether a model's shape can depend on the motion's history at all:
  the torsionally compliant, unloaded mechanics (a :class:`~ctrplan.shape.physics.PhysicsModel`
  or an :class:`~ctrplan.shape.effects.EffectModel` over it). Not the torsionally rigid model
  (one shape per configuration), a learned model (a function of q), or loaded models (their
  kernel does not test stability). Decided from the model's mechanics, per model.
- :func:`solve` : shapes with each row's equilibrium (``uz0``) and stability; with ``chain`` the
  rows are motions and each row continues the previous one's equilibrium
  (:mod:`ctrplan.shape._continuation`), a chain starting where ``uz_init`` says.
- :func:`branch_labels` : the ``branch`` label of plan.json.

Stability measure. ``stability`` = det J, J = d uz(end) / d uz(0) the shooting Jacobian at the
equilibrium (Gilbert, Hendrick & Webster, T-RO 2016; the derivation is in
:mod:`ctrplan.shape._shooting`). By Forman's theorem det J = det Q / det Q0: the second variation
of the elastic energy relative to the same tubes without the interaction of their curvatures
(for which J = I), so it is normalised: 1 for tubes that do not interact, > 1 where the
curvatures stiffen the twist (aligned tubes), 0 at a fold, < 0 unstable. Near a fold it is the
stiffness left in the softest torsional mode, as a fraction of the bare tubes'; the response of
the twist to the actuators (and to any unmodelled torque) grows like 1/stability. Dimensionless,
larger is safer.

Branch label (``branch_labels``): 0 where the model finds one stable equilibrium at that
configuration; where it finds two, +1 for the one whose innermost tube has the larger base
torsion uz_1(0) (turned further counter-clockwise about +z at the base than in the other one)
and -1 for the other. Along a continued motion through a bistable range the label stays the
same: a two-tube robot's equilibria lie on a line in uz(0) (sum_i GJ_i uz_i(0) = 0), so two of
them cannot swap order without meeting at a fold (for three or more tubes this is the same
convention, not a theorem).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from ctrplan.shape.base import Shape

#: default smallest stability (det J, see the module docstring) of a planned state: the softest
#: torsional mode keeps at least a tenth of the stiffness the tubes have without the interaction
#: of their curvatures, so the twist responds to the actuators and to unmodelled torques at most
#: about 10x as strongly as in tubes that do not interact. (two_tube_nylon at full overlap: about
#: 0.6 deg of relative rotation before the fold, where S falls as the square root of the
#: distance; seed1: 0.01 % of uniformly sampled configurations are below it, and the shipped
#: scenes' hard problems pass at 0.14 and above.)
DEFAULT_STABILITY_MARGIN = 0.1


@dataclass(frozen=True)
class Tracked:
    """Shapes with their equilibria.

    shape : the :class:`Shape` (B, ...); ``ok`` is False where the branch ended.
    uz0 : (B, n) 1/mm, base torsions of each row's equilibrium.
    stability : (B,) det J of it (module docstring); NaN where not computed.
    continued : (B,) bool, the row's equilibrium is the continuation of its chain start's
        (stable, no jump); for an unchained solve: the solve succeeded.
    """

    shape: Shape
    uz0: np.ndarray
    stability: np.ndarray
    continued: np.ndarray

    def __getitem__(self, index) -> Tracked:
        return Tracked(self.shape[index], self.uz0[index], self.stability[index],
                       self.continued[index])


def tracks_branches(model) -> bool:
    """Whether ``model`` is torsionally compliant unloaded mechanics (module docstring): the
    shapes it gives can depend on how the robot got to a configuration."""
    from ctrplan.shape.effects import EffectModel
    from ctrplan.shape.physics import PhysicsModel

    if isinstance(model, PhysicsModel):
        return model.torsion and model.loads is None and model.config.stability
    if isinstance(model, EffectModel):
        if not model.config.stability:
            return False
        ld = model.effects.get("load")
        if ld is not None and any(float(v) != 0.0 for v in ld.values()):
            return False
        tor = model.effects.get("torsion")
        if tor is not None:
            return float(tor.get("compliance", 0.0)) > 0.0
        return model.base == "compliant"
    return False


def solve(model, q: np.ndarray, points: int, direction: np.ndarray | None = None,
          uz_init: np.ndarray | None = None, chain: np.ndarray | None = None) -> Tracked:
    """Shapes of q (B, 2n) with their equilibria, for a model that :func:`tracks_branches`.

    chain : None, the model's own choice per row (history-free); or (B,) bool, True where a
        row starts a chain (at the equilibrium Newton reaches from its ``uz_init`` row, or the
        model's own choice where that row is NaN); the other rows continue the row before.
    uz_init : (B, n) 1/mm (read on chain starts; without ``chain``: Newton's initial guesses).
    direction : (B, 2n) direction of motion (direction-aware effect models).
    """
    from ctrplan.shape.effects import EffectModel, evaluate

    q = np.atleast_2d(np.asarray(q, dtype=float))
    if isinstance(model, EffectModel):
        from ctrplan.shape.base import check_q

        shape = evaluate(model, check_q(model.robot, q), points, direction=direction,
                         uz_init=uz_init, chain=chain)
        info = model._compliant.last_info
    else:
        if chain is None and uz_init is None:
            shape = model.shape(q, points)
        else:
            from ctrplan.shape.base import check_q

            shape = model.solve(check_q(model.robot, q), points, model.base_params(len(q)),
                                uz_init=uz_init, chain=chain)
        info = model.last_info
    cont = np.asarray(shape.ok, dtype=bool) if info.continued is None else info.continued
    stab = np.asarray(info.detj, dtype=float) if info.detj is not None else np.full(len(q), np.nan)
    return Tracked(shape, np.array(info.uz0, dtype=float), stab, np.asarray(cont, dtype=bool))


def settle(model, q: np.ndarray, uz0: np.ndarray, points: int,
           direction: np.ndarray | None = None) -> Tracked:
    """The equilibria Newton reaches from ``uz0`` (B, n) at each row of q (B, 2n), each row
    its own start: the shapes of states whose equilibrium is known (from a nearby state of the
    same branch, or exactly)."""
    B = len(np.atleast_2d(q))
    return solve(model, q, points, direction, uz_init=uz0, chain=np.ones(B, dtype=bool))


def probing(model):
    """``model`` with ``probe_bistable`` on (cached on the model object: freed with it)."""
    from ctrplan.objcache import owned
    from ctrplan.shape.effects import EffectModel

    cache = owned(model)
    hit = None if cache is None else cache.get("probing")
    if hit is not None:
        return hit
    if isinstance(model, EffectModel):
        pm = EffectModel(model.robot, model.base, model.effects,
                         replace(model.config, probe_bistable=True), pure=model.pure)
    else:
        pm = model.with_config(probe_bistable=True)
    if cache is not None:
        cache["probing"] = pm
    return pm


def stable_equilibria(model, q: np.ndarray,
                      direction: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """The stable equilibria the model finds at each row of q (B, 2n): (first (B, n), second
    (B, n), NaN where it finds only one). The second is searched where an unstable equilibrium
    was met or two curved tubes are rotated apart by more than 90 deg
    (:class:`~ctrplan.shape.physics.PhysicsConfig` ``probe_bistable``); not finding one does not
    prove there is none."""
    from ctrplan.shape.effects import EffectModel, evaluate

    pm = probing(model)
    q = np.atleast_2d(np.asarray(q, dtype=float))
    if isinstance(pm, EffectModel):
        evaluate(pm, q, 2, direction=direction)
        info = pm._compliant.last_info
    else:
        pm.shape(q, 2)
        info = pm.last_info
    return np.array(info.uz0, dtype=float), np.array(info.uz0_alt, dtype=float)


def same_equilibrium(a: np.ndarray, b: np.ndarray, robot) -> np.ndarray:
    """(B,) bool: base torsions a, b (B, n) 1/mm are the same equilibrium (max norm within
    1e-4 of the robot's largest |curvature|, far below the gap between two equilibria)."""
    amp = max(float(np.max(np.abs(robot.array("curvature")))), 1e-12)
    with np.errstate(invalid="ignore"):
        return np.max(np.abs(np.asarray(a) - np.asarray(b)), axis=-1) <= 1e-4 * amp


def label_of(uz0: np.ndarray, first: np.ndarray, second: np.ndarray, robot) -> np.ndarray:
    """(B,) int8 branch labels (module docstring) of equilibria uz0 (B, n) given the stable
    equilibria found at the same configurations (:func:`stable_equilibria`)."""
    uz0 = np.atleast_2d(uz0)
    two = np.all(np.isfinite(second), axis=1)
    on_first = same_equilibrium(uz0, first, robot)
    other = np.where((two & on_first)[:, None], second, first)
    bistable = two | ~on_first        # a stable equilibrium other than the one found first
    sign = np.where(uz0[:, 0] > other[:, 0], 1, -1)
    return np.where(bistable, sign, 0).astype(np.int8)


def branch_labels(model, q: np.ndarray, uz0: np.ndarray,
                  direction: np.ndarray | None = None) -> np.ndarray:
    """(B,) int8 ``branch`` of equilibria uz0 (B, n) at configurations q (B, 2n): 0 one stable
    equilibrium found there, +1 / -1 the one of two with the larger / smaller uz_1(0)."""
    first, second = stable_equilibria(model, q, direction)
    return label_of(uz0, first, second, model.robot)
