"""Host-side CAN drivers: CANopen CiA 301/402 drives in cyclic synchronous position mode.

The drive's object dictionary ships as an EDS file beside the code, read (as every
drive's device file) by :mod:`drivers.protocol.cia306`:

>>> from drivers.protocol.cia306 import canopen_dictionary, read_device_file
>>> od = canopen_dictionary(read_device_file(eds_path()), 5)
>>> hex(od[0x1400][1].default)
'0x205'
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

EDS_RESOURCE = "hrm_drive.eds"
DEFAULT_BOX_RESOURCE = "box.toml"


def eds_path() -> Path:
    """Path of the drive's EDS file (``drivers/data/hrm_drive.eds``).

    >>> eds_path().name
    'hrm_drive.eds'
    """
    return Path(str(resources.files("drivers.data").joinpath(EDS_RESOURCE)))


def default_box_path() -> Path:
    """Path of the default bus configuration (``drivers/data/box.toml``).

    >>> default_box_path().name
    'box.toml'
    """
    return Path(str(resources.files("drivers.data").joinpath(DEFAULT_BOX_RESOURCE)))
