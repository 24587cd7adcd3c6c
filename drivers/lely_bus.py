"""A Lely ``dcfgen`` ``bus.yml`` read as a box configuration (``hrm box check --lely-bus``).

The subset of a ``bus.yml`` that maps onto hrm, one file a bus (one Lely master drives one
bus; :mod:`drivers.lely_export` writes what this reads):

``options``
    ``dcf_path`` (read, not used: each slave's ``dcf`` is taken from the ``bus.yml``'s
    folder), ``heartbeat_multiplier`` (x each slave's ``heartbeat_producer``: the host's
    watch of the drives, ``heartbeat_timeout_ms``).
``master``
    ``node_id`` (``host_node_id``), ``baudrate`` (kbit/s; default 1000),
    ``sync_period`` (us, required: hrm streams on SYNC; ``rate_hz``),
    ``heartbeat_producer`` (``host_heartbeat_ms``), ``heartbeat_multiplier`` (x the
    host's heartbeat: each drive's watch of the host, ``heartbeat_timeout_ms`` too: hrm
    has one timeout for both directions, so the two must agree), ``heartbeat_consumer``
    (read, not used: hrm always watches the drives).
every other key: a slave, named by its rope motor
    ``node_id`` (required), ``dcf`` (required: the device file), ``heartbeat_producer``
    (``node_heartbeat_ms``, the same on every slave; 0: none, a guarded drive),
    ``heartbeat_consumer`` (read, not used: hrm's drives always watch the host),
    ``vendor_id``, ``product_code``,
    ``revision_number``, ``serial_number`` (the expected identity), ``guard_time`` (of a
    drive the host guards: ``host_heartbeat_ms``; ``life_time_factor`` read, not used: hrm
    derives it from the heartbeat timeout), ``sdo`` (a list of
    ``{index, sub_index, value}``: the drive's SDO overlay; of the objects hrm's bring-up
    writes itself, 0x60C2 must give the SYNC period, 0x6060 CSP (8), and 0x6065 and 0x605A
    become ``[control]``'s ``following_error_window_counts`` and
    ``quick_stop_option_code``, the same on every slave; the others are refused),
    ``rpdo`` and ``tpdo`` (read, not used: hrm maps its own RPDO1 and TPDO1), ``driver``
    and ``package`` (ros2_canopen's; not used).

Every other ``[control]`` value is hrm's default.  Each file is one bus, named after the
folder it is in (``hrm box export --lely DIR`` writes ``DIR/BUS/bus.yml``; ``bus0``,
``bus1``, ... where the folder's name cannot name a bus), on SocketCAN channel of that
name: nothing is opened, the configuration is for ``hrm box check``.

Bad input is one line naming the file and the key (:class:`drivers.config.BusConfigError`):
YAML that does not parse (with its line), a duplicate or unknown key, a value of the wrong
kind, a file of more than 1 MiB; a value outside hrm's ranges is named by the
``box.toml`` key it maps to.

>>> import tempfile
>>> folder = Path(tempfile.mkdtemp()) / "can0"
>>> folder.mkdir()
>>> from drivers import eds_path
>>> _ = (folder / "bus.yml").write_text(
...     "master: {node_id: 127, sync_period: 10000, heartbeat_producer: 100}\\n"
...     f"j01r0: {{node_id: 1, dcf: {eds_path()}, heartbeat_producer: 100}}\\n")
>>> box = load_lely_buses([folder / "bus.yml"])
>>> [(b.name, b.nodes, b.bitrate) for b in box.buses], box.control.rate_hz
([('can0', {'j01r0': 1}, 1000000)], 100.0)
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import yaml

from drivers.config import (
    BRINGUP_OBJECTS,
    BUS_NAME_PATTERN,
    BoxConfig,
    BusConfigError,
    ControlConfig,
    box_config_from_dict,
    rate_problem,
)
from drivers.protocol import cia402
from hrm_ctrl.files import read_text_file

MAX_BUS_YML_BYTES = 2**20  # a bus of 127 slaves is some 100 kB

OPTIONS_KEYS = frozenset({"dcf_path", "heartbeat_multiplier"})
MASTER_KEYS = frozenset(
    {"node_id", "baudrate", "sync_period", "heartbeat_producer", "heartbeat_multiplier",
     "heartbeat_consumer", "driver", "package"}
)  # fmt: skip
SLAVE_KEYS = frozenset(
    {"node_id", "dcf", "heartbeat_producer", "heartbeat_consumer", "vendor_id", "product_code",
     "revision_number", "serial_number", "sdo", "rpdo", "tpdo", "driver", "package",
     "guard_time", "life_time_factor"}
)  # fmt: skip
SDO_KEYS = frozenset({"index", "sub_index", "value"})
#: slave key -> box.toml identity key
IDENTITY_OF = {
    "vendor_id": "vendor_id",
    "product_code": "product_code",
    "revision_number": "revision",
    "serial_number": "serial",
}
#: objects hrm writes itself that a bus.yml's sdo may give (the export writes them)
_CONTROL_OBJECTS = {
    cia402.OD_FOLLOWING_ERROR_WINDOW: "following_error_window_counts",
    cia402.OD_QUICK_STOP_OPTION_CODE: "quick_stop_option_code",
}


class _Loader(yaml.SafeLoader):
    """PyYAML's safe loader, refusing a key given twice in one mapping."""


def _mapping(loader: _Loader, node: yaml.MappingNode) -> dict[Any, Any]:
    seen = set()
    for key_node, _value in node.value:
        key = loader.construct_object(key_node)
        try:
            duplicate = key in seen
        except TypeError:  # an unhashable key: PyYAML's own error below names it
            continue
        if duplicate:
            raise yaml.constructor.ConstructorError(
                None, None, f"duplicate key {key!r}", key_node.start_mark
            )
        seen.add(key)
    return dict(loader.construct_mapping(node))


_Loader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _mapping)


def parse_bus_yml(text: str, source: str) -> dict[str, Any]:
    """The YAML document of a ``bus.yml`` (a mapping), or one-line
    :class:`BusConfigError` naming ``source`` and the line.

    >>> parse_bus_yml("master: {node_id: 1}", "b.yml")
    {'master': {'node_id': 1}}
    >>> parse_bus_yml("a: 1\\na: 2\\n", "b.yml")
    Traceback (most recent call last):
    drivers.config.BusConfigError: b.yml: line 2: duplicate key 'a'
    """
    try:
        doc = yaml.load(text, Loader=_Loader)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        line = f"line {mark.line + 1}: " if mark is not None else ""
        what = " ".join(str(exc.problem or exc.context or "not YAML").split())
        raise BusConfigError(f"{source}: {line}{what}") from None
    except yaml.YAMLError as exc:
        raise BusConfigError(f"{source}: not YAML ({' '.join(str(exc).split())})") from None
    except RecursionError:
        raise BusConfigError(f"{source}: nested too deeply") from None
    if not isinstance(doc, dict):
        raise BusConfigError(f"{source}: must be a mapping of options, master and slaves")
    return doc


def _int(value: Any, where: str, lo: int | None = None, hi: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise BusConfigError(f"{where}: expected an integer, got {value!r}")
    if (lo is not None and value < lo) or (hi is not None and value > hi):
        raise BusConfigError(f"{where}: {value} outside {lo}..{hi}")
    return value


def _number(value: Any, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not value > 0:
        raise BusConfigError(f"{where}: expected a positive number, got {value!r}")
    return float(value)


def _table(value: Any, where: str, keys: frozenset[str]) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise BusConfigError(f"{where}: must be a mapping")
    for key in value:
        if key not in keys:
            raise BusConfigError(
                f"{where}.{key}: unknown key (hrm reads: {', '.join(sorted(keys))})"
            )
    return value


class _Agreed:
    """One ``[control]`` value several keys of several files give: they must agree."""

    def __init__(self) -> None:
        self.values: dict[str, tuple[Any, str]] = {}

    def set(self, key: str, value: Any, where: str, tolerance: float = 0.0) -> None:
        if key in self.values:
            old, old_where = self.values[key]
            if abs(value - old) > tolerance:
                raise BusConfigError(
                    f"{where}: gives {key} = {value:g}, {old_where} gave {old:g}: hrm has one "
                    f"{key} for the whole box"
                )
        else:
            self.values[key] = (value, where)


def _sdo(entries: Any, where: str, control: _Agreed, period_s: float) -> dict[str, int]:
    """A slave's ``sdo`` list as a ``box.toml`` overlay (``"0xIIII:SS" = value``)."""
    if not isinstance(entries, list):
        raise BusConfigError(f"{where}: must be a list of {{index, sub_index, value}}")
    overlay: dict[str, int] = {}
    period: dict[int, int] = {}
    for k, e in enumerate(entries):
        w = f"{where}[{k}]"
        _table(e, w, SDO_KEYS)
        for key in ("index", "value"):
            if key not in e:
                raise BusConfigError(f"{w}: missing key '{key}'")
        index = _int(e["index"], f"{w}.index", 0x1000, 0xFFFF)
        sub = _int(e.get("sub_index", 0), f"{w}.sub_index", 0, 0xFF)
        value = _int(e["value"], f"{w}.value")
        if index in _CONTROL_OBJECTS and sub == 0:
            control.set(_CONTROL_OBJECTS[index], value, f"{w} (0x{index:04X})")
            continue
        if index == cia402.OD_MODES_OF_OPERATION and sub == 0:
            if value != cia402.MODE_CSP:
                raise BusConfigError(
                    f"{w}: 0x6060 = {value}: hrm drives in cyclic synchronous position mode (8)"
                )
            continue
        if index == cia402.OD_INTERPOLATION_TIME_PERIOD and sub in (1, 2):
            period[sub] = value
            continue
        if any(index == i and (s is None or s == sub) for i, s in BRINGUP_OBJECTS):
            raise BusConfigError(
                f"{w}: hrm's bring-up writes 0x{index:04X} itself (from [control] and the rope "
                "layer)"
            )
        overlay[f"0x{index:04X}:{sub:02X}"] = value
    if period:
        value, exponent = period.get(1), period.get(2)
        signed = None if exponent is None else (exponent - 256 if exponent > 127 else exponent)
        if value is None or signed is None or abs(value * 10.0**signed - period_s) > 1e-9:
            raise BusConfigError(
                f"{where}: 0x60C2 = {value} x 10^{signed} s is not master.sync_period "
                f"({period_s * 1e6:g} us)"
            )
    return overlay


def _bus_name(path: Path, k: int, taken: set[str]) -> str:
    name = path.resolve().parent.name
    if not BUS_NAME_PATTERN.fullmatch(name) or name in taken:
        name = f"bus{k}"
    return name


def load_lely_buses(paths: Sequence[str | Path]) -> BoxConfig:
    """The box of the ``bus.yml`` files ``paths`` (one bus each; see the module)."""
    control = _Agreed()
    buses: dict[str, Any] = {}
    drives: dict[str, Any] = {}
    for k, p in enumerate(paths):
        path = Path(p)
        source = str(path)
        text = read_text_file(
            path, BusConfigError, "Lely bus.yml", source, max_bytes=MAX_BUS_YML_BYTES
        )
        doc = parse_bus_yml(text, source)
        options = _table(doc.get("options", {}), f"{source}: options", OPTIONS_KEYS)
        if "master" not in doc:
            raise BusConfigError(f"{source}: master: missing (its node id and sync_period)")
        master = _table(doc["master"], f"{source}: master", MASTER_KEYS)
        w = f"{source}: master"
        if "sync_period" not in master:
            raise BusConfigError(f"{w}.sync_period: missing (hrm streams on SYNC)")
        sync_us = _int(master["sync_period"], f"{w}.sync_period", 1, 10**8)
        rate = 1e6 / sync_us
        problem = rate_problem(rate)
        if problem:
            raise BusConfigError(f"{w}.sync_period: {sync_us} us: {problem}")
        control.set("rate_hz", rate, f"{w}.sync_period", 1e-9)
        if "node_id" in master:
            control.set("host_node_id", _int(master["node_id"], f"{w}.node_id", 1, 127), w)
        host_hb = None
        if "heartbeat_producer" in master:
            host_hb = _int(master["heartbeat_producer"], f"{w}.heartbeat_producer", 1, 65535)
            control.set("host_heartbeat_ms", host_hb, f"{w}.heartbeat_producer")
        if "heartbeat_multiplier" in master:
            factor = _number(master["heartbeat_multiplier"], f"{w}.heartbeat_multiplier")
            base = host_hb or ControlConfig().host_heartbeat_ms
            control.set("heartbeat_timeout_ms", round(factor * base), f"{w}.heartbeat_multiplier")
        bitrate = _int(master.get("baudrate", 1000), f"{w}.baudrate", 1, 1000) * 1000
        slaves = {key: v for key, v in doc.items() if key not in ("options", "master")}
        if not slaves:
            raise BusConfigError(f"{source}: no slave (a key naming a rope motor)")
        nodes: dict[str, int] = {}
        for motor, slave in slaves.items():
            ws = f"{source}: {motor}"
            if not isinstance(motor, str):
                raise BusConfigError(f"{ws}: a slave is named by its rope motor (a string)")
            _table(slave, ws, SLAVE_KEYS)
            for key in ("node_id", "dcf"):
                if key not in slave:
                    raise BusConfigError(f"{ws}.{key}: missing")
            nodes[motor] = _int(slave["node_id"], f"{ws}.node_id", 1, 127)
            if not isinstance(slave["dcf"], str) or not slave["dcf"]:
                raise BusConfigError(f"{ws}.dcf: expected the path of an EDS or DCF")
            if "heartbeat_consumer" in slave and not isinstance(slave["heartbeat_consumer"], bool):
                raise BusConfigError(f"{ws}.heartbeat_consumer: expected true or false")
            spec: dict[str, Any] = {"device_file": str(path.parent / slave["dcf"])}
            if "guard_time" in slave:  # node guarding: at the host heartbeat's period
                guard = _int(slave["guard_time"], f"{ws}.guard_time", 1, 65535)
                control.set("host_heartbeat_ms", guard, f"{ws}.guard_time")
            if "life_time_factor" in slave:
                _int(slave["life_time_factor"], f"{ws}.life_time_factor", 0, 255)
            hb = _int(slave.get("heartbeat_producer", 0), f"{ws}.heartbeat_producer", 0, 65535)
            if hb:  # 0: no heartbeat (a guarded drive)
                control.set("node_heartbeat_ms", hb, f"{ws}.heartbeat_producer")
                if "heartbeat_multiplier" in options:
                    factor = _number(
                        options["heartbeat_multiplier"], f"{source}: options.heartbeat_multiplier"
                    )
                    control.set(
                        "heartbeat_timeout_ms",
                        round(factor * hb),
                        f"{source}: options.heartbeat_multiplier",
                        0.5,
                    )
            identity = {
                IDENTITY_OF[key]: _int(slave[key], f"{ws}.{key}", 0, 2**32 - 1)
                for key in IDENTITY_OF
                if key in slave
            }
            if identity:
                spec["identity"] = identity
            sdo = _sdo(slave.get("sdo", []), f"{ws}.sdo", control, sync_us / 1e6)
            if sdo:
                spec["sdo"] = sdo
            drives[motor] = spec
        name = _bus_name(path, k, set(buses))
        buses[name] = {
            "interface": "socketcan",
            "channel": name,
            "bitrate": bitrate,
            "nodes": nodes,
        }
    ctl = {key: value for key, (value, _where) in control.values.items()}
    doc_box: dict[str, Any] = {"control": ctl, "buses": buses, "drives": drives}
    return box_config_from_dict(doc_box, ", ".join(str(p) for p in paths))
