"""The shipped EDS loads with canopen and holds every object the drivers use."""

from __future__ import annotations

import canopen
import pytest

from drivers import eds_path
from drivers.protocol import cia402 as c


@pytest.fixture(scope="module")
def od() -> canopen.ObjectDictionary:
    return canopen.import_od(str(eds_path()), 0x21)


REQUIRED = [
    0x1000, 0x1001, 0x1005, 0x1014, 0x1016, 0x1017, 0x1018, 0x1400, 0x1600, 0x1800, 0x1A00,
    0x603F, 0x6040, 0x6041, 0x605A, 0x6060, 0x6061, 0x6064, 0x6065, 0x607A, 0x607D, 0x60C2,
]  # fmt: skip


@pytest.mark.parametrize("index", REQUIRED)
def test_object_present(od: canopen.ObjectDictionary, index: int) -> None:
    assert index in od


def test_defaults(od: canopen.ObjectDictionary) -> None:
    assert od[0x1000].default == 0x00020192
    assert od[0x1400][1].default == 0x200 + 0x21
    assert od[0x1800][1].default == 0x180 + 0x21
    assert od[0x1014].default == 0x80 + 0x21
    assert (od[0x1600][1].default, od[0x1600][2].default) == c.RPDO_TARGET_MAPPING
    assert (od[0x1A00][1].default, od[0x1A00][2].default) == c.TPDO_FEEDBACK_MAPPING
    for index in (0x6040, 0x6041, 0x6064, 0x607A):
        assert od[index].pdo_mappable
    assert od[0x6041].access_type == "ro" and od[0x607A].access_type == "rw"
    assert od[0x607D][1].data_type == canopen.objectdictionary.INTEGER32
    assert od[0x60C2][2].data_type == canopen.objectdictionary.INTEGER8
