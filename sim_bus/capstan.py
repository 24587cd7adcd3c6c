"""Capstan friction where the ropes bend through the joints' holes.

A rope runs parallel to the link axis inside a link and straight across a joint, from
its hole in the proximal disk to its hole in the distal disk (``docs/ropes.md``).  So it
bends twice at each joint it crosses: at the proximal hole by ``beta_p``, the angle
between the proximal link's axis and the crossing, and at the distal hole by
``beta_d``, between the crossing and the distal link's axis (none at the hole it is
anchored in).  Over a bend of ``beta`` a sliding rope loses tension by the capstan
law, ``T_out = T_in e^(-mu beta)`` in the direction of travel: paid out (travelling
towards the tip) its tension rises towards the anchor, wound in it falls.

Per rope a mobilisation ``nu`` (-r..r, ``r = mu_s / mu_k``) says how much of the friction
acts: the tension in a stretch of rope beyond bends ``beta_i`` at joints ``i`` is the drum
tension times ``exp(nu sum_i mu_k_i beta_i)``.  Sliding (``|nu| = 1``, kinetic) it keeps
its sign while the rope travels the same way; on reversal or from rest the rope sticks,
and ``nu`` moves with the rope's travel ``du`` by ``du / presliding_mm`` until it reaches the
static ``r``, where it breaks away to the kinetic 1 (static above kinetic).  A rope at rest
keeps its ``nu``: the friction holds what it held.

>>> nu, slip = friction_update(np.zeros(2), np.zeros(2, bool), np.array([0.01, -1.0]), 0.05, 1.5)
>>> nu.round(6).tolist(), slip.tolist()      # 0.01 mm: still sticking; 1 mm wound in: sliding
([0.2, -1.0], [False, True])
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from hrm_ctrl.kinematics import joint_rotation
from hrm_ctrl.ropes.routing import RopeRouting

TRAVEL_AT_REST_MM = 1e-6  # rope travel below this between two states: the rope is at rest


@dataclass(frozen=True, eq=False)
class HoleGeometry:
    """Every rope's holes at every joint (read-only): ``p`` (12, n, 3) in the frame before
    the joint, ``q`` (12, n, 3) in the frame after it, ``crosses`` (12, n), ``anchor``
    (12, n) (joint j is where the rope is anchored), ``in_link`` (12, n) the rope inside
    link j beyond joint j (0 past its anchor)."""

    p: np.ndarray
    q: np.ndarray
    crosses: np.ndarray
    anchor: np.ndarray
    in_link: np.ndarray


def hole_geometry(routing: RopeRouting, links_mm: np.ndarray) -> HoleGeometry:
    """The holes of ``routing`` on links ``links_mm`` (12,)."""
    n_j = int(routing.proximal_disk.shape[0])
    joints = np.arange(n_j)[:, None]
    k = routing.joint_of_rope[None, :]
    crosses = joints <= k
    anchor = joints == k
    r, phi = routing.hole_radius, routing.hole_angle
    p = np.zeros((n_j, routing.n_ropes, 3))
    p[..., 0] = r * np.cos(phi)
    p[..., 1] = r * np.sin(phi)
    q = p.copy()
    p[..., 2] = -routing.proximal_disk[:, None]
    q[..., 2] = routing.distal_disk[:, None]
    gap = np.asarray(links_mm, float) - routing.distal_disk
    gap[:-1] -= routing.proximal_disk[1:]
    in_link = gap[:, None] * (joints < k)
    for a in (p, q, crosses, anchor, in_link):
        a.setflags(write=False)
    return HoleGeometry(p, q, crosses, anchor, in_link)


def wrap_angles(
    holes: HoleGeometry, alpha: np.ndarray, theta: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(beta_p, beta_d, s)``, each (12, n): the rope's bend (rad) at the proximal and
    the distal hole of every joint it crosses (0 elsewhere and at its anchor) and the
    crossing's length (mm), for rope-geometric angles ``alpha``, ``theta`` (12,).

    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.routing import routing_from_model
    >>> m = default_robot()
    >>> h = hole_geometry(routing_from_model(m), m.links)
    >>> a = np.zeros(12); a[0] = 0.4
    >>> bp, bd, s = wrap_angles(h, a, np.zeros(12))
    >>> bool(np.allclose(bp[1:], 0.0))          # only joint 1 is bent
    True
    >>> round(float(bp[0, 3] + bd[0, 3]), 6), round(float(bp[0, 0]), 6)   # passing; anchored
    (0.4, 0.2)
    """
    R = joint_rotation(alpha, theta)  # (12, 3, 3)
    v = np.einsum("jab,jmb->jma", R, holes.q) - holes.p  # crossing, frame before
    s = np.sqrt(np.einsum("jma,jma->jm", v, v))
    safe = np.where(s > 0.0, s, 1.0)
    cos_p = v[..., 2] / safe
    cos_d = np.einsum("ja,jma->jm", R[:, :, 2], v) / safe  # against the distal axis
    beta_p = np.where(holes.crosses, np.arccos(np.clip(cos_p, -1.0, 1.0)), 0.0)
    beta_d = np.where(holes.crosses & ~holes.anchor, np.arccos(np.clip(cos_d, -1.0, 1.0)), 0.0)
    return beta_p, beta_d, s * holes.crosses


def friction_update(
    nu: np.ndarray,
    sliding: np.ndarray,
    travel_mm: np.ndarray,
    presliding_mm: float,
    static_ratio: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The ropes' friction mobilisation ``nu`` (n,) and sliding flags after each rope
    travelled ``travel_mm`` (n,; > 0 paid out towards the tip): see the module docstring."""
    moving = np.abs(travel_mm) > TRAVEL_AT_REST_MM
    direction = np.sign(travel_mm)
    keeps = sliding & moving & (direction == np.sign(nu))
    trial = nu + travel_mm / presliding_mm
    breaks = ~keeps & moving & (np.abs(trial) >= static_ratio)
    out = np.where(keeps | breaks, direction, np.clip(trial, -static_ratio, static_ratio))
    out = np.where(moving, out, nu)
    return out, keeps | breaks


def tension_factors(
    nu: np.ndarray,
    mu_kinetic: np.ndarray,
    beta_p: np.ndarray,
    beta_d: np.ndarray,
    s: np.ndarray,
    holes: HoleGeometry,
    box_mm: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``(crossing, anchor, mean)``: the tension across every joint's crossing (12, n)
    and at the anchor (n,) as multiples of the drum tension, and the length-weighted
    mean factor along the whole free rope (n,) (box, crossings, links), which sets its
    stretch: ``stretched = u (1 + T_drum mean / EA)``.

    >>> from hrm_ctrl.model import default_robot
    >>> from hrm_ctrl.ropes.routing import routing_from_model
    >>> m = default_robot(); rt = routing_from_model(m); h = hole_geometry(rt, m.links)
    >>> a = np.zeros(12); a[11] = 0.5
    >>> bp, bd, s = wrap_angles(h, a, np.zeros(12))
    >>> c, anc, mean = tension_factors(-np.ones(36), np.full(12, 0.1), bp, bd, s, h, rt.box_length)
    >>> bool(np.isclose(anc[33], np.exp(-0.1 * bp[11, 33])))   # wound in: e^(-mu beta)
    True
    """
    mu = mu_kinetic[:, None]
    bends = mu * (beta_p + beta_d)  # (12, n)
    before = np.cumsum(bends, axis=0) - bends  # up to the joint's proximal hole
    crossing = np.exp(nu * (before + mu * beta_p))
    beyond = np.exp(nu * (before + bends))  # in the link after the joint
    anchor = np.exp(nu * (before + mu * beta_p)).max(axis=0, initial=0.0, where=holes.anchor)
    total = box_mm + s.sum(axis=0) + holes.in_link.sum(axis=0)
    weighted = box_mm + (s * crossing).sum(axis=0) + (holes.in_link * beyond).sum(axis=0)
    return crossing * holes.crosses, anchor, weighted / total
