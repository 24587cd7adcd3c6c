"""The in-process simulated box's wiring, as the commands import it: it lives in
:mod:`hrm_ctrl.runtime.simulated` (the runtime layer); these names are re-exported."""

from hrm_ctrl.runtime.simulated import (
    PROCESS_WIRE,
    SIM_HEARTBEAT_TIMEOUT_MS,
    SIM_LISTEN_S,
    SIM_MISSING_TPDO_CYCLES,
    SIM_SWITCH_INTERVAL_S,
    SIM_TENSION_STALE_S,
    SIM_WIRES,
    calibration_counts,
    sim_listen,
    start_in_process_sim,
)

__all__ = [
    "PROCESS_WIRE",
    "SIM_HEARTBEAT_TIMEOUT_MS",
    "SIM_LISTEN_S",
    "SIM_MISSING_TPDO_CYCLES",
    "SIM_SWITCH_INTERVAL_S",
    "SIM_TENSION_STALE_S",
    "SIM_WIRES",
    "calibration_counts",
    "sim_listen",
    "start_in_process_sim",
]
