"""Plots and 3-D views: a static PNG (matplotlib) and a self-contained interactive HTML view
(plotly, with plotly.js embedded so the file works offline and fetches nothing).

All geometry here is in the scene frame, mm.
"""

from __future__ import annotations

import os
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

ROLE_COLOURS = {"wall": "#d9a38f", "obstacle": "#c0392b"}
ROBOT_COLOUR = "#1f4e9c"
TIP_COLOUR = "#0b8a3c"
TARGET_COLOUR = "#f39c12"


@dataclass(frozen=True)
class ViewMesh:
    """A mesh to draw: name, role (wall/obstacle), vertices (V,3) mm, faces (F,3) int."""

    name: str
    role: str
    vertices: np.ndarray
    faces: np.ndarray


def scene_meshes(scene) -> list[ViewMesh]:
    """The meshes of a :class:`ctrplan.collision.scene.Scene` as :class:`ViewMesh` objects."""
    return [ViewMesh(m.name, m.role, np.asarray(m.mesh.vertices), np.asarray(m.mesh.faces))
            for m in scene.meshes]


#: A tip pose goal (:class:`GoalView`): its colour, the length (mm) of the approach arrow and of
#: the cone drawn at the goal, the points on the cone's rim and the generator lines drawn.
GOAL_COLOUR = "#16a085"
GOAL_LENGTH_MM = 10.0
CONE_RIM_POINTS = 48
CONE_GENERATORS = 4


@dataclass(frozen=True)
class GoalView:
    """A tip pose goal to draw (scene frame, mm): ``surface`` (3,) the target on the tissue,
    ``point`` (3,) where the tip stops (``surface`` + standoff along the normal), ``direction``
    (3,) unit, the way the tip must point (None: any), ``cone_deg`` the half-angle of the
    allowed tip directions around it (None: no cone)."""

    surface: np.ndarray
    point: np.ndarray
    direction: np.ndarray | None = None
    cone_deg: float | None = None


def goal_lines(goal: GoalView, length_mm: float = GOAL_LENGTH_MM,
               rim: int = CONE_RIM_POINTS) -> dict[str, np.ndarray]:
    """Polylines (name -> (k, 3) mm, scene frame; NaN rows split a polyline) that draw a tip
    pose goal: ``standoff`` from the surface target to the standoff point, ``approach`` the
    approach direction ending at the standoff point (``length_mm`` long), and ``cone`` the
    cone of allowed tip directions: apex at the standoff point, opening back along the approach
    (the way the robot arrives), its rim ``length_mm`` from the apex along the axis and
    :data:`CONE_GENERATORS` lines from the apex to the rim."""
    surface, point = np.asarray(goal.surface, dtype=float), np.asarray(goal.point, dtype=float)
    out = {"standoff": np.stack([surface, point])}
    if goal.direction is None:
        return out
    d = np.asarray(goal.direction, dtype=float)
    d = d / np.linalg.norm(d)
    out["approach"] = np.stack([point - length_mm * d, point])
    if goal.cone_deg is None:
        return out
    # two unit vectors across the axis: the axis crossed with the world axis least along it
    u = np.cross(d, np.eye(3)[int(np.argmin(np.abs(d)))])
    u /= np.linalg.norm(u)
    v = np.cross(d, u)
    half = np.radians(min(float(goal.cone_deg), 89.0))   # a 90 deg cone is a plane: drawn at 89
    centre, radius = point - length_mm * d, length_mm * np.tan(half)
    phi = np.linspace(0.0, 2.0 * np.pi, rim + 1)
    ring = centre + radius * (np.cos(phi)[:, None] * u + np.sin(phi)[:, None] * v)
    gaps = [np.full((1, 3), np.nan)]
    spokes = [np.concatenate([[point, ring[k]], gaps[0]])
              for k in range(0, rim, max(1, rim // CONE_GENERATORS))]
    out["cone"] = np.concatenate([ring, *gaps, *spokes])
    return out


#: States drawn along a plan: in the HTML view and in the PNG.
HTML_FRAMES = 12
PNG_FRAMES = 8
#: Frames of the HTML view's animation along a trajectory (backbones computed only for them).
ANIMATION_FRAMES = 60
MOVING_COLOUR = "#7b2cbf"


@dataclass(frozen=True)
class Animation:
    """The robot along its trajectory: t (F,) s, backbones (F, m, 3) mm scene frame, tips
    (F, 3) mm; ``duration_s`` the trajectory's (t[-1])."""

    t: np.ndarray
    backbones: np.ndarray
    tips: np.ndarray

    @property
    def duration_s(self) -> float:
        return float(self.t[-1])


def pick_frames(k: int, count: int) -> np.ndarray:
    """Indices of ``count`` states spread evenly over ``k`` (the first and the last included)."""
    if k <= count:
        return np.arange(k)
    return np.unique(np.linspace(0, k - 1, count).round().astype(int))



def plan_html(
    path: str | os.PathLike,
    meshes: Sequence[ViewMesh],
    backbones: np.ndarray,
    tip_path: np.ndarray | None = None,
    target: np.ndarray | None = None,
    title: str = "ctrplan",
    frames: int = HTML_FRAMES,
    animation: Animation | None = None,
    goal: GoalView | None = None,
) -> None:
    """Write an interactive, self-contained HTML view (:func:`plan_figure`)."""
    from ctrplan.io import write_text_atomic

    fig = plan_figure(meshes, backbones, tip_path, target, title, frames, animation, goal)
    # include_plotlyjs=True embeds the whole library: the file works offline and loads no URL.
    # auto_play=False: an animation starts with its play button (real time), not on load
    html = fig.to_html(include_plotlyjs=True, full_html=True, config={"displaylogo": False},
                       auto_play=False)
    write_text_atomic(path, html)


def _goal_traces(go, goal: GoalView) -> list:
    """plotly traces of a tip pose goal (:func:`goal_lines`, the surface target and the
    standoff point)."""
    names = {"standoff": "standoff (surface target to tip goal)", "approach": "approach direction",
             "cone": "approach cone"}
    traces = [go.Scatter3d(x=xyz[:, 0], y=xyz[:, 1], z=xyz[:, 2], mode="lines", name=names[key],
                           line={"color": GOAL_COLOUR, "width": 6 if key == "approach" else 3,
                                 "dash": "dash" if key == "standoff" else "solid"},
                           connectgaps=False)
              for key, xyz in goal_lines(goal).items()]
    for where, name, symbol in ((goal.surface, "surface target", "x"),
                                (goal.point, "standoff point (tip goal)", "circle")):
        p = np.asarray(where, dtype=float)
        traces.append(go.Scatter3d(x=[p[0]], y=[p[1]], z=[p[2]], mode="markers", name=name,
                                   marker={"size": 5, "color": GOAL_COLOUR, "symbol": symbol}))
    if goal.direction is not None:     # the arrow's head at the tip goal
        d, p = np.asarray(goal.direction, dtype=float), np.asarray(goal.point, dtype=float)
        traces.append(go.Cone(x=[p[0]], y=[p[1]], z=[p[2]], u=[d[0]], v=[d[1]], w=[d[2]],
                              anchor="tip", sizemode="absolute", sizeref=2.0, showscale=False,
                              colorscale=[[0, GOAL_COLOUR], [1, GOAL_COLOUR]],
                              name="approach direction (head)", showlegend=False))
    return traces


def plan_figure(
    meshes: Sequence[ViewMesh],
    backbones: np.ndarray,
    tip_path: np.ndarray | None = None,
    target: np.ndarray | None = None,
    title: str = "ctrplan",
    frames: int = HTML_FRAMES,
    animation: Animation | None = None,
    goal: GoalView | None = None,
):
    """The interactive view as a plotly Figure.

    backbones : (K, m, 3) mm, scene frame — robot shapes along the path (a subset is drawn,
    the final one bold). tip_path : (K, 3) mm. target : (3,) mm. animation : the robot along
    its trajectory, played in real time with a time slider (plotly frames). goal : a tip pose
    goal (approach direction, cone, surface target and standoff point; :func:`goal_lines`).
    """
    import plotly.graph_objects as go

    traces = []
    for mesh in meshes:
        v, f = mesh.vertices, mesh.faces
        traces.append(go.Mesh3d(
            x=v[:, 0], y=v[:, 1], z=v[:, 2], i=f[:, 0], j=f[:, 1], k=f[:, 2],
            color=ROLE_COLOURS.get(mesh.role, "#999999"),
            opacity=0.25 if mesh.role == "wall" else 0.6, name=f"{mesh.name} ({mesh.role})",
            showlegend=True, flatshading=True, hoverinfo="name",
        ))
    backbones = np.asarray(backbones, dtype=float).reshape(-1, backbones.shape[-2], 3)
    idx = pick_frames(len(backbones), frames)
    for n_shown, k in enumerate(idx):
        last = bool(k == len(backbones) - 1)
        b = backbones[k]
        traces.append(go.Scatter3d(
            x=b[:, 0], y=b[:, 1], z=b[:, 2], mode="lines",
            line={"color": ROBOT_COLOUR, "width": 9 if last else 3},
            opacity=1.0 if last else 0.35, name="robot (final)" if last else "robot along path",
            showlegend=last or n_shown == 0, legendgroup="final" if last else "path",
        ))
    if tip_path is not None and len(tip_path):
        t = np.asarray(tip_path, dtype=float)
        traces.append(go.Scatter3d(x=t[:, 0], y=t[:, 1], z=t[:, 2], mode="lines+markers",
                                   line={"color": TIP_COLOUR, "width": 4}, marker={"size": 2},
                                   name="tip path"))
    if target is not None:
        t = np.asarray(target, dtype=float).reshape(3)
        traces.append(go.Scatter3d(x=[t[0]], y=[t[1]], z=[t[2]], mode="markers",
                                   marker={"size": 6, "color": TARGET_COLOUR, "symbol": "diamond"},
                                   name="target"))
    if goal is not None:
        traces.extend(_goal_traces(go, goal))
    fig = go.Figure(data=traces)
    fig.update_layout(
        title=title, scene={"aspectmode": "data", "xaxis_title": "x (mm)", "yaxis_title": "y (mm)",
                            "zaxis_title": "z (mm)"},
        margin={"l": 0, "r": 0, "t": 40, "b": 0}, legend={"itemsizing": "constant"},
    )
    if animation is not None:
        _animate(fig, animation)
    return fig


def _moving(go, b: np.ndarray, tip: np.ndarray, t: float) -> list:
    """The robot and its tip at one time of the animation."""
    return [go.Scatter3d(x=b[:, 0], y=b[:, 1], z=b[:, 2], mode="lines",
                         line={"color": MOVING_COLOUR, "width": 8}, name="robot at t"),
            go.Scatter3d(x=[tip[0]], y=[tip[1]], z=[tip[2]], mode="markers",
                         marker={"size": 4, "color": MOVING_COLOUR}, name=f"tip at t = {t:.2f} s",
                         showlegend=False)]


def _animate(fig, anim: Animation) -> None:
    """Add the moving robot, one plotly frame per sample of ``anim``, a play button (real
    time) and a time slider."""
    import plotly.graph_objects as go

    first = len(fig.data)
    fig.add_traces(_moving(go, anim.backbones[0], anim.tips[0], float(anim.t[0])))
    idx = [first, first + 1]
    fig.frames = [go.Frame(data=_moving(go, b, tip, float(t)), traces=idx, name=str(k))
                  for k, (t, b, tip) in enumerate(zip(anim.t, anim.backbones, anim.tips))]
    step_ms = 1000.0 * anim.duration_s / max(1, len(anim.t) - 1)

    def args(names, ms):
        return [names, {"frame": {"duration": ms, "redraw": True}, "mode": "immediate",
                        "transition": {"duration": 0}, "fromcurrent": True}]

    fig.update_layout(
        updatemenus=[{"type": "buttons", "showactive": False, "x": 0.02, "y": 0.02,
                      "xanchor": "left", "yanchor": "bottom", "buttons": [
                          {"label": "play", "method": "animate",
                           "args": args(None, max(20.0, step_ms))},
                          {"label": "pause", "method": "animate", "args": args([None], 0)}]}],
        sliders=[{"active": 0, "x": 0.15, "len": 0.8, "y": 0.02, "yanchor": "bottom",
                  "currentvalue": {"prefix": "t = ", "suffix": " s"},
                  "steps": [{"label": f"{t:.2f}", "method": "animate",
                             "args": args([str(k)], 0)} for k, t in enumerate(anim.t)]}],
    )


def _crop_faces(v: np.ndarray, f: np.ndarray, lo: np.ndarray, hi: np.ndarray, max_faces: int) -> np.ndarray:
    c = v[f].mean(axis=1)
    keep = np.all((c >= lo) & (c <= hi), axis=1)
    f = f[keep]
    if len(f) > max_faces:
        f = f[np.random.default_rng(0).choice(len(f), max_faces, replace=False)]
    return f


def _shaded(tri: np.ndarray, colour: str, alpha: float) -> np.ndarray:
    """Per-face RGBA with simple Lambert shading (light from the viewer's upper left)."""
    from matplotlib.colors import to_rgb

    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True) + 1e-12
    light = np.array([-0.4, -0.5, 0.77])
    k = 0.45 + 0.55 * np.abs(n @ light)
    rgb = np.clip(np.asarray(to_rgb(colour))[None, :] * k[:, None], 0, 1)
    return np.concatenate([rgb, np.full((len(tri), 1), alpha)], axis=1)


def cube_axes(ax, lo: np.ndarray, hi: np.ndarray) -> None:
    """A matplotlib 3D axis showing the box lo..hi (3,) mm as a cube (equal scales), labelled
    in mm (the scene frame)."""
    ctr, half = (lo + hi) / 2, (hi - lo).max() / 2
    ax.set_xlim(ctr[0] - half, ctr[0] + half)
    ax.set_ylim(ctr[1] - half, ctr[1] + half)
    ax.set_zlim(ctr[2] - half, ctr[2] + half)
    ax.set_xlabel("x (mm)")
    ax.set_ylabel("y (mm)")
    ax.set_zlabel("z (mm)")


def plan_png(
    path: str | os.PathLike,
    meshes: Sequence[ViewMesh],
    backbones: np.ndarray,
    tip_path: np.ndarray | None = None,
    target: np.ndarray | None = None,
    title: str = "ctrplan",
    frames: int = PNG_FRAMES,
    crop_mm: float = 40.0,
    goal: GoalView | None = None,
) -> None:
    """Write a static PNG (:func:`plan_png_figure`)."""
    from ctrplan.io import save_figure

    save_figure(plan_png_figure(meshes, backbones, tip_path, target, title, frames, crop_mm, goal),
                path)


def plan_png_figure(
    meshes: Sequence[ViewMesh],
    backbones: np.ndarray,
    tip_path: np.ndarray | None = None,
    target: np.ndarray | None = None,
    title: str = "ctrplan",
    frames: int = PNG_FRAMES,
    crop_mm: float = 40.0,
    goal: GoalView | None = None,
):
    """The static view as a matplotlib Figure: anatomy near the robot (cropped), shapes along
    the path, target, and a tip pose goal (``goal``: :func:`goal_lines` and its points)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    backbones = np.asarray(backbones, dtype=float)
    pts = backbones.reshape(-1, 3)
    if tip_path is not None and len(tip_path):
        pts = np.vstack([pts, np.asarray(tip_path, dtype=float).reshape(-1, 3)])
    if target is not None:
        pts = np.vstack([pts, np.asarray(target, dtype=float).reshape(1, 3)])
    lines = goal_lines(goal) if goal is not None else {}
    for xyz in lines.values():
        pts = np.vstack([pts, xyz[np.all(np.isfinite(xyz), axis=1)]])
    lo = pts.min(axis=0) - crop_mm
    hi = pts.max(axis=0) + crop_mm
    fig = plt.figure(figsize=(8, 7), dpi=110)
    ax = fig.add_subplot(111, projection="3d")
    for mesh in meshes:
        f = _crop_faces(mesh.vertices, mesh.faces, lo, hi, 20000)
        if len(f) == 0:
            continue
        tri = mesh.vertices[f]
        poly = Poly3DCollection(tri, facecolors=_shaded(tri, ROLE_COLOURS.get(mesh.role, "#999999"),
                                                        0.22 if mesh.role == "wall" else 0.6),
                                edgecolor="none")
        ax.add_collection3d(poly)
    for k in pick_frames(len(backbones), frames):
        last = bool(k == len(backbones) - 1)
        b = backbones[k]
        ax.plot(b[:, 0], b[:, 1], b[:, 2], color=ROBOT_COLOUR, lw=3 if last else 1,
                alpha=1.0 if last else 0.4)
    if tip_path is not None and len(tip_path):
        t = np.asarray(tip_path)
        ax.plot(t[:, 0], t[:, 1], t[:, 2], color=TIP_COLOUR, lw=1.5, label="tip path")
    if target is not None:
        t = np.asarray(target).reshape(3)
        ax.scatter([t[0]], [t[1]], [t[2]], color=TARGET_COLOUR, s=60, marker="D", label="target")
    if goal is not None:
        _goal_artists(ax, goal, lines)
    cube_axes(ax, lo, hi)
    ax.set_title(title)
    ax.legend(loc="upper left")
    return fig


def _goal_artists(ax, goal: GoalView, lines: dict[str, np.ndarray]) -> None:
    """matplotlib artists of a tip pose goal: its polylines (labelled ``standoff``,
    ``approach direction``, ``approach cone``) and the surface target and standoff point."""
    labels = {"standoff": "standoff", "approach": "approach direction", "cone": "approach cone"}
    for key, xyz in lines.items():
        ax.plot(xyz[:, 0], xyz[:, 1], xyz[:, 2], color=GOAL_COLOUR, label=labels[key],
                lw=2.5 if key == "approach" else 1.2, ls="--" if key == "standoff" else "-")
    s, p = np.asarray(goal.surface, dtype=float), np.asarray(goal.point, dtype=float)
    ax.scatter([s[0]], [s[1]], [s[2]], color=GOAL_COLOUR, s=40, marker="x", label="surface target")
    ax.scatter([p[0]], [p[1]], [p[2]], color=GOAL_COLOUR, s=40, marker="o",
               label="standoff point (tip goal)")
