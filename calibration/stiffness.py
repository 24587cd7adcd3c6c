"""Rope stiffness (``hrm calibrate stiffness``, issue 12, part 3): each rope's axial
rigidity EA from tension against motor-position sweeps in the zero fixture.

In the fixture (every physical joint angle held at 0, :mod:`calibration.zero`) a rope's
tension depends on its own motor only.  The rope layer's model
(:mod:`hrm_ctrl.ropes.motor_map`): a rope of free length ``L`` under tension ``T`` has
the unstretched length ``u = L / (1 + T/EA)`` paid out, and the drum pays out
``u = u_z - x`` with ``x = d (c - z) / c_mm`` the rope wound in from the zero ``z``
(``d`` the motor's direction, ``c_mm`` its counts per mm).  So ``T = EA (L/u - 1)`` and

    dT/dx = EA L / u^2 = (EA + T)^2 / (EA L)          (with L/u = 1 + T/EA)

A straight line fitted through ``steps`` readings ``(x_i, T_i)`` has the slope ``b`` of
the curve at the readings' mean tension ``T_m`` (the curve is straight to 1e-3 over a
sweep of a few mm: its slope changes by ``2 dx/u``), hence, solving
``(EA + T_m)^2 = b EA L`` for EA (:func:`ea_from_slope`),

    EA = ((b L - 2 T_m) + sqrt((b L - 2 T_m)^2 - 4 T_m^2)) / 2  ~  b L - 2 T_m,

i.e. ``EA = slope_per_count * L * c_mm`` less twice the mean tension (0.2 % at 30 N).
``L`` is the straight arm's free length of the calibrated rope layer (box part + rope
geometry: :func:`calibration.zero.straight_free_length_mm`); an error of it enters EA
one to one (the description's links are +-2 mm: at most 1 % for joint 12's ropes).

Noise: each reading is the mean of ``n_samples`` frames (sigma 0.05 N per frame; at most
0.035 N for the mean, :mod:`calibration.zero`).  For ``m`` readings evenly over a sweep
spanning ``dT`` of tension the slope's relative standard deviation is ``sigma_mean
sqrt(12 (m - 1) / (m (m + 1))) / dT``: 0.44 % at the default ``dT`` = 10 N and 5 steps,
a tenth of the 5 % the rope layer's stretch compensation needs (and the fit's own
sigma is reported per rope).  The sweep for rope m spans ``sweep_N / k_m`` counts above
its zero, ``k_m`` the model's slope (:func:`calibration.zero.tension_slope_N_per_count`),
so every rope sweeps the same tension whatever its length (``sweep_counts`` overrides).

>>> from hrm_ctrl.ropes.motor_map import rope_tension_N
>>> L, EA = 1000.0, 25000.0
>>> x = np.linspace(0.0, 0.4, 5)                      # mm wound in from the zero
>>> T = rope_tension_N(L, L / (1 + 30.0 / EA) - x, EA)
>>> b, _ = np.polyfit(x, T, 1)
>>> round(float(b * L)), round(ea_from_slope(b, L, float(T.mean())))
(25070, 25000)
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration.zero import (
    DEFAULT_N_SAMPLES,
    DEFAULT_SPEED_COUNTS_PER_S,
    START_MARGIN_N,
    TAUT_N,
    FixtureMover,
    RopeTensionError,
    TensionGuard,
    TensionReader,
    fixture_offset_counts,
    groups_of,
    read_only,
    read_tensions,
    straight_free_length_mm,
    tension_slope_N_per_count,
)
from drivers.session import DriveSession
from hrm_ctrl.errors import CalibrationError, HrmError
from hrm_ctrl.ropes.actuation import Actuation

DEFAULT_SWEEP_N = 10.0  # tension each sweep spans (model slope)
DEFAULT_STEPS = 5
MIN_TAUT_POINTS = 3
ZERO_TENSION_FRACTION = 0.2  # at its zero a rope must read within 20 % of the pretension
MAX_FIT_RMS_N = 0.25  # 5 frame sigmas: a worse line is not a rope following the model


@dataclass(frozen=True)
class StiffnessResult:
    """What :func:`estimate_rope_stiffness` found, per rope (the rope layer's order);
    ropes of joints not swept keep the rope layer's EA, with sigma NaN."""

    motor_ids: tuple[str, ...]
    EA_N: np.ndarray  # (n,)
    EA_sigma_N: np.ndarray  # (n,) from the linear fit's residuals
    before_EA_N: np.ndarray  # (n,) the rope layer's
    fit_rms_N: np.ndarray  # (n,) residual rms of the line
    mean_tension_N: np.ndarray  # (n,)
    slope_N_per_count: np.ndarray  # (n,) signed by direction
    sweep_counts: np.ndarray  # (n,) counts swept above the zero
    points: np.ndarray  # (n,) readings in the fit
    moves: int
    elapsed_s: float

    def __post_init__(self) -> None:
        read_only(self)

    def residuals(self) -> dict[str, float]:
        """The figures a calibration version keeps (``residuals``)."""
        ok = np.isfinite(self.EA_sigma_N)
        rel = self.EA_sigma_N[ok] / self.EA_N[ok]
        change = np.abs(self.EA_N / self.before_EA_N - 1.0)
        return {
            "max_rel_sigma_EA": float(rel.max()) if rel.size else 0.0,
            "max_fit_rms_N": float(np.nanmax(np.where(ok, self.fit_rms_N, np.nan)))
            if ok.any()
            else 0.0,
            "max_rel_change_EA": float(change.max()),
            "moves": float(self.moves),
        }


def ea_from_slope(slope_N_per_mm: float, free_length_mm: float, mean_tension_N: float) -> float:
    """EA (N) of a rope whose tension rises ``slope_N_per_mm`` per mm wound in at the mean
    tension ``mean_tension_N``: the root of ``(EA + T)^2 = b EA L`` near ``b L``.

    >>> round(ea_from_slope(30.06, 1000.0, 30.0), 1)       # (30000 + 30)^2 / 3e7 = 30.06
    30000.0
    """
    bL = float(slope_N_per_mm) * float(free_length_mm)
    T = float(mean_tension_N)
    p = bL - 2.0 * T
    disc = p * p - 4.0 * T * T
    if not (bL > 0 and p > 0 and disc >= 0):
        return math.nan
    return 0.5 * (p + math.sqrt(disc))


def fit_rope_EA(
    x_mm: np.ndarray, tension_N: np.ndarray, free_length_mm: float
) -> tuple[float, float, float, float]:
    """``(EA, sigma_EA, rms, slope per mm)`` of readings ``tension_N`` at ``x_mm`` wound in
    (a straight line; sigma from its residuals, ``dEA/db = L EA / (2 (EA + T) - b L)``)."""
    x = np.asarray(x_mm, dtype=float)
    T = np.asarray(tension_N, dtype=float)
    m = x.size
    xc = x - x.mean()
    sxx = float(xc @ xc)
    b = float(xc @ (T - T.mean())) / sxx
    fit = T.mean() + b * xc
    rss = float(((T - fit) ** 2).sum())
    rms = math.sqrt(rss / m)
    sigma_b = math.sqrt(rss / (m - 2) / sxx) if m > 2 else math.inf
    EA = ea_from_slope(b, free_length_mm, float(T.mean()))
    L = float(free_length_mm)
    denom = 2.0 * (EA + T.mean()) - b * L
    dEA_db = L * EA / denom if denom > 0 else math.inf
    return EA, abs(dEA_db) * sigma_b, rms, b


def estimate_rope_stiffness(
    session: DriveSession,
    tension: TensionReader,
    actuation: Actuation,
    *,
    sweep_counts: int | Sequence[int] | np.ndarray | None = None,
    steps: int = DEFAULT_STEPS,
    sweep_N: float = DEFAULT_SWEEP_N,
    zero_counts: Any = None,
    max_tension_N: float | None = None,
    speed_counts_per_s: float = DEFAULT_SPEED_COUNTS_PER_S,
    n_samples: int = DEFAULT_N_SAMPLES,
    joints: Sequence[int] | None = None,
    progress: Callable[[str], None] | None = None,
) -> StiffnessResult:
    """Sweep each rope group (of ``joints``, 0-based; default all), one group at a time,
    from its zero (``zero_counts``, default the rope layer's zero offsets: run the zero
    calibration first; in the fixture, which holds the rope geometry straight, the pretension
    count, :func:`calibration.zero.fixture_offset_counts`) over ``sweep_counts`` (default
    ``sweep_N`` of tension on the model's slope) in ``steps`` readings, fit each rope's EA
    (module docstring), and put the group back at its zero (after a refusal: where it
    started).  ``session`` is ENABLED and left so.  Refuses
    (:class:`~calibration.zero.RopeTensionError`, naming the rope) a rope that does not
    read near the pretension at its zero, a sweep that would pass ``max_tension_N``
    (default twice the pretension), too few taut readings or a line that does not fit."""
    t_start = time.monotonic()
    ids = actuation.motor_ids
    n = actuation.n_motors
    if not (isinstance(steps, int | np.integer) and 3 <= steps <= 50):
        raise CalibrationError(f"stiffness: steps must be an integer in 3..50, got {steps!r}")
    pre = float(actuation.routing.pretension_N)
    limit = 2.0 * pre if max_tension_N is None else float(max_tension_N)
    z = (
        np.asarray(actuation.motors.zero_offsets_counts, dtype=np.int64)
        if zero_counts is None
        else np.asarray(zero_counts, dtype=np.int64)
    )
    if z.shape != (n,):
        raise CalibrationError(f"stiffness: zero_counts must have {n} values, got {z.shape}")
    z = z + fixture_offset_counts(actuation)  # the zeros' counts in the fixture
    k_model = tension_slope_N_per_count(actuation, pre)
    d = np.asarray(actuation.motors.direction)
    if sweep_counts is None:
        if not (math.isfinite(sweep_N) and 1.0 <= sweep_N <= limit - pre):
            raise CalibrationError(
                f"stiffness: sweep_N must be in [1, {limit - pre:g}] N, got {sweep_N}"
            )
        span = np.rint(sweep_N / np.abs(k_model)).astype(np.int64)
    else:
        span = np.broadcast_to(np.asarray(sweep_counts, dtype=np.int64), (n,)).copy()
        if np.any(span < steps - 1):
            raise CalibrationError(f"stiffness: sweep_counts must be >= steps - 1 = {steps - 1}")
    rise = 1.5 * np.abs(k_model) * span  # a rope up to 1.5x stiffer than described
    L = straight_free_length_mm(actuation)
    cpm = np.asarray(actuation.motors.counts_per_mm, dtype=float)
    before = np.broadcast_to(np.asarray(actuation.routing.stiffness_EA_N, dtype=float), (n,)).copy()
    EA, sig = before.copy(), np.full(n, np.nan)
    rms, T_mean = np.full(n, np.nan), np.full(n, np.nan)
    slope, used = np.full(n, np.nan), np.zeros(n, dtype=np.int64)
    groups = groups_of(actuation, joints)

    first = read_tensions(tension, ids, n_samples=n_samples)
    limits = np.maximum(limit, first.tensions_N + START_MARGIN_N)
    with TensionGuard(session, tension, limits) as guard:
        mover = FixtureMover(
            session, tension, speed_counts_per_s=speed_counts_per_s,
            n_samples=n_samples, guard=guard, name="stiffness",
        )  # fmt: skip
        for g in groups:
            start = mover.held
            home = start.copy()
            home[g] = z[g]
            frac = np.arange(steps, dtype=np.float64) / (steps - 1)
            offsets = np.rint(frac[:, None] * span[g][None, :]).astype(np.int64) * d[g][None, :]
            readings = np.zeros((steps, len(g)))
            for s in range(steps):
                target = home.copy()
                target[g] = z[g] + offsets[s]
                mover.move(target)
                T = mover.read(g).tensions_N[g]
                for col, i in enumerate(g):
                    ii = int(i)
                    if s == 0 and abs(T[col] - pre) > ZERO_TENSION_FRACTION * pre:
                        _back(mover, start)
                        raise RopeTensionError(
                            f"stiffness: rope {actuation.motor_label(ii)} reads {T[col]:.1f} N "
                            f"at its zero ({int(z[ii])} counts in the fixture), not near the "
                            f"pretension {pre:g} N (run the zero calibration first)"
                        )
                    if T[col] > limits[ii] or (s == 0 and T[col] + rise[ii] > limits[ii]):
                        _back(mover, start)
                        raise RopeTensionError(
                            f"stiffness: rope {actuation.motor_label(ii)}: the sweep would pass "
                            f"{limits[ii]:g} N (reads {T[col]:.1f} N)"
                        )
                readings[s] = T
            mover.move(home)
            for col, i in enumerate(g):
                ii = int(i)
                taut = readings[:, col] >= TAUT_N
                if int(taut.sum()) < MIN_TAUT_POINTS:
                    raise RopeTensionError(
                        f"stiffness: rope {actuation.motor_label(ii)}: {int(taut.sum())} of "
                        f"{steps} readings taut (>= {TAUT_N:g} N)"
                    )
                x_mm = np.abs(offsets[:, col]).astype(float) / cpm[ii]
                ea, s_ea, r, b = fit_rope_EA(x_mm[taut], readings[taut, col], float(L[ii]))
                if not (math.isfinite(ea) and r <= MAX_FIT_RMS_N):
                    raise RopeTensionError(
                        f"stiffness: rope {actuation.motor_label(ii)}: tension does not follow "
                        f"the sweep (slope {b:.4g} N/mm, residual rms {r:.3f} N)"
                    )
                EA[ii], sig[ii], rms[ii] = ea, s_ea, r
                T_mean[ii] = float(readings[taut, col].mean())
                slope[ii] = d[ii] * b / cpm[ii]
                used[ii] = int(taut.sum())
            if progress is not None:
                j = int(actuation.joint_of_motor[g[0]]) + 1
                text = " ".join(
                    f"{ids[i]} {EA[i] / 1000.0:.2f}+-{sig[i] / 1000.0:.2f} kN" for i in g
                )
                progress(f"joint {j:2d}: EA {text}")
    return StiffnessResult(
        motor_ids=tuple(ids),
        EA_N=EA,
        EA_sigma_N=sig,
        before_EA_N=before,
        fit_rms_N=rms,
        mean_tension_N=T_mean,
        slope_N_per_count=slope,
        sweep_counts=span,
        points=used,
        moves=mover.moves,
        elapsed_s=time.monotonic() - t_start,
    )


def _back(mover: FixtureMover, start: np.ndarray) -> None:
    """Before a refusal: the group back to where it started, when the session can still
    move."""
    try:
        if mover.session.enabled:
            mover.move(start)
    except HrmError:
        pass
