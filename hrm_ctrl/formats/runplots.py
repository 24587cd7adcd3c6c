"""Figures of a run (``hrm report``, the console's ``run``): PNGs drawn off screen (Agg),
each written atomically, from a :class:`~hrm_ctrl.formats.runlog.RunLog`.

- ``angles.png``: every joint's alpha and theta (deg) over time, planned (the commanded
  targets, through the rope layer's inverse) dashed and measured (the drives' reported
  positions, the same way) solid;
- ``tracking.png``: the tracking error over time (the largest joint-angle difference,
  deg, and the tip's distance, mm, measured against planned one cycle earlier: a
  target is reported back at the SYNC after the one that applied it) and, when the run
  has a tension side file, every rope's tension (N);
- ``lateness.png``: each SYNC's interval less the control period (ms) and its histogram.

The three are drawn before any is written (a figure that cannot be drawn leaves no file),
and a write that fails removes what this call wrote.

:func:`run_analysis` returns the arrays and figures the plots show (and ``hrm report
--json`` prints).
"""

from __future__ import annotations

import contextlib
import io
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from hrm_ctrl.files import write_atomic
from hrm_ctrl.formats.runlog import RunLog, RunLogError, joint_angles, tension_csv, tension_path

FEEDBACK_LAG_CYCLES = 1  # the TPDO after SYNC k reports the target SYNC k-1 applied
FIGURE_NAMES = ("angles.png", "tracking.png", "lateness.png")  # what write_run_figures writes


@dataclass(frozen=True)
class RunAnalysis:
    """One stream of a run: ``t_s`` (cycles,), planned and measured angles (cycles, 12)
    rad, ``angle_error_rad`` / ``tip_error_mm`` (cycles,) (NaN where feedback is missing),
    ``lateness_s`` (cycles,), tensions (``tension_t_s``, ``tension_N``) or None."""

    t_s: np.ndarray
    planned_alpha: np.ndarray
    planned_theta: np.ndarray
    measured_alpha: np.ndarray
    measured_theta: np.ndarray
    angle_error_rad: np.ndarray
    tip_error_mm: np.ndarray
    counts_error: np.ndarray
    lateness_s: np.ndarray
    tension_t_s: np.ndarray | None
    tension_N: np.ndarray | None

    def summary(self) -> dict[str, Any]:
        def mx(a: np.ndarray) -> float | None:
            return float(np.nanmax(a)) if np.isfinite(a).any() else None

        return {
            "cycles": int(self.t_s.shape[0]),
            "duration_s": float(self.t_s[-1] - self.t_s[0]) if self.t_s.size else 0.0,
            "max_angle_error_deg": None
            if mx(self.angle_error_rad) is None
            else float(np.degrees(mx(self.angle_error_rad))),
            "max_tip_error_mm": mx(self.tip_error_mm),
            "max_counts_error": mx(self.counts_error),
            "median_counts_error": float(np.nanmedian(self.counts_error))
            if np.isfinite(self.counts_error).any()
            else None,
            "max_sync_lateness_ms": None
            if not self.lateness_s.size
            else float(1e3 * np.max(self.lateness_s)),
            "tension_samples": 0 if self.tension_N is None else int(self.tension_N.shape[0]),
        }


def run_analysis(
    log: RunLog,
    actuation: Any,
    stream: int = -1,
    *,
    lag: int = FEEDBACK_LAG_CYCLES,
    tensions: tuple[np.ndarray, np.ndarray] | None = None,
) -> RunAnalysis:
    """Angles, tracking and lateness of stream ``stream`` of ``log`` for ``actuation``
    (the rope layer the run used).  ``lag``: rows by which the feedback follows the
    targets (1 for a CAN log; 0 for samples taken together); ``tensions``: (times from
    the log's first row, N per motor) instead of the run's tension side file."""
    from hrm_ctrl.kinematics import end_point

    ours = tuple(actuation.motor_ids)
    if tuple(log.motor_ids) != ours:
        raise RunLogError(
            f"{log.record_path}: the run's {len(log.motor_ids)} motors are not the robot "
            f"description's {len(ours)} ({', '.join(ours[:3])}, ...)"
        )
    s = log.stream(stream)
    tgt, act = log.target[s], log.actual[s]
    planned = np.full_like(tgt, np.nan)
    planned[lag:] = tgt[:-lag] if lag else tgt
    pa, pt = joint_angles(actuation, planned)
    ma, mt = joint_angles(actuation, act)
    err = np.nanmax(np.abs(np.concatenate([pa - ma, pt - mt], axis=1)), axis=1, initial=-1.0)
    err = np.where(err < 0, np.nan, err)
    model = actuation.robot
    ok = np.isfinite(pa).all(axis=1) & np.isfinite(ma).all(axis=1)
    tip = np.full(pa.shape[0], np.nan)
    if ok.any():
        tip[ok] = np.linalg.norm(
            end_point(model, pa[ok], pt[ok]) - end_point(model, ma[ok], mt[ok]), axis=-1
        )
    with np.errstate(invalid="ignore"):
        cerr = np.nanmax(np.abs(planned - act), axis=1, initial=-1.0)
    cerr = np.where(cerr < 0, np.nan, cerr)
    tt = tn = None
    tp = tension_path(log.record_path)
    if tensions is not None:
        tt, tn = np.asarray(tensions[0], np.float64), np.asarray(tensions[1], np.float64)
    elif tp.exists():
        t_unix, tens = tension_csv(tp, log.motor_ids)
        t_rel = t_unix - log.t0_unix
        keep = (t_rel >= log.t_s[s][0] - 1.0) & (t_rel <= log.t_s[s][-1] + 1.0)
        tt, tn = t_rel[keep], tens[keep]
    return RunAnalysis(
        t_s=log.t_s[s],
        planned_alpha=pa,
        planned_theta=pt,
        measured_alpha=ma,
        measured_theta=mt,
        angle_error_rad=err,
        tip_error_mm=tip,
        counts_error=cerr,
        lateness_s=log.sync_lateness_s()[s],
        tension_t_s=tt,
        tension_N=tn,
    )


def _png(fig: Figure) -> bytes:
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)
    return buf.getvalue()


def write_run_figures(a: RunAnalysis, out_dir: str | Path, title: str = "") -> list[Path]:
    """Write ``angles.png``, ``tracking.png`` and ``lateness.png`` (:data:`FIGURE_NAMES`)
    into ``out_dir`` (created if missing), all drawn first.  A write that fails raises
    ``OSError`` after removing the figures this call wrote (and ``out_dir`` if it made it)."""
    pngs = render_run_figures(a, title)
    out = Path(out_dir)
    made = [d for d in (out, *out.parents) if not os.path.lexists(d)]
    written: list[Path] = []
    try:
        out.mkdir(parents=True, exist_ok=True)
        for name, data in zip(FIGURE_NAMES, pngs, strict=True):
            write_atomic(out / name, data, make_parents=False)
            written.append(out / name)
    except BaseException:
        for f in written:
            with contextlib.suppress(OSError):
                f.unlink()
        for d in made:  # deepest first
            with contextlib.suppress(OSError):
                d.rmdir()
        raise
    return written


def render_run_figures(a: RunAnalysis, title: str = "") -> list[bytes]:
    """The PNGs of :data:`FIGURE_NAMES`, in that order."""
    pngs = []
    t = a.t_s - (a.t_s[0] if a.t_s.size else 0.0)
    fig = Figure(figsize=(11.0, 7.0), layout="constrained")
    axes = fig.subplots(2, 1, sharex=True)
    for ax, name, planned, measured in (
        (axes[0], "alpha", a.planned_alpha, a.measured_alpha),
        (axes[1], "theta", a.planned_theta, a.measured_theta),
    ):
        for j in range(planned.shape[1]):
            line = ax.plot(t, np.degrees(measured[:, j]), lw=1.0, label=f"joint {j + 1}")[0]
            ax.plot(t, np.degrees(planned[:, j]), lw=1.0, ls="--", color=line.get_color())
        ax.set_ylabel(f"{name} (deg)")
        ax.grid(alpha=0.3)
    axes[0].legend(ncol=6, fontsize=7, title="solid: measured, dashed: planned", title_fontsize=7)
    axes[1].set_xlabel("time (s)")
    fig.suptitle(f"{title} joint angles".strip())
    pngs.append(_png(fig))

    rows = 3 if a.tension_N is not None else 2
    fig = Figure(figsize=(11.0, 2.6 * rows + 1.0), layout="constrained")
    axes = fig.subplots(rows, 1, sharex=True)
    axes[0].plot(t, np.degrees(a.angle_error_rad), lw=1.0)
    axes[0].set_ylabel("largest joint-angle\nerror (deg)")
    axes[1].plot(t, a.tip_error_mm, lw=1.0, color="C1")
    axes[1].set_ylabel("tip error (mm)")
    if a.tension_N is not None and a.tension_t_s is not None:
        t_off = a.t_s[0] if a.t_s.size else 0.0
        axes[2].plot(a.tension_t_s - t_off, a.tension_N, lw=0.7)
        axes[2].set_ylabel("rope tension (N)")
    for ax in axes:
        ax.grid(alpha=0.3)
    axes[-1].set_xlabel("time (s)")
    fig.suptitle(f"{title} tracking (measured against planned)".strip())
    pngs.append(_png(fig))

    fig = Figure(figsize=(11.0, 4.5), layout="constrained")
    ax1, ax2 = fig.subplots(1, 2, width_ratios=[3, 1])
    ms = 1e3 * a.lateness_s
    ax1.plot(t, ms, lw=0.8)
    ax1.set_xlabel("time (s)")
    ax1.set_ylabel("SYNC interval - period (ms)")
    ax1.grid(alpha=0.3)
    if ms.size:
        ax2.hist(ms, bins=40)
    ax2.set_xlabel("ms")
    ax2.set_ylabel("cycles")
    fig.suptitle(f"{title} cycle lateness".strip())
    pngs.append(_png(fig))
    return pngs
