"""The arm's physics switches and its slow effects: creep over a simulated hour (by hand),
backlash (gravity takes up the play; a reversal within it moves nothing), the tension
sensors' drift, and ``--physics`` specs."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hrm_ctrl.cli import main
from hrm_ctrl.model import default_robot
from hrm_ctrl.ropes.actuation import load_actuation
from sim_bus.arm import SimArm
from sim_bus.physics import (
    BACKLASH_RAD,
    CREEP_FRACTION,
    CREEP_TIME_S,
    Effect,
    Physics,
    PhysicsSpecError,
)

ACT = load_actuation(default_robot())
ZERO = np.zeros(36, dtype=np.int64)  # the nominal arm's true zero counts


def test_creep_over_a_simulated_hour_loses_the_pretension_the_hand_formula_says() -> None:
    """Held at a fixed length (the zero fixture, the motors still) a rope's creep
    ``c`` grows as ``c' = (f (T/T0) d0 - c) / tau`` with ``T = T0 - (EA/w) c``: the
    tension falls as ``T0 (1 - f/(1+f) (1 - e^(-(1+f) t/tau)))``."""
    arm = SimArm(ACT, noise_N=0.0, physics=Physics(frozenset({Effect.CREEP})))
    arm.set_fixture(True)
    for second in range(3601):
        s = arm.state(ZERO, float(second))
    f, tau, T0 = CREEP_FRACTION, CREEP_TIME_S, ACT.routing.pretension_N
    want = T0 * (1.0 - f / (1.0 + f) * (1.0 - math.exp(-(1.0 + f) * 3600.0 / tau)))
    drop = T0 - want
    assert drop > 2.0  # 2.6 N of 30 in the first hour
    assert np.abs(s.tension_N - want).max() < 0.02 * drop
    ps = arm.physics_state
    assert ps is not None and np.all(ps.creep_mm > 0.0)


def test_creep_off_keeps_the_pretension_for_an_hour() -> None:
    arm = SimArm(ACT, noise_N=0.0, physics=Physics(frozenset({Effect.BACKLASH})))
    arm.set_fixture(True)
    for second in (0.0, 1800.0, 3600.0):
        s = arm.state(ZERO, second)
    assert np.allclose(s.tension_N, ACT.routing.pretension_N)


def test_gravity_takes_up_the_play_downwards() -> None:
    physics = Physics(frozenset({Effect.GRAVITY, Effect.BACKLASH}))
    arm = SimArm(ACT, noise_N=0.0, physics=physics)
    c = ACT.counts_from_angles(np.zeros(12), np.zeros(12))
    for i in range(3):
        s = arm.state(c, 0.01 * i)
    assert s.rope_alpha is not None and s.rope_theta is not None
    half = BACKLASH_RAD / 2.0
    assert np.allclose(s.alpha - s.rope_alpha, -half)  # every alpha axis loaded downwards
    assert np.allclose(s.theta - s.rope_theta, 0.0)  # level: no moment about theta


def test_a_reversal_within_the_play_moves_no_link() -> None:
    arm = SimArm(ACT, noise_N=0.0, physics=Physics(frozenset({Effect.BACKLASH})))
    half = BACKLASH_RAD / 2.0

    def at(theta12: float, t: float) -> tuple[float, float]:
        th = np.zeros(12)
        th[11] = theta12
        s = arm.state(ACT.counts_from_angles(np.zeros(12), th), t)
        assert s.rope_theta is not None
        return float(s.theta[11]), float(s.rope_theta[11])

    for i, th in enumerate(np.linspace(0.0, 0.1, 21)):
        link, rope = at(float(th), 0.01 * i)
    assert link - rope == pytest.approx(-half, abs=1e-9)  # the link lags the ropes by half
    held = link
    link, rope = at(0.1 - 0.8 * half, 1.0)  # back, within the play
    assert link == pytest.approx(held, abs=1e-5)  # the link stays (to the counts' quantum)
    link, rope = at(0.1 - 3.0 * half, 2.0)  # back beyond it: dragged the other way
    assert link - rope == pytest.approx(half, abs=1e-9)


def test_sensor_offsets_drift_by_a_random_walk_and_move_nothing() -> None:
    sensor = Physics(frozenset({Effect.SENSOR}))
    arm = SimArm(ACT, noise_N=0.0, physics=sensor)
    c = ACT.counts_from_angles(np.full(12, 0.1), np.zeros(12))
    for second in range(0, 3601, 10):
        s = arm.state(c, float(second))
    plain = SimArm(ACT, noise_N=0.0).state(c, 0.0)
    assert np.abs(s.centres - plain.centres).max() < 1e-3
    offsets = s.tension_N - plain.tension_N
    spread = sensor.sensor_drift_N_per_sqrt_s * 60.0  # after an hour: 0.2 N
    assert 0.5 * spread < float(offsets.std()) < 1.6 * spread  # 36 sensors
    assert np.abs(offsets).max() < 5.0 * spread


@pytest.mark.parametrize(
    ("spec", "effects"),
    [
        ("all", set(Effect)),
        ("none", set()),
        ("gravity", {Effect.GRAVITY}),
        ("Capstan, creep", {Effect.CAPSTAN, Effect.CREEP}),
        ("backlash,sensor,gravity", {Effect.BACKLASH, Effect.SENSOR, Effect.GRAVITY}),
    ],
)
def test_physics_specs(spec: str, effects: set[Effect]) -> None:
    p = Physics.of(spec)
    assert p.effects == effects and p.active == bool(effects)
    assert Physics.of(p.describe()).effects == effects  # what hrm sim is passed


@pytest.mark.parametrize("spec", ["", ",", "gravity,frition", "all;none"])
def test_bad_physics_specs_are_refused(spec: str) -> None:
    with pytest.raises(PhysicsSpecError, match="physics"):
        Physics.of(spec)


@pytest.mark.parametrize(
    ("constants", "what"),
    [
        ({"payload_kg": -1.0}, "payload_kg"),
        ({"gravity_dir": (0.0, 0.0, 0.0)}, "gravity_dir"),
        ({"static_ratio": 0.5}, "static_ratio"),
        ({"creep_time_s": 0.0}, "creep_time_s"),
        ({"mu_kinetic": float("nan")}, "mu_kinetic"),
    ],
)
def test_bad_physical_constants_are_refused(constants: dict, what: str) -> None:
    with pytest.raises(Exception, match=what):
        Physics.of("all", **constants)


def test_hrm_sim_refuses_a_bad_physics_switch_in_one_line(
    capsys: pytest.CaptureFixture[str],
) -> None:
    assert main(["sim", "--physics", "gravity,frition", "--duration", "1"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "unknown effect 'frition'" in err[0], err
