"""Console commands over past runs: ``log`` (list them), ``log show RUN`` (one run's
summary), ``log replay RUN [--bus NAME=IF:CH]...`` (play a run's CAN logs onto buses).

A run is a run record (``hrm-run/1``) in the console's runs folder (``--log-dir``),
named by its file name with or without ``.json``, or by its number in the ``log`` list
(1 the newest).  ``log replay`` reads each bus's log with python-can's
:class:`can.LogReader` and sends it with :class:`can.MessageSync` (the log's own timing:
python-can's ``can.player`` semantics) onto the bus named by ``--bus`` (default: a
python-can virtual bus ``hrm-replay-<bus>``); a bus of this console's box (connected or
not) is refused, so a replay never commands a drive of this console's box.
"""

from __future__ import annotations

import datetime as dt
from pathlib import Path
from typing import Any

from hrm_ctrl.cli._console.context import ConsoleContext
from hrm_ctrl.cli._console.table import ConsoleError, command

MAX_RUNS_LISTED = 200  # run records read for ``log`` at most (the newest)
MAX_REPLAY_FRAMES = 30_000_000  # frames sent by one replay at most
REPLAY_CHANNEL = "hrm-replay-{bus}"
USAGE = "usage: log | log show RUN | log replay RUN [--bus NAME=INTERFACE:CHANNEL]..."


def run_records(runs_dir: Path, limit: int = MAX_RUNS_LISTED) -> list[Path]:
    """The run records in ``runs_dir``, newest first, at most ``limit``."""
    if not runs_dir.is_dir():
        return []
    found = []
    for p in runs_dir.glob("*.json"):
        try:
            found.append((p.stat().st_mtime, p))
        except OSError:
            continue
    found.sort(reverse=True)
    return [p for _t, p in found[:limit]]


def outcome(record: dict[str, Any]) -> tuple[str, str]:
    """(outcome, cause) of a run record: completed / aborted / stopped / none, and the
    first stop cause (or abort reason, or '')."""
    streams = _list(record.get("streams"))
    sp = _setpoints(record)
    if not streams:
        causes = _list(record.get("idle_stop_causes"))
        cause = causes[0].get("text", "") if causes and isinstance(causes[0], dict) else ""
        return ("stopped" if cause else "no stream"), str(cause)
    last = streams[-1] if isinstance(streams[-1], dict) else {}
    causes = _list(last.get("causes"))
    if causes:
        first = causes[0]
        return "stopped", str(first.get("text", first) if isinstance(first, dict) else first)
    if isinstance(sp, dict) and sp.get("play_state") == "aborted":
        return "aborted", str(sp.get("abort_reason") or "")
    return ("completed" if last.get("completed") else "ended"), ""


def _list(x: object) -> list[Any]:
    """``x`` if a record gave a list there, else empty (a damaged record is shown, not
    raised on)."""
    return x if isinstance(x, list) else []


def _count(x: object) -> str:
    """``x`` if a record gave a whole count there, else ``-``."""
    return str(x) if isinstance(x, int) and not isinstance(x, bool) else "-"


def _number(x: object) -> float | None:
    """``x`` if a record gave a number there (not a bool), else None."""
    return float(x) if isinstance(x, int | float) and not isinstance(x, bool) else None


def _setpoints(record: dict[str, Any]) -> dict[str, Any]:
    """The last plan run of a record: ``hrm run``'s ``setpoints``, or the console's last
    ``console_runs`` entry."""
    runs = record.get("console_runs")
    if isinstance(runs, list) and runs and isinstance(runs[-1], dict):
        return runs[-1]
    sp = record.get("setpoints")
    return sp if isinstance(sp, dict) else {}


def find_run(ctx: ConsoleContext, name: str) -> Path:
    """A run record by number in the ``log`` list, file name or path."""
    runs = run_records(ctx.runs_dir)
    if name.isdigit():
        k = int(name)
        if not 1 <= k <= len(runs):
            raise ConsoleError(f"run {k}: the log lists {len(runs)} run(s)")
        return runs[k - 1]
    for cand in (Path(name), ctx.runs_dir / name, ctx.runs_dir / f"{name}.json"):
        try:
            if cand.is_file():
                return cand
        except (OSError, ValueError):  # a name too long, a NUL: no such run
            continue
    raise ConsoleError(f"{name}: no such run in {ctx.runs_dir}")


def _read(path: Path) -> dict[str, Any]:
    from hrm_ctrl.formats.runlog import read_record

    return read_record(path)


def _when(record: dict[str, Any], path: Path) -> str:
    w = record.get("written_utc")
    if isinstance(w, str):
        return w.replace("+00:00", "Z")
    return dt.datetime.fromtimestamp(path.stat().st_mtime, dt.UTC).isoformat(timespec="seconds")


def _plan(record: dict[str, Any]) -> str:
    sp = _setpoints(record)
    plan = record.get("plan_file") or (sp.get("plan") if isinstance(sp, dict) else None)
    if plan:
        return Path(str(plan)).name
    return str(sp.get("source", record.get("source", "-"))) if isinstance(sp, dict) else "-"


def _log_list(ctx: ConsoleContext) -> None:
    runs = run_records(ctx.runs_dir)
    if not runs:
        ctx.out(f"no runs in {ctx.runs_dir}")
        return
    ctx.out(f"{'#':>3}  {'time (UTC)':20}  {'plan':24}  {'outcome':9}  cause")
    for k, p in enumerate(runs, start=1):
        try:
            rec = _read(p)
            what, cause = outcome(rec)
            line = f"{k:>3}  {_when(rec, p):20}  {_plan(rec):24}  {what:9}  {cause}"
        except Exception as exc:  # a damaged record is listed as such, the rest still
            line = f"{k:>3}  {'?':20}  {p.name:24}  {'unreadable':9}  {exc}"
        ctx.out(line)


def _log_show(ctx: ConsoleContext, name: str) -> None:
    path = find_run(ctx, name)
    rec = _read(path)
    what, cause = outcome(rec)
    ctx.out(f"run {rec.get('run')}  ({path})")
    ctx.out(f"written: {_when(rec, path)}  plan: {_plan(rec)}  outcome: {what}")
    if cause:
        ctx.out(f"cause: {cause}")
    cal = rec.get("calibration")
    ctx.out(f"calibration: {cal.get('version') if isinstance(cal, dict) else cal}")
    for i, s in enumerate(_list(rec.get("streams"))):
        s = s if isinstance(s, dict) else {}
        st = s.get("stats") if isinstance(s.get("stats"), dict) else {}
        p99 = _number(st.get("jitter_p99_s"))
        ctx.out(
            f"stream {i}: {_count(s.get('cycles'))} cycles, completed {s.get('completed')}, "
            f"late {_count(st.get('late_cycles', 0))}, jitter p99 "
            + ("-" if p99 is None else f"{1e3 * p99:.3f} ms")
        )
    sp = _setpoints(rec)
    if sp.get("pausable"):
        ctx.out(
            f"play: {sp.get('play_state')}, paused {sp.get('paused_s')} s, stopped at row "
            f"{sp.get('stopped_at_row')} of {sp.get('rows')}"
        )
    for log, n in zip(_list(rec.get("can_logs")), _list(rec.get("can_log_frames")), strict=False):
        ctx.out(f"CAN log: {log} ({n} frames)")


def _replay_targets(ctx: ConsoleContext, rec: dict[str, Any], args: list[str]) -> dict[str, Any]:
    """Bus name -> (interface, channel, bitrate) to replay onto."""
    from drivers.config import BusConfigError, parse_bus_override

    buses = list((rec.get("config") or {}).get("buses") or {})
    out: dict[str, Any] = {b: ("virtual", REPLAY_CHANNEL.format(bus=b), None) for b in buses}
    i = 0
    while i < len(args):
        if args[i] != "--bus" or i + 1 >= len(args):
            raise ConsoleError(USAGE)
        try:
            o = parse_bus_override(args[i + 1])
        except BusConfigError as exc:
            raise ConsoleError(str(exc)) from None
        if o.name not in out:
            raise ConsoleError(
                f"--bus {o.text}: the run has no bus {o.name!r} ({', '.join(buses)})"
            )
        out[o.name] = (o.interface, o.channel, o.bitrate)
        i += 2
    own = _own_buses(ctx)
    for name, (iface, chan, _br) in out.items():
        if any(str(chan) == c and (i is None or str(iface) == i) for i, c in own):
            raise ConsoleError(
                f"bus {name} -> {iface}:{chan}: a bus of this console's box (a replay would "
                "command its drives, connected or not); pick another bus"
            )
    return out


def _own_buses(ctx: ConsoleContext) -> set[tuple[str | None, str]]:
    """(interface, channel) of every bus of the console's box configuration (the simulated
    box's channels with ``--sim``), whether a session is connected or not: its drives
    are there either way.  An interface None (python-can's configuration picks it)
    matches any."""
    if ctx.config is None:
        return set()
    return {
        (None if b.interface is None else str(b.interface), str(b.channel))
        for b in ctx.config.buses
    }


def replay(
    rec: dict[str, Any], record_path: Path, targets: dict[str, Any], *, timeout_s: float = 3600.0
) -> list[int]:
    """Send each bus's CAN log onto its target bus with the log's timing
    (:class:`can.MessageSync`, python-can's player), every bus at once (a thread each, as
    the buses ran); the frames sent per bus."""
    import threading

    import can

    from hrm_ctrl.formats.runlog import (
        RunLogError,
        _log_path,
        check_can_log,
        iter_can_log,
        log_errors,
    )

    names = list((rec.get("config") or {}).get("buses") or {})
    logs = [str(x) for x in rec.get("can_logs") or []]
    if len(logs) != len(names):
        raise ConsoleError(f"{record_path}: {len(logs)} CAN logs for {len(names)} buses")
    recorded = _list(rec.get("can_log_frames"))
    for i, x in enumerate(logs):  # before any bus is opened
        lp = _log_path(record_path, x)
        try:
            check_can_log(lp)
            expected = recorded[i] if len(recorded) == len(logs) else None
            if isinstance(expected, int) and not isinstance(expected, bool):
                # a whole read (bounded; the replay takes the run's own time anyway): a log
                # cut short would otherwise replay its first part as if it were the run
                found = sum(1 for _ in iter_can_log(lp, MAX_REPLAY_FRAMES))
                if found != expected:
                    raise ConsoleError(
                        f"{lp}: {found} frames, the run record says {expected} (a cut or "
                        "changed log): not replayed"
                    )
        except RunLogError as exc:
            raise ConsoleError(str(exc)) from None
    read_errors = log_errors()
    opened = []
    try:
        for name in names:
            iface, chan, bitrate = targets[name]
            kw: dict[str, Any] = {"interface": iface, "channel": chan}
            if bitrate is not None:
                kw["bitrate"] = bitrate
            try:
                opened.append(can.Bus(**kw))
            except (can.CanError, OSError, ValueError, ImportError) as exc:
                raise ConsoleError(f"bus {name} -> {iface}:{chan}: cannot open ({exc})") from None
        sent = [0] * len(names)
        errors: list[str] = []

        def play(i: int) -> None:
            lp = _log_path(record_path, logs[i])
            try:
                with can.LogReader(str(lp)) as reader:
                    for msg in can.MessageSync(reader, timestamps=True):
                        if sent[i] >= MAX_REPLAY_FRAMES:
                            errors.append(f"{lp}: more than {MAX_REPLAY_FRAMES} frames")
                            return
                        if msg.is_error_frame:
                            continue
                        opened[i].send(msg)
                        sent[i] += 1
            except read_errors as exc:  # a log damaged past its bounds check
                errors.append(f"{lp}: replay failed after {sent[i]} frames ({exc})")

        threads = [threading.Thread(target=play, args=(i,), daemon=True) for i in range(len(names))]
        for t in threads:
            t.start()
        for t in threads:
            t.join(timeout_s)
        if any(t.is_alive() for t in threads):
            errors.append(f"replay did not end within {timeout_s:g} s")
        if errors:
            raise ConsoleError(errors[0])
        return sent
    finally:
        for bus in opened:
            bus.shutdown()


@command("log", "past runs: list them (time, plan, outcome, cause), show one, or replay its "
         "CAN logs onto buses (default: virtual)",
         "log | log show RUN | log replay RUN [--bus NAME=INTERFACE:CHANNEL]...",
         complete=lambda ctx, words: ["show", "replay"] if len(words) <= 2 else [])  # fmt: skip
def _log(ctx: ConsoleContext, args: list[str]) -> None:
    if not args:
        _log_list(ctx)
        return
    if args[0] == "show" and len(args) == 2:
        _log_show(ctx, args[1])
        return
    if args[0] == "replay" and len(args) >= 2:
        path = find_run(ctx, args[1])
        rec = _read(path)
        targets = _replay_targets(ctx, rec, args[2:])
        sent = replay(rec, path, targets)
        for (name, (iface, chan, _b)), n in zip(targets.items(), sent, strict=True):
            ctx.out(f"replayed {n} frames of bus {name} onto {iface}:{chan}")
        return
    raise ConsoleError(USAGE)
