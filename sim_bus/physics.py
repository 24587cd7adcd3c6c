"""The simulated arm's physics: which effects are on, and the arm's physical constants.

Without physics (the default, ``None``) the simulated arm goes where its ropes' lengths
put it (``sim_bus.arm``).  :class:`Physics` switches on, each alone or together, what a
real arm of this size has (defaults and their sources in ``docs/sim.md``, "Physics"):

* :attr:`Effect.GRAVITY`: link masses and a tip payload under gravity along
  ``gravity_dir`` of the base frame (default -z: the arm held out horizontally);
* :attr:`Effect.CAPSTAN`: friction where a rope bends through a joint's holes
  (``T_out = T_in e^(-mu beta)``), static above kinetic, the sign from the rope's travel;
* :attr:`Effect.CREEP`: the ropes lengthen slowly under tension (pretension lost);
* :attr:`Effect.BACKLASH`: play in each universal joint's two axes;
* :attr:`Effect.SENSOR`: the tension sensors' offsets drift (a random walk).

With any effect on, the arm is the quasi-static equilibrium of its elastic ropes (the
true EA) and the loads on it (``sim_bus.statics``), solved at every arm state.

>>> p = Physics.of("gravity,capstan")
>>> sorted(e.value for e in p.effects), p.on(Effect.CREEP)
(['capstan', 'gravity'], False)
>>> Physics.of("all").effects == frozenset(Effect), Physics.of("none").active
(True, False)
>>> Physics.of("gravity,frition")  # doctest: +ELLIPSIS
Traceback (most recent call last):
...
sim_bus.physics.PhysicsSpecError: physics 'gravity,frition': unknown effect 'frition' (have ...)
"""

from __future__ import annotations

import dataclasses
import enum
import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hrm_ctrl.errors import SimError

N_JOINTS = 12
G_M_PER_S2 = 9.81

# Defaults: a real arm of this size (2007 mm, 30 mm outer diameter, 12 universal joints,
# 1 mm steel ropes through PTFE-lined holes).  Sources and arithmetic in docs/sim.md.
LINK_MASS_KG = 0.020  # a thin CFRP tube, two aluminium disks, a steel cross (docs/sim.md)
PAYLOAD_KG = 0.020  # a small camera head at the tip
GRAVITY_DIR = (0.0, 0.0, -1.0)  # in the base frame: the arm (along +x0) held horizontally
MU_KINETIC = 0.10  # steel rope on PTFE-lined holes
STATIC_RATIO = 1.5  # mu_static / mu_kinetic
PRESLIDING_MM = 0.05  # rope travel that mobilises the kinetic friction from rest
CREEP_FRACTION = 0.10  # of the pretension stretch, at the pretension, in the long run
CREEP_TIME_S = 1200.0  # its time constant
BACKLASH_RAD = math.radians(0.2)  # total play per joint axis
BACKLASH_TORQUE_NMM = 2.0  # a gravity torque above this takes up the play
SENSOR_DRIFT_N_PER_SQRT_S = 0.2 / 60.0  # 0.2 N per square-root hour


class PhysicsSpecError(SimError):
    """A physics switch (``--physics``) names no effect."""


class Effect(enum.Enum):
    """An effect the simulated arm's physics can switch on."""

    GRAVITY = "gravity"
    CAPSTAN = "capstan"
    CREEP = "creep"
    BACKLASH = "backlash"
    SENSOR = "sensor"


def _vec(v: Any, n: int) -> np.ndarray:
    a = np.array(np.broadcast_to(np.asarray(v, dtype=float), (n,)))
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class Physics:
    """Which effects are on and the arm's physical constants (SI but mm, N, N mm, rad)."""

    effects: frozenset[Effect] = frozenset(Effect)
    link_mass_kg: Any = LINK_MASS_KG  # (12,) or one value
    payload_kg: float = PAYLOAD_KG
    gravity_dir: Any = GRAVITY_DIR  # (3,) in the base frame; normalised
    g_m_per_s2: float = G_M_PER_S2
    mu_kinetic: Any = MU_KINETIC  # (12,) per joint or one value
    static_ratio: float = STATIC_RATIO
    presliding_mm: float = PRESLIDING_MM
    creep_fraction: float = CREEP_FRACTION
    creep_time_s: float = CREEP_TIME_S
    backlash_rad: Any = BACKLASH_RAD  # (12,) per joint or one value: both axes
    backlash_torque_Nmm: float = BACKLASH_TORQUE_NMM
    sensor_drift_N_per_sqrt_s: float = SENSOR_DRIFT_N_PER_SQRT_S
    seed: int = 0
    source: str = field(default="<physics>")

    def __post_init__(self) -> None:
        put = object.__setattr__
        put(self, "effects", frozenset(self.effects))
        put(self, "link_mass_kg", _vec(self.link_mass_kg, N_JOINTS))
        put(self, "mu_kinetic", _vec(self.mu_kinetic, N_JOINTS))
        put(self, "backlash_rad", _vec(self.backlash_rad, N_JOINTS))
        g = np.asarray(self.gravity_dir, dtype=float).reshape(3)
        norm = float(np.linalg.norm(g))
        if not (math.isfinite(norm) and norm > 0.0):
            raise SimError(f"{self.source}: gravity_dir must be a non-zero vector, got {g}")
        g = g / norm
        g.setflags(write=False)
        put(self, "gravity_dir", g)
        checks = (
            ("link_mass_kg", self.link_mass_kg.min(), 0.0),
            ("payload_kg", self.payload_kg, 0.0),
            ("mu_kinetic", self.mu_kinetic.min(), 0.0),
            ("backlash_rad", self.backlash_rad.min(), 0.0),
            ("creep_fraction", self.creep_fraction, 0.0),
            ("sensor_drift_N_per_sqrt_s", self.sensor_drift_N_per_sqrt_s, 0.0),
            ("backlash_torque_Nmm", self.backlash_torque_Nmm, 0.0),
        )
        for name, value, low in checks:
            if not (math.isfinite(float(value)) and float(value) >= low):
                raise SimError(f"{self.source}: {name} must be >= {low:g}, got {value}")
        for name in ("presliding_mm", "creep_time_s", "g_m_per_s2"):
            v = float(getattr(self, name))
            if not (math.isfinite(v) and v > 0.0):
                raise SimError(f"{self.source}: {name} must be > 0, got {v}")
        if not (math.isfinite(self.static_ratio) and self.static_ratio >= 1.0):
            raise SimError(f"{self.source}: static_ratio must be >= 1, got {self.static_ratio}")

    @classmethod
    def of(cls, spec: str, **constants: Any) -> Physics:
        """Physics from a switch: ``all``, ``none`` or effects joined by commas
        (``gravity,capstan``), the defaults for the rest (``constants`` override them)."""
        names = [s.strip().lower() for s in spec.split(",") if s.strip()]
        effects: set[Effect] = set()
        known = {e.value: e for e in Effect}
        for name in names:
            if name == "all":
                effects |= set(Effect)
            elif name == "none":
                continue
            elif name in known:
                effects.add(known[name])
            else:
                have = ", ".join(["all", "none", *known])
                raise PhysicsSpecError(f"physics {spec!r}: unknown effect {name!r} (have {have})")
        if not names:
            raise PhysicsSpecError(f"physics {spec!r}: name effects (all, none, gravity, ...)")
        return cls(frozenset(effects), source=f"<physics {spec}>", **constants)

    def on(self, effect: Effect) -> bool:
        return effect in self.effects

    @property
    def active(self) -> bool:
        """Whether any effect is on (else the arm is the one without physics)."""
        return bool(self.effects)

    def only(self, *effects: Effect) -> Physics:
        """The same constants with only ``effects`` on."""
        return dataclasses.replace(self, effects=frozenset(effects))

    @property
    def gravity_N_per_kg(self) -> np.ndarray:
        """Gravity (3,) in the base frame, N per kg."""
        return np.asarray(self.gravity_dir) * self.g_m_per_s2

    def describe(self) -> str:
        """The effects on, for a ``ready`` line or a log: ``gravity,capstan`` or ``none``."""
        return ",".join(e.value for e in Effect if e in self.effects) or "none"
