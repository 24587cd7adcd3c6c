"""The online step computes what it computed before it was made faster.

``data/bent_pipe_online_steps.npz`` holds, for every tenth cycle of the bent pipe steered
by its keys at 20 Hz (1 mm a step, as ``test_follow.py`` drives it), the planner's state
before the cycle (travel, refined and paper-fit angles, the last modal factors) and the
angles and clearance after it, recorded from the online step as it was before its
fitting, kinematics, projection and clearance sampling were restructured.  The drive is
run again, the planner put into each recorded state before its cycle, and the step must
land on the recorded angles.

One step at a time: the refinement is greedy along the travel in the null space of the
tip, so a rounding difference of 1e-13 rad drifts to tenths of a degree over a few
hundred steps (the same quality of path, another path); from the same state a step must
agree to rounding.  The recording was made with the refinement's clearance cap at 40 mm
(the online default is 15 mm): the planner is given the options it was recorded with.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hrm_ctrl.drive.command import SteerLimits
from hrm_ctrl.drive.driver import Driver
from hrm_ctrl.drive.online import OnlineOptions, OnlinePlanner
from hrm_ctrl.drive.script import KeyScript, bent_pipe_keys
from hrm_ctrl.drive.trail import Trail
from hrm_ctrl.model import default_robot
from hrm_ctrl.planning.refine import RefineOptions
from hrm_ctrl.planning.scenarios import scenario

RECORDED = Path(__file__).parent / "data" / "bent_pipe_online_steps.npz"
PERIOD_S = 0.05
# the online options the steps were recorded with
RECORDED_OPTIONS = OnlineOptions(
    refine=RefineOptions(max_iterations=1, trials=1, patient_iterations=0, clearance_cap_mm=40.0)
)


def test_each_recorded_step_gives_the_recorded_angles() -> None:
    rec = np.load(RECORDED)
    forced = {int(k): i for i, k in enumerate(rec["cycle"])}
    sc = scenario("bent-pipe")
    limits = SteerLimits(pitch_rate_rad_s=0.2, yaw_rate_rad_s=0.2)
    keys = KeyScript.parse(bent_pipe_keys(limits, period_s=PERIOD_S), "bent-pipe keys")
    P = sc.path.points
    trail = Trail.starting_at(P[0], P[1] - P[0])
    planner = OnlinePlanner(default_robot(), trail, sc.environment, RECORDED_OPTIONS)
    drv = Driver(planner, limits, PERIOD_S)
    angle_err, clearance_err = [], []
    for k in range(int(rec["cycle"][-1]) + 1):
        i = forced.get(k)
        if i is not None:
            assert abs(planner.travel - rec["travel"][i]) < 1e-9
            a_hist = rec["a_hist"][i]
            planner.q = rec["q"][i].copy()
            planner.q_paper = rec["q_paper"][i].copy()
            planner.a_hist = a_hist[~np.isnan(a_hist[:, 0])].copy()
        status = drv.cycle(keys.command_at(k * PERIOD_S, limits))
        assert status.refusal is None, (k, status.refusal)
        if i is not None:
            angle_err.append(float(np.abs(planner.q - rec["q_next"][i]).max()))
            clearance_err.append(abs(planner.clearance_mm - float(rec["clearance_next"][i])))
    assert len(angle_err) == len(rec["cycle"]) == 69
    assert max(angle_err) < 1e-9  # rad
    assert max(clearance_err) < 1e-7  # mm
