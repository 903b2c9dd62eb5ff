"""Micro-image and microlens lattices from a white (flat-field) image (``shared/OPTICS.md`` §1–2).

:func:`fit_mla_grid` finds the square lattice of **micro-image centres** in a
raw white image to sub-pixel accuracy and converts it to the lattice of
**lens centres** (projected along z onto the sensor).

Conventions: pixel (column x, row y) has its centre at integer coordinates
(x, y) (OpenCV's); arrays are indexed ``[y, x]``; positions are ``(x, y)`` in
pixels; angles are radians unless a name says ``_deg``. Lens ``(i, j)`` of a
:class:`~calibration.lens_grid.LensGrid` sits at ``origin + i·pitch·e1 +
j·pitch·e2``. The image and the lens lattice share indices: micro-image
``(i, j)`` is the image of lens ``(i, j)``; index ``(0, 0)`` is the micro-image
centre nearest the principal point.

Method (all vectorized; no per-pixel Python loops):

1. **Initial lattice** (:mod:`calibration.mla_spectrum`). The power spectrum of a Hann-windowed central crop
   shows the lattice's fundamental peaks at ``|k| = 1/pitch``; the strongest
   peak in the expected pitch band gives pitch and rotation (modulo 90°,
   reported in (-45°, 45°]); the phases of the two fundamentals give the origin.
2. **Per-micro-image centres** (:mod:`calibration.mla_centroids`). Each micro-image is cut out as a square patch
   around its predicted centre. A global background (the dark gaps between
   discs) is subtracted; a plane fitted to the flat top of the disc models the
   vignetting gradient (``cos⁴`` is centred on the *lens* centre, not on the
   micro-image centre, so raw intensity centroids are pulled toward the axis).
   The patch divided by that plane is a point-symmetric disc; its centre is the
   centroid of ``clip((J - lo) / (hi - lo), 0, 1)`` (a symmetric function of the
   normalized intensity ``J``, zero in the dark gaps and flat on the plateau, so
   noise there does not enter) inside the circle of radius pitch/2.
3. **Whole-lattice fit.** A 4-parameter similarity lattice (origin, pitch,
   rotation) is fitted by least squares to all centres, with iterative
   rejection of outliers; micro-images cut by the sensor edge and dark (dead)
   lenses are excluded beforehand. Steps 2–3 repeat with the refined
   predictions until the lattice moves by less than ``tol_px`` anywhere on the
   sensor (the first rounds use a sparse subset of lenses).
4. **Lens centres.** Lens centres lie ``L/(L+b)`` times as far from the
   principal point as micro-image centres; with the data-sheet lens pitch
   ``D/δ`` that factor is ``lens_pitch_px / image_pitch_px``, so the lens
   lattice is the image lattice scaled about the principal point
   (:meth:`LensGrid.scaled_about`).

The input is screened: an image that is uniform, too small, shows no
lattice in the expected pitch band (or only a harmonic of one), or whose
micro-images are largely dark or not flat on top (a board frame) raises
``ValueError`` with a specific message.

:func:`micro_image_labels` maps every pixel to the micro-image it belongs to.

Accuracy (``bench/bench_mla.py``, simulated 5120×5120 whites): lens centres
within ~0.001 px RMS, rotation within ~1e-5°, image pitch within ~2e-5. The
plane normalization removes ~80 % of the vignetting pull; what remains is a
radial pull toward the axis proportional to the distance from it, i.e. a
pure scale of the image lattice about the principal point (image pitch about
2e-5 low, micro-image centres ~0.04 px off at 2500 px from the axis). Most of
it is the shading of the rims, not of the plateau: a rim is the main aperture's
edge blurred by the microlens aperture scaled by ``|β - Q0|`` (``β = b/L``; the
aperture sits ``L`` in front of the MLA), and the angular weights that make the
shading (:mod:`calibration.shading`, ``η = Var(p)·c``) move that blur's centroid
toward the lens centre, so each disc is scaled about its lens centre by
``1 + (β - Q0)·η`` and the lattice's ``(L+b)/L`` reads ``1 + β·(1 + (β - Q0)·η)``
(-1.5e-5 for the paper's optics). :mod:`calibration.camera_model` uses the
measured scale with that model. The scale cancels exactly in the lens centres,
which use the exact ``D/δ`` pitch.
It also means the lens lattice is only as right as ``principal_point_px``:
an error ``e`` in the principal point moves the lens centres by about
``e·(1 − L/(L+b))`` (≈ 5 % of ``e``).
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .lens_grid import LensGrid
from .mla_centroids import (
    CentroidParams,
    MeasuredCentres,
    background_level,
    central_stats,
    gather_patches,
    half_radius,
    local_radius,
    measure_centres,
    radial_profile,
    radial_profile_normalized,
    thresholds,
)
from .mla_lattice import (
    MIN_LENSES,
    candidate_lenses,
    dead_lenses,
    max_move_px,
    recentre,
    robust_fit,
    sparse_subset,
)
from .mla_spectrum import Lattice, initial_lattice
from .shading import WhiteShading
from .vignetting import vignetting_onset
from .white_rim import WhiteRim
from .white_screen import check_white, validate_white

__all__ = ["MlaGrid", "fit_mla_grid", "micro_image_labels"]

#: Status codes of the per-lens diagnostic arrays (:attr:`MlaGrid.lens_status`).
STATUS_USED = 0
STATUS_DEAD = 1
STATUS_OUTLIER = 2
STATUS_VIGNETTED = 3
STATUS_NAMES = {
    STATUS_USED: "used",
    STATUS_DEAD: "dead",
    STATUS_OUTLIER: "outlier",
    STATUS_VIGNETTED: "vignetted",
}

_SUBSET_MAX = 400  # lenses per early (sparse) round


@dataclass(frozen=True, eq=False)
class MlaGrid:
    """A fitted microlens array: micro-image and lens lattices plus diagnostics.

    Pixel units throughout; pixel centres at integer ``(x, y)``. ``scale`` is
    ``(L+b)/L`` as measured (``image_pitch_px / lens_pitch_px``);
    ``disc_radius_px`` is the radius at which the normalized micro-image
    profile falls to half its plateau. ``n_rejected`` counts every lens whose
    centre lies on the sensor but was not used: ``rejected`` gives the reasons
    (``border``: disc cut by the sensor edge; ``dead``: dark lens; ``outlier``:
    centre off the lattice; ``vignetted``: disc cut by the main lens's vignetting,
    beyond ``vignetting_onset_px`` from the principal point, :mod:`calibration.vignetting`).
    The per-lens arrays cover the measured lenses
    (not the border ones): index ``lens_i``, ``lens_j``, measured centre
    ``measured_x``, ``measured_y``, residual ``residual_x/y`` (measured minus
    fitted) and ``lens_status`` (:data:`STATUS_NAMES`).
    """

    image_grid: LensGrid
    lens_grid: LensGrid
    image_pitch_px: float
    lens_pitch_px: float
    rotation_deg: float
    scale: float
    disc_radius_px: float
    principal_point_px: tuple[float, float]
    n_lenses_used: int
    n_rejected: int
    rejected: dict[str, int]
    residual_rms_px: float
    iterations: int
    background: float
    lens_i: NDArray[np.int64] = field(repr=False)
    lens_j: NDArray[np.int64] = field(repr=False)
    measured_x: NDArray[np.float64] = field(repr=False)
    measured_y: NDArray[np.float64] = field(repr=False)
    residual_x: NDArray[np.float64] = field(repr=False)
    residual_y: NDArray[np.float64] = field(repr=False)
    lens_status: NDArray[np.int8] = field(repr=False)
    shading: WhiteShading | None = None
    rim: WhiteRim | None = None
    """The micro-images' rim blur (:mod:`calibration.white_rim`; None: not measured)."""
    white_clipped_fraction: float = 0.0
    """The fraction of the white image's lit pixels at the sensor's full scale."""
    vignetting_onset_px: float = math.inf
    """Distance from the principal point (px) beyond which the micro-images are cut by the
    main lens's vignetting and left out of the lattice (``inf``: none are)."""

    @property
    def residual_px(self) -> NDArray[np.float64]:
        """Per measured lens: distance (px) of its measured centre from the fitted lattice."""
        return np.hypot(self.residual_x, self.residual_y)

    @property
    def used(self) -> NDArray[np.bool_]:
        """Per measured lens: whether it entered the final lattice fit."""
        return self.lens_status == STATUS_USED

    @property
    def scale_se(self) -> float:
        """Statistical 1σ of :attr:`scale` (``(L+b)/L``) from the lattice fit's residuals.

        The pitch's least-squares error ``σ/sqrt(Σ(i'² + j'²))`` (``i'``, ``j'`` the
        lens indices about their mean, ``σ`` the residual RMS per coordinate),
        divided by the lens pitch. The systematic pull of the shaded rims
        (module docstring) is not included: :mod:`calibration.camera_model`
        models it.
        """
        keep = self.used
        if keep.sum() < 3:
            return float("inf")
        i = self.lens_i[keep] - self.lens_i[keep].mean()
        j = self.lens_j[keep] - self.lens_j[keep].mean()
        sigma = float(np.sqrt(np.mean(np.r_[self.residual_x[keep], self.residual_y[keep]] ** 2)))
        pitch_se = sigma / float(np.sqrt(np.sum(i**2 + j**2)))
        return pitch_se / self.lens_pitch_px

    def labels(
        self, shape: tuple[int, int], radius_px: float | None = None
    ) -> tuple[NDArray[np.int32], NDArray[np.int32], NDArray[np.bool_]]:
        """:func:`micro_image_labels` for this grid (default radius: the measured disc radius)."""
        r = self.disc_radius_px if radius_px is None else radius_px
        return micro_image_labels(shape, self.image_grid, radius_px=r)

    def to_dict(self, *, include_lenses: bool = False) -> dict[str, Any]:
        """JSON-ready summary; ``include_lenses`` adds the per-lens diagnostic rows."""
        out: dict[str, Any] = {
            "image_grid": _grid_dict(self.image_grid),
            "lens_grid": _grid_dict(self.lens_grid),
            "image_pitch_px": self.image_pitch_px,
            "lens_pitch_px": self.lens_pitch_px,
            "rotation_deg": self.rotation_deg,
            "scale": self.scale,
            "scale_se": self.scale_se,
            "disc_radius_px": self.disc_radius_px,
            "principal_point_px": [float(v) for v in self.principal_point_px],
            "n_lenses_used": self.n_lenses_used,
            "n_rejected": self.n_rejected,
            "rejected": dict(self.rejected),
            "residual_rms_px": self.residual_rms_px,
            "residual_max_px": float(self.residual_px[self.used].max(initial=0.0)),
            "iterations": self.iterations,
            "background": self.background,
            "shading": None if self.shading is None else self.shading.to_dict(),
            "rim": None if self.rim is None else self.rim.to_dict(),
            "white_clipped_fraction": self.white_clipped_fraction,
            "vignetting_onset_px": (
                None if math.isinf(self.vignetting_onset_px) else self.vignetting_onset_px
            ),
        }
        if include_lenses:
            out["lenses"] = {
                "columns": ["i", "j", "x", "y", "residual_x", "residual_y", "status"],
                "rows": [
                    [int(i), int(j), float(x), float(y), float(rx), float(ry), STATUS_NAMES[int(s)]]
                    for i, j, x, y, rx, ry, s in zip(
                        self.lens_i,
                        self.lens_j,
                        self.measured_x,
                        self.measured_y,
                        self.residual_x,
                        self.residual_y,
                        self.lens_status,
                        strict=True,
                    )
                ],
            }
        return out


def _grid_dict(g: LensGrid) -> dict[str, Any]:
    return {
        "origin_px": [float(g.origin_px[0]), float(g.origin_px[1])],
        "pitch_px": float(g.pitch_px),
        "rotation_deg": float(g.rotation_deg),
    }


# --------------------------------------------------------------------------- labels


def micro_image_labels(
    shape: tuple[int, int],
    grid: LensGrid,
    *,
    radius_px: float | None = None,
    workers: int | None = None,
) -> tuple[NDArray[np.int32], NDArray[np.int32], NDArray[np.bool_]]:
    """Which micro-image every pixel belongs to (OPTICS §2).

    ``grid`` is the **micro-image** lattice (:attr:`MlaGrid.image_grid`): each
    pixel belongs to the lens whose micro-image centre is nearest. Returns
    ``(i, j, inside)``, arrays of ``shape`` (``[y, x]``): the lens indices
    (valid for both :attr:`MlaGrid.image_grid` and :attr:`MlaGrid.lens_grid`)
    and whether the pixel centre lies within ``radius_px`` of its micro-image
    centre (all ``True`` when ``radius_px`` is None). Memory: 9 bytes a pixel;
    1–1.5 s for 5120×5120 px.
    """
    h, w = int(shape[0]), int(shape[1])
    ii = np.empty((h, w), dtype=np.int32)
    jj = np.empty((h, w), dtype=np.int32)
    inside = np.ones((h, w), dtype=bool)
    xs = np.arange(w, dtype=np.float64)[None, :]

    def rows(r0: int) -> None:
        r1 = min(r0 + 128, h)
        ys = np.arange(r0, r1, dtype=np.float64)[:, None]
        fi, fj = grid.fractional_index(xs, ys)
        ni, nj = np.rint(fi), np.rint(fj)
        ii[r0:r1] = ni
        jj[r0:r1] = nj
        if radius_px is not None:
            fi -= ni
            fj -= nj
            inside[r0:r1] = fi * fi + fj * fj <= (radius_px / grid.pitch_px) ** 2

    with ThreadPoolExecutor(workers or min(4, os.cpu_count() or 1)) as pool:
        list(pool.map(rows, range(0, h, 128)))
    return ii, jj, inside


# --------------------------------------------------------------------------- main entry


def fit_mla_grid(
    white: NDArray[Any],
    *,
    lens_pitch_px: float,
    principal_point_px: tuple[float, float],
    pitch_guess_px: float | None = None,
    max_iterations: int = 12,
    tol_px: float = 5e-3,
    outlier_sigma: float = 4.0,
    outlier_floor_px: float = 0.05,
    dead_fraction: float = 0.5,
    max_dark_fraction: float = 0.25,
    max_nonflat_fraction: float = 0.25,
    workers: int | None = None,
    progress: Callable[[str], None] | None = None,
) -> MlaGrid:
    """Fit the micro-image and lens lattices of a raw white (flat-field) image.

    Parameters (pixels; pixel centres at integer coordinates; ``white[y, x]``):

    - ``white``: raw flat-field image (any integer or float dtype, any black
      level); micro-images are bright discs on a dark background.
    - ``lens_pitch_px``: microlens pitch ``D/δ`` from the data sheet (exact prior).
    - ``principal_point_px``: ``(cx, cy)`` where the optical axis meets the sensor.
    - ``pitch_guess_px``: approximate micro-image pitch; ``None`` searches
      ``[0.99, 1.25]·lens_pitch_px`` in the spectrum (else ±5 % around the guess).
    - ``max_iterations``/``tol_px``: measure–fit rounds until the lattice moves
      less than ``tol_px`` at every sensor corner.
    - ``outlier_sigma``/``outlier_floor_px``: centres farther than
      ``max(outlier_sigma·σ, outlier_floor_px)`` from the lattice are rejected.
    - ``dead_fraction``: a lens darker than this fraction of the smooth
      brightness trend is dead.
    - ``max_dark_fraction``/``max_nonflat_fraction``: above these fractions of
      dark or non-flat micro-images the image is not a white image.
    - ``workers``: threads (default ``min(4, cpu_count)``).

    Raises ``ValueError`` with a specific message for an image that is too
    small, uniform, has no lattice in the expected pitch band, or is not a
    flat-field (e.g. a checkerboard frame).
    """
    img = validate_white(white, lens_pitch_px)
    if max_iterations < 1 or not tol_px > 0:
        raise ValueError("max_iterations must be >= 1 and tol_px > 0")
    say = progress or (lambda _msg: None)
    lat = initial_lattice(img, lens_pitch_px, pitch_guess_px)
    say(f"spectrum: pitch {lat.pitch:.3f} px, rotation {math.degrees(lat.theta):.4f} deg")
    n_workers = workers or min(4, os.cpu_count() or 1)
    pool = ThreadPoolExecutor(n_workers) if n_workers > 1 else None
    try:
        return _fit(
            img,
            lat,
            lens_pitch_px=float(lens_pitch_px),
            pp=(float(principal_point_px[0]), float(principal_point_px[1])),
            max_iterations=max_iterations,
            tol_px=tol_px,
            outlier_sigma=outlier_sigma,
            outlier_floor_px=outlier_floor_px,
            dead_fraction=dead_fraction,
            max_dark_fraction=max_dark_fraction,
            max_nonflat_fraction=max_nonflat_fraction,
            pool=pool,
            say=say,
        )
    finally:
        if pool is not None:
            pool.shutdown()


def _setup(
    img: NDArray[Any],
    lat: Lattice,
    pp: tuple[float, float],
    dead_fraction: float,
    max_dark_fraction: float,
    max_nonflat_fraction: float,
) -> tuple[CentroidParams, float]:
    """Background, noise, thresholds and the disc radius from ≤ 128 lenses nearest the
    principal point ``pp`` (or the nearest point of the image when it lies outside):
    there the main lens does not vignet the discs (:mod:`calibration.vignetting`).

    Also screens those lenses: too many dark or non-uniform micro-images mean
    the image is not a white image (``ValueError``).
    """
    h, w = img.shape
    pitch = lat.pitch
    half = int(math.ceil(0.5 * pitch)) + 1
    ii, jj, _ = candidate_lenses(lat, img.shape, half + 1)
    if ii.size < MIN_LENSES:
        raise ValueError(
            f"white image: only {ii.size} whole micro-images in view (need {MIN_LENSES})"
        )
    x, y = lat.centre(ii, jj)
    near_x, near_y = min(max(pp[0], 0.0), w - 1.0), min(max(pp[1], 0.0), h - 1.0)
    order = np.argsort(np.hypot(x - near_x, y - near_y))[:128]
    x, y = x[order], y[order]
    bg, noise = background_level(img, x, y, half, pitch)
    xi, yi, r = local_radius(x, y, half)
    patch = gather_patches(img, xi, yi, half)
    patch -= np.float32(bg)
    level, spread = central_stats(patch, r, pitch)
    dark = ~(level > max(dead_fraction * float(np.percentile(level, 90)), 5.0 * noise))
    check_white(dark, spread, max_dark_fraction, max_nonflat_fraction)
    radii, prof = radial_profile(patch[~dark], r[~dark], level[~dark], pitch)
    plateau, lo, hi, r_half = thresholds(radii, prof, pitch)
    return CentroidParams(half, pitch, bg, noise, plateau, lo, hi), r_half


def _fit(
    img: NDArray[Any],
    lat: Lattice,
    *,
    lens_pitch_px: float,
    pp: tuple[float, float],
    max_iterations: int,
    tol_px: float,
    outlier_sigma: float,
    outlier_floor_px: float,
    dead_fraction: float,
    max_dark_fraction: float,
    max_nonflat_fraction: float,
    pool: ThreadPoolExecutor | None,
    say: Callable[[str], None],
) -> MlaGrid:
    h, w = img.shape
    prm, r_half = _setup(img, lat, pp, dead_fraction, max_dark_fraction, max_nonflat_fraction)
    margin = max(prm.half, r_half + 2.0) + 1.0
    sparse_phase = True
    last: _Round | None = None
    iterations = 0
    moved = math.inf
    for iterations in range(1, max_iterations + 1):  # noqa: B007
        ii, jj, n_border = candidate_lenses(lat, img.shape, margin)
        if ii.size < MIN_LENSES:
            raise ValueError(
                f"white image: only {ii.size} whole micro-images in view (need {MIN_LENSES})"
            )
        sparse = sparse_phase and ii.size > 2 * _SUBSET_MAX
        if sparse:
            sel = sparse_subset(ii, jj, _SUBSET_MAX)
            ii, jj = ii[sel], jj[sel]
        xp, yp = lat.centre(ii, jj)
        m = measure_centres(img, xp, yp, prm, pool, flatness=iterations == 1)
        dead = dead_lenses(m.x, m.y, m.level, dead_fraction)
        # discs cut by the main lens's vignetting are not centred where the lattice is, nor
        # flat on top
        radius = np.hypot(xp - pp[0], yp - pp[1])
        onset = vignetting_onset(radius, np.where(dead, np.nan, m.area), lat.pitch)
        vignetted = radius > onset
        if np.sum(~dead & ~vignetted) < MIN_LENSES:
            vignetted[:] = False
        if iterations == 1:
            check_white(
                dead[~vignetted], m.spread[~vignetted], max_dark_fraction, max_nonflat_fraction
            )
        new, keep = robust_fit(
            ii,
            jj,
            m.x,
            m.y,
            ~dead & ~vignetted,
            outlier_sigma=outlier_sigma,
            outlier_floor_px=outlier_floor_px,
        )
        moved = max_move_px(lat, new, w, h)
        say(
            f"round {iterations}{' (sparse)' if sparse else ''}: {int(keep.sum())}/{ii.size} "
            f"lenses, lattice moved {moved:.4f} px"
        )
        if moved > 0.25 * lat.pitch:
            raise ValueError("white image: the lattice fit does not converge (no regular lattice?)")
        lat = new
        if sparse:
            sparse_phase = moved >= 0.05 and iterations < 4
            continue
        last = _Round(ii, jj, m, dead, vignetted, keep, n_border, onset)
        if moved < tol_px:
            break
    if last is not None and moved >= tol_px:
        say(f"not converged after {max_iterations} rounds (last move {moved:.4f} px)")
    if last is None:
        raise ValueError(
            f"white image: the lattice fit did not converge in {max_iterations} rounds"
        )
    lat, di, dj = recentre(lat, pp)
    return _result(
        img,
        lat,
        prm,
        last.i - di,
        last.j - dj,
        last,
        lens_pitch_px,
        pp,
        iterations,
    )


@dataclass
class _Round:
    """One full measure–fit round: lens indices, measurements, flags and the border count."""

    i: NDArray[np.int64]
    j: NDArray[np.int64]
    m: MeasuredCentres
    dead: NDArray[np.bool_]
    vignetted: NDArray[np.bool_]
    keep: NDArray[np.bool_]
    n_border: int
    vignetting_onset_px: float


def _result(
    img: NDArray[Any],
    lat: Lattice,
    prm: CentroidParams,
    ii: NDArray[np.int64],
    jj: NDArray[np.int64],
    last: _Round,
    lens_pitch_px: float,
    pp: tuple[float, float],
    iterations: int,
) -> MlaGrid:
    image_grid = lat.grid()
    scale = image_grid.pitch_px / lens_pitch_px
    scaled = image_grid.scaled_about(pp, 1.0 / scale)
    lens_grid = LensGrid(scaled.origin_px, float(lens_pitch_px), image_grid.rotation_rad)
    m, dead, keep = last.m, last.dead, last.keep
    px, py = lat.centre(ii, jj)
    rx, ry = m.x - px, m.y - py
    status = np.full(ii.size, STATUS_OUTLIER, dtype=np.int8)
    status[last.vignetted] = STATUS_VIGNETTED
    status[dead] = STATUS_DEAD
    status[keep] = STATUS_USED
    res = np.hypot(rx[keep], ry[keep])
    radii, prof = radial_profile_normalized(img, lat, ii[keep], jj[keep], prm)
    disc = half_radius(radii, prof)
    rejected = {
        "border": last.n_border,
        "dead": int(np.sum(status == STATUS_DEAD)),
        "outlier": int(np.sum(status == STATUS_OUTLIER)),
        "vignetted": int(np.sum(status == STATUS_VIGNETTED)),
    }
    return MlaGrid(
        image_grid=image_grid,
        lens_grid=lens_grid,
        image_pitch_px=float(image_grid.pitch_px),
        lens_pitch_px=float(lens_pitch_px),
        rotation_deg=float(image_grid.rotation_deg),
        scale=float(scale),
        disc_radius_px=disc,
        principal_point_px=pp,
        n_lenses_used=int(keep.sum()),
        n_rejected=int(sum(rejected.values())),
        rejected=rejected,
        residual_rms_px=float(np.sqrt(np.mean(res**2))),
        iterations=iterations,
        background=prm.background,
        lens_i=ii.astype(np.int64),
        lens_j=jj.astype(np.int64),
        measured_x=np.asarray(m.x, dtype=np.float64),
        measured_y=np.asarray(m.y, dtype=np.float64),
        residual_x=np.asarray(rx, dtype=np.float64),
        residual_y=np.asarray(ry, dtype=np.float64),
        lens_status=status,
        vignetting_onset_px=last.vignetting_onset_px,
    )
