"""Wiring the simulated box into the console (``--sim``): the only place that does.

The drivers only ever see buses: here the configured interfaces are replaced by
in-process buses (python-can ``virtual``, or ``hrm_sim``, the simulated wire at the
configured bitrate) and a :class:`sim_bus.box.SimBox` is started on the other end,
with its tension-sensor board on a pseudo-terminal, which becomes the configuration's
``[tension]`` port (thresholds from the file's table if it has one, else the defaults).
Host and box take the same :class:`drivers.config.BoxConfig`: the one configuration.
"""

from __future__ import annotations

import sys
import uuid
from typing import Any

from drivers.config import BoxConfig
from hrm_ctrl.errors import DriverError
from hrm_ctrl.ropes.actuation import Actuation

SIM_MISSING_TPDO_CYCLES = 10
SIM_TENSION_STALE_S = 0.5  # the top of the safe range: the board shares this interpreter
SIM_WIRES = ("virtual", "hrm_sim")


def start_in_process_sim(
    config: BoxConfig, actuation: Actuation, wire: str = "virtual", prog: str = "hrm"
) -> tuple[BoxConfig, Any]:
    """Return the configuration rewritten onto in-process buses and the started box.

    The simulated drives and tension board run in this interpreter and share its CPU,
    so their TPDOs get ``SIM_MISSING_TPDO_CYCLES`` cycles before the host calls them
    missing and the tension samples ``SIM_TENSION_STALE_S`` before they are stale (a line
    on stderr says so, and the run record keeps the configuration used).
    """
    from sim_bus.box import SimBox

    if wire not in SIM_WIRES:
        raise DriverError(f"--wire must be one of {', '.join(SIM_WIRES)}, got {wire!r}")
    raised = []
    if config.control.missing_tpdo_cycles < SIM_MISSING_TPDO_CYCLES:
        config = config.with_control(missing_tpdo_cycles=SIM_MISSING_TPDO_CYCLES)
        raised.append(f"TPDO tolerance raised to {SIM_MISSING_TPDO_CYCLES} cycles")
    tension: dict[str, Any] = {}
    if config.tension is None or config.tension.stale_s < SIM_TENSION_STALE_S:
        tension["stale_s"] = SIM_TENSION_STALE_S
        raised.append(f"tension staleness to {SIM_TENSION_STALE_S * 1000:.0f} ms")
    tag = uuid.uuid4().hex[:8]
    config = config.with_bus_kwargs(
        [{"interface": wire, "channel": f"hrm-sim-{tag}-{b.name}"} for b in config.buses]
    )
    sim = SimBox(config, actuation=actuation)
    sim.start()
    try:
        config = config.with_tension(port=sim.start_tension_board().port, **tension)
    except BaseException:
        sim.stop()
        raise
    if raised:
        print(
            f"{prog}: --sim: {', '.join(raised)} (the simulated box shares this interpreter)",
            file=sys.stderr,
        )
    return config, sim
