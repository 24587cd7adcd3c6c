"""What tests outside ``tests/hil`` still import from the old HIL rig
(``tests/drivers/test_canlog_durability.py``, ``tests/drivers/test_config_busload.py``); the rig
itself is ``hrm_ctrl.hil.rig`` now, and the HIL tests use the ``hrm_hil`` plugin at
production settings.

"""

from __future__ import annotations

from pathlib import Path

from hrm_ctrl.hil.rig import BoxProcess, vcan_pair_available
from hrm_ctrl.hil.rig import default_nodes as default_buses

REPO = Path(__file__).resolve().parents[2]

__all__ = ["REPO", "BoxProcess", "default_buses", "vcan_pair_available"]
