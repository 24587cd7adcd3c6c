"""CAN frame bit lengths of drivers.protocol.frames: known frames, bit for bit."""

from __future__ import annotations

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from drivers.protocol import cia301, cia402
from drivers.protocol import frames as f
from hrm_ctrl.errors import DriverError


def bits(text: str) -> list[int]:
    return [int(ch) for ch in text]


def std(cob: int, data: bytes) -> can.Message:
    return can.Message(arbitration_id=cob, data=data, is_extended_id=False)


def test_crc15_is_crc15_can() -> None:
    # The catalogue check value of CRC-15/CAN over the ASCII digits "123456789".
    ascii_bits = [(byte >> (7 - i)) & 1 for byte in b"123456789" for i in range(8)]
    assert f.crc15(ascii_bits) == 0x059E
    assert f.crc15([]) == 0


# (frame, SOF..CRC pattern, stuff bits, exact bits, worst-case bits)
KNOWN = [
    (
        cia301.make_sync(),
        "0" + "00010000000" + "000" + "0000" + "001110000000101",
        4,
        51,
        55,
    ),
    (
        cia301.make_heartbeat(0x7F, cia301.NMT_STATE_OPERATIONAL),
        "0" + "11101111111" + "000" + "0001" + "00000101" + "110000001101000",
        4,
        59,
        65,
    ),
    (
        cia301.make_nmt(cia301.NMT_RESET_NODE, 0),
        "0" + "00000000000" + "000" + "0010" + "10000001" + "00000000" + "101100110011101",
        5,
        68,
        75,
    ),
    (
        cia402.make_rpdo_target(1, cia402.CW_ENABLE_OPERATION, 0),
        "0" + "01000000001" + "000" + "0110" + "00001111" + "00000000" * 5 + "001010101110110",
        11,
        106,
        115,
    ),
]


@pytest.mark.parametrize(("msg", "pattern", "stuff", "exact", "worst"), KNOWN)
def test_known_frames_bit_for_bit(
    msg: can.Message, pattern: str, stuff: int, exact: int, worst: int
) -> None:
    got = f.stuffable_bits(msg)
    assert got == bits(pattern)
    assert len(got) == f.stuffable_bit_count(len(msg.data))
    assert f.stuff_bit_count(got) == stuff
    assert f.frame_bits(msg, f.Stuffing.EXACT) == exact == len(got) + stuff + f.TRAILER_BITS
    assert f.frame_bits(msg) == f.frame_bits(msg, "worst") == worst


def test_worst_case_lengths() -> None:
    assert [f.worst_case_frame_bits(n) for n in range(9)] == [
        55,
        65,
        75,
        85,
        95,
        105,
        115,
        125,
        135,
    ]
    assert f.worst_case_frame_bits(8, extended_id=True) == 160
    assert f.worst_case_frame_bits(0, extended_id=True) == 80
    ext = can.Message(arbitration_id=0x18FF0000, data=bytes(8), is_extended_id=True)
    assert (f.frame_bits(ext), f.frame_bits(ext, "exact")) == (160, 151)
    rtr = can.Message(arbitration_id=0x701, is_remote_frame=True, dlc=1, is_extended_id=False)
    assert (f.frame_bits(rtr), f.frame_bits(rtr, "exact")) == (55, 51)  # a remote frame: no data


def test_stuff_bit_count_counts_the_stuff_bit_in_the_next_run() -> None:
    assert f.stuff_bit_count(bits("11111000")) == 1  # the stuff bit 0 joins the run
    assert f.stuff_bit_count(bits("111110000")) == 2
    assert f.stuff_bit_count(bits("0" * 15)) == 3
    assert f.stuff_bit_count(bits("01" * 20)) == 0


@settings(max_examples=100, deadline=None)
@given(st.integers(0, 0x7FF), st.binary(min_size=0, max_size=8))
def test_exact_never_exceeds_the_worst_case(cob: int, data: bytes) -> None:
    m = std(cob, data)
    assert 34 + 8 * len(data) + 13 <= f.frame_bits(m, "exact") <= f.frame_bits(m, "worst")


def test_bad_lengths_and_modes_raise() -> None:
    with pytest.raises(DriverError, match=r"0\.\.8"):
        f.worst_case_frame_bits(9)
    with pytest.raises(DriverError, match=r"0\.\.8"):
        f.stuffable_bits(can.Message(arbitration_id=1, data=bytes(12), is_fd=True))
    with pytest.raises(DriverError, match="stuffing"):
        f.frame_bits(std(1, b""), "best")  # type: ignore[arg-type]
    assert f.Stuffing("exact") is f.Stuffing.EXACT
