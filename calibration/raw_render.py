"""Rendering any raw frame of a calibrated camera: checks, flat field, patch size, score.

What ``lfcal render``, ``POST /api/v1/render`` and the report share:

1. :func:`check_frame` refuses a frame that is not of the calibrated camera: a
   frame of another size, or one that does not show the calibrated micro-image
   lattice (a frame of another camera, or a result of another camera). The
   lattice test compares the brightness at the micro-image centres with the
   brightness at the lattice's dark corners (the points between four
   micro-images, where the main aperture cuts the micro-images off): on any
   frame of the calibrated camera -- board, scene, white -- the centres are far
   brighter; on a frame whose micro-images sit elsewhere (another pitch,
   rotation or origin) the two sample sets see the same mixture and the
   contrast ``(C − G)/(C + G)`` is near 0. Below :data:`MIN_LATTICE_CONTRAST`
   the frame is refused.
2. :func:`flat_field` divides by a white image of the same camera (optional):
   vignetting inside the micro-images then no longer makes brightness steps
   between neighbouring patches.
3. :func:`choose_patch` turns ``calibrated``, ``designed`` or a number, and an
   optional object distance, into the ESIF patch size ``p = Q·D/δ``
   (:class:`calibration.export_model.CalibratedCamera`).
4. :func:`render_frame_with` renders (Georgiev–Lumsdaine, the seam-free patch
   ``p − (μ − D/δ)``), turns the image upright and scores its seams:
   :func:`artefact_score` is :func:`calibration.rendering.seam_scan` at that
   patch size (raw smoothed by 1.5 px, 20 output px per patch, so scores of one
   frame at different ``p`` compare; about 1 is seam-free, larger is worse).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .export_model import CalibratedCamera
from .lens_grid import LensGrid
from .rendering import render_patches, seam_scan

MIN_LATTICE_CONTRAST = 0.15
"""Smallest centre/corner contrast of a frame of the calibrated camera (measured on
simulated frames: 0.99 on boards, scenes and whites of the camera; 0.02 on a frame
of another camera of the same size, ``tests/test_lab_render.py``)."""

SCORE_TILE_PX = 20
"""Output pixels per patch of the artefact score's renders (fixed, so that scores compare)."""


class FrameMismatch(ValueError):
    """The raw frame is not a frame of the calibrated camera (one line says why)."""


@dataclass(frozen=True)
class RenderedFrame:
    """A rendered frame and how it was made.

    Attributes:
        image: the rendered image, upright (float32, raw counts or flat-fielded).
        patch_px: the ESIF patch size ``p`` used (px).
        render_patch_px: the seam-free rendering patch ``p − (μ − D/δ)`` (px).
        tile_px: output pixels per patch.
        score: artefact score (:func:`artefact_score`); NaN when too few patches.
        lattice_contrast: the frame's centre/corner contrast (:func:`lattice_contrast`).
        render_s, score_s: wall times (s).
    """

    image: NDArray[np.float32]
    patch_px: float
    render_patch_px: float
    tile_px: int
    score: float
    lattice_contrast: float
    render_s: float
    score_s: float


def lattice_contrast(raw: NDArray[Any], grid: LensGrid) -> float:
    """``(C − G)/(C + G)``: mean brightness at the micro-image centres (``C``) against
    the lattice's corner points between four micro-images (``G``), black level (the
    0.5th percentile) removed, each a 3×3 px mean. NaN when no lens is inside.

    Only the sampled pixels are read (about 30 ms for a 5120×5120 frame)."""
    img = np.asarray(raw)
    h, w = img.shape
    margin = 0.5 * grid.pitch_px + 2.0
    ii, jj = grid.indices_in(w, h, margin_px=margin)
    if ii.size == 0:
        return float("nan")
    step = max(1, ii.size // 20000)  # 20 000 lenses are plenty
    ii, jj = ii[::step].astype(np.float64), jj[::step].astype(np.float64)
    sub = img[:: max(1, h // 512), :: max(1, w // 512)]
    black = float(np.percentile(sub, 0.5))
    offsets = np.arange(-1, 2)

    def mean_at(i: NDArray[Any], j: NDArray[Any]) -> float:
        x, y = grid.centre(i, j)
        xi = np.rint(x).astype(np.int64)[:, None, None] + offsets[None, None, :]
        yi = np.rint(y).astype(np.int64)[:, None, None] + offsets[None, :, None]
        values = img[np.clip(yi, 0, h - 1), np.clip(xi, 0, w - 1)]
        return float(values.mean(dtype=np.float64)) - black

    centre = mean_at(ii, jj)
    corner = mean_at(ii + 0.5, jj + 0.5)
    total = centre + corner
    if not total > 0:
        return 0.0
    return float((centre - corner) / total)


def check_frame(raw: NDArray[Any], camera: CalibratedCamera, *, what: str = "the frame") -> float:
    """Refuse a frame that is not of the calibrated camera; returns its lattice contrast.

    :class:`FrameMismatch` (one line) for another size or a lattice mismatch.
    """
    arr = np.asarray(raw)
    if arr.ndim != 2:
        raise FrameMismatch(f"{what} must be a 2-D grey image, got shape {arr.shape}")
    h, w = arr.shape
    if (w, h) != (camera.width, camera.height):
        raise FrameMismatch(
            f"{what} is {w}x{h} px, the calibration is for {camera.width}x{camera.height} px "
            "frames: render frames of the calibrated camera with the same ROI"
        )
    contrast = lattice_contrast(arr, camera.image_grid)
    if not contrast >= MIN_LATTICE_CONTRAST:
        raise FrameMismatch(
            f"{what} does not show the calibrated micro-image lattice (centre/corner contrast "
            f"{contrast:.2f}, a frame of this camera has more than {MIN_LATTICE_CONTRAST}): "
            "a frame of another camera, a result of another camera, or a dark frame"
        )
    return contrast


def flat_field(raw: NDArray[Any], white: NDArray[Any]) -> NDArray[np.float32]:
    """``(raw − black)/(white − black)`` where the white image is lit (above 10 % of its
    99.9th percentile), 0 in the dark rims; ``black`` is the white's 0.5th percentile."""
    r = np.asarray(raw, dtype=np.float32)
    wht = np.asarray(white, dtype=np.float32)
    if r.shape != wht.shape:
        raise FrameMismatch(
            f"the white image is {wht.shape[1]}x{wht.shape[0]} px, the frame "
            f"{r.shape[1]}x{r.shape[0]} px"
        )
    sub = wht[:: max(1, wht.shape[0] // 512), :: max(1, wht.shape[1] // 512)]
    black, top = (float(v) for v in np.percentile(sub, [0.5, 99.9]))
    lit = (wht - black) > 0.1 * (top - black)
    out = np.zeros_like(r)
    np.divide(r - black, wht - black, out=out, where=lit)
    return out


def choose_patch(
    camera: CalibratedCamera,
    choice: str | float,
    *,
    object_distance_mm: float | None = None,
    designed_px: float | None = None,
) -> float:
    """The ESIF patch size ``p`` (px) for ``choice``.

    ``"calibrated"``: ``p(u)`` of the calibrated model at ``object_distance_mm``
    (default: the focus plane, i.e. the calibrated ``p``). ``"designed"``:
    ``designed_px`` (the caller computes it from the designed optics). A number:
    that ``p``. ``ValueError`` for an impossible choice.
    """
    if isinstance(choice, int | float) and not isinstance(choice, bool):
        p = float(choice)
        if not (np.isfinite(p) and p > 0):
            raise ValueError(f"the patch size must be a positive number of pixels, got {choice}")
        return p
    if choice == "calibrated":
        if object_distance_mm is None:
            return camera.patch_px
        return camera.patch_at(object_distance_mm)
    if choice == "designed":
        if designed_px is None:
            raise ValueError(
                "the designed patch size needs the designed optics (designed b, and a)"
            )
        return float(designed_px)
    raise ValueError(f"p must be calibrated, designed or a number of pixels, got {choice!r}")


def artefact_score(raw: NDArray[Any], grid: LensGrid, render_patch_px: float) -> float:
    """Seam-artefact score of rendering ``raw`` with the rendering patch ``render_patch_px``
    (:func:`calibration.rendering.seam_scan`, 20 px per patch, 1.5 px smoothing)."""
    return float(
        seam_scan(
            raw, image_grid=grid, patch_sizes_px=[render_patch_px], out_patch_px=SCORE_TILE_PX
        )[0]
    )


def render_frame_with(
    raw: NDArray[Any],
    camera: CalibratedCamera,
    patch_px: float,
    *,
    white: NDArray[Any] | None = None,
    tile_px: int | None = None,
    score: bool = True,
    check: bool = True,
) -> RenderedFrame:
    """Check, flat-field (with ``white``), render with the ESIF patch ``patch_px`` and score.

    ``tile_px``: output pixels per patch (default: the rendering patch rounded,
    at least 4). :class:`FrameMismatch` for a frame of another camera;
    ``ValueError`` when the patch size leaves nothing to render.
    """
    contrast = check_frame(raw, camera) if check else float("nan")
    if white is not None:
        if check:
            check_frame(white, camera, what="the white image")
        data: NDArray[Any] = flat_field(raw, white)
    else:
        data = np.asarray(raw)
    render_patch = camera.seamless_patch(patch_px)
    if not render_patch > 0:
        raise ValueError(
            f"p = {patch_px:g} px gives a rendering patch of {render_patch:g} px "
            f"(p − (μ − D/δ)): nothing to render"
        )
    n = max(4, int(round(render_patch))) if tile_px is None else int(tile_px)
    t0 = time.perf_counter()
    image = render_patches(
        data, image_grid=camera.image_grid, patch_size_px=render_patch, out_patch_px=n
    )
    image = np.ascontiguousarray(np.rot90(image, 2))
    t1 = time.perf_counter()
    value = artefact_score(data, camera.image_grid, render_patch) if score else float("nan")
    t2 = time.perf_counter()
    return RenderedFrame(
        image=image,
        patch_px=float(patch_px),
        render_patch_px=float(render_patch),
        tile_px=n,
        score=value,
        lattice_contrast=contrast,
        render_s=t1 - t0,
        score_s=t2 - t1,
    )


__all__ = [
    "MIN_LATTICE_CONTRAST",
    "SCORE_TILE_PX",
    "FrameMismatch",
    "RenderedFrame",
    "artefact_score",
    "check_frame",
    "choose_patch",
    "flat_field",
    "lattice_contrast",
    "render_frame_with",
]
