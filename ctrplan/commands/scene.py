"""``ctrplan scene``: list the shipped scenes, or render one (optionally with robot shapes);
``scene reach`` (:mod:`ctrplan.commands.reach`) maps what a robot reaches in one."""

from __future__ import annotations

import argparse
import logging

import numpy as np

from ctrplan.commands._common import MAX_MB, NONNEGATIVE, add_model_arg, output_path
from ctrplan.commands._vocab import DEFAULT_OUT

log = logging.getLogger("ctrplan")


def register(sub: argparse._SubParsersAction) -> None:
    p = sub.add_parser("scene", help="list or render anatomy scenes; map what a robot reaches in one",
                       description="List the shipped anatomy scenes, or render one as a PNG "
                                   "(matplotlib) or a self-contained HTML view (plotly, works "
                                   "offline): meshes by role, the robot base pose, the example "
                                   "targets and optionally robot shapes; or map which surface "
                                   "points a robot reaches ('scene reach').")
    ss = p.add_subparsers(dest="scene_command", metavar="ACTION")
    ls = ss.add_parser("list", help="list the shipped scenes", description="List the shipped scenes.")
    ls.set_defaults(func=run_list)
    sh = ss.add_parser("show", help="render a scene", description="Render a scene to PNG or HTML.")
    sh.add_argument("scene", help="shipped scene name or scene folder")
    sh.add_argument("--out", default=DEFAULT_OUT["scene show"], help=f"output .png or .html (default {DEFAULT_OUT['scene show']})")
    sh.add_argument("--configs", help="configuration CSV: draw these robot shapes")
    sh.add_argument("--robot", default="seed1", help="robot for --configs (default seed1)")
    add_model_arg(sh)
    sh.set_defaults(func=run_show)
    fl = ss.add_parser(
        "from-labels", help="make a scene folder from a NIfTI label map",
        description="Make a scene folder (meshes + scene.yaml) from a segmented image: a NIfTI "
                    "label map (.nii or .nii.gz, integer labels). Coordinates are the scanner "
                    "frame of the image's affine (NIfTI RAS+: x right, y anterior, z superior; "
                    "a DICOM/ITK LPS point is (-x, -y, z)), mm. Wall labels are meshed together "
                    "as the lumen the robot stays inside; obstacle and landmark labels get one "
                    "mesh each. Surfaces stay within --max-shift of the voxel (marching-cubes) "
                    "surface, measured both ways. Labels are values or names from a label table "
                    "(a 3D Slicer colour table .ctbl/.txt, an ITK-SNAP .txt or a JSON "
                    "{name: value}) beside the image (same name) or given with --label-table.")
    fl.add_argument("image", metavar="SEG.nii[.gz]", help="the label map")
    fl.add_argument("--wall", required=True, action="append", metavar="LABELS",
                    help="lumen labels (values or names, comma-separated)")
    fl.add_argument("--obstacle", action="append", default=[], metavar="LABELS",
                    help="labels the robot must not touch")
    fl.add_argument("--landmark", action="append", default=[], metavar="LABELS",
                    help="labels drawn but never collision-checked")
    fl.add_argument("--entry", required=True, nargs="+", metavar="X,Y,Z",
                    help="robot base position, mm, scanner frame (inside a wall label)")
    fl.add_argument("--toward", required=True, nargs="+", metavar="X,Y,Z",
                    help="a point the insertion direction (+z of the robot base) points at")
    fl.add_argument("--targets", nargs="+", default=[], metavar="LABELS|X,Y,Z",
                    help="example targets: points X,Y,Z (mm) or labels (the label voxel nearest "
                         "its centroid); three comma-separated numbers are a point")
    fl.add_argument("--name", default=None, help="scene name (default: the image's name)")
    fl.add_argument("--label-table", default=None, help="label table (default: beside the image)")
    fl.add_argument("--max-shift", type=NONNEGATIVE, default=None, metavar="MM",
                    help="how far a surface may move from the voxel surface (default: half the "
                         "smallest voxel size)")
    fl.add_argument("--max-mb", type=MAX_MB, default=None, metavar="MB",
                    help="memory budget for the volume (default 2048)")
    fl.add_argument("--licence", default=None, help="licence of the image, written into scene.yaml")
    fl.add_argument("--out", default=DEFAULT_OUT["scene from-labels"], help=f"scene folder to write (default {DEFAULT_OUT['scene from-labels']})")
    from ctrplan.commands.plan import allow_negative_values

    allow_negative_values(fl)
    fl.set_defaults(func=run_from_labels)
    from ctrplan.commands import reach

    reach.register(ss)
    p.set_defaults(func=lambda args: (p.print_help(), 2)[1])


def run_list(args: argparse.Namespace) -> int:
    from ctrplan.collision.scene import list_scenes, load_scene

    for name in list_scenes():
        sc = load_scene(name)
        roles = ", ".join(f"{m.name} ({m.role})" for m in sc.meshes)
        print(f"{name}: {len(sc.targets)} targets; {roles}")
        if sc.targets:
            print(f"  targets: {sc.target_names()}")
    return 0


def run_show(args: argparse.Namespace) -> int:
    from ctrplan.collision.scene import load_scene

    out = output_path(args.out, (".png", ".html"))
    scene = load_scene(args.scene)
    backbones = np.zeros((0, 2, 3))
    if args.configs:
        from ctrplan.robot import load_robot, read_configs
        from ctrplan.shape.models import load_model

        robot = load_robot(args.robot)
        q = read_configs(args.configs, robot)
        backbones = scene.to_scene(load_model(args.model, robot).backbone(q, points=40))
    if out.suffix.lower() == ".html":
        render_html(scene, out, backbones)
    else:
        render_png(scene, out, backbones)
    log.info("wrote %s", out)
    return 0


def run_from_labels(args: argparse.Namespace) -> int:
    from ctrplan.collision.labels import DEFAULT_MAX_MB, LabelSceneConfig, scene_from_labels
    from ctrplan.errors import InputError

    try:
        cfg = LabelSceneConfig(max_shift_mm=args.max_shift,
                               max_mb=DEFAULT_MAX_MB if args.max_mb is None else args.max_mb,
                               label_table=args.label_table,
                               **({"licence": args.licence} if args.licence else {}))
    except InputError as exc:
        flag = {"max_shift_mm": "--max-shift", "max_mb": "--max-mb"}.get(exc.source, exc.source)
        raise InputError(flag, "", exc.message) from None
    command = _command_line(args)
    result = scene_from_labels(args.image, args.out, wall=args.wall, obstacle=args.obstacle,
                               landmark=args.landmark, entry=" ".join(args.entry),
                               toward=" ".join(args.toward), targets=args.targets, name=args.name,
                               config=cfg, command=command)
    for m in result.meshes:
        print(f"{m.name} ({m.role}, labels {', '.join(map(str, m.labels))}): {m.stats.faces} "
              f"triangles, within {m.stats.max_shift_mm:.3f} mm of the voxel surface "
              f"(bound {m.stats.bound_mm:.3f} mm)")
    log.info("wrote %s", result.path)
    return 0


def _command_line(args: argparse.Namespace) -> str:
    """The command, rebuilt from the parsed arguments (written into scene.yaml)."""
    import shlex

    parts = ["ctrplan", "scene", "from-labels", args.image]
    for opt in ("wall", "obstacle", "landmark"):
        for v in getattr(args, opt):
            parts += [f"--{opt}", v]
    parts += ["--entry=" + ",".join(args.entry), "--toward=" + ",".join(args.toward)]
    if args.targets:
        parts += ["--targets", *args.targets]
    for opt, val in (("name", args.name), ("label-table", args.label_table),
                     ("max-shift", args.max_shift), ("max-mb", args.max_mb), ("licence", args.licence)):
        if val is not None:
            parts += [f"--{opt}", str(val)]
    parts += ["--out", args.out]
    return " ".join(shlex.quote(p) for p in parts)


def _base_axis(scene, length: float = 25.0) -> np.ndarray:
    return scene.to_scene(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, length]]))


def render_html(scene, out, backbones: np.ndarray) -> None:
    """Self-contained interactive view (plotly.js embedded: no network needed)."""
    import plotly.graph_objects as go

    from ctrplan.io import write_text_atomic
    from ctrplan.viz import ROBOT_COLOUR, ROLE_COLOURS, TARGET_COLOUR

    traces = []
    for m in scene.meshes:
        v, f = np.asarray(m.mesh.vertices), np.asarray(m.mesh.faces)
        traces.append(go.Mesh3d(x=v[:, 0], y=v[:, 1], z=v[:, 2], i=f[:, 0], j=f[:, 1], k=f[:, 2],
                                color=ROLE_COLOURS.get(m.role, "#7f8c8d"),
                                opacity=0.2 if m.role == "wall" else 0.6, name=f"{m.name} ({m.role})",
                                showlegend=True, flatshading=True, hoverinfo="name"))
    ax = _base_axis(scene)
    traces.append(go.Scatter3d(x=ax[:, 0], y=ax[:, 1], z=ax[:, 2], mode="lines+markers",
                               line={"color": "black", "width": 6}, marker={"size": 3},
                               name="robot base (+z)"))
    t = scene.target_positions()
    if len(t):
        traces.append(go.Scatter3d(x=t[:, 0], y=t[:, 1], z=t[:, 2], mode="markers+text",
                                   text=[x.display for x in scene.targets], marker={"size": 4, "color": TARGET_COLOUR},
                                   name="targets"))
    for k, b in enumerate(backbones):
        traces.append(go.Scatter3d(x=b[:, 0], y=b[:, 1], z=b[:, 2], mode="lines",
                                   line={"color": ROBOT_COLOUR, "width": 5}, name="robot",
                                   showlegend=k == 0, legendgroup="robot"))
    fig = go.Figure(data=traces)
    fig.update_layout(title=f"scene {scene.name}", margin={"l": 0, "r": 0, "t": 40, "b": 0},
                      scene={"aspectmode": "data", "xaxis_title": "x (mm)", "yaxis_title": "y (mm)",
                             "zaxis_title": "z (mm)"})
    write_text_atomic(out, fig.to_html(include_plotlyjs=True, full_html=True,
                                       config={"displaylogo": False}))


def render_png(scene, out, backbones: np.ndarray) -> None:
    """Static view (matplotlib, faces subsampled for speed)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    from ctrplan.io import save_figure
    from ctrplan.viz import ROBOT_COLOUR, ROLE_COLOURS, TARGET_COLOUR, cube_axes

    fig = plt.figure(figsize=(8, 7), dpi=110)
    ax3 = fig.add_subplot(111, projection="3d")
    rng = np.random.default_rng(0)
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for m in scene.meshes:
        v, f = np.asarray(m.mesh.vertices), np.asarray(m.mesh.faces)
        if len(f) > 5000:
            f = f[rng.choice(len(f), 5000, replace=False)]
        ax3.add_collection3d(Poly3DCollection(v[f], alpha=0.1 if m.role == "wall" else 0.5,
                                              facecolor=ROLE_COLOURS.get(m.role, "#7f8c8d"),
                                              edgecolor="none"))
        lo, hi = np.minimum(lo, v.min(axis=0)), np.maximum(hi, v.max(axis=0))
    ax = _base_axis(scene)
    ax3.plot(ax[:, 0], ax[:, 1], ax[:, 2], color="black", lw=3, label="robot base (+z)")
    t = scene.target_positions()
    if len(t):
        ax3.scatter(t[:, 0], t[:, 1], t[:, 2], color=TARGET_COLOUR, s=18, label="targets")
    for k, b in enumerate(backbones):
        ax3.plot(b[:, 0], b[:, 1], b[:, 2], color=ROBOT_COLOUR, lw=1.5, label="robot" if k == 0 else None)
    cube_axes(ax3, lo, hi)
    ax3.set_title(f"scene {scene.name}")
    ax3.legend(loc="upper left")
    save_figure(fig, out)
