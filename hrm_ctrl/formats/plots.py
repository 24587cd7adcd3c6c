"""Figures of a plan, like the paper's Figs. 11-13 (PNG, drawn off screen with Agg).

:func:`write_plan_figures` reads an ``hrm-plan/1`` dict and writes

- ``backbone.png``: the backbone curves at the chosen steps and the path, in 3D
  (only when a chosen step carries ``backbone_mm``);
- ``arm.png``: the arm (links as lines, joints as dots) at the chosen steps
  and the path, in 3D;
- ``angles.png``: alpha and theta of every joint (degrees) against the
  travelled distance, with the joint limits.

The 3D axes are scaled equally, so bends look as bent as they are.  The plan is
checked completely before anything is drawn; a missing or malformed key raises
:class:`~hrm_ctrl.errors.PlanFileError` naming it, and no file is written.
Each PNG is written atomically (temp file + ``os.replace``).

>>> default_figure_steps(41, backbone_steps=[])
[0, 20, 40]
>>> default_figure_steps(41, backbone_steps=[0, 10, 30, 40])
[0, 10, 40]
"""

from __future__ import annotations

import io
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib import colormaps
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from hrm_ctrl.errors import HrmError, PlanFileError
from hrm_ctrl.files import write_atomic
from hrm_ctrl.formats.planfile import PLAN_FORMAT

DPI = 110
BACKBONE_PNG = "backbone.png"
ARM_PNG = "arm.png"
ANGLES_PNG = "angles.png"


class PlotError(HrmError):
    """The figures cannot be made as asked (bad step choice, unwritable directory)."""


@dataclass(frozen=True)
class PlanArrays:
    """The parts of a plan the figures need, checked and as arrays (mm, rad)."""

    path: np.ndarray  # (P, 3)
    travel: np.ndarray  # (S,) travel_mm as stored
    distance: np.ndarray  # (S,) distance travelled so far (sum of |step|)
    alpha: np.ndarray  # (S, n)
    theta: np.ndarray  # (S, n)
    joints: np.ndarray  # (S, n + 1, 3)
    backbones: dict[int, np.ndarray]  # step index -> (Q, 3)
    limit_alpha_deg: float | None
    limit_theta_deg: float | None
    title: str

    @property
    def n_steps(self) -> int:
        return int(self.travel.shape[0])

    @property
    def n_joints(self) -> int:
        return int(self.alpha.shape[1])


def _key(doc: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in doc:
        raise PlanFileError(f"{where}: missing key '{key}'")
    return doc[key]


def _array(value: Any, shape: tuple[int | None, ...], where: str) -> np.ndarray:
    """``value`` as a finite float array of ``shape`` (None: any length >= 1)."""
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise PlanFileError(f"{where}: expected numbers, got {_short(value)}") from None
    ok = arr.ndim == len(shape) and all(
        (s is None and d >= 1) or d == s for s, d in zip(shape, arr.shape, strict=False)
    )
    if not ok:
        if not shape:
            raise PlanFileError(f"{where}: expected a number, got {_short(value)}")
        want = " x ".join("N" if s is None else str(s) for s in shape)
        raise PlanFileError(f"{where}: expected an array of {want} numbers, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise PlanFileError(f"{where}: contains NaN or inf")
    return arr


def _short(value: Any) -> str:
    text = repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _limit_deg(robot: Mapping[str, Any], name: str, where: str) -> float | None:
    limits = robot.get("joint_limits_deg")
    if not isinstance(limits, Mapping) or name not in limits:
        return None
    value = limits[name]
    if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
        raise PlanFileError(f"{where}.robot.joint_limits_deg.{name}: expected a number > 0")
    return float(value)


def plan_arrays(plan: Mapping[str, Any], source: str = "plan") -> PlanArrays:
    """Check an ``hrm-plan/1`` dict and return what the figures draw.

    Raises :class:`PlanFileError` naming ``source`` and the key that is missing
    or malformed.

    >>> plan_arrays({"format": "hrm-plan/1", "robot": {}, "steps": []})
    Traceback (most recent call last):
    ...
    hrm_ctrl.errors.PlanFileError: plan: missing key 'path_mm'
    """
    if not isinstance(plan, Mapping):
        raise PlanFileError(f"{source}: a plan must be a JSON object, got {type(plan).__name__}")
    fmt = _key(plan, "format", source)
    if fmt != PLAN_FORMAT:
        raise PlanFileError(f"{source}: format is {fmt!r}, expected {PLAN_FORMAT!r}")
    robot = _key(plan, "robot", source)
    if not isinstance(robot, Mapping):
        raise PlanFileError(f"{source}: 'robot' must be an object")
    path = _array(_key(plan, "path_mm", source), (None, 3), f"{source}: path_mm")
    links = _array(
        _key(robot, "links_mm", f"{source}: robot"), (None,), f"{source}: robot.links_mm"
    )
    n = int(links.shape[0])
    steps = _key(plan, "steps", source)
    if not isinstance(steps, list | tuple) or not steps:
        raise PlanFileError(f"{source}: 'steps' must be a non-empty list")
    travel = np.empty(len(steps))
    alpha = np.empty((len(steps), n))
    theta = np.empty((len(steps), n))
    joints = np.empty((len(steps), n + 1, 3))
    backbones: dict[int, np.ndarray] = {}
    for k, step in enumerate(steps):
        where = f"{source}: steps[{k}]"
        if not isinstance(step, Mapping):
            raise PlanFileError(f"{where}: must be an object")
        travel[k] = _array(_key(step, "travel_mm", where), (), f"{where}.travel_mm")
        alpha[k] = _array(_key(step, "alpha_rad", where), (n,), f"{where}.alpha_rad")
        theta[k] = _array(_key(step, "theta_rad", where), (n,), f"{where}.theta_rad")
        joints[k] = _array(_key(step, "joints_mm", where), (n + 1, 3), f"{where}.joints_mm")
        if "backbone_mm" in step:
            backbones[k] = _array(step["backbone_mm"], (None, 3), f"{where}.backbone_mm")
    distance = travel[0] + np.concatenate(([0.0], np.cumsum(np.abs(np.diff(travel)))))
    scenario = plan.get("scenario")
    name = scenario.get("name") if isinstance(scenario, Mapping) else None
    robot_name = robot.get("name")
    title = str(name) if name else (str(robot_name) if robot_name else "plan")
    return PlanArrays(
        path=path,
        travel=travel,
        distance=distance,
        alpha=alpha,
        theta=theta,
        joints=joints,
        backbones=backbones,
        limit_alpha_deg=_limit_deg(robot, "alpha", source),
        limit_theta_deg=_limit_deg(robot, "theta", source),
        title=title,
    )


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


def _step_label(data: PlanArrays, k: int) -> str:
    return f"step {k} (travel {data.travel[k]:.1f} mm)"


def _draw_path(ax: Any, data: PlanArrays) -> None:
    p = data.path
    ax.plot(p[:, 0], p[:, 1], p[:, 2], color="crimson", lw=2.0, ls="--", label="path")


def _backbone_figure(data: PlanArrays, steps: Sequence[int]) -> Figure | None:
    shown = [k for k in steps if k in data.backbones]
    if not shown:
        return None
    fig = Figure(figsize=(10.0, 7.0), layout="constrained")
    ax = fig.add_subplot(projection="3d")
    _draw_path(ax, data)
    pts = [data.path, data.joints[shown, 0, :]]
    for k, colour in zip(shown, _step_colours(len(shown)), strict=True):
        b = data.backbones[k]
        ax.plot(b[:, 0], b[:, 1], b[:, 2], color=colour, lw=1.6, label=_step_label(data, k))
        ax.scatter(*b[-1], color=colour, s=18)
        pts.append(b)
    base = data.joints[shown[0], 0]
    ax.scatter(*base, color="black", marker="s", s=30, label="base O1")
    _equal_axes_3d(ax, np.concatenate(pts))
    ax.set_title(f"{data.title}: backbone curves")
    fig.legend(loc="outside lower center", ncols=3, fontsize=8)
    return fig


def _arm_figure(data: PlanArrays, steps: Sequence[int]) -> Figure:
    fig = Figure(figsize=(10.0, 7.0), layout="constrained")
    ax = fig.add_subplot(projection="3d")
    _draw_path(ax, data)
    pts = [data.path]
    for k, colour in zip(steps, _step_colours(len(steps)), strict=True):
        j = data.joints[k]
        ax.plot(j[:, 0], j[:, 1], j[:, 2], color=colour, lw=2.2, label=_step_label(data, k))
        ax.scatter(j[:-1, 0], j[:-1, 1], j[:-1, 2], color=colour, s=14, depthshade=False)
        ax.scatter(*j[-1], color=colour, marker="^", s=30, depthshade=False)
        pts.append(j)
    ax.scatter(*data.joints[steps[0], 0], color="black", marker="s", s=30, label="base O1")
    _equal_axes_3d(ax, np.concatenate(pts))
    ax.set_title(f"{data.title}: arm (dots: joint centres, triangle: end point)")
    fig.legend(loc="outside lower center", ncols=3, fontsize=8)
    return fig


def _angles_figure(data: PlanArrays, steps: Sequence[int]) -> Figure:
    fig = Figure(figsize=(10.0, 7.5), layout="constrained")
    axes = fig.subplots(2, 1, sharex=True)
    tab10 = colormaps["tab10"]
    colours = [tab10(i) for i in range(10)] + ["black", "darkgoldenrod"]
    x = data.distance
    series = (
        (axes[0], data.alpha, data.limit_alpha_deg, "α (deg, about y)"),
        (axes[1], data.theta, data.limit_theta_deg, "θ (deg, about the new x)"),
    )
    for ax, values, limit, label in series:
        deg = np.degrees(values)
        for i in range(data.n_joints):
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
    limits = "; dashed red: joint limits" if data.limit_alpha_deg is not None else ""
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
    plan: Mapping[str, Any],
    out_dir: str | Path,
    steps: Sequence[int] | None = None,
    *,
    source: str = "plan",
) -> list[Path]:
    """Write the figures of ``plan`` into ``out_dir`` (created if missing).

    ``steps`` are indices into ``plan["steps"]`` to draw in 3D; by default the
    first, middle and last of the steps that carry ``backbone_mm`` (of all
    steps if none does).  Returns the written paths: ``backbone.png`` (only if
    a drawn step carries a backbone), ``arm.png``, ``angles.png``.
    """
    data = plan_arrays(plan, source)
    if steps is None:
        chosen = default_figure_steps(data.n_steps, sorted(data.backbones))
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
    "PLAN_FORMAT",
    "PlanArrays",
    "PlotError",
    "default_figure_steps",
    "plan_arrays",
    "write_plan_figures",
]
