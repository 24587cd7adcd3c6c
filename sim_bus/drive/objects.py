"""The object dictionary of one simulated drive: the shipped EDS, its values, access rules.

Every service of :class:`~sim_bus.drive.DriveSim` reads and writes its objects
here; the SDO server (:mod:`sim_bus.drive.sdo_server`) is the only way in from
the bus besides the PDOs.

>>> od = ObjectDictionary(5)
>>> hex(od.int_value(0x1400, 1))                # RPDO1 COB-ID: $NODEID + 0x200
'0x205'
>>> od.lookup(0x2000, 0)
Traceback (most recent call last):
...
sim_bus.drive.objects.SdoAbort: SDO abort 0x06020000
"""

from __future__ import annotations

import functools
import re
from pathlib import Path

import canopen
from canopen.objectdictionary import ODArray, ODRecord, ODVariable, datatypes

from drivers import eds_path
from drivers.protocol import cia301
from drivers.protocol.cia306 import canopen_dictionary, read_device_file

Key = tuple[int, int]
Value = int | str | bytes

READABLE = frozenset({"ro", "rw", "rwr", "rww", "const"})
WRITABLE = frozenset({"rw", "wo", "rwr", "rww"})


class SdoAbort(Exception):  # noqa: N818 (an SDO abort answer, not a stack error)
    """An access the drive refuses, with its CiA 301 abort code (answered as an SDO abort).

    Internal to the simulated drive: the SDO server turns it into an abort frame.
    """

    def __init__(self, code: int) -> None:
        super().__init__(f"SDO abort 0x{code:08X}")
        self.code = code


@functools.lru_cache(maxsize=8)
def _load_od(path: str) -> canopen.ObjectDictionary:
    """The device file read by the drivers' one reader (:mod:`drivers.protocol.cia306`)."""
    return canopen_dictionary(read_device_file(path))


def object_table(path: str | Path | None = None) -> dict[Key, ODVariable]:
    """Every (index, sub-index) of the EDS with its canopen variable description.

    >>> t = object_table()
    >>> (0x6041, 0) in t, (0x607D, 2) in t, (0x1016, 1) in t
    (True, True, True)
    """
    od = _load_od(str(path if path is not None else eds_path()))
    out: dict[Key, ODVariable] = {}
    for obj in od.values():
        if isinstance(obj, ODRecord | ODArray):
            for sub in obj.subindices.values():
                out[(obj.index, sub.subindex)] = sub
        else:
            out[(obj.index, 0)] = obj
    return out


def _default_value(var: ODVariable, node_id: int) -> Value:
    raw = getattr(var, "default_raw", None)
    if getattr(var, "relative", False) and raw is not None:
        return int(re.sub(r"\+?\$NODEID\+?", "", raw.replace(" ", "").upper()), 0) + node_id
    if var.default is None:
        if var.data_type == datatypes.VISIBLE_STRING:
            return ""
        if var.data_type in (datatypes.DOMAIN, datatypes.OCTET_STRING):
            return b""
        return 0
    return var.default


#: Objects a drive writes every cycle (an RPDO's controlword and target position): written
#: without a new :attr:`ObjectDictionary.generation`, so no service may cache anything
#: derived from them.
CYCLIC_KEYS = frozenset({(0x6040, 0), (0x607A, 0)})


class ObjectDictionary:
    """Values of every EDS object of the drive at ``node_id`` (``$NODEID`` resolved).

    ``generation`` changes with every write but those of :data:`CYCLIC_KEYS` (and with
    every reset): a service keeps what it derives from its parameters (PDO communication
    and mapping, heartbeat consumers, the interpolation period) while the generation it
    was derived at is current, instead of reading and decoding them again at every SYNC.
    Writes go through :meth:`write`.

    >>> od = ObjectDictionary(5)
    >>> g = od.generation
    >>> od.write((0x607A, 0), 100); od.generation == g
    True
    >>> od.write((0x1017, 0), 100); od.generation == g
    False
    """

    def __init__(self, node_id: int, eds: str | Path | None = None) -> None:
        self.node_id = node_id
        self.objects = object_table(eds)
        self._indices = frozenset(index for index, _sub in self.objects)
        self.values: dict[Key, Value] = {}
        self.generation = 0
        self.reset()

    def reset(self) -> None:
        """Power-on / reset node: every object to its EDS default."""
        self.values = {key: _default_value(var, self.node_id) for key, var in self.objects.items()}
        self.generation += 1

    def reset_communication(self) -> None:
        """Reset communication: the communication objects (0x1000..0x1FFF but the error
        register 0x1001) to their defaults."""
        for key, var in self.objects.items():
            if 0x1000 <= key[0] < 0x2000 and key[0] != cia301.OD_ERROR_REGISTER:
                self.values[key] = _default_value(var, self.node_id)
        self.generation += 1

    def write(self, key: Key, value: Value) -> None:
        """Store a value (a new generation unless ``key`` is one of :data:`CYCLIC_KEYS`)."""
        self.values[key] = value
        if key not in CYCLIC_KEYS:
            self.generation += 1

    def int_value(self, index: int, sub: int = 0) -> int:
        """The value of an integer object."""
        return int(self.values[(index, sub)])  # type: ignore[arg-type]

    def lookup(self, index: int, sub: int) -> ODVariable:
        """The description of an object; :class:`SdoAbort` 0x06020000 (no object) or
        0x06090011 (no sub-index) when the EDS has none."""
        var = self.objects.get((index, sub))
        if var is None:
            if index not in self._indices:
                raise SdoAbort(cia301.SDO_ABORT_NO_OBJECT)
            raise SdoAbort(cia301.SDO_ABORT_NO_SUBINDEX)
        return var
