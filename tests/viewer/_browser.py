"""Headless Chromium screenshots and an independent pinhole model of meshcat's camera.

The projection is the oracle of the browser tests: three.js' PerspectiveCamera (75 deg
vertical field of view, aspect = window width / height) at ``view_center + camera_offset``
looking at ``view_center`` with z up. It uses only numpy, not the viewer's code.
"""

from __future__ import annotations

import shutil
import subprocess
import tempfile
from pathlib import Path

import numpy as np
from scipy import ndimage

WIDTH, HEIGHT = 1280, 720
FOVY_DEG = 75.0
INSTALL_HINT = (
    "headless Chromium is needed by the viewer's browser tests: install Debian's package with "
    "`apt-get install -y --no-install-recommends chromium` (see the README's test command)"
)


def chromium() -> str:
    path = shutil.which("chromium") or shutil.which("chromium-browser")  # Debian / Ubuntu names
    if path is None:
        raise AssertionError(INSTALL_HINT)
    return path


def project(points, view_center, camera_offset, *, width: int = WIDTH, height: int = HEIGHT) -> np.ndarray:
    """Pixel (column, row) of world points [m] in meshcat's view; NaN behind the camera."""
    c = np.asarray(camera_offset, float)
    f = -c / np.linalg.norm(c)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    d = np.asarray(points, float).reshape(-1, 3) - np.asarray(view_center, float) - c
    x, y, z = d @ r, d @ u, d @ f
    t = np.tan(np.radians(FOVY_DEG / 2))
    with np.errstate(divide="ignore", invalid="ignore"):
        col = (x / (z * t * width / height) + 1) / 2 * width
        row = (1 - y / (z * t)) / 2 * height
    out = np.column_stack([col, row])
    out[z <= 0] = np.nan
    return out


def region(points, view_center, camera_offset, *, dilate_px: int) -> np.ndarray:
    """Boolean (H, W) mask of the pixels within ``dilate_px`` of the projected points."""
    px = project(points, view_center, camera_offset)
    px = px[np.all(np.isfinite(px), axis=1)].round().astype(int)
    inside = (px[:, 0] >= 0) & (px[:, 0] < WIDTH) & (px[:, 1] >= 0) & (px[:, 1] < HEIGHT)
    mask = np.zeros((HEIGHT, WIDTH), bool)
    mask[px[inside, 1], px[inside, 0]] = True
    return ndimage.binary_dilation(mask, iterations=dilate_px) if dilate_px > 0 else mask


def capsule_samples(p0, p1, radius: float, n: int = 24) -> np.ndarray:
    """Points on a capsule's surface (axis samples offset by the radius in many directions) [m]."""
    p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
    axis = p1 - p0
    length = np.linalg.norm(axis)
    a = axis / length if length > 1e-9 else np.array([0.0, 0.0, 1.0])
    helper = np.array([1.0, 0.0, 0.0]) if abs(a[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    e1 = np.cross(a, helper)
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    s = np.linspace(0, 1, max(2, int(length / 0.01)))[:, None]
    centres = p0 + s * axis
    ang = np.linspace(0, 2 * np.pi, n, endpoint=False)
    ring = radius * (np.cos(ang)[:, None] * e1 + np.sin(ang)[:, None] * e2)
    sphere = radius * np.array([a, -a, e1, -e1, e2, -e2])
    return np.concatenate([(centres[:, None, :] + ring[None]).reshape(-1, 3), centres, p0 + sphere, p1 + sphere])


# Colour classes of the screenshot (RGB uint8). The robot is 0x8FA9D8 shaded by the lights;
# the cloud colours are unlit; the stem is the scene's STEM_COLOR (0.85, 0.08, 0.08) shaded.
def robot_pixels(img: np.ndarray) -> np.ndarray:
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (b - r > 30) & (b - g > 12) & (r > 40) & (b > 90)


def stem_pixels(img: np.ndarray) -> np.ndarray:
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (r > 90) & (r > 3 * g) & (r > 3 * b)


def yellow_pixels(img: np.ndarray) -> np.ndarray:
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (r > 200) & (g > 190) & (b < 80)


def cyan_pixels(img: np.ndarray) -> np.ndarray:
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (r < 70) & (g > 180) & (b > 180)


def magenta_pixels(img: np.ndarray) -> np.ndarray:
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (r > 180) & (g < 110) & (b > 180)


def p_gd_pixels(img: np.ndarray) -> np.ndarray:
    """The p_gd marker's blue (0x2979FF, shaded)."""
    r, g, b = (img[..., k].astype(int) for k in range(3))
    return (b > 150) & (b - r > 120) & (b - g > 40)


def screenshot(url: str, out: Path, *, settle_s: float = 3.0, timeout_s: float = 120.0) -> np.ndarray:
    """Screenshot ``url`` (http:// or file://) into ``out`` (PNG); returns the RGB image (H, W, 3) uint8.

    STACK_NOTES' ``chromium --headless --virtual-time-budget=8000 --screenshot`` sometimes
    never exits on the live page (1 to 2 of 3 runs with a 10k-point cloud, 1 in ~10 with
    2k points), so Chromium runs with a DevTools port instead: it loads the page, waits in
    real time until the scene has arrived, ``settle_s`` more seconds to draw it, and
    captures the screen. Uses tornado's websocket client (a meshcat dependency).
    """
    import asyncio
    import base64
    import json
    import re
    import time
    import urllib.request

    from PIL import Image
    from tornado.websocket import websocket_connect

    out = Path(out)
    with tempfile.TemporaryDirectory(ignore_cleanup_errors=True) as profile:
        cmd = [
            chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
            "--disable-component-update", "--disable-sync", "--no-first-run", "--enable-unsafe-swiftshader",
            f"--user-data-dir={profile}", f"--window-size={WIDTH},{HEIGHT}", "--remote-debugging-port=0",
            "about:blank",
        ]  # fmt: skip
        proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
        try:
            deadline = time.monotonic() + 30
            port = None
            while port is None and time.monotonic() < deadline:
                line = proc.stderr.readline().decode(errors="replace")
                match = re.search(r"DevTools listening on ws://127\.0\.0\.1:(\d+)/", line)
                if match:
                    port = int(match.group(1))
                elif not line and proc.poll() is not None:
                    break
            assert port is not None, "chromium did not open its DevTools port"
            pages = json.loads(urllib.request.urlopen(f"http://127.0.0.1:{port}/json/list", timeout=10).read())
            ws_url = next(p["webSocketDebuggerUrl"] for p in pages if p.get("type") == "page")

            async def capture() -> bytes:
                ws = await websocket_connect(ws_url, max_message_size=64 * 2**20)
                counter = 0

                async def call(method: str, **params):
                    nonlocal counter
                    counter += 1
                    ws.write_message(json.dumps({"id": counter, "method": method, "params": params}))
                    while True:
                        reply = json.loads(await ws.read_message())
                        if reply.get("id") == counter:
                            assert "error" not in reply, reply
                            return reply.get("result", {})

                await call("Emulation.setDeviceMetricsOverride", width=WIDTH, height=HEIGHT, deviceScaleFactor=1,
                           mobile=False)  # fmt: skip
                await call("Page.enable")
                await call("Page.navigate", url=url)
                # Wait for the page, then (live page) until the scene has arrived: meshcat counts
                # the websocket messages it handled; when the count has stopped growing for 1 s,
                # let it render. A file:// page runs its commands itself once loaded.
                start, last, since = time.monotonic(), -1, time.monotonic()
                live = url.startswith("http")
                expression = "viewer.num_messages_received" if live else "document.readyState"
                while time.monotonic() - start < 60:
                    state = await call("Runtime.evaluate", expression=expression)
                    value = state.get("result", {}).get("value", -1)
                    if not live:
                        if value == "complete":
                            break
                    elif value != last:
                        last, since = value, time.monotonic()
                    elif value > 0 and time.monotonic() - since > 1.0:
                        break
                    await asyncio.sleep(0.1)
                await asyncio.sleep(settle_s)
                shot = await call("Page.captureScreenshot", format="png")
                ws.close()
                return base64.b64decode(shot["data"])

            png = asyncio.run(asyncio.wait_for(capture(), timeout_s))
        finally:
            proc.terminate()
            try:
                proc.wait(timeout=10)
            except subprocess.TimeoutExpired:
                proc.kill()
                proc.wait()
    out.write_bytes(png)
    return np.asarray(Image.open(out).convert("RGB"))
