"""Figures of a plan, like the paper's Figs. 11-13 (PNG, drawn off screen with Agg).

:func:`write_plan_figures` draws a :class:`~hrm_ctrl.formats.planfile.PlanDoc` (or an
``hrm-plan/1`` dict, read through it) and writes

- ``backbone.png``: the backbone curves at the chosen steps and the path, in 3D
  (only when a chosen step carries ``backbone_mm``);
- ``arm.png``: the arm (links as lines, joints as dots) at the chosen steps
  and the path, in 3D;
- ``angles.png``: alpha and theta of every joint (degrees) against the
  travelled distance, with the joint limits;
- ``clearance.png`` (only for a plan that stores its environment): the worst link
  clearance of each group of links against the travelled distance, zero marked.

The 3D figures draw the plan's environment: a pipe as rings of its inner diameter along
the axis, a wall as a translucent patch around its openings with the openings' outlines
(cut where the wall is bounded), a box as its edges.

The 3D axes are scaled equally, so bends look as bent as they are.  A dict is
checked completely (:meth:`PlanDoc.from_dict`) before anything is drawn; a missing or
malformed key raises :class:`~hrm_ctrl.errors.PlanFileError` naming it, and no file is
written.
Each PNG is written atomically (temp file + ``os.replace``).

>>> default_figure_steps(41, backbone_steps=[])
[0, 20, 40]
>>> default_figure_steps(41, backbone_steps=[0, 10, 30, 40])
[0, 10, 40]
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from hrm_ctrl.errors import HrmError
from hrm_ctrl.files import write_atomic
from hrm_ctrl.formats.planfile import PlanDoc
from hrm_ctrl.planning.environment import Box, Environment, Pipe, Wall
from hrm_ctrl.planning.report import plan_file_clearance
from hrm_ctrl.view.geometry import circle, wall_shapes

DPI = 110
BACKBONE_PNG = "backbone.png"
ARM_PNG = "arm.png"
ANGLES_PNG = "angles.png"
CLEARANCE_PNG = "clearance.png"
PIPE_RING_SPACING = 15.0  # mm between the rings drawn of a pipe
LINK_GROUPS = ((1, 3), (4, 6), (7, 9), (10, 12))  # links drawn together in clearance.png
CLEARANCE_SHOWN_MM = 100.0  # clearance.png shows clearances up to this
ENV_COLOUR = "slategray"


class PlotError(HrmError):
    """The figures cannot be made as asked (bad step choice, unwritable directory)."""


def default_figure_steps(n_steps: int, backbone_steps: Sequence[int]) -> list[int]:
    """First, middle and last step, among the steps that carry a backbone if any do."""
    candidates = sorted(backbone_steps) if backbone_steps else list(range(n_steps))
    if not candidates:
        return []
    picks = [candidates[0], candidates[(len(candidates) - 1) // 2], candidates[-1]]
    return sorted(set(picks))


def _equal_axes_3d(ax: Any, points: np.ndarray) -> None:
    """Limits around ``points`` with the same scale on x, y and z."""
    lo, hi = points.min(axis=0), points.max(axis=0)
    span = hi - lo
    span = np.maximum(span, max(0.25 * float(span.max()), 1.0))  # no flat box
    mid = (lo + hi) / 2.0
    lo, hi = mid - span / 2.0 * 1.05, mid + span / 2.0 * 1.05
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(tuple(hi - lo))
    ax.view_init(elev=22.0, azim=-60.0)
    ax.set_xlabel("x (mm)", labelpad=10)
    ax.set_ylabel("y (mm)", labelpad=10)
    ax.set_zlabel("z (mm)", labelpad=10)


def _step_colours(n: int) -> list[Any]:
    cmap = colormaps["viridis"]
    return [cmap(v) for v in np.linspace(0.0, 0.85, max(n, 1))]


def _step_label(data: PlanDoc, k: int) -> str:
    return f"step {k} (travel {data.travel_mm[k]:.1f} mm)"


def _draw_path(ax: Any, data: PlanDoc) -> None:
    p = data.path_mm
    ax.plot(p[:, 0], p[:, 1], p[:, 2], color="crimson", lw=2.0, ls="--", label="path")


# the environment's drawn shapes are the live view's (one place for the geometry)
_circle = circle
_wall_outline = wall_shapes


def _box_edges(b: Box) -> list[np.ndarray]:
    h = 0.5 * b.size
    corners = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)]) * h
    world = b.centre + corners @ b.rotation.T
    edges = []
    for i in range(8):
        for j in range(i + 1, 8):
            if np.count_nonzero(corners[i] != corners[j]) == 1:
                edges.append(world[[i, j]])
    return edges


def _draw_environment(ax: Any, env: Environment | None, near: np.ndarray) -> list[np.ndarray]:
    """Draw ``env`` into the 3D axes; returns the points drawn (for the axes' limits)."""
    if env is None:
        return []
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    drawn: list[np.ndarray] = []
    labelled = False

    def label() -> dict[str, str]:
        nonlocal labelled
        first, labelled = not labelled, True
        return {"label": "environment"} if first else {}

    for o in env.obstacles:
        if isinstance(o, Pipe):
            axis = o.axis
            k = max(2, int(np.ceil(axis.length / PIPE_RING_SPACING)) + 1)
            for d in np.linspace(0.0, axis.length, k):
                ring = _circle(axis.point_at(d), axis.tangent_at(d), o.inner_radius, 36)
                ax.plot(*ring.T, color=ENV_COLOUR, lw=0.6, alpha=0.6, **label())
                drawn.append(ring)
            for d in (0.0, axis.length):  # the ends, bold
                ring = _circle(axis.point_at(d), axis.tangent_at(d), o.inner_radius, 48)
                ax.plot(*ring.T, color=ENV_COLOUR, lw=1.6)
        elif isinstance(o, Wall):
            patch, outlines = _wall_outline(o, near)
            if len(patch) >= 3:
                ax.add_collection3d(
                    Poly3DCollection(
                        [patch], facecolor=ENV_COLOUR, alpha=0.12, edgecolor=ENV_COLOUR
                    )
                )
                drawn.append(patch)
            for line in outlines:
                ax.plot(*line.T, color=ENV_COLOUR, lw=1.6, **label())
                drawn.append(line)
        else:
            for e in _box_edges(o):
                ax.plot(*e.T, color=ENV_COLOUR, lw=1.2, **label())
                drawn.append(e)
    return drawn


def _backbone_figure(data: PlanDoc, steps: Sequence[int]) -> Figure | None:
    shown = [k for k in steps if k in data.backbones_mm]
    if not shown:
        return None
    fig = Figure(figsize=(10.0, 7.0), layout="constrained")
    ax = fig.add_subplot(projection="3d")
    _draw_path(ax, data)
    pts = [data.path_mm, data.joints_mm[shown, 0, :]]
    pts += _draw_environment(ax, data.environment, data.path_mm.mean(axis=0))
    for k, colour in zip(shown, _step_colours(len(shown)), strict=True):
        b = data.backbones_mm[k]
        ax.plot(b[:, 0], b[:, 1], b[:, 2], color=colour, lw=1.6, label=_step_label(data, k))
        ax.scatter(*b[-1], color=colour, s=18)
        pts.append(b)
    base = data.joints_mm[shown[0], 0]
    ax.scatter(*base, color="black", marker="s", s=30, label="base O1")
    _equal_axes_3d(ax, np.concatenate(pts))
    ax.set_title(f"{data.title}: backbone curves")
    fig.legend(loc="outside lower center", ncols=3, fontsize=8)
    return fig


def _arm_figure(data: PlanDoc, steps: Sequence[int]) -> Figure:
    fig = Figure(figsize=(10.0, 7.0), layout="constrained")
    ax = fig.add_subplot(projection="3d")
    _draw_path(ax, data)
    pts = [data.path_mm]
    pts += _draw_environment(ax, data.environment, data.path_mm.mean(axis=0))
    for k, colour in zip(steps, _step_colours(len(steps)), strict=True):
        j = data.joints_mm[k]
        ax.plot(j[:, 0], j[:, 1], j[:, 2], color=colour, lw=2.2, label=_step_label(data, k))
        ax.scatter(j[:-1, 0], j[:-1, 1], j[:-1, 2], color=colour, s=14, depthshade=False)
        ax.scatter(*j[-1], color=colour, marker="^", s=30, depthshade=False)
        pts.append(j)
    ax.scatter(*data.joints_mm[steps[0], 0], color="black", marker="s", s=30, label="base O1")
    _equal_axes_3d(ax, np.concatenate(pts))
    ax.set_title(f"{data.title}: arm (dots: joint centres, triangle: end point)")
    fig.legend(loc="outside lower center", ncols=3, fontsize=8)
    return fig


def _angles_figure(data: PlanDoc, steps: Sequence[int]) -> Figure:
    fig = Figure(figsize=(10.0, 7.5), layout="constrained")
    axes = fig.subplots(2, 1, sharex=True)
    tab10 = colormaps["tab10"]
    colours = [tab10(i) for i in range(10)] + ["black", "darkgoldenrod"]
    x = data.distance_mm
    limit_alpha, limit_theta = data.joint_limits_deg
    series = (
        (axes[0], data.alpha_rad, limit_alpha, "α (deg, about y)"),
        (axes[1], data.theta_rad, limit_theta, "θ (deg, about the new x)"),
    )
    for ax, values, limit, label in series:
        deg = np.degrees(values)
        for i in range(values.shape[1]):
            colour = colours[i % len(colours)]
            ax.plot(x, deg[:, i], color=colour, lw=1.3, label=f"joint {i + 1}")
        if limit is not None:
            for sign in (-1.0, 1.0):
                ax.axhline(sign * limit, color="red", ls="--", lw=1.0)
            ax.set_ylim(-1.15 * limit, 1.15 * limit)
        for k in steps:
            ax.axvline(x[k], color="0.6", lw=0.8, ls=":")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="outside right center", fontsize=8)
    axes[1].set_xlabel("travelled distance (mm)")
    limits = "; dashed red: joint limits" if limit_alpha is not None else ""
    axes[0].set_title(f"{data.title}: joint angles (dotted: steps drawn in 3D{limits})")
    return fig


def _clearance_figure(data: PlanDoc, steps: Sequence[int]) -> Figure | None:
    c = plan_file_clearance(data)
    if c is None or not np.isfinite(c).any():
        return None
    fig = Figure(figsize=(10.0, 5.5), layout="constrained")
    ax = fig.add_subplot()
    x = data.distance_mm
    tab10 = colormaps["tab10"]
    for g, (lo, hi) in enumerate(LINK_GROUPS):
        if lo > c.shape[1]:
            break
        worst = c[:, lo - 1 : hi].min(axis=1)
        ax.plot(x, np.where(np.isfinite(worst), worst, np.nan), color=tab10(g), lw=1.4,
                label=f"links {lo}-{min(hi, c.shape[1])}")  # fmt: skip
    i, j = np.unravel_index(int(np.argmin(c)), c.shape)
    v = float(c[i, j])
    ax.axhline(0.0, color="black", ls="--", lw=1.2, label="0: contact")
    ax.scatter([x[i]], [v], color="red" if v < 0 else "black", zorder=5,
               label=f"worst {v:.2f} mm: step {i}, link {j + 1}")  # fmt: skip
    for k in steps:
        ax.axvline(x[k], color="0.6", lw=0.8, ls=":")
    finite = c[np.isfinite(c)]
    top = min(float(finite.max()), CLEARANCE_SHOWN_MM)
    ax.set_ylim(min(v, 0.0) - 0.08 * (top - min(v, 0.0)) - 1.0, top + 2.0)
    ax.set_xlabel("travelled distance (mm)")
    ax.set_ylabel("clearance (mm)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8, loc="best")
    ax.set_title(
        f"{data.title}: worst link clearance against the environment "
        f"(negative: collision; dotted: steps drawn in 3D)"
    )
    return fig


def _png_bytes(fig: Figure) -> bytes:
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def _write_atomic(path: Path, data: bytes) -> None:
    try:
        write_atomic(path, data, make_parents=False)
    except OSError as exc:
        raise PlotError(f"{path}: cannot write figure ({exc.strerror or exc})") from None


def write_plan_figures(
    plan: PlanDoc | Mapping[str, Any],
    out_dir: str | Path,
    steps: Sequence[int] | None = None,
    *,
    source: str = "plan",
) -> list[Path]:
    """Write the figures of ``plan`` into ``out_dir`` (created if missing).

    ``steps`` are indices of the plan's steps to draw in 3D; by default the
    first, middle and last of the steps that carry ``backbone_mm`` (of all
    steps if none does).  Returns the written paths: ``backbone.png`` (only if
    a drawn step carries a backbone), ``arm.png``, ``angles.png``, ``clearance.png`` (only
    if the plan stores its environment).
    """
    data = plan if isinstance(plan, PlanDoc) else PlanDoc.from_dict(plan, source)
    if steps is None:
        chosen = default_figure_steps(data.n_steps, sorted(data.backbones_mm))
    else:
        chosen = []
        for k in steps:
            if isinstance(k, bool) or not isinstance(k, int | np.integer):
                raise PlotError(f"step to draw must be an integer, got {k!r}")
            if not 0 <= int(k) < data.n_steps:
                raise PlotError(f"step {k} to draw is out of range: the plan has {data.n_steps}")
            chosen.append(int(k))
        chosen = sorted(set(chosen))
        if not chosen:
            raise PlotError("no step to draw")
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PlotError(f"{out}: cannot create figure directory ({exc.strerror or exc})") from None
    figures: list[tuple[str, Figure]] = []
    backbone = _backbone_figure(data, chosen)
    if backbone is not None:
        figures.append((BACKBONE_PNG, backbone))
    figures.append((ARM_PNG, _arm_figure(data, chosen)))
    figures.append((ANGLES_PNG, _angles_figure(data, chosen)))
    clearance = _clearance_figure(data, chosen)
    if clearance is not None:
        figures.append((CLEARANCE_PNG, clearance))
    rendered = [(name, _png_bytes(fig)) for name, fig in figures]  # draw all before writing

    written: list[Path] = []
    try:
        for name, png in rendered:
            path = out / name
            _write_atomic(path, png)
            written.append(path)
    except PlotError:
        for path in written:  # all figures or none
            path.unlink(missing_ok=True)
        raise
    return written


__all__ = [
    "ANGLES_PNG",
    "ARM_PNG",
    "BACKBONE_PNG",
    "CLEARANCE_PNG",
    "PlotError",
    "default_figure_steps",
    "write_plan_figures",
]
