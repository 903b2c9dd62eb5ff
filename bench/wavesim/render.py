"""Render the white image and the frames of a wavesim sweep (signal, then sensor counts).

Random numbers only enter through the sensor noise, drawn from mcsim's
per-image generators (:func:`bench.mcsim.render.frame_rng`: (seed, 1, frame)
and (seed, 0) for the white image), so renders are reproducible and
independent of the number of jobs.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from bench.mcsim.camera import Camera
from bench.mcsim.render import WHITE, frame_rng
from bench.mcsim.sensor import expose
from bench.mcsim.windows import corner_windows, lens_pixels
from bench.wavesim.kernel import Kernel, frame_kernel, half_width_mm
from bench.wavesim.micro import micro_grid, micro_image
from bench.wavesim.psf import Pupil
from bench.wavesim.settings import WaveSpec
from bench.wavesim.vignetting import transmission

WHITE_BAND_ROWS = 32
WHITE_REFLECTANCE = 0.95


@dataclass
class WaveStats:
    """What one image cost and the PSF it used (mm, µm where named)."""

    index: int
    u_mm: float | None
    pixels: int
    micro_images: int
    windows_inside_frame: bool = True
    window_micro_images: dict[str, int] = field(default_factory=dict)
    kernel_half_px: int = 0
    truncated_energy: float = 0.0
    defocus_wavefront_um: float = 0.0
    geometric_blur_px: float = 0.0
    fft_sizes: list[int] = field(default_factory=list)
    seconds: float = 0.0
    cpu_seconds: float = 0.0


def pupil_of(ws: WaveSpec) -> Pupil:
    cam = ws.sweep.camera
    return Pupil(cam.microlens_aperture, cam.mla_pitch_mm, cam.theta_deg)


def kernel_for(ws: WaveSpec, u_mm: float) -> tuple[Kernel, int]:
    """The frame's PSF kernel at object distance u and its half-width K in pixels."""
    cam, wave = ws.sweep.camera, ws.wave
    c = 1.0 / cam.a_mm(u_mm) - 1.0 / cam.a_focus_mm  # 1/b - 1/b', mm^-1
    pupil = pupil_of(ws)
    b = cam.sensor_distance_mm
    h = half_width_mm(pupil, wave.wavelengths_mm, b, c, cam.pixel_mm, wave.rings)
    k_px = math.ceil(h / cam.pixel_mm)
    cell = cam.pixel_mm / wave.oversample
    kernel = frame_kernel(pupil, wave.wavelengths_mm, b, c, cell, k_px * wave.oversample)
    return kernel, k_px


def frame_signal(ws: WaveSpec, index: int) -> tuple[npt.NDArray[np.float32], WaveStats]:
    """The noiseless signal of frame ``index``: the corner windows, dark elsewhere."""
    spec = ws.sweep
    cam = spec.camera
    u = spec.rail.u_mm(index)
    windows = corner_windows(cam, spec.board, u, spec.corners, spec.margin)
    pairs = {(int(i), int(j)) for w in windows for i, j in zip(w.lens_i, w.lens_j, strict=True)}
    lens_i = np.array([p[0] for p in sorted(pairs)], dtype=np.int64)
    lens_j = np.array([p[1] for p in sorted(pairs)], dtype=np.int64)
    signal, kernel, k_px = lenses_signal(ws, u, lens_i, lens_j)
    c = 1.0 / cam.a_mm(u) - 1.0 / cam.a_focus_mm
    stats = WaveStats(
        index=index,
        u_mm=u,
        pixels=int(lens_pixels(cam, lens_i, lens_j)[0].size),
        micro_images=len(pairs),
        windows_inside_frame=all(w.inside_frame(cam) for w in windows),
        window_micro_images={w.corner: int(w.lens_i.size) for w in windows},
        kernel_half_px=k_px,
        truncated_energy=kernel.truncated_energy,
        defocus_wavefront_um=(cam.mla_pitch_mm / 2) ** 2 * abs(c) / 2 * 1e3,
        geometric_blur_px=cam.defocus_blur_px(u),
        fft_sizes=list(kernel.fft_sizes),
    )
    return signal, stats


def lenses_signal(
    ws: WaveSpec, u_mm: float, lens_i: np.ndarray, lens_j: np.ndarray
) -> tuple[npt.NDArray[np.float32], Kernel, int]:
    """Signal of every pixel of the given lenses at object distance u (others 0).

    Also returns the frame's kernel and its half-width K (px).
    """
    spec = ws.sweep
    cam = spec.camera
    xs, ys = lens_pixels(cam, lens_i, lens_j)
    signal = np.zeros((cam.height, cam.width), dtype=np.float32)
    kernel, k_px = kernel_for(ws, u_mm)
    groups = _group_by_lens(cam, xs, ys)
    box_x = max((int(gx.max() - gx.min()) + 1 for _, gx, _ in groups), default=1)
    box_y = max((int(gy.max() - gy.min()) + 1 for _, _, gy in groups), default=1)
    grid = micro_grid(kernel, box_x, box_y, ws.wave.oversample, ws.wave.pupil_rows)
    for lens, gx, gy in groups:
        signal[gy, gx] = micro_image(cam, spec.board, u_mm, grid, lens, gx, gy)
    return signal, kernel, k_px


def _group_by_lens(
    cam: Camera, xs: np.ndarray, ys: np.ndarray
) -> list[tuple[tuple[int, int], np.ndarray, np.ndarray]]:
    """The pixels (xs, ys) split by owning lens (nearest micro-image centre)."""
    if xs.size == 0:
        return []
    pi, pj = cam.lens_of_pixels(xs, ys)
    span = int(pj.max() - pj.min()) + 1
    key = (pi - pi.min()) * span + (pj - pj.min())
    order = np.argsort(key, kind="stable")
    key, xs, ys, pi, pj = key[order], xs[order], ys[order], pi[order], pj[order]
    starts = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
    ends = np.r_[starts[1:], key.size]
    return [((int(pi[s]), int(pj[s])), xs[s:e], ys[s:e]) for s, e in zip(starts, ends, strict=True)]


def white_signal(ws: WaveSpec) -> npt.NDArray[np.float32]:
    """Flat field: reflectance 0.95 · cos⁴ · V, pixel-area integrated, over the whole frame."""
    cam = ws.sweep.camera
    ss = ws.wave.oversample
    sub = 2 if ss % 2 == 0 else ss
    offsets = (np.arange(sub) + 0.5) / sub - 0.5
    signal = np.zeros((cam.height, cam.width), dtype=np.float32)
    xs = np.arange(cam.width, dtype=np.float64)
    for y0 in range(0, cam.height, WHITE_BAND_ROWS):
        y1 = min(y0 + WHITE_BAND_ROWS, cam.height)
        gy, gx = np.meshgrid(np.arange(y0, y1, dtype=np.float64), xs, indexing="ij")
        li, lj = cam.lens_of_pixels(gx, gy)
        mx, my = cam.px_to_mm(*cam.lens_centre_px(li, lj))
        total = np.zeros(gx.shape)
        for oy in offsets:
            for ox in offsets:
                sx, sy = cam.px_to_mm(gx + ox, gy + oy)
                total += transmission(cam, sx, sy, mx, my, ws.wave.pupil_rows)
        signal[y0:y1] = WHITE_REFLECTANCE * total / (sub * sub)
    return signal


def render_image(ws: WaveSpec, index: int) -> tuple[npt.NDArray[np.uint16], WaveStats]:
    """Counts of the white image (``index == WHITE``) or of frame ``index``."""
    wall, cpu = time.perf_counter(), time.process_time()
    spec = ws.sweep
    rng = frame_rng(spec.seed, index)
    if index == WHITE:
        signal = white_signal(ws)
        cam = spec.camera
        stats = WaveStats(WHITE, None, cam.width * cam.height, 0)
        exposure = spec.sensor.white_exposure
    else:
        signal, stats = frame_signal(ws, index)
        exposure = spec.sensor.exposure
    counts = expose(signal, spec.sensor, rng, exposure=exposure)
    stats.seconds = time.perf_counter() - wall
    stats.cpu_seconds = time.process_time() - cpu
    return counts, stats
