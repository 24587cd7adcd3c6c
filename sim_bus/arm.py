"""The simulated arm: motor positions → rope lengths → joint angles → joint centres.

Where the arm really is follows from where the motors really are (the drive
simulators' actual positions, not the host's setpoints) and from the arm's truth
(:class:`sim_bus.truth.TrueArm`: how the real arm differs from its description; the
default is the description itself).  Per rope m, with the true zero count ``z_m``, the true
axial rigidity ``EA_m``, the pretension ``T0`` and the description's drum constants
(``direction``, ``counts_per_mm``):

* the drum has paid out the unstretched length ``u_m = u0_m - direction (c_m - z_m) /
  counts_per_mm``, where ``u0_m = (box_m + L_m(phi = 0)) / (1 + T0/EA_m)`` is the length
  that holds rope m at ``T0`` with the rope geometry straight (every joint's two rope
  disks coaxial, phi = 0): at ``c_m = z_m`` the rope is at its pretension there, the
  truth's definition of the motor zero;
* a rope carries tension only beyond its slack: its effective length is ``u_m + slack_m``;
* the rope-geometric joint angles phi follow from the rope layer's inverse
  (:meth:`hrm_ctrl.ropes.actuation.Actuation.angles_from_counts` of the description's
  rope layer, fed the counts that give the same rope lengths at the pretension: each
  joint settles where its ropes' length misfit is least, least squares per joint);
* the physical joint angle is phi + offset (true angle = commanded angle + offset); the
  joint centres are the planner's FK (:func:`hrm_ctrl.kinematics.joint_centres`) with the
  TRUE link lengths;
* tension ``T_m = EA_m (F_m - w_m) / w_m``, ``F_m`` the free length the pose needs
  (``box_m + L_m(phi)``), ``w_m = u_m + slack_m``; never below 0 (a slack rope), plus
  N(0, ``noise_N``) sensor noise.

The zero fixture (:meth:`SimArm.set_fixture`): a jig that clamps every joint's two rope
disks coaxial, so the rope geometry is held straight (phi = 0) whatever the motors do; the
links then stand at their joint zero offsets (physical angle = 0 + offset, which the jig
does not see), and each rope's tension follows from its own length alone, ``T_m = EA_m
(box_m + L_m(0) - w_m) / w_m`` (>= 0): the pretension at ``c_m = z_m``, rising ``EA_m /
u_m`` N per mm of rope wound in.  That is how the motor zeros and EAs are observable (on
the free arm 3 ropes share 2 joint angles), and why the zeros it gives are the rope
layer's (the count at the pretension with the rope geometry straight, commanded angles 0):
the joint offsets stay for the kinematic calibration to find, exactly as its convention
(true angle = commanded angle + offset) has them.  (A fixture that held the *links*
straight would fold the offsets into the zeros to first order and leave pose-dependent
errors of the order of angle x offset, millimetres at the tip, that no constant offset
explains.)

A snapped rope carries no tension and its joint drifts away from it (the other ropes of
the joint pull it) at ``snap_drift_rad_per_s`` until the joint limit (not in the fixture).

With ``physics`` (:class:`sim_bus.physics.Physics`, any effect on) the arm is instead the
quasi-static equilibrium of its elastic ropes and its loads at every state
(``sim_bus.statics``): gravity on the link masses and the payload (``sim_bus.gravity``),
capstan friction where the ropes bend through the joints (``sim_bus.capstan``), rope creep
(``sim_bus.creep``), play in the joints (``sim_bus.backlash``) and the tension sensors'
offset drift (``sim_bus.sensor_drift``), each switchable.  Those effects have memory (the
friction's direction, the creep, the play): each state continues from the previous one,
so states are asked for in time order (the box does, at the tension board's rate).  A
snapped rope then pulls nothing and its joint turns away from it as the equilibrium
says.  ``physics=None`` (the default) is the arm above, unchanged.

>>> import numpy as np
>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> act = load_actuation(default_robot())
>>> arm = SimArm(act, noise_N=0.0)
>>> a = np.full(12, 0.2); t = np.full(12, -0.1)
>>> s = arm.state(act.counts_from_angles(a, t), now=0.0)
>>> bool(np.abs(s.alpha - a).max() < 1e-3), s.centres.shape
(True, (13, 3))
>>> float(s.tension_N.min()) > 29.0     # pretension 30 N, ropes consistent
True
>>> arm.set_fixture(True)
>>> s = arm.state(np.zeros(36, dtype=np.int64), now=0.0)   # true zero counts: 0 here
>>> float(np.abs(s.alpha).max()), bool(np.allclose(s.tension_N, 30.0))
(0.0, True)
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from hrm_ctrl.errors import SimError
from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.ropes.actuation import Actuation, load_actuation
from hrm_ctrl.ropes.inverse import load_fallback_solver
from sim_bus.backlash import backlash_update
from sim_bus.capstan import friction_update, hole_geometry
from sim_bus.creep import creep_update
from sim_bus.gravity import gravity_forces
from sim_bus.physics import Effect, Physics
from sim_bus.sensor_drift import drift_update
from sim_bus.statics import LoadedPose, Loads, solve_equilibrium
from sim_bus.truth import TrueArm

FIRST_ITERATIONS = 60  # Newton steps of the first physical state (from the rope inverse)
STEP_ITERATIONS = 4  # of every later one (warm: 2-4 converge; a jump goes on converging)


@dataclass(frozen=True)
class ArmState:
    """The simulated arm at one instant (mm, rad, N)."""

    t: float
    counts: np.ndarray  # (n,) actual motor positions
    alpha: np.ndarray  # (12,) physical joint angles: rope-geometric + the joint's zero offset
    theta: np.ndarray  # (12,)
    centres: np.ndarray  # (13, 3) true joint centres O_1..O_12 and end point (true links)
    tension_N: np.ndarray  # (n,)
    residual_mm: np.ndarray  # (n,) rope length the counts give minus what the pose needs
    rope_alpha: np.ndarray | None = None  # (12,) rope-geometric angles phi (alpha - offset)
    rope_theta: np.ndarray | None = None
    fixture: bool = False  # the arm was held straight by the fixture
    anchor_tension_N: np.ndarray | None = None  # (n,) at each rope's anchor (physics only)


@dataclass
class PhysicsState:
    """What the arm's physics remembers from one state to the next (``SimArm.physics_state``):
    time, drum lengths (n,) mm, rope-geometric angles (12,) each, friction mobilisation and
    sliding (n,), creep (n,) mm, play (24,) rad, sensor offsets (n,) N, drum tensions (n,) N
    and the Newton steps of the last solve."""

    t: float
    u_mm: np.ndarray
    alpha: np.ndarray
    theta: np.ndarray
    nu: np.ndarray
    sliding: np.ndarray
    creep_mm: np.ndarray
    play_rad: np.ndarray
    drift_N: np.ndarray
    tension_N: np.ndarray
    iterations: int = 0
    loaded: LoadedPose | None = None  # the loads of the last solve (reused within 1e-3 rad)


class SimArm:
    """Arm state from motor counts, with its truth, fixture and snapped ropes (thread-safe).

    ``actuation`` names the motors and gives the robot description; the arm's physics
    uses the rope layer of the description with the true link lengths and nothing else
    of a calibration (``load_actuation(truth.model(actuation.robot))``: zero offsets, EAs
    and joint offsets a host's actuation may carry are not the arm's), with ``truth``
    applied as the module docstring says.  So with an explicit truth the arm does not
    depend on which calibration the host's actuation carries.
    """

    def __init__(
        self,
        actuation: Actuation,
        *,
        truth: TrueArm | None = None,
        noise_N: float = 0.05,
        snap_drift_rad_per_s: float = 0.2,
        seed: int = 0,
        physics: Physics | None = None,
    ) -> None:
        self.actuation = actuation
        if truth is None:
            truth = TrueArm.nominal(load_actuation(actuation.robot))
        self.truth = truth
        self.model = truth.model(actuation.robot)  # true link lengths, for the FK
        rope = load_actuation(self.model)  # the ropes of the true arm: no calibration in it
        self.rope = rope
        load_fallback_solver()  # state() may need it at any cycle: import it before
        if self.truth.motor_ids != rope.motor_ids:
            raise SimError(
                f"{self.truth.source}: the truth's motors differ from the rope layer's "
                f"({len(self.truth.motor_ids)} vs {rope.n_motors})"
            )
        self.noise_N = float(noise_N)
        self.snap_drift_rad_per_s = float(snap_drift_rad_per_s)
        self._rng = np.random.default_rng(seed)
        self._snapped: dict[int, float] = {}  # motor index -> time of the snap
        self._fixture = False
        self._lock = threading.Lock()
        self._warm: tuple[np.ndarray, np.ndarray] | None = None
        self._cache: tuple[np.ndarray, bool, tuple[np.ndarray, ...]] | None = None
        n = rope.n_motors
        routing = rope.routing
        self.pretension_N = np.broadcast_to(
            np.asarray(routing.pretension_N, dtype=float), (n,)
        ).copy()
        self.stiffness_EA_N = self.truth.rope_EA_N.copy()  # the true EA
        self.slack_mm = self.truth.slack_mm.copy()
        self._box = np.broadcast_to(np.asarray(routing.box_length, dtype=float), (n,)).copy()
        self.offset_alpha = self.truth.alpha_offset_rad.copy()
        self.offset_theta = self.truth.theta_offset_rad.copy()
        # the rope geometry held straight (phi = 0): the zero fixture's pose
        zero = np.zeros_like(self.offset_alpha)
        self.straight_rope_mm = rope.rope_lengths(zero, zero)
        self.required_free_mm = self._box + self.straight_rope_mm  # fixture: free length needed
        stretch = 1.0 + self.pretension_N / self.stiffness_EA_N
        self.u0_mm = self.required_free_mm / stretch  # paid out at the true zero count
        self._dir = np.asarray(rope.motors.direction, dtype=float)
        self._cpm = np.asarray(rope.motors.counts_per_mm, dtype=float)
        self._zero = self.truth.motor_zero_counts.astype(float)
        # counts in the description's rope layer that give the same rope length at T0
        ea_desc = np.broadcast_to(np.asarray(routing.stiffness_EA_N, dtype=float), (n,))
        self._rho = stretch / (1.0 + self.pretension_N / ea_desc)
        self._u_ref = np.asarray(rope.motors.u_ref, dtype=float)
        self._rope_zero = np.asarray(rope.motors.zero_offsets_counts, dtype=float)
        self.physics = physics if physics is not None and physics.active else None
        self.physics_state: PhysicsState | None = None
        self._physics_lock = threading.Lock()
        if self.physics is not None:
            self._holes = hole_geometry(routing, self.model.links)
            self._physics_rng = np.random.default_rng(self.physics.seed)
            self._backlash24 = np.repeat(self.physics.backlash_rad, 2)

    # ---- faults and the fixture -----------------------------------------------------------

    def snap(self, motor: int | str, now: float) -> None:
        """Fault injection: the rope of ``motor`` (index or id) breaks at ``now``."""
        i = self.motor_index(motor)
        with self._lock:
            self._snapped.setdefault(i, now)

    def repair(self) -> None:
        with self._lock:
            self._snapped.clear()

    @property
    def snapped(self) -> tuple[int, ...]:
        with self._lock:
            return tuple(sorted(self._snapped))

    def set_fixture(self, on: bool) -> None:
        """The straight fixture (parking tube) on or off (see the module docstring)."""
        with self._lock:
            self._fixture = bool(on)

    @property
    def fixture(self) -> bool:
        with self._lock:
            return self._fixture

    def motor_index(self, motor: int | str) -> int:
        ids = self.actuation.motor_ids
        if isinstance(motor, str):
            if motor not in ids:
                raise SimError(f"unknown rope motor '{motor}'")
            return ids.index(motor)
        if not 0 <= int(motor) < len(ids):
            raise SimError(f"rope motor index {motor} outside 0..{len(ids) - 1}")
        return int(motor)

    # ---- the ropes ------------------------------------------------------------------------

    def unstretched_mm(self, counts: np.ndarray) -> np.ndarray:
        """The true paid-out unstretched rope length (..., n) for motor counts (mm)."""
        c = np.asarray(counts, dtype=float)
        return self.u0_mm - self._dir * (c - self._zero) / self._cpm

    def _equivalent_counts(self, w: np.ndarray) -> np.ndarray:
        """Counts (float) at which the description's rope layer, at the pretension, gives
        the rope length a rope of effective unstretched length ``w`` has at T0 with the
        true EA: ``w (1 + T0/EA_true) = u_desc (1 + T0/EA_desc)``."""
        return self._rope_zero + self._dir * self._cpm * (self._u_ref - w * self._rho)

    def _tension(self, free_mm: np.ndarray, w: np.ndarray) -> np.ndarray:
        return np.maximum(self.stiffness_EA_N * (free_mm - w) / w, 0.0)

    # ---- the state ------------------------------------------------------------------------

    def state(self, counts: np.ndarray, now: float) -> ArmState:
        """The arm for actual motor positions ``counts`` (n,) at time ``now``."""
        rope = self.rope
        c = np.asarray(counts, dtype=np.int64)
        if c.shape != (rope.n_motors,):
            raise SimError(f"expected {rope.n_motors} motor counts, got shape {c.shape}")
        with self._lock:
            warm = self._warm
            snapped = dict(self._snapped)
            fixture = self._fixture
        if self.physics is not None:
            with self._physics_lock:
                return self._physical_state(c, now, snapped, fixture, warm)
        cache = self._cache
        if cache is not None and cache[1] == fixture and np.array_equal(cache[0], c):
            phi_a, phi_t, res, tension = (v.copy() for v in cache[2])  # motors did not move
        else:
            w = self.unstretched_mm(c) + self.slack_mm
            stretched = w * (1.0 + self.pretension_N / self.stiffness_EA_N)  # at T0
            if fixture:
                phi_a, phi_t = np.zeros_like(self.offset_alpha), np.zeros_like(self.offset_theta)
                free = self.required_free_mm
                res = stretched - free
            else:
                a0, t0 = warm if warm is not None else (None, None)
                phi_a, phi_t, res = rope.angles_from_counts(
                    self._equivalent_counts(w), self.pretension_N, a0, t0
                )
                phi_a = np.asarray(phi_a, dtype=float).copy()
                phi_t = np.asarray(phi_t, dtype=float).copy()
                res = np.asarray(res, dtype=float)
                free = rope.free_lengths(phi_a, phi_t)
                with self._lock:
                    self._warm = (phi_a.copy(), phi_t.copy())
            tension = self._tension(free, w)
            self._cache = (
                c.copy(),
                fixture,
                (phi_a.copy(), phi_t.copy(), np.array(res, dtype=float), tension.copy()),
            )
        if not fixture:
            for i, t_snap in snapped.items():
                j = int(rope.joint_of_motor[i])
                phi_a[j], phi_t[j] = self._drift(phi_a, phi_t, i, j, max(0.0, now - t_snap))
        for i in snapped:
            tension[i] = 0.0
        if self.noise_N > 0:
            tension = np.maximum(tension + self._rng.normal(0.0, self.noise_N, tension.shape), 0.0)
            for i in snapped:
                tension[i] = 0.0
        alpha = phi_a + self.offset_alpha  # physical: in the fixture, the offsets
        theta = phi_t + self.offset_theta
        centres = joint_centres(self.model, alpha, theta)
        return ArmState(now, c, alpha, theta, centres, tension, res, phi_a, phi_t, fixture)

    def _drift(
        self, alpha: np.ndarray, theta: np.ndarray, rope: int, joint: int, dt: float
    ) -> tuple[float, float]:
        """Joint ``joint`` (rope-geometric angles) turned by ``rate·dt`` in the direction that
        lengthens ``rope``."""
        act = self.rope
        h = 1e-4
        base = float(act.rope_lengths(alpha, theta)[rope])
        ga, gt = 0.0, 0.0
        for k, (da, dtt) in enumerate(((h, 0.0), (0.0, h))):
            a2, t2 = alpha.copy(), theta.copy()
            a2[joint] += da
            t2[joint] += dtt
            g = (float(act.rope_lengths(a2, t2)[rope]) - base) / h
            if k == 0:
                ga = g
            else:
                gt = g
        norm = float(np.hypot(ga, gt)) or 1.0
        step = self.snap_drift_rad_per_s * dt
        lim_a = act.robot.limit_alpha * 0.999
        lim_t = act.robot.limit_theta * 0.999
        a_new = float(np.clip(alpha[joint] + step * ga / norm, -lim_a, lim_a))
        t_new = float(np.clip(theta[joint] + step * gt / norm, -lim_t, lim_t))
        return a_new, t_new

    # ---- the physics ----------------------------------------------------------------------

    def _physical_state(
        self,
        c: np.ndarray,
        now: float,
        snapped: dict[int, float],
        fixture: bool,
        warm: tuple[np.ndarray, np.ndarray] | None,
    ) -> ArmState:
        """The arm with its physics (module docstring), continuing from the last state."""
        ph = self.physics
        assert ph is not None
        n = self.rope.n_motors
        prev = self.physics_state
        u = self.unstretched_mm(c)
        t0 = self.pretension_N
        if prev is None:
            prev = PhysicsState(
                now, u, np.zeros(12), np.zeros(12), np.zeros(n), np.zeros(n, dtype=bool),
                np.zeros(n), np.zeros(24), np.zeros(n), t0.copy(),
            )  # fmt: skip
            first = True
        else:
            first = False
        dt = max(0.0, now - prev.t)
        nu, sliding = prev.nu, prev.sliding
        if ph.on(Effect.CAPSTAN):
            nu, sliding = friction_update(
                nu, sliding, u - prev.u_mm, ph.presliding_mm, ph.static_ratio
            )
        creep = prev.creep_mm
        if ph.on(Effect.CREEP):
            creep = creep_update(
                creep, prev.tension_N, float(t0[0]), u, self.stiffness_EA_N,
                ph.creep_fraction, ph.creep_time_s, dt,
            )  # fmt: skip
        drift = prev.drift_N
        if ph.on(Effect.SENSOR):
            drift = drift_update(drift, ph.sensor_drift_N_per_sqrt_s, dt, self._physics_rng)
        w = u + self.slack_mm + creep
        taut = np.ones(n, dtype=bool)
        taut[list(snapped)] = False
        play = prev.play_rad
        iterations = 0
        loaded = None
        if fixture:
            phi_a, phi_t = np.zeros(12), np.zeros(12)
            free = self.required_free_mm
            tension = np.where(taut, self._tension(free, w), 0.0)
            anchor = tension.copy()
            res = w * (1.0 + tension / self.stiffness_EA_N) - free
        else:
            if first:
                a0, t0_ = warm if warm is not None else (None, None)
                a_start, t_start, _res = self.rope.angles_from_counts(
                    self._equivalent_counts(w), self.pretension_N, a0, t0_
                )
                a_start = np.asarray(a_start, dtype=float)
                t_start = np.asarray(t_start, dtype=float)
            else:
                a_start, t_start = prev.alpha, prev.theta
            loads = Loads(
                self._gravity(play) if ph.on(Effect.GRAVITY) else None,
                nu if ph.on(Effect.CAPSTAN) else None,
                np.asarray(ph.mu_kinetic) if ph.on(Effect.CAPSTAN) else None,
                taut,
                float(t0[0]),
            )
            eq = solve_equilibrium(
                self.rope, self._holes, w, self.stiffness_EA_N, a_start, t_start, loads,
                max_iter=FIRST_ITERATIONS if first else STEP_ITERATIONS,
                loaded=None if first else prev.loaded,
            )  # fmt: skip
            phi_a, phi_t, iterations, loaded = eq.alpha, eq.theta, eq.iterations, eq.loaded
            tension, anchor, res = eq.tension_N, eq.anchor_N, -eq.residual_mm
            if ph.on(Effect.BACKLASH):
                turned = np.empty(24)
                turned[0::2], turned[1::2] = phi_a - prev.alpha, phi_t - prev.theta
                if first:
                    turned[:] = 0.0
                play = backlash_update(
                    play, turned, eq.gravity_Nmm, self._backlash24, ph.backlash_torque_Nmm
                )
        self.physics_state = PhysicsState(
            now, u, phi_a, phi_t, nu, sliding, creep, play, drift, tension, iterations, loaded
        )
        reading = tension + drift
        if self.noise_N > 0:
            reading = reading + self._rng.normal(0.0, self.noise_N, reading.shape)
        reading = np.where(taut, np.maximum(reading, 0.0), 0.0)
        alpha = phi_a + self.offset_alpha + (0.0 if fixture else play[0::2])
        theta = phi_t + self.offset_theta + (0.0 if fixture else play[1::2])
        centres = joint_centres(self.model, alpha, theta)
        return ArmState(now, c, alpha, theta, centres, reading, res, phi_a, phi_t, fixture, anchor)

    def _gravity(self, play: np.ndarray) -> Callable[[np.ndarray, np.ndarray], np.ndarray]:
        """The gravity forces (24,) at rope-geometric angles, the physical ones being
        those plus the joint offsets and the play ``play`` (24,)."""
        ph = self.physics
        assert ph is not None
        off_a = self.offset_alpha + play[0::2]
        off_t = self.offset_theta + play[1::2]
        masses = np.asarray(ph.link_mass_kg)
        g = ph.gravity_N_per_kg

        def forces(a: np.ndarray, t: np.ndarray) -> np.ndarray:
            return gravity_forces(self.model, a + off_a, t + off_t, masses, ph.payload_kg, g)

        return forces
