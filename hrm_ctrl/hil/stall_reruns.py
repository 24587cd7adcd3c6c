"""pytest plugin: a test that must tolerate a shared machine is rerun only on evidence that
the machine stalled through a watchdog window, never because of what failed.

A test marked ``@pytest.mark.stall_tolerant(window_s=W, watchdog="what")`` runs with a
:class:`~hrm_ctrl.hil.stalls.StallProbe` on every CPU of the process.  When its setup (a
fixture's bring-up) or its call fails, the probe's stalls are read: a stall of one CPU at
least ``W`` long (its probe's late wake-ups joined, :func:`~hrm_ctrl.hil.stalls.covering`)
during the failed phase held that
CPU through a whole window of the watchdog ``what``, enough to trip it with nothing else
wrong.  Then, and only then, the test runs again, at most ``reruns`` times (default 2);
the evidence (which CPU, when, how long, which window) is printed at once, kept in the
failed attempt's report and listed in the run's summary ("stall reruns").  A failure with
no such stall, or with the probe unavailable (no ``SCHED_FIFO``), is the test's failure;
its report says what the probe saw.

``W`` is the shortest watchdog window the test's run arms: a stall shorter than every
window trips none of them.

The probes wake every millisecond (:data:`~hrm_ctrl.hil.stalls.PROBE_PERIOD_S`) unless
``--stall-probe-period SECONDS`` says otherwise: the vcan guest (one CPU, 30-60 us per
system call) runs them at 20 ms (``tests/vcan_guest.py``).  A probe of period ``P`` records
a pause of ``D`` at least ``D - P`` long, so a test's ``W`` must exceed ``P`` (a usage error
otherwise), and only a pause of ``W + P`` or more is sure to be evidence.

The fixture ``stall_probe`` is the probe of the running attempt (e.g. to add stalls in a
test of this plugin).  Load the plugin with ``-p hrm_ctrl.hil.stall_reruns``.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass

import pytest
from _pytest.runner import runtestprotocol

from hrm_ctrl.hil.stalls import PROBE_PERIOD_S, Stall, StallProbe, covering, probe_period_s

MARKER = "stall_tolerant"
DEFAULT_RERUNS = 2
PROBE = pytest.StashKey[StallProbe]()
RERUNS = pytest.StashKey[list[str]]()
PERIOD = pytest.StashKey[float]()
PERIOD_OPTION = "--stall-probe-period"


@dataclass(frozen=True)
class Tolerance:
    """A test's ``stall_tolerant`` marker: the watchdog window a stall must cover."""

    window_s: float
    watchdog: str
    reruns: int

    def window(self) -> str:
        """``'the 250 ms window of 25 missing TPDO cycles'``."""
        return f"the {self.window_s * 1000:g} ms window of {self.watchdog}"


def tolerance(item: pytest.Item, period_s: float = PROBE_PERIOD_S) -> Tolerance | None:
    """The item's marker read and checked against the probe's period; None for an unmarked
    test."""
    mark = item.get_closest_marker(MARKER)
    if mark is None:
        return None
    window_s = mark.kwargs.get("window_s")
    watchdog = mark.kwargs.get("watchdog")
    reruns = mark.kwargs.get("reruns", DEFAULT_RERUNS)
    if mark.args or set(mark.kwargs) - {"window_s", "watchdog", "reruns"}:
        raise pytest.UsageError(
            f"{item.nodeid}: {MARKER} takes window_s=, watchdog= and reruns= only"
        )
    if not isinstance(window_s, int | float) or not math.isfinite(window_s) or window_s <= 0:
        raise pytest.UsageError(f"{item.nodeid}: {MARKER} window_s={window_s!r} is not > 0 s")
    if not isinstance(watchdog, str) or not watchdog:
        raise pytest.UsageError(f"{item.nodeid}: {MARKER} needs watchdog= (what fires)")
    if not isinstance(reruns, int) or reruns < 0:
        raise pytest.UsageError(f"{item.nodeid}: {MARKER} reruns={reruns!r} is not >= 0")
    if window_s <= period_s:
        raise pytest.UsageError(
            f"{item.nodeid}: {MARKER} window_s={window_s!r} is not longer than the stall "
            f"probe's period ({PERIOD_OPTION}={period_s:g}): the probe could not see it"
        )
    return Tolerance(float(window_s), watchdog, reruns)


def evidence_line(stall: Stall, t0_s: float, tol: Tolerance) -> str:
    """One stall as evidence: which CPU, when (seconds into the failed phase and monotonic),
    how long.

    >>> tol = Tolerance(0.25, "25 missing TPDO cycles", 2)
    >>> print(evidence_line(Stall(1, 103.5, 0.4125), 100.0, tol))  # doctest: +NORMALIZE_WHITESPACE
    CPU 1 stalled 412.5 ms from 3.500 s into the failed phase (monotonic 103.500 s),
    covering the 250 ms window of 25 missing TPDO cycles
    """
    return (
        f"CPU {stall.cpu} stalled {stall.late_s * 1000:.1f} ms from {stall.at_s - t0_s:.3f} s "
        f"into the failed phase (monotonic {stall.at_s:.3f} s), covering {tol.window()}"
    )


def _verdict(probe: StallProbe, tol: Tolerance, lo_s: float, hi_s: float) -> list[Stall] | str:
    """The covering stalls of a failed phase, or why there are none (one line)."""
    if not probe.available:
        return f"stall probe unavailable ({probe.refusal}): no evidence of a machine stall"
    found = covering(probe.stalls, tol.window_s, lo_s, hi_s)
    if found:
        return found
    during = [s for s in probe.stalls if lo_s <= s.at_s <= hi_s]
    longest = max((s.late_s for s in during), default=0.0)
    return (
        f"no machine stall covered {tol.window()} during the failed phase (probe on CPUs "
        f"{','.join(map(str, probe.cpus))}, every {probe.period_s * 1000:g} ms: "
        f"{len(during)} stalls, longest {longest * 1000:.1f} ms)"
    )


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption(
        PERIOD_OPTION,
        default=None,
        metavar="SECONDS",
        help=f"the stall probes' period (default {PROBE_PERIOD_S:g}; the vcan guest: 0.02)",
    )


def _period_s(config: pytest.Config) -> float:
    text = config.getoption(PERIOD_OPTION)
    if text is None:
        return PROBE_PERIOD_S
    try:
        return probe_period_s(str(text), PERIOD_OPTION)
    except ValueError as exc:
        raise pytest.UsageError(str(exc)) from None


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line(
        "markers",
        f"{MARKER}(window_s, watchdog, reruns={DEFAULT_RERUNS}): rerun a failed test only "
        "when the stall probe saw a machine stall covering the watchdog window window_s "
        "(hrm_ctrl.hil.stall_reruns)",
    )
    config.stash[RERUNS] = []
    config.stash[PERIOD] = _period_s(config)


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:  # a bad marker is a usage error before anything runs
        tolerance(item, config.stash[PERIOD])


@pytest.fixture
def stall_probe(request: pytest.FixtureRequest) -> StallProbe:
    """The stall probe running through this attempt of a ``stall_tolerant`` test."""
    probe = request.node.stash.get(PROBE, None)
    if probe is None:
        raise pytest.UsageError(f"{request.node.nodeid}: stall_probe needs @pytest.mark.{MARKER}")
    return probe


@pytest.hookimpl(tryfirst=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> bool | None:
    period_s = item.config.stash[PERIOD]
    tol = tolerance(item, period_s)
    if tol is None:
        return None
    item.ihook.pytest_runtest_logstart(nodeid=item.nodeid, location=item.location)
    mono_minus_wall = time.monotonic() - time.time()
    for attempt in range(tol.reruns + 1):
        with StallProbe(os.sched_getaffinity(0), period_s) as probe:
            item.stash[PROBE] = probe
            reports = runtestprotocol(item, nextitem=nextitem, log=False)
        del item.stash[PROBE]
        # the failed phase: the setup (a fixture's bring-up) or the call
        failed = next((r for r in reports if r.when in ("setup", "call") and r.failed), None)
        rerun = False
        if failed is not None:
            lo_s, hi_s = failed.start + mono_minus_wall, failed.stop + mono_minus_wall
            verdict = _verdict(probe, tol, lo_s, hi_s)
            if isinstance(verdict, str):
                failed.sections.append(("stall probe", f"{verdict}: not rerun"))
            elif attempt == tol.reruns:
                lines = [evidence_line(s, lo_s, tol) for s in verdict]
                failed.sections.append(
                    ("stall probe", "\n".join([*lines, f"reruns exhausted ({tol.reruns})"]))
                )
            else:
                rerun = True
                lines = [evidence_line(s, lo_s, tol) for s in verdict]
                text = f"attempt {attempt + 1} failed; " + "; ".join(lines) + ": rerun"
                failed.sections.append(("stall probe", text))
                failed.outcome = "rerun"  # type: ignore[assignment]
                item.config.stash[RERUNS].append(f"{item.nodeid}: {text}")
                reporter = item.config.pluginmanager.get_plugin("terminalreporter")
                if reporter is not None:
                    reporter.ensure_newline()
                    reporter.write_line(f"{item.nodeid}: {text}", yellow=True)
        for report in reports:
            item.ihook.pytest_runtest_logreport(report=report)
        if not rerun:
            break
        item._initrequest()  # type: ignore[attr-defined]  # fresh fixtures for the rerun
        _forget_failed_fixtures(item)
    item.ihook.pytest_runtest_logfinish(nodeid=item.nodeid, location=item.location)
    return True


def _forget_failed_fixtures(item: pytest.Item) -> None:
    """Drop the cached exception of every fixture of the item that failed (a module-scoped
    box that did not start), so that the rerun sets it up again instead of re-raising."""
    if not isinstance(item, pytest.Function):
        return
    for defs in item._fixtureinfo.name2fixturedefs.values():
        for fixturedef in defs:
            cached = fixturedef.cached_result
            if cached is not None and cached[2] is not None:
                fixturedef.finish(item._request)  # its finalizers run, its cache cleared


Status = tuple[str, str, tuple[str, dict[str, bool]]]


def pytest_report_teststatus(report: pytest.TestReport) -> Status | None:
    if report.outcome == "rerun":
        return "rerun", "R", ("RERUN", {"yellow": True})
    return None


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    reruns = terminalreporter.config.stash.get(RERUNS, [])
    if reruns:
        terminalreporter.section("stall reruns", sep="-", yellow=True)
        for line in reruns:
            terminalreporter.write_line(line)
