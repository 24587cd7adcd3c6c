"""``hrm status``: the console's ``status`` as a one-shot command.

Connects (one bring-up: the drives are configured and left pre-operational again; a box
whose drives another master operates is refused), waits until every drive's heartbeat
came after the bring-up (at most :data:`FRESH_HEARTBEAT_PERIODS` heartbeat periods: the NMT
column shows the last heartbeat's state, and a drive configured just before the snapshot
would still show its boot-up frame), prints every drive's NMT and CiA 402
state, position, following error, tension, heartbeat age and last EMCY, every bus's load
and error counters and the session state, then finishes the session.  The same command
table as ``hrm console`` (``connect``, ``status``, ``quit``).

>>> import argparse
>>> p = argparse.ArgumentParser(prog="hrm status")
>>> register(p)
>>> p.parse_args(["--sim", "--json"]).json
True
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from typing import Any

HELP = "one-shot status of every drive and bus (connect, status, finish)"
FRESH_HEARTBEAT_PERIODS = 2.5  # the longest wait for every drive's next heartbeat


def register(parser: argparse.ArgumentParser) -> None:
    from hrm_ctrl.cli._options import add_console_box, add_json

    add_console_box(parser)
    add_json(parser, "the snapshot")


def run(args: argparse.Namespace) -> int:
    from hrm_ctrl.cli._console.shell import build_context, finish_context
    from hrm_ctrl.cli._console.streaming import tension_sample
    from hrm_ctrl.cli._console.table import run_words

    ctx = build_context(args, "hrm status")
    try:
        if args.json:
            ctx.out = lambda _text: None  # the connect line is not JSON
            run_words(ctx, ["connect"])
            await_fresh_heartbeats(ctx.session)
            st = ctx.session.status_snapshot(tension_sample(ctx))
            doc = dataclasses.asdict(st)
            for node, n in zip(doc["nodes"], st.nodes, strict=True):
                node["following_error_counts"] = n.following_error_counts
            print(json.dumps(doc, indent=1))
        else:
            run_words(ctx, ["connect"])
            await_fresh_heartbeats(ctx.session)
            run_words(ctx, ["status"])
    finally:
        finish_context(ctx)
    return 0


def await_fresh_heartbeats(session: Any) -> bool:
    """Wait until every drive's heartbeat has come since now, at most
    :data:`FRESH_HEARTBEAT_PERIODS` of ``node_heartbeat_ms``; True if they all did (a
    silent drive then shows its age in the table)."""
    mon = session.monitor
    since = mon.clock()
    timeout_s = FRESH_HEARTBEAT_PERIODS * session.control.node_heartbeat_ms / 1000.0
    deadline = time.monotonic() + timeout_s
    while (mon.hb_time <= since).any():
        if time.monotonic() >= deadline:
            return False
        time.sleep(0.01)
    return True
