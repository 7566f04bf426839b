"""What planning needs from a shape model, as one typed record built by one function.

A shape model (the :class:`~ctrplan.shape.base.ShapeModel` protocol: ``robot``, ``name``,
``shape``, ``backbone``) may carry more that planning uses: the direction of the last motion
(friction), an error bound and where it was measured, the insertions it was measured over, a
curvature bound, an exact tip Jacobian, a sensor registration that collision checking must not
see, mechanics whose shape depends on the motion's history (elastic branches). Each model kind
(physics, rigid, an effect model from ``diagnose``, a learned network, a user's object) states
these in its own way; :func:`planning_model` reads them once, in this module only, into a frozen
:class:`PlanningModel`. Planning (:mod:`ctrplan.planning`) asks the record, never the model.

The record is itself a shape model (``robot``, ``name``, ``shape``, ``backbone``), so everything
that takes a model takes it; :meth:`PlanningModel.shape` passes ``direction`` to a model that
needs it and nothing more to one that does not, and the branch queries
(:meth:`~PlanningModel.solve`, :meth:`~PlanningModel.settle`,
:meth:`~PlanningModel.stable_equilibria`, :meth:`~PlanningModel.branch_labels`) go to
:mod:`ctrplan.shape.branches`.

Fitting (``fit=True``, what a planner uses): a model with ``planning_model()`` (an effect
model) is replaced by what that returns (no sensor registration, friction a pure function of
the configuration and the direction of motion); a user's calibrated object without it but with
``effects`` and ``with_effects`` gets the same effects without ``registration`` and, with
friction, every row evaluated as its own motion (:class:`RowwiseModel`); any other model is
used as it is. ``fit=False`` describes a model as given (a validator handed a model).

Optional attributes of a model that this module reads (all optional; docs/conventions.md):
``needs_direction`` (bool), ``error_quantiles`` ({p50, p95, p99, max} mm), ``error_profile``
(an :class:`~ctrplan.shape.error_bounds.ErrorProfile` or its mapping), ``error_bound``
(``measured`` / ``surrogate``), ``measured_insertion`` ({min: [n], max: [n]} mm),
``max_curvature`` (1/mm), ``effects`` (an effect model's mapping), ``planning_model()``,
``with_effects(effects)``, ``tip_and_jacobian(q)`` and ``meta`` (a learned model's metadata).
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from ctrplan.robot import Robot
from ctrplan.shape import branches as _br
from ctrplan.shape import error_bounds as _eb
from ctrplan.shape.base import Shape, needs_direction
from ctrplan.shape.bounds import curvature_bound


@dataclass(frozen=True, eq=False)
class PlanningModel:
    """What planning needs from a shape model (module docstring). Frozen; compared by identity.

    shape_model : the model planning evaluates (fitted, see :func:`planning_model`).
    given : the model the record was built from.
    robot : its Robot; name : its ``name``; label : how plan.json names it (the name or file
        given for it, else its ``name``).
    needs_direction : ``shape`` takes the direction of the last motion (friction).
    tracks_branches : compliant unloaded mechanics, whose shape depends on the motion
        (:func:`~ctrplan.shape.branches.tracks_branches`); then :meth:`solve` can chain.
    stability_margin : the default smallest stability of a planned state for a model that
        tracks branches (:data:`~ctrplan.shape.branches.DEFAULT_STABILITY_MARGIN`), else None.
    exact_jacobian : the model computes tip Jacobians itself (:meth:`tip_and_jacobian`).
    curvature_bound : bound (1/mm) of its unloaded backbone curvature
        (:func:`~ctrplan.shape.bounds.curvature_bound`): the sagitta padding of capsules
        (computed when first read: a planner without sagitta padding never asks).
    error_quantiles : {p50, p95, p99, max} mm, or None; error_profile : the same along the
        shaft (:class:`~ctrplan.shape.error_bounds.ErrorProfile`), or None;
        error_problem : why a stated profile is malformed ("" when it is fine).
    error_bound : where the bound was measured: ``measured`` (on a robot), ``surrogate``
        (against the simulated model a network imitates) or None (no bound).
    calibrated : the bound was measured on a robot (plan.json's ``calibrated``).
    surrogate_error : a surrogate's ``{p50, p95, p99, max, against}`` (plan.json), or None.
    measured_insertion : {"min": [n], "max": [n]} mm where the bound was measured, or None.
    effects : an effect model's effects (a calibrated model: its own reference), or None.
    """

    shape_model: Any
    given: Any
    robot: Robot | None
    name: str
    label: str
    needs_direction: bool
    tracks_branches: bool
    stability_margin: float | None
    exact_jacobian: bool
    error_quantiles: Mapping[str, float] | None
    error_profile: _eb.ErrorProfile | None
    error_problem: str
    error_bound: str | None
    calibrated: bool
    surrogate_error: dict | None
    measured_insertion: dict | None
    effects: Mapping[str, Any] | None

    @functools.cached_property
    def curvature_bound(self) -> float:
        return curvature_bound(self.shape_model)

    # ------------------------------------------------------------------ a shape model
    def shape(self, q: np.ndarray, points: int = 20, direction: np.ndarray | None = None) -> Shape:
        """Backbones of q (B, 2n) rad and mm; ``direction`` (B, 2n) in {-1, 0, +1} reaches only
        a model that needs it."""
        if direction is not None and self.needs_direction:
            return self.shape_model.shape(q, points=points, direction=direction)
        return self.shape_model.shape(q, points=points)

    def backbone(self, q: np.ndarray, points: int = 20) -> np.ndarray:
        """(B, points, 3) backbone points, mm, robot base frame."""
        return self.shape(q, points).points

    def tip_and_jacobian(self, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tips (B, 3) mm and Jacobians (B, 3, 2n) from the model itself (``exact_jacobian``)."""
        if not self.exact_jacobian:
            raise TypeError(f"model {self.name!r} has no tip_and_jacobian")
        return self.shape_model.tip_and_jacobian(q)

    # ------------------------------------------------------------------ error bound
    def auto_margin(self) -> float | _eb.ErrorProfile:
        """What ``--margin auto`` pads with: the error profile, else the uniform p99 of the
        error quantiles (mm), else 0.0. Raises ValueError on a malformed bound."""
        if self.error_problem:
            raise ValueError(self.error_problem)
        if self.error_profile is not None:
            return self.error_profile
        from ctrplan.shape.base import model_error_bound

        return model_error_bound(self, _eb.MARGIN_QUANTILE)

    # ------------------------------------------------------------------ branches
    def solve(self, q: np.ndarray, points: int, direction: np.ndarray | None = None,
              uz_init: np.ndarray | None = None, chain: np.ndarray | None = None) -> _br.Tracked:
        """Shapes with their equilibria (:func:`ctrplan.shape.branches.solve`; the chained
        solve with ``chain``)."""
        return _br.solve(self.shape_model, q, points, direction, uz_init=uz_init, chain=chain)

    def settle(self, q: np.ndarray, uz0: np.ndarray, points: int,
               direction: np.ndarray | None = None) -> _br.Tracked:
        """The equilibria Newton reaches from ``uz0`` (B, n) (:func:`ctrplan.shape.branches.settle`)."""
        return _br.settle(self.shape_model, q, uz0, points, direction)

    def stable_equilibria(self, q: np.ndarray,
                          direction: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """(first (B, n), second (B, n)) stable equilibria (:func:`ctrplan.shape.branches.stable_equilibria`)."""
        return _br.stable_equilibria(self.shape_model, q, direction)

    def branch_labels(self, q: np.ndarray, uz0: np.ndarray,
                      direction: np.ndarray | None = None) -> np.ndarray:
        """(B,) int8 plan.json ``branch`` labels (:func:`ctrplan.shape.branches.branch_labels`)."""
        return _br.branch_labels(self.shape_model, q, uz0, direction)


class RowwiseModel:
    """A calibrated model whose friction depends on the order of the rows, made a pure function
    of each row (every row its own motion): the stand-in for ``planning_model()`` on models
    that do not have it."""

    needs_direction = False

    def __init__(self, inner: Any):
        self.inner = inner
        self.robot = inner.robot
        self.name = inner.name
        self.effects = getattr(inner, "effects", None)
        self.error_quantiles = getattr(inner, "error_quantiles", None)
        self.error_profile = getattr(inner, "error_profile", None)
        self.error_bound = getattr(inner, "error_bound", None)
        self.measured_insertion = getattr(inner, "measured_insertion", None)

    def shape(self, q: np.ndarray, points: int = 20) -> Shape:
        q = np.atleast_2d(np.asarray(q, dtype=float))
        return self.inner.shape(q, points=points, sweep=np.arange(len(q)))

    def backbone(self, q: np.ndarray, points: int = 20) -> np.ndarray:
        return self.shape(q, points).points


def fitted(model: Any) -> Any:
    """The model fit for collision checking (module docstring, "Fitting")."""
    make = getattr(model, "planning_model", None)
    if callable(make):
        return make()
    effects = getattr(model, "effects", None)
    if not (isinstance(effects, dict) and hasattr(model, "with_effects")
            and ("registration" in effects or "friction" in effects)):
        return model
    pm = model.with_effects({k: v for k, v in effects.items() if k != "registration"})
    for name in ("error_quantiles", "error_profile"):
        if getattr(model, name, None) is not None:
            setattr(pm, name, getattr(model, name))
    pm.error_bound = getattr(model, "error_bound", None)
    return RowwiseModel(pm) if "friction" in effects else pm


def planning_model(model: Any, label: str | None = None, fit: bool = True) -> PlanningModel:
    """The :class:`PlanningModel` of any shape model (a record is returned as it is).

    model : a ShapeModel (physics, rigid, effect, learned, or a user's object).
    label : plan.json's name of the model (the name or file given; default its ``name``).
    fit : replace the model by its planning variant (module docstring); False: as given.
    """
    if isinstance(model, PlanningModel):
        return model
    sm = fitted(model) if fit else model
    name = str(getattr(sm, "name", type(sm).__name__))
    tracks = _br.tracks_branches(sm)
    try:
        profile, problem = _eb.error_profile_of(sm), ""
    except ValueError as exc:
        profile, problem = None, str(exc)
    effects = getattr(model, "effects", None)
    return PlanningModel(
        shape_model=sm, given=model, robot=getattr(sm, "robot", None), name=name,
        label=label if label is not None else str(getattr(model, "name", type(model).__name__)),
        needs_direction=needs_direction(sm), tracks_branches=tracks,
        stability_margin=_br.DEFAULT_STABILITY_MARGIN if tracks else None,
        exact_jacobian=callable(getattr(sm, "tip_and_jacobian", None)),
        error_quantiles=getattr(sm, "error_quantiles", None) or None,
        error_profile=profile, error_problem=problem, error_bound=_eb.error_bound_kind(sm),
        calibrated=_eb.is_calibrated(model) or _eb.is_calibrated(sm),
        surrogate_error=_eb.surrogate_error(model) or _eb.surrogate_error(sm),
        measured_insertion=(getattr(model, "measured_insertion", None)
                            or getattr(sm, "measured_insertion", None)),
        effects=effects if isinstance(effects, dict) else None)
