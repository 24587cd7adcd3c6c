"""drivers/protocol/pdo.py: one layout per PDO; every encoder of the host's setpoint RPDO
and feedback TPDO gives the same bytes, written out here by hand."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.bus import BusPort
from drivers.cycle import BusLayout
from drivers.protocol import batch, cia301, cia402
from drivers.protocol.pdo import PdoEntry, PdoLayout

U16 = st.integers(0, 0xFFFF)
I32 = st.integers(cia402.INT32_MIN, cia402.INT32_MAX)


def by_hand(word: int, value: int) -> bytes:
    """UNSIGNED16 then INTEGER32, little-endian (CiA 301 7.1.2)."""
    return word.to_bytes(2, "little") + value.to_bytes(4, "little", signed=True)


def test_the_layouts_map_what_the_drives_are_configured_with() -> None:
    assert cia402.RPDO_TARGET.mapping == (0x60400010, 0x607A0020)
    assert cia402.TPDO_FEEDBACK.mapping == (0x60410010, 0x60640020)
    assert cia402.RPDO_TARGET.size == cia402.TPDO_FEEDBACK.size == batch.RPDO_DLC == 6
    assert cia402.RPDO_TARGET_LAYOUT is cia402.RPDO_TARGET.struct  # one encoder, named twice


@given(U16, I32, st.integers(1, 127))
def test_every_rpdo_encoder_gives_the_same_bytes(cw: int, target: int, node: int) -> None:
    want = by_hand(cw, target)
    assert cia402.RPDO_TARGET.pack(cw, target) == want
    assert bytes(cia402.make_rpdo_target(node, cw, target).data) == want
    assert cia402.make_rpdo_target_payloads(np.array([cw]), np.array([target])) == want
    b = batch.rpdo_batch(np.array([0x200 + node]), cw, np.array([target]))
    assert bytes(b[0]["data"][:6]) == want and b[0]["dlc"] == 6
    lay = BusLayout(BusPort("b", None), np.array([0]), np.array([node]))
    assert bytes(lay.rpdo_frames(cw, np.array([target]))[0].data) == want
    assert bytes(lay.rpdo_batch(cw, np.array([target]))[0]["data"][:6]) == want
    # and every parser reads it back
    assert cia402.parse_rpdo_target(want) == (cw, target)
    assert cia402.RPDO_TARGET.unpack(want) == (cw, target)
    v = b.view(batch.RPDO_VIEW)[0]
    assert (int(v["controlword"]), int(v["target"])) == (cw, target)


@given(U16, I32, st.integers(1, 127))
def test_every_tpdo_encoder_and_parser_agree(sw: int, pos: int, node: int) -> None:
    want = by_hand(sw, pos)
    msg = cia402.make_tpdo_feedback(node, sw, pos)
    assert bytes(msg.data) == want == cia402.TPDO_FEEDBACK.pack(sw, pos)
    assert cia402.parse_tpdo(want) == (sw, pos)
    v = batch.from_messages([msg]).view(batch.TPDO_VIEW)[0]
    assert (int(v["statusword"]), int(v["position"])) == (sw, pos)


def test_a_controlword_is_taken_modulo_16_bits_and_a_target_must_fit() -> None:
    assert cia402.RPDO_TARGET.pack(0x1000F, 1) == by_hand(0x000F, 1)
    with pytest.raises(cia301.FrameError, match=r"^target position 2147483648 outside INTEGER32$"):
        cia402.RPDO_TARGET.pack(0, 2**31)
    with pytest.raises(cia301.FrameError, match=r"^target position outside INTEGER32$"):
        cia402.RPDO_TARGET.pack_many(controlword=0, target=np.array([0, -(2**31) - 1]))
    lay = BusLayout(BusPort("b", None), np.array([0]), np.array([1]))
    with pytest.raises(cia301.FrameError, match="outside INTEGER32"):
        lay.rpdo_batch(0, np.array([2**31]))
    with pytest.raises(cia301.FrameError, match="must carry 6 bytes, got 5"):
        cia402.RPDO_TARGET.unpack(bytes(5))


def test_a_layout_of_a_mapping_compares_by_what_is_on_the_wire() -> None:
    codes = {0x6040: "H", 0x607A: "i"}
    layout = PdoLayout.of_mapping(cia402.RPDO_TARGET.mapping, lambda i, s, b: codes.get(i))
    assert layout == cia402.RPDO_TARGET  # names differ, the entries do not
    assert layout.pack(15, -2) == by_hand(15, -2)


def test_dummy_and_raw_entries() -> None:
    layout = PdoLayout(
        (
            PdoEntry("a", 0x2000, 1, "B"),
            PdoEntry("gap", 0x0005, 0, "2x"),
            PdoEntry("s", 0x2001, 0, "3s"),
        )
    )
    assert layout.size == 6 and [e.name for e in layout.values] == ["a", "s"]
    assert layout.offsets == (0, 3)
    assert layout.pack(0x1FF, b"abc") == b"\xff\x00\x00abc"
    assert layout.unpack(b"\x01\x00\x00xyz") == (1, b"xyz")
    assert layout.mapping == (0x20000108, 0x00050010, 0x20010018)
