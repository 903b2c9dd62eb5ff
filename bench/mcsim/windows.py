"""Render windows around the board corners, snapped to whole micro-images.

OPTICS.md §3: the images of a board point at lateral position X_b (mm from the
axis) lie around ``-X_b·(L+b)/u`` on the sensor (where the chief ray through the
main-lens centre meets it), spread over about ±N/2 micro-image pitches with
``N = (a/b)(L+b)/(L-a)`` micro-images per axis. A window is the square of half
width ``(N/2 + margin)`` micro-image pitches around that point; every pixel of
every micro-image whose centre lies inside it is rendered, the rest of the
frame stays dark.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from bench.mcsim.board import Board
from bench.mcsim.camera import Camera, IntArray


@dataclass(frozen=True)
class Window:
    """One corner's window: which micro-images (lens indices) it renders."""

    corner: str
    centre_px: tuple[float, float]
    half_width_px: float
    lens_i: IntArray
    lens_j: IntArray

    def bounds_px(self, camera: Camera) -> tuple[float, float, float, float]:
        """(x_min, y_min, x_max, y_max) of the window's micro-images (centres ± pitch/√2)."""
        x, y = camera.micro_image_centre_px(self.lens_i, self.lens_j)
        r = camera.micro_image_pitch_px / math.sqrt(2.0)
        return (float(x.min() - r), float(y.min() - r), float(x.max() + r), float(y.max() + r))

    def inside_frame(self, camera: Camera) -> bool:
        """True when no micro-image of the window is cut by the frame's edge."""
        x0, y0, x1, y1 = self.bounds_px(camera)
        return x0 >= -0.5 and y0 >= -0.5 and x1 <= camera.width - 0.5 and y1 <= camera.height - 0.5


def corner_image_px(
    camera: Camera, lateral_mm: tuple[float, float], u_mm: float
) -> tuple[float, float]:
    """Where the chief ray from a board point (lateral mm) meets the sensor, pixels."""
    scale = -(camera.mla_distance_mm + camera.sensor_distance_mm) / u_mm / camera.pixel_mm
    cx, cy = camera.principal_point_px
    return cx + lateral_mm[0] * scale, cy + lateral_mm[1] * scale


def corner_windows(
    camera: Camera, board: Board, u_mm: float, corners: tuple[str, ...], margin: float
) -> list[Window]:
    """The windows of the named corners ("standard", "reference") at object distance u."""
    half = (camera.micro_images_per_axis(u_mm) / 2.0 + margin) * camera.micro_image_pitch_px
    windows = []
    for name, lateral in board.corner_positions_mm(corners).items():
        cx, cy = corner_image_px(camera, lateral, u_mm)
        box_x = np.array([cx - half, cx + half, cx - half, cx + half])
        box_y = np.array([cy - half, cy - half, cy + half, cy + half])
        li, lj = camera.lattice_coords(box_x, box_y)
        grid_i, grid_j = np.meshgrid(
            np.arange(math.floor(li.min()) - 1, math.ceil(li.max()) + 2),
            np.arange(math.floor(lj.min()) - 1, math.ceil(lj.max()) + 2),
            indexing="ij",
        )
        ii, jj = grid_i.ravel(), grid_j.ravel()
        mx, my = camera.micro_image_centre_px(ii, jj)
        keep = (np.abs(mx - cx) <= half) & (np.abs(my - cy) <= half)
        windows.append(Window(name, (cx, cy), half, ii[keep], jj[keep]))
    return windows


def lens_pixels(camera: Camera, lens_i: IntArray, lens_j: IntArray) -> tuple[IntArray, IntArray]:
    """All frame pixels (x, y) that belong to the given lenses (each pixel once)."""
    empty = np.zeros(0, dtype=np.int64)
    if lens_i.size == 0:
        return empty, empty
    mx, my = camera.micro_image_centre_px(lens_i, lens_j)
    reach = camera.micro_image_pitch_px  # a cell's corner is pitch/√2 from its centre
    x0 = max(0, math.floor(mx.min() - reach))
    x1 = min(camera.width - 1, math.ceil(mx.max() + reach))
    y0 = max(0, math.floor(my.min() - reach))
    y1 = min(camera.height - 1, math.ceil(my.max() + reach))
    if x1 < x0 or y1 < y0:
        return empty, empty
    ys, xs = np.mgrid[y0 : y1 + 1, x0 : x1 + 1]
    xs, ys = xs.ravel(), ys.ravel()
    pi, pj = camera.lens_of_pixels(xs, ys)
    # membership through a boolean table over the lenses' index range
    i0, j0 = int(lens_i.min()), int(lens_j.min())
    table = np.zeros((int(lens_i.max()) - i0 + 1, int(lens_j.max()) - j0 + 1), dtype=bool)
    table[lens_i - i0, lens_j - j0] = True
    ti, tj = pi - i0, pj - j0
    member = (ti >= 0) & (ti < table.shape[0]) & (tj >= 0) & (tj < table.shape[1])
    member[member] = table[ti[member], tj[member]]
    return xs[member].astype(np.int64), ys[member].astype(np.int64)
