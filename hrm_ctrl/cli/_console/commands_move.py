"""The console's small moves: ``jog JOINT AXIS DEG``, ``jog MOTOR COUNTS`` and ``home``.

Every move starts from what the drives hold, is checked against the joint, rope and
motor limits before anything is sent (one line naming the limit when it would leave
one), is jerk-limited (Ruckig: :func:`drivers.sources.move_table`,
:class:`~drivers.sources.JogSource`) or time-parameterised within every motor's limits
(``home``: :func:`hrm_ctrl.ropes.jog.home_setpoints`, its straight move in joint space
checked against the environment of the last run's plan), and is stopped by Ctrl-C.
"""

from __future__ import annotations

import math

import numpy as np

from hrm_ctrl.cli._console.context import ConsoleContext
from hrm_ctrl.cli._console.streaming import play
from hrm_ctrl.cli._console.table import ConsoleError, Need, command, parse_float, parse_int

# A jog moves at no more than this share of each motor's speed: a small move an operator
# watches (at the shipped motors' 409600 counts/s, 20480 counts/s: 9.5 mm of rope a second).
JOG_SPEED_FRACTION = 0.05
JOG_HOLD_S = 0.1  # held at the end of a jog before the stream ends (the drives settle)
HOME_SPEED_MM_S = 20.0  # the tip's speed cap of `home` unless given


def _held_and_actual(ctx: ConsoleContext) -> tuple[np.ndarray, np.ndarray]:
    """What the drives hold (the supervisor's targets) and where they are (by SDO)."""
    session = ctx.session
    held = session.supervisor.targets
    if held is None:
        raise ConsoleError("the drives hold no known position (enable first)")
    actual = session.actual_positions()
    return np.asarray(held, dtype=np.int64).copy(), actual


def _complete_jog(ctx: ConsoleContext, words: list[str]) -> list[str]:
    n_j = ctx.actuation.robot.n_joints
    if len(words) <= 2:
        return [str(j) for j in range(1, n_j + 1)] + list(ctx.actuation.motor_ids)
    if len(words) == 3 and words[1].isascii() and words[1].isdigit():
        return ["alpha", "theta"]
    return []


@command("jog", "a small jerk-limited move: one joint's angle by DEG (from the feedback), or "
         "one rope motor by COUNTS; refused when it would leave a joint, rope or motor limit",
         "jog JOINT alpha|theta DEG | jog MOTOR COUNTS", needs=Need.ENABLED,
         complete=_complete_jog)  # fmt: skip
def _jog(ctx: ConsoleContext, args: list[str]) -> None:
    from drivers.safety.limits import accel_limits, check_move, jerk_limits
    from drivers.sources import CountsSource, JogSource, at_samples, path_move
    from hrm_ctrl.ropes.jog import check_motor_jog, joint_jog

    act = ctx.actuation
    period_s = ctx.config.control.period_s
    if len(args) == 3:
        usage = "jog JOINT alpha|theta DEG (e.g. jog 5 theta +2)"
        joint, deg = parse_int(args[0], "JOINT", usage), parse_float(args[2], "DEG", usage)
        held, actual = _held_and_actual(ctx)
        jj = joint_jog(act, held, actual, joint, args[1], deg)
        v = np.asarray(act.max_rate_counts_per_s, dtype=np.float64)
        what = f"jog {joint} {jj.axis.value} {deg:+g} deg"
        if np.array_equal(jj.target_counts, held):  # rounds to no count of any rope
            ctx.out(f"{what}: nothing to move (less than one encoder count on every rope)")
            return
        # a line in joint space from the jog's start to its end, judged at its poses
        line = act.joint_line(held, jj.target_counts, from_pose=(jj.alpha_from, jj.theta_from),
                              to_pose=(jj.alpha_to, jj.theta_to))  # fmt: skip
        rows, x = path_move(line.counts, period_s, v, accel_limits(act), jerk_limits(act),
                            JOG_SPEED_FRACTION * v, what)  # fmt: skip
        body = np.vstack([held[None, :], rows])
        poses = (np.vstack([line.alpha[:1], at_samples(x, line.alpha)]),
                 np.vstack([line.theta[:1], at_samples(x, line.theta)]))  # fmt: skip
        check_move(act, body, what, poses)
        source = CountsSource(act, body, period_s, name="jog", hold_s=JOG_HOLD_S,
                              label=lambda r: f"{what}, cycle {r}",
                              info={"joint": joint, "axis": jj.axis.value, "deg": deg})  # fmt: skip
        angles = jj.alpha_from if jj.axis == "alpha" else jj.theta_from
        before = math.degrees(float(angles[joint - 1]))
        result = play(ctx, source, "jog")
        ctx.out(
            f"{what}: done, {result.cycles} cycles ({result.cycles * period_s:.2f} s); "
            f"joint {joint} {jj.axis.value} {before:.2f} -> {before + deg:.2f} deg"
        )
        return
    if len(args) == 2:
        motor = args[0]
        counts = parse_int(args[1], "COUNTS", "jog MOTOR COUNTS (e.g. jog j05r1 -800)")
        held = ctx.session.supervisor.targets
        if held is None:
            raise ConsoleError("the drives hold no known position (enable first)")
        i = check_motor_jog(act, motor, counts, held)
        speed = JOG_SPEED_FRACTION * float(act.max_rate_counts_per_s[i])
        source = JogSource(act, motor, math.copysign(speed, counts), abs(counts) / speed,
                           hold_s=JOG_HOLD_S, label=f"jog {motor} {counts:+d} counts")  # fmt: skip
        result = play(ctx, source, "jog")
        ctx.out(f"jog {motor} {counts:+d} counts: done, {result.cycles} cycles "
                f"({result.cycles * period_s:.2f} s)")  # fmt: skip
        return
    raise ConsoleError("usage: jog JOINT alpha|theta DEG | jog MOTOR COUNTS")


def _refuse_home_into_obstacle(ctx: ConsoleContext, held: np.ndarray) -> None:
    """``home``'s straight move in joint space checked against the environment the
    console knows (the last run's plan's): refused, naming the link and ``return``, where
    it would meet an obstacle."""
    from hrm_ctrl.cli._console.commands_run import LAST_PLAYED, SURROUNDINGS
    from hrm_ctrl.runtime.wayback import straight_home_clearance

    known = ctx.extra.get(SURROUNDINGS)
    if known is None:
        return
    c, at = straight_home_clearance(ctx.actuation, known, held)
    if c.least_mm >= 0.0:
        return
    other = ("; 'return' backs out along the path of " + ctx.extra[LAST_PLAYED]["plan"]
             if ctx.extra.get(LAST_PLAYED) else "")  # fmt: skip
    raise ConsoleError(
        f"home: refused: the straight move in joint space to the zero configuration meets "
        f"an obstacle of {known.source} (link {c.link}, clearance {c.least_mm:.1f} mm, "
        f"{100 * at:.0f} % of the way){other}"
    )


@command("home", "back to the calibrated zero configuration (the straight arm) by a "
         "checked, time-parameterised trajectory; refused where it would meet an obstacle "
         "of the last run's environment", "home [SPEED_MM_S]",
         needs=Need.ENABLED)  # fmt: skip
def _home(ctx: ConsoleContext, args: list[str]) -> None:
    from drivers.sources import CountsSource
    from hrm_ctrl.ropes.jog import home_setpoints

    if len(args) > 1:
        raise ConsoleError("usage: home [SPEED_MM_S]")
    speed = parse_float(args[0], "SPEED_MM_S", "home [SPEED_MM_S]") if args else HOME_SPEED_MM_S
    if not (math.isfinite(speed) and speed > 0):
        raise ConsoleError(f"SPEED_MM_S must be > 0, got {args[0]}")
    held, actual = _held_and_actual(ctx)
    period_s = ctx.config.control.period_s
    n_j = ctx.actuation.robot.n_joints
    zero = ctx.actuation.counts_from_angles(np.zeros(n_j), np.zeros(n_j), check=False)
    if np.array_equal(held, zero):  # a script's home where the arm is: not an error
        ctx.out("home: the arm is at its zero configuration already (nothing to move)")
        return
    _refuse_home_into_obstacle(ctx, held)
    sp = home_setpoints(ctx.actuation, actual, period_s=period_s, speed_mm_per_s=speed)
    source = CountsSource.of_plan(ctx.actuation, sp, name="home", info={"speed_mm_per_s": speed})
    result = play(ctx, source, "home")
    ctx.out(f"home: done, {result.cycles} cycles ({result.cycles * period_s:.2f} s) at up to "
            f"{speed:g} mm/s")  # fmt: skip
