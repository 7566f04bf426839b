"""The public, typed result of a diagnosis: :class:`DiagnoseReport` and its parts.

Shared by every stage of the calibration pipeline (:mod:`ctrplan.calibration.diagnose`) and by
the report writer; imports no other stage, so no stage has to import a later one.
"""

from __future__ import annotations

import enum
import math
from dataclasses import asdict, dataclass, field

from ctrplan.robot import Robot
from ctrplan.shape.effects import EffectModel, effect_params

__all__ = ["DiagnoseReport", "DiagnoseStatus", "Step", "Candidate", "headline"]


class DiagnoseStatus(str, enum.Enum):
    """Outcome of a diagnosis (``status`` in report.json)."""

    FOUND = "found"
    NO_MISSING_EFFECT = "no missing effect"
    AMBIGUOUS = "ambiguous"
    UNEXPLAINED = "unexplained"
    INSUFFICIENT = "insufficient data"


@dataclass
class Candidate:
    """One screened candidate: effect (and form), its BIC change and held-out error (mm)."""

    effect: str
    delta_bic: float
    test_mean_mm: float
    justified: bool
    form: str = ""


@dataclass
class Step:
    """One accepted effect (or the final, rejected screening when ``accepted`` is False)."""

    effect: str | None
    accepted: bool
    parameters: dict[str, dict[str, float]]
    sigma: dict[str, dict[str, float]]
    error_before_mm: float
    error_after_mm: float
    max_before_mm: float
    max_after_mm: float
    delta_bic: float
    heldout_gain: float
    runner_up: str | None
    runner_up_delta_bic: float | None
    ambiguous: bool
    screened: list[Candidate] = field(default_factory=list)
    form: str = ""
    named: bool = True
    #: why an effect that failed the shares is named (its signature in the data), else ""
    named_by: str = ""


@dataclass
class DiagnoseReport:
    """Result of :func:`diagnose`.

    effects : names added, in order ([] = nothing named). parameters : effect -> param ->
    value (joint final fit); sigma : the same, standard uncertainties. error_before_mm /
    error_after_mm : held-out mean tip error of the base / calibrated model (max_*: maximum).
    evidence : the data-only tests before and after; unexplained : what the residual still
    correlates with and how much is left (None when it is at the noise floor); warnings : what
    limits the diagnosis; experiment : what data would support one (when insufficient).
    """

    success: bool
    status: DiagnoseStatus
    conclusion: str
    robot: Robot
    base: str
    effects: list[str]
    parameters: dict[str, dict[str, float]]
    sigma: dict[str, dict[str, float]]
    steps: list[Step]
    error_before_mm: float
    error_after_mm: float
    max_before_mm: float
    max_after_mm: float
    train_sweeps: list[str]
    test_sweeps: list[str]
    diagnostics_before: dict
    diagnostics_after: dict
    settings: dict
    elapsed_s: float
    model_effects: dict[str, dict[str, float]] = field(default_factory=dict)
    forms: dict[str, str] = field(default_factory=dict)
    evidence_before: dict = field(default_factory=dict)
    evidence_after: dict = field(default_factory=dict)
    unexplained: dict | None = None
    warnings: list[str] = field(default_factory=list)
    experiment: list[str] = field(default_factory=list)
    partial: list[str] = field(default_factory=list)
    error_quantiles: dict[str, float] | None = None
    split: dict = field(default_factory=dict)
    learned_residual: dict | None = None
    partial_values: dict = field(default_factory=dict)
    outliers: dict = field(default_factory=dict)
    nuisance_tests: list = field(default_factory=list)
    #: {"min": [n], "max": [n]} mm: the insertions of the measured rows (where the error bound
    #: was measured), or None
    measured_insertion: dict | None = None
    #: the base model's test-row tip error quantiles (as ``error_quantiles``)
    error_quantiles_before: dict[str, float] | None = None
    #: effects whose tip changes the rows cannot tell apart (:mod:`ctrplan.calibration.confound`)
    confounded: list = field(default_factory=list)
    #: the fitted model compared with the base on the test rows, the default output and the
    #: cross-fitted errors (:func:`ctrplan.calibration.verdict.heldout_choice`)
    heldout_comparison: dict = field(default_factory=dict)
    #: the fitted model's effects (equal to ``model_effects`` unless the base model is the
    #: default output because the fit is worse on the test rows)
    fit_effects: dict = field(default_factory=dict)

    def model(self) -> EffectModel:
        """The calibrated shape model with its held-out error quantiles (tip error on the test
        rows) and the error profile along the shaft they imply
        (:func:`ctrplan.shape.error_bounds.extend_tip_bound`: tip bound x arc-length fraction),
        which ``--margin auto`` pads each capsule with."""
        from ctrplan.shape.error_bounds import extend_tip_bound

        prof = extend_tip_bound(self.error_quantiles).to_dict() if self.error_quantiles else None
        return EffectModel(self.robot, self.base, self.model_effects,
                           error_quantiles=self.error_quantiles, error_profile=prof,
                           measured_insertion=self.measured_insertion)

    def headline(self) -> str:
        """One line: held-out mean AND max tip error before -> after, each judged honestly."""
        return headline(self.error_before_mm, self.error_after_mm, self.max_before_mm,
                        self.max_after_mm)

    def to_dict(self) -> dict:
        """JSON-ready dict (the report.json fields of docs/conventions.md and more), each value
        under one key (``max_error_before_mm`` / ``max_error_after_mm``, ``partial``; the
        Python attributes are ``max_before_mm`` / ``max_after_mm``)."""
        steps = [asdict(s) for s in self.steps]
        return {
            "headline": self.headline(),
            "robot": self.robot.name, "base": self.base, "status": self.status.value,
            "conclusion": self.conclusion, "effects": list(self.effects),
            "forms": dict(self.forms),
            "parameters": _params_json(self.parameters, self.sigma, self.robot, self.base),
            "steps": steps, "error_before_mm": self.error_before_mm,
            "error_after_mm": self.error_after_mm,
            "max_error_before_mm": self.max_before_mm, "max_error_after_mm": self.max_after_mm,
            "error_quantiles": self.error_quantiles,
            "error_quantiles_before": self.error_quantiles_before,
            "confounded": list(self.confounded),
            "heldout_comparison": self.heldout_comparison,
            "measured_insertion": self.measured_insertion,
            "unexplained": self.unexplained, "warnings": list(self.warnings),
            "experiment": list(self.experiment), "partial": list(self.partial),
            "partial_values": self.partial_values,
            "learned_residual": self.learned_residual,
            "evidence": {"before": self.evidence_before, "after": self.evidence_after},
            "split": {"train_sweeps": self.train_sweeps, "test_sweeps": self.test_sweeps,
                      **self.split},
            "diagnostics": {"before": self.diagnostics_before, "after": self.diagnostics_after},
            "test_rows": self.split.get("test_row_ranges", []),
            "outliers": self.outliers, "nuisance_tests": self.nuisance_tests,
            "settings": self.settings, "elapsed_s": self.elapsed_s,
        }


def headline(mb: float, ma: float, xb: float, xa: float) -> str:
    """``Held-out tip error: mean B -> A mm (improved), max B -> A mm (worse)``."""
    def judge(b, a):
        if not (math.isfinite(b) and math.isfinite(a)):
            return "not measured"
        if a < b - 1e-9:
            return "improved"
        if a > b + 1e-9:
            return "worse"
        return "unchanged"

    return (f"Held-out tip error: mean {mb:.3f} -> {ma:.3f} mm ({judge(mb, ma)}), "
            f"max {xb:.3f} -> {xa:.3f} mm ({judge(xb, xa)})")


def _params_json(values, sigma, robot, base) -> dict:
    out: dict = {}
    for e, vals in values.items():
        units = {p.name: p.unit for p in effect_params(e, robot, base)}
        out[e] = {k: {"value": v, "sigma": sigma.get(e, {}).get(k), "unit": units.get(k, "")}
                  for k, v in vals.items()}
    return out
