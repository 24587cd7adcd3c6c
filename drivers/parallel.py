"""SDO work on every drive at once: one thread per drive, a time bound, the first error.

The session configures, enables, reads and disables its drives by SDO (each transfer
bounded by the SDO timeout and canopen's retries; each CiA 402 transition by the state
timeout).  :func:`run_parallel` runs one function per drive in a thread pool and waits
for all of them within a budget (:func:`budget_s`); a drive still busy after it is named
in a :class:`~hrm_ctrl.errors.DriverError`, and the first failure is raised as what it is
(its class and its fields kept, the other drives' failures counted in its message, the
original chained as its cause: :func:`with_message`).

>>> import time
>>> run_parallel("square", lambda x: x * x, [2, 3], 1.0, label=str)
[4, 9]
>>> run_parallel("slow", lambda x: time.sleep(x), [0.0, 1.0], 0.05, label=str)
Traceback (most recent call last):
...
hrm_ctrl.errors.DriverError: slow: no answer within 0.05 s from 1 drive(s): 1.0
"""

from __future__ import annotations

import concurrent.futures
from collections.abc import Callable, Sequence
from typing import TypeVar

import canopen

from hrm_ctrl.errors import DriverError, HrmError

#: at most this many SDO threads at once (the largest box: 36 drives)
MAX_WORKERS = 36
#: added to every budget (thread start-up, the GIL on a busy machine)
PARALLEL_MARGIN_S = 1.0

E = TypeVar("E", bound=BaseException)
T = TypeVar("T")
R = TypeVar("R")


def sdo_transfer_s(sdo_timeout_s: float) -> float:
    """Longest one SDO transfer can take: the timeout times (1 + canopen's retries).

    >>> sdo_transfer_s(0.5) == 0.5 * (1 + canopen.sdo.SdoClient.MAX_RETRIES)
    True
    """
    return sdo_timeout_s * (1 + canopen.sdo.SdoClient.MAX_RETRIES)


def budget_s(
    sdo_timeout_s: float, state_timeout_s: float, transfers: int, transitions: int = 0
) -> float:
    """Time bound of parallel work of ``transfers`` SDO transfers and ``transitions``
    CiA 402 transitions per drive (each transition: the state timeout and one transfer).

    >>> budget_s(0.1, 0.5, 2, 1) == 2 * sdo_transfer_s(0.1) + 0.5 + sdo_transfer_s(0.1) + 1.0
    True
    """
    transfer = sdo_transfer_s(sdo_timeout_s)
    return transfers * transfer + transitions * (state_timeout_s + transfer) + PARALLEL_MARGIN_S


def with_message(exc: E, message: str) -> E:
    """A copy of ``exc`` (same class, same fields) whose message is ``message``: for an
    error raised again with more context, without calling its constructor (whose
    signature may ask for more than a message).

    >>> class Coded(DriverError):
    ...     def __init__(self, message: str, code: int) -> None:
    ...         super().__init__(message)
    ...         self.code = code
    >>> e = with_message(Coded("bad", 7), "bad (and 1 more)")
    >>> type(e).__name__, str(e), e.code
    ('Coded', 'bad (and 1 more)', 7)
    """
    out = type(exc).__new__(type(exc))
    out.args = (message,)
    out.__dict__.update(exc.__dict__)
    return out


def run_parallel(
    what: str,
    fn: Callable[[T], R],
    items: Sequence[T],
    timeout_s: float,
    label: Callable[[T], str],
    on_error: Callable[[str], None] | None = None,
) -> list[R]:
    """``fn`` for every item (drive) at once, results in ``items``' order.

    Waits for all within ``timeout_s``: the items still busy then raise
    :class:`DriverError` naming them (by ``label``).  Otherwise the first failure is
    raised: an :class:`HrmError` as itself (:func:`with_message`: class and fields kept,
    "(and k more drive(s) failed)" added), anything else as a :class:`DriverError`
    naming ``what``; either chained to the original.  ``on_error`` gets each error's
    one-line text first (the session's event log)."""
    if not items:
        return []
    pool = concurrent.futures.ThreadPoolExecutor(
        max_workers=min(MAX_WORKERS, len(items)), thread_name_prefix=f"drives-{what}"
    )
    try:
        futures = [pool.submit(fn, item) for item in items]
        _done, busy = concurrent.futures.wait(futures, timeout=timeout_s)
    finally:
        pool.shutdown(wait=False, cancel_futures=True)
    if busy:
        names = [label(item) for item, f in zip(items, futures, strict=True) if f in busy]
        text = f"{what}: no answer within {timeout_s:g} s from {len(names)} drive(s): " + (
            ", ".join(names)
        )
        if on_error is not None:
            on_error(text)
        raise DriverError(text)
    errors = [e for e in (f.exception() for f in futures) if e is not None]
    if errors:
        first = errors[0]
        more = f" (and {len(errors) - 1} more drive(s) failed)" if len(errors) > 1 else ""
        if on_error is not None:
            on_error(f"{what}: {first}{more}")
        if isinstance(first, HrmError):
            raise with_message(first, f"{first}{more}") from first
        raise DriverError(f"{what}: {first}{more}") from first
    return [f.result() for f in futures]
