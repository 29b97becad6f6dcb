"""The steering of a recorded run drawn onto its movie: captions and pull arrows.

A caption names each steering action (`server.pipeline.marks`) for `hold_frames` frames after
the frame it took effect at; an arrow runs from each pulled atom to the point it was being
pulled to, while the pull lasts. Drawn with Pillow onto the rendered RGBA image, after the
render and before the encoder, so the picture under it is the same image as without overlay.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import numpy.typing as npt
from PIL import Image, ImageDraw

import protocol as p
from server.pipeline.marks import active_pulls
from server.render.camera import camera_frame, project

CELL = (200, 205, 215, 255)
CAPTION = (255, 255, 255, 255)
SHADOW = (0, 0, 0, 200)
ARROW = (239, 71, 111, 255)


def draw_overlay(
    rgba: npt.NDArray[np.uint8],
    frame: int,
    overlay: dict[str, Any],
    camera: p.Camera,
    positions: npt.NDArray[Any],
) -> npt.NDArray[np.uint8]:
    """`rgba` (H, W, 4) with the captions and arrows due at trajectory frame `frame`."""
    hold = int(overlay.get("hold_frames", 60))
    captions = [
        f"step {m['step']}: {m['text']}"
        for m in overlay.get("marks", [])
        if 0 <= frame - int(m["frame"]) < hold
    ]
    pulls = active_pulls(overlay.get("pulls", []), frame)
    if not captions and not pulls:
        return rgba
    h, w = rgba.shape[:2]
    image = Image.fromarray(np.ascontiguousarray(rgba), "RGBA")
    draw = ImageDraw.Draw(image)
    if pulls:
        view = camera_frame(camera, w, h)
        scale = max(1, round(min(w, h) / 240))
        for atom, target in pulls.items():
            if not 0 <= atom < positions.shape[0]:
                continue
            ends = project(view, np.array([positions[atom], target], dtype=np.float64))
            if not np.all(np.isfinite(ends)) or np.any(ends[:, 2] <= 0):
                continue
            (x0, y0), (x1, y1) = ends[0, :2], ends[1, :2]
            draw.line([(x0, y0), (x1, y1)], fill=ARROW, width=2 * scale)
            _head(draw, (x0, y0), (x1, y1), 6 * scale)
            draw.ellipse([x0 - 3 * scale, y0 - 3 * scale, x0 + 3 * scale, y0 + 3 * scale],
                         outline=ARROW, width=scale)  # fmt: skip
    y = 6
    for text in captions[-4:]:
        draw.text((9, y + 1), text, fill=SHADOW)
        draw.text((8, y), text, fill=CAPTION)
        y += 14
    return np.asarray(image)


def _head(
    draw: ImageDraw.ImageDraw, a: tuple[float, float], b: tuple[float, float], size: float
) -> None:
    d = np.array([b[0] - a[0], b[1] - a[1]])
    n = float(np.hypot(*d))
    if n < 1e-6:
        return
    d /= n
    side = np.array([-d[1], d[0]])
    tip = np.array(b)
    left = tip - size * d + 0.5 * size * side
    right = tip - size * d - 0.5 * size * side
    draw.polygon([tuple(tip), tuple(left), tuple(right)], fill=ARROW)


def cell_edges(cell: p.Cell) -> npt.NDArray[np.float64]:
    """The 12 edges (12, 2, 3) of a periodic box: its corners joined along its vectors."""
    origin = np.asarray(cell.origin, dtype=np.float64)
    vectors = np.asarray(cell.vectors, dtype=np.float64)
    corners = {
        (i, j, k): origin + i * vectors[0] + j * vectors[1] + k * vectors[2]
        for i in (0, 1)
        for j in (0, 1)
        for k in (0, 1)
    }
    edges = []
    for corner, point in corners.items():
        for axis in range(3):
            if corner[axis] == 0:
                other = tuple(1 if a == axis else c for a, c in enumerate(corner))
                edges.append((point, corners[other]))  # type: ignore[index]
    return np.asarray(edges)


def draw_cell(rgba: npt.NDArray[np.uint8], camera: p.Camera, cell: p.Cell) -> npt.NDArray[np.uint8]:
    """`rgba` (H, W, 4) with the periodic box drawn as an outline over it (an edge that
    reaches behind the camera is left out)."""
    h, w = rgba.shape[:2]
    view = camera_frame(camera, w, h)
    image = Image.fromarray(np.ascontiguousarray(rgba), "RGBA")
    draw = ImageDraw.Draw(image)
    width = max(1, round(min(w, h) / 400))
    for a, b in cell_edges(cell):
        ends = project(view, np.array([a, b]))
        if not np.all(np.isfinite(ends)) or np.any(ends[:, 2] <= 0):
            continue
        draw.line([tuple(ends[0, :2]), tuple(ends[1, :2])], fill=CELL, width=width)
    return np.asarray(image)
