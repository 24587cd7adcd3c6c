"""The box as a Lely ``dcfgen`` configuration (``hrm box export --lely DIR``), for ros2_canopen.

Lely's ``dcfgen`` (PyPI ``dcf-tools``) turns a ``bus.yml`` (a ``master``, one entry per
slave naming its device file, node id, heartbeats, PDOs and SDO writes) into the master's
DCF and one concise SDO script per slave, which Lely's master (and ros2_canopen on it) runs
at boot.  One master drives one bus, so the export writes one folder per bus of the box:

``DIR/BUS/bus.yml``
    ``options`` (``dcf_path`` empty: the files beside it; ``heartbeat_multiplier`` =
    ``heartbeat_timeout_ms`` / ``node_heartbeat_ms``: the master's watch of each drive),
    ``master`` (``node_id`` = ``host_node_id``, ``baudrate`` in kbit/s, ``sync_period`` in
    us, ``heartbeat_producer`` = ``host_heartbeat_ms``, its ``heartbeat_multiplier``:
    ``heartbeat_timeout_ms`` / ``host_heartbeat_ms``, each drive's watch of it), then one
    slave per rope motor: ``node_id``, ``dcf``, ``heartbeat_producer``
    (``node_heartbeat_ms``), ``heartbeat_consumer: true`` (a drive the host guards:
    ``heartbeat_producer: 0``, ``guard_time`` and ``life_time_factor``), the expected
    vendor-ID, product code, revision and serial number where the box configuration gives
    them, RPDO1 and TPDO1 as hrm maps them (on SYNC, ``cob_id: auto``: 0x200/0x180 + node), and
    ``sdo``: the box configuration's SDO overlay, then what hrm's bring-up writes from
    ``[control]`` (0x60C2 in the drive's encoding, 0x6065, 0x605A, 0x6060 = 8).  The
    software position limits 0x607D and the quick-stop deceleration 0x6085 come from the
    rope layer's limits (``hrm run`` writes them at every bring-up); they are not in the
    export.
``DIR/BUS/NAME.eds``
    each device file the bus uses, written again by :func:`cia306.format_device_file`
    (``dcfgen`` in strict mode refuses four of the six vendor files as their vendors ship
    them: a ``[ToolInfos]`` section, INTEGER8 ``0xFD``, ``SupportedObjects`` in hex).

Only a box ``hrm box check`` passes is exported (:class:`DeviceCheckError` otherwise).
:mod:`drivers.lely_bus` reads such a ``bus.yml`` back (``hrm box check --lely-bus``).

>>> from drivers.config import load_box_config
>>> text = bus_yml(load_box_config(None), "can0")
>>> print("\\n".join(text.splitlines()[:13]))
options:
  dcf_path: ""
  heartbeat_multiplier: 3.5
master:
  node_id: 127
  baudrate: 1000
  sync_period: 10000
  heartbeat_producer: 100
  heartbeat_multiplier: 3.5
j01r0:
  node_id: 1
  dcf: "hrm_drive.eds"
  heartbeat_producer: 100
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from drivers.config import BoxConfig
from drivers.device_check import BoxCheck, NodeCheck, check_box
from drivers.protocol import cia402
from drivers.protocol.cia306 import format_device_file, read_device_file
from hrm_ctrl.files import write_atomic


def _yaml(value: Any, indent: int) -> list[str]:
    """Block-style YAML of nested mappings and lists of scalars (what ``bus.yml`` holds):
    integers as written (hex where the key is an object or a value), strings quoted."""
    pad = "  " * indent
    out: list[str] = []
    if isinstance(value, Mapping):
        for key, v in value.items():
            if isinstance(v, Mapping | list) and v:
                out.append(f"{pad}{key}:")
                out += _yaml(v, indent + 1)
            else:
                out.append(f"{pad}{key}: {_scalar(v)}")
    else:
        for item in value:
            flow = ", ".join(f"{k}: {_scalar(v)}" for k, v in item.items())
            out.append(f"{pad}- {{{flow}}}")
    return out


def _scalar(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, Hex):
        return f"0x{int(v):04X}"
    if isinstance(v, int | float):
        return str(v)
    if isinstance(v, Mapping | list):
        return "{}" if isinstance(v, Mapping) else "[]"
    return json.dumps(str(v))


class Hex(int):
    """An integer ``bus.yml`` shows in hex (object indices)."""


def _slave(node: NodeCheck, config: BoxConfig, dcf: str) -> dict[str, Any]:
    ctl = config.control
    setup = node.setup
    slave: dict[str, Any] = {"node_id": node.node_id, "dcf": dcf}
    if setup.guarding is None:
        slave["heartbeat_producer"] = ctl.node_heartbeat_ms
        slave["heartbeat_consumer"] = True
    else:  # no heartbeat consumer: the master guards the drive (dcfgen writes 0x100C/0x100D)
        slave["heartbeat_producer"] = 0
        slave["guard_time"], slave["life_time_factor"] = setup.guarding
    for key, value in zip(
        ("vendor_id", "product_code", "revision_number", "serial_number"),
        setup.identity.values(),
        strict=True,
    ):
        if value is not None:
            slave[key] = value
    for kind, use in (("rpdo", node.verdict.pdos[0]), ("tpdo", node.verdict.pdos[1])):
        slave[kind] = {
            1: {
                "enabled": True,
                "cob_id": "auto",
                "transmission": use.transmission_type,
                "mapping": [
                    {"index": Hex(e.index), "sub_index": e.subindex} for e in use.layout.entries
                ],
            }
        }
    value, index = setup.interpolation or cia402.interpolation_time_period(ctl.period_s)
    writes = [(w.index, w.sub, w.value) for w in setup.sdo] + [
        (cia402.OD_INTERPOLATION_TIME_PERIOD, 1, value),
        (cia402.OD_INTERPOLATION_TIME_PERIOD, 2, index),
        (cia402.OD_FOLLOWING_ERROR_WINDOW, 0, ctl.following_error_window_counts),
        (cia402.OD_QUICK_STOP_OPTION_CODE, 0, ctl.quick_stop_option_code),
        (cia402.OD_MODES_OF_OPERATION, 0, cia402.MODE_CSP),
    ]
    slave["sdo"] = [{"index": Hex(i), "sub_index": s, "value": v} for i, s, v in writes]
    return slave


def _device_names(report: BoxCheck) -> dict[Path, str]:
    """A file name in the export for each device file (its stem, ``.eds``; numbered when
    two files share a stem)."""
    names: dict[Path, str] = {}
    for node in report.nodes:
        if node.path in names:
            continue
        stem, k = node.path.stem, 1
        while f"{stem}.eds" in names.values():
            k += 1
            stem = f"{node.path.stem}-{k}"
        names[node.path] = f"{stem}.eds"
    return names


def bus_yml(config: BoxConfig, bus: str, report: BoxCheck | None = None) -> str:
    """The ``bus.yml`` of bus ``bus`` of ``config`` (``report``: its :func:`check_box`)."""
    report = check_box(config) if report is None else report
    ctl = config.control
    the_bus = next(b for b in config.buses if b.name == bus)
    names = _device_names(report)
    doc: dict[str, Any] = {
        "options": {
            "dcf_path": "",
            "heartbeat_multiplier": ctl.heartbeat_timeout_ms / ctl.node_heartbeat_ms,
        },
        "master": {
            "node_id": ctl.host_node_id,
            "baudrate": the_bus.bitrate // 1000,
            "sync_period": round(ctl.period_s * 1e6),
            "heartbeat_producer": ctl.host_heartbeat_ms,
            "heartbeat_multiplier": ctl.heartbeat_timeout_ms / ctl.host_heartbeat_ms,
        },
    }
    for node in report.nodes:
        if node.bus == bus:
            doc[node.motor] = _slave(node, config, names[node.path])
    return "\n".join(_yaml(doc, 0)) + "\n"


def export_lely(config: BoxConfig, directory: Path) -> list[Path]:
    """Write ``directory/BUS/bus.yml`` and the device files it names for every bus of
    ``config`` (see the module); the files written.  :class:`DeviceCheckError` (nothing
    written) when ``hrm box check`` refuses the box."""
    report = check_box(config)
    report.raise_if_refused()
    names = _device_names(report)
    texts = {path: format_device_file(read_device_file(path), name) for path, name in names.items()}
    written = []
    for bus in config.buses:
        folder = directory / bus.name
        for path in {n.path for n in report.nodes if n.bus == bus.name}:
            write_atomic(folder / names[path], texts[path])
            written.append(folder / names[path])
        write_atomic(folder / "bus.yml", bus_yml(config, bus.name, report))
        written.append(folder / "bus.yml")
    return written
