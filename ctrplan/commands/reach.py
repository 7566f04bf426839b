"""``ctrplan scene reach``: a reachability map of a scene's surface (reach.csv, .html, .png).

The map itself is :func:`ctrplan.planning.reach.reach_map`; this module parses the command
line, samples the surface (:func:`ctrplan.collision.surface.sample_surface`) and draws the two
views: ``reach.html`` (plotly, self-contained: works offline) and ``reach.png`` (matplotlib).
Both show the scene's meshes faintly and every sampled point as a dot on the surface: reachable
points coloured by the clearance of their plan, unreachable ones red (failed plans) or grey
(no pose found by the screen).
"""

from __future__ import annotations

import argparse
import logging
from pathlib import Path

import numpy as np

from ctrplan.commands._common import NONNEGATIVE, POSITIVE, WORKERS, int_arg
from ctrplan.commands._vocab import DEFAULT_OUT
from ctrplan.errors import InputError

log = logging.getLogger("ctrplan")

#: colours of the views: planned but not reached, and screened out
FAILED_COLOUR = "#d62728"
NO_POSE_COLOUR = "#9e9e9e"
#: the colour scale of reachable points (by clearance, mm)
CLEARANCE_SCALE = "Viridis"


def register(ss: argparse._SubParsersAction) -> None:
    """Add ``reach`` to the ``scene`` subcommands."""
    from ctrplan.commands.plan import add_planning_args, allow_negative_values

    p = ss.add_parser(
        "reach", help="which surface points the robot can reach (reach.csv, .html, .png)",
        description="Sample the anatomy surface (wall and obstacle meshes, area-weighted, seeded; "
                    "or the region near named targets) and decide for each point whether the "
                    "robot can put its tip at it: at --standoff from the surface along its "
                    "normal, with --approach within --cone. A batched IK screen first; then a "
                    "full plan to every point the screen passes (the map's verdict is the "
                    "plan's). Writes OUT/reach.csv, OUT/reach.html, OUT/reach.png and one "
                    "OUT/points/<id>.json per point, so an interrupted map resumes. Plans run in "
                    "a local process pool (--workers) or on Ray (--ray ADDRESS).")
    p.add_argument("--scene", required=True, help="shipped scene name or scene folder")
    p.add_argument("--points", type=int_arg(1, 1_000_000), default=200,
                   help="surface points to sample (default 200)")
    region = p.add_mutually_exclusive_group()
    region.add_argument("--region", default=None, metavar="TARGETS",
                        help="sample only near these targets (names or ids, comma-separated)")
    region.add_argument("--near-targets", action="store_true",
                        help="sample only near the scene's named targets")
    p.add_argument("--radius", type=POSITIVE, default=20.0, metavar="MM",
                   help="with --region / --near-targets: how near, mm (default 20)")
    p.add_argument("--standoff", type=NONNEGATIVE, default=2.0, metavar="MM",
                   help="the tip stops this far from the surface along its normal, mm (default 2)")
    p.add_argument("--approach", default=None, metavar="normal|X,Y,Z",
                   help="the tip's direction: 'normal' (pointing at the surface) or X,Y,Z "
                        "(scene frame); needs --cone (default: any direction)")
    p.add_argument("--cone", type=float_cone, default=None, metavar="DEG",
                   help="half-angle of the approach cone, deg (0 < DEG <= 90)")
    add_planning_args(p)
    p.set_defaults(time=2.0)
    for a in p._actions:
        if a.dest == "time":
            a.help = "time limit per plan, s (default 2)"
    p.add_argument("--ik-seeds", type=int_arg(1, 1024), default=None, metavar="K",
                   help="IK seeds per point and round in the screen (default: the planner's, "
                        "as a plan's goal rounds)")
    p.add_argument("--seed", type=int_arg(0, 2**31 - 1), default=0,
                   help="seed of the surface sample and of every plan (default 0)")
    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=WORKERS, default=1, help="local worker processes (default 1)")
    where.add_argument("--ray", default=None, metavar="ADDRESS",
                       help="plan on a Ray cluster at ADDRESS ('local' starts one here)")
    p.add_argument("--out", default=DEFAULT_OUT["scene reach"],
                   help=f"output folder (default {DEFAULT_OUT['scene reach']})")
    allow_negative_values(p)
    p.set_defaults(func=run)


def float_cone(text: str) -> float:
    from ctrplan.commands._common import float_arg

    return float_arg(0.0, 90.0, lo_open=True)(text)


def run(args: argparse.Namespace) -> int:
    from ctrplan.commands.plan import one_thread, parse_margin, parse_objective
    from ctrplan.planning.batch import check_scene_spec
    from ctrplan.planning.reach import ReachSettings, parse_direction, reach_map
    from ctrplan.planning.space import check_planner
    from ctrplan.robot import load_robot

    one_thread()
    out = Path(args.out)
    if out.exists() and not out.is_dir():
        raise InputError("--out", "", f"{args.out!r} exists and is not a folder")
    if (args.approach is None) != (args.cone is None):
        raise InputError("--cone" if args.cone is None else "--approach", "",
                         "--approach and --cone go together")
    approach = ""
    if args.approach is not None:
        approach = args.approach.strip().lower()
        if approach != "normal":
            approach = ",".join(repr(float(v)) for v in parse_direction(args.approach))
    check_scene_spec(args.scene)
    load_robot(args.robot)
    margin = parse_margin(args.margin)
    settings = ReachSettings(scene=args.scene, robot=args.robot, model=args.model,
                             standoff_mm=float(args.standoff), approach=approach,
                             cone_deg=args.cone, tolerance_mm=float(args.tolerance),
                             time_limit=float(args.time), planner=check_planner(args.planner),
                             margin="auto" if margin is None else repr(margin),
                             objective=parse_objective(args.objective), seed=args.seed,
                             ik_seeds=args.ik_seeds)
    samples = sample_for(args)
    summary = reach_map(settings, samples, out, workers=args.workers, ray_address=args.ray)
    from ctrplan.collision.scene import load_scene

    scene = load_scene(args.scene)
    render_html(scene, summary.rows, out / "reach.html", settings)
    render_png(scene, summary.rows, out / "reach.png", settings)
    print(f"{summary.reachable}/{summary.total} points reachable "
          f"({100.0 * summary.reachable / max(summary.total, 1):.0f}%); "
          f"{summary.total - summary.skipped} decided now ({summary.screened_out} screened out, {summary.planned} planned), "
          f"{summary.skipped} were already done")
    print(f"wrote {out / 'reach.csv'}, {out / 'reach.html'} and {out / 'reach.png'}")
    return 0


def sample_for(args: argparse.Namespace):
    """The command's surface sample (the whole surface, or near the region's targets); the
    library's errors name their arguments, the command line shows the flags
    (:mod:`ctrplan.commands._names`)."""
    from ctrplan.collision.scene import load_scene
    from ctrplan.collision.surface import sample_surface
    from ctrplan.planning.reach import region_points

    scene = load_scene(args.scene)
    near = region_points(scene, args.region, args.near_targets)
    return sample_surface(scene, args.points, seed=args.seed, near=near, radius_mm=args.radius)


# ---------------------------------------------------------------------- views
def _title(scene, rows, settings) -> str:
    n = sum(int(r["reachable"]) for r in rows)
    cone = (f", approach {settings.approach} within {settings.cone_deg:g} deg"
            if settings.approach else "")
    return (f"reach: {scene.name}, robot {settings.robot} ({settings.model}): {n}/{len(rows)} "
            f"points reachable (standoff {settings.standoff_mm:g} mm{cone})")


def _split(rows):
    xyz = np.array([[r["x"], r["y"], r["z"]] for r in rows], dtype=float).reshape(-1, 3)
    reach = np.array([bool(r["reachable"]) for r in rows], dtype=bool)
    screened = np.array([bool(r["screen"]) for r in rows], dtype=bool)
    clear = np.array([np.nan if r["clearance_mm"] is None else r["clearance_mm"] for r in rows], dtype=float)
    return xyz, reach, screened, clear


def render_html(scene, rows, out: Path, settings) -> None:
    """reach.html: the meshes and the points coloured by verdict (plotly.js embedded)."""
    import plotly.graph_objects as go

    from ctrplan.io import write_text_atomic
    from ctrplan.viz import ROLE_COLOURS

    traces = []
    for m in scene.meshes:
        v, f = np.asarray(m.mesh.vertices), np.asarray(m.mesh.faces)
        traces.append(go.Mesh3d(x=v[:, 0], y=v[:, 1], z=v[:, 2], i=f[:, 0], j=f[:, 1], k=f[:, 2],
                                color=ROLE_COLOURS.get(m.role, "#7f8c8d"), opacity=0.15,
                                name=f"{m.name} ({m.role})", showlegend=True, flatshading=True,
                                hoverinfo="name"))
    xyz, reach, screened, clear = _split(rows)
    text = [f"point {r['point']}: {r['status']}" + (f", clearance {r['clearance_mm']:.2f} mm"
                                                    if r["clearance_mm"] is not None else "")
            for r in rows]
    groups = ((reach, "reachable", None), (~reach & screened, "planned, not reached", FAILED_COLOUR),
              (~screened, "no pose (screen)", NO_POSE_COLOUR))
    for mask, name, colour in groups:
        if not mask.any():
            continue
        p = xyz[mask]
        marker = {"size": 5, "color": colour}
        if colour is None:
            marker = {"size": 6, "color": np.nan_to_num(clear[mask]), "colorscale": CLEARANCE_SCALE,
                      "colorbar": {"title": "clearance (mm)"}, "showscale": True}
        traces.append(go.Scatter3d(x=p[:, 0], y=p[:, 1], z=p[:, 2], mode="markers", marker=marker,
                                   name=name, text=[t for t, k in zip(text, mask) if k],
                                   hoverinfo="text"))
    fig = go.Figure(data=traces)
    fig.update_layout(title=_title(scene, rows, settings), margin={"l": 0, "r": 0, "t": 40, "b": 0},
                      legend={"x": 0.01, "y": 0.95, "bgcolor": "rgba(255,255,255,0.6)"},
                      scene={"aspectmode": "data", "xaxis_title": "x (mm)", "yaxis_title": "y (mm)",
                             "zaxis_title": "z (mm)"})
    write_text_atomic(out, fig.to_html(include_plotlyjs=True, full_html=True,
                                       config={"displaylogo": False}))


def render_png(scene, rows, out: Path, settings) -> None:
    """reach.png: the points coloured by verdict over the faint meshes (matplotlib)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from ctrplan.io import save_figure
    from ctrplan.viz import ROLE_COLOURS, cube_axes

    xyz, reach, screened, clear = _split(rows)
    fig = plt.figure(figsize=(8, 7), dpi=110)
    ax = fig.add_subplot(111, projection="3d")
    rng = np.random.default_rng(0)
    lo, hi = xyz.min(axis=0) - 10, xyz.max(axis=0) + 10
    for m in scene.meshes:
        v, f = np.asarray(m.mesh.vertices), np.asarray(m.mesh.faces)
        near = np.all((v[f] >= lo) & (v[f] <= hi), axis=(1, 2))   # the meshes around the points
        f = f[near]
        if len(f) > 4000:
            f = f[rng.choice(len(f), 4000, replace=False)]
        ax.add_collection3d(Poly3DCollection(v[f], alpha=0.06, facecolor=ROLE_COLOURS.get(m.role, "#7f8c8d"),
                                             edgecolor="none"))
    for mask, colour, label in ((~screened, NO_POSE_COLOUR, "no pose (screen)"),
                                (~reach & screened, FAILED_COLOUR, "planned, not reached")):
        if mask.any():
            ax.scatter(*xyz[mask].T, color=colour, s=10, label=label, depthshade=False)
    if reach.any():
        sc = ax.scatter(*xyz[reach].T, c=np.nan_to_num(clear[reach]), cmap=CLEARANCE_SCALE.lower(),
                        s=16, label="reachable", depthshade=False)
        fig.colorbar(sc, ax=ax, shrink=0.6, label="clearance (mm)")
    cube_axes(ax, lo, hi)
    ax.set_title(_title(scene, rows, settings), fontsize=9)
    ax.legend(loc="upper left", fontsize=8)
    save_figure(fig, out)
