"""SDO server of a simulated drive (CiA 301 7.2.4) for every object of the EDS.

Expedited and segmented upload and download; abort codes for a missing object
(0x06020000) or sub-index (0x06090011), read-only (0x06010002) / write-only
(0x06010001) access, wrong sizes (0x06070010/12/13), values out of range
(0x06090030/31/32), unmappable objects or too long PDO mappings
(0x06040041/42), a toggle error (0x05030000), an unknown command (0x05040001)
and mapping changes while the PDO is valid (0x06010000).  Frames that are not 8
bytes long are ignored (as CANopenNode does).  The device rules of a write are
asked of the service that owns the object (:meth:`DriveSim.check_write`).
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from enum import Enum
from typing import TYPE_CHECKING

import can
from canopen.objectdictionary import ODVariable

from drivers.protocol import cia301
from sim_bus.drive.objects import READABLE, WRITABLE, SdoAbort

if TYPE_CHECKING:
    from sim_bus.drive import DriveSim

MAX_SEGMENTED_BYTES = 4096


class TransferKind(Enum):
    UPLOAD = "upload"
    DOWNLOAD = "download"


@dataclass
class _Transfer:
    """A segmented transfer in progress."""

    kind: TransferKind
    index: int
    sub: int
    data: bytes
    toggle: int
    size: int | None = None  # download: the size the client announced, if any


class SdoServer:
    """The default SDO server (COB-IDs 0x600/0x580 + node id) of one drive."""

    def __init__(self, drive: DriveSim) -> None:
        self._drive = drive
        self._od = drive.od
        self._transfer: _Transfer | None = None

    def reset(self) -> None:
        """Reset communication: a transfer in progress is forgotten."""
        self._transfer = None

    def on_request(self, data: bytes, now: float) -> None:
        """One client request; answers with a response or an abort frame."""
        if len(data) != 8:
            return  # CANopenNode ignores SDO frames of another length
        cs = data[0] >> 5
        index, sub = struct.unpack_from("<HB", data, 1)
        try:
            if cs == cia301.SDO_CS_ABORT:
                self._transfer = None
            elif cs == cia301.SDO_CCS_INITIATE_UPLOAD:
                self._initiate_upload(index, sub)
            elif cs == cia301.SDO_CCS_UPLOAD_SEGMENT:
                self._upload_segment(data)
            elif cs == cia301.SDO_CCS_INITIATE_DOWNLOAD:
                self._initiate_download(data, index, sub, now)
            elif cs == cia301.SDO_CCS_DOWNLOAD_SEGMENT:
                self._download_segment(data, now)
            else:
                raise SdoAbort(cia301.SDO_ABORT_COMMAND_SPECIFIER)
        except (SdoAbort, ValueError, TypeError, KeyError, struct.error) as exc:
            code = exc.code if isinstance(exc, SdoAbort) else cia301.SDO_ABORT_GENERAL
            if not isinstance(exc, SdoAbort):
                self._drive.log(
                    f"SDO request {data.hex()} failed internally ({exc!r}): general abort"
                )
            if self._transfer is not None and cs in (
                cia301.SDO_CCS_UPLOAD_SEGMENT,
                cia301.SDO_CCS_DOWNLOAD_SEGMENT,
            ):
                index, sub = self._transfer.index, self._transfer.sub
            self._transfer = None
            self._drive.transmit(cia301.make_sdo_abort(self._drive.node_id, index, sub, code))

    def _reply(self, payload: bytes) -> None:
        self._drive.transmit(
            can.Message(
                arbitration_id=cia301.COB_SDO_TX + self._drive.node_id,
                data=payload.ljust(8, b"\x00"),
                is_extended_id=False,
            )
        )

    # ---------------------------------------------------------------- upload
    def read_object(self, index: int, sub: int = 0) -> bytes:
        """The encoded value of an object, as an SDO upload would return it."""
        var = self._od.lookup(index, sub)
        if var.access_type not in READABLE:
            raise SdoAbort(cia301.SDO_ABORT_WRITE_ONLY)
        return var.encode_raw(self._drive.live_value((index, sub)))

    def _initiate_upload(self, index: int, sub: int) -> None:
        self._transfer = None
        raw = self.read_object(index, sub)
        head = struct.pack("<HB", index, sub)
        if 0 < len(raw) <= 4:
            cmd = (cia301.SDO_SCS_INITIATE_UPLOAD << 5) | ((4 - len(raw)) << 2) | 0x03
            self._reply(bytes((cmd,)) + head + raw)
        else:
            cmd = (cia301.SDO_SCS_INITIATE_UPLOAD << 5) | 0x01
            self._reply(bytes((cmd,)) + head + struct.pack("<I", len(raw)))
            self._transfer = _Transfer(TransferKind.UPLOAD, index, sub, raw, 0)

    def _upload_segment(self, data: bytes) -> None:
        st = self._transfer
        if st is None or st.kind is not TransferKind.UPLOAD:
            raise SdoAbort(cia301.SDO_ABORT_COMMAND_SPECIFIER)
        toggle = (data[0] >> 4) & 1
        if toggle != st.toggle:
            raise SdoAbort(cia301.SDO_ABORT_TOGGLE_BIT)
        chunk, rest = st.data[:7], st.data[7:]
        last = not rest
        cmd = (cia301.SDO_SCS_UPLOAD_SEGMENT << 5) | (toggle << 4) | ((7 - len(chunk)) << 1) | last
        self._reply(bytes((cmd,)) + chunk)
        if last:
            self._transfer = None
        else:
            st.data, st.toggle = rest, toggle ^ 1

    # ---------------------------------------------------------------- download
    def _initiate_download(self, data: bytes, index: int, sub: int, now: float) -> None:
        self._transfer = None
        var = self._od.lookup(index, sub)
        if var.access_type not in WRITABLE:
            raise SdoAbort(cia301.SDO_ABORT_READ_ONLY)
        expedited = bool(data[0] & 0x02)
        size_given = bool(data[0] & 0x01)
        head = struct.pack("<HB", index, sub)
        if expedited:
            n = 4 - ((data[0] >> 2) & 0x03) if size_given else None
            if n is None:
                n = len(var) // 8 if var.fixed_size else 4
            self.write_object(index, sub, data[4 : 4 + n], now)
            self._reply(bytes((cia301.SDO_SCS_INITIATE_DOWNLOAD << 5,)) + head)
            return
        size = struct.unpack_from("<I", data, 4)[0] if size_given else None
        if size is not None and var.fixed_size:
            _check_size(var, size)
        self._transfer = _Transfer(TransferKind.DOWNLOAD, index, sub, b"", 0, size)
        self._reply(bytes((cia301.SDO_SCS_INITIATE_DOWNLOAD << 5,)) + head)

    def _download_segment(self, data: bytes, now: float) -> None:
        st = self._transfer
        if st is None or st.kind is not TransferKind.DOWNLOAD:
            raise SdoAbort(cia301.SDO_ABORT_COMMAND_SPECIFIER)
        toggle = (data[0] >> 4) & 1
        if toggle != st.toggle:
            raise SdoAbort(cia301.SDO_ABORT_TOGGLE_BIT)
        n = 7 - ((data[0] >> 1) & 0x07)
        st.data = st.data + data[1 : 1 + n]
        if len(st.data) > MAX_SEGMENTED_BYTES:
            raise SdoAbort(cia301.SDO_ABORT_OUT_OF_MEMORY)
        last = bool(data[0] & 0x01)
        if last:
            if st.size is not None and st.size != len(st.data):
                raise SdoAbort(cia301.SDO_ABORT_TYPE_MISMATCH)
            self.write_object(st.index, st.sub, st.data, now)
            self._transfer = None
        else:
            st.toggle = toggle ^ 1
        self._reply(bytes(((cia301.SDO_SCS_DOWNLOAD_SEGMENT << 5) | (toggle << 4),)))

    def write_object(self, index: int, sub: int, raw: bytes, now: float) -> None:
        """Validate and store a download; raises :class:`SdoAbort` with the CiA 301 code."""
        var = self._od.lookup(index, sub)
        if var.access_type not in WRITABLE:
            raise SdoAbort(cia301.SDO_ABORT_READ_ONLY)
        if var.fixed_size:
            _check_size(var, len(raw))
        value = var.decode_raw(raw)
        if isinstance(value, int):
            if var.min is not None and value < var.min:
                raise SdoAbort(cia301.SDO_ABORT_VALUE_TOO_LOW)
            if var.max is not None and value > var.max:
                raise SdoAbort(cia301.SDO_ABORT_VALUE_TOO_HIGH)
            self._drive.check_write(index, sub, value)
        self._od.write((index, sub), value)
        self._drive.after_write(index, sub, value, now)


def _check_size(var: ODVariable, size: int) -> None:
    want = len(var) // 8
    if size > want:
        raise SdoAbort(cia301.SDO_ABORT_LENGTH_TOO_HIGH)
    if size < want:
        raise SdoAbort(cia301.SDO_ABORT_LENGTH_TOO_LOW)
