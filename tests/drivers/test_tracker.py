"""The host's laser-tracker reader over a real pseudo-terminal, against the simulated
instrument (``sim_bus.tracker``) and against raw bytes written to the line."""

from __future__ import annotations

import os
import threading
import tty
from collections.abc import Iterator

import numpy as np
import pytest

from drivers import default_box_path
from drivers.config import BusConfigError, load_box_config
from drivers.protocol.tracker import make_error_line, make_point_line
from drivers.tracker import TrackerError, TrackerReader, TrackerTargetLostError
from sim_bus.tracker import Tracker

POINT = np.array([1500.0, -200.0, 300.0])


def _rotation(yaw: float, pitch: float) -> np.ndarray:
    cy, sy, cp, sp = np.cos(yaw), np.sin(yaw), np.cos(pitch), np.sin(pitch)
    Rz = np.array([[cy, -sy, 0.0], [sy, cy, 0.0], [0.0, 0.0, 1.0]])
    Ry = np.array([[cp, 0.0, sp], [0.0, 1.0, 0.0], [-sp, 0.0, cp]])
    return Rz @ Ry


R = _rotation(0.7, -0.05)
T = np.array([-800.0, 2100.0, 150.0])


@pytest.fixture
def instrument() -> Iterator[Tracker]:
    with Tracker(lambda: POINT, R, T, noise_mm=0.05, seed=4) as t:
        yield t


def test_noise_statistics_and_frame(instrument: Tracker) -> None:
    with TrackerReader(instrument.port, timeout_s=2.0) as reader:
        pts = np.array([reader.measure(1) for _ in range(400)])
        mean10 = reader.measure(10)
        assert reader.readings == 410
    want = R @ POINT + T
    assert np.abs(pts.mean(axis=0) - want).max() < 0.02  # 4 sigma of the mean: 0.01 mm
    sd = pts.std(axis=0, ddof=1)
    assert (np.abs(sd - 0.05) < 0.01).all(), sd  # sigma 0.05 mm per axis
    assert np.abs(mean10 - want).max() < 0.08  # sigma/sqrt(10) = 0.016 mm, 5 sigma
    # independent axes: no strong correlation between them
    c = np.corrcoef(pts.T)
    assert np.abs(c[np.triu_indices(3, 1)]).max() < 0.2
    # the instrument saw every request (counted before it answers)
    assert instrument.requests == 410


def test_timeout_when_silent_then_recovers(instrument: Tracker) -> None:
    with TrackerReader(instrument.port, timeout_s=0.05) as reader:
        instrument.set_silent(True)
        with pytest.raises(TrackerError, match=r"no reply within 0\.05 s") as info:
            reader.measure(3)
        assert instrument.port in str(info.value) and "\n" not in str(info.value)
        instrument.set_silent(False)
        assert reader.measure(2).shape == (3,)


def test_lost_target_is_its_own_error(instrument: Tracker) -> None:
    with TrackerReader(instrument.port, timeout_s=1.0) as reader:
        instrument.lose_target(True)
        with pytest.raises(TrackerTargetLostError, match="target lost"):
            reader.measure()
        instrument.lose_target(False)
        assert np.abs(reader.measure() - (R @ POINT + T)).max() < 0.5


def test_garbage_is_a_bad_reply(instrument: Tracker) -> None:
    with TrackerReader(instrument.port, timeout_s=1.0) as reader:
        instrument.inject_garbage(1)
        with pytest.raises(TrackerError, match="bad reply") as info:
            reader.measure(5)  # no partial mean: the first bad reading raises
        assert info.value.__class__ is TrackerError
        assert reader.measure().shape == (3,)


def _raw_line() -> tuple[int, str]:
    master, slave = os.openpty()
    tty.setraw(slave)
    return master, os.ttyname(slave)


def _answer_with(master: int, replies: list[bytes], done: threading.Event) -> None:
    """Read requests on ``master``; answer the k-th with ``replies[k]``."""
    k = 0
    while not done.is_set() and k < len(replies):
        try:
            data = os.read(master, 64)
        except OSError:
            return
        for _ in range(data.count(b"\n")):
            if k < len(replies):
                os.write(master, replies[k])
                k += 1


@pytest.mark.parametrize(
    ("reply", "error", "match"),
    [
        (b"$PT,1,1.0000,2.0000,3.0000,00*FF\r\n", TrackerError, "bad reply.*checksum"),
        (b"PT,1,1.0000,2.0000,3.0000,00*00\r\n", TrackerError, "bad reply.*not a reply"),
        (b"$PT,1,1.00", TrackerError, "incomplete"),  # no end of line
        (b"x" * 200, TrackerError, "bad reply.*longer"),
    ],
)
def test_bad_replies_on_a_raw_line(reply: bytes, error: type, match: str) -> None:
    master, port = _raw_line()
    done = threading.Event()
    t = threading.Thread(target=_answer_with, args=(master, [reply], done), daemon=True)
    t.start()
    try:
        with TrackerReader(port, timeout_s=0.2) as reader, pytest.raises(error, match=match):
            reader.measure()
    finally:
        done.set()
        os.close(master)
        t.join(1.0)


def test_error_reply_and_a_reply_left_over_from_a_timeout() -> None:
    master, port = _raw_line()
    try:
        with TrackerReader(port, timeout_s=0.1) as reader:
            # an error reply: the instrument refused the request
            os.write(master, make_error_line(1, "BADCMD"))  # waiting before the request
            done = threading.Event()
            replies = [make_error_line(2, "BADCMD"), make_point_line(3, [1.0, 2.0, 3.0])]
            t = threading.Thread(target=_answer_with, args=(master, replies, done), daemon=True)
            t.start()
            with pytest.raises(TrackerError, match="refused the request"):
                reader.measure()
            # the stale error line written before the request was dropped, not taken
            assert reader.measure().tolist() == [1.0, 2.0, 3.0]
            assert reader.last_seq == 3
            done.set()
            t.join(1.0)
    finally:
        os.close(master)


def test_bad_arguments_and_missing_port(tmp_path) -> None:
    with pytest.raises(TrackerError, match="cannot open"):
        TrackerReader(str(tmp_path / "no-such-tty"), timeout_s=0.5)
    for bad in (0.0, float("nan"), 11.0):
        with pytest.raises(TrackerError, match="timeout_s"):
            TrackerReader("/dev/null", timeout_s=bad)
    master, port = _raw_line()
    try:
        reader = TrackerReader(port, timeout_s=0.1)
        for n in (0, 10_001, 2.0):
            with pytest.raises(TrackerError, match="readings per measurement"):
                reader.measure(n)  # type: ignore[arg-type]
        reader.close()
        with pytest.raises(TrackerError, match="closed"):
            reader.measure()
        reader.close()  # twice is fine
    finally:
        os.close(master)


def test_tracker_table_in_the_bus_configuration(tmp_path) -> None:
    base = load_box_config(None)
    cfg = base.with_tracker(port="/dev/ttyUSB1", timeout_s=0.5)
    assert (cfg.tracker.port, cfg.tracker.timeout_s, cfg.tracker.baudrate) == (
        "/dev/ttyUSB1",
        0.5,
        115_200,
    )
    assert cfg.with_control(missing_tpdo_cycles=5).tracker == cfg.tracker  # kept on copies
    assert base.tracker is None
    for changes, match in [
        ({"timeout_s": 0.001}, "tracker.timeout_s"),
        ({"timeout_s": True}, "tracker.timeout_s"),
        ({"baudrate": 10}, "tracker.baudrate"),
        ({"colour": 1}, "tracker.colour: unknown key"),
    ]:
        with pytest.raises(BusConfigError, match=match):
            cfg.with_tracker(**changes)
    with pytest.raises(BusConfigError, match=r"tracker\.port: missing"):
        base.with_tracker(timeout_s=1.0)
    path = tmp_path / "box.toml"
    path.write_text(
        default_box_path().read_text() + '\n[tracker]\nport = "/dev/ttyACM0"\ntimeout_s = 2\n'
    )
    loaded = load_box_config(path)
    assert loaded.tracker.port == "/dev/ttyACM0" and loaded.tracker.timeout_s == 2.0
