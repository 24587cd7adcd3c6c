"""The host's watchdog tolerances for a simulated box that shares the host's interpreter.

A box in its own process (``hrm sim``, the HIL plugin's ``--hrm-box process``) runs the
production settings of ``box.toml``.  A :class:`sim_bus.box.SimBox` started in the host's
own interpreter (``hrm demo``, ``--sim``, the plugin's ``inprocess`` mode, the driver
tests' rigs) shares its GIL and its core with the host: its 36 drives, its tension board
and the host's dozen threads use about 0.7 of a core on the 2-core development machine,
and a busy moment puts the box's TPDOs behind by more than the production 3 cycles (one
run in three stopped at 10 cycles; the CI run of ``03390e1`` stopped a 3-node driver test
at 3).  Whoever starts such a box raises the host's tolerances to these values, each
within its safe range (``drivers.config.CONTROL_RANGES``), and says so.

>>> IN_PROCESS_MISSING_TPDO_CYCLES, IN_PROCESS_HEARTBEAT_TIMEOUT_MS, IN_PROCESS_TENSION_STALE_S
(25, 1000, 0.5)
"""

from __future__ import annotations

#: cycles without a TPDO before the host stops (the top of the safe range: 250 ms at 100 Hz)
IN_PROCESS_MISSING_TPDO_CYCLES = 25
#: the host's heartbeat consumer time (heartbeats were seen 379-860 ms apart with both
#: cores busy; the top of the range is 2000 ms)
IN_PROCESS_HEARTBEAT_TIMEOUT_MS = 1000
#: age at which a tension sample is stale (the top of the safe range)
IN_PROCESS_TENSION_STALE_S = 0.5

__all__ = [
    "IN_PROCESS_HEARTBEAT_TIMEOUT_MS",
    "IN_PROCESS_MISSING_TPDO_CYCLES",
    "IN_PROCESS_TENSION_STALE_S",
]
