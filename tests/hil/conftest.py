"""Fixtures of the hardware-in-the-loop tests (helpers live in ``hil_rig``)."""

from tests.hil.hil_rig import (
    bent_pipe_plan,
    bus_kind,
    fault_box,
    fault_config,
    full_box,
    full_config,
)

__all__ = ["bent_pipe_plan", "bus_kind", "fault_box", "fault_config", "full_box", "full_config"]
