"""The console's ``view``: the arm as the drives' feedback shows it, live in the browser
(:func:`hrm_ctrl.cli._live.start_live_view`, served on 127.0.0.1), until ``view stop`` or
the session ends."""

from __future__ import annotations

from hrm_ctrl.cli._console.context import ConsoleContext
from hrm_ctrl.cli._console.table import ConsoleError, Need, command

LIVE_VIEW = "live_view"  # ctx.extra key of the running view


def close_view(ctx: ConsoleContext) -> bool:
    """Close the running live view, if any; whether one ran."""
    view = ctx.extra.pop(LIVE_VIEW, None)
    if view is None:
        return False
    view.close()
    return True


@command("view", "the arm as the feedback shows it, live in the browser (127.0.0.1; PORT 0: "
         "a free one); 'view stop' ends it", "view [PORT] | view stop",
         needs=Need.CONNECTED,
         complete=lambda ctx, words: ["stop"] if len(words) == 2 else [])  # fmt: skip
def _view(ctx: ConsoleContext, args: list[str]) -> None:
    from hrm_ctrl.cli._live import start_live_view

    if args == ["stop"]:
        ctx.out("view: closed" if close_view(ctx) else "view: none running")
        return
    if len(args) > 1:
        raise ConsoleError("usage: view [PORT] | view stop")
    try:
        port = int(args[0]) if args else 0
    except ValueError:
        raise ConsoleError(f"PORT must be a number, got {args[0]!r}") from None
    if not 0 <= port <= 65535:
        raise ConsoleError(f"PORT must be in [0, 65535], got {port}")
    if LIVE_VIEW in ctx.extra:
        raise ConsoleError(f"running already at {ctx.extra[LIVE_VIEW].url} (view stop first)")
    view = start_live_view(ctx.session, ctx.actuation, ctx.model, None, port)
    ctx.extra[LIVE_VIEW] = view
    ctx.out(f"view: {view.url} (the arm as the feedback shows it; view stop ends it)")
