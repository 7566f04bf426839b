"""Stage 6 of the calibration pipeline: write the report, as a set (:func:`write_report`).

report.json, report.md, PNG plots and the calibrated model files are written into a temporary
folder beside the output folder and moved in only when all are complete, so a full disk leaves
the previous report complete (or none), never a mix. Files in the output folder:

``report.json``          docs/conventions.md fields (effects, parameters, steps, error_before_mm,
                         error_after_mm) plus conclusion, split, diagnostics and settings.
``report.md``            a table per step (effect, fitted parameters +- uncertainty, held-out error
                         before/after, statistic, runner-up) and the conclusion.
``residuals_rotation.png``  tip error vs relative rotation of each tube pair, by direction.
``residuals_insertion.png`` tip error vs insertion (tip arc length).
``residuals_arclength.png`` backbone error vs arc length (only when shapes are measured).
``errors_by_step.png``   held-out mean/max tip error after each step.
``tip_paths.png``        held-out sweeps: measured tip path, base model, calibrated model.
``calibrated.yaml``      the calibrated model (robot + base + effects): ``--model PATH``.
``calibrated_robot.yaml`` the robot with the effects that fold into tube parameters
                         (precurvature, stiffness) folded in: ``--robot PATH``.
"""

from __future__ import annotations

import contextlib
import errno
import glob
import logging
import math
import os
import shutil
import tempfile
from collections.abc import Iterator, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from ctrplan.calibration.binned import motion_direction
from ctrplan.calibration.evidence import supporting
from ctrplan.calibration.nuisance import NUISANCES
from ctrplan.calibration.result import DiagnoseReport, headline
from ctrplan.errors import InputError
from ctrplan.io import jsonable, save_figure, write_json_atomic, write_text_atomic
from ctrplan.measured import MeasuredData
from ctrplan.robot import Robot, wrap_angle

log = logging.getLogger("ctrplan")


def folded_robot(robot: Robot, effects: dict[str, dict[str, float]]) -> Robot:
    """The robot with precurvature scales and stiffness ratios folded into its tubes."""
    tubes = []
    n = robot.n
    for i, t in enumerate(robot.tubes):
        k = t.curvature * effects.get("precurvature", {}).get(f"scale{i + 1}", 1.0)
        e = t.youngs_modulus
        if i < n - 1:
            e *= effects.get("stiffness", {}).get(f"ratio{i + 1}", 1.0)
        tubes.append(replace(t, curvature=k, youngs_modulus=e))
    return Robot(name=f"{robot.name}_calibrated", tubes=tuple(tubes), beta_min=robot.beta_min)


def _fmt(v: float | None, s: float | None = None) -> str:
    if v is None or not math.isfinite(v):
        return "-"
    if s is None or not math.isfinite(s):
        return f"{v:.4g}"
    return f"{v:.4g} ± {s:.2g}"


def markdown(rep: DiagnoseReport) -> str:
    """report.md: headline, conclusion, warnings, selection rule, evidence, remainder, the
    learned residual, a table per step and the file list."""
    lines = [rep.headline() + ".", "",
             f"# ctrplan diagnose: {rep.robot.name} ({rep.base} base)", "",
             f"**Conclusion: {rep.conclusion}.**", ""]
    if rep.warnings:
        lines += ["**Warnings:**", ""] + [f"- {w}" for w in rep.warnings] + [""]
    if rep.experiment:
        lines += ["**What experiment would support a diagnosis:**", ""] + \
            [f"- {w}" for w in rep.experiment] + [""]
    lines += _rule_md(rep)
    lines += _heldout_md(rep)
    lines += _evidence_md(rep)
    lines += _named_md(rep)
    lines += _unexplained_md(rep)
    if rep.partial:
        lines += ["Partial (in the calibrated model, not named): " + ", ".join(rep.partial)
                  + ".", ""]
    for o in getattr(rep, "nuisance_tests", []) or []:
        lines += [f"Nuisance test {o['kind'].lstrip('~')} (after the robot fit): "
                  + ("claimed" if o["claimed"] else "not claimed") + f" ({o['why']}).", ""]
    rng = getattr(rep, "measured_insertion", None)
    if rng:
        from ctrplan.shape.error_bounds import measured_text

        lines += ["Measured insertions (where the error bound holds; plans beyond them are "
                  f"extrapolated): {measured_text(rng)}.", ""]
    lines += _learned_md(rep)
    for k, s in enumerate(rep.steps, 1):
        lines += _step_md(k, s)
    lines += ["## Files", "", "- `calibrated.yaml`: calibrated model (`--model calibrated.yaml`)",
              "- `calibrated_robot.yaml`: robot with precurvature/stiffness folded in (`--robot`)",
              "- plots: `residuals_rotation.png`, `residuals_insertion.png`, `errors_by_step.png`, "
              "`tip_paths.png`" + (", `residuals_arclength.png`" if rep.settings.get("shapes_measured") else ""),
              ""]
    return "\n".join(lines)


def _rule_md(rep: DiagnoseReport) -> list[str]:
    st = rep.settings
    return ["Selection rule: parameters are fitted on the fit rows; an effect enters the "
            f"calibrated model when it lowers the BIC and the validation mean tip error by at "
            f"least {100 * st.get('keep_gain', 0.02):.0f} %; it is NAMED only when its BIC "
            f"change is below -{st['bic_threshold']:g} AND it lowers the validation error by "
            f"at least {100 * st['min_heldout_gain']:.0f} %, and the named effects leave at "
            f"most {100 * st.get('max_remainder', 0.5):.0f} % of the validation error above "
            "the noise floor. Friction, the one effect whose shapes depend on the direction of "
            "motion, is also named when the residual without it shows significant hysteresis "
            "on the fit and validation rows and it removes at least half of the gap. The "
            "chosen model is refitted on fit + validation rows; the errors "
            f"above are on the test rows, which chose nothing: {', '.join(rep.test_sweeps)} "
            f"({rep.split.get('method', 'whole sweeps')}). Step tables show validation "
            "errors.", ""]


def _heldout_md(rep: DiagnoseReport) -> list[str]:
    """How many independent test blocks the numbers rest on; base vs fit on the test rows."""
    sp, hc = rep.split, rep.heldout_comparison
    lines = ["## Held-out rows", ""]
    if "independent_test_blocks" in sp:
        unit = {"whole sweeps": "whole sweeps", "blocks": "blocks of the recording",
                "rows": "independent rows"}.get(sp.get("kind"), "units")
        lines.append(f"The held-out numbers rest on {sp['independent_test_blocks']} independent "
                     f"test {unit} ({rep.settings.get('test_rows', '?')} rows)"
                     + (f", each separated from the fit and validation rows by a gap of "
                        f"{sp['gap_rows']} rows (the motion's autocorrelation length: "
                        f"{sp['autocorrelation_rows']} rows)" if sp.get("kind") == "blocks"
                        else "") + ".")
    if hc:
        b, f = hc["base"], hc["fit"]
        lines += ["", "| model on the test rows | mean (mm) | p99 (mm) | max (mm) |",
                  "|---|---|---|---|"]
        for name, x in (("base", b), ("fitted", f)):
            lines.append(f"| {name} | {_fmt(x['mean_mm'])} | {_fmt(x['p99_mm'])} | "
                         f"{_fmt(x['max_mm'])} |")
        lines += ["", f"Default output: the {'fitted' if hc['output'] == 'fit' else 'base'} "
                  f"model. Rule: {hc['rule']}."]
    for c in getattr(rep, "confounded", []) or []:
        lines.append(f"- confounded: {c['effects'][0]} and {c['effects'][1]} (correlation "
                     f"{c['tip_change_correlation']:.2f}, shares {c['share_a_by_b']:.2f} / "
                     f"{c['share_b_by_a']:.2f})")
    return lines + [""]


def _named_md(rep: DiagnoseReport) -> list[str]:
    if not rep.effects:
        return []
    lines = ["## Evidence for each named effect", ""]
    for e in rep.effects:
        sup = supporting(e, rep.evidence_before)
        form = rep.forms.get(e)
        head = f"- **{e}**" + (f" (form: {form})" if form else "") + ": "
        lines.append(head + ("; ".join(sup) if sup else "no data-only test singles it out; "
                             "named by the fit (BIC and held-out error) alone"))
    return lines + [""]


def _unexplained_md(rep: DiagnoseReport) -> list[str]:
    u = rep.unexplained
    if not u:
        return []
    corr = ", ".join(f"{c['description']} (r2 {c['r2']:.2f})" if c.get("r2") is not None
                     else c["description"] for c in u.get("correlates_with", []))
    lines = ["## Unexplained remainder", "",
             f"Held-out mean error {u['heldout_mean_mm']:.3f} mm against "
             f"{u['noise_mean_mm']:.3f} mm expected from the noise floor: "
             f"{u['excess_mean_mm']:.3f} mm left ({100 * u['fraction_of_initial_excess']:.0f} % "
             "of the initial excess). " + (f"It still correlates with: {corr}." if corr else
                                           "No tested quantity explains it.")]
    for o in u.get("outside_vocabulary", []):
        lines.append(f"It follows {o['description']}: with that removed (not a vocabulary "
                     f"effect) the held-out mean error would be "
                     f"{o['heldout_mean_mm_once_removed']:.3f} mm.")
    return lines + [""]


def _learned_md(rep: DiagnoseReport) -> list[str]:
    lr = rep.learned_residual
    if not (lr and "heldout_mean_after_mm" in lr):
        return []
    return ["## Learned residual (separate from the calibrated model)", "",
            f"A learned correction on top of the calibrated model ({lr['method']}). "
            + headline(lr["heldout_mean_before_mm"], lr["heldout_mean_after_mm"],
                       lr["heldout_max_before_mm"], lr["heldout_max_after_mm"]) + ": "
            + ("offered (it lowers the held-out mean error)." if lr["offered"] else
               f"not offered: {lr.get('why')}."), ""]


def _step_md(k: int, s) -> list[str]:
    """The section of step ``k`` (1-based): heading, parameter table, screened candidates."""
    if s.accepted and s.effect in NUISANCES:
        lines = [f"## Step {k}: the residual follows {NUISANCES[s.effect]} "
                 "(outside the effect vocabulary: not named, not in the calibrated model)", "",
                 f"Removing it lowers the validation mean tip error {s.error_before_mm:.3f} -> "
                 f"{s.error_after_mm:.3f} mm (ΔBIC {s.delta_bic:.1f}); later steps are "
                 "screened on the data with it removed.", ""]
    elif s.accepted:
        lines = [f"## Step {k}: {s.effect}" + (f" (form: {s.form})" if s.form else "")
                 + ("" if getattr(s, "named", True) else
                    " (kept in the model; evidence too weak to name it)"), ""]
        if getattr(s, "named_by", ""):
            lines += [f"Named by its signature (its drop is below the shares): {s.named_by}.", ""]
    else:
        lines = [f"## Step {k}: nothing more justified", ""]
    if s.accepted and s.effect not in NUISANCES:
        lines += _params_table(s)
    elif not s.accepted:
        lines += [f"Best remaining candidate {s.runner_up}: ΔBIC {s.delta_bic:.1f}, validation "
                  f"gain {100 * s.heldout_gain:.1f} % — not justified."]
    lines += ["", "Screened candidates (best form of each; `~` = outside the vocabulary):", "",
              "| candidate | form | ΔBIC | validation mean (mm) | named-grade |",
              "|---|---|---|---|---|"]
    for c in s.screened:
        lines.append(f"| {c.effect} | {c.form or '-'} | {c.delta_bic:.1f} | "
                     f"{c.test_mean_mm:.3f} | {'yes' if c.justified else 'no'} |")
    return lines + [""]


def _params_table(s) -> list[str]:
    lines = ["| effect | parameter | fitted ± 1 sigma | validation before (mm) | "
             "validation after (mm) | ΔBIC | validation gain | runner-up (ΔBIC) |",
             "|---|---|---|---|---|---|---|---|"]
    first = True
    for eff, vals in s.parameters.items():
        for p, v in vals.items():
            sig = s.sigma.get(eff, {}).get(p)
            cells = [eff, p, _fmt(v, sig)]
            if first:
                cells += [f"{s.error_before_mm:.3f}", f"{s.error_after_mm:.3f}",
                          f"{s.delta_bic:.1f}", f"{100 * s.heldout_gain:.1f} %",
                          f"{s.runner_up or '-'} ({_fmt(s.runner_up_delta_bic)})"]
            else:
                cells += [""] * 5
            lines.append("| " + " | ".join(cells) + " |")
            first = False
    if s.ambiguous:
        lines += ["", f"Ambiguous at this step: {s.runner_up} explains the data almost as "
                      "well (ΔBIC within the ambiguity margin)."]
    return lines


def _evidence_md(rep) -> list[str]:
    e = rep.evidence_before
    if not e:
        return []
    nf = e.get("noise", {})
    sd = nf.get("sd_mm")
    lines = ["## Evidence from the data (base model residual)", "",
             "| test | result |", "|---|---|",
             f"| rows / distinct configurations | {e['rows']} / {e['distinct_configurations']} |",
             f"| noise floor | {_fmt(sd)} mm per axis ({nf.get('method')}) |",
             f"| residual rms / above noise | {_fmt(e['residual_rms_mm'])} / "
             f"{_fmt(e['excess_rms_mm'])} mm |"]
    h = e.get("hysteresis", {})
    if h.get("tested"):
        lines.append(f"| hysteresis (opposite vs same direction) | gap {_fmt(h['median_gap_mm'])} mm, "
                     f"ratio {_fmt(h['ratio'])}, p {h['p_value']:.1e}: "
                     f"{'yes' if h['significant'] else 'no'} |")
    else:
        lines.append(f"| hysteresis | not tested: {h.get('why')} |")
    for item in e.get("harmonics", []):
        pair = f"{item['pair'][0]}-{item['pair'][1]}"
        if item.get("tested"):
            hs = ", ".join(f"order {x['order']}: {_fmt(x['amplitude_mm'])} mm at "
                           f"{x['phase_deg']:.0f} deg" for x in item["harmonics"])
            lines.append(f"| harmonics in relative rotation {pair} | {hs}; r2 {item['r2']:.2f}, "
                         f"p {item['p_value']:.1e}: {'yes' if item['significant'] else 'no'} |")
        else:
            lines.append(f"| harmonics in relative rotation {pair} | not tested: {item.get('why')} |")
    ins = e.get("insertion", {})
    if ins.get("tested"):
        lines.append(f"| trend with insertion | {_fmt(ins['slope_norm'])} mm/mm, r2 "
                     f"{ins['r2']:.2f}: {'yes' if ins['significant'] else 'no'} |")
    pr = e.get("procrustes", {})
    if pr.get("tested"):
        lines.append(f"| rigid transform (Procrustes) | removes {100 * pr['fraction_explained']:.0f} % "
                     f"(rotation {pr['rotation_deg']:.2f} deg, rms {_fmt(pr['rms_before_mm'])} -> "
                     f"{_fmt(pr['rms_after_mm'])} mm): {'yes' if pr['significant'] else 'no'} |")
    for key, label in (("time", "trend with time"), ("position", "field of tip position")):
        it = e.get(key, {})
        if it.get("tested"):
            lines.append(f"| {label} | r2 {it['r2']:.2f}: {'yes' if it['significant'] else 'no'} |")
    return lines + [""]


#: every file a diagnose report may hold: a new report replaces all of them as a set
REPORT_FILES = ("report.json", "report.md", "calibrated.yaml", "calibrated_robot.yaml",
                "calibrated_fit.yaml",
                "residuals_rotation.png", "residuals_insertion.png", "residuals_arclength.png",
                "errors_by_step.png", "tip_paths.png")


def write_report(rep: DiagnoseReport, data: MeasuredData, out: str | os.PathLike,
                 base_pred: np.ndarray, final_pred: np.ndarray, test: np.ndarray) -> Path:
    """Write every report file into folder ``out`` as a set (:func:`output_set`, replacing
    the previous report's :data:`REPORT_FILES`); returns the folder.

    A write that fails (a full disk) leaves ``out`` as it was: the previous report complete,
    or no report, never a mix; it raises :class:`InputError` naming ``--out`` (one line on the
    command line, exit 2).
    """
    out = Path(out)
    with output_set(out, REPORT_FILES) as folder:
        _write_files(rep, data, folder, base_pred, final_pred, test)
    return out


@contextlib.contextmanager
def output_set(out: str | os.PathLike, names: Sequence[str]) -> Iterator[Path]:
    """Yield an empty temporary folder beside folder ``out``; when the block ends normally,
    move everything written there into ``out`` (created), replacing the entries ``names`` of a
    previous set (those the new set lacks are removed; other files in ``out`` stay). Renames
    need no free space; should one fail, the previous entries are put back.

    When the block fails, ``out`` is untouched and the temporary folder removed (with the
    folders created for it). A write error (OSError, or the InputError of a file write under
    the temporary folder) becomes an InputError naming ``--out``; other errors pass unchanged.
    """
    out = Path(out)
    if out.exists() and not out.is_dir():
        raise InputError("--out", "", f"{str(out)!r} exists and is not a folder")
    made = _first_missing(out.parent)
    try:
        if made is None:
            for line in recover(out, names):
                log.warning(line)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.diagnose-{os.getpid()}-", dir=out.parent))
    except OSError as exc:
        raise _out_error(out, exc) from None
    ok = False
    try:
        yield tmp
        _swap_in(tmp, out, names)
        ok = True
    except (OSError, InputError) as exc:
        if not _is_write_error(exc, tmp, out):
            raise
        raise _out_error(out, exc) from None
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
        if not ok and made is not None:
            shutil.rmtree(made, ignore_errors=True)


def _is_write_error(exc: Exception, tmp: Path, out: Path) -> bool:
    if isinstance(exc, InputError):
        return exc.source.startswith(str(tmp))
    where = str(getattr(exc, "filename", None) or "")
    return (where.startswith((str(tmp), str(out)))
            or getattr(exc, "errno", None) in (errno.ENOSPC, errno.EDQUOT, errno.EFBIG))


def _write_files(rep: DiagnoseReport, data: MeasuredData, folder: Path, base_pred: np.ndarray,
                 final_pred: np.ndarray, test: np.ndarray) -> None:
    d = rep.to_dict()
    d["files"] = {"model": "calibrated.yaml", "robot": "calibrated_robot.yaml"}
    write_json_atomic(folder / "report.json", jsonable(d))
    write_text_atomic(folder / "report.md", markdown(rep))
    rep.model().save(folder / "calibrated.yaml")
    if rep.fit_effects and rep.fit_effects != rep.model_effects:
        # the fit the held-out comparison did not make the default output (report.json says why)
        from ctrplan.shape.effects import EffectModel

        EffectModel(rep.robot, rep.base, rep.fit_effects).save(folder / "calibrated_fit.yaml")
    folded_robot(rep.robot, rep.model_effects).save(folder / "calibrated_robot.yaml")
    _plots(rep, data, folder, base_pred, final_pred, test)


def _swap_in(tmp: Path, out: Path, names: Sequence[str]) -> None:
    """Move the complete new set from ``tmp`` into ``out`` (a new folder: one rename); the
    previous set's entries go to a backup folder first and come back if a move fails."""
    if not out.exists():
        os.rename(tmp, out)
        return
    backup = Path(tempfile.mkdtemp(prefix=f".{out.name}.previous-{os.getpid()}-", dir=out.parent))
    moved_old: list[str] = []
    moved_new: list[str] = []
    try:
        for name in names:
            if (out / name).exists():
                os.replace(out / name, backup / name)
                moved_old.append(name)
        # from here on every entry of the previous set is in the backup (see recover)
        (backup / _PHASE2).touch()
        for f in sorted(tmp.iterdir()):
            os.replace(f, out / f.name)
            moved_new.append(f.name)
    except OSError:
        for name in moved_new:           # roll back: the previous set, complete
            with contextlib.suppress(OSError):
                _remove(out / name)
        for name in moved_old:
            with contextlib.suppress(OSError):
                os.replace(backup / name, out / name)
        raise
    finally:
        shutil.rmtree(backup, ignore_errors=True)


#: marker in a swap's backup folder: every entry of the previous set has been moved there
_PHASE2 = ".all-previous-entries-here"


def recover(out: Path, names: Sequence[str]) -> list[str]:
    """Put back the previous report set of ``out`` where a swap (:func:`_swap_in`) was killed
    part-way (SIGKILL, power loss), and remove the temporary folders such a run left beside
    ``out``; folders of a run that is still alive (its pid is in their name) are left alone.
    Returns what was done, one line per folder. Before its marker file, a backup holds some
    entries of the previous set and ``out`` the rest (they go back); after it, the backup holds
    all of them and ``out`` may hold some new entries (they are removed, the old ones go back)."""
    done: list[str] = []
    parent = out.parent
    if not parent.is_dir():
        return done
    for kind in ("previous", "diagnose"):
        for folder in sorted(parent.glob(f".{glob.escape(out.name)}.{kind}-*")):
            pid = folder.name[len(out.name) + len(kind) + 3:].split("-", 1)[0]
            if not folder.is_dir() or folder.is_symlink() or _alive(pid):
                continue
            if kind == "previous" and out.is_dir():     # (a deleted --out is not brought back)
                complete = (folder / _PHASE2).exists()
                for name in names:
                    old = folder / name
                    if old.exists() or old.is_symlink():
                        if (out / name).exists() or (out / name).is_symlink():
                            _remove(out / name)
                        os.replace(old, out / name)
                    elif complete and ((out / name).exists() or (out / name).is_symlink()):
                        _remove(out / name)     # an entry the interrupted new set brought
                done.append(f"restored the previous report set of {str(out)!r} (a write was "
                            "interrupted)")
            shutil.rmtree(folder, ignore_errors=True)
    return done


def _alive(pid: str) -> bool:
    """Whether another process of this pid runs now (a name that is not a pid: not alive)."""
    if not pid.isdigit():
        return False
    try:
        os.kill(int(pid), 0)
    except ProcessLookupError:
        return False
    except (PermissionError, OverflowError):
        return True
    return int(pid) != os.getpid()


def _remove(path: Path) -> None:
    if path.is_dir() and not path.is_symlink():
        shutil.rmtree(path)
    else:
        os.unlink(path)


def _first_missing(folder: Path) -> Path | None:
    """The outermost ancestor of ``folder`` (itself included) that does not exist yet."""
    missing = None
    p = Path(os.path.abspath(folder))
    while not p.exists():
        missing = p
        p = p.parent
    return missing


def _out_error(out: Path, exc: Exception) -> InputError:
    reason = exc.strerror if isinstance(exc, OSError) and exc.strerror else (
        exc.message if isinstance(exc, InputError) else exc.__class__.__name__)
    return InputError("--out", "", f"cannot write the report to {str(out)!r} ({reason}); "
                      "nothing there was changed")


def _plots(rep: DiagnoseReport, data: MeasuredData, out: Path, base_pred: np.ndarray,
           final_pred: np.ndarray, test: np.ndarray) -> None:
    """Write the report's PNG plots into ``out``."""
    import matplotlib

    matplotlib.use("Agg")
    eb = np.linalg.norm(base_pred[:, -1] - data.tip, axis=1)
    ea = np.linalg.norm(final_pred[:, -1] - data.tip, axis=1)
    _plot_rotation(rep, data, out, eb, ea)
    _plot_insertion(rep, data, out, eb, ea)
    if data.points is not None and base_pred.shape[1] == data.points.shape[1]:
        _plot_arclength(rep, data, out, base_pred, final_pred)
    _plot_steps(rep, out)
    _plot_tip_paths(data, out, base_pred, final_pred, test)


def _plot_rotation(rep: DiagnoseReport, data: MeasuredData, out: Path, eb: np.ndarray,
                   ea: np.ndarray) -> None:
    """Residual vs relative rotation, by direction of motion."""
    import matplotlib.pyplot as plt

    n = rep.robot.n
    sweep = data.sweeps()
    pairs = max(1, n - 1)
    fig, axes = plt.subplots(1, pairs, figsize=(5.5 * pairs, 4), dpi=100, squeeze=False)
    for i in range(n - 1):
        ax = axes[0, i]
        rel = data.q[:, i] - data.q[:, i + 1]
        dirn = motion_direction(rel, sweep)[:, 0]
        x = wrap_angle(rel)
        for sel, c, lab in ((dirn > 0, "#c0392b", "moving +"), (dirn < 0, "#1f4e9c", "moving -"),
                            (dirn == 0, "#999999", "still")):
            if sel.any():
                ax.scatter(x[sel], eb[sel], s=6, c=c, alpha=0.6, label=f"base, {lab}")
        ax.scatter(x, ea, s=4, c="#0b8a3c", alpha=0.4, marker="x", label="calibrated")
        ax.set_xlabel(f"relative rotation alpha{i + 1} - alpha{i + 2} (rad)")
        ax.set_ylabel("tip error (mm)")
        ax.legend(fontsize=7)
    if n == 1:
        axes[0, 0].text(0.5, 0.5, "single tube: no relative rotation", ha="center")
    fig.suptitle("Residuals vs relative rotation, split by direction of motion")
    save_figure(fig, out / "residuals_rotation.png")


def _plot_insertion(rep: DiagnoseReport, data: MeasuredData, out: Path, eb: np.ndarray,
                    ea: np.ndarray) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    ins = rep.robot.tip_length(data.q)
    ax.scatter(ins, eb, s=6, c="#c0392b", alpha=0.5, label=f"{rep.base} base")
    ax.scatter(ins, ea, s=6, c="#0b8a3c", alpha=0.5, label="calibrated")
    ax.set_xlabel("insertion: tip arc length (mm)")
    ax.set_ylabel("tip error (mm)")
    ax.legend()
    save_figure(fig, out / "residuals_insertion.png")


def _plot_arclength(rep: DiagnoseReport, data: MeasuredData, out: Path, base_pred: np.ndarray,
                    final_pred: np.ndarray) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    fr = np.linspace(0, 1, data.points.shape[1])
    ax.plot(fr, np.nanmean(np.linalg.norm(base_pred - data.points, axis=2), 0), "o-",
            c="#c0392b", label=f"{rep.base} base")
    ax.plot(fr, np.nanmean(np.linalg.norm(final_pred - data.points, axis=2), 0), "o-",
            c="#0b8a3c", label="calibrated")
    ax.set_xlabel("arc length / tip arc length")
    ax.set_ylabel("mean backbone error (mm)")
    ax.legend()
    save_figure(fig, out / "residuals_arclength.png")


def _plot_steps(rep: DiagnoseReport, out: Path) -> None:
    """Held-out mean and max tip error after each step."""
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4), dpi=100)
    labels = ["base"] + [s.effect for s in rep.steps if s.accepted]
    means = [rep.error_before_mm] + [s.error_after_mm for s in rep.steps if s.accepted]
    maxes = [rep.max_before_mm] + [s.max_after_mm for s in rep.steps if s.accepted]
    xs = np.arange(len(labels))
    ax.bar(xs - 0.2, means, 0.4, label="held-out mean", color="#1f4e9c")
    ax.bar(xs + 0.2, maxes, 0.4, label="held-out max", color="#d9a38f")
    ax.set_xticks(xs, ["+" + lab if k else lab for k, lab in enumerate(labels)], rotation=20)
    ax.set_ylabel("tip error (mm)")
    ax.legend()
    save_figure(fig, out / "errors_by_step.png")


def _plot_tip_paths(data: MeasuredData, out: Path, base_pred: np.ndarray,
                    final_pred: np.ndarray, test: np.ndarray) -> None:
    """Tip paths (x-y) of up to four held-out sweeps."""
    import matplotlib.pyplot as plt

    sweep = data.sweeps()
    names = list(dict.fromkeys(sweep[test].tolist()))[:4]
    fig, axes = plt.subplots(1, max(1, len(names)), figsize=(4.5 * max(1, len(names)), 4.2),
                             dpi=100, squeeze=False)
    for k, nm in enumerate(names):
        ax = axes[0, k]
        sel = sweep == nm
        for arr, c, lab in ((data.tip[sel], "k", "measured"), (base_pred[sel, -1], "#c0392b", "base"),
                            (final_pred[sel, -1], "#0b8a3c", "calibrated")):
            ax.plot(arr[:, 0], arr[:, 1], "-", c=c, lw=1.2, label=lab)
        ax.set_title(str(nm))
        ax.set_xlabel("x (mm)")
        ax.set_ylabel("y (mm)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.legend(fontsize=7)
    fig.suptitle("Held-out tip paths (x-y)")
    save_figure(fig, out / "tip_paths.png")
