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
    path = shutil.which("chromium") or shutil.which("chromium-browser")
    if path is None:
        raise AssertionError(INSTALL_HINT)
    return path


def screenshot(url: str, out: Path, *, budget_ms: int = 8000, attempts: int = 3) -> np.ndarray:
    """Screenshot ``url`` (http:// or file://) into ``out`` (PNG); returns the RGB image (H, W, 3) uint8.

    Headless Chromium 156 with a virtual time budget occasionally never exits (seen once in
    about ten runs on a loaded 2-core machine, on the live page and not on our side: the
    server kept answering); a hung attempt is killed after 60 s and retried.
    """
    from PIL import Image

    out = Path(out)
    errors = []
    for _ in range(attempts):
        out.unlink(missing_ok=True)
        with tempfile.TemporaryDirectory() as profile:
            cmd = [
                chromium(), "--headless", "--no-sandbox", "--disable-gpu", "--disable-background-networking",
                "--disable-component-update", "--disable-sync", "--no-first-run", "--enable-unsafe-swiftshader",
                f"--virtual-time-budget={budget_ms}", f"--user-data-dir={profile}",
                f"--window-size={WIDTH},{HEIGHT}", f"--screenshot={out}", url,
            ]  # fmt: skip
            try:
                result = subprocess.run(cmd, capture_output=True, timeout=60)
            except subprocess.TimeoutExpired:
                errors.append("timed out after 60 s")
                continue
        if out.is_file():
            return np.asarray(Image.open(out).convert("RGB"))
        errors.append(f"exit {result.returncode}: {result.stderr[-1000:]!r}")
    raise AssertionError(f"chromium wrote no screenshot of {url} in {attempts} attempts: {errors}")


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
