"""The best model of the robot from its measurements, in one call (``ctrplan diagnose --best``).

Procedure (:func:`best_model`):

1. **One split** (:func:`ctrplan.split.split`, the one held-out splitter of diagnose and train):
   fit / validation / test rows, ``holdout`` of the sweeps (or of the blocks of a continuous
   recording, with gaps) for test and as many for validation. Directions of motion are taken
   from the row order of the whole data set (the commanded history, not the measurements).
2. **Calibrated physics**: :func:`ctrplan.calibration.diagnose.diagnose` with that split
   (parameters fitted on the fit rows, effects chosen on the validation rows, refitted on
   both); its calibrated model (:meth:`DiagnoseReport.model`) is a candidate, next to the
   nominal model.
3. **Learned residual over the calibrated model** (:mod:`ctrplan.shape.training`): the network
   learns the difference between the measured shapes and the calibrated model's on the fit
   rows; the direction-aware form competes when the rows show motion with reversals (chosen on
   the validation rows, :func:`ctrplan.shape.training.select_variant`). With tip-only data the
   residual has one basis term (a correction growing linearly along the shaft: the data say
   nothing about its shape between base and tip).
4. **Learned alone** (shapes measured only): the robot's shipped network fine-tuned on the
   measured shapes (or a new network where no shipped one fits the robot), pure or
   direction-aware, chosen the same way.
5. **Comparison on the test rows**: every candidate's max deviation along the shaft per test
   configuration (tip deviation where only tips are measured), on the rows every candidate
   answers (a row where a model's solver fails is counted in its ``failed_rows``; only the
   candidates with the fewest failed rows may win); the one with the lowest mean wins (ties:
   the simpler, in the order above).
6. **The winner's error bound from rows that did not choose it** (cross-fitting): the test
   units (sweeps or blocks) are dealt into two folds; each fold's deviations are those of the
   candidate the *other* fold chooses by the same rule, and the winner is written with the
   quantiles of these deviations (``error_quantiles``) and, where shapes are measured, the
   ``error_profile`` per arc-length fraction (docs/conventions.md). When both folds choose the
   winner these are its own test deviations; otherwise the bound covers the choice as well.

Frames: a calibrated ``registration`` (tracker to robot) is not part of the robot. When the
calibrated model has one, the measured points are mapped into the robot base frame with it,
and every candidate is compared there (distances are unchanged for the calibrated model);
the learned models work in the robot base frame, as planning needs.
"""

from __future__ import annotations

import inspect
import logging
import math
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ctrplan.measured import MeasuredData, read_measured
from ctrplan.robot import Robot, load_robot
from ctrplan.split import HeldOut, is_ordered, row_ranges, split

log = logging.getLogger("ctrplan")

__all__ = ["best_model", "BestResult", "holdout_split", "CANDIDATES"]

#: candidate names, in order of simplicity (ties go to the first)
CANDIDATES = ("nominal", "calibrated", "calibrated+learned", "learned")
#: fewer development rows than this: no learned candidates (nothing to train and validate on)
MIN_LEARNED_ROWS = 20
#: the comparison metric
#: files and folders of the comparison (next to diagnose's report files)
BEST_FILES = ("best_model.yaml", "best_model.pt", "best_model.json", "best_model.md",
              "best_candidates")
METRIC = "max deviation along the shaft per test configuration (tip deviation with tip-only data), mm"


@dataclass
class BestResult:
    """What :func:`best_model` did: the winner's name and model, every candidate's test
    metrics (``candidates``: name -> dict), the split, the diagnose report of the development
    rows, and the files written (name -> path)."""

    winner: str
    model: Any
    candidates: dict[str, dict[str, Any]]
    split: dict[str, Any]
    report: Any
    shapes: bool
    elapsed_s: float = 0.0
    files: dict[str, str] = field(default_factory=dict)

    def table(self) -> dict[str, Any]:
        """JSON-ready comparison (best_model.json)."""
        return {"winner": self.winner, "metric": METRIC, "shapes_measured": self.shapes,
                "candidates": self.candidates, "split": self.split, "files": self.files,
                "elapsed_s": self.elapsed_s,
                "note": "all candidates evaluated on the same test rows, which no fit and no "
                        "choice saw before this comparison; the winner's error bound "
                        "(error_quantiles of best_model) is cross-fitted: each fold of the test "
                        "units contributes the deviations of the candidate the other fold "
                        "chooses"}


# ---------------------------------------------------------------------------------- split
def holdout_split(data: MeasuredData, test_fraction: float = 0.25,
                  seed: int = 0) -> tuple[np.ndarray, np.ndarray, dict[str, Any]]:
    """(test mask, unit labels (B,) object, description) of the one held-out splitter
    (:func:`ctrplan.split.split` with ``test_fraction`` for test and as many for validation):
    labels are the sweep ids, ``"<sweep>#block<k>"`` for the blocks of a continuous recording,
    or ``"row<k>"`` for independent samples."""
    h = _heldout(data, test_fraction, seed)
    return h.test, h.labels, _describe(h, data)


def _heldout(data: MeasuredData, holdout: float, seed: int) -> HeldOut:
    return split(data.sweep, len(data), holdout, holdout, seed, q=data.q,
                 ordered=is_ordered(data.sweeps(), len(data)))


def _describe(h: HeldOut, data: MeasuredData) -> dict[str, Any]:
    """best_model.json ``split``: how the rows were held out."""
    if h.kind == "whole sweeps":
        desc: dict[str, Any] = {"method": "whole sweeps held out",
                                "test_sweeps": sorted(set(np.asarray(data.sweeps())[h.test]
                                                          .astype(str).tolist()))}
    elif h.kind == "rows":
        desc = {"method": "random rows held out (rows are independent samples)",
                "test_rows": int(h.test.sum())}
    else:
        blocks = sorted(set(h.labels[h.test].tolist()))
        desc = {"method": f"contiguous blocks held out ({len(blocks)}; fewer than 8 sweeps), "
                          f"{h.gap_rows} rows left out on each side",
                "test_blocks": blocks, "test_rows": row_ranges(h.test)}
    return {**desc, **h.describe()}


def to_robot_frame(effects: dict, points: np.ndarray) -> np.ndarray:
    """Sensor-frame points (..., 3) -> robot base frame, inverting a calibrated
    ``registration`` (p_sensor = R p + t); unchanged without one."""
    from ctrplan.shape.effects import _rotvec_matrix

    rg = (effects or {}).get("registration")
    if not rg:
        return points
    t = np.array([rg["tx"], rg["ty"], rg["tz"]], dtype=float)
    r = np.array([rg["rx"], rg["ry"], rg["rz"]], dtype=float)
    return (np.asarray(points, dtype=float) - t) @ _rotvec_matrix(r)


# ---------------------------------------------------------------------------------- metrics
def _deviations(model: Any, q: np.ndarray, direction: np.ndarray, target: np.ndarray) -> np.ndarray:
    """(B, m) distances between the model's points (m evenly spaced, base to tip) and target."""
    from ctrplan.shape.base import needs_direction

    m = target.shape[1]
    if needs_direction(model):
        pred = model.shape(q, m, direction=direction).points
    else:
        pred = model.backbone(q, m)
    return np.linalg.norm(pred - target, axis=2)


def _metrics(dev: np.ndarray, common: np.ndarray, shapes: bool) -> dict[str, Any]:
    """Test metrics of one candidate on the rows every candidate answered (``common``)."""
    from ctrplan.shape.learned import error_quantiles
    from ctrplan.shape.training import error_profile

    mx = dev.max(axis=1)
    out: dict[str, Any] = {"rows": int(common.sum()), "failed_rows": int((~np.isfinite(mx)).sum()),
                           "mean_mm": math.inf, "tip_mean_mm": math.inf, "error_quantiles": None}
    if common.any():
        out.update(mean_mm=float(mx[common].mean()), tip_mean_mm=float(dev[common, -1].mean()),
                   error_quantiles=error_quantiles(mx[common]))
        if shapes:
            out["error_profile"] = error_profile(dev[common])
    return out


# ---------------------------------------------------------------------------------- main
@dataclass(frozen=True)
class _Rows:
    """The measured rows and how :func:`best_model` splits them (``heldout``: fit, validation,
    test and gap rows, unit labels), ``direction`` (B, 2n) of motion (zeros when rows are
    independent samples) and the split's description."""

    data: MeasuredData
    shapes: bool
    ordered: bool
    direction: np.ndarray
    heldout: HeldOut
    split: dict[str, Any]

    @property
    def test(self) -> np.ndarray:
        return self.heldout.test

    @property
    def dev(self) -> np.ndarray:
        """Development rows (fit | validation)."""
        return self.heldout.dev


def _split_rows(data: MeasuredData, holdout: float, seed: int) -> _Rows:
    from ctrplan.shape.base import direction_from_rows

    sw = np.asarray(data.sweeps()).astype(str)
    ordered = is_ordered(sw, len(data))
    direction = (direction_from_rows(data.q, sw) if ordered else np.zeros(data.q.shape, dtype=np.int8))
    h = _heldout(data, holdout, seed)
    split = _describe(h, data)
    split.update({"rows": len(data), "test_rows_count": int(h.test.sum()),
                  "dev_rows": int(h.dev.sum()), "fit_rows": int(h.fit.sum()),
                  "validation_rows": int(h.val.sum()),
                  "test_row_indices": np.flatnonzero(h.test).tolist(),
                  "row_index_note": "0-based data rows of the measured CSV (header excluded)"})
    return _Rows(data, data.points is not None, ordered, direction, h, split)


def best_model(robot: Robot | str, data: MeasuredData | str | os.PathLike, out: str | os.PathLike | None = None,
               base: str = "rigid", holdout: float = 0.25, seed: int = 0,
               diagnose_kwargs: dict[str, Any] | None = None, epochs: int = 300, patience: int = 20,
               width: int = 30, depth: int = 3, learned: bool = True,
               test_fraction: float | None = None) -> BestResult:
    """Calibrate, learn, compare on untouched test rows, write the winner (module docstring).

    robot : Robot or name / YAML. data : MeasuredData or measured CSV path. out : folder for
    diagnose's files and ``best_model.{yaml,pt}``, ``best_model.json`` / ``.md`` (the
    comparison) and ``best_candidates/<name>.{yaml,pt}`` (every candidate, each with its own
    test quantiles). holdout : fraction of the sweeps (blocks) held out for test, and as many
    for validation (the one split, :func:`ctrplan.split.split`). diagnose_kwargs : passed to
    :func:`diagnose` (candidates, bic_threshold, ...). epochs / patience / width / depth : the
    learned networks' training. learned : False = physics candidates only. test_fraction :
    deprecated name of ``holdout`` (one release).
    """
    t0 = time.perf_counter()
    if test_fraction is not None:
        import warnings

        warnings.warn("best_model(test_fraction=...) is deprecated; use holdout=",
                      DeprecationWarning, stacklevel=2)
        holdout = test_fraction
    robot = load_robot(robot)
    if not isinstance(data, MeasuredData):
        data = read_measured(data, robot)
    if not 0.0 < holdout < 1.0:
        from ctrplan.errors import InputError

        raise InputError("holdout", "", f"must be in (0, 1), got {holdout}")
    rows = _split_rows(data, holdout, seed)
    net = dict(epochs=epochs, patience=patience, width=width, depth=depth)
    if out is None:
        res = _best(robot, rows, None, base, seed, diagnose_kwargs, learned, net, t0)
    else:
        # diagnose's report and the comparison are one set: written beside ``out`` and
        # swapped in whole (a full disk leaves the previous set complete)
        from ctrplan.calibration.report import REPORT_FILES, output_set

        with output_set(out, REPORT_FILES + BEST_FILES) as stage:
            res = _best(robot, rows, stage, base, seed, diagnose_kwargs, learned, net, t0)
    log.info("best model: %s (test mean max deviation %.3f mm)", res.winner,
             res.candidates[res.winner]["mean_mm"])
    return res


def _best(robot: Robot, rows: _Rows, out: Path | None, base: str, seed: int,
          diagnose_kwargs: dict[str, Any] | None, learned: bool, net: dict[str, int],
          t0: float) -> BestResult:
    """The work of :func:`best_model` (started at ``t0``, perf_counter), writing into folder
    ``out`` (None: nothing written)."""
    from ctrplan.calibration.diagnose import diagnose
    from ctrplan.shape.effects import EffectModel

    data, shapes, split = rows.data, rows.shapes, rows.split
    log.info("best model: %d test rows held out (%s), %d fit and %d validation rows",
             int(rows.test.sum()), split["method"], int(rows.heldout.fit.sum()),
             int(rows.heldout.val.sum()))
    dkw = {k: v for k, v in (diagnose_kwargs or {}).items() if k != "holdout"}
    if "learned_residual" in inspect.signature(diagnose).parameters:
        dkw.setdefault("learned_residual", False)   # superseded by the candidates below
    rep = diagnose(robot, data, base=base, seed=seed, out=out, heldout=rows.heldout, **dkw)
    calibrated = rep.model()
    effects = {k: dict(v) for k, v in calibrated.effects.items()}
    frame_effects = {k: v for k, v in effects.items() if k != "registration"}

    # targets in the robot base frame; tip-only data: base point (origin) and tip
    if shapes:
        target = to_robot_frame(effects, data.points)
    else:
        tip = to_robot_frame(effects, data.tip)
        target = np.stack([np.zeros_like(tip), tip], axis=1)
    models: dict[str, Any] = {
        "nominal": EffectModel(robot, base),
        "calibrated": EffectModel(robot, base, frame_effects),
    }
    desc = {"nominal": f"the nominal {base} model (no effects)",
            "calibrated": "diagnose's calibrated model" + (
                f" ({', '.join(frame_effects)})" if frame_effects else " (no effect kept: nominal)")}
    selections: dict[str, Any] = {}
    skipped = None
    n_dev = int(rows.dev.sum())
    if learned and (n_dev < MIN_LEARNED_ROWS or not rows.heldout.val.any()):
        skipped = f"learned candidates skipped: {n_dev} development rows (< {MIN_LEARNED_ROWS})"
        log.info("best model: %s", skipped)
        learned = False
    if learned:
        _learned_candidates(robot, rows, target, models, desc, selections, seed, net)
    table, winner = _compare(models, desc, selections, rows, target)
    res = BestResult(winner=winner, model=models[winner], candidates=table, split=split,
                     report=rep, shapes=shapes)
    split["frame"] = ("robot base frame (measured points mapped with the calibrated registration)"
                      if "registration" in effects else "robot base frame (no registration calibrated)")
    if skipped:
        split["note"] = skipped
    split["directions"] = "from the row order of the whole data set" if rows.ordered else "none (rows are independent samples)"
    res.elapsed_s = time.perf_counter() - t0
    if out is not None:
        _write(res, models, Path(out))
    return res


def _learned_candidates(robot: Robot, rows: _Rows, target: np.ndarray, models: dict[str, Any],
                        desc: dict[str, str], selections: dict[str, Any], seed: int,
                        net: dict[str, int]) -> None:
    """Add the learned candidates (calibrated + learned residual; learned alone where shapes
    are measured) to ``models`` / ``desc`` / ``selections``, each variant chosen on a
    validation part of the development sweeps."""
    import torch

    from ctrplan.shape import training as T

    data, shapes, ordered = rows.data, rows.shapes, rows.ordered
    width, depth = net["width"], net["depth"]
    torch_threads = torch.get_num_threads()
    sdata = T.ShapeData(data.q, target, source=str(getattr(data, "source", "measured")),
                        direction=rows.direction.astype(float) if ordered else None,
                        sweep=rows.heldout.labels, measured=True)
    dv = sdata.subset(np.flatnonzero(rows.dev))
    # weights fitted on the fit rows, variants chosen on the validation rows of the one split
    tr = sdata.subset(np.flatnonzero(rows.heldout.fit))
    va = sdata.subset(np.flatnonzero(rows.heldout.val))
    motion = ordered and T.has_motion(dv)
    cfg = T.TrainConfig(epochs=net["epochs"], patience=net["patience"], batch_size=128, seed=seed,
                        progress=False, label="train (real)")
    fine = cfg.replace(lr=5e-4, label="fine-tune (real)")
    res_base = models["calibrated"].planning_model()
    terms = None if shapes else 1
    cands = ["residual", "residual+direction"] if motion else ["residual"]
    m, _, sel = T.select_variant(robot, tr, va, None, candidates=cands, residual_base=res_base,
                                 width=width, depth=depth, seed=seed,
                                 terms=terms or 7, fine=fine, real_only=cfg)
    m.set_domain(dv.q, source="measured (development rows)")
    models["calibrated+learned"] = m
    selections["calibrated+learned"] = sel
    desc["calibrated+learned"] = (f"learned residual ({sel['chosen']}) over the calibrated model"
                                  + ("" if shapes else ", one basis term (tip-only data)"))
    if shapes:
        sim = _shipped(robot)
        cands = ["pure", "direction"] if motion else ["pure"]
        m, _, sel = T.select_variant(robot, tr, va, None, candidates=cands, sim_model=sim,
                                     width=width, depth=depth, seed=seed, fine=fine, real_only=cfg)
        m.set_domain(dv.q, source="measured (development rows)")
        models["learned"] = m
        selections["learned"] = sel
        desc["learned"] = (f"learned alone ({sel['chosen']}; "
                           + ("the shipped network fine-tuned" if sim is not None else "a new network")
                           + ")")
    torch.set_num_threads(torch_threads)


def _compare(models: dict[str, Any], desc: dict[str, str], selections: dict[str, Any],
             rows: _Rows, target: np.ndarray) -> tuple[dict[str, dict[str, Any]], str]:
    """Every candidate on the same test rows: (table, winner); attaches each model's bound
    (the winner's cross-fitted, :func:`crossfit`)."""
    data, test, split, shapes = rows.data, rows.test, rows.split, rows.shapes
    qt, dt, yt = data.q[test], rows.direction[test], target[test]
    table: dict[str, dict[str, Any]] = {}
    devs = {name: _deviations(model, qt, dt, yt) for name, model in models.items()}
    common = np.all([np.isfinite(d.max(axis=1)) for d in devs.values()], axis=0)
    split["compared_rows"] = int(common.sum())
    for name in models:
        table[name] = {"description": desc[name], **_metrics(devs[name], common, shapes)}
        if name in selections:
            table[name]["variant_selection"] = selections[name]
        log.info("best model: %-18s test mean max deviation %.3f mm", name, table[name]["mean_mm"])
    winner = choose_winner(table)
    folds = fold_of_test_rows(rows.heldout.labels[test])
    cf_dev, chosen = crossfit(devs, folds, shapes)
    split["crossfit"] = {
        "folds": [np.flatnonzero(test)[folds == f].tolist() for f in (0, 1)],
        "chosen_by_other_fold": chosen,
        "note": "0-based rows of each fold of the test units; each fold's deviations come "
                "from the candidate the other fold chose (the winner's error bound)"}
    for name, model in models.items():
        row = table[name]
        if name == winner:
            ok = np.isfinite(cf_dev.max(axis=1))
            row = {**row, **_metrics(cf_dev, ok, shapes)}
            table[name]["crossfit_error_quantiles"] = row["error_quantiles"]
        _attach_bound(model, row, shapes, split, crossfitted=name == winner)
        table[name]["winner"] = name == winner
    return table, winner


def fold_of_test_rows(units: np.ndarray) -> np.ndarray:
    """(T,) fold 0 / 1 of each test row: its unit's place among the test units, alternating
    (one unit: its first and second half)."""
    names = list(dict.fromkeys(np.asarray(units).tolist()))
    if len(names) >= 2:
        place = {nm: k % 2 for k, nm in enumerate(names)}
        return np.array([place[u] for u in np.asarray(units).tolist()], dtype=int)
    T = len(units)
    return (np.arange(T) >= T // 2).astype(int)


def crossfit(devs: dict[str, np.ndarray], folds: np.ndarray,
             shapes: bool) -> tuple[np.ndarray, list[str]]:
    """Cross-fitted deviations (T, m): the rows of fold f take the deviations of the candidate
    chosen (:func:`choose_winner`) on the other fold's rows; and those two choices."""
    out = np.full_like(next(iter(devs.values())), np.nan)
    chosen = []
    for f in (0, 1):
        other = folds != f
        if not other.any() or not (folds == f).any():
            chosen.append("")
            continue
        sub = {name: d[other] for name, d in devs.items()}
        common = np.all([np.isfinite(d.max(axis=1)) for d in sub.values()], axis=0)
        pick = choose_winner({name: _metrics(d, common, shapes) for name, d in sub.items()})
        out[folds == f] = devs[pick][folds == f]
        chosen.append(pick)
    return out, chosen


def choose_winner(table: dict[str, dict[str, Any]]) -> str:
    """The candidate with the lowest test mean among those with the fewest failed rows
    (ties: the simpler, in the order of :data:`CANDIDATES`)."""
    fewest = min(row["failed_rows"] for row in table.values())
    return min((k for k, row in table.items() if row["failed_rows"] == fewest),
               key=lambda k: (table[k]["mean_mm"], CANDIDATES.index(k)))


def _shipped(robot: Robot):
    """The robot's shipped network when it was trained for the same tubes, else None."""
    from ctrplan.shape.learned import LearnedModel, shipped_model_path

    p = shipped_model_path(robot.name)
    if p is None:
        return None
    try:
        return LearnedModel.load(p, robot=robot)
    except Exception:  # noqa: BLE001 - another robot of the same name: no pre-trained start
        return None


def _attach_bound(model: Any, row: dict[str, Any], shapes: bool, split: dict[str, Any],
                  crossfitted: bool = False) -> None:
    """Store a candidate's test quantiles (and profile where shapes are measured) in it."""
    eq = row.get("error_quantiles")
    model.error_quantiles = dict(eq) if eq else None
    prof = row.get("error_profile") if shapes else None
    src = {"part": "best-model test rows (" + split["method"] + ")"
           + ("; cross-fitted over two folds of the test units" if crossfitted else ""),
           "rows": row["rows"], "metric": METRIC}
    extended = False
    if not prof and eq:   # tip-only: the bound along the shaft by the documented extension rule
        from ctrplan.shape.error_bounds import extend_tip_bound

        prof, extended = extend_tip_bound(eq).to_dict(), True
    model.error_profile = dict(prof) if prof else None
    model.error_bound = "measured" if (eq or prof) else None   # the robot's held-out test rows
    if hasattr(model, "meta"):                    # learned model: where the numbers come from
        model.meta["error_quantiles_source"] = src
        model.meta.pop("error_profile_source", None)
        if prof:
            model.meta["error_profile_source"] = {**src, "metric": (
                "tip bound x arc-length fraction (error_bounds.extend_tip_bound)" if extended else
                "distance of the backbone point at each arc-length fraction, mm")}


def _write(res: BestResult, models: dict[str, Any], out: Path) -> None:
    from ctrplan.io import jsonable, write_json_atomic, write_text_atomic

    out.mkdir(parents=True, exist_ok=True)
    cdir = out / "best_candidates"
    cdir.mkdir(exist_ok=True)
    files = {}
    for name, model in models.items():
        suffix = ".pt" if hasattr(model, "meta") else ".yaml"
        path = cdir / (name.replace("+", "_") + suffix)
        if hasattr(model, "meta"):
            model.meta["best_model"] = {"candidate": name, "winner": name == res.winner}
        model.save(path)
        files[name] = str(path.relative_to(out))
    win = models[res.winner]
    suffix = ".pt" if hasattr(win, "meta") else ".yaml"
    best = out / ("best_model" + suffix)
    other = out / ("best_model" + (".yaml" if suffix == ".pt" else ".pt"))
    win.save(best)
    if other.exists():
        other.unlink()
    files["best_model"] = best.name
    res.files = files
    write_json_atomic(out / "best_model.json", jsonable(res.table()))
    write_text_atomic(out / "best_model.md", markdown(res))


def markdown(res: BestResult) -> str:
    """The comparison as markdown (best_model.md)."""
    lines = [f"# Best model: {res.winner} (`{res.files.get('best_model', '')}`)", "",
             f"Test rows: {res.split['test_rows_count']} of {res.split['rows']} "
             f"({res.split['method']}), untouched by every fit and choice before this comparison. "
             f"Metric: {METRIC}. Frame: {res.split.get('frame', '')}.", "",
             "| candidate | test mean (mm) | p50 | p95 | p99 | max | winner |", "|---|---|---|---|---|---|---|"]
    for name, row in res.candidates.items():
        eq = row.get("error_quantiles") or {}
        vals = " | ".join(f"{eq[k]:.3f}" if k in eq else "-" for k in ("p50", "p95", "p99", "max"))
        lines.append(f"| {name}: {row['description']} | {row['mean_mm']:.3f} | {vals} | "
                     f"{'yes' if row.get('winner') else ''} |")
    cf = res.candidates[res.winner].get("crossfit_error_quantiles") or {}
    if cf:
        chosen = res.split.get("crossfit", {}).get("chosen_by_other_fold", [])
        lines += ["", "Error bound written with the winner (cross-fitted: each of two folds of "
                  "the test units takes the deviations of the candidate the other fold chooses"
                  + (f": {' / '.join(chosen)}" if chosen else "") + "): "
                  + ", ".join(f"{k} {cf[k]:.3f} mm" for k in ("p50", "p95", "p99", "max")
                              if k in cf) + "."]
    lines += ["", f"Use it with `--model {res.files.get('best_model', 'best_model')}` in plan, "
                  "shape and check.", ""]
    return "\n".join(lines)
