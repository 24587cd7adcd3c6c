"""Benchmark of the tip camera rendered on the host (``hrm_ctrl/view/tip_camera.py``).

The camera is moved along each scenario's path (bent pipe, cabins), looking along its
tangent, a frame every ``--step`` mm; per frame the CPU time of this thread
(``time.thread_time``) for the ray cast alone and with the JPEG encoding the view sends
(viser's own encoder), and the wall time.  Reported: median, p90 and max per scenario,
with the frame rate one core would sustain at the median (1 / CPU per frame).

Run: ``python benchmarks/bench_tip_camera.py [--step 5] [--width W --height H] [--browser S]``;
prints JSON.  The rate the browser shows is measured by the browser test
(``tests/hrm_ctrl/cli/test_view.py``) and by ``--browser`` here: headless Chromium
loads the live view while the tip moves along the bent pipe (``--speed``, 50 mm/s), and the
frames the page shows a second are counted on the page, with its animation frames (it
draws its 3D scene and drains the server's messages in them); ``--lighting`` adds runs with
the tip camera off and the scene lit as the view lights it, and with viser's default
shadows (and environment map) put back.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from enum import StrEnum
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

from _machine import machine

from hrm_ctrl.planning.scenarios import scenario
from hrm_ctrl.view.server import TIP_CAMERA_FOV_RAD, TIP_CAMERA_HEIGHT, TIP_CAMERA_WIDTH
from hrm_ctrl.view.tip_camera import TipCamera, TipScene, render


def poses_along(points: np.ndarray, step_mm: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """Camera poses along a polyline every ``step_mm``: position, rotation (z along the
    tangent, x carried along by parallel transport)."""
    seg = np.diff(points, axis=0)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
    out = []
    x = np.array([0.0, 1.0, 0.0])
    for d in np.arange(step_mm, s[-1] - step_mm, step_mm):
        k = min(int(np.searchsorted(s, d, side="right")) - 1, len(seg) - 1)
        z = seg[k] / np.linalg.norm(seg[k])
        p = points[k] + (d - s[k]) * z
        x = x - (x @ z) * z
        x /= np.linalg.norm(x)
        out.append((p, np.stack([x, np.cross(z, x), z], axis=1)))
    return out


def ms(values: list[float]) -> dict[str, float]:
    a = np.array(values) * 1e3
    return {
        "median": round(float(np.median(a)), 2),
        "p90": round(float(np.percentile(a, 90)), 2),
        "max": round(float(a.max()), 2),
    }


def host(name: str, cam: TipCamera, step_mm: float) -> dict[str, Any]:
    from viser._scene_api import _encode_image_binary

    sc = scenario(name)
    scene = TipScene.of(sc.environment)
    poses = poses_along(sc.path.points, step_mm)
    trail = sc.path.points
    render(scene, cam, *poses[0], trail)  # warm
    cpu, cpu_jpeg, wall = [], [], []
    for p, R in poses:
        w0, c0 = time.perf_counter(), time.thread_time()
        img, _depth = render(scene, cam, p, R, trail)
        c1 = time.thread_time()
        _encode_image_binary(img, "jpeg", jpeg_quality=None)
        c2, w1 = time.thread_time(), time.perf_counter()
        cpu.append(c1 - c0)
        cpu_jpeg.append(c2 - c0)
        wall.append(w1 - w0)
    med = float(np.median(cpu_jpeg))
    return {
        "frames": len(poses),
        "cpu_ms": ms(cpu),
        "cpu_with_jpeg_ms": ms(cpu_jpeg),
        "wall_ms": ms(wall),
        "one_core_rate_hz": round(1.0 / med, 1) if med > 0 else math.inf,
    }


CHROMIUM = Path("/usr/bin/chromium")
CHROMIUM_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--no-first-run",
    "--disable-background-networking",
    "--disable-component-update",
    "--disable-sync",
    "--use-angle=swiftshader",  # WebGL without a GPU, as the browser test
    "--enable-unsafe-swiftshader",
]
# every tip camera frame the page decodes (its <img> of a blob: URL): the time, ms
COUNT_FRAMES = """
window.__tipFrames = [];
document.addEventListener('load', (e) => {
  const t = e.target;
  if (t && t.tagName === 'IMG' && t.src.startsWith('blob:')) {
    window.__tipFrames.push(performance.now());
  }
}, true);
"""


# the page's own animation frames (its 3D scene and the messages it drains are drawn in them)
COUNT_ANIMATION_FRAMES = """
window.__animationFrames = 0;
const __count = () => { window.__animationFrames++; requestAnimationFrame(__count); };
requestAnimationFrame(__count);
"""


class Lighting(StrEnum):
    """How the 3D scene is lit in a browser run: the view's own (no shadows, no
    environment map), or viser's defaults put back (shadows, and with them the
    environment map)."""

    VIEW = "view"
    SHADOWS = "shadows"
    SHADOWS_AND_MAP = "shadows+map"


def browser(
    seconds: float, speed_mm_s: float, camera: bool = True, lighting: Lighting = Lighting.VIEW
) -> dict[str, Any]:
    """The live view of the bent pipe in headless Chromium, the arm's pose stepped along
    the paper's plan at ``speed_mm_s`` (poses at 30 Hz, as the view's update rate bound):
    frames sent by the host, frames the page showed and the page's animation frames, a
    second; ``camera`` False: the tip camera unticked."""
    import threading

    from playwright.sync_api import sync_playwright

    from hrm_ctrl.model import default_robot
    from hrm_ctrl.planning.planner import FitMode, PlanOptions, plan_path
    from hrm_ctrl.view.server import ArmView

    model = default_robot()
    sc = scenario("bent-pipe")
    plan = plan_path(model, sc.path, PlanOptions(step=1.0, fit=FitMode.PAPER), sc)
    stop = threading.Event()
    with sync_playwright() as pw:
        b = pw.chromium.launch(executable_path=str(CHROMIUM), headless=True, args=CHROMIUM_ARGS)
        try:
            with ArmView(model, sc.environment, None, live=True) as view:
                scene = view.server.scene
                if lighting != Lighting.VIEW:
                    scene.configure_default_lights(enabled=True, cast_shadow=True)
                if lighting == Lighting.SHADOWS_AND_MAP:
                    scene.configure_environment_map("warehouse")
                view._tip_on.value = camera
                page = b.new_page(viewport={"width": 480, "height": 360})
                page.add_init_script(COUNT_FRAMES + COUNT_ANIMATION_FRAMES)
                page.goto(view.url, timeout=90_000)

                def feed() -> None:
                    k, dt = 0, 1.0 / 30.0
                    per_pose = max(1, round(speed_mm_s * dt))  # plan steps are 1 mm
                    while not stop.wait(dt):
                        view.update(plan.alpha[k], plan.theta[k])
                        k = (k + per_pose) % len(plan.alpha)

                th = threading.Thread(target=feed, daemon=True)
                th.start()
                end = time.monotonic() + 90.0
                while (
                    camera
                    and page.evaluate("window.__tipFrames.length") < 3
                    and time.monotonic() < end
                ):
                    time.sleep(0.1)
                time.sleep(1.0)
                n0, f0 = page.evaluate("window.__tipFrames.length"), view.tip_frames
                a0 = page.evaluate("window.__animationFrames")
                c0, w0 = time.process_time(), time.monotonic()
                time.sleep(seconds)
                frames = page.evaluate("window.__tipFrames")
                a1 = page.evaluate("window.__animationFrames")
                f1, w1, c1 = view.tip_frames, time.monotonic(), time.process_time()
                stop.set()
                th.join(5.0)
                shown = frames[n0:]
                page_rate = (
                    (len(shown) - 1) / ((shown[-1] - shown[0]) * 1e-3) if len(shown) > 1 else 0.0
                )
                return {
                    "camera": camera,
                    "lighting": lighting.value,
                    "seconds": round(w1 - w0, 2),
                    "host_frames_a_second": round((f1 - f0) / (w1 - w0), 1),
                    "page_frames_a_second": round(page_rate, 1),
                    "page_frames": len(shown),
                    "page_animation_frames_a_second": round((a1 - a0) / (w1 - w0), 1),
                    "tip_thread_cpu_ms_median": round(view.tip_cpu_ms(), 2),
                    "view_process_cpu_share": round((c1 - c0) / (w1 - w0), 2),
                    "load_1min": round(os.getloadavg()[0], 2),
                }
        finally:
            b.close()


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--step", type=float, default=5.0, help="mm between frames")
    ap.add_argument("--width", type=int, default=TIP_CAMERA_WIDTH)
    ap.add_argument("--height", type=int, default=TIP_CAMERA_HEIGHT)
    ap.add_argument(
        "--browser", type=float, default=0.0, metavar="S",
        help="also count the frames headless Chromium shows over S seconds (0: not)",
    )  # fmt: skip
    ap.add_argument("--speed", type=float, default=50.0, help="mm/s of the tip (--browser)")
    ap.add_argument(
        "--lighting", action="store_true",
        help="with --browser: also the page's animation frames with the tip camera off, lit "
        "as the view lights it and with viser's shadows (and environment map) put back",
    )  # fmt: skip
    args = ap.parse_args()
    cam = TipCamera(args.width, args.height, TIP_CAMERA_FOV_RAD)
    load0 = machine()["load_1min"]
    out: dict[str, Any] = {
        "benchmark": "tip camera",
        "pixels": [args.width, args.height],
        "host": {name: host(name, cam, args.step) for name in ("bent-pipe", "cabins")},
    }
    if args.browser > 0:
        out["browser"] = browser(args.browser, args.speed)
        if args.lighting:
            out["browser_camera_off"] = [
                browser(args.browser, args.speed, camera=False, lighting=lit) for lit in Lighting
            ]
    out["machine"] = machine()
    out["machine"]["load_1min_before"] = load0
    print(json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
