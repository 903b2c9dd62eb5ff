#!/usr/bin/env python3
"""Independent reference renderer for a focused (Keplerian, plenoptic 2.0)
camera looking at the double-checkerboard board of ``../shared/OPTICS.md``.

A cross-check for the calibration core, not part of the product: it was written
in a separate session from OPTICS.md alone, without reading the calibration core
or the project's own simulator (``calibration/simulator.py``), so that the core
is measured on frames whose modelling choices it was not developed against
(different aperture and pixel sampling, PSF applied per ray on the board,
area-weighted main-aperture clipping, cos⁴ at the sensor, no black level).
Imports nothing from the project. Writes an ``lfcal-sweep/1`` archive
(sweep.json, white.png, frames/NNNN.png) plus truth.json.

Run: ``python -m bench.crosscheck.indsim OUT --frames N ... (see --help)``;
``bench/bench_crosscheck.py`` renders its three sweeps and calibrates them.

Model (all thin lenses, paraxial, units mm; z axis = optical axis):
  main lens at z=0 (focal F, circular aperture diameter A = L*D/b),
  MLA at z=L (square lattice, pitch D, rotation theta, square lens apertures
  of side D = 100 % fill factor), sensor at z=L+b, board at z=-u.
Each sensor pixel belongs to the lens whose micro-image centre (projection of
the main-lens centre through the lens centre) is nearest to the pixel centre.
For every pixel we trace nsub x nsub sub-pixel positions times nap x nap
aperture points on that lens (cell centres of a regular grid in the lens's
own, rotated, frame):  sensor point s -> microlens point q (refract, focal f,
centre m) -> main-lens plane (reject if outside A/2) -> refract (focal F) ->
board plane.  Because the system is paraxial the board point is an affine
function  Xb = c_s*s + (c_m + c_q)*m + c_q*(q - m)  (verified against an
explicit step-by-step trace in checks.py).

Board radiance seen by a ray = board reflectance convolved with
  Gaussian(sigma_b)  (PSF stand-in; sigma_b = psf_sigma_px * pixel * |c_s|,
                      i.e. the sensor-px sigma mapped to the board through the
                      chief-ray magnification of the current frame)
  (x) box(|c_s|*pixel/nsub)    (area of the sub-pixel cell -> exact pixel-area
                                integration for interior pixels)
  (x) box(|c_q|*D/nap)         (area of the aperture cell, axis-aligned
                                approximation of the theta-rotated cell)
computed analytically-separably per dark square onto a fine raster (at least
RASTER_PER_PX points per sensor pixel) and read with bilinear interpolation
(cv2.remap).  Each ray is weighted by cos^4 of its
angle to the z axis at the sensor.
Expected electrons = photons * mean over the nsub^2*nap^2 rays of
  (pass_main_aperture * cos^4 * reflectance);
Poisson shot noise + Gaussian read noise, gain such that a fully lit light
(0.95) pixel is at 80 % of full scale, rounding, clipping to 0..2^bits-1.
"""

import argparse
import json
import math
import os
import sys
import time

import cv2
import numpy as np

DARK = 0.05
LIGHT = 0.95
BOARD_HALF = 150.0
RASTER_PER_PX = 32
"""Board raster points per sensor pixel (at least): bilinear reading then blurs by
<= 1/(32*sqrt(6)) = 0.013 px rms, a diameter error of about 0.001 px at 1 px blur."""


# ----------------------------------------------------------------------------
# optics
# ----------------------------------------------------------------------------
def v_of_u(u, F):
    return u * F / (u - F)


def u_of_v(v, F):
    return v * F / (v - F)


class Camera:
    def __init__(
        self,
        F=35.0,
        f=2.5,
        D=0.25,
        pixel=0.0025,
        b=3.0,
        L=None,
        u0=None,
        W=3000,
        H=1000,
        pp=None,
        theta_deg=0.0,
        mla_offset=(0.0, 0.0),
        board_offset=(0.0, 0.0),
        square=10.0,
        cr=0.1,
        nsub=2,
        nap=5,
        psf_sigma_px=0.4,
    ):
        self.F, self.f, self.D, self.pix, self.b = (
            float(F),
            float(f),
            float(D),
            float(pixel),
            float(b),
        )
        self.a_f = self.f * self.b / (self.b - self.f)  # 1/a_f + 1/b = 1/f
        if L is None:
            if u0 is None:
                raise ValueError("need L or u0")
            L = v_of_u(float(u0), self.F) + self.a_f
        self.L = float(L)
        self.u0 = u_of_v(self.L - self.a_f, self.F)
        self.A = self.L * self.D / self.b  # f-number matching L/A = b/D
        self.W, self.H = int(W), int(H)
        if pp is None:
            pp = ((self.W - 1) / 2.0, (self.H - 1) / 2.0)
        self.cx, self.cy = float(pp[0]), float(pp[1])
        self.theta = math.radians(theta_deg)
        self.theta_deg = float(theta_deg)
        self.mla_offset = (float(mla_offset[0]), float(mla_offset[1]))
        # O: projected centre of lens (0,0) in pixel coordinates
        self.Ox = self.cx + self.mla_offset[0]
        self.Oy = self.cy + self.mla_offset[1]
        self.board_offset = (float(board_offset[0]), float(board_offset[1]))
        self.square, self.cr = float(square), float(cr)
        self.nsub, self.nap = int(nsub), int(nap)
        self.psf_sigma_px = float(psf_sigma_px)
        self.P = self.D / self.pix  # lens pitch in px
        self.kmi = (self.L + self.b) / self.L  # micro-image / lens spacing ratio
        self.e1 = (math.cos(self.theta), math.sin(self.theta))
        self.e2 = (-math.sin(self.theta), math.cos(self.theta))

    # --- per-frame coefficients ------------------------------------------------
    def coeffs(self, u):
        k1 = 1.0 - u / self.F
        a = self.L - v_of_u(u, self.F)
        c_s = -k1 * a / self.b
        c_m = k1 * a / self.f
        c_q = k1 * (1.0 - a / self.a_f)
        return dict(a=a, c_s=c_s, c_m=c_m, c_q=c_q, cmq=c_m + c_q)

    # --- lens assignment -------------------------------------------------------
    def lens_of_pixel(self, xs, ys):
        """xs, ys: pixel-coordinate arrays. Returns lens indices (i, j) of the
        nearest micro-image centre and the lens centre lateral position (mm)."""
        # micro-image centres (px, relative to pp):
        #   kmi * ((O - pp) + i P e1 + j P e2)
        rx = (xs - self.cx) / self.kmi - (self.Ox - self.cx)
        ry = (ys - self.cy) / self.kmi - (self.Oy - self.cy)
        fi = (rx * self.e1[0] + ry * self.e1[1]) / self.P
        fj = (rx * self.e2[0] + ry * self.e2[1]) / self.P
        i = np.floor(fi + 0.5)
        j = np.floor(fj + 0.5)
        mx, my = self.lens_centre_mm(i, j)
        return i, j, mx, my

    def lens_centre_mm(self, i, j):
        """lateral position (mm, relative to the axis) of lens (i, j)."""
        mx = ((self.Ox - self.cx) + i * self.P * self.e1[0] + j * self.P * self.e2[0]) * self.pix
        my = ((self.Oy - self.cy) + i * self.P * self.e1[1] + j * self.P * self.e2[1]) * self.pix
        return mx, my

    def offsets(self):
        """sub-pixel offsets (px) and aperture offsets q-m (mm, lens frame rotated)."""
        n = self.nsub
        sub = (np.arange(n) + 0.5) / n - 0.5
        subs = [(dx, dy) for dy in sub for dx in sub]
        n = self.nap
        g = ((np.arange(n) + 0.5) / n - 0.5) * self.D
        aps = []
        for gv in g:
            for gu in g:
                aps.append((gu * self.e1[0] + gv * self.e2[0], gu * self.e1[1] + gv * self.e2[1]))
        return subs, aps

    # --- explicit single ray trace (for verification) ---------------------------
    def trace(self, s, q, m, u):
        """s, q, m lateral 2-vectors (mm).  Returns (board point physical lateral,
        main-lens plane point).  Explicit step-by-step paraxial trace."""
        s, q, m = map(np.asarray, (s, q, m))
        t = (s - q) / self.b  # slope dr/dz after the microlens (towards sensor)
        t_in = t + (q - m) / self.f  # before the microlens (thin lens: t_out = t_in - (q-m)/f)
        p = q - self.L * t_in  # at z = 0
        t_before = t_in + p / self.F  # before main lens (t_after = t_before - p/F)
        X = p - u * t_before  # at z = -u
        return X, p


# ----------------------------------------------------------------------------
# board raster
# ----------------------------------------------------------------------------
def kernel_cdf(sigma, w1, w2, step_hint):
    """CDF of Gaussian(sigma) (x) box(w1) (x) box(w2) on a fine symmetric grid,
    as (grid, cdf, half_support).  Gaussian (x) box(w1) is analytic,
    (sigma/w)[Psi((x+w/2)/sigma) - Psi((x-w/2)/sigma)] with Psi(z) = z*Phi(z) + phi(z);
    the second box is integrated with a symmetric midpoint rule."""
    from scipy.special import ndtr

    sigma = max(sigma, 1e-6)
    e = min(sigma / 40.0, step_hint / 8.0)
    half = 6.0 * sigma + 0.5 * (w1 + w2) + 4 * e
    n = int(math.ceil(half / e))
    x = e * np.arange(-n, n + 1)

    def psi(z):
        return z * ndtr(z) + np.exp(-0.5 * z * z) / math.sqrt(2 * math.pi)

    def g_box(xx):
        if w1 < 1e-4 * sigma:
            return ndtr(xx / sigma)
        return (sigma / w1) * (psi((xx + 0.5 * w1) / sigma) - psi((xx - 0.5 * w1) / sigma))

    if w2 < 1e-4 * sigma:
        cdf = g_box(x)
    else:
        nq = 64
        offs = ((np.arange(nq) + 0.5) / nq - 0.5) * w2
        cdf = np.mean([g_box(x - o) for o in offs], axis=0)
    return x, cdf, half


class BoardRaster:
    def __init__(self, cam, bbox, sigma_b, w_sub, w_ap, h):
        X0, X1, Y0, Y1 = bbox
        self.h = h
        self.X0 = X0
        self.Y0 = Y0
        nx = int(math.ceil((X1 - X0) / h)) + 2
        ny = int(math.ceil((Y1 - Y0) / h)) + 2
        if nx >= 32000 or ny >= 32000:
            raise RuntimeError(f"board raster too large ({nx} x {ny})")
        self.nx, self.ny = nx, ny
        xg = X0 + h * np.arange(nx)
        yg = Y0 + h * np.arange(ny)
        kx, kc, rad = kernel_cdf(sigma_b, w_sub, w_ap, h)
        R = np.full((ny, nx), LIGHT, np.float32)
        s = cam.square
        crh = cam.cr / 2.0
        c_lo = max(int(math.floor((X0 - rad) / s)) - 1, -int(BOARD_HALF / s))
        c_hi = min(int(math.floor((X1 + rad) / s)) + 1, int(BOARD_HALF / s) - 1)
        r_lo = max(int(math.floor((Y0 - rad) / s)) - 1, -int(BOARD_HALF / s))
        r_hi = min(int(math.floor((Y1 + rad) / s)) + 1, int(BOARD_HALF / s) - 1)
        for c in range(c_lo, c_hi + 1):
            for r in range(r_lo, r_hi + 1):
                if (c + r) % 2:
                    continue
                x0, x1, y0, y1 = c * s, (c + 1) * s, r * s, (r + 1) * s
                if c >= 1:
                    x0 += crh
                    x1 -= crh
                    y0 += crh
                    y1 -= crh
                ix0 = max(int(math.floor((x0 - rad - X0) / h)), 0)
                ix1 = min(int(math.ceil((x1 + rad - X0) / h)) + 1, nx)
                iy0 = max(int(math.floor((y0 - rad - Y0) / h)), 0)
                iy1 = min(int(math.ceil((y1 + rad - Y0) / h)) + 1, ny)
                if ix0 >= ix1 or iy0 >= iy1:
                    continue
                xx = xg[ix0:ix1]
                yy = yg[iy0:iy1]
                gx = np.interp(xx - x0, kx, kc, 0.0, 1.0) - np.interp(xx - x1, kx, kc, 0.0, 1.0)
                gy = np.interp(yy - y0, kx, kc, 0.0, 1.0) - np.interp(yy - y1, kx, kc, 0.0, 1.0)
                R[iy0:iy1, ix0:ix1] -= ((LIGHT - DARK) * np.outer(gy, gx)).astype(np.float32)
        self.R = R


# ----------------------------------------------------------------------------
# rendering
# ----------------------------------------------------------------------------
def board_bbox(cam, co, pad):
    """Bounding box (board coords) of every board point any ray can hit."""
    W, H = cam.W, cam.H
    corners = np.array([[0, 0], [W - 1, 0], [0, H - 1], [W - 1, H - 1]], float)
    _, _, mx, my = cam.lens_of_pixel(corners[:, 0], corners[:, 1])
    # lens index range: take all lenses whose micro-image centre is within the
    # frame expanded by 2 pitches
    i_c, j_c, _, _ = cam.lens_of_pixel(corners[:, 0], corners[:, 1])
    ii, jj = np.meshgrid(
        np.arange(i_c.min() - 3, i_c.max() + 4), np.arange(j_c.min() - 3, j_c.max() + 4)
    )
    mx, my = cam.lens_centre_mm(ii.ravel(), jj.ravel())
    scx = cam.cx + cam.kmi * mx / cam.pix
    scy = cam.cy + cam.kmi * my / cam.pix
    mp = cam.kmi * cam.P
    keep = (scx > -mp) & (scx < W - 1 + mp) & (scy > -mp) & (scy < H - 1 + mp)
    mx, my = mx[keep], my[keep]
    # board point of micro-image centre
    Xc = co["c_s"] * cam.kmi * mx + co["cmq"] * mx - cam.board_offset[0]
    Yc = co["c_s"] * cam.kmi * my + co["cmq"] * my - cam.board_offset[1]
    spread = abs(co["c_s"]) * 0.75 * mp * cam.pix + abs(co["c_q"]) * cam.D + pad
    return (Xc.min() - spread, Xc.max() + spread, Yc.min() - spread, Yc.max() + spread)


def _half_plane_fraction(t, a, b):
    """Fraction of a square cell lying on the inner side of a straight boundary
    at signed distance t (t > 0: cell centre inside).  a >= b >= 0 are the
    half-extents of the cell projected on the boundary normal, i.e. the CDF of
    U(-a,a) + U(-b,b) (trapezoidal density) evaluated at t."""
    ta = np.abs(t)
    bb = np.maximum(b, np.float32(1e-9))
    s = a + b
    tail = np.where(
        ta >= s,
        np.float32(0.0),
        np.where(
            ta > a - b,
            (s - ta) ** 2 / (np.float32(8.0) * a * bb),
            np.float32(0.5) - ta / (np.float32(2.0) * a),
        ),
    )
    return np.where(t > 0, np.float32(1.0) - tail, tail)


def render_expected(cam, u=None, chunk_rows=64, raster_h=None, stats=None, window=None):
    """Expected fraction E/photons for every pixel (float64 array).
    u=None renders the white image (uniform LIGHT board).
    window=(x0, x1, y0, y1) renders only that sub-rectangle (returned alone).

    Main-aperture clipping is area-weighted: every aperture sample stands for a
    square cell (side D/nap on the lens, |kq|*D/nap on the main-lens plane) and
    gets the exact fraction of that cell inside the main aperture, treating the
    aperture rim as straight across the cell (rim radius >> cell)."""
    W, H = cam.W, cam.H
    if window is None:
        window = (0, W, 0, H)
    wx0, wx1, wy0, wy1 = window
    subs, aps = cam.offsets()
    nrays = len(subs) * len(aps)
    Lb = cam.L / cam.b
    kq = 1.0 + cam.L / cam.b - cam.L / cam.f  # main-plane footprint scale of q-m
    Rap = cam.A / 2.0
    hcell = abs(kq) * cam.D / cam.nap  # aperture cell side on the main-lens plane
    ib2 = 1.0 / cam.b**2
    c1, s1 = cam.e1
    out = np.zeros((wy1 - wy0, wx1 - wx0), np.float64)
    raster = None
    if u is not None:
        co = cam.coeffs(u)
        sigma_b = cam.psf_sigma_px * cam.pix * abs(co["c_s"])
        w_sub = abs(co["c_s"]) * cam.pix / cam.nsub
        w_ap = abs(co["c_q"]) * cam.D / cam.nap
        # the bilinear read adds a triangle blur of variance h^2/6: keep h a small
        # fraction of a sensor pixel on the board, or the edges come out wider
        # than the physics (0.005 mm was 0.06-0.1 px on the mcsim-small camera)
        px_on_board = abs(co["c_s"]) * cam.pix
        h = (
            raster_h
            if raster_h
            else min(0.005, max(sigma_b, w_sub) / 5.0, px_on_board / RASTER_PER_PX)
        )
        pad = 8 * sigma_b + w_sub + w_ap + 0.1
        bbox = board_bbox(cam, co, pad)
        raster = BoardRaster(cam, bbox, sigma_b, w_sub, w_ap, h)
        if stats is not None:
            stats.update(
                sigma_b_mm=sigma_b,
                raster_h_mm=h,
                raster_shape=[raster.ny, raster.nx],
                a_mm=co["a"],
                c_s=co["c_s"],
                c_q=co["c_q"],
            )
    xs_row = np.arange(wx0, wx1, dtype=np.float64)
    oob = 0
    f32 = np.float32
    for y0 in range(wy0, wy1, chunk_rows):
        y1 = min(wy1, y0 + chunk_rows)
        ys, xs = np.meshgrid(np.arange(y0, y1, dtype=np.float64), xs_row, indexing="ij")
        _, _, mx, my = cam.lens_of_pixel(xs, ys)
        sx = (xs - cam.cx) * cam.pix
        sy = (ys - cam.cy) * cam.pix
        # main-lens plane point of the ray through the lens centre from the pixel centre
        p0x = ((1.0 + Lb) * mx - Lb * sx).astype(f32)
        p0y = ((1.0 + Lb) * my - Lb * sy).astype(f32)
        dmx = (sx - mx).astype(f32)
        dmy = (sy - my).astype(f32)
        acc = np.zeros(xs.shape, f32)
        if raster is not None:
            bx = (
                ((co["c_s"] * sx + co["cmq"] * mx - cam.board_offset[0]) - raster.X0) / raster.h
            ).astype(f32)
            by = (
                ((co["c_s"] * sy + co["cmq"] * my - cam.board_offset[1]) - raster.Y0) / raster.h
            ).astype(f32)
        for qx, qy in aps:
            # main-lens plane point at the pixel centre: p = p0 + kq*(q-m)
            px = p0x + f32(kq * qx)
            py = p0y + f32(kq * qy)
            pr = np.sqrt(px * px + py * py) + f32(1e-12)
            nx_ = px / pr
            ny_ = py / pr
            # projected half-extents of the (theta-rotated) cell on the normal
            g1 = np.abs(nx_ * f32(c1) + ny_ * f32(s1))
            g2 = np.abs(ny_ * f32(c1) - nx_ * f32(s1))
            ha = f32(0.5 * hcell) * np.maximum(g1, g2)
            hb = f32(0.5 * hcell) * np.minimum(g1, g2)
            t0 = f32(Rap) - pr
            # cos^4 of the ray angle at the sensor (tan = |s - q| / b), per pixel centre
            tx = dmx - f32(qx)
            ty = dmy - f32(qy)
            c = f32(1.0) + (tx * tx + ty * ty) * f32(ib2)
            cos4 = f32(1.0) / (c * c)
            for dsx, dsy in subs:
                ddx = dsx * cam.pix
                ddy = dsy * cam.pix
                # sub-pixel shift moves p by -Lb*ds; first order in |p|
                t = t0 + (nx_ * f32(Lb * ddx) + ny_ * f32(Lb * ddy))
                frac = _half_plane_fraction(t, ha, hb)
                wgt = frac * cos4
                if raster is None:
                    acc += wgt
                else:
                    ox = f32((co["c_s"] * ddx + co["c_q"] * qx) / raster.h)
                    oy = f32((co["c_s"] * ddy + co["c_q"] * qy) / raster.h)
                    val = cv2.remap(
                        raster.R,
                        bx + ox,
                        by + oy,
                        interpolation=cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT,
                        borderValue=-1.0,
                    )
                    bad = (val < 0) & (frac > 0)
                    if bad.any():
                        oob += int(bad.sum())
                        val = np.where(val < 0, f32(LIGHT), val)
                    acc += wgt * val
        if raster is None:
            acc *= f32(LIGHT)
        out[y0 - wy0 : y1 - wy0] = acc / nrays
    if oob:
        print(f"WARNING: {oob} rays fell outside the board raster", file=sys.stderr)
    return out


def sensor(expected, photons, read_noise, bit_depth, rng):
    full = 2**bit_depth - 1
    gain = 0.8 * full / (photons * LIGHT)  # counts per electron
    e = rng.poisson(photons * expected).astype(np.float64)
    if read_noise > 0:
        e += rng.normal(0.0, read_noise, e.shape)
    c = np.clip(np.rint(e * gain), 0, full)
    return c.astype(np.uint16), gain


# ----------------------------------------------------------------------------
# truth / geometry helpers
# ----------------------------------------------------------------------------
def corner_images(cam, u, Xb, Yb, min_pass=0.5):
    """Predicted sensor positions (px) of board point (Xb, Yb) in every
    micro-image that shows it: list of (i, j, x_px, y_px, pass_fraction).
    Uses OPTICS.md Sec. 1: main image r = -Xphys*v/u (at distance a in front
    of the MLA), lens m images it to m + (m - r)*b/a."""
    v = v_of_u(u, cam.F)
    a = cam.L - v
    rx = -(Xb + cam.board_offset[0]) * v / u
    ry = -(Yb + cam.board_offset[1]) * v / u
    # lenses around r*L/(L-a)
    cxl = rx * cam.L / (cam.L - a) / cam.pix + cam.cx
    cyl = ry * cam.L / (cam.L - a) / cam.pix + cam.cy
    # lens lattice coordinates of that position
    rxl = cxl - cam.Ox
    ryl = cyl - cam.Oy
    fi = (rxl * cam.e1[0] + ryl * cam.e1[1]) / cam.P
    fj = (rxl * cam.e2[0] + ryl * cam.e2[1]) / cam.P
    res = []
    nmax = 8
    kq = 1.0 + cam.L / cam.b - cam.L / cam.f
    _, aps = cam.offsets()
    aps = np.array(aps)
    for i in range(int(round(fi)) - nmax, int(round(fi)) + nmax + 1):
        for j in range(int(round(fj)) - nmax, int(round(fj)) + nmax + 1):
            mx, my = cam.lens_centre_mm(i, j)
            sxm = mx + (mx - rx) * cam.b / a
            sym = my + (my - ry) * cam.b / a
            xp = cam.cx + sxm / cam.pix
            yp = cam.cy + sym / cam.pix
            ii, jj, _, _ = cam.lens_of_pixel(np.array([xp]), np.array([yp]))
            if ii[0] != i or jj[0] != j:
                continue
            # fraction of aperture samples passing at that sensor point
            p0x = (1 + cam.L / cam.b) * mx - cam.L / cam.b * sxm
            p0y = (1 + cam.L / cam.b) * my - cam.L / cam.b * sym
            px = p0x + kq * aps[:, 0]
            py = p0y + kq * aps[:, 1]
            frac = float(np.mean(px * px + py * py <= (cam.A / 2) ** 2))
            if frac >= min_pass:
                res.append((i, j, xp, yp, frac))
    return res


def truth_dict(cam, frames, u_rail0, direction, extra=None):
    Q = cam.b / cam.a_f
    t = {
        "generator": "indsim (independent reference renderer, written from OPTICS.md only)",
        "F_mm": cam.F,
        "f_mm": cam.f,
        "D_mm": cam.D,
        "pixel_pitch_mm": cam.pix,
        "b_mm": cam.b,
        "L_mm": cam.L,
        "a_f_mm": cam.a_f,
        "Q_focus": Q,
        "patch_size_px_focus": Q * cam.D / cam.pix,
        "u0_mm": cam.u0,
        "focus_rail_mm": (cam.u0 - u_rail0) / direction,
        "u_rail0_mm": u_rail0,
        "direction": direction,
        "main_aperture_diameter_mm": cam.A,
        "main_aperture_note": "circular, A = L*D/b (f-number matching)",
        "microlens_aperture": "square, side D, aligned with the (rotated) MLA grid (fill factor 1)",
        "width": cam.W,
        "height": cam.H,
        "principal_point_px": [cam.cx, cam.cy],
        "theta_deg": cam.theta_deg,
        "theta_rad": cam.theta,
        "mla_offset_px": list(cam.mla_offset),
        "lens_grid": {
            "origin_px": [cam.Ox, cam.Oy],
            "origin_note": "O = principal point + mla_offset: projected (straight along z) centre of lens (0,0)",
            "pitch_px": cam.P,
            "theta_deg": cam.theta_deg,
            "e1": list(cam.e1),
            "e2": list(cam.e2),
        },
        "micro_image_grid": {
            "origin_px": [
                cam.cx + cam.kmi * (cam.Ox - cam.cx),
                cam.cy + cam.kmi * (cam.Oy - cam.cy),
            ],
            "pitch_px": cam.P * cam.kmi,
            "ratio_(L+b)/L": cam.kmi,
            "theta_deg": cam.theta_deg,
        },
        "board": {
            "square_mm": cam.square,
            "reference_gap_mm": cam.cr,
            "offset_mm": list(cam.board_offset),
            "offset_note": "board corner (0,0) sits at lateral (offset_x, offset_y) mm from the optical axis",
            "dark": DARK,
            "light": LIGHT,
            "half_extent_mm": BOARD_HALF,
        },
        "render": {
            "subpixel_samples": cam.nsub,
            "aperture_samples": cam.nap,
            "psf_sigma_px": cam.psf_sigma_px,
            "psf_note": "Gaussian applied to the board radiance per ray; sigma_board = psf_sigma_px*pixel*|c_s(u)|, c_s = (u/v)(a/b) = chief-ray board-mm per sensor-mm",
            "cos4": "cos^4 of ray angle to z at the sensor",
        },
        "frames": [],
    }
    for fr in frames:
        u = fr["u_mm"]
        a = cam.L - v_of_u(u, cam.F)
        q = cam.b / a
        t["frames"].append(
            {
                "index": fr["index"],
                "rail_mm": fr["rail_mm"],
                "u_mm": u,
                "v_mm": v_of_u(u, cam.F),
                "a_mm": a,
                "Q": q,
                "p_px": q * cam.D / cam.pix,
                "defocus_blur_px": cam.D * cam.b * abs(1 / cam.a_f - 1 / a) / cam.pix,
                "n_micro_images_per_axis": (a / cam.b) * (cam.L + cam.b) / (cam.L - a),
                "corners_px": {
                    "note": "[i, j, x, y, pass_fraction] per micro-image, OPTICS.md Sec.1 formula; pass>=0.5",
                    "standard": [
                        [p[0], p[1], round(p[2], 5), round(p[3], 5), round(p[4], 3)]
                        for p in corner_images(cam, u, 0.0, 0.0, 0.5)
                    ],
                    "reference": [
                        [p[0], p[1], round(p[2], 5), round(p[3], 5), round(p[4], 3)]
                        for p in corner_images(cam, u, 2 * cam.square, 0.0, 0.5)
                    ],
                },
            }
        )
    if extra:
        t.update(extra)
    return t


# ----------------------------------------------------------------------------
# CLI
# ----------------------------------------------------------------------------
def pair(s):
    a, b = s.split(",")
    return (float(a), float(b))


def build_parser():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("out_dir")
    ap.add_argument("--frames", type=int, default=100)
    ap.add_argument("--start-mm", type=float, default=0.0)
    ap.add_argument("--step-mm", type=float, default=1.0)
    ap.add_argument("--width", type=int, default=3000)
    ap.add_argument("--height", type=int, default=1000)
    ap.add_argument("--pp", type=pair, default=None, help="principal point x,y (px)")
    ap.add_argument("--F", type=float, default=35.0)
    ap.add_argument("--f", type=float, default=2.5)
    ap.add_argument("--D", type=float, default=0.25)
    ap.add_argument("--pixel", type=float, default=0.0025)
    ap.add_argument("--b", type=float, default=3.0)
    g = ap.add_mutually_exclusive_group()
    g.add_argument("--L", type=float, default=None)
    g.add_argument("--u0", type=float, default=None)
    ap.add_argument("--theta-deg", type=float, default=0.2)
    ap.add_argument("--mla-offset", type=pair, default=(1.3, -0.7))
    ap.add_argument("--board-offset", type=pair, default=(0.0, 0.0))
    ap.add_argument("--u-rail0", type=float, default=250.0)
    ap.add_argument("--direction", type=int, default=1, choices=[1, -1])
    ap.add_argument("--bit-depth", type=int, default=12)
    ap.add_argument("--photons", type=float, default=3000.0)
    ap.add_argument("--read-noise", type=float, default=3.0)
    ap.add_argument("--psf-sigma-px", type=float, default=0.4)
    ap.add_argument("--square-mm", type=float, default=10.0)
    ap.add_argument("--gap-mm", type=float, default=0.1)
    ap.add_argument("--nsub", type=int, default=2, help="sub-pixel samples per axis")
    ap.add_argument("--nap", type=int, default=5, help="microlens aperture samples per axis")
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument(
        "--manifest-main-focal-mm", type=float, default=None, help="F stated in the manifest"
    )
    ap.add_argument(
        "--manifest-mla-focal-mm", type=float, default=None, help="f stated in the manifest"
    )
    ap.add_argument(
        "--manifest-rail-zero-mm",
        type=float,
        default=None,
        help="rail zero object distance stated in the manifest",
    )
    ap.add_argument(
        "--manifest-tolerances",
        default=None,
        help="F_TOL,f_TOL,RAIL_TOL (mm, 1 sigma) stated in the manifest",
    )
    ap.add_argument("--jobs", type=int, default=1)
    ap.add_argument(
        "--only",
        type=str,
        default=None,
        help="comma list of frame indices to (re)render (debug); manifest is still complete",
    )
    return ap


def make_camera(args):
    u0 = args.u0
    if args.L is None and u0 is None:
        u0 = 300.0
    return Camera(
        F=args.F,
        f=args.f,
        D=args.D,
        pixel=args.pixel,
        b=args.b,
        L=args.L,
        u0=u0,
        W=args.width,
        H=args.height,
        pp=args.pp,
        theta_deg=args.theta_deg,
        mla_offset=args.mla_offset,
        board_offset=args.board_offset,
        square=args.square_mm,
        cr=args.gap_mm,
        nsub=args.nsub,
        nap=args.nap,
        psf_sigma_px=args.psf_sigma_px,
    )


_G = {}


def _work(task):
    cam, args, idx, u, path = _G["cam"], _G["args"], task[0], task[1], task[2]
    t0 = time.time()
    exp = render_expected(cam, u)
    rng = np.random.default_rng([args.seed, 1 if idx >= 0 else 0, max(idx, 0)])
    img, gain = sensor(exp, args.photons, args.read_noise, args.bit_depth, rng)
    if not cv2.imwrite(path, img):
        raise RuntimeError("cannot write " + path)
    return idx, time.time() - t0


def main(argv=None):
    args = build_parser().parse_args(argv)
    cv2.setNumThreads(1 if args.jobs > 1 else 2)
    cam = make_camera(args)
    out = args.out_dir
    os.makedirs(os.path.join(out, "frames"), exist_ok=True)
    frames = []
    for k in range(args.frames):
        rail = args.start_mm + k * args.step_mm
        rail = round(rail, 9)
        frames.append(
            {
                "index": k,
                "rail_mm": rail,
                "file": f"frames/{k:04d}.png",
                "u_mm": args.u_rail0 + args.direction * rail,
            }
        )
    for fr in frames:
        if fr["u_mm"] <= cam.F or cam.L - v_of_u(fr["u_mm"], cam.F) <= 0:
            raise SystemExit(f"frame {fr['index']}: not Keplerian (a <= 0)")
    manifest = {
        "format": "lfcal-sweep/1",
        "camera": {
            "width": cam.W,
            "height": cam.H,
            "pixel_pitch_mm": cam.pix,
            "bit_depth": args.bit_depth,
            "principal_point_px": [cam.cx, cam.cy],
        },
        "optics": {"main_focal_mm": cam.F, "mla_focal_mm": cam.f, "mla_pitch_mm": cam.D},
        "board": {"square_mm": cam.square, "reference_gap_mm": cam.cr},
        "rail": {"zero_object_distance_mm": args.u_rail0, "direction": args.direction},
        "white": "white.png",
        "frames": [
            {"index": f["index"], "rail_mm": f["rail_mm"], "file": f["file"]} for f in frames
        ],
        "generator": "indsim",
        "exposure": {
            "photons_full_light": args.photons,
            "read_noise_e": args.read_noise,
            "gain_counts_per_e": 0.8 * (2**args.bit_depth - 1) / (args.photons * LIGHT),
        },
    }
    # data-sheet values other than the rendered camera's (the truth keeps the true ones)
    if args.manifest_main_focal_mm is not None:
        manifest["optics"]["main_focal_mm"] = args.manifest_main_focal_mm
    if args.manifest_mla_focal_mm is not None:
        manifest["optics"]["mla_focal_mm"] = args.manifest_mla_focal_mm
    if args.manifest_rail_zero_mm is not None:
        manifest["rail"]["zero_object_distance_mm"] = args.manifest_rail_zero_mm
    if args.manifest_tolerances:
        tol_f_main, tol_f_mla, tol_rail = (float(v) for v in args.manifest_tolerances.split(","))
        manifest["optics"]["main_focal_tolerance_mm"] = tol_f_main
        manifest["optics"]["mla_focal_tolerance_mm"] = tol_f_mla
        manifest["rail"]["zero_object_distance_tolerance_mm"] = tol_rail
    with open(os.path.join(out, "sweep.json"), "w") as fh:
        json.dump(manifest, fh, indent=1)
    truth = truth_dict(
        cam,
        frames,
        args.u_rail0,
        args.direction,
        extra={
            "command": " ".join(sys.argv),
            "seed": args.seed,
            "bit_depth": args.bit_depth,
            "photons": args.photons,
            "read_noise_e": args.read_noise,
        },
    )
    with open(os.path.join(out, "truth.json"), "w") as fh:
        json.dump(truth, fh, indent=1)

    tasks = [(-1, None, os.path.join(out, "white.png"))]
    tasks += [(f["index"], f["u_mm"], os.path.join(out, f["file"])) for f in frames]
    if args.only is not None:
        want = set(int(x) for x in args.only.split(",") if x != "")
        tasks = [t for t in tasks if t[0] in want]
    _G["cam"], _G["args"] = cam, args
    t0 = time.time()
    times = []
    if args.jobs > 1:
        import multiprocessing as mp

        with mp.get_context("fork").Pool(args.jobs) as pool:
            for idx, dt in pool.imap_unordered(_work, tasks):
                times.append(dt)
                print(
                    f"frame {idx} done in {dt:.1f} s (elapsed {time.time() - t0:.0f} s)",
                    flush=True,
                )
    else:
        for t in tasks:
            idx, dt = _work(t)
            times.append(dt)
            print(f"frame {idx} done in {dt:.1f} s (elapsed {time.time() - t0:.0f} s)", flush=True)
    print(
        f"all done: {len(times)} images, {time.time() - t0:.1f} s, "
        f"{np.mean(times) if times else 0:.1f} s/image",
        flush=True,
    )


if __name__ == "__main__":
    main()
