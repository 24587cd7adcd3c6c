"""The 3D view in the browser (issue 11): a viser server on 127.0.0.1 showing the
environment (pipe, walls with their openings, boxes), the planned path and backbone, the
arm at a step chosen with a slider, and, fed by :meth:`ArmView.update`, the arm as the
host estimates it, every link a cylinder coloured by its clearance band
(:mod:`hrm_ctrl.view.geometry`).

The websocket serves the view's own page only: a connection with another page's
``Origin`` is closed before the scene is sent (:func:`origin_allowed`).  viser ships its
built web client in its wheel: the page needs no internet.  The viewer's
unit is the metre (the stack's millimetres scaled by :data:`M_PER_MM`).

Scene names (a test or a tool finds the objects by them in viser's scene tree):
``/env/...``, ``/plan/path``, ``/plan/backbone``, ``/plan/arm/linkNN`` (the planned arm
at the slider's step), ``/arm/linkNN`` (the arm shown: the planned one, or with
``live`` the estimated one, hidden until the first :meth:`ArmView.update`),
``/tip/camera`` (the tip camera's frustum) and ``/live/trail`` (the trail the tip has
drawn, from :meth:`ArmView.show_trail`).

The tip camera (a ``live`` view's): a virtual camera at the end effector looking along
the tip's axis (:func:`hrm_ctrl.view.geometry.tip_camera_pose`), shown in the panel as
the image "tip camera" (on from the start; its checkbox turns it off).  The host renders
it (:mod:`hrm_ctrl.view.tip_camera`: a ray cast in NumPy of the known environment, the
trail drawn in) and sends the frame as a JPEG image; the page only decodes and shows it
(it needs no GPU for it).  A thread renders a frame whenever the tip has moved,
the trail has changed or a page has connected, at most :data:`TIP_CAMERA_RATE_HZ` times a
second, and only while a page is connected (``tip_frames`` counts the frames sent,
:meth:`ArmView.tip_rate_hz` their rate, :meth:`ArmView.tip_cpu_ms` the thread's CPU per
frame)."""

from __future__ import annotations

import contextlib
import io
import math
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from hrm_ctrl.errors import HrmError
from hrm_ctrl.formats.planfile import PlanDoc
from hrm_ctrl.kinematics import frames, joint_centres
from hrm_ctrl.model import RobotModel
from hrm_ctrl.planning.environment import (
    DISPLAY_GOLDEN_ITERATIONS,
    GOLDEN_ITERATIONS,
    Box,
    Environment,
    Pipe,
    Wall,
    link_clearance,
)
from hrm_ctrl.view import geometry as g
from hrm_ctrl.view.tip_camera import TipCamera, TipScene
from hrm_ctrl.view.tip_camera import render as render_tip_camera

M_PER_MM = 1e-3
HOST = "127.0.0.1"  # the view is served to this machine only
# update() pushes at most this many poses a second to the browser (a faster caller's poses
# in between are dropped; the latest is kept for flush()).
MAX_UPDATE_RATE_HZ = 30.0
SAME_POSE_MM = 0.01  # a pose within this of the one shown is not sent again
CLEARANCE_REUSE_MM = 0.25  # the clearance shown may be this much off (see ArmView._push),
# and as much again from its search (DISPLAY_GOLDEN_ITERATIONS)
PLANNED_OPACITY = 0.35
TIP_CAMERA_WIDTH, TIP_CAMERA_HEIGHT = 192, 144  # pixels of the tip camera's frame
TIP_CAMERA_FOV_RAD = math.radians(70.0)  # vertical field of view
TIP_CAMERA_RATE_HZ = 15.0  # frames a second at most (the tip moving)
TIP_CAMERA_COSTS_KEPT = 512  # the CPU per frame of this many last frames is kept
TIP_THREAD_JOIN_S = 30.0  # close() waits this long at most for a frame being rendered
TRAIL_MIN_INTERVAL_S = 0.2  # a growing trail is sent at most this often (it is whole each time)
TIP_FRUSTUM_M = 0.03  # the frustum drawn at the tip (m)
TIP_FRUSTUM_RGB = (250, 210, 40)
ENV_OPACITY = 0.18


WS_POLICY_VIOLATION = 1008  # websocket close code (RFC 6455): a foreign Origin


class ViewError(HrmError):
    """The view cannot be served (port, bad step, bad pose)."""


def own_origins(port: int) -> frozenset[str]:
    """The origins of the view's own page: the URL printed, or ``localhost`` for it.

    >>> sorted(own_origins(8080))
    ['http://127.0.0.1:8080', 'http://localhost:8080']
    """
    return frozenset({f"http://{HOST}:{port}", f"http://localhost:{port}"})


def origin_allowed(origins: list[str], port: int) -> bool:
    """Whether a websocket handshake with these ``Origin`` header values may see the view.

    A browser always sends one ``Origin`` on a websocket handshake: it must be the
    view's own page (:func:`own_origins`; ``null``, another host or another port is a
    foreign page, and so is a host name that merely resolves to 127.0.0.1, the DNS
    rebinding case).  No ``Origin`` at all is a client that is not a browser (a script
    on this machine, which can reach 127.0.0.1 anyway): accepted.  More than one
    ``Origin`` is refused.

    >>> origin_allowed(["http://127.0.0.1:8080"], 8080), origin_allowed([], 8080)
    (True, True)
    >>> origin_allowed(["http://evil.example"], 8080), origin_allowed(["null"], 8080)
    (False, False)
    >>> origin_allowed(["http://127.0.0.1:8081"], 8080)
    False
    """
    if not origins:
        return True
    return len(origins) == 1 and origins[0].lower().rstrip("/") in own_origins(port)


def _link_name(prefix: str, i: int) -> str:
    return f"{prefix}/link{i + 1:02d}"


class ArmView:
    """A running view; ``close()`` (or leaving the ``with`` block) stops its server.

    ``plan`` gives the path, the backbone and the slider over its steps (``step`` first);
    ``live``: the arm shown is the one :meth:`update` gives (the plan's arm at the slider
    step drawn translucent beside it).  ``port`` 0 picks a free port.
    """

    def __init__(
        self,
        model: RobotModel,
        environment: Environment | None = None,
        plan: PlanDoc | None = None,
        *,
        port: int = 0,
        step: int = 0,
        live: bool = False,
        max_rate_hz: float = MAX_UPDATE_RATE_HZ,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        import viser

        if not (isinstance(port, int) and 0 <= port <= 65535):
            raise ViewError(f"--port must be 0..65535, got {port!r}")
        if not (math.isfinite(max_rate_hz) and max_rate_hz > 0):
            raise ViewError(f"max_rate_hz must be > 0, got {max_rate_hz}")
        if plan is not None and not 0 <= step < plan.n_steps:
            raise ViewError(f"--step must be 0..{plan.n_steps - 1} (the plan's steps), got {step}")
        self.model = model
        self.environment = environment
        self.plan = plan
        self.live = live
        self.radius_mm = 0.5 * np.asarray(model.outer_diameter, dtype=float)
        self._min_dt_s = 1.0 / max_rate_hz
        self._clock = clock
        self._lock = threading.Lock()
        self._last_push = -math.inf
        self._pending: tuple[np.ndarray, np.ndarray] | None = None
        self.updates = 0  # update() calls
        self.pushes = 0  # poses sent to the browser
        self.last_clearance_mm: np.ndarray | None = None
        self.step = step
        self._pushed_O: np.ndarray | None = None
        self._clearance_O: np.ndarray | None = None
        self._clearance = np.zeros(0)
        self._names: list[str] = []
        self._sent: dict[int, dict[tuple[str, int], Any]] = {}
        self.tip_pose_mm: tuple[np.ndarray, np.ndarray] | None = None  # position, wxyz
        self._tip_version = 0  # bumped whenever the tip pose or the trail changes
        self._trail: Any = None
        self.trail_mm: np.ndarray | None = None  # the trail drawn (thinned)
        self._trail_t = -math.inf
        self._tip_R: np.ndarray | None = None  # the tip camera's world-from-camera rotation
        self.tip_frames = 0  # tip camera frames sent
        self.tip_error: str | None = None  # why the tip camera stopped, if it did
        self._tip_t: list[float] = []  # times of the first and the last frame sent
        self._tip_cpu_s: list[float] = []  # the thread's CPU per frame (the last ones)
        self._tip_stop = threading.Event()
        self._tip_thread: threading.Thread | None = None
        try:
            with contextlib.redirect_stdout(io.StringIO()):  # viser's banner: we print the URL
                self.server = viser.ViserServer(host=HOST, port=port, verbose=False)
        except OSError as exc:
            raise ViewError(f"cannot serve on {HOST}:{port} ({exc.strerror or exc})") from None
        self.port = int(self.server.get_port())
        self.url = f"http://{HOST}:{self.port}/"
        self._closed = False
        if port and self.port != port:  # viser moves on to the next free port: refuse that
            self.close()
            raise ViewError(f"--port {port}: the port is in use on {HOST}")
        self.refused_origins: list[str] = []  # the Origin headers of connections refused
        try:
            self._guard_origin()
        except BaseException:
            self.close()
            raise
        try:
            self._build()
        except BaseException:
            self.close()
            raise
        if live:
            self._tip_camera = TipCamera(TIP_CAMERA_WIDTH, TIP_CAMERA_HEIGHT, TIP_CAMERA_FOV_RAD)
            self._tip_scene = TipScene.of(environment)
            self.server.on_client_connect(self._new_page)
            self._tip_thread = threading.Thread(
                target=self._tip_camera_loop, name="hrm-view-tip-camera", daemon=True
            )
            self._tip_thread.start()

    # ------------------------------------------------------------------ origin
    def _guard_origin(self) -> None:
        """Close every websocket whose ``Origin`` is not this server's own page before
        anything is sent on it (:func:`origin_allowed`).

        A web page in the operator's browser can open a websocket to 127.0.0.1; only the
        ``Origin`` header the browser sets tells it from the view's own page.  viser
        offers no hook on the handshake, so the check runs as the first thing after it:
        a callback of viser's websocket server, run for a new connection before the
        tasks that send the scene start; the connection is closed with code 1008
        (policy violation) and the scene never leaves.  A viser without the connection
        table this needs is refused (:class:`ViewError`) rather than served unchecked.
        """
        ws = self.server._websock_server
        try:
            live = ws._live_connections
        except AttributeError:
            raise ViewError(
                "this viser version does not expose its websocket connections: "
                "the view cannot check a connection's Origin and is not served"
            ) from None
        port = self.port

        async def close_foreign(conn: Any) -> None:
            connection = live[conn.client_id]
            origins = connection.request.headers.get_all("Origin")
            if not origin_allowed(origins, port):
                self.refused_origins.append(", ".join(origins))
                await connection.close(WS_POLICY_VIOLATION, "origin not allowed")

        ws.on_client_connect(close_foreign)

    # ------------------------------------------------------------------ scene
    def _build(self) -> None:
        gui = self.server.gui
        # No shadows, no environment map: a page without a GPU (WebGL in software) drew
        # the moving arm 0.9 frames a second with both, 3.7-3.8 without the environment
        # map, and it shows the tip camera's frames in the same loop
        # (benchmarks/bench_tip_camera.py --lighting).
        self.server.scene.configure_default_lights(enabled=True, cast_shadow=False)
        self.server.scene.configure_environment_map(None)
        n = self.model.n_joints
        env_pts = self._draw_environment()
        self._arm = [
            self._add(
                "add_cylinder",
                _link_name("/arm", i),
                radius=float(self.radius_mm[i]) * M_PER_MM,
                height=1.0,
                color=g.BAND_RGB[g.ClearanceBand.FREE],
                receive_shadow=False,
                cast_shadow=False,
                visible=False,
            )
            for i in range(n)
        ]
        self._planned: list[Any] = []
        self._backbone = None
        self._tipcam = self._add(
            "add_camera_frustum",
            "/tip/camera",
            fov=TIP_CAMERA_FOV_RAD,
            aspect=TIP_CAMERA_WIDTH / TIP_CAMERA_HEIGHT,
            scale=TIP_FRUSTUM_M,
            thickness=1.5,
            thickness_units="screen",
            color=TIP_FRUSTUM_RGB,
            visible=False,
            cast_shadow=False,
            receive_shadow=False,
        )
        if self.live:
            self._tip_on = gui.add_checkbox("tip camera", initial_value=True)
            self._tip_image = gui.add_image(
                np.zeros((TIP_CAMERA_HEIGHT, TIP_CAMERA_WIDTH, 3), dtype=np.uint8),
                label="tip camera",
                format="jpeg",
            )
        gui.add_text(
            "arm shown",
            initial_value="estimated from drive feedback" if self.live else "the plan's",
            disabled=True,
        )
        self._clearance_text = gui.add_text("worst clearance", initial_value="-", disabled=True)
        gui.add_markdown(
            f"links: **green** clearance ≥ {g.WARN_CLEARANCE_MM:g} mm, **amber** "
            f"0–{g.WARN_CLEARANCE_MM:g} mm, **red** collision, **blue** no obstacle known"
        )
        pts = [env_pts]
        if self.plan is not None:
            p = self.plan
            self._add(
                "add_line_segments",
                "/plan/path",
                g.polyline_segments(p.path_mm) * M_PER_MM,
                g.PATH_RGB,
                thickness=3.0,
                thickness_units="screen",
            )
            pts.append(p.path_mm)
            pts.append(p.joints_mm.reshape(-1, 3))
            if self.live:
                self._planned = [
                    self._add(
                        "add_cylinder",
                        _link_name("/plan/arm", i),
                        radius=float(self.radius_mm[i]) * M_PER_MM,
                        height=1.0,
                        color=g.PLANNED_ARM_RGB,
                        opacity=PLANNED_OPACITY,
                        receive_shadow=False,
                        cast_shadow=False,
                    )
                    for i in range(n)
                ]
            self._step_slider = gui.add_slider(
                "plan step", min=0, max=max(p.n_steps - 1, 1), step=1, initial_value=self.step
            )
            self._step_text = gui.add_text("travel", initial_value="", disabled=True)
            self._step_slider.on_update(lambda _e: self.show_step(int(self._step_slider.value)))
            self.show_step(self.step)
        else:
            pts.append(joint_centres(self.model, np.zeros(n), np.zeros(n)))
        allp = np.concatenate([q.reshape(-1, 3) for q in pts if q.size])
        lo, hi = allp.min(axis=0), allp.max(axis=0)
        centre, size = 0.5 * (lo + hi), float(np.linalg.norm(hi - lo))
        cam = self.server.initial_camera
        cam.look_at = tuple(centre * M_PER_MM)
        cam.position = tuple((centre + size * np.array([0.25, -0.55, 0.45])) * M_PER_MM)

    def _add(self, method: str, name: str, *args: Any, **kwargs: Any) -> Any:
        """``self.server.scene.<method>(name, ...)``, the name kept for :meth:`scene_names`."""
        handle = getattr(self.server.scene, method)(name, *args, **kwargs)
        self._names.append(name)
        return handle

    def _draw_environment(self) -> np.ndarray:
        drawn: list[np.ndarray] = []
        near = self.plan.path_mm.mean(axis=0) if self.plan is not None else np.zeros(3)
        for k, o in enumerate(g.obstacles(self.environment)):
            name = f"/env/{type(o).__name__.lower()}{k + 1:02d}"
            if isinstance(o, Pipe):
                v, f = g.pipe_mesh(o)
                self._add(
                    "add_mesh_simple",
                    name,
                    v * M_PER_MM,
                    f,
                    color=g.ENV_RGB,
                    opacity=ENV_OPACITY,
                    side="double",
                    cast_shadow=False,
                    receive_shadow=False,
                )
                drawn.append(v)
            elif isinstance(o, Wall):
                patch, outlines = g.wall_shapes(o, near)
                if len(patch) >= 3:
                    self._add(
                        "add_mesh_simple",
                        name,
                        patch * M_PER_MM,
                        g.fan(patch),
                        color=g.ENV_RGB,
                        opacity=ENV_OPACITY,
                        side="double",
                        cast_shadow=False,
                        receive_shadow=False,
                    )
                    drawn.append(patch)
                for j, line in enumerate(outlines):
                    self._add(
                        "add_line_segments",
                        f"{name}/opening{j + 1:02d}",
                        g.polyline_segments(line) * M_PER_MM,
                        g.ENV_RGB,
                        thickness=2.0,
                        thickness_units="screen",
                    )
                    drawn.append(line)
            elif isinstance(o, Box):
                self._add(
                    "add_box",
                    name,
                    color=g.ENV_RGB,
                    dimensions=tuple(o.size * M_PER_MM),
                    opacity=0.35,
                    wxyz=g.box_wxyz(o),
                    position=tuple(o.centre * M_PER_MM),
                    cast_shadow=False,
                    receive_shadow=False,
                )
                drawn.append(o.centre[None] + 0.5 * o.size[None])
                drawn.append(o.centre[None] - 0.5 * o.size[None])
        return np.concatenate(drawn) if drawn else np.zeros((0, 3))

    def _place(self, handles: list[Any], O: np.ndarray, colours: np.ndarray | None) -> None:
        """Put the link cylinders ``handles`` on joint centres ``O``; only what changed is
        sent (a live pose: positions and orientations, a colour when its band changes)."""
        c, q, h = g.link_cylinders(O)
        state = self._sent.setdefault(id(handles), {})
        for i, hd in enumerate(handles):
            hd.position = tuple(c[i] * M_PER_MM)
            hd.wxyz = tuple(q[i])
            height = round(float(h[i]) * M_PER_MM, 7)
            if state.get(("h", i)) != height:
                hd.height = state[("h", i)] = height
            if colours is not None:
                rgb = tuple(int(x) for x in colours[i])
                if state.get(("c", i)) != rgb:
                    hd.color = state[("c", i)] = rgb
            if not state.get(("v", i)):
                hd.visible = state[("v", i)] = True

    def clearance_mm(self, O: np.ndarray, iterations: int = GOLDEN_ITERATIONS) -> np.ndarray:
        """(12,) link clearance (mm) of joint centres ``O`` (13, 3) against the
        environment (+inf where none is known); ``iterations`` of its golden-section
        search (:func:`~hrm_ctrl.planning.environment.link_clearance`)."""
        if self.environment is None:
            return np.full(len(O) - 1, math.inf)
        return link_clearance(self.environment, O[None], self.radius_mm, iterations=iterations)[0]

    def _show_clearance(self, c: np.ndarray) -> None:
        self.last_clearance_mm = c
        if np.isfinite(c).any():
            i = int(np.argmin(c))
            self._clearance_text.value = f"{c[i]:.1f} mm (link {i + 1})"
        else:
            self._clearance_text.value = "no obstacle known"

    def show_step(self, step: int) -> None:
        """Show the plan's arm at ``step`` (0-based): the arm itself, or with ``live`` the
        translucent planned arm beside the estimated one."""
        if self.plan is None:
            raise ViewError("no plan: no steps to show")
        if not 0 <= step < self.plan.n_steps:
            raise ViewError(f"step must be 0..{self.plan.n_steps - 1}, got {step}")
        p = self.plan
        O = p.joints_mm[step]
        with self._lock, self.server.atomic():
            self.step = step
            if self.live:
                self._place(self._planned, O, None)
            else:
                c = self.clearance_mm(O)
                self._place(self._arm, O, g.clearance_colours(c))
                self._show_clearance(c)
                R = frames(self.model, p.alpha_rad[step], p.theta_rad[step])[0]
                self._place_tip(R[-1], O[-1])
            self._step_text.value = f"{p.travel_mm[step]:.1f} mm ({p.phase[step].value})"
            bb = p.backbones_mm.get(step)
            if bb is not None:
                seg = g.polyline_segments(bb) * M_PER_MM
                if self._backbone is None:
                    self._backbone = self._add(
                        "add_line_segments",
                        "/plan/backbone",
                        seg,
                        g.BACKBONE_RGB,
                        thickness=2.0,
                        thickness_units="screen",
                    )
                else:
                    self._backbone.points = seg
                    self._backbone.visible = True
            elif self._backbone is not None:
                self._backbone.visible = False

    # ------------------------------------------------------------------ live
    def update(self, alpha: np.ndarray, theta: np.ndarray) -> bool:
        """Show the arm at joint angles ``alpha``, ``theta`` (rad, 12 each), coloured by
        clearance; thread-safe.  At most ``max_rate_hz`` poses a second reach the
        browser: a call sooner after the last one shown keeps its pose for the next call
        or :meth:`flush` and returns False.  A pose within :data:`SAME_POSE_MM` of the
        one shown sends nothing; the clearance is recomputed once a joint has moved
        :data:`CLEARANCE_REUSE_MM` (the colours and the worst value shown are off by less)."""
        a = np.asarray(alpha, dtype=float).reshape(-1)
        t = np.asarray(theta, dtype=float).reshape(-1)
        n = self.model.n_joints
        if (
            a.shape != (n,)
            or t.shape != (n,)
            or not (np.isfinite(a).all() and np.isfinite(t).all())
        ):
            raise ViewError(f"update: alpha and theta must be {n} finite angles each")
        with self._lock:
            self.updates += 1
            if self._closed:
                return False
            now = self._clock()
            if now - self._last_push < self._min_dt_s:
                self._pending = (a, t)
                return False
            self._last_push = now
            self._pending = None
            self._push(a, t)
            return True

    def flush(self) -> bool:
        """Show the pose an :meth:`update` held back, if any; True if one was shown."""
        with self._lock:
            if self._pending is None or self._closed:
                return False
            a, t = self._pending
            self._pending = None
            self._last_push = self._clock()
            self._push(a, t)
            return True

    def _push(self, a: np.ndarray, t: np.ndarray) -> None:
        R, O = frames(self.model, a, t)
        moved = math.inf if self._pushed_O is None else float(np.abs(O - self._pushed_O).max())
        if moved < SAME_POSE_MM:  # a held arm: nothing to send
            return
        # Clearance is 1-Lipschitz in the joints (a free distance along segments): within
        # CLEARANCE_REUSE_MM of the pose it was computed for, it is off by less than that.
        if self._clearance_O is None or float(np.abs(O - self._clearance_O).max()) >= (
            CLEARANCE_REUSE_MM
        ):
            self._clearance = self.clearance_mm(O, DISPLAY_GOLDEN_ITERATIONS)
            self._clearance_O = O
        c = self._clearance
        with self.server.atomic():
            self._place(self._arm, O, g.clearance_colours(c))
            self._show_clearance(c)
            self._place_tip(R[-1], O[-1])
        self._pushed_O = O
        self.pushes += 1

    def _place_tip(self, R_tip: np.ndarray, O_tip: np.ndarray) -> None:
        """Put the tip camera (its frustum, the pose its frames are rendered from) on the
        tip frame ``R_tip``, ``O_tip`` (mm)."""
        pos, wxyz = g.tip_camera_pose(R_tip, O_tip)
        self._tipcam.position = tuple(pos * M_PER_MM)
        self._tipcam.wxyz = tuple(wxyz)
        if not self._tipcam.visible:
            self._tipcam.visible = True
        self.tip_pose_mm = (pos, wxyz)
        self._tip_R = np.asarray(R_tip, dtype=float)
        self._tip_version += 1

    def show_trail(self, points_mm: np.ndarray) -> bool:
        """Draw the trail the tip has drawn (``/live/trail``): points (P, 3) mm, P >= 2,
        thinned to :data:`~hrm_ctrl.view.geometry.MAX_TRAIL_POINTS`; thread-safe.  A
        trail within :data:`SAME_POSE_MM` of the one drawn, or one given sooner than
        :data:`TRAIL_MIN_INTERVAL_S` after the last one drawn, sends nothing (False: the
        caller gives it again, as the live feed does every tick)."""
        p = np.asarray(points_mm, dtype=float)
        if p.ndim != 2 or p.shape[1] != 3 or len(p) < 2 or not np.isfinite(p).all():
            raise ViewError(f"trail: expected (P >= 2, 3) finite points in mm, got {p.shape}")
        p = g.trail_points(p)
        with self._lock:
            if self._closed:
                return False
            old = self.trail_mm
            if old is not None and old.shape == p.shape and np.abs(old - p).max() < SAME_POSE_MM:
                return False
            now = self._clock()
            if now - self._trail_t < TRAIL_MIN_INTERVAL_S:
                return False
            self._trail_t = now
            seg = g.polyline_segments(p) * M_PER_MM
            if self._trail is None:
                self._trail = self._add(
                    "add_line_segments",
                    "/live/trail",
                    seg,
                    g.TRAIL_RGB,
                    thickness=3.0,
                    thickness_units="screen",
                )
            else:
                self._trail.points = seg
            self.trail_mm = p
            self._tip_version += 1
            return True

    # ------------------------------------------------------------------ tip camera
    def _new_page(self, _client: Any) -> None:
        """A page connected: render the tip camera again (the frame shown may predate
        the scene it now has)."""
        with self._lock:
            self._tip_version += 1

    def _tip_camera_loop(self) -> None:
        """Render the tip camera's frames on the host and send them (module doc)."""
        period_s = 1.0 / TIP_CAMERA_RATE_HZ
        shown_version = -1
        due = time.monotonic()
        while not self._tip_stop.wait(max(due - time.monotonic(), 0.0)):
            due = max(due + period_s, time.monotonic())  # late: no burst to catch up
            with self._lock:
                pose, R, version = self.tip_pose_mm, self._tip_R, self._tip_version
                trail = self.trail_mm
            if pose is None or R is None or version == shown_version:
                continue
            if not self._tip_on.value or not self.server.get_clients():
                continue
            cpu0 = time.thread_time()
            try:
                img, _depth = render_tip_camera(
                    self._tip_scene, self._tip_camera, pose[0], R, trail
                )
            except Exception as exc:  # a bug: said (tip_error), the camera stops
                self.tip_error = f"{type(exc).__name__}: {exc}"
                return
            try:
                self._tip_image.image = img  # encoded (JPEG) and sent
            except Exception as exc:  # e.g. a page gone mid-send: said, tried again
                self.tip_error = f"{type(exc).__name__}: {exc}"
                continue
            cost = time.thread_time() - cpu0
            now = time.monotonic()
            shown_version = version
            self.tip_frames += 1
            self._tip_t = [self._tip_t[0] if self._tip_t else now, now]
            self._tip_cpu_s = [*self._tip_cpu_s[-(TIP_CAMERA_COSTS_KEPT - 1) :], cost]

    def tip_rate_hz(self) -> float:
        """Tip camera frames sent a second so far (0 before two were sent)."""
        if self.tip_frames < 2 or len(self._tip_t) < 2 or self._tip_t[1] <= self._tip_t[0]:
            return 0.0
        return (self.tip_frames - 1) / (self._tip_t[1] - self._tip_t[0])

    def tip_cpu_ms(self) -> float:
        """The tip camera thread's median CPU time per frame (render and JPEG), ms, of
        the last :data:`TIP_CAMERA_COSTS_KEPT` frames (NaN before the first)."""
        costs = list(self._tip_cpu_s)
        return 1e3 * float(np.median(costs)) if costs else math.nan

    @property
    def arm_links(self) -> tuple[Any, ...]:
        """The scene handles of the arm shown (``/arm/linkNN``): ``position`` (m),
        ``wxyz``, ``height`` (m), ``color``, ``visible``."""
        return tuple(self._arm)

    def scene_names(self) -> list[str]:
        """The names of the scene nodes this view added, in the order added."""
        return list(self._names)

    # ------------------------------------------------------------------ life
    def close(self) -> None:
        """Stop the server (idempotent)."""
        with self._lock:
            if self._closed:
                return
            self._closed = True
        self._tip_stop.set()  # a frame being rendered is sent before the server stops
        if self._tip_thread is not None and self._tip_thread is not threading.current_thread():
            self._tip_thread.join(TIP_THREAD_JOIN_S)
        with contextlib.redirect_stdout(io.StringIO()):  # viser's "Server stopped"
            self.server.stop()

    def __enter__(self) -> ArmView:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
