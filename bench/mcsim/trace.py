"""The Monte-Carlo ray tracer: sensor point -> microlens -> main lens -> board.

Rays are traced backwards, from point samples on the sensor to the board. For
a sensor point s (lateral mm, at z = L + b) in a pixel that belongs to lens
centre c, a ray goes through a random point m of that lens's aperture (z = L):

* between sensor and MLA its slope (lateral mm per mm of z) is ``(s - m)/b``;
* the ideal thin microlens (focal f) deflects a ray by ``-h/f``, h = m - c the
  height from the lens centre, so in front of the MLA the slope is
  ``t = (s - m)/b + (m - c)/f``;
* the ray meets the main-lens plane z = 0 at ``x0 = m - L·t``; rays with
  ``|x0| > A/2`` are blocked (vignetting, soft micro-image rims);
* the thin main lens (focal F, or F(ρ) with spherical aberration) deflects by
  ``-x0/F``, so on the object side the slope is ``t + x0/F`` and the ray meets
  the board plane z = -u at ``X = x0 - u·(t + x0/F)``;
* an optional second circular stop at z = Z (diameter A_v, mechanical
  vignetting) blocks rays whose lateral position there exceeds A_v/2: for
  0 < Z < L the ray is the straight line from x0 (z = 0) to m (z = L), at
  ``(1 - Z/L)·x0 + (Z/L)·m``; for Z < 0 it is the object-side ray, at
  ``x0 + Z·(t + x0/F)`` (F(ρ) with spherical aberration).

Every step is affine in m and s, so each sample point is reduced to a few
per-point constants and every ray costs a handful of multiply-adds.

Radiometry: the board is Lambertian and radiance is conserved through thin
lenses, so the irradiance at s is ``∫ radiance · cos⁴θ dA / b²`` over the lens
aperture, θ the ray's angle to the axis at the sensor. Sampling aperture points
uniformly in area and weighting each ray by cos⁴θ is therefore the exact
estimator (not an ad-hoc vignetting law). A sample point's signal is the mean
over its rays of ``reflectance · cos⁴θ`` (0 for blocked rays); a pixel's signal
is the mean over its sample points. Signal 1 is a reflectance-1 board seen
along the axis through the whole aperture.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import numpy.typing as npt

from bench.mcsim.board import DARK, LIGHT, Board
from bench.mcsim.camera import Camera
from bench.mcsim.diffraction import DiffractionSampler

F32 = np.float32
CHUNK_RAYS = 16384  # rays per vectorised chunk (fits the per-core L2 cache)
PIXEL_BLOCK = 8192  # pixels whose per-point constants are held at once


@dataclass(frozen=True)
class TraceSettings:
    """Sampling and lens-aberration settings of one render.

    ``rays`` per sample point, ``subpixel``×``subpixel`` sample points per pixel
    (cell centres, or uniformly jittered inside each cell with ``jitter``);
    ``airy_wavelength_um`` enables microlens diffraction; ``spherical_mm`` is the
    main lens's longitudinal spherical aberration (see :func:`main_focal_at`);
    ``cos4`` weighs each ray by ``cos⁴θ`` of its angle at the sensor (off: every ray
    that passes counts alike, as a renderer that ignores the sensor's obliquity does).
    """

    rays: int = 30
    subpixel: int = 2
    jitter: bool = False
    airy_wavelength_um: float | None = None
    spherical_mm: float = 0.0
    cos4: bool = True


def main_focal_at(camera: Camera, rho2_mm2: np.ndarray, spherical_mm: float) -> np.ndarray:
    """Focal length of the main lens for rays at height ρ (``rho2_mm2`` = ρ²).

    ``F(ρ) = F - S·(ρ/(A/2))²``: a ray through the rim of the aperture focuses
    a parallel beam S mm closer to the lens than a paraxial ray (S > 0: the
    under-corrected spherical aberration of a simple positive lens). For an
    object at finite distance the longitudinal focus shift is ``S·(v/F)²·(ρ/R)²``
    to first order: proportional to (ρ/(A/2))² as for third-order spherical
    aberration (transverse aberration ∝ ρ³).
    """
    radius2 = (camera.main_aperture_mm / 2.0) ** 2
    return camera.main_focal_mm - spherical_mm * rho2_mm2 / radius2


@dataclass(frozen=True)
class StopPlane:
    """The second stop's plane: a ray's lateral position there, as an affine map.

    Position ``c_x0·x0 + c_m·m + c_t·t`` (x0 the main-lens point, m the aperture
    point, t the slope in front of the MLA), plus for a stop in front of the main
    lens ``Z·x0·(1/F(ρ) - 1/F)`` with spherical aberration (``front``). ``d_m``
    and ``d_s`` are its derivatives along an aperture offset and a sensor shift.
    """

    z_mm: float
    radius2: float
    c_x0: float
    c_m: float
    c_t: float
    d_m: float
    d_s: float
    front: bool


def stop_plane(camera: Camera, k: float) -> StopPlane | None:
    """The camera's second stop (None without one); ``k`` = d x0 / d m."""
    z, diameter = camera.vignetting_stop_mm, camera.vignetting_diameter_mm
    if z is None or diameter is None:
        return None
    L, b, f = camera.mla_distance_mm, camera.sensor_distance_mm, camera.mla_focal_mm
    if z > 0:  # the straight line from x0 (z = 0) to m (z = L)
        c_x0, c_m, c_t = 1.0 - z / L, z / L, 0.0
    else:  # the object-side ray x0 + z·(t + x0/F)
        c_x0, c_m, c_t = 1.0 + z / camera.main_focal_mm, 0.0, z
    return StopPlane(
        z_mm=z,
        radius2=(diameter / 2.0) ** 2,
        c_x0=c_x0,
        c_m=c_m,
        c_t=c_t,
        d_m=c_x0 * k + c_m + c_t * (1.0 / f - 1.0 / b),
        d_s=-c_x0 * L / b + c_t / b,
        front=z < 0,
    )


class Tracer:
    """Traces pixels of one camera, at one object distance (or a white board)."""

    def __init__(
        self,
        camera: Camera,
        board: Board | None,
        u_mm: float,
        settings: TraceSettings,
        rays: int | None = None,
    ) -> None:
        self.camera = camera
        self.board = board
        self.u = float(u_mm)
        self.settings = settings
        self.rays = int(rays if rays is not None else settings.rays)
        self.sampler = (
            DiffractionSampler(
                settings.airy_wavelength_um * 1e-3,
                camera.sensor_distance_mm / camera.mla_pitch_mm,
                camera.microlens_aperture,
            )
            if settings.airy_wavelength_um
            else None
        )
        L, b = camera.mla_distance_mm, camera.sensor_distance_mm
        f, F = camera.mla_focal_mm, camera.main_focal_mm
        u = self.u
        self.k = 1.0 + L / b - L / f  # d x0 / d m
        g = 1.0 - u / F
        # X_phys = g·x0 - u·t with x0 = k·m - (L/b)s + (L/f)c and t = (s-c)/b + (m-c)(1/f-1/b)
        self.dX_dm = g * self.k - u * (1.0 / f - 1.0 / b)
        self.dX_ds = -g * L / b - u / b
        self.radius2 = (camera.main_aperture_mm / 2.0) ** 2
        self.stop = stop_plane(camera, self.k)
        self.theta_rad = math.radians(camera.theta_deg)
        self.traced_rays = 0

    # ------------------------------------------------------------------------------
    def _point_constants(
        self, x_px: np.ndarray, y_px: np.ndarray, rng: np.random.Generator
    ) -> tuple[np.ndarray, ...]:
        """Per-sample-point constants for the pixels (x_px, y_px), and the lit mask.

        Returns (lit, bX, bY, b0x, b0y, bwx, bwy): ``lit`` marks pixels that some
        ray can pass (the others are dark for certain and are not traced); the
        other arrays hold, for every sample point of the lit pixels (pixel-major,
        ``subpixel²`` points each), the board point X, Y, the main-lens point
        x0, y0 and the sensor-side slopes (s - m)/b of the ray through the base
        aperture point m: the lens centre (circle) or the square lens's corner
        at (-D/2, -D/2) along the grid's axes (the random offsets of
        :meth:`_aperture_samples` are added to it); with a second stop, two more:
        the ray's lateral position on the stop's plane (:class:`StopPlane`).
        The footprint test looks at the main aperture only: the second stop can
        only block more rays.
        """
        cam, n = self.camera, self.settings.subpixel
        L, b, f, D = (
            cam.mla_distance_mm,
            cam.sensor_distance_mm,
            cam.mla_focal_mm,
            cam.mla_pitch_mm,
        )
        i, j = cam.lens_of_pixels(x_px, y_px)
        lcx, lcy = cam.px_to_mm(*cam.lens_centre_px(i, j))
        sx, sy = cam.px_to_mm(x_px, y_px)
        # the main-lens footprint of every ray the pixel can send, as a box
        k = self.k
        x0c = (k + L / f) * lcx - (L / b) * sx
        y0c = (k + L / f) * lcy - (L / b) * sy
        reach = 0.5 * cam.pixel_mm + (self.sampler.max_offset_mm if self.sampler else 0.0)
        t = math.radians(cam.theta_deg)
        spread = abs(math.cos(t)) + abs(math.sin(t))  # the rotated square's bounding box
        half = abs(k) * D / 2.0 * spread + (L / b) * reach * (1.0 + 1e-9)
        gap_x = np.maximum(np.abs(x0c) - half, 0.0)
        gap_y = np.maximum(np.abs(y0c) - half, 0.0)
        lit = gap_x * gap_x + gap_y * gap_y <= self.radius2
        lcx, lcy, sx, sy = lcx[lit], lcy[lit], sx[lit], sy[lit]
        # sample points inside each pixel
        offsets = (np.arange(n) + 0.5) / n - 0.5
        ox = np.tile(offsets, n)
        oy = np.repeat(offsets, n)
        npix = int(lit.sum())
        px = np.repeat(sx, n * n) + np.tile(ox, npix) * cam.pixel_mm
        py = np.repeat(sy, n * n) + np.tile(oy, npix) * cam.pixel_mm
        if self.settings.jitter:
            px += (rng.random(px.shape) - 0.5) * (cam.pixel_mm / n)
            py += (rng.random(py.shape) - 0.5) * (cam.pixel_mm / n)
        cx = np.repeat(lcx, n * n)
        cy = np.repeat(lcy, n * n)
        if cam.microlens_aperture == "square":
            # the lens's corner at local (-D/2, -D/2), the square turned by θ with the grid
            cos_t, sin_t = math.cos(t), math.sin(t)
            mx = cx - D / 2.0 * (cos_t - sin_t)
            my = cy - D / 2.0 * (sin_t + cos_t)
        else:
            mx, my = cx, cy
        u, F = self.u, cam.main_focal_mm
        x0x = k * mx - (L / b) * px + (L / f) * cx
        x0y = k * my - (L / b) * py + (L / f) * cy
        tx = (px - mx) / b + (mx - cx) / f
        ty = (py - my) / b + (my - cy) / f
        ox_mm, oy_mm = self.board.offset_mm if self.board is not None else (0.0, 0.0)
        bX = x0x - u * (tx + x0x / F) - ox_mm
        bY = x0y - u * (ty + x0y / F) - oy_mm
        bwx = (px - mx) / b
        bwy = (py - my) / b
        on_stop: tuple[np.ndarray, ...] = ()
        if self.stop is not None:
            st = self.stop
            zx = st.c_x0 * x0x + st.c_m * mx + st.c_t * tx
            zy = st.c_x0 * x0y + st.c_m * my + st.c_t * ty
            on_stop = (zx.astype(F32), zy.astype(F32))
        return (
            lit,
            bX.astype(F32),
            bY.astype(F32),
            x0x.astype(F32),
            x0y.astype(F32),
            bwx.astype(F32),
            bwy.astype(F32),
            *on_stop,
        )

    def _aperture_samples(
        self, rng: np.random.Generator, shape: tuple[int, int]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Random aperture offsets m - m_base in mm (see :meth:`_point_constants`).

        Square lenses: uniform in the square of side D along the grid's axes
        e1, e2 (turned by θ), measured from the lens's corner.
        """
        D = self.camera.mla_pitch_mm
        if self.camera.microlens_aperture == "square":
            along1 = rng.random(shape, dtype=F32)
            along2 = rng.random(shape, dtype=F32)
            if self.theta_rad == 0.0:
                along1 *= F32(D)
                along2 *= F32(D)
                return along1, along2
            c, s = F32(D * math.cos(self.theta_rad)), F32(D * math.sin(self.theta_rad))
            ex = along1 * c
            ex -= along2 * s
            along1 *= s
            along2 *= c
            along2 += along1
            return ex, along2
        radius = np.sqrt(rng.random(shape, dtype=F32)) * F32(D / 2.0)
        angle = rng.random(shape, dtype=F32) * F32(2.0 * math.pi)
        return radius * np.cos(angle), radius * np.sin(angle)

    def _trace_chunk(self, consts: tuple[np.ndarray, ...], rng: np.random.Generator) -> np.ndarray:
        """Sum over the rays of every point of ``reflectance · cos⁴θ · passed``."""
        bX, bY, b0x, b0y, bwx, bwy = consts[:6]
        cam, st = self.camera, self.stop
        L, b = cam.mla_distance_mm, cam.sensor_distance_mm
        shape = (bX.shape[0], self.rays)
        ex, ey = self._aperture_samples(rng, shape)
        dm = F32(self.dX_dm)
        X = ex * dm
        X += bX[:, None]
        Y = ey * dm
        Y += bY[:, None]
        kf = F32(self.k)
        x0 = ex * kf
        x0 += b0x[:, None]
        y0 = ey * kf
        y0 += b0y[:, None]
        wx = ex * F32(-1.0 / b)
        wx += bwx[:, None]
        wy = ey * F32(-1.0 / b)
        wy += bwy[:, None]
        if st is not None:  # the ray's lateral position on the second stop's plane
            zx = ex * F32(st.d_m)
            zx += consts[6][:, None]
            zy = ey * F32(st.d_m)
            zy += consts[7][:, None]
        if self.sampler is not None:
            dx, dy = self.sampler.sample(rng, shape)
            ds = F32(self.dX_ds)
            X += dx * ds
            Y += dy * ds
            x0 -= dx * F32(L / b)
            y0 -= dy * F32(L / b)
            wx += dx * F32(1.0 / b)
            wy += dy * F32(1.0 / b)
            if st is not None:
                zx += dx * F32(st.d_s)
                zy += dy * F32(st.d_s)
        r2 = x0 * x0
        r2 += y0 * y0
        if self.settings.spherical_mm:
            # X = x0 - u·(t + x0/F(ρ)): add -u·x0·(1/F(ρ) - 1/F)
            extra = 1.0 / main_focal_at(cam, r2, self.settings.spherical_mm)
            extra -= F32(1.0 / cam.main_focal_mm)
            extra *= F32(-self.u)
            X += x0 * extra
            Y += y0 * extra
            if st is not None and st.front:  # object side: + Z·x0·(1/F(ρ) - 1/F)
                extra *= F32(-st.z_mm / self.u)
                zx += x0 * extra
                zy += y0 * extra
        passed = r2 <= F32(self.radius2)
        if st is not None:
            zx *= zx
            zy *= zy
            zx += zy
            passed &= zx <= F32(st.radius2)
        if self.settings.cos4:
            wx *= wx
            wy *= wy
            wx += wy
            wx += F32(1.0)
            wx *= wx
            weight = np.reciprocal(wx, out=wx)  # cos⁴θ = 1/(1 + tan²θ)²
            weight *= passed
        else:
            weight = passed.astype(F32)
        if self.board is None:
            weight *= F32(LIGHT)
        else:
            dark = self.board.dark_mask(X, Y)
            weight *= np.where(dark, F32(DARK), F32(LIGHT))
        self.traced_rays += weight.size
        return weight.sum(axis=1, dtype=np.float64)

    # ------------------------------------------------------------------------------
    def trace(
        self, x_px: np.ndarray, y_px: np.ndarray, rng: np.random.Generator
    ) -> npt.NDArray[np.float32]:
        """Signal (mean of reflectance·cos⁴θ over all rays) of each pixel (x_px, y_px)."""
        x_px = np.asarray(x_px, dtype=np.float64).ravel()
        y_px = np.asarray(y_px, dtype=np.float64).ravel()
        signal = np.zeros(x_px.shape, dtype=np.float32)
        per_pixel = self.settings.subpixel**2
        chunk_points = max(1, CHUNK_RAYS // self.rays)
        for start in range(0, x_px.size, PIXEL_BLOCK):
            stop = min(start + PIXEL_BLOCK, x_px.size)
            lit, *consts = self._point_constants(x_px[start:stop], y_px[start:stop], rng)
            npoints = consts[0].shape[0]
            sums = np.empty(npoints, dtype=np.float64)
            for p in range(0, npoints, chunk_points):
                q = min(p + chunk_points, npoints)
                sums[p:q] = self._trace_chunk(tuple(c[p:q] for c in consts), rng)
            pixel_sums = sums.reshape(-1, per_pixel).sum(axis=1)
            block = np.zeros(stop - start, dtype=np.float32)
            block[lit] = pixel_sums / (per_pixel * self.rays)
            signal[start:stop] = block
        return signal
