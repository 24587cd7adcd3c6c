"""How a stop reaches the caller of a stream: :class:`SafetyStopError`, with the causes
and the stream's result, and its one-line message.

>>> from drivers.safety.causes import StopCause, StopKind
>>> c = StopCause(StopKind.OPERATOR, "stop requested", None, 1.0)
>>> r = StreamResult(False, 12, [c], {}, np.zeros(2, np.int64))
>>> e = stream_stop_error(r, None)
>>> str(e), e.causes == [c], e.result is r
('stopped: stop requested', True, True)
>>> str(stopped_refusal([c], idle=True, stop_error=None, n=2))
'stopped while idle: stop requested'
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from drivers.cycle import StreamResult
from drivers.safety.causes import StopCause, StopKind
from hrm_ctrl.errors import DriverError


class SafetyStopError(DriverError):
    """Streaming was stopped by a watchdog, a limit or a bus failure; every axis got a
    quick stop.  ``causes`` lists why."""

    def __init__(self, message: str, causes: list[StopCause], result: StreamResult) -> None:
        super().__init__(message)
        self.causes = causes
        self.result = result


def stream_stop_error(result: StreamResult, busy: str | None) -> SafetyStopError:
    """The error of a stream that stopped (``result.causes`` not empty): its first cause
    (a refused setpoint: the limit's own message) and how many more, and ``busy``: the
    traffic of devices not in the configuration during the stream, if any."""
    first = result.causes[0]
    more = f" (+{len(result.causes) - 1} more)" if len(result.causes) > 1 else ""
    also = "" if busy is None else f" ({busy})"
    if result.error is not None and first.kind is StopKind.LIMIT:
        return SafetyStopError(f"stopped: {result.error}{also}", result.causes, result)
    return SafetyStopError(f"stopped: {first.text}{more}{also}", result.causes, result)


def stopped_refusal(
    causes: Sequence[StopCause], idle: bool, stop_error: str | None, n: int
) -> SafetyStopError:
    """A stream asked for after a stop (``idle``: while no stream ran) naming why the box
    stopped (and why its quick stop failed, if it did); ``n`` drives."""
    failed = f" ({stop_error})" if stop_error is not None else ""
    where = "while idle" if idle else "earlier"
    return SafetyStopError(
        f"stopped {where}: {causes[0].text}{failed}",
        list(causes),
        StreamResult(False, 0, list(causes), {}, np.zeros(n, np.int64)),
    )
