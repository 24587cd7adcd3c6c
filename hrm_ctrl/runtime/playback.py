"""A plan to what the drives play: checked setpoints, a setpoint source, the collision gate.

The one plan -> counts path of ``hrm ropes``, ``hrm run``, ``hrm view --live``, the
console and the benchmarks: :func:`setpoints_of_plan` (the rope layer's
:func:`hrm_ctrl.ropes.setpoints.plan_setpoints` for the arm that plays it),
:func:`refuse_collision` before anything is sent, and :func:`setpoint_source`: the source
a run asks for (a plan, a hold, or a jog) as :class:`Playback`.

>>> parse_jog("j01r0:20000:0.2")
('j01r0', 20000.0, 0.2)
>>> parse_jog("j01r0:fast")
Traceback (most recent call last):
...
hrm_ctrl.errors.DriverError: --jog 'j01r0:fast': expected MOTOR:COUNTS_PER_S:SECONDS
"""

from __future__ import annotations

import hashlib
import math
import sys
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from hrm_ctrl.errors import DriverError

if TYPE_CHECKING:
    from drivers.sources import SetpointSource
    from hrm_ctrl.formats.planfile import PlanDoc
    from hrm_ctrl.model import RobotModel
    from hrm_ctrl.ropes.actuation import Actuation
    from hrm_ctrl.ropes.estimator import Compensation
    from hrm_ctrl.ropes.setpoints import PlanSetpoints


def setpoints_of_plan(
    doc: PlanDoc,
    act: Actuation,
    *,
    period_s: float,
    speed_mm_per_s: float,
    max_duration_s: float | None = None,
    progress: Callable[[float], None] | None = None,
    compensate: bool = False,
) -> PlanSetpoints:
    """The plan's checked counts at the control rate for this arm: what ``hrm ropes``
    reports and ``hrm run`` plays (``max_duration_s`` None:
    :data:`hrm_ctrl.ropes.setpoints.MAX_PLAN_DURATION_S`).  Refuses a plan made for other
    link lengths; every message starts with the plan file.  ``compensate``: the counts
    that hold each configuration against the arm's loads
    (:class:`hrm_ctrl.ropes.feedforward.Feedforward` of the description's ``[physics]``)."""
    from hrm_ctrl.ropes.feedforward import Feedforward
    from hrm_ctrl.ropes.setpoints import MAX_PLAN_DURATION_S, plan_setpoints

    if max_duration_s is None:
        max_duration_s = MAX_PLAN_DURATION_S

    doc.check_robot(act.robot)
    return plan_setpoints(
        act,
        doc.travel_mm,
        doc.alpha_rad,
        doc.theta_rad,
        phase=doc.phase,
        period_s=period_s,
        speed_mm_per_s=speed_mm_per_s,
        max_duration_s=max_duration_s,
        where=doc.source,
        progress=progress,
        feedforward=Feedforward.of(act) if compensate else None,
    )


def setpoint_summary(act: Actuation, sp: PlanSetpoints) -> dict[str, Any]:
    """Largest travel and step-to-step change per motor (counts and mm of rope) over the
    plan's steps, and the playback at the control rate (duration, cycles, peak motor
    speed, acceleration and jerk: finite differences of the counts sent, from and to
    rest; and what the jerk bound costs: the duration without it)."""
    import numpy as np

    from hrm_ctrl.ropes.trajectory import finite_differences, finite_jerk

    travel, counts = sp.travel_mm, sp.step_counts
    cpm = act.motors.counts_per_mm
    rates, accels = finite_differences(sp.counts, sp.period_s)
    jerks = finite_jerk(sp.counts, sp.period_s)
    j_limit = np.asarray(act.max_jerk_counts_per_s3, dtype=np.float64)
    limit = np.asarray(act.max_rate_counts_per_s, dtype=np.float64)
    a_limit = np.asarray(act.max_accel_counts_per_s2, dtype=np.float64)
    rel = counts - act.motors.zero_offsets_counts
    k_travel = np.abs(rel).argmax(axis=0)
    diff = np.abs(np.diff(counts, axis=0)) if counts.shape[0] > 1 else np.zeros((1, act.n_motors))
    k_diff = diff.argmax(axis=0)
    motors = []
    for i, mid in enumerate(act.motor_ids):
        motors.append(
            {
                "motor": mid,
                "min_counts": int(counts[:, i].min()),
                "max_counts": int(counts[:, i].max()),
                "largest_travel_counts": int(rel[k_travel[i], i]),
                "largest_travel_mm": float(act.motors.direction[i] * rel[k_travel[i], i] / cpm[i]),
                "largest_travel_step": int(k_travel[i]),
                "largest_change_counts": int(diff[k_diff[i], i]),
                "largest_change_mm": float(diff[k_diff[i], i] / cpm[i]),
                "largest_change_step": int(k_diff[i]) + 1 if counts.shape[0] > 1 else 0,
                "peak_rate_counts_per_s": float(rates[i]),
                "rate_limit_counts_per_s": float(limit[i]),
                "peak_accel_counts_per_s2": float(accels[i]),
                "accel_limit_counts_per_s2": float(a_limit[i]),
                "peak_jerk_counts_per_s3": float(jerks[i]),
                "jerk_limit_counts_per_s3": float(j_limit[i]),
            }
        )
    return {
        "steps": int(counts.shape[0]),
        "motors": motors,
        "travel_mm": [float(travel[0]), float(travel[-1])],
        "playback": {
            "speed_mm_per_s": sp.speed_mm_per_s,
            "period_s": sp.period_s,
            "duration_s": round(sp.duration_s, 9),
            "cycles": sp.n_cycles,
            # the jerk bound's cost: the playback without it (TOPP-RA alone) and the difference
            "duration_without_jerk_bound_s": round(sp.law_duration_s, 9),
            "jerk_bound_cost_s": round(sp.jerk_cost_s, 9),
        },
    }


def refuse_collision(
    doc: PlanDoc, allow: bool, model: RobotModel | None = None, *, prog: str = "hrm run"
) -> None:
    """Refuse (one line naming step and link) a plan whose arm meets an obstacle: its
    stored clearance (``report.clearance_mm``), and the clearance recomputed against the
    environment it stores, of the stored joint centres and of the joints its angles put
    ``model``'s arm at (the robot that plays it: an edited summary or edited joint centres
    cannot hide a collision).  With ``allow`` (``--allow-collision``) a warning line on
    stderr instead."""
    from hrm_ctrl.planning.report import check_clearance, clearance_summary, plan_file_clearance

    c = plan_file_clearance(doc, model=model)
    for summary in (doc.clearance, None if c is None else clearance_summary(c)):
        if summary is None:
            continue
        if not allow:
            check_clearance(dict(summary), doc.source)
        elif summary.get("min") is not None and summary["min"] < 0.0:
            print(
                f"{prog}: warning: {doc.source}: link {summary['link']} meets an obstacle at "
                f"step {summary['step']} (clearance {summary['min']:.2f} mm); played as "
                "--allow-collision asks",
                file=sys.stderr,
            )
            return


def plan_record(path: Path, plan: PlanDoc) -> dict[str, Any]:
    """What the run record keeps of the plan: file, sha256 of its bytes, format, steps."""
    from hrm_ctrl.formats.planfile import PLAN_FORMAT

    try:
        digest = hashlib.sha256(path.read_bytes()).hexdigest()
    except OSError as exc:
        raise DriverError(f"{path}: cannot read plan file ({exc.strerror or exc})") from None
    return {
        "plan_file": str(path),
        "plan_sha256": digest,
        "plan_format": PLAN_FORMAT,
        "plan_steps": plan.n_steps,
    }


def parse_jog(text: str) -> tuple[str, float, float]:
    """``MOTOR:COUNTS_PER_S:SECONDS`` (seconds > 0) as (motor, speed, seconds)."""
    parts = str(text).split(":")
    try:
        motor, vel, dur = parts[0], float(parts[1]), float(parts[2])
    except (IndexError, ValueError):
        raise DriverError(f"--jog {text!r}: expected MOTOR:COUNTS_PER_S:SECONDS") from None
    if len(parts) != 3 or not (math.isfinite(dur) and dur > 0):
        raise DriverError(f"--jog {text!r}: expected MOTOR:COUNTS_PER_S:SECONDS (S > 0)")
    return motor, vel, dur


@dataclass(frozen=True)
class Playback:
    """What a run plays: its ``source``, the hold time of a hold (s, else None), what the
    run record keeps of a plan (``plan_record``, else empty) and a plan's ``setpoints``
    (None for a hold or a jog)."""

    source: SetpointSource
    hold_s: float | None
    plan_record: dict[str, Any]
    setpoints: PlanSetpoints | None = None

    @property
    def compensation(self) -> Compensation | None:
        """What a feed-forward added to the plan's rows (None: nothing), for the rope
        consistency watch (:class:`hrm_ctrl.runtime.box.WatchOptions`) to take off."""
        from hrm_ctrl.ropes.estimator import Compensation

        sp = self.setpoints
        if sp is None or sp.compensation_counts is None:
            return None
        return Compensation.of(sp.counts, sp.compensation_counts)


def setpoint_source(
    actuation: Actuation,
    period_s: float,
    *,
    plan: Path | None = None,
    hold_s: float | None = None,
    jog: str | None = None,
    speed_mm_per_s: float,
    allow_collision: bool = False,
    progress: Callable[[float], None] | None = None,
    compensate: bool = False,
) -> Playback:
    """The setpoint source of exactly one of ``plan``, ``hold_s``, ``jog`` (else one line).
    A plan goes through the rope layer's one plan -> counts path (as in ``hrm ropes``) at
    the control period ``period_s``, refused first when its arm meets an obstacle
    (:func:`refuse_collision`), and is played by :class:`drivers.sources.CountsSource`."""
    from drivers.safety.limits import MAX_SOURCE_DURATION_S
    from drivers.sources import CountsSource, HoldSource, JogSource

    chosen = [x for x in (plan, hold_s, jog) if x is not None]
    if len(chosen) != 1:
        raise DriverError("give exactly one of PLAN.json, --hold S, --jog MOTOR:COUNTS_PER_S:S")
    if hold_s is not None:
        if not (math.isfinite(hold_s) and 0 < hold_s <= MAX_SOURCE_DURATION_S):
            raise DriverError(
                f"--hold must be > 0 s and at most {MAX_SOURCE_DURATION_S:g} s, got {hold_s}"
            )
        return Playback(HoldSource(n_cycles=None), hold_s, {})
    if jog is not None:
        motor, vel, dur = parse_jog(jog)
        return Playback(JogSource(actuation, motor, vel, dur), None, {})
    from hrm_ctrl.formats.planfile import read_plan

    assert plan is not None
    doc = read_plan(plan)
    refuse_collision(doc, allow_collision, actuation.robot)  # before anything is sent to a bus
    record = plan_record(Path(plan), doc)
    sp = setpoints_of_plan(
        doc,
        actuation,
        period_s=period_s,
        speed_mm_per_s=speed_mm_per_s,
        max_duration_s=MAX_SOURCE_DURATION_S,
        progress=progress,
        compensate=compensate,
    )
    info = {
        "plan": str(plan),
        "steps": sp.n_steps,
        "speed_mm_per_s": sp.speed_mm_per_s,
        "duration_s": sp.duration_s,
        "compensated": compensate,
    }
    return Playback(CountsSource.of_plan(actuation, sp, info=info), None, record, sp)
