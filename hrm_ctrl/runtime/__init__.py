"""The runtime layer: the one composition root every entry point shares.

The entry points (``hrm_ctrl.cli``, the console, ``hrm_ctrl.hil``, the benchmarks) turn
their arguments into explicit parameters and call this layer; it wires the layers below
(``drivers``, ``sim_bus``, ``calibration``, the rope layer) together:

* :mod:`hrm_ctrl.runtime.arm`: the arm a command works with (:class:`~.arm.Arm`: robot
  description, calibrated model and rope layer, the active calibration);
* :mod:`hrm_ctrl.runtime.playback`: a plan to checked setpoints and a setpoint source,
  and the collision gate;
* :mod:`hrm_ctrl.runtime.simulated`: the simulated box (its controls, wherever it runs; the
  box in this process) and the physical arm it simulates;
* :mod:`hrm_ctrl.runtime.watches`: the feedback watches of a drive session;
* :mod:`hrm_ctrl.runtime.box`: :func:`~.box.open_box`, the one way to open a box (real
  buses, the in-process simulated box, or a box in its own process) with its session,
  CAN logs and watches, closed in order on any exit.

Nothing is imported here: ``import hrm_ctrl.runtime`` costs nothing (the CLI's start).
"""
