"""The view library (hrm_ctrl/view): the scene built from a plan, the clearance colours
against link_clearance on a hand case, the update() rate bound, bad input.  The server
is real (viser on 127.0.0.1, port 0); what it holds is read from its scene handles."""

from __future__ import annotations

import socket
from typing import Any

import numpy as np
import pytest

from hrm_ctrl.formats.planfile import PlanDoc
from hrm_ctrl.kinematics import joint_centres
from hrm_ctrl.model import default_robot
from hrm_ctrl.planning.environment import Box, Environment, link_clearance
from hrm_ctrl.view import geometry as g
from hrm_ctrl.view.server import M_PER_MM, ArmView, ViewError

MODEL = default_robot()
R = 0.5 * MODEL.outer_diameter  # link radii (15 mm)


def _box_beside(link: int, gap_mm: float) -> Box:
    """A 40 mm cube beside the middle of 1-based ``link`` of the straight arm (along +x),
    ``gap_mm`` from the link's surface (in +y)."""
    O = joint_centres(MODEL, np.zeros(12), np.zeros(12))
    mid = 0.5 * (O[link - 1] + O[link])
    return Box(mid + np.array([0.0, R[link - 1] + gap_mm + 20.0, 0.0]), np.full(3, 40.0))


def _plan(steps: int, env: Environment | None) -> PlanDoc:
    """A plan of ``steps`` steps bending every alpha from 0 to 10 deg, joints by Eq. 4."""
    out = []
    for k in range(steps):
        a = np.full(12, np.deg2rad(10.0) * k / max(steps - 1, 1))
        t = np.zeros(12)
        out.append(
            {
                "travel_mm": 5.0 * k,
                "alpha_rad": a.tolist(),
                "theta_rad": t.tolist(),
                "joints_mm": joint_centres(MODEL, a, t).tolist(),
            }
        )
    doc: dict[str, Any] = {
        "format": "hrm-plan/1",
        "robot": {"links_mm": [float(v) for v in MODEL.links]},
        "path_mm": [[2007.0, 0.0, 0.0], [2100.0, 0.0, 0.0]],
        "steps": out,
        "report": {},
    }
    if env is not None:
        doc["scenario"] = {"environment": env.to_dict()}
    return PlanDoc.from_dict(doc)


def _centres_m(view: ArmView) -> np.ndarray:
    return np.array([h.position for h in view.arm_links])


def test_scene_from_a_plan_holds_environment_path_and_arm_at_the_step() -> None:
    env = Environment((_box_beside(3, 50.0),))
    plan = _plan(5, env)
    with ArmView(MODEL, plan.environment, plan, step=2) as view:
        assert view.url == f"http://127.0.0.1:{view.port}/" and view.port > 0
        names = view.scene_names()
        assert "/env/box01" in names and "/plan/path" in names
        assert [f"/arm/link{i:02d}" for i in range(1, 13)] == [
            n for n in names if n.startswith("/arm/")
        ]
        c, _q, h = g.link_cylinders(plan.joints_mm[2])
        assert np.allclose(_centres_m(view), c * M_PER_MM, atol=1e-9)
        assert np.allclose([hd.height for hd in view.arm_links], h * M_PER_MM, atol=1e-6)
        assert all(hd.visible for hd in view.arm_links)
        view.show_step(4)  # what the slider does
        c4 = g.link_cylinders(plan.joints_mm[4])[0]
        assert np.allclose(_centres_m(view), c4 * M_PER_MM, atol=1e-9)
        assert np.abs(c4 - c)[-1].max() > 50.0  # the tip moved: the step shown changed


def test_link_cylinder_turns_z_onto_the_link() -> None:
    O = joint_centres(MODEL, np.full(12, 0.2), np.full(12, -0.1))
    _c, q, h = g.link_cylinders(O)
    for i in range(12):
        w, x, y, z = q[i]
        # rotate +z by the quaternion
        v = np.array([2 * (x * z + w * y), 2 * (y * z - w * x), 1 - 2 * (x * x + y * y)])
        d = (O[i + 1] - O[i]) / h[i]
        assert np.allclose(v, d, atol=1e-12)


def test_clearance_colours_match_link_clearance_on_a_hand_case() -> None:
    # link 3 is 2 mm into a box, link 7 is 3 mm off another, link 10 is 30 mm off a third
    env = Environment((_box_beside(3, -2.0), _box_beside(7, 3.0), _box_beside(10, 30.0)))
    a = t = np.zeros(12)
    c = link_clearance(env, joint_centres(MODEL, a, t)[None], R)[0]
    assert c[2] == pytest.approx(-2.0, abs=1e-3)
    assert c[6] == pytest.approx(3.0, abs=1e-3)
    assert c[9] == pytest.approx(30.0, abs=1e-3)
    with ArmView(MODEL, env, live=True) as view:
        assert not any(h.visible for h in view.arm_links)  # nothing before the first pose
        assert view.update(a, t)
        colours = [tuple(int(v) for v in h.color) for h in view.arm_links]
        assert np.allclose(view.last_clearance_mm, c)
    want = [g.BAND_RGB[g.clearance_band(v)] for v in c]
    assert colours == want
    assert colours[2] == g.BAND_RGB[g.ClearanceBand.COLLISION]
    assert colours[6] == g.BAND_RGB[g.ClearanceBand.CLOSE]
    assert colours[9] == g.BAND_RGB[g.ClearanceBand.CLEAR]
    assert g.clearance_colours(np.full(2, np.inf)).tolist() == [list(g.BAND_RGB["free"])] * 2


def test_update_is_bounded_to_its_rate_and_flush_shows_the_last_pose() -> None:
    now = [0.0]
    with ArmView(MODEL, None, live=True, max_rate_hz=30.0, clock=lambda: now[0]) as view:
        shown = 0
        for k in range(200):  # 200 poses in 0.2 s (1 kHz)
            now[0] = 0.001 * k
            shown += view.update(np.full(12, 0.001 * k), np.zeros(12))
        assert view.updates == 200
        assert shown == view.pushes
        assert 6 <= view.pushes <= 0.2 * 30.0 + 1  # every 1/30 s, the first at once
        last = joint_centres(MODEL, np.full(12, 0.199), np.zeros(12))
        assert not np.allclose(_centres_m(view), g.link_cylinders(last)[0] * M_PER_MM)
        assert view.flush()
        assert np.allclose(_centres_m(view), g.link_cylinders(last)[0] * M_PER_MM, atol=1e-9)
        assert not view.flush()  # nothing held back any more
        n = view.pushes
        now[0] = 1.0
        assert view.update(np.full(12, 0.199), np.zeros(12))  # the same pose again
        assert view.pushes == n  # nothing sent


def test_update_from_threads_is_consistent() -> None:
    import threading

    with ArmView(MODEL, None, live=True, max_rate_hz=1e6) as view:

        def feed(sign: float) -> None:
            for k in range(50):
                view.update(np.full(12, sign * 0.002 * k), np.zeros(12))

        th = [threading.Thread(target=feed, args=(s,)) for s in (1.0, -1.0)]
        for x in th:
            x.start()
        for x in th:
            x.join(30.0)
        assert view.updates == 100
        # every link shows one pose: all centres from the same alpha
        got = _centres_m(view) / M_PER_MM
        ok = False
        for s in (1.0, -1.0):
            for k in range(50):
                c = g.link_cylinders(joint_centres(MODEL, np.full(12, s * 0.002 * k), np.zeros(12)))
                ok |= bool(np.allclose(got, c[0], atol=1e-6))
        assert ok


def test_bad_input_is_refused() -> None:
    plan = _plan(3, None)
    with pytest.raises(ViewError, match=r"--step must be 0\.\.2"):
        ArmView(MODEL, None, plan, step=3)
    with pytest.raises(ViewError, match="--port"):
        ArmView(MODEL, None, plan, port=70000)
    with ArmView(MODEL, None, live=True) as view:
        with pytest.raises(ViewError, match="12 finite angles"):
            view.update(np.zeros(11), np.zeros(12))
        with pytest.raises(ViewError, match="12 finite angles"):
            view.update(np.full(12, np.nan), np.zeros(12))
        with pytest.raises(ViewError, match="no plan"):
            view.show_step(0)
    with socket.socket() as s:  # a port in use is refused, not silently moved
        s.bind(("127.0.0.1", 0))
        s.listen()
        port = s.getsockname()[1]
        with pytest.raises(ViewError, match=f"--port {port}: the port is in use"):
            ArmView(MODEL, None, plan, port=port)


def _received_bytes(url: str, origin: str | None) -> tuple[int, int | None]:
    """Connect to the view's websocket as a browser page of ``origin`` would (viser's
    subprotocol); the bytes received in the first second and the close code, if closed."""
    import viser
    from websockets.exceptions import ConnectionClosed
    from websockets.sync.client import connect
    from websockets.typing import Origin, Subprotocol

    ws_url = url.replace("http://", "ws://")
    got = 0
    with connect(
        ws_url,
        origin=None if origin is None else Origin(origin),
        subprotocols=[Subprotocol(f"viser-v{viser.__version__}")],
        proxy=None,
        open_timeout=10,
    ) as ws:
        try:
            while True:
                msg = ws.recv(timeout=1.0)
                got += len(msg)
        except TimeoutError:
            return got, None
        except ConnectionClosed as exc:
            return got, exc.rcvd.code if exc.rcvd is not None else None


def test_a_foreign_origin_gets_nothing_of_the_scene() -> None:
    env = Environment(tuple(_box_beside(k, 50.0) for k in (3, 6, 9)))
    plan = _plan(5, env)
    with ArmView(MODEL, plan.environment, plan, step=2) as view:
        for origin in ("http://evil.example", "null", f"http://127.0.0.1:{view.port + 1}"):
            got, code = _received_bytes(view.url, origin)
            assert (got, code) == (0, 1008), origin
        assert view.refused_origins == [
            "http://evil.example",
            "null",
            f"http://127.0.0.1:{view.port + 1}",
        ]
        # the view's own page (by the URL printed, or by localhost), and a client that is
        # not a browser (no Origin), get the scene
        for origin in (f"http://127.0.0.1:{view.port}", f"http://localhost:{view.port}", None):
            got, code = _received_bytes(view.url, origin)
            assert code is None and got > 1_000, (origin, got)
        assert len(view.refused_origins) == 3


def test_the_trail_is_served_thinned_and_not_resent_unchanged() -> None:
    from hrm_ctrl.view.server import TRAIL_MIN_INTERVAL_S

    now = [0.0]
    with ArmView(MODEL, None, None, live=True, clock=lambda: now[0]) as view:
        assert "/live/trail" not in view.scene_names()
        trail = np.stack([np.linspace(0.0, 2500.0, 6001), np.zeros(6001), np.zeros(6001)], 1)
        assert view.show_trail(trail[:2000])
        assert "/live/trail" in view.scene_names()
        seg = view._trail.points  # what the page is sent (m)
        assert seg.shape == (1999, 2, 3)
        assert np.allclose(seg, g.polyline_segments(trail[:2000]) * M_PER_MM, atol=1e-7)
        now[0] += 0.5 * TRAIL_MIN_INTERVAL_S
        assert not view.show_trail(trail)  # grown, but too soon after the last one sent
        now[0] += 0.5 * TRAIL_MIN_INTERVAL_S
        assert not view.show_trail(trail[:2000] + 0.001)  # within SAME_POSE_MM: not resent
        assert view.show_trail(trail)  # the trail grew: thinned to MAX_TRAIL_POINTS
        assert view.trail_mm is not None and len(view.trail_mm) == g.MAX_TRAIL_POINTS
        assert np.array_equal(view.trail_mm[[0, -1]], trail[[0, -1]])
        assert view._trail.points.shape == (g.MAX_TRAIL_POINTS - 1, 2, 3)
        assert view.scene_names().count("/live/trail") == 1
        for bad in (np.zeros((1, 3)), np.zeros((4, 2)), np.full((3, 3), np.nan)):
            with pytest.raises(ViewError, match="trail: expected"):
                view.show_trail(bad)


def test_the_tip_camera_sits_on_the_tip_frame_looking_along_the_last_link() -> None:
    from hrm_ctrl.kinematics import frames

    a = np.linspace(-0.2, 0.25, 12)
    t = np.linspace(0.15, -0.1, 12)
    with ArmView(MODEL, None, None, live=True) as view:
        assert view.tip_pose_mm is None and not view._tipcam.visible
        assert view.update(a, t)
        R, O = frames(MODEL, a, t)
        pos, wxyz = view.tip_pose_mm
        link12 = (O[12] - O[11]) / np.linalg.norm(O[12] - O[11])
        assert np.allclose(pos, O[12] + g.TIP_CAMERA_AHEAD_MM * link12, atol=1e-9)
        assert np.allclose(g.quaternion_rotate(wxyz, np.array([0.0, 0.0, 1.0])), link12)
        assert np.allclose(g.quaternion_rotate(wxyz, np.array([1.0, 0.0, 0.0])), R[11][:, 0])
        assert view._tipcam.visible
        assert np.allclose(view._tipcam.position, pos * M_PER_MM)
        assert np.allclose(view._tipcam.wxyz, wxyz)


def test_the_tip_camera_is_rendered_on_the_host_when_the_tip_moves(monkeypatch: Any) -> None:
    import time

    from hrm_ctrl.kinematics import frames
    from hrm_ctrl.view import server as srv
    from hrm_ctrl.view import tip_camera as tc

    ahead = Box(np.array([2300.0, 0.0, 0.0]), np.full(3, 100.0))  # before the straight tip
    env = Environment((ahead,))
    a0, a1 = np.zeros(12), np.full(12, 0.002)

    def wait(cond: Any, what: str) -> None:
        end = time.monotonic() + 30.0
        while not cond() and time.monotonic() < end:
            time.sleep(0.02)
        assert cond(), what

    with ArmView(MODEL, env, None, live=True) as view:
        assert view._tip_on.value  # on from the start
        view.update(a0, np.zeros(12))
        time.sleep(0.3)
        assert view.tip_frames == 0  # no page connected: nothing rendered
        monkeypatch.setattr(view.server, "get_clients", lambda: {7: object()})
        wait(lambda: view.tip_frames >= 1, "a frame once a page is there")
        R = frames(MODEL, a0, np.zeros(12))[0]
        cam = tc.TipCamera(srv.TIP_CAMERA_WIDTH, srv.TIP_CAMERA_HEIGHT, srv.TIP_CAMERA_FOV_RAD)
        want, depth = tc.render(tc.TipScene.of(env), cam, view.tip_pose_mm[0], R[-1])
        assert np.array_equal(view._tip_image.image, want)  # the frame sent
        assert np.isfinite(depth).sum() > 100  # it shows the box
        assert view.tip_cpu_ms() > 0.0 and view.tip_error is None
        n = view.tip_frames
        time.sleep(0.5)  # a still tip is not rendered again
        assert view.tip_frames == n
        assert view.update(a1, np.zeros(12)) or view.flush()  # shown, not held back
        wait(lambda: view.tip_frames > n, "a frame of the moved tip")
        n = view.tip_frames
        view._tip_on.value = False  # unticked: no frames
        assert view.update(a0, np.zeros(12)) or view.flush()  # the tip did move
        time.sleep(0.5)
        assert view.tip_frames == n
    assert not view._tip_thread.is_alive()  # closed with the view
