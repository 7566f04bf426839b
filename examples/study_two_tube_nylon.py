"""Study-style comparison: what does the traditional model miss on a two-tube nylon robot?

The Sensors 2023 study (clearance, friction and torsion on two nylon tubes; its text is in
``../shared/papers/``) reports the tip error of the traditional (torsionally rigid) model and of
its improved model in three experiments: feed the inner tube, rotate the inner tube, rotate the
outer tube. Here the "robot" is the independent foreign generator of ``tests/foreign`` (its own
mechanics and its own forms of the three effects: the clearance tilt peaking at 205 deg of
relative rotation, friction as the concentrated end moment with the rotation correction
``dtheta``, torsion by its own Cosserat shooting; ``generate_study``), plus tracker noise.
``ctrplan diagnose`` is run on one study run; the table compares the traditional and the
calibrated ("improved") model on a fresh study run with another seed (mean and max tip error
per experiment), the study's table shape.

Run from a checkout (the generator lives in tests/):
    python examples/study_two_tube_nylon.py [--seed S] [--out DIR]
Writes DIR/study.md (the table), DIR/study.json, DIR/paths_<experiment>.png and the diagnose
report in DIR/report/.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
EXPERIMENTS = ("feed", "inner_rotation", "outer_rotation")
STUDY = {  # the study's own numbers (mean / max, mm), for the table's last columns
    "feed": (0.2, 0.39), "inner_rotation": (1.02, 2.6), "outer_rotation": (1.96, 4.5)}
TRADITIONAL_STUDY = {"feed": 4.95, "inner_rotation": 4.2, "outer_rotation": 6.7}


def _foreign():
    if str(ROOT) not in sys.path:
        sys.path.insert(0, str(ROOT))
    from tests import foreign

    return foreign


def _measured(parts: dict):
    """The three experiments as one measured data set (sweep ids prefixed by experiment)."""
    from ctrplan.measured import MeasuredData

    q, tip, t, sw = [], [], [], []
    t0 = 0.0
    for exp in EXPERIMENTS:
        d = parts[exp]
        q.append(np.asarray(d.q, float))
        tip.append(np.asarray(d.tip, float))
        tt = np.asarray(d.time, float)
        t.append(tt - tt.min() + t0)
        t0 = t[-1].max() + 1.0
        sw.append(np.array([f"{exp}:{s}" for s in d.sweep], dtype=object))
    return MeasuredData(q=np.concatenate(q), tip=np.concatenate(tip), time=np.concatenate(t),
                        sweep=np.concatenate(sw))


def study(seed: int = 0, validation_seed: int | None = None, out: Path | None = None) -> dict:
    """Calibrate on ``generate_study(seed)``, compare on ``generate_study(validation_seed)``."""
    from ctrplan.calibration.diagnose import diagnose
    from ctrplan.robot import load_robot
    from ctrplan.shape.effects import EffectModel

    foreign = _foreign()
    robot = load_robot("two_tube_nylon")
    calib = _measured(foreign.generate_study(seed=seed))
    rep = diagnose(robot, calib, base="rigid", seed=seed,
                   out=None if out is None else out / "report")
    vseed = 1000 + seed if validation_seed is None else validation_seed
    val = foreign.generate_study(seed=vseed)
    traditional = EffectModel(robot, "rigid")
    improved = rep.model()
    table, et_all, ei_all = [], [], []
    for exp in EXPERIMENTS:
        d = val[exp]
        q = np.asarray(d.q, float)
        sw = np.asarray(d.sweep, dtype=object)
        pt = traditional.shape(q, 2).tip
        pi = improved.shape(q, 2, sweep=sw).tip
        et = np.linalg.norm(pt - d.tip, axis=1)
        ei = np.linalg.norm(pi - d.tip, axis=1)
        et_all.append(et)
        ei_all.append(ei)
        table.append({"experiment": exp, "rows": int(len(q)),
                      "traditional_mean_mm": float(et.mean()), "traditional_max_mm": float(et.max()),
                      "improved_mean_mm": float(ei.mean()), "improved_max_mm": float(ei.max())})
        if out is not None:
            _path_plot(out / f"paths_{exp}.png", exp, d, sw, pt, pi)
    et_all, ei_all = np.concatenate(et_all), np.concatenate(ei_all)
    return {"seed": seed, "validation_seed": vseed, "conclusion": rep.conclusion,
            "effects": rep.effects, "forms": rep.forms, "headline": rep.headline(),
            "traditional_mean_mm": float(et_all.mean()), "improved_mean_mm": float(ei_all.mean()),
            "traditional_max_mm": float(et_all.max()), "improved_max_mm": float(ei_all.max()),
            "traditional_p99_mm": float(np.percentile(et_all, 99)),
            "improved_p99_mm": float(np.percentile(ei_all, 99)),
            # the diagnosis's own held-out rows (test sweeps of the calibration run)
            "heldout_mean_mm": [rep.error_before_mm, rep.error_after_mm],
            "heldout_p99_mm": [(rep.error_quantiles_before or {}).get("p99"),
                               (rep.error_quantiles or {}).get("p99")],
            "table": table, "parameters": rep.parameters}


def markdown(res: dict) -> str:
    md = ["# Study-style comparison on two_tube_nylon (foreign generator)", "",
          f"Calibrated on `generate_study(seed={res['seed']})`; compared on "
          f"`generate_study(seed={res['validation_seed']})`. Workflow found: "
          f"**{res['conclusion']}**.", "",
          "| experiment | traditional mean / max (mm) | improved mean / max (mm) | "
          "study: traditional mean, improved mean / max (mm) |", "|---|---|---|---|"]
    for r in res["table"]:
        s = STUDY[r["experiment"]]
        md.append(f"| {r['experiment']} | {r['traditional_mean_mm']:.2f} / "
                  f"{r['traditional_max_mm']:.2f} | {r['improved_mean_mm']:.2f} / "
                  f"{r['improved_max_mm']:.2f} | {TRADITIONAL_STUDY[r['experiment']]}, "
                  f"{s[0]} / {s[1]} |")
    md += ["", f"All experiments: traditional mean {res['traditional_mean_mm']:.2f} mm, improved "
               f"{res['improved_mean_mm']:.2f} mm "
               f"({100 * res['improved_mean_mm'] / res['traditional_mean_mm']:.0f} % left)."]
    return "\n".join(md) + "\n"


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=0, help="seed of the calibration run (default 0)")
    ap.add_argument("--out", default="study_out", help="output folder (default study_out)")
    args = ap.parse_args(argv)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    res = study(args.seed, out=out)
    text = markdown(res)
    (out / "study.md").write_text(text, encoding="utf-8")
    (out / "study.json").write_text(json.dumps(res, indent=2, default=float), encoding="utf-8")
    print(text)
    return 0


def _path_plot(path: Path, exp: str, d, sw, pt: np.ndarray, pi: np.ndarray) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    first = sw == sw[0]
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.5), dpi=100)
    for ax, (a, b) in zip(axes, ((0, 1), (0, 2))):
        for arr, c, lab in ((np.asarray(d.tip)[first], "k", "measured"),
                            (pt[first], "#c0392b", "traditional"), (pi[first], "#0b8a3c", "improved")):
            ax.plot(arr[:, a], arr[:, b], "-", c=c, lw=1.3, label=lab)
        ax.set_xlabel(f"{'xyz'[a]} (mm)")
        ax.set_ylabel(f"{'xyz'[b]} (mm)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.legend(fontsize=8)
    fig.suptitle(f"{exp}: tip path of the first validation sweep")
    fig.savefig(path, bbox_inches="tight")
    plt.close(fig)


if __name__ == "__main__":
    sys.exit(main())
