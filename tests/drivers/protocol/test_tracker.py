"""The laser tracker's line protocol, byte for byte (builders and parsers are pure)."""

from __future__ import annotations

import functools
import operator

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

from drivers.protocol.tracker import (
    MAX_LINE_BYTES,
    REQUEST_MEASURE,
    STATUS_TARGET_LOST,
    Request,
    TrackerLineError,
    checksum,
    make_error_line,
    make_point_line,
    parse_reply,
    parse_request,
)


def _framed(body: bytes) -> bytes:
    """An independent framing: ``$`` body ``*`` XOR (two upper-case hex) CR LF."""
    cs = functools.reduce(operator.xor, body, 0)
    return b"$" + body + b"*" + b"%02X" % cs + b"\r\n"


def _wrong_checksum(body: bytes) -> bytes:
    cs = functools.reduce(operator.xor, body, 0) ^ 0x01
    return b"$" + body + b"*" + b"%02X" % cs + b"\r\n"


def test_request_bytes() -> None:
    assert REQUEST_MEASURE == b"\x4d\x45\x41\x53\x0a"  # "MEAS\n"
    assert parse_request(b"MEAS\n") is Request.MEASURE
    assert parse_request(b"MEAS\r\n") is Request.MEASURE
    assert parse_request(b"MEAS") is Request.MEASURE
    assert parse_request(b"meas\n") is None and parse_request(b"MEASURE\n") is None


@pytest.mark.parametrize(
    ("seq", "point", "status", "body"),
    [
        (0, [0.0, 0.0, 0.0], 0, b"PT,0,0.0000,0.0000,0.0000,00"),
        (65535, [-1234567.1234, 1.00005, 2.5], 0, b"PT,65535,-1234567.1234,1.0001,2.5000,00"),
        (65536, [1.0, 2.0, 3.0], 0, b"PT,0,1.0000,2.0000,3.0000,00"),  # wraps
        (12, [-0.00001, 0.0, 7.0], 0, b"PT,12,0.0000,0.0000,7.0000,00"),  # no "-0.0000"
        (3, None, STATUS_TARGET_LOST, b"PT,3,,,,01"),
    ],
)
def test_point_lines_byte_for_byte(seq, point, status, body) -> None:
    line = make_point_line(seq, point, status)
    assert line == _framed(body)
    assert len(line) <= MAX_LINE_BYTES
    r = parse_reply(line)
    assert r.seq == seq % 65536 and r.status == status and r.error is None
    if point is None:
        assert r.point_mm is None and r.target_lost
    else:
        assert not r.target_lost
        assert np.allclose(r.point_mm, point, atol=5e-5)


def test_error_line_byte_for_byte() -> None:
    assert make_error_line(9, "BADCMD") == _framed(b"ER,9,BADCMD")
    r = parse_reply(_framed(b"ER,9,BADCMD"))
    assert (r.seq, r.error, r.point_mm) == (9, "BADCMD", None)
    with pytest.raises(TrackerLineError, match="upper-case"):
        make_error_line(1, "bad")


def test_checksum_is_the_xor_between_dollar_and_star() -> None:
    assert checksum(b"") == 0 and checksum(b"\x01\x02\x04") == 7
    assert checksum(b"PT,1,,,,01") == functools.reduce(operator.xor, b"PT,1,,,,01", 0)


def test_builder_refuses_what_the_protocol_cannot_say() -> None:
    for bad in ([np.nan, 0, 0], [1e8, 0, 0], [1.0, 2.0]):
        with pytest.raises(TrackerLineError, match="3 finite"):
            make_point_line(1, bad)
    with pytest.raises(TrackerLineError, match="target-lost"):
        make_point_line(1, None)
    with pytest.raises(TrackerLineError, match="sequence"):
        make_point_line(-1, [0, 0, 0])
    with pytest.raises(TrackerLineError, match="one byte"):
        make_point_line(1, [0, 0, 0], 0x100)


@pytest.mark.parametrize(
    ("line", "why"),
    [
        (b"", "not a reply line"),
        (b"PT,1,0.0000,0.0000,0.0000,00*00\r\n", "not a reply line"),  # no $
        (b"$PT,1,0.0000,0.0000,0.0000,00\r\n", "not a reply line"),  # no checksum
        (_framed(b"PT,1,0.0000,0.0000,0.0000,00")[:-4] + b"zz\r\n", "two upper-case hex"),
        (_wrong_checksum(b"PT,1,0.0000,0.0000,0.0000,00"), "checksum"),
        (_framed(b"pt,1,1.0000,0.0000,0.0000,00"), "not a $PT or $ER"),
        (_framed(b"PT,1,1.000,0.0000,0.0000,00"), "not a $PT"),  # 3 decimals
        (_framed(b"PT,1,1e3,0.0000,0.0000,00"), "not a $PT"),
        (_framed(b"PT,1,nan,0.0000,0.0000,00"), "not a $PT"),
        (_framed(b"PT,1,,,,00"), "flag the target lost"),
        (_framed(b"PT,1,1.0000,0.0000,0.0000,01"), "must not carry"),
        (_framed(b"PT,1,1.0000,0.0000,0.0000,02"), "reserved"),
        (_framed(b"PT,99999,1.0000,0.0000,0.0000,00"), "beyond"),
        (_framed(b"PT,1,1.0000,0.0000,00"), "not a $PT"),
        (_framed(b"XX,1"), "not a $PT or $ER"),
        (_framed("PT,1,\u00e9".encode()), "not ASCII"),
        (b"$" + b"0" * 200 + b"*00\r\n", "longer than"),
    ],
)
def test_parser_refuses_with_one_line(line: bytes, why: str) -> None:
    with pytest.raises(TrackerLineError) as info:
        parse_reply(line)
    assert why in str(info.value) and "\n" not in str(info.value)


@settings(max_examples=200, deadline=None)
@given(st.binary(max_size=120))
@example(b"$*00")
@example(b"$PT*\r\n")
def test_random_bytes_never_crash_the_parser(data: bytes) -> None:
    try:
        r = parse_reply(data)
    except TrackerLineError:
        return
    assert r.point_mm is None or r.point_mm.shape == (3,)


@settings(max_examples=100, deadline=None)
@given(
    st.integers(0, 10**6),
    st.lists(st.floats(-9e6, 9e6, allow_nan=False), min_size=3, max_size=3),
)
def test_point_round_trip(seq: int, point: list[float]) -> None:
    r = parse_reply(make_point_line(seq, point))
    assert r.seq == seq % 65536
    assert np.abs(r.point_mm - np.array(point)).max() <= 5e-5 + 1e-9 * np.abs(point).max()
