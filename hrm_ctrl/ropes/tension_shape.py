"""The arm's shape from its rope tensions, every control cycle.

What a host has each cycle: the counts it commanded (the drums are there within a cycle:
each rope's paid-out unstretched length ``u``), the tension board's drum tensions ``T``,
and the calibration (the rope layer's EA, the ``[physics]`` table's friction).  A rope of
unstretched length ``u`` under drum tension ``T`` spans the free length

    F = u (1 + T fbar / EA)

(``fbar``: the length-weighted mean of its capstan factors along it, the stretch law of
:mod:`hrm_ctrl.ropes.feedforward`), and the pose ``q`` is where the rope layer's free
lengths ``box + L(q)`` are those: 36 lengths for 24 angles, a least-squares fit.  The
friction factors need each rope's friction mobilisation ``nu``; it is a function of the
rope's own drum travel (the presliding law, :func:`~hrm_ctrl.ropes.feedforward.friction_step`),
and the host knows that travel (it commands it), so :class:`TensionShape` tracks ``nu``
from the commanded lengths, cycle by cycle.

:meth:`TensionShape.step` returns the rope-held (commanded) angles' error against a
target pose: linearised at the target (one Gauss-Newton step; ``iterations`` more from
the estimate), ``dq = (J^T J)^-1 J^T (F - box - L(q_target))``.  What it cannot see: the
joints' play (beyond the ropes), creep (a slow lengthening of ``u``), the sensors'
offset drift (through ``T``).

>>> from hrm_ctrl.model import default_robot
>>> from hrm_ctrl.ropes.actuation import load_actuation
>>> from hrm_ctrl.ropes.feedforward import Feedforward
>>> act = load_actuation(default_robot())
>>> shape = TensionShape(Feedforward.of(act))
>>> a, t = np.full(12, 0.05), np.full(12, -0.03)
>>> c = act.counts_from_angles(a, t)               # the ropes at the pretension, unloaded
>>> shape.reset(c)
>>> dq = shape.step(c, np.full(36, 30.0), a, t)
>>> bool(np.abs(dq).max() < 1e-4)                   # the pose the counts were made for
True
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hrm_ctrl.ropes.feedforward import Feedforward, friction_step, tension_factors, wrap_angles
from hrm_ctrl.ropes.length import lengths_and_jacobian


@dataclass
class FrictionState:
    """Each rope's friction mobilisation ``nu`` (n,), whether it slides (n,), and its
    last commanded unstretched length (n,) mm (mutable: the tracker's state)."""

    nu: np.ndarray
    sliding: np.ndarray
    u_mm: np.ndarray


class TensionShape:
    """The rope-held pose's error from the tension board, with the friction tracked from
    the commanded drum travel (module docstring).  One per arm; :meth:`reset` at the
    first commanded counts, then :meth:`step` every cycle in time order."""

    def __init__(self, ff: Feedforward, iterations: int = 1) -> None:
        act = ff.actuation
        self.ff = ff
        self.iterations = int(iterations)
        n = act.n_motors
        self._EA = np.broadcast_to(np.asarray(act.routing.stiffness_EA_N, float), (n,)).copy()
        self._box = np.broadcast_to(np.asarray(act.routing.box_length, float), (n,)).copy()
        self._friction = bool(ff.capstan and ff.physics.mu_kinetic.any())
        self.state = FrictionState(np.zeros(n), np.zeros(n, dtype=bool), np.zeros(n))
        self._a = np.empty((1, act.n_joints))
        self._t = np.empty((1, act.n_joints))
        self._F = np.empty(n)
        self._dq = np.zeros(2 * act.n_joints)
        self.jacobian = np.zeros((n, 2 * act.n_joints))  # dL/dq at the last estimate

    def reset(self, counts: np.ndarray, nu: np.ndarray | None = None) -> None:
        """Start tracking at ``counts`` (n,), each rope's friction ``nu`` (n,) there (None:
        at rest, none mobilised: the simulated box's state at power-on)."""
        st = self.state
        st.u_mm[:] = self.ff.actuation.motors.unstretched_from_counts(counts)
        st.nu[:] = 0.0 if nu is None else nu
        st.sliding[:] = np.abs(st.nu) == 1.0

    def track(self, counts: np.ndarray) -> np.ndarray:
        """The commanded ``counts`` (n,) of this cycle: the friction tracked by the drum
        travel since the last (:func:`~hrm_ctrl.ropes.feedforward.friction_step`);
        returns the unstretched lengths (n,) mm."""
        st = self.state
        u = self.ff.actuation.motors.unstretched_from_counts(counts)
        ph = self.ff.physics
        st.nu[:], st.sliding[:] = friction_step(
            st.nu, st.sliding, u - st.u_mm, ph.presliding_mm, ph.static_ratio
        )
        st.u_mm[:] = u
        return u

    def step(
        self, counts: np.ndarray, tension_N: np.ndarray, alpha: np.ndarray, theta: np.ndarray
    ) -> np.ndarray:
        """The measured rope-held true angles minus the target ``alpha``, ``theta`` (12,)
        each, as (24,) rad (columns alpha_1, theta_1, ...), from this cycle's commanded
        ``counts`` (n,) and drum tensions ``tension_N`` (n,).  The returned array is
        reused by the next call."""
        u = self.track(counts)
        act = self.ff.actuation
        ga, gt = act.commanded_angles(alpha, theta)
        self._a[0], self._t[0] = ga, gt
        F = self._F
        np.multiply(u, 1.0 + tension_N * self._fbar() / self._EA, out=F)
        dq = self._dq
        dq[:] = 0.0
        for _ in range(max(1, self.iterations)):
            L, J, _s = lengths_and_jacobian(act.geometry, self._a, self._t)
            Jm = J[0]
            self.jacobian[:] = Jm
            r = F - self._box - L[0]
            step = np.linalg.solve(Jm.T @ Jm, Jm.T @ r)
            dq += step
            self._a[0] += step[0::2]
            self._t[0] += step[1::2]
        return dq

    def _fbar(self) -> np.ndarray:
        """Each rope's mean friction factor at the current estimate's angles."""
        if not self._friction:
            return np.ones_like(self._F)
        ph = self.ff.physics
        wraps = wrap_angles(self.ff.holes, self._a[0], self._t[0])
        _cross, mean = tension_factors(self.state.nu, ph.mu_kinetic, wraps, self.ff.holes,
                                       self._box)  # fmt: skip
        return mean


__all__ = ["FrictionState", "TensionShape"]
