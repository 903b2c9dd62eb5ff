"""Physically based renderer of raw focused-plenoptic frames (``shared/OPTICS.md`` §1–3).

Each sensor pixel is back-projected: it belongs to the lens whose micro-image
centre is nearest; rays from the pixel through a grid of points on that
microlens' (square, pitch-sized) aperture are refracted by the microlens
(thin lens, focal ``f``), tested against the main-lens aperture (vignetting,
soft micro-image rims), refracted by the main lens (thin lens, ``F``) and
intersected with the board plane at object distance ``u``. For each ray the
board reflectance is integrated analytically over the pixel's footprint on the
board (exact area sampling of the pixel) after blurring the board with the
PSF (a Gaussian standing in for diffraction, ``psf_sigma_px`` on the sensor,
mapped onto the board through the micro-image magnification: exact for the
board content of a micro-image, where the sensor-to-board map is affine; the
rims keep their geometric softness), each ray is weighted by ``cos⁴`` of its
incidence angle on the sensor, and the irradiance is turned into counts with
Poisson shot noise, Gaussian read noise, a black level and bit-depth
quantization.

Speed: for a given frame the board point of every ray is affine in the
aperture sample ``q`` with one scalar slope (``λ``, zero at the focus plane),
and the main-lens hit point is affine with slope ``κ``. So only pixels near a
micro-image rim or near a board edge need the per-ray loop; every other pixel
takes its exact value in closed form. Rows are processed in chunks on a thread
pool (numpy releases the GIL), which bounds the peak memory.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .board import Board
from .lens_grid import LensGrid
from .optics import CameraOptics, image_centre_scale, image_distance


@dataclass(frozen=True)
class SensorModel:
    """Sensor geometry and noise (pixels; electrons; digital numbers DN).

    ``principal_point_px`` is where the optical axis meets the sensor, in pixel
    coordinates (pixel centres at integers); ``None`` means the sensor centre
    ``((W-1)/2, (H-1)/2)``. ``white_level_e`` is the signal in electrons of a
    reflectance-1 pixel on the axis; counts are ``e / full_well_e ·
    (2^bit_depth - 1)`` plus ``black_level_dn``.
    """

    width: int = 5120
    height: int = 5120
    principal_point_px: tuple[float, float] | None = None
    bit_depth: int = 12
    full_well_e: float = 10000.0
    white_level_e: float = 8000.0
    read_noise_e: float = 3.0
    black_level_dn: float = 8.0
    stray_light: float = 0.004

    def __post_init__(self) -> None:
        if self.width < 1 or self.height < 1:
            raise ValueError(f"sensor size {self.width}x{self.height} px must be positive")
        if not 1 <= self.bit_depth <= 16:
            raise ValueError(f"bit depth {self.bit_depth} must be 1..16")
        if self.full_well_e <= 0 or self.white_level_e <= 0 or self.read_noise_e < 0:
            raise ValueError(
                "sensor noise model needs full well > 0, white level > 0, read noise >= 0"
            )

    @property
    def pp(self) -> tuple[float, float]:
        """The principal point ``(cx, cy)`` in pixels."""
        if self.principal_point_px is None:
            return ((self.width - 1) / 2.0, (self.height - 1) / 2.0)
        return (float(self.principal_point_px[0]), float(self.principal_point_px[1]))

    @property
    def max_count(self) -> int:
        return (1 << self.bit_depth) - 1


@dataclass(frozen=True)
class SimCamera:
    """Everything the renderer needs: optics, sensor, MLA placement, board and rendering quality.

    ``mla_offset_px`` is the lens lattice origin (the projected centre of lens
    (0, 0)) relative to the principal point; ``mla_rotation_deg`` its rotation.
    ``psf_sigma_px`` is the Gaussian standard deviation of the diffraction
    stand-in. ``aperture_samples`` is the number of ray samples per axis on
    each microlens aperture.
    """

    optics: CameraOptics
    sensor: SensorModel = field(default_factory=SensorModel)
    board: Board = field(default_factory=Board)
    mla_rotation_deg: float = 0.0
    mla_offset_px: tuple[float, float] = (0.0, 0.0)
    psf_sigma_px: float = 0.4
    aperture_samples: int = 4

    def __post_init__(self) -> None:
        lens_px = self.optics.lens_pitch_px
        if self.sensor.width < lens_px or self.sensor.height < lens_px:
            raise ValueError(
                f"the sensor ({self.sensor.width}x{self.sensor.height} px) is "
                f"smaller than one lens ({lens_px:.1f} px)"
            )
        if self.aperture_samples < 1:
            raise ValueError("aperture_samples must be >= 1")
        if self.psf_sigma_px < 0:
            raise ValueError("psf_sigma_px must be >= 0")

    @property
    def lens_grid(self) -> LensGrid:
        """The true lens-centre lattice (projected along z onto the sensor), pixels."""
        cx, cy = self.sensor.pp
        return LensGrid(
            (cx + self.mla_offset_px[0], cy + self.mla_offset_px[1]),
            self.optics.lens_pitch_px,
            math.radians(self.mla_rotation_deg),
        )

    @property
    def image_grid(self) -> LensGrid:
        """The micro-image-centre lattice: lens lattice scaled by ``(L+b)/L`` about the pp."""
        return self.lens_grid.scaled_about(
            self.sensor.pp, image_centre_scale(self.optics.L, self.optics.b)
        )

    def with_sensor(self, **changes: object) -> SimCamera:
        return replace(self, sensor=replace(self.sensor, **changes))  # type: ignore[arg-type]


@dataclass(frozen=True)
class Roi:
    """A sensor window: ``x, y`` of its first pixel, ``width, height`` in pixels."""

    x: int
    y: int
    width: int
    height: int


class _FrameGeometry:
    """Per-frame constants of the ray model (see the module docstring)."""

    def __init__(self, cam: SimCamera, u_mm: float) -> None:
        o = cam.optics
        self.cam = cam
        self.u = float(u_mm)
        self.a_s = o.a_f  # distance of the plane conjugate to the sensor, in front of the MLA
        self.kappa = 1.0 - o.L / self.a_s
        self.lam = self.kappa * (1.0 - self.u / o.F) - self.u * (1.0 - self.kappa) / o.L
        board_mm_per_px = o.delta * abs((o.L + self.u - self.u * o.L / o.F) / o.b)
        self.footprint_half_mm = 0.5 * board_mm_per_px
        self.psf_board_mm = cam.psf_sigma_px * board_mm_per_px
        n = cam.aperture_samples
        t = (np.arange(n) + 0.5) / n - 0.5
        qa, qb = np.meshgrid(t * o.D, t * o.D, indexing="xy")
        th = math.radians(cam.mla_rotation_deg)
        self.qx = (math.cos(th) * qa - math.sin(th) * qb).ravel()
        self.qy = (math.sin(th) * qa + math.cos(th) * qb).ravel()
        self.q_radius = float(np.max(np.hypot(self.qx, self.qy)))
        self.q_sq_mean = float(np.mean(self.qx**2 + self.qy**2))


def _irradiance_rows(
    geo: _FrameGeometry,
    roi: Roi,
    row0: int,
    row1: int,
    white: bool,
    board_offset_mm: tuple[float, float],
) -> NDArray[np.float32]:
    """Normalized irradiance (1 = reflectance-1 pixel on the axis) for sensor rows [row0, row1)."""
    cam, o = geo.cam, geo.cam.optics
    cx, cy = cam.sensor.pp
    xs = np.arange(roi.x, roi.x + roi.width, dtype=np.float64)
    ys = np.arange(row0, row1, dtype=np.float64)
    px, py = np.meshgrid(xs, ys)
    ii, jj = cam.image_grid.nearest(px, py)
    mxp, myp = cam.lens_grid.centre(ii, jj)
    del ii, jj
    delta = o.delta
    sx, sy = (px - cx) * delta, (py - cy) * delta
    mx, my = (mxp - cx) * delta, (myp - cy) * delta
    del px, py, mxp, myp
    dx, dy = sx - mx, sy - my  # pixel relative to its lens centre (mm)
    del sx, sy
    r_ab = o.L / geo.a_s
    # main-lens hit point of the ray through the lens centre: base = m*kappa + P*L/a_s,
    # P = m - d*a_s/b the point conjugate to the pixel.
    bx = mx * geo.kappa + (mx - dx * geo.a_s / o.b) * r_ab
    by = my * geo.kappa + (my - dy * geo.a_s / o.b) * r_ab
    half_ap = 0.5 * o.aperture
    rad = np.hypot(bx, by)
    k_abs = abs(geo.kappa) * geo.q_radius
    outside = rad - k_abs > half_ap
    rim = ~outside & (rad + k_abs > half_ap)
    b2 = o.b * o.b
    if white:
        value = np.where(outside, 0.0, 1.0 / (1.0 + (dx * dx + dy * dy + geo.q_sq_mean) / b2) ** 2)
        need = rim
        X0 = Y0 = None
    else:
        # board point of the ray through the lens centre
        gain = 1.0 - geo.u / o.F
        X0 = bx * gain - geo.u * (mx - bx) / o.L - board_offset_mm[0]
        Y0 = by * gain - geo.u * (my - by) / o.L - board_offset_mm[1]
        h = geo.footprint_half_mm
        reach = abs(geo.lam) * geo.q_radius + h + 5.0 * geo.psf_board_mm + 1e-6
        near_edge = cam.board.distance_to_edge_mm(X0, Y0) < reach
        need = ~outside & (rim | near_edge)
        simple = ~outside & ~need
        value = np.zeros(X0.shape, dtype=np.float64)
        value[simple] = (
            cam.board.box_reflectance(X0[simple], Y0[simple], h)
            / (1.0 + (dx[simple] ** 2 + dy[simple] ** 2 + geo.q_sq_mean) / b2) ** 2
        )
    if np.any(need):
        # per-ray loop, only where a rim or a board edge makes the rays differ
        nbx, nby = bx[need], by[need]
        ndx, ndy = dx[need], dy[need]
        ha2 = half_ap * half_ap

        def ray_weights(sel: NDArray[np.bool_] | slice) -> Iterator[tuple[Any, Any, Any]]:
            """(qx, qy, weight of the ray through aperture point q) for pixels ``sel``."""
            sbx, sby, sdx, sdy = nbx[sel], nby[sel], ndx[sel], ndy[sel]
            for qx, qy in zip(geo.qx, geo.qy, strict=True):
                hx = sbx + geo.kappa * qx
                hy = sby + geo.kappa * qy
                ex, ey = sdx - qx, sdy - qy
                yield qx, qy, (hx * hx + hy * hy <= ha2) / (1.0 + (ex * ex + ey * ey) / b2) ** 2

        if white:
            acc = np.zeros(nbx.shape, dtype=np.float64)
            for _, _, w in ray_weights(slice(None)):
                acc += w
        else:
            assert X0 is not None and Y0 is not None
            # rim pixels away from board edges see one reflectance through every ray:
            # only their aperture weights are summed
            edge_rays = near_edge[need]
            flat = ~edge_rays
            acc = np.zeros(nbx.shape, dtype=np.float64)
            flat_w = np.zeros(int(flat.sum()), dtype=np.float64)
            for _, _, w in ray_weights(flat):
                flat_w += w
            acc[flat] = flat_w * cam.board.box_reflectance(
                X0[need][flat], Y0[need][flat], geo.footprint_half_mm
            )
            nX, nY = X0[need][edge_rays], Y0[need][edge_rays]
            edge_acc = np.zeros(nX.shape, dtype=np.float64)
            for qx, qy, w in ray_weights(edge_rays):
                edge_acc += w * cam.board.box_reflectance(
                    nX + geo.lam * qx, nY + geo.lam * qy, geo.footprint_half_mm, geo.psf_board_mm
                )
            acc[edge_rays] = edge_acc
        value[need] = acc / geo.qx.size
    return value.astype(np.float32)


def render_irradiance(
    cam: SimCamera,
    *,
    object_distance_mm: float,
    white: bool = False,
    board_offset_mm: tuple[float, float] = (0.0, 0.0),
    roi: Roi | None = None,
    threads: int | None = None,
    chunk_rows: int = 128,
) -> NDArray[np.float32]:
    """Noise-free, PSF-free irradiance of a frame (1.0 = reflectance 1 on the axis).

    ``white=True`` renders the flat-field image (a uniform reflectance-1 target).
    ``board_offset_mm`` is where the board origin (the standard corner) sits in
    the object plane, relative to the optical axis (mm, board X/Y axes).
    """
    if object_distance_mm <= cam.optics.F:
        raise ValueError(
            f"object distance {object_distance_mm} mm must exceed F = {cam.optics.F} mm"
        )
    roi = roi or Roi(0, 0, cam.sensor.width, cam.sensor.height)
    geo = _FrameGeometry(cam, object_distance_mm)
    out = np.empty((roi.height, roi.width), dtype=np.float32)
    bounds = [
        (r, min(r + chunk_rows, roi.y + roi.height))
        for r in range(roi.y, roi.y + roi.height, chunk_rows)
    ]

    def work(b: tuple[int, int]) -> None:
        out[b[0] - roi.y : b[1] - roi.y] = _irradiance_rows(
            geo, roi, b[0], b[1], white, board_offset_mm
        )

    n_threads = threads or min(4, os.cpu_count() or 1)
    if n_threads <= 1 or len(bounds) == 1:
        for b in bounds:
            work(b)
    else:
        with ThreadPoolExecutor(n_threads) as pool:
            list(pool.map(work, bounds))
    return out


def expose(
    irradiance: NDArray[np.float32], cam: SimCamera, rng: np.random.Generator
) -> NDArray[np.uint16]:
    """Irradiance -> counts: stray light, Poisson shot noise, read noise, black level, quantization."""
    sensor = cam.sensor
    electrons = (irradiance + np.float32(sensor.stray_light)) * np.float32(sensor.white_level_e)
    np.clip(electrons, 0.0, None, out=electrons)
    signal = rng.poisson(electrons).astype(np.float32)
    if sensor.read_noise_e > 0:
        signal += rng.standard_normal(signal.shape, dtype=np.float32) * np.float32(
            sensor.read_noise_e
        )
    counts = signal * np.float32(sensor.max_count / sensor.full_well_e) + np.float32(
        sensor.black_level_dn
    )
    np.rint(counts, out=counts)
    np.clip(counts, 0, sensor.max_count, out=counts)
    return counts.astype(np.uint16)


def render_frame(
    cam: SimCamera,
    *,
    object_distance_mm: float,
    white: bool = False,
    board_offset_mm: tuple[float, float] = (0.0, 0.0),
    roi: Roi | None = None,
    seed: int | Sequence[int] | None = 0,
    noise: bool = True,
    threads: int | None = None,
) -> NDArray[np.uint16]:
    """One raw frame in sensor counts (uint16, right-aligned ``bit_depth`` bits).

    ``seed`` makes the noise reproducible; an ROI renders only that window.
    """
    full = Roi(0, 0, cam.sensor.width, cam.sensor.height)
    roi = roi or full
    if (
        roi.x < 0
        or roi.y < 0
        or roi.width < 1
        or roi.height < 1
        or roi.x + roi.width > full.width
        or roi.y + roi.height > full.height
    ):
        raise ValueError(f"ROI {roi} lies outside the {full.width}x{full.height} sensor")
    irr = render_irradiance(
        cam,
        object_distance_mm=object_distance_mm,
        white=white,
        board_offset_mm=board_offset_mm,
        roi=roi,
        threads=threads,
    )
    if not noise:
        counts = irr * np.float32(
            cam.sensor.white_level_e * cam.sensor.max_count / cam.sensor.full_well_e
        ) + np.float32(cam.sensor.black_level_dn)
        return np.clip(np.rint(counts), 0, cam.sensor.max_count).astype(np.uint16)
    return expose(irr, cam, np.random.default_rng(seed))


def main_image_position_mm(
    cam: SimCamera,
    board_xy_mm: tuple[float, float],
    object_distance_mm: float,
    board_offset_mm: tuple[float, float] = (0.0, 0.0),
) -> NDArray[np.float64]:
    """Lateral position ``r`` (mm from the axis) of the main image of a board point (inverted)."""
    v = float(image_distance(object_distance_mm, cam.optics.F))
    X = np.asarray(board_xy_mm, dtype=np.float64) + np.asarray(board_offset_mm, dtype=np.float64)
    return -X * v / object_distance_mm


def corner_images_px(
    cam: SimCamera,
    board_xy_mm: tuple[float, float],
    object_distance_mm: float,
    board_offset_mm: tuple[float, float] = (0.0, 0.0),
    *,
    rim_margin_px: float = 0.0,
) -> list[dict[str, float | int]]:
    """True sensor positions of a board point in every micro-image that shows it.

    Uses OPTICS.md §1: lens centre ``m`` images main-image point ``r`` to
    ``m + (m - r)·b/a``. A micro-image counts when the point lies inside the
    micro-image disc (radius = half the lens pitch ``D/2`` around the micro-image
    centre) shrunk by ``rim_margin_px``, and inside the sensor.
    Returns dicts with lens index ``i, j``, lens centre ``mx, my`` and the image
    ``x, y`` in pixels.
    """
    o = cam.optics
    cx, cy = cam.sensor.pp
    a = float(o.a(object_distance_mm))
    r = main_image_position_mm(cam, board_xy_mm, object_distance_mm, board_offset_mm)
    # lenses near the chief ray r*L/(L-a)
    centre_mm = r * o.L / (o.L - a)
    grid = cam.lens_grid
    ci, cj = grid.nearest(
        np.array([cx + centre_mm[0] / o.delta]), np.array([cy + centre_mm[1] / o.delta])
    )
    span = int(math.ceil(micro_span(a, o))) + 2
    ii, jj = np.meshgrid(
        np.arange(ci[0] - span, ci[0] + span + 1),
        np.arange(cj[0] - span, cj[0] + span + 1),
        indexing="ij",
    )
    i_flat, j_flat = ii.ravel(), jj.ravel()
    mxp, myp = grid.centre(i_flat, j_flat)
    mx, my = (mxp - cx) * o.delta, (myp - cy) * o.delta
    sx = mx + (mx - r[0]) * o.b / a
    sy = my + (my - r[1]) * o.b / a
    xp, yp = cx + sx / o.delta, cy + sy / o.delta
    k = image_centre_scale(o.L, o.b)
    icx, icy = cx + k * (mxp - cx), cy + k * (myp - cy)
    disc = 0.5 * o.lens_pitch_px - rim_margin_px
    keep = (
        (np.hypot(xp - icx, yp - icy) <= disc)
        & (xp >= 0)
        & (yp >= 0)
        & (xp <= cam.sensor.width - 1)
        & (yp <= cam.sensor.height - 1)
    )
    return [
        {"i": int(i), "j": int(j), "mx": float(a_), "my": float(b_), "x": float(x), "y": float(y)}
        for i, j, a_, b_, x, y in zip(
            i_flat[keep], j_flat[keep], mxp[keep], myp[keep], xp[keep], yp[keep], strict=True
        )
    ]


def micro_span(a: float, optics: CameraOptics) -> float:
    """Half the number of micro-images (per axis) that show one board point."""
    return 0.5 * (a / optics.b) * (optics.L + optics.b) / (optics.L - a)
