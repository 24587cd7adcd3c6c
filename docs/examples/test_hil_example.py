"""A HIL test of your own on the simulated box (docs/hil.md): copy this file into your
tests and run ``pytest`` (the ``hrm_hil`` plugin comes with the ``hrm`` package)."""

import time

import numpy as np
import pytest

from drivers.safety.causes import StopKind
from drivers.session import SafetyStopError
from drivers.sources import CountsSource, HoldSource


@pytest.fixture(scope="module")
def hrm_box_nodes():
    """A small box: the three rope motors of joint 1 on one bus (node ids 1..3)."""
    return ({"j01r0": 1, "j01r1": 2, "j01r2": 3},)


def test_joint_1_bends_where_it_is_told(hrm_host, hrm_arm_state):
    limits = hrm_host.limits  # the rope layer, for this box's motors
    alpha = np.zeros(12)
    alpha[0] = np.radians(5.0)  # joint 1: 5 degrees about its first axis
    target = limits.counts_from_angles(alpha, np.zeros(12))
    period_s = hrm_host.config.control.period_s
    result = hrm_host.session.stream(CountsSource(limits, target[None, :], period_s))
    assert result.completed
    arm = hrm_arm_state()  # the simulated arm's truth, not what the drives report
    assert np.degrees(arm.alpha[0]) == pytest.approx(5.0, abs=0.05)
    assert np.degrees(arm.theta[0]) == pytest.approx(0.0, abs=0.05)
    # (joint 2 bends back: its ropes run through joint 1, their motors are not in this box)


def test_a_lost_drive_heartbeat_stops_every_axis(hrm_session, hrm_fault, hrm_arm_state):
    hrm_fault.after(0.3, "heartbeat-stop:j01r1")  # 0.3 s into the stream
    with pytest.raises(SafetyStopError) as stop:
        hrm_session.stream(HoldSource(n_cycles=200))  # 2 s; the heartbeat times out at ~0.65 s
    assert any(c.kind is StopKind.HEARTBEAT and "j01r1" in c.text for c in stop.value.causes)
    deadline = time.monotonic() + 2.0  # the drives ramp down (quick stop), then disable
    while hrm_arm_state().enabled() and time.monotonic() < deadline:
        time.sleep(0.05)
    assert hrm_arm_state().enabled() == []
