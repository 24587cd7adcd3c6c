"""What tests outside ``tests/hil`` still import from the old HIL rig
(``tests/drivers/test_log_durability.py``, ``tests/drivers/test_config_busload.py``); the rig
itself is ``hrm_ctrl.hil.rig`` now, and the HIL tests use the ``hrm_hil`` plugin at
production settings.

``HIL_CONTROL`` is the relaxed watchdog timing the HIL tests ran with before (25 cycles,
1000 ms): the HIL tests no longer use it; the kill -9 log test still runs ``hrm run`` with it.
"""

from __future__ import annotations

from pathlib import Path

from hrm_ctrl.hil.rig import BoxProcess, vcan_pair_available
from hrm_ctrl.hil.rig import default_nodes as default_buses

REPO = Path(__file__).resolve().parents[2]
HIL_CONTROL = {"missing_tpdo_cycles": 25, "heartbeat_timeout_ms": 1000, "bootup_timeout_s": 5.0}

__all__ = ["HIL_CONTROL", "REPO", "BoxProcess", "default_buses", "vcan_pair_available"]
