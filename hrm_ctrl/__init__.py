"""hrm: host-side control stack for a rope-driven hyper-redundant manipulator."""

__version__ = "0.1.0"
