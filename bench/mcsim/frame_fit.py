"""Size a frame (and place the principal point) to just hold a sweep's windows."""

from __future__ import annotations

import dataclasses
import math

from bench.mcsim.board import Board
from bench.mcsim.camera import Camera
from bench.mcsim.windows import corner_windows

PAD_PX = 8  # dark border around the outermost rendered micro-image
ROUND_PX = 16  # frame sizes are multiples of this


def fit_frame(
    camera: Camera,
    board: Board,
    u_values_mm: list[float],
    corners: tuple[str, ...],
    margin: float,
) -> tuple[int, int, tuple[float, float]]:
    """(width, height, principal point) holding every corner window of every frame.

    The windows move with u (their centres scale with (L+b)/u), so the extremes
    are taken over all frames. The principal point lands on a pixel centre plus
    the half-pixel of a centred grid, (k + 0.5, m + 0.5), like a sensor centre.
    """
    origin = dataclasses.replace(
        camera,
        principal_point_px=(0.0, 0.0),
        lens_origin_px=(
            camera.lens_origin_px[0] - camera.principal_point_px[0],
            camera.lens_origin_px[1] - camera.principal_point_px[1],
        ),
    )
    x_lo = y_lo = math.inf
    x_hi = y_hi = -math.inf
    for u in u_values_mm:
        for window in corner_windows(origin, board, u, corners, margin):
            x0, y0, x1, y1 = window.bounds_px(origin)
            x_lo, y_lo = min(x_lo, x0), min(y_lo, y0)
            x_hi, y_hi = max(x_hi, x1), max(y_hi, y1)
    width = ROUND_PX * math.ceil((x_hi - x_lo + 2 * PAD_PX) / ROUND_PX)
    height = ROUND_PX * math.ceil((y_hi - y_lo + 2 * PAD_PX) / ROUND_PX)
    # centre the used region in the frame
    cx = math.floor(-x_lo + (width - (x_hi - x_lo)) / 2.0) + 0.5
    cy = math.floor(-y_lo + (height - (y_hi - y_lo)) / 2.0) + 0.5
    return width, height, (cx, cy)
