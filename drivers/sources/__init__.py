"""Setpoint sources for cyclic streaming, one module per kind: hold
(:mod:`~drivers.sources.hold`), jog (:mod:`~drivers.sources.jog`), a precomputed counts
table (:mod:`~drivers.sources.counts`: plan playback, the console turns a plan into counts
with the rope layer's ``hrm_ctrl.ropes.setpoints`` and hands the table to
:class:`CountsSource`) and its pausable playback (:mod:`~drivers.sources.pausable`).  The
moves a source makes itself (a lead-in from the actual positions, a jog, the stop of a
table that ends moving) are jerk-limited with Ruckig (:mod:`~drivers.sources.moves`),
within every motor's speed, acceleration and jerk limits, checked on the integers.

A source (:class:`~drivers.sources.table.SetpointSource`) is started with the drives'
actual positions (counts, the rope layer's motor order) and the control period, then
asked for the setpoint of every control slot (``setpoint(k)``, k = 0, 1, ...); ``None``
ends the run.  Sources precompute their whole table where they can and check it against
the rope layer's limits (``check_counts`` of a :class:`~drivers.rope_model.MotorLimits`)
*before* anything is sent, so a bad plan is refused up front; the supervisor checks
every setpoint again before sending it.

>>> import numpy as np
>>> src = HoldSource(n_cycles=2)
>>> src.start(np.array([5, -5]), 0.01)
>>> [src.setpoint(k) for k in range(3)]
[array([ 5, -5]), array([ 5, -5]), None]
"""

from __future__ import annotations

from drivers.safety.limits import SetpointError
from drivers.sources.counts import LEAD_IN_SPEED_FRACTION, CountsSource
from drivers.sources.hold import HoldSource
from drivers.sources.jog import JOG_ANGLE_CHECK_STEP_COUNTS, JogSource
from drivers.sources.moves import (
    MOVE_MARGIN,
    MOVE_RETRIES,
    MOVE_SLOWDOWN,
    at_samples,
    move_table,
    path_move,
    stop_table,
)
from drivers.sources.pausable import (
    MAX_OFF_PATH_COUNTS,
    MAX_PAUSE_S,
    MAX_PLAYED_ROWS,
    PAUSE_RAMP_S,
    PausableSource,
    PlayState,
)
from drivers.sources.table import (
    LabelOfRow,
    SetpointSource,
    TabledSource,
    TableSource,
    check_table,
)

__all__ = [
    "JOG_ANGLE_CHECK_STEP_COUNTS",
    "LEAD_IN_SPEED_FRACTION",
    "MAX_OFF_PATH_COUNTS",
    "MAX_PAUSE_S",
    "MAX_PLAYED_ROWS",
    "MOVE_MARGIN",
    "MOVE_RETRIES",
    "MOVE_SLOWDOWN",
    "PAUSE_RAMP_S",
    "CountsSource",
    "HoldSource",
    "JogSource",
    "LabelOfRow",
    "PausableSource",
    "PlayState",
    "SetpointError",
    "SetpointSource",
    "TableSource",
    "TabledSource",
    "at_samples",
    "check_table",
    "move_table",
    "path_move",
    "stop_table",
]
