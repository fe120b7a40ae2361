"""meshcat's scene objects and commands as plain data: colours, transforms, materials, meshes, point
clouds, the text panel's PNG, and :class:`Batch`, the packed commands of one viewer frame.

What :class:`harvest_qp.viewer.viewer.MeshcatViewer` sends, without the scene's logic.
"""

from __future__ import annotations

import io
import math
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
import umsgpack
from meshcat import geometry as mg
from numpy.typing import NDArray

from harvest_qp.viewer.geometry import read_stl


def hex_rgb(color: int) -> tuple[float, float, float]:
    return ((color >> 16) & 255) / 255.0, ((color >> 8) & 255) / 255.0, (color & 255) / 255.0


def rgba_int(rgba: Sequence[float]) -> int:
    r, g, b = (int(round(255 * min(max(c, 0.0), 1.0))) for c in rgba[:3])
    return (r << 16) | (g << 8) | b


def y_to(direction: NDArray[np.float64]) -> NDArray[np.float64]:
    """A rotation whose y axis is ``direction`` (unit); meshcat cylinders run along y."""
    y = direction / np.linalg.norm(direction)
    helper = np.array([1.0, 0.0, 0.0]) if abs(y[0]) < 0.9 else np.array([0.0, 0.0, 1.0])
    x = np.cross(y, helper)
    x /= np.linalg.norm(x)
    z = np.cross(x, y)
    return np.column_stack([x, y, z])


def segment_transform(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Transform of a unit cylinder node (y from 0 to 1) onto the segment a-b (scaled along y)."""
    d = b - a
    length = float(np.linalg.norm(d))
    T = np.eye(4)
    if length < 1e-9:
        T[:3, :3] = np.diag([1.0, 1e-6, 1.0])
    else:
        T[:3, :3] = y_to(d) * np.array([1.0, length, 1.0])
    T[:3, 3] = a
    return T


def translation(p: Sequence[float], scale: float = 1.0) -> NDArray[np.float64]:
    T = np.eye(4)
    T[:3, :3] *= scale
    T[:3, 3] = p
    return T


class PointsMaterial(mg.Material):
    """Unlit points of one colour (meshcat's PointsMaterial forces per-vertex colours)."""

    def __init__(self, color: int, size: float) -> None:
        super().__init__()
        self.color, self.size = color, size

    def lower(self, object_data):
        return {"uuid": self.uuid, "type": "PointsMaterial", "color": self.color, "size": self.size,
                "vertexColors": 0, "sizeAttenuation": True}  # fmt: skip


def points_object(points: NDArray[np.floating], color: int, size: float) -> dict:
    pts = np.ascontiguousarray(points, dtype=np.float32)
    if len(pts) == 0:
        pts = np.zeros((1, 3), np.float32) + np.float32(1e6)  # three.js dislikes empty buffers
    geometry = mg.PointsGeometry(pts.T)
    return mg.Points(geometry, PointsMaterial(color, size)).lower()


def mesh_object(geometry: mg.Geometry, color: int, *, opacity: float = 1.0, basic: bool = False,
                 texture: mg.Texture | None = None) -> dict:  # fmt: skip
    cls = mg.MeshBasicMaterial if basic else mg.MeshPhongMaterial
    material = cls(color=color, opacity=opacity, map=texture) if texture else cls(color=color, opacity=opacity)
    return mg.Mesh(geometry, material).lower()


def stl_object(path: Path, color: int) -> dict:
    triangles, _ = read_stl(path)
    vertices = triangles.reshape(-1, 3)
    faces = np.arange(len(vertices), dtype=np.uint32).reshape(-1, 3)
    # Indexed BufferGeometry: three.js computes the normals itself (meshcat does so when none
    # are given), and the file is read here so the viewer does not depend on the JS STL loader.
    return mesh_object(mg.TriangularMeshGeometry(vertices, faces), color)


_MATRIX_DTYPE = np.dtype([("tag", "u1"), ("value", ">f8")])
_TRANSFORM_PREFIX: dict[str, tuple[bytes, bytes]] = {}


def pack_transform(path: str, matrix: NDArray[np.float64]) -> tuple[bytes, bytes]:
    """msgpack of ``{"type": "set_transform", "path": path, "matrix": 16 floats}``, column-major.

    The same bytes as ``umsgpack.packb`` of that dict (float64 values), about 20 times faster:
    the dict's head is cached per path and the floats are packed by numpy.
    """
    cached = _TRANSFORM_PREFIX.get(path)
    if cached is None:
        head = umsgpack.packb({"type": "set_transform", "path": path, "matrix": []})
        # the empty array's header (0x90) ends the dict; a 16-element array starts with 0xdc 0x00 0x10
        cached = (path.encode(), head[:-1] + b"\xdc\x00\x10")
        _TRANSFORM_PREFIX[path] = cached
    values = np.empty(16, _MATRIX_DTYPE)
    values["tag"] = 0xCB
    values["value"] = np.asarray(matrix, dtype=float).T.reshape(-1)
    return cached[0], cached[1] + values.tobytes()


class Batch:
    """Commands of one viewer frame, packed for :meth:`Connection.send`."""

    __slots__ = ("messages",)

    def __init__(self) -> None:
        self.messages: list[tuple[bytes, bytes, bytes]] = []

    def transform(self, path: str, matrix: NDArray[np.float64]) -> None:
        encoded_path, data = pack_transform(path, matrix)
        self.messages.append((b"set_transform", encoded_path, data))

    def object(self, path: str, obj: dict) -> None:
        self.messages.append(
            (b"set_object", path.encode(), umsgpack.packb({"type": "set_object", "object": obj, "path": path}))
        )

    def property(self, path: str, key: str, value: Any) -> None:
        self.messages.append((b"set_property", path.encode(), umsgpack.packb(
            {"type": "set_property", "path": path, "property": key, "value": value})))  # fmt: skip

    def delete(self, path: str) -> None:
        self.messages.append((b"delete", path.encode(), umsgpack.packb({"type": "delete", "path": path})))

    def animation(self, animations: list[dict], *, play: bool, repetitions: int) -> None:
        self.messages.append((b"set_animation", b"", umsgpack.packb({
            "type": "set_animation", "animations": animations, "path": "",
            "options": {"play": play, "repetitions": repetitions}})))  # fmt: skip


def render_text_png(lines: Sequence[str], *, width: int = 320, line_height: int = 26, compress_level: int = 0) -> bytes:
    """The text panel as a greyscale PNG (light text on a dark, opaque background).

    Glyphs are rendered once and cached, and lines composed from them (rendering a line
    with FreeType took ~1 ms here); ``compress_level`` 0 encodes fastest (live view), 6
    gives ~0.5 KB panels (replay files).
    """
    from PIL import Image

    height = max(1, len(lines)) * line_height + 12
    canvas = np.full((height, width), _PANEL_BACKGROUND, np.uint8)
    for i, line in enumerate(lines):
        top, x = 6 + i * line_height, 10.0
        for ch in line:
            glyph, advance = _glyph(ch, line_height)
            left = int(round(x))
            right = min(width, left + glyph.shape[1])
            if right > left:
                region = canvas[top : top + line_height, left:right]
                np.maximum(region, glyph[:, : right - left], out=region)
            x += advance
    buffer = io.BytesIO()
    Image.fromarray(canvas, mode="L").save(buffer, format="PNG", compress_level=compress_level)
    return buffer.getvalue()


_PANEL_BACKGROUND = 26
_GLYPHS: dict[tuple[str, int], tuple[NDArray[np.uint8], float]] = {}


def _glyph(ch: str, line_height: int) -> tuple[NDArray[np.uint8], float]:
    key = (ch, line_height)
    cached = _GLYPHS.get(key)
    if cached is None:
        from PIL import Image, ImageDraw

        font = _font(int(line_height * 0.8))
        advance = float(font.getlength(ch))
        image = Image.new("L", (max(1, int(math.ceil(advance)) + 2), line_height), _PANEL_BACKGROUND)
        ImageDraw.Draw(image).text((0, 2), ch, fill=240, font=font)
        cached = (np.asarray(image), advance)
        _GLYPHS[key] = cached
    return cached


_FONTS: dict[int, Any] = {}


def _font(size: int):
    from PIL import ImageFont

    if size not in _FONTS:
        try:
            _FONTS[size] = ImageFont.load_default(size=size)
        except TypeError:  # Pillow < 10.1: bitmap font only
            _FONTS[size] = ImageFont.load_default()
    return _FONTS[size]
