"""Console commands that play plans: ``run PLAN`` and ``return``.

``run PLAN`` turns the plan into the motors' checked counts (as ``hrm run``: collision
refused, time-parameterised within every motor's limits at ``--speed``) and plays it as a
:class:`drivers.sources.PausableSource`: at a terminal with a progress bar and a live line
(travel, tip error against the plan, worst tension, bus load, late cycles) and keys
(``p``/space pause and resume on the path, ``a`` abort: stop on the path and end, Ctrl-C:
quick stop of every axis, which says where it stopped); in a script ``--pause-at 30%
--resume-after 1s`` and ``--abort-at 60%`` do the same.  At the end it writes the run's
figures (planned vs measured angles, tracking error and tensions, from samples the console
took at 10 Hz; ``hrm report`` draws them from the CAN log once the session is closed) and
prints where, and after a stop or an abort which way back there is.  ``return`` backs
out along the last run's path to where it started, from where the drives' feedback says the
arm is (:func:`hrm_ctrl.runtime.wayback.way_back`: the nearest point of the path, joined by
a straight move in joint space, the join and the path back checked against the plan's
environment), also after a quick stop (Ctrl-C, a safety stop) and a return that stopped.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path
from typing import Any

import numpy as np

from hrm_ctrl.cli._console.context import ConsoleContext
from hrm_ctrl.cli._console.table import ConsoleError, Need, command, complete_paths
from hrm_ctrl.errors import HrmError

LAST_PLAYED = "last_played"  # ctx.extra key: what the last run played (for ``return``)
SURROUNDINGS = "surroundings"  # ctx.extra key: the environment of the last run's plan
RUN_USAGE = (
    "run PLAN [--speed MM_S] [--pause-at F%] [--resume-after S] [--abort-at F%] "
    "[--allow-collision] [--no-figures]"
)


class _Parser(argparse.ArgumentParser):
    def error(self, message: str) -> Any:  # one line, no exit
        raise ConsoleError(f"{message} (usage: {RUN_USAGE})")


def _run_parser() -> argparse.ArgumentParser:
    """The options of ``run PLAN``: the run controls of ``hrm run``, and ``--no-figures``."""
    from hrm_ctrl.cli._options import add_run_controls

    p = _Parser(prog="run", add_help=False)
    p.add_argument("plan", type=Path, help="plan to play (PLAN.json)")
    add_run_controls(p)  # --speed, --pause-at, --resume-after, --abort-at, --allow-collision
    p.add_argument(
        "--no-figures", action="store_true",
        help="write no figures of the run at its end",
    )  # fmt: skip
    return p


def _complete_run(ctx: ConsoleContext, words: list[str]) -> list[str]:
    if len(words) == 2:
        return complete_paths(words[-1])
    return [o for a in _run_parser()._actions for o in a.option_strings]


def _play_pausable(
    ctx: ConsoleContext, source: Any, sp: Any, what: str, script: Any, note: Any = None
) -> Any:
    """Play ``source`` with the keys, the script, the bar and the live line; return
    (result, driver, display).  A stop names where it happened.  ``note(driver, where)``,
    when given, is called however the play ends (a stop, a signal: the run record keeps
    what was played and where it stopped)."""
    from hrm_ctrl.cli._console.streaming import play
    from hrm_ctrl.cli._progress import ProgressBar
    from hrm_ctrl.cli._runcontrol import RunDisplay, RunDriver

    display = RunDisplay(source, sp, ctx.session, ctx.model, ctx.watches)
    with ProgressBar(what, enabled=ctx.interactive) as bar:
        driver = RunDriver(source, script, keys=ctx.interactive, display=display, bar=bar)
        driver.start()
        try:
            result = play(ctx, source, what)
        except ConsoleError as exc:
            raise ConsoleError(f"{exc} (at {display.where_text()})") from None
        finally:
            driver.stop()
            if note is not None:
                note(driver, display.where_text())
    return result, driver, display


def _note_run(ctx: ConsoleContext, source: Any, plan: str, where: str, driver: Any) -> None:
    """What the session's run record keeps of a console run (``console_runs``)."""
    extra = ctx.session.record_extra
    runs = extra.setdefault("console_runs", [])
    runs.append({
        "plan": plan,
        **source.describe(),
        "where": where,
        "run_control": [{"action": x, "fraction": round(f, 4)} for x, f in driver.events],
    })  # fmt: skip


def _figures(ctx: ConsoleContext, driver: Any, n: int) -> list[Path]:
    """The run's figures from the driver's samples, into the runs folder."""
    from hrm_ctrl.formats.runlog import RunLog
    from hrm_ctrl.formats.runplots import run_analysis, write_run_figures

    rows = [s for s in driver.samples if s[1] is not None]
    if len(rows) < 2:
        return []
    t = np.array([r[0] for r in rows])
    target = np.array([r[1] for r in rows], dtype=np.float64)
    actual = np.array([r[2] for r in rows], dtype=np.float64)
    name = f"{getattr(ctx.session, 'run_name', 'run')}_run{n}"
    folder = ctx.runs_dir / f"{name}_report"
    log = RunLog(
        record_path=ctx.runs_dir / f"{name}.json",
        record={"run": name},
        motor_ids=tuple(ctx.actuation.motor_ids),
        period_s=float(np.median(np.diff(t))),
        t0_unix=float(t[0]),
        t_s=t - t[0],
        target=target,
        actual=actual,
        streams=[(0, len(t))],
        frames=[],
    )
    tens = [(r[0] - t[0], r[3]) for r in rows if r[3] is not None]
    tensions = None
    if tens:
        tensions = (np.array([x[0] for x in tens]), np.array([x[1] for x in tens]))
    analysis = run_analysis(log, ctx.actuation, lag=0, tensions=tensions)
    return write_run_figures(analysis, folder, title=name)


@command("run", "play a plan (progress bar, live line; keys: p pause/resume, a abort, Ctrl-C "
         "stop) and write its figures", RUN_USAGE, needs=Need.ENABLED,
         complete=_complete_run)  # fmt: skip
def _run(ctx: ConsoleContext, args: list[str]) -> None:
    from drivers.safety.limits import MAX_SOURCE_DURATION_S
    from drivers.sources import CountsSource, PausableSource
    from hrm_ctrl.cli._progress import ProgressBar
    from hrm_ctrl.cli._runcontrol import RunScript
    from hrm_ctrl.formats.planfile import read_plan
    from hrm_ctrl.runtime.playback import refuse_collision, setpoints_of_plan

    a = _run_parser().parse_args(args)
    if not (math.isfinite(a.speed) and a.speed > 0):
        raise ConsoleError(f"--speed must be > 0 mm/s, got {a.speed}")
    script = RunScript.from_args(a)
    if script.pause_at is not None and script.resume_after_s is None and not ctx.interactive:
        # a script's keys are its lines, read between commands: nothing would resume it
        raise ConsoleError(
            "--pause-at without --resume-after in a script: nothing could resume the run (it "
            "would stand paused until it is aborted); give --resume-after"
        )
    doc = read_plan(a.plan)
    refuse_collision(doc, a.allow_collision, ctx.actuation.robot)
    period_s = ctx.config.control.period_s
    with ProgressBar("time parameterisation", enabled=ctx.interactive) as bar:
        sp = setpoints_of_plan(
            doc, ctx.actuation, period_s=period_s, speed_mm_per_s=a.speed,
            max_duration_s=MAX_SOURCE_DURATION_S, progress=bar,
        )  # fmt: skip
        bar(1.0)
    info = {"plan": str(a.plan), "steps": sp.n_steps, "speed_mm_per_s": sp.speed_mm_per_s}
    inner = CountsSource.of_plan(ctx.actuation, sp, info=info)
    source = PausableSource(inner, ctx.actuation)
    n = int(ctx.extra.get("runs_played", 0)) + 1
    ctx.extra["runs_played"] = n

    def note(driver: Any, where: str) -> None:
        _note_run(ctx, source, str(a.plan), where, driver)

    from hrm_ctrl.runtime.wayback import surroundings_of_plan

    ctx.extra[SURROUNDINGS] = surroundings_of_plan(doc, ctx.actuation.robot)
    held = ctx.session.supervisor.targets
    start = np.asarray(sp.counts[0] if held is None else held, dtype=np.int64).copy()
    try:
        result, driver, display = _play_pausable(ctx, source, sp, "run", script, note)
    except ConsoleError:  # a stop: the way back along the path stays
        _keep_way_back(ctx, str(a.plan), sp, source, inner, a, start)
        _say_ways_back(ctx)
        raise
    except BaseException:  # a signal: kept as well (the console ends)
        _keep_way_back(ctx, str(a.plan), sp, source, inner, a, start)
        raise
    _keep_way_back(ctx, str(a.plan), sp, source, inner, a, start)
    state = source.state.value
    where = display.where_text()
    if state == "aborted":
        ctx.out(f"run {a.plan}: {source.abort_reason}: stopped on the path at {where}; "
                f"{result.cycles} cycles")  # fmt: skip
        _say_ways_back(ctx)
    else:
        ctx.out(f"run {a.plan}: done, {result.cycles} cycles ({result.cycles * period_s:.2f} s), "
                f"paused {source.paused_cycles * period_s:.2f} s")  # fmt: skip
    if not a.no_figures:
        try:
            figs = _figures(ctx, driver, n)
        except (HrmError, OSError, ValueError) as exc:
            ctx.err(f"run: figures not written: {exc}")
            return
        if figs:
            ctx.out(f"figures: {figs[0].parent} ({', '.join(p.name for p in figs)})")


def _keep_way_back(
    ctx: ConsoleContext,
    plan: str,
    sp: Any,
    source: Any,
    inner: Any,
    a: argparse.Namespace,
    start: np.ndarray,
) -> None:
    """What ``return`` needs of a run: its plan's setpoints, how far it played (a row of
    the plan's table), where it started (``start``, counts), its speed and whether it was
    let collide."""
    played = max(0.0, float(source.position) - float(inner.n_lead_in))
    ctx.extra[LAST_PLAYED] = {"plan": plan, "setpoints": sp, "played_row": played,
                              "start_counts": start,
                              "speed_mm_per_s": float(a.speed),
                              "allow_collision": bool(a.allow_collision)}  # fmt: skip


def _say_ways_back(ctx: ConsoleContext) -> None:
    """One line after a run that ended early: which way back there is (``return`` along
    the path; ``home`` where a straight move in joint space stays clear of the
    environment the console knows)."""
    last = ctx.extra.get(LAST_PLAYED)
    ways = []
    if last is not None:
        ways.append(f"'return' backs out along the path of {last['plan']}")
    ways.append(_home_verdict(ctx, ctx.session.supervisor.targets))
    ctx.out(f"way back (once enabled): {'; '.join(ways)}")


def _home_verdict(ctx: ConsoleContext, held: Any) -> str:
    """``home`` from ``held`` in words: clear, refused (where it would hit), or not
    checked (no environment known)."""
    from hrm_ctrl.runtime.wayback import straight_home_clearance

    known = ctx.extra.get(SURROUNDINGS)
    if known is None:
        return "'home' (no environment known: its clearance is not checked)"
    if held is None:
        return "'home' (where the arm is not known yet)"
    try:
        c, at = straight_home_clearance(ctx.actuation, known, held)
    except HrmError as exc:
        return f"'home' not possible: {exc}"
    if c.least_mm < 0.0:
        return (f"'home' refused: its straight move in joint space meets an obstacle of "
                f"{known.source} (link {c.link}, {100 * at:.0f} % of the way)")  # fmt: skip
    return f"'home' is clear of {known.source} (least clearance {c.least_mm:.1f} mm)"


@command("return", "back out along the last run's path to where it started, from where the "
         "arm is (after a stop too): joined to the nearest point of the path, checked against "
         "the plan's environment", "return", needs=Need.ENABLED)  # fmt: skip
def _return(ctx: ConsoleContext, args: list[str]) -> None:
    from drivers.sources import CountsSource, PausableSource
    from hrm_ctrl.cli._console.streaming import play
    from hrm_ctrl.cli._runcontrol import RunScript
    from hrm_ctrl.runtime.wayback import return_setpoints, way_back

    if args:
        raise ConsoleError("usage: return")
    last = ctx.extra.get(LAST_PLAYED)
    if last is None:
        raise ConsoleError("no run to return from (run a plan first)")
    held = ctx.session.supervisor.targets
    if held is None:
        raise ConsoleError("the drives hold no known position (enable first)")
    back = way_back(ctx.actuation, last["setpoints"], held, last["played_row"],
                    ctx.extra.get(SURROUNDINGS), start_counts=last["start_counts"],
                    allow_collision=last["allow_collision"])  # fmt: skip
    ctx.out(f"return: {back.describe()}")
    period_s = ctx.config.control.period_s
    sp = return_setpoints(ctx.actuation, back, period_s=period_s,
                          speed_mm_per_s=last["speed_mm_per_s"],
                          where=f"return along {last['plan']}")  # fmt: skip
    info = {"plan": last["plan"], "joined_at_row": back.row, "steps": back.n_steps}
    inner = CountsSource.of_plan(ctx.actuation, sp, name="return", info=info)
    source = PausableSource(inner, ctx.actuation)
    # a return that stops leaves the arm on the same path: the run's way back stays
    result, _driver, _display = _play_pausable(ctx, source, sp, "return",
                                               RunScript(None, None, None))  # fmt: skip
    if source.state.value == "aborted":
        ctx.out(f"return: {source.abort_reason}: stopped on the way back; {result.cycles} cycles")
        return
    cycles = result.cycles
    if back.lead_out_blocked is not None and not last["allow_collision"]:
        ctx.extra[LAST_PLAYED] = None
        ctx.out(f"return: back at the first step of {last['plan']}, {cycles} cycles "
                f"({cycles * period_s:.2f} s); not on to where the run started: that straight "
                f"move in joint space {back.lead_out_blocked}")  # fmt: skip
        return
    if not np.array_equal(np.asarray(ctx.session.supervisor.targets), back.start_counts):
        # the run's lead-in, reversed: a straight move in joint space to where it started
        lead = CountsSource(ctx.actuation, back.start_counts[None, :], period_s, name="return",
                            hold_s=0.1, first_pose=back.start_pose, info=info)  # fmt: skip
        cycles += play(ctx, lead, "return").cycles
    ctx.extra[LAST_PLAYED] = None
    ctx.out(f"return: back at the start of {last['plan']}, {cycles} cycles "
            f"({cycles * period_s:.2f} s)")  # fmt: skip


def _check_lines(ctx: ConsoleContext, path: Path, speed: float) -> tuple[list[str], int]:
    """The lines of ``check`` and how many problems they name."""
    from drivers.safety.limits import MAX_SOURCE_DURATION_S
    from hrm_ctrl.formats.planfile import read_plan
    from hrm_ctrl.planning.report import clearance_summary, plan_file_clearance
    from hrm_ctrl.runtime.playback import setpoint_summary as summary
    from hrm_ctrl.runtime.playback import setpoints_of_plan

    doc = read_plan(path)
    model = ctx.actuation.robot
    lines: list[str] = []
    bad = 0
    a = np.abs(np.asarray(doc.alpha_rad, dtype=float))
    t = np.abs(np.asarray(doc.theta_rad, dtype=float))
    margin = np.minimum(model.limit_alpha - a, model.limit_theta - t)
    k, j = np.unravel_index(int(np.argmin(margin)), margin.shape)
    m_deg = float(np.degrees(margin[k, j]))
    bad += m_deg < 0
    lines.append(f"joint limits: {'BROKEN' if m_deg < 0 else 'ok'}, least margin {m_deg:.2f} deg "
                 f"(step {k}, joint {j + 1})")  # fmt: skip
    try:
        sp = setpoints_of_plan(
            doc, ctx.actuation, period_s=ctx.config.control.period_s,
            speed_mm_per_s=speed, max_duration_s=MAX_SOURCE_DURATION_S,
        )  # fmt: skip
    except HrmError as exc:
        lines.append(f"rope travel, motor speed and acceleration: BROKEN: {exc}")
        bad += 1
    else:
        s = summary(ctx.actuation, sp)
        act = ctx.actuation
        span = np.maximum(np.asarray(act.counts_max) - np.asarray(act.counts_min), 1)
        lo = [
            min(m["min_counts"] - int(act.counts_min[i]), int(act.counts_max[i]) - m["max_counts"])
            for i, m in enumerate(s["motors"])
        ]
        i = int(np.argmin(lo))
        share = 100.0 * lo[i] / span[i]
        lines.append(f"rope travel: ok, closest to a drum end: {s['motors'][i]['motor']} "
                     f"{lo[i]} counts ({share:.1f} % of its range) away")  # fmt: skip
        for key, lim, what in (
            ("peak_rate_counts_per_s", "rate_limit_counts_per_s", "motor speed"),
            ("peak_accel_counts_per_s2", "accel_limit_counts_per_s2", "motor acceleration"),
        ):
            share = [m[key] / m[lim] for m in s["motors"]]
            i = int(np.argmax(share))
            lines.append(f"{what}: ok, peak {100.0 * share[i]:.1f} % of the limit "
                         f"({s['motors'][i]['motor']})")  # fmt: skip
        pb = s["playback"]
        lines.append(f"playback: {pb['duration_s']:.2f} s, {pb['cycles']} cycles at up to "
                     f"{pb['speed_mm_per_s']:g} mm/s")  # fmt: skip
    c = plan_file_clearance(doc, model=model)
    if c is None:
        lines.append("clearance: no environment in the plan (not checked)")
    else:
        cs = clearance_summary(c)
        if cs["min"] is None:
            lines.append("clearance: no link near an obstacle")
        else:
            neg = cs["min"] < 0.0
            bad += neg
            lines.append(f"clearance: {'COLLISION' if neg else 'ok'}, least {cs['min']:.2f} mm "
                         f"(step {cs['step']}, link {cs['link']})")  # fmt: skip
    return lines, int(bad)


@command("check", "check a plan before running it: joint limits, rope travel, motor speed and "
         "acceleration, clearance where the plan knows its environment",
         "check PLAN [SPEED_MM_S]",
         complete=_complete_run)  # fmt: skip
def _check(ctx: ConsoleContext, args: list[str]) -> None:
    from hrm_ctrl.ropes.setpoints import DEFAULT_TIP_SPEED_MM_PER_S

    if not 1 <= len(args) <= 2:
        raise ConsoleError("usage: check PLAN [SPEED_MM_S]")
    try:
        speed = float(args[1]) if len(args) == 2 else DEFAULT_TIP_SPEED_MM_PER_S
    except ValueError:
        raise ConsoleError(f"SPEED_MM_S {args[1]!r}: a number") from None
    if not (math.isfinite(speed) and speed > 0):
        raise ConsoleError(f"SPEED_MM_S must be > 0, got {args[1]}")
    lines, bad = _check_lines(ctx, Path(args[0]), speed)
    for line in lines:
        ctx.out(line)
    if bad:
        raise ConsoleError(f"{args[0]}: {bad} problem(s) (see above)")
    ctx.out(f"{args[0]}: ok to run at up to {speed:g} mm/s")


@command("plan", "plan a path as 'hrm plan' does (same arguments)", "plan ARGS... (as hrm plan)")
def _plan(ctx: ConsoleContext, args: list[str]) -> None:
    import contextlib
    import io

    from hrm_ctrl.cli import plan as plan_cli

    p = _Parser(prog="plan", add_help=False)
    plan_cli.register(p)
    try:
        parsed = p.parse_args(args)
    except ConsoleError as exc:
        raise ConsoleError(str(exc).replace(RUN_USAGE, "as hrm plan")) from None
    if ctx.script_path is not None:  # --out or --plot over the script being run: refused
        from hrm_ctrl.cli._common import Input

        parsed.extra_inputs = [Input("console script", ctx.script_path)]
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        status = plan_cli.run(parsed)
    for line in out.getvalue().splitlines():
        ctx.out(line)
    for line in err.getvalue().splitlines():
        ctx.err(line)
    if status:
        raise ConsoleError(f"exit status {status}")
