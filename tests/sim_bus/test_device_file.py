"""The simulated drive holds the object dictionary of the device file it is given, read by
the drivers' one reader (``drivers.protocol.cia306``)."""

from __future__ import annotations

from pathlib import Path

import canopen
import pytest

from drivers import eds_path
from drivers.protocol.cia306 import canopen_dictionary, read_device_file
from sim_bus.drive import DriveSim
from sim_bus.drive.objects import SdoAbort

VENDOR = Path(__file__).parents[1] / "drivers" / "vendor_eds"
EPOS4 = VENDOR / "epos4_50_15_can_ec90flat_gp52c_mile800_node1.dcf"


def test_hrm_drive_as_canopen_reads_it() -> None:
    """hrm's own EDS gives the same dictionary through either reader."""
    ours = canopen_dictionary(read_device_file(eds_path()), 9)
    theirs = canopen.import_od(str(eds_path()), 9)
    for obj in theirs.values():
        subs = getattr(obj, "subindices", {0: obj})
        for sub, var in subs.items():
            mine = ours[obj.index][sub] if hasattr(obj, "subindices") else ours[obj.index]
            for attr in (
                "data_type",
                "access_type",
                "pdo_mappable",
                "default",
                "min",
                "max",
                "relative",
            ):
                assert getattr(mine, attr) == getattr(var, attr), (hex(obj.index), sub, attr)


def test_a_simulated_epos4_has_its_dcf_values() -> None:
    d = DriveSim(5, lambda m: None, eds=EPOS4)
    assert d.od.int_value(0x6502) == 0x3A5  # the DCF's ParameterValue (no DefaultValue)
    assert d.od.int_value(0x60A8) == 0x00B50000  # increments
    assert d.od.int_value(0x60C2, 2) == -3
    assert d.od.lookup(0x1600, 12).access_type == "rw"  # 12 mapping entries
    with pytest.raises(SdoAbort):
        d.od.lookup(0x1604, 0)  # 4 RPDOs only
    ours = DriveSim(5, lambda m: None)
    with pytest.raises(SdoAbort):
        ours.od.lookup(0x60A8, 0)
