"""One frame's micro-images: geometric image ⊗ defocused PSF, times cos⁴·V, pixel-integrated.

Units: mm for optics, px for sensor positions (pixel (x, y) covers
[x - 0.5, x + 0.5] × [y - 0.5, y + 0.5], OPTICS.md §2).

For lens m, sensor point s sees along the chief ray through the lens centre the
main-image point ``r = m - (s - m)·a/b``, i.e. the board point ``P = -r·u/v``
(board coordinates ``P - offset``): upright inside the micro-image, scale
``u·a/(v·b)`` board mm per sensor mm. Each micro-image is formed on a cell grid
of ``ss`` cells per pixel over the bounding box of the lens's own pixels plus a
margin of K px (the kernel half-width): the board's exact cell-mean
reflectance (:mod:`bench.wavesim.coverage`), one FFT convolution with the
frame's kernel (circular on a padded grid; only the box, whose every kernel
tap stays inside the margin, is kept, so nothing wraps), then
cos⁴·V (:mod:`bench.wavesim.vignetting`) on 2×2 sub-cells per pixel (all ss×ss
cells when ss is odd), then the mean over each pixel's cells.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.fft

from bench.mcsim.board import Board
from bench.mcsim.camera import Camera, IntArray
from bench.wavesim.coverage import reflectance
from bench.wavesim.kernel import Kernel
from bench.wavesim.psf import FloatArray
from bench.wavesim.vignetting import transmission


@dataclass(frozen=True)
class MicroGrid:
    """The per-frame grid every micro-image shares: box (px), margin K (px), kernel spectrum."""

    box_x: int
    box_y: int
    margin_px: int
    oversample: int
    fft_shape: tuple[int, int]
    kernel_spectrum: np.ndarray  # complex rfft2 of the kernel, centre at [0, 0]
    pupil_rows: int

    @property
    def sub(self) -> int:
        """Transmission samples per pixel and axis."""
        return 2 if self.oversample % 2 == 0 else self.oversample


def micro_grid(
    kernel: Kernel, box_x: int, box_y: int, oversample: int, pupil_rows: int
) -> MicroGrid:
    """Prepare the shared grid and the kernel's spectrum (once per frame)."""
    m = kernel.half_cells
    if m % oversample:
        raise ValueError("the kernel half-width must be a whole number of pixels")
    margin = m // oversample
    ny = (box_y + 2 * margin) * oversample
    nx = (box_x + 2 * margin) * oversample
    shape = (scipy.fft.next_fast_len(ny, real=True), scipy.fft.next_fast_len(nx, real=True))
    placed = np.zeros(shape)
    width = 2 * m + 1
    placed[:width, :width] = kernel.values
    placed = np.roll(placed, (-m, -m), axis=(0, 1))  # kernel centre to [0, 0]
    spectrum = scipy.fft.rfft2(placed)
    return MicroGrid(box_x, box_y, margin, oversample, shape, spectrum, pupil_rows)


def micro_image(
    camera: Camera,
    board: Board,
    u_mm: float,
    grid: MicroGrid,
    lens: tuple[int, int],
    xs: IntArray,
    ys: IntArray,
) -> FloatArray:
    """Signal (full light = 1) of the pixels (xs, ys) of lens ``lens`` = (i, j)."""
    ss, k = grid.oversample, grid.margin_px
    x0, y0 = int(xs.min()), int(ys.min())
    if xs.max() - x0 >= grid.box_x or ys.max() - y0 >= grid.box_y:
        raise ValueError("a lens's pixels exceed the frame's micro-image box")
    mpx, mpy = camera.lens_centre_px(np.array([lens[0]]), np.array([lens[1]]))
    mx, my = (float(v[0]) for v in camera.px_to_mm(mpx, mpy))
    v, a, b = camera.v_mm(u_mm), camera.a_mm(u_mm), camera.sensor_distance_mm
    scale = u_mm * a / (v * b)  # board mm per sensor mm, > 0: upright
    ox, oy = board.offset_mm
    cx, cy = camera.principal_point_px
    pix = camera.pixel_mm
    # source cell edges (px) -> sensor mm -> board coordinates
    ex = x0 - k - 0.5 + np.arange((grid.box_x + 2 * k) * ss + 1) / ss
    ey = y0 - k - 0.5 + np.arange((grid.box_y + 2 * k) * ss + 1) / ss
    bx = scale * ((ex - cx) * pix - mx) - (u_mm / v) * mx - ox
    by = scale * ((ey - cy) * pix - my) - (u_mm / v) * my - oy
    source = reflectance(board, bx, by)
    spectrum = scipy.fft.rfft2(source, s=grid.fft_shape)
    blurred = scipy.fft.irfft2(spectrum * grid.kernel_spectrum, s=grid.fft_shape)
    m = k * ss
    box = blurred[m : m + grid.box_y * ss, m : m + grid.box_x * ss]
    sub = grid.sub
    per = ss // sub
    cells = box.reshape(grid.box_y * sub, per, grid.box_x * sub, per).mean(axis=(1, 3))
    tx = x0 - 0.5 + (np.arange(grid.box_x * sub) + 0.5) / sub
    ty = y0 - 0.5 + (np.arange(grid.box_y * sub) + 0.5) / sub
    sx = ((tx - cx) * pix)[None, :]
    sy = ((ty - cy) * pix)[:, None]
    weight = transmission(camera, sx, sy, mx, my, grid.pupil_rows)
    pixels = (cells * weight).reshape(grid.box_y, sub, grid.box_x, sub).mean(axis=(1, 3))
    return pixels[ys - y0, xs - x0]
