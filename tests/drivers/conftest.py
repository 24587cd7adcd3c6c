"""Fixtures of the driver tests (helpers live in ``driver_rig``)."""

from tests.drivers.driver_rig import actuation, bus_backend, rig_factory

__all__ = ["actuation", "bus_backend", "rig_factory"]
