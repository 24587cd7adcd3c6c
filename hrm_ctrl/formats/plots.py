"""Figures of a plan, like the paper's Figs. 11-13 (PNG, drawn off screen with Agg).

:func:`write_plan_figures` draws a :class:`~hrm_ctrl.formats.planfile.PlanDoc` (or an
``hrm-plan/1`` dict, read through it) and writes

- ``backbone.png``: the backbone curves at the chosen steps and the path, in 3D
  (only when a chosen step carries ``backbone_mm``);
- ``arm.png``: the arm (links as lines, joints as dots) at the chosen steps
  and the path, in 3D;
- ``angles.png``: alpha and theta of every joint (degrees) against the
  travelled distance, with the joint limits.

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

DPI = 110
BACKBONE_PNG = "backbone.png"
ARM_PNG = "arm.png"
ANGLES_PNG = "angles.png"


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


def _backbone_figure(data: PlanDoc, steps: Sequence[int]) -> Figure | None:
    shown = [k for k in steps if k in data.backbones_mm]
    if not shown:
        return None
    fig = Figure(figsize=(10.0, 7.0), layout="constrained")
    ax = fig.add_subplot(projection="3d")
    _draw_path(ax, data)
    pts = [data.path_mm, data.joints_mm[shown, 0, :]]
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
    a drawn step carries a backbone), ``arm.png``, ``angles.png``.
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
    "PlotError",
    "default_figure_steps",
    "write_plan_figures",
]
