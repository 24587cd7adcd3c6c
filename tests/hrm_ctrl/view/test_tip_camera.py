"""The tip camera rendered on the host (hrm_ctrl/view/tip_camera.py) against the
environment's own distance functions: every pixel's hit lies on the obstacle's surface
(free distance 0) and the ray before it runs through free space; what no ray meets is
the background; the trail shows where it is seen and not behind a wall."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hrm_ctrl.planning.environment import Box, Environment, RoundOpening, Wall
from hrm_ctrl.planning.scenarios import scenario
from hrm_ctrl.view import tip_camera as tc
from hrm_ctrl.view.geometry import perpendicular

CAM = tc.TipCamera(64, 48, math.radians(70.0))
PIPE = scenario("bent-pipe")
PIPE_SCENE = tc.TipScene.of(PIPE.environment)
# the hit on a pipe's wall: off the model's wall by the axis' simplification at most
# (plus the float32 of the cast)
ON_WALL_MM = tc.AXIS_TOLERANCE_MM + 0.05


def _looking(z: np.ndarray, roll: float = 0.0) -> np.ndarray:
    """A world-from-camera rotation whose z axis is along ``z``."""
    z = z / np.linalg.norm(z)
    x = perpendicular(z)
    y = np.cross(z, x)
    x, y = math.cos(roll) * x + math.sin(roll) * y, -math.sin(roll) * x + math.cos(roll) * y
    return np.stack([x, y, z], axis=1)


def _hits(o: np.ndarray, R: np.ndarray, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The world rays of the pixels (P, 3) and the hit points of those that hit (H, 3)."""
    rays = CAM.rays.astype(float) @ R.T
    d = depth.reshape(-1).astype(float)
    hit = np.isfinite(d)
    return rays, o + d[hit, None] * rays[hit]


def _check_against_model(env: Environment, o: np.ndarray, R: np.ndarray, depth: np.ndarray,
                         on_surface_mm: float) -> int:  # fmt: skip
    rays, p = _hits(o, R, depth)
    if not len(p):
        return 0
    assert np.abs(env.free_distance(p)).max() <= on_surface_mm
    d = depth.reshape(-1)
    hit = np.isfinite(d)
    for s in (0.1, 0.3, 0.5, 0.7, 0.9):  # the way to each hit is free
        q = o + s * d[hit, None].astype(float) * rays[hit]
        assert env.free_distance(q).min() >= -on_surface_mm
    return int(hit.sum())


@settings(max_examples=40, deadline=None)
@given(
    along=st.floats(5.0, PIPE.path.length - 5.0),
    off=st.floats(0.0, 25.0),
    turn=st.floats(0.0, 2.0 * math.pi),
    tilt=st.floats(0.0, math.radians(35.0)),
    back=st.booleans(),
)
def test_every_pixel_in_the_bent_pipe_shows_its_wall(
    along: float, off: float, turn: float, tilt: float, back: bool
) -> None:
    axis = PIPE.path
    c, tangent = axis.point_at(along), axis.tangent_at(along)
    u = perpendicular(tangent)
    v = np.cross(tangent, u)
    side = math.cos(turn) * u + math.sin(turn) * v
    o = c + off * side
    z = (-1.0 if back else 1.0) * tangent
    z = math.cos(tilt) * z + math.sin(tilt) * np.cross(side, z)
    R = _looking(z, roll=turn)
    img, depth = tc.render(PIPE_SCENE, CAM, o, R)
    assert img.shape == (48, 64, 3)
    _check_against_model(PIPE.environment, o, R, depth, ON_WALL_MM)
    # a ray with no hit leaves through an end of the pipe: beyond its end plane
    rays, _p = _hits(o, R, depth)
    missed = rays[~np.isfinite(depth.reshape(-1))]
    ends = list(zip(PIPE_SCENE.pipes.end_centre, PIPE_SCENE.pipes.end_normal, strict=True))
    far = o + tc.MAX_RANGE_MM * missed
    out = np.zeros(len(missed), dtype=bool)
    for end, into in ends:
        out |= (far - end) @ into < 0.0
    assert out.all()


def test_the_depth_on_a_straight_pipe_is_the_analytic_one() -> None:
    o = PIPE.path.points[0] + np.array([40.0, 0.0, 0.0])  # on the axis, first straight
    R = _looking(np.array([1.0, 0.0, 0.0]))
    _img, depth = tc.render(PIPE_SCENE, CAM, o, R)
    rays = CAM.rays.astype(float)  # the camera's frame: z along the axis
    want = 35.0 / np.hypot(rays[:, 0], rays[:, 1])  # radius 35 mm across the axis
    near = want * rays[:, 2] < 80.0  # within the straight part (the bend starts 118 mm on)
    got = depth.reshape(-1)[near]
    assert np.allclose(got, want[near], atol=ON_WALL_MM / 0.3)  # at >= 17 deg to the wall


def test_walls_show_their_openings_and_bounds() -> None:
    sc = scenario("cabins")
    scene = tc.TipScene.of(sc.environment)
    entrance = sc.environment.obstacles[0]
    assert isinstance(entrance, Wall)
    # in front of the entrance wall (x = 1200), 300 mm out, looking at its opening
    o = entrance.openings[0].centre + np.array([-300.0, 0.0, 0.0])
    R = _looking(np.array([1.0, 0.0, 0.0]))
    img, depth = tc.render(scene, CAM, o, R)
    _check_against_model(sc.environment, o, R, depth, 1e-3)
    # the centre looks through the opening (80 mm at 300 mm: 15 deg across) onto the
    # partition or nothing; the image's corners (45 deg off) hit the wall at x = 1200
    centre = depth[24, 32]
    assert not (abs(centre - 300.0) < 1.0)
    for r, c in ((0, 0), (0, 63), (47, 0), (47, 63)):
        ray = CAM.rays[r * 64 + c].astype(float)
        assert depth[r, c] == pytest.approx(300.0 / ray[2], rel=1e-4)
    assert tuple(img[5, 5]) != tc.BACKGROUND_RGB


def test_a_box_is_drawn_where_it_is_and_nowhere_else() -> None:
    box = Box(np.array([500.0, 0.0, 0.0]), np.array([100.0, 60.0, 40.0]))
    env = Environment((box,))
    scene = tc.TipScene.of(env)
    o, R = np.zeros(3), _looking(np.array([1.0, 0.0, 0.0]))
    img, depth = tc.render(scene, CAM, o, R)
    n = _check_against_model(env, o, R, depth, 1e-3)
    assert depth[24, 32] == pytest.approx(450.0 / float(CAM.rays[24 * 64 + 32][2]), rel=1e-5)
    # the box's face (60 x 40 at 450 mm) seen as about fy * 60 / 450 x fy * 40 / 450 pixels
    w, h = CAM.fy * 60.0 / 450.0, CAM.fy * 40.0 / 450.0
    assert abs(n - w * h) < 2.0 * (w + h) + 4.0
    miss = ~np.isfinite(depth) & ~(img == tc.CROSS_RGB).all(axis=2)
    assert (img[miss] == tc.BACKGROUND_RGB).all()
    assert not (img[np.isfinite(depth)] == tc.BACKGROUND_RGB).all(axis=1).any()
    # boxes behind the camera, or off to the side, are not drawn
    away = Environment((Box(np.array([-500.0, 0.0, 0.0]), np.full(3, 50.0)),))
    assert not np.isfinite(tc.render(tc.TipScene.of(away), CAM, o, R)[1]).any()


def test_the_trail_shows_unless_a_wall_hides_it() -> None:
    o, R = np.zeros(3), _looking(np.array([1.0, 0.0, 0.0]))
    # the camera's x is the world's +y, its y (down in the image) the world's +z
    trail = np.array([[100.0, 30.0, -20.0], [300.0, 30.0, -20.0]])  # ahead, right, up
    img, _ = tc.render(tc.TipScene.of(None), CAM, o, R, trail)
    orange = (img == tc.TRAIL_RGB).all(axis=2)
    rows, cols = np.nonzero(orange)
    assert len(rows) > 10
    u = CAM.cx + CAM.fy * 30.0 / np.array([100.0, 300.0])  # the ends' pixels
    v = CAM.cy - CAM.fy * 20.0 / np.array([100.0, 300.0])
    assert u.min() - 1 <= cols.min() and cols.max() <= u.max() + 1
    assert v.min() - 1 <= rows.min() and rows.max() <= v.max() + 1
    wall = Environment((Wall(np.array([50.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0])),))
    img, depth = tc.render(tc.TipScene.of(wall), CAM, o, R, trail)
    assert not (img == tc.TRAIL_RGB).all(axis=2).any()  # behind the wall
    assert np.isfinite(depth).all()
    hole = Wall(np.array([50.0, 0.0, 0.0]), np.array([1.0, 0.0, 0.0]),
                openings=(RoundOpening(np.zeros(3), 200.0),))  # fmt: skip
    img, _ = tc.render(tc.TipScene.of(Environment((hole,))), CAM, o, R, trail)
    assert (img == tc.TRAIL_RGB).all(axis=2).sum() == len(rows)  # seen through the hole


def test_no_environment_is_the_background_and_the_cross() -> None:
    img, depth = tc.render(tc.TipScene.of(None), CAM, np.zeros(3), np.eye(3))
    assert not np.isfinite(depth).any()
    cross = (img == tc.CROSS_RGB).all(axis=2)
    assert cross.sum() == 4 * (tc.CROSS_PX - 1)
    assert (img[~cross] == tc.BACKGROUND_RGB).all()


def test_the_simplified_axis_stays_within_its_tolerance() -> None:
    pts = PIPE.path.points
    kept = tc.simplify_polyline(pts, tc.AXIS_TOLERANCE_MM)
    assert len(kept) < len(pts) // 4
    seg = np.diff(kept, axis=0)
    t = np.clip(
        np.einsum("psj,sj->ps", pts[:, None] - kept[None, :-1], seg) / (seg * seg).sum(1), 0, 1
    )
    near = kept[None, :-1] + t[..., None] * seg[None]
    assert np.linalg.norm(near - pts[:, None], axis=2).min(axis=1).max() <= tc.AXIS_TOLERANCE_MM
