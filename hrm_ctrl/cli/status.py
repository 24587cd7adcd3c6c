"""``hrm status``: the console's ``status`` as a one-shot command.

Connects (one bring-up: the drives are configured and left pre-operational again; a box
whose drives another master operates is refused), prints every drive's NMT and CiA 402
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

HELP = "one-shot status of every drive and bus (connect, status, finish)"


def register(parser: argparse.ArgumentParser) -> None:
    from hrm_ctrl.cli._console.shell import add_context_arguments

    add_context_arguments(parser)
    parser.add_argument("--json", action="store_true", help="print the snapshot as JSON")


def run(args: argparse.Namespace) -> int:
    from hrm_ctrl.cli._console.shell import build_context, finish_context
    from hrm_ctrl.cli._console.streaming import tension_sample
    from hrm_ctrl.cli._console.table import run_words

    ctx = build_context(args, "hrm status")
    try:
        if args.json:
            ctx.out = lambda _text: None  # the connect line is not JSON
            run_words(ctx, ["connect"])
            st = ctx.session.status_snapshot(tension_sample(ctx))
            doc = dataclasses.asdict(st)
            for node, n in zip(doc["nodes"], st.nodes, strict=True):
                node["following_error_counts"] = n.following_error_counts
            print(json.dumps(doc, indent=1))
        else:
            run_words(ctx, ["connect"])
            run_words(ctx, ["status"])
    finally:
        finish_context(ctx)
    return 0
