"""Outputs of ``ctrplan design``: robot.yaml, design.json, paths/<target>.json, report.md and
coverage.png (format: docs/conventions.md, "design.json")."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from ctrplan.io import jsonable, write_json_atomic, write_text_atomic
from ctrplan.robot import robot_record


def _num(v) -> float | None:
    return None if v is None or not math.isfinite(float(v)) else float(v)


def design_json(result) -> dict:
    """The design.json document of a :class:`~ctrplan.design.DesignResult`."""
    from dataclasses import asdict

    cfg = result.config
    targets = []
    for t in result.targets:
        targets.append({"name": t.name, "position": [float(v) for v in t.position],
                        "reached": bool(t.reached), "status": t.status,
                        "clearance_mm": _num(t.clearance_mm),
                        "clearance_estimate_mm": _num(t.clearance_estimate_mm),
                        "tip_error_mm": _num(t.tip_error_mm),
                        "path_file": f"paths/{t.name}.json" if t.plan is not None else None})
    evals = []
    for e in result.evaluations:
        evals.append({"index": e["index"], "generation": e.get("generation"), "tubes": e["k"],
                      "parameters": e["parameters"],
                      "robot": e["robot"], "entry_ok": e["entry_ok"],
                      "entry_clearance_mm": e.get("entry_clearance_mm"),
                      "screen_passed": e["screen_passed"], "screen_errors_mm": e.get("screen_errors"),
                      "planned": e["planned"], "planned_at": e.get("planned_at"), "reached": e["reached"],
                      "clearance_mm": e["clearance_mm"],
                      "clearance_estimate_mm": e.get("clearance_estimate_mm"),
                      "score": list(score_of(e)) if e["planned"] else None,
                      "binding": e["binding"]})
    return jsonable({
        "success": result.success, "status": result.status.value, "message": result.message,
        "scene": result.scene, "seed": result.seed,
        "robot": result.robot.to_dict() if result.robot is not None else None,
        "robot_file": "robot.yaml" if result.robot is not None else None,
        "reached": result.reached, "targets_total": len(result.targets),
        "targets": targets, "binding": list(result.binding), "constraints": result.constraints,
        "blocked": list(result.blocked), "closest": result.closest,
        "anatomy": result.anatomy, "space": result.space,
        "objective": ["targets reached (verified, stable, collision-free plan)",
                      "min clearance along those plans (0.25 mm bins; FCL's minimum where the plan "
                      "settled it, else the distance fields' estimate)",
                      "simplicity: fewer tubes, less bending (sum kappa x curved length), shorter"],
        "config": asdict(cfg), "time_cap_hit": result.time_cap_hit, "timings": result.timings,
        "counts": result.counts, "evaluations": evals,
    })


def score_of(e: dict) -> tuple:
    from ctrplan.design.search import Search

    return Search.score(e)


def coverage_curve(evaluations) -> np.ndarray:
    """(E,) best number of targets reached after each evaluation (planned designs)."""
    best, out = 0, []
    for e in evaluations:
        if e["planned"]:
            best = max(best, e["reached"])
        out.append(best)
    return np.array(out, dtype=int)


def write_outputs(result, out: str | Path) -> list[Path]:
    """Write every output into ``out`` (atomically, file by file); returns the paths."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    if result.robot is not None:
        result.robot.save(out / "robot.yaml")
        written.append(out / "robot.yaml")
        for t in result.targets:
            if t.plan is None:
                continue
            doc = t.plan.to_json()
            doc["robot"] = str((out / "robot.yaml").resolve())   # `ctrplan view` loads it
            doc.update(robot_record(result.robot))      # robot_spec + robot_sha256
            doc["target_name"] = t.name
            doc["stable"] = bool(t.reached) if t.status != "UNSTABLE" else False
            (out / "paths").mkdir(exist_ok=True)
            write_json_atomic(out / "paths" / f"{t.name}.json", jsonable(doc))
            written.append(out / "paths" / f"{t.name}.json")
    png = out / "coverage.png"
    _plot(result, png)
    written.append(png)
    written += _scene_views(result, out)
    write_json_atomic(out / "design.json", design_json(result))
    written.append(out / "design.json")
    write_text_atomic(out / "report.md", report_md(result))
    written.append(out / "report.md")
    return written


def _scene_views(result, out: Path) -> list[Path]:
    """paths.png and paths.html: the chosen design at the end of each reached target's plan
    (final backbones, scene frame) with the tip paths, in the scene."""
    from ctrplan import viz
    from ctrplan.collision.scene import load_scene

    plans = [t.plan for t in result.targets if t.reached and t.plan is not None]
    if not plans:
        return []
    scene = load_scene(result.scene)
    meshes = viz.scene_meshes(scene)
    backbones = np.stack([np.asarray(p.backbones)[-1] for p in plans])
    tips = np.concatenate([np.asarray(p.tip_path) for p in plans])
    title = f"{result.robot.name}: {len(plans)}/{len(result.targets)} targets"
    viz.plan_png(out / "paths.png", meshes, backbones, tips, None, title=title, frames=len(plans))
    viz.plan_html(out / "paths.html", meshes, backbones, tips, None, title=title, frames=len(plans))
    return [out / "paths.png", out / "paths.html"]


def _plot(result, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from ctrplan.io import atomic_path

    cov = coverage_curve(result.evaluations)
    fig, ax = plt.subplots(figsize=(6, 3.2), dpi=100)
    ax.step(np.arange(1, len(cov) + 1), cov, where="post")
    ax.set_xlabel("designs evaluated")
    ax.set_ylabel("targets reached (best so far)")
    ax.set_ylim(-0.2, max(1, len(result.targets)) + 0.2)
    ax.set_title("ctrplan design: coverage against evaluations")
    ax.grid(alpha=0.3)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png")
    plt.close(fig)


def report_md(result) -> str:
    """A short human-readable report."""
    lines = ["# ctrplan design report", "",
             f"Scene `{result.scene}`, seed {result.seed}: **{result.message}** "
             f"({result.status.value}; {result.counts.get('evaluations', 0)} designs screened, "
             f"{result.counts.get('planned', 0)} planned in full"
             + (", stopped by the time cap" if result.time_cap_hit else "") + ").", ""]
    if result.robot is not None:
        lines += ["## Design (robot.yaml)", "", "| tube | od mm | id mm | straight mm | curved mm | curvature 1/mm |",
                  "|---|---|---|---|---|---|"]
        for i, t in enumerate(result.robot.tubes):
            lines.append(f"| {i + 1} | {t.od:g} | {t.id:g} | {t.straight_length:g} | {t.curved_length:g} "
                         f"| {t.curvature:g} |")
        lines += ["", "## Targets", "", "| target | reached | status | clearance mm | tip error mm | path |",
                  "|---|---|---|---|---|---|"]
        for t in result.targets:
            c = "" if not math.isfinite(t.clearance_mm) else f"{t.clearance_mm:.2f}"
            e = "" if not math.isfinite(t.tip_error_mm) else f"{t.tip_error_mm:.2f}"
            p = f"paths/{t.name}.json" if t.plan is not None else ""
            lines.append(f"| {t.name} | {'yes' if t.reached else 'no'} | {t.status} | {c} | {e} | {p} |")
        lines += ["", "## Hard constraints", "", "| constraint | value | limit | satisfied | binds |",
                  "|---|---|---|---|---|"]
        for k, v in result.constraints.items():
            val = f"{v['value']:.4g}" if "value" in v else ""
            lim = f"{v['limit']:.4g}" if "limit" in v else ""
            lines.append(f"| {k} | {val} | {lim} | {'yes' if v['satisfied'] else 'NO'} | "
                         f"{'yes' if v['binds'] else ''} |")
    lines += _blocked_md(result) + _anatomy_md(result)
    t = result.timings
    if any(t.reached for t in result.targets):
        lines += ["", "## Paths", "", "![the design at each reached target](paths.png)", "",
                  "Interactive view (offline): [paths.html](paths.html)."]
    lines += ["", "## Search", "", "![coverage against evaluations](coverage.png)", "",
              "Time per stage (s): " + ", ".join(f"{k} {v:.1f}" for k, v in t.items()), ""]
    return "\n".join(lines)


def _blocked_md(result) -> list[str]:
    """Why targets are not reached, and the closest design found."""
    if not result.blocked:
        return []
    lines = ["", "## Why targets are not reached", "",
             "| target | blocked by | kind | what and where | relax (alone) | closest (screen tip error) |",
             "|---|---|---|---|---|---|"]
    for b in result.blocked:
        c = b.get("closest") or {}
        near = f"{c['tip_error_mm']:.2f} mm (design {c['design_index']})" if "tip_error_mm" in c else "none"
        lines.append(f"| {b['target']} | {b['blocking']} | {b['kind']} | {b['message']} | "
                     f"{b['relax'].get('why') or ''} | {near} |")
    cl = result.closest
    if result.robot is None and cl is not None and cl.get("robot"):
        lines += ["", f"Closest design found (design {cl['index']}, not reaching any target; "
                      f"{'start free' if cl['entry_ok'] else 'retracted start collides'}, "
                      f"{cl['screen_passed']} targets passing the screen):", "",
                  "| tube | od mm | id mm | straight mm | curved mm | curvature 1/mm |", "|---|---|---|---|---|---|"]
        for i, t in enumerate(cl["robot"]["tubes"]):
            lines.append(f"| {i + 1} | {t['od']:g} | {t['id']:g} | {t['straight_length']:g} | "
                         f"{t['curved_length']:g} | {t['curvature']:g} |")
    return lines


def _anatomy_md(result) -> list[str]:
    """The corridors read before the search and the design space derived from them."""
    a = result.anatomy
    if not a:
        return []
    lines = ["", "## Anatomy (read before the search)", "",
             f"Distance-field grid {a['resolution_mm']:g} mm; clearance at the base "
             f"{a['base_clearance_mm']:.2f} mm.", "",
             "| target | corridor | narrowest (width, mm past the entry) | depth mm | bends (deg over mm, at mm) |",
             "|---|---|---|---|---|"]
    for r in a["routes"]:
        n = r["narrowest"]
        nw = "" if n is None else f"{n['width_mm']:.2f} mm at {n['at_mm']:.1f} mm"
        bends = ", ".join(f"{b['angle_deg']:.0f} over {b['length_mm']:.0f} at {b['at_mm']:.0f}" for b in r["bends"])
        depth = "" if r["depth_mm"] is None or not math.isfinite(r["depth_mm"]) else f"{r['depth_mm']:.1f}"
        lines.append(f"| {r['target']} | {'open' if r['connected'] else 'closed'} | {nw} | {depth} | {bends} |")
    if result.space:
        lines += ["", "Design space derived from it:", ""] + [f"- {x}" for x in result.space["notes"]]
    return lines
