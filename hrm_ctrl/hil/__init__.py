"""Hardware-in-the-loop testing: the simulated box, a drive session on it, fault injection
and the true arm state, as pytest fixtures (``docs/hil.md``).

* :mod:`hrm_ctrl.hil.plugin`: the pytest plugin (entry point ``pytest11``, name ``hrm_hil``):
  the ``--hrm-bus`` / ``--hrm-box`` options and the ``hrm_*`` fixtures;
* :mod:`hrm_ctrl.hil.rig`: what the fixtures are made of (box configurations, the box in
  this process or as its own process, the host side), usable without pytest;
* :mod:`hrm_ctrl.hil.wirelog`: detection and stop times read off a run's CAN logs.

Like :mod:`hrm_ctrl.cli` this package is an entry point: the host side opens its box
through the runtime layer (:func:`hrm_ctrl.runtime.box.open_box`).  Importing it imports
neither the simulator nor the drivers (pytest loads the plugin in every run of the
project): the fixtures import them when used.
"""
