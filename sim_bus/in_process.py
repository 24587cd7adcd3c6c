"""The host's watchdog tolerances for a simulated box that shares the host's interpreter.

A box in its own process (``hrm sim``, the HIL plugin's ``--hrm-box process``) runs the
production settings of ``box.toml``.  A :class:`sim_bus.box.SimBox` started in the host's
own interpreter (``hrm demo``, ``--sim``, the plugin's ``inprocess`` mode, the driver
tests' rigs) shares its GIL and its core with the host: its 36 drives, its tension board
and the host's dozen threads use about 0.7 of a core on the 2-core development machine,
and a busy moment puts the box's TPDOs behind by more than the production 3 cycles (one
run in three stopped at 10 cycles; a CI run stopped a 3-node driver test
at 3).  Whoever starts such a box raises the host's tolerances to these values, each
within its safe range (``drivers.config.CONTROL_RANGES``), and says so; the process runs
with a longer GIL switch interval (:data:`IN_PROCESS_SWITCH_INTERVAL_S`).

>>> IN_PROCESS_MISSING_TPDO_CYCLES, IN_PROCESS_HEARTBEAT_TIMEOUT_MS, IN_PROCESS_TENSION_STALE_S
(25, 1000, 0.5)
>>> IN_PROCESS_SDO_TIMEOUT_S
1.0
"""

from __future__ import annotations

#: cycles without a TPDO before the host stops (the top of the safe range: 250 ms at 100 Hz)
IN_PROCESS_MISSING_TPDO_CYCLES = 25
#: the host's heartbeat consumer time (heartbeats were seen 379-860 ms apart with both
#: cores busy; the top of the range is 2000 ms)
IN_PROCESS_HEARTBEAT_TIMEOUT_MS = 1000
#: age at which a tension sample is stale (the top of the safe range)
IN_PROCESS_TENSION_STALE_S = 0.5
#: each SDO transfer: the 36 drives' SDO servers answer from the host's interpreter while the
#: bring-up's 36 transfers run in parallel; with both cores busy (``stress --cpu 2``) a
#: console test's connect and enable missed 0.5 s twice in three runs of the suite
IN_PROCESS_SDO_TIMEOUT_S = 1.0
IN_PROCESS_SWITCH_INTERVAL_S = 1e-3
"""The GIL switch interval of a command that runs the simulated box in its interpreter
(``drivers.realtime.SWITCH_INTERVAL_S``, 0.2 ms, elsewhere).  Measured on the 2-core
development machine, ``hrm run --sim`` of the bent-pipe plan (box, host and their 13
threads in one interpreter), four runs each: at 1 ms the process used 5.9-7.2 ms of CPU
per 10 ms cycle and no run stopped; at 0.2 ms 7.5-8.2 ms, and 5 of 16 runs stopped on a
late TPDO (each forced hand-over is a futex round and a cold cache, and the bursts, a rope
check or a SYNC's 18 TPDOs, were cut into more of them); 5 ms was no better than 1 ms.
Across processes (``bench_drivers.py --box-process``) 0.2 ms kept the SYNC jitter lower."""

__all__ = [
    "IN_PROCESS_HEARTBEAT_TIMEOUT_MS",
    "IN_PROCESS_MISSING_TPDO_CYCLES",
    "IN_PROCESS_SDO_TIMEOUT_S",
    "IN_PROCESS_SWITCH_INTERVAL_S",
    "IN_PROCESS_TENSION_STALE_S",
]
