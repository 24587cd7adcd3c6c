"""Fixtures of the driver tests (helpers live in ``driver_rig``)."""

from driver_rig import actuation, rig_factory

__all__ = ["actuation", "rig_factory"]
