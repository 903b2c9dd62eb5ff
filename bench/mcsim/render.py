"""Render the white image and the frames of a sweep (signal, then sensor counts).

Random numbers: every frame draws all of them (jitter, rays, diffraction,
sensor noise) from its own generator, seeded by ``(seed, 1, frame index)``;
the white image's by ``(seed, 0)``. A render is therefore the same whatever
the number of jobs and the order in which frames finish.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np
import numpy.typing as npt

from bench.mcsim.sensor import expose
from bench.mcsim.spec import SweepSpec
from bench.mcsim.trace import Tracer
from bench.mcsim.windows import corner_windows, lens_pixels

WHITE_BAND_ROWS = 32
WHITE = -1  # task index of the white image


@dataclass
class RenderStats:
    """What one image cost: rays traced, pixels traced, wall and CPU time (s)."""

    index: int
    u_mm: float | None
    rays: int
    pixels: int
    micro_images: int
    windows_inside_frame: bool = True
    window_micro_images: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0
    cpu_seconds: float = 0.0

    @property
    def rays_per_cpu_second(self) -> float:
        return self.rays / self.cpu_seconds if self.cpu_seconds > 0 else 0.0


def frame_rng(seed: int, index: int) -> np.random.Generator:
    stream = [seed, 0] if index == WHITE else [seed, 1, index]
    return np.random.default_rng(np.random.SeedSequence(stream))


def white_signal(spec: SweepSpec, rng: np.random.Generator) -> tuple[npt.NDArray[np.float32], int]:
    """Flat field: a uniform light board (reflectance 0.95) over every pixel of the frame."""
    cam = spec.camera
    tracer = Tracer(cam, None, spec.rail.u_mm(0), spec.trace, rays=spec.white_rays)
    signal = np.zeros((cam.height, cam.width), dtype=np.float32)
    xs = np.arange(cam.width, dtype=np.float64)
    for y0 in range(0, cam.height, WHITE_BAND_ROWS):
        y1 = min(y0 + WHITE_BAND_ROWS, cam.height)
        gy, gx = np.meshgrid(np.arange(y0, y1, dtype=np.float64), xs, indexing="ij")
        signal[y0:y1] = tracer.trace(gx, gy, rng).reshape(y1 - y0, cam.width)
    return signal, tracer.traced_rays


def frame_signal(
    spec: SweepSpec, index: int, rng: np.random.Generator
) -> tuple[npt.NDArray[np.float32], RenderStats]:
    """The noiseless signal of frame ``index``: the corner windows, dark elsewhere."""
    cam = spec.camera
    u = spec.rail.u_mm(index)
    windows = corner_windows(cam, spec.board, u, spec.corners, spec.margin)
    selected = np.zeros((cam.height, cam.width), dtype=bool)
    for w in windows:
        xs, ys = lens_pixels(cam, w.lens_i, w.lens_j)
        selected[ys, xs] = True  # overlapping windows share pixels
    flat = np.flatnonzero(selected)
    ys, xs = np.divmod(flat, cam.width)
    tracer = Tracer(cam, spec.board, u, spec.trace)
    signal = np.zeros((cam.height, cam.width), dtype=np.float32)
    signal.ravel()[flat] = tracer.trace(xs, ys, rng)
    lenses = {(int(i), int(j)) for w in windows for i, j in zip(w.lens_i, w.lens_j, strict=True)}
    stats = RenderStats(
        index=index,
        u_mm=u,
        rays=tracer.traced_rays,
        pixels=int(flat.size),
        micro_images=len(lenses),
        windows_inside_frame=all(w.inside_frame(cam) for w in windows),
        window_micro_images={w.corner: int(w.lens_i.size) for w in windows},
    )
    return signal, stats


def render_image(spec: SweepSpec, index: int) -> tuple[npt.NDArray[np.uint16], RenderStats]:
    """Counts of the white image (``index == WHITE``) or of frame ``index``."""
    wall, cpu = time.perf_counter(), time.process_time()
    rng = frame_rng(spec.seed, index)
    if index == WHITE:
        signal, rays = white_signal(spec, rng)
        cam = spec.camera
        stats = RenderStats(WHITE, None, rays, cam.width * cam.height, 0)
    else:
        signal, stats = frame_signal(spec, index, rng)
    exposure = spec.sensor.white_exposure if index == WHITE else spec.sensor.exposure
    counts = expose(signal, spec.sensor, rng, exposure=exposure)
    stats.seconds = time.perf_counter() - wall
    stats.cpu_seconds = time.process_time() - cpu
    return counts, stats
