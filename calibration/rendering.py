"""Georgiev–Lumsdaine patch rendering of focused-plenoptic raw frames, and a seam score.

Patch rendering (full-resolution rendering): from every micro-image take a
square patch of ``p`` sensor pixels centred on the micro-image centre, sampled
along the lattice axes ``e1``, ``e2`` (so an MLA rotation is undone), resample it
to ``n = out_patch_px`` output pixels with bilinear interpolation, and tile the
patches in lattice order: lens ``(i, j)`` fills output tile column ``i - i_min``,
tile row ``j - j_min``. Conventions follow ``shared/OPTICS.md``: pixel centres at
integer coordinates, arrays indexed ``[y, x]``, all sizes in sensor pixels.

Orientation (Keplerian mode). Inside a micro-image the board is upright (board
+X is sensor +x), but neighbouring micro-images step through the *inverted*
main image: the lens to the +x side shows board content at smaller X. Tiling
upright patches in lattice order can therefore never join up. Each patch is
rotated by 180° (flipped along both ``e1`` and ``e2``) before tiling, and the
rendered image then has the orientation of the main image, like the sensor
image of a conventional camera: **the board appears inverted** (board +X
towards rendered -x, board +Y towards rendered -y). ``np.rot90(img, 2)`` shows
it upright. ``tests/test_rendering.py`` checks this on simulated frames.

Which patch size joins the patches seamlessly. A main-image point at lateral
position ``r`` is imaged by lens ``m`` to ``m + (m - r)·Q`` (OPTICS.md §1), so
it moves by ``(1 + Q)·D/δ`` pixels from one micro-image to the next, while the
micro-image centres (the patch centres) are ``μ = (L + b)/L · D/δ`` apart. Its
position relative to the patch centre therefore moves by
``(1 + Q)·D/δ - μ = p - (μ - D/δ)`` pixels per lens, and that is the patch size
that renders without seams, with ``p = Q·D/δ`` the patch size of ESIF Eq. 4
(``p`` is exact only for a main lens infinitely far from the MLA, ``μ = D/δ``).
:func:`seamless_patch_px` converts; with the paper's optics at the focus plane
``p = 20`` px, ``μ - D/δ = 5.49`` px, and the seam-free patch is 14.51 px.

Seam score: :func:`seam_score` compares the discontinuity across tile borders
with the same measure inside tiles (about 1 when seam-free, larger is worse);
:func:`seam_scan` scores a range of patch sizes and :func:`best_patch_size`
finds the minimum, so a calibrated ``p`` can be checked on any raw frame.
"""

from __future__ import annotations

from collections.abc import Sequence

import cv2
import numpy as np
from numpy.typing import NDArray

from .lens_grid import LensGrid

Region = tuple[int, int, int, int]
"""A raw-frame window ``(x, y, width, height)`` in pixels."""


def seamless_patch_px(patch_px: float, *, lens_pitch_px: float, image_pitch_px: float) -> float:
    """Rendering patch size (px) that joins patches without seams, from the ESIF ``p = Q·D/δ``.

    ``lens_pitch_px`` is ``D/δ`` (lens-centre pitch), ``image_pitch_px`` the
    micro-image-centre pitch ``μ``; the result is ``p - (μ - D/δ)`` (module
    docstring).
    """
    return float(patch_px) - (float(image_pitch_px) - float(lens_pitch_px))


def _lens_box(
    grid: LensGrid, width: int, height: int, reach_px: float
) -> tuple[int, int, int, int] | None:
    """Largest index box ``(i0, i1, j0, j1)`` (inclusive) of patches inside ``width × height``.

    ``grid`` is in window coordinates; ``reach_px`` is the largest distance of a
    sample from its micro-image centre. ``None`` when no lens fits.
    """
    ii, jj = grid.indices_in(width, height, margin_px=0.0)
    if ii.size == 0:
        return None
    i0, i1, j0, j1 = int(ii.min()), int(ii.max()), int(jj.min()), int(jj.max())
    ib, jb = np.meshgrid(
        np.arange(i0, i1 + 1, dtype=np.float64),
        np.arange(j0, j1 + 1, dtype=np.float64),
        indexing="ij",
    )
    cx, cy = grid.centre(ib, jb)
    ok = (
        (cx - reach_px >= 0)
        & (cx + reach_px <= width - 1)
        & (cy - reach_px >= 0)
        & (cy + reach_px <= height - 1)
    )
    return _trim_box(ok, i0, j0)


def _trim_box(ok: NDArray[np.bool_], i0: int, j0: int) -> tuple[int, int, int, int] | None:
    """Shrink a boolean ``[i, j]`` validity box until all of it is valid (greedy, borders)."""
    lo_i, hi_i, lo_j, hi_j = 0, ok.shape[0], 0, ok.shape[1]
    while lo_i < hi_i and lo_j < hi_j:
        sub = ok[lo_i:hi_i, lo_j:hi_j]
        if sub.all():
            return (i0 + lo_i, i0 + hi_i - 1, j0 + lo_j, j0 + hi_j - 1)
        bad = {
            "i_lo": int((~sub[0, :]).sum()),
            "i_hi": int((~sub[-1, :]).sum()),
            "j_lo": int((~sub[:, 0]).sum()),
            "j_hi": int((~sub[:, -1]).sum()),
        }
        worst = max(bad, key=lambda k: bad[k])
        if worst == "i_lo":
            lo_i += 1
        elif worst == "i_hi":
            hi_i -= 1
        elif worst == "j_lo":
            lo_j += 1
        else:
            hi_j -= 1
    return None


def patch_maps(
    image_grid: LensGrid,
    box: tuple[int, int, int, int],
    patch_size_px: float,
    out_patch_px: int,
) -> tuple[NDArray[np.float32], NDArray[np.float32]]:
    """``cv2.remap`` maps (raw x, raw y per output pixel) for the lenses of index box ``box``.

    Output pixel ``(row, col)`` with ``col = (i - i0)·n + a``, ``row = (j - j0)·n + c``
    samples micro-image ``(i, j)`` at offset ``-((a + ½)/n - ½)·p`` along ``e1`` and
    ``-((c + ½)/n - ½)·p`` along ``e2`` (the minus signs are the 180° patch flip).
    """
    i0, i1, j0, j1 = box
    n = int(out_patch_px)
    t = -(((np.arange(n) + 0.5) / n) - 0.5) * float(patch_size_px)  # flipped sample offsets
    ni, nj = i1 - i0 + 1, j1 - j0 + 1
    # along the output columns: lens index i and offset a; along the rows: j and c
    col_i = np.repeat(np.arange(i0, i1 + 1, dtype=np.float64), n)
    col_t = np.tile(t, ni)
    row_j = np.repeat(np.arange(j0, j1 + 1, dtype=np.float64), n)
    row_t = np.tile(t, nj)
    # centre(i, j) + ta e1 + tc e2 is the lattice point at fractional index
    # (i + ta/pitch, j + tc/pitch); x and y are sums of a column term and a row term
    pitch = image_grid.pitch_px
    fi = col_i + col_t / pitch
    fj = row_j + row_t / pitch
    c, s = np.cos(image_grid.rotation_rad), np.sin(image_grid.rotation_rad)
    ox, oy = image_grid.origin_px
    x = (ox + pitch * c * fi)[None, :] + (-pitch * s * fj)[:, None]
    y = (oy + pitch * s * fi)[None, :] + (pitch * c * fj)[:, None]
    return x.astype(np.float32), y.astype(np.float32)


def render_patches(
    raw: NDArray[np.generic],
    *,
    image_grid: LensGrid,
    patch_size_px: float,
    out_patch_px: int | None = None,
    region: Region | None = None,
) -> NDArray[np.float32]:
    """Patch-render a raw frame (Georgiev–Lumsdaine); returns float32 in raw counts.

    ``image_grid`` is the micro-image-centre lattice (not the lens-centre one),
    in raw-frame pixel coordinates. ``patch_size_px`` is the patch width ``p`` on
    the sensor (may be fractional; for seam-free output use
    :func:`seamless_patch_px`); ``out_patch_px`` the tile width ``n`` in the
    output (default ``round(p)``, at least 1). ``region`` ``(x, y, width, height)``
    limits the rendering to the lenses whose whole patch lies in that raw-frame
    window, clipped to the frame (default: the whole frame). The lenses form
    the largest index box ``(i0..i1, j0..j1)`` whose patches all fit
    (:func:`render_box`); the output is ``n·(j1-j0+1)`` rows by ``n·(i1-i0+1)``
    columns, lens ``(i0, j0)`` in the top-left tile, and it is inverted with
    respect to the board (module docstring). Resampling is bilinear
    (``cv2.remap``), without a low-pass filter when ``n < p``. The input is
    not modified. ``ValueError`` when no patch fits.
    """
    arr = _check_raw(raw)
    p = float(patch_size_px)
    if not np.isfinite(p) or p <= 0:
        raise ValueError(f"patch size must be a positive number of pixels, got {patch_size_px}")
    n = max(1, int(round(p))) if out_patch_px is None else int(out_patch_px)
    if n < 1:
        raise ValueError(f"out_patch_px must be >= 1, got {out_patch_px}")
    box = render_box(arr.shape, image_grid=image_grid, patch_size_px=p, region=region)
    return _render_window(arr, image_grid, box, p, n)


def _render_window(
    arr: NDArray[np.generic],
    grid: LensGrid,
    box: tuple[int, int, int, int],
    patch_px: float,
    n: int,
) -> NDArray[np.float32]:
    """Render ``box`` from only the raw window its samples need (float32 copy of that window)."""
    x0, y0, x1, y1 = _sample_window(arr.shape, grid, box, patch_px, 2.0)
    win = np.ascontiguousarray(arr[y0:y1, x0:x1], dtype=np.float32)
    map_x, map_y = patch_maps(grid, box, patch_px, n)
    map_x -= np.float32(x0)
    map_y -= np.float32(y0)
    out = cv2.remap(
        win, map_x, map_y, interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE
    )
    return np.asarray(out, dtype=np.float32)


def _sample_window(
    shape: Sequence[int],
    grid: LensGrid,
    box: tuple[int, int, int, int],
    patch_px: float,
    pad_px: float,
) -> tuple[int, int, int, int]:
    """Raw window ``(x0, y0, x1, y1)`` (ends exclusive) holding all samples of ``box`` + a pad."""
    i0, i1, j0, j1 = box
    cx, cy = grid.centre(
        np.array([i0, i1, i0, i1], dtype=np.float64), np.array([j0, j0, j1, j1], dtype=np.float64)
    )
    reach = 0.5 * patch_px * np.sqrt(2.0) + 1.0 + pad_px
    h, w = int(shape[0]), int(shape[1])
    x0, x1 = max(0, int(np.floor(cx.min() - reach))), min(w, int(np.ceil(cx.max() + reach)) + 1)
    y0, y1 = max(0, int(np.floor(cy.min() - reach))), min(h, int(np.ceil(cy.max() + reach)) + 1)
    return x0, y0, x1, y1


def render_box(
    shape: Sequence[int],
    *,
    image_grid: LensGrid,
    patch_size_px: float,
    region: Region | None = None,
) -> tuple[int, int, int, int]:
    """Lens index box ``(i0, i1, j0, j1)`` (inclusive) that :func:`render_patches` tiles."""
    h, w = int(shape[0]), int(shape[1])
    reg = (0, 0, w, h) if region is None else tuple(int(v) for v in region)
    if len(reg) != 4:
        raise ValueError(f"region must be (x, y, width, height), got {region}")
    x0, y0, rw, rh = reg
    x1, y1 = min(w, x0 + rw), min(h, y0 + rh)
    x0, y0 = max(0, x0), max(0, y0)
    if x1 - x0 < 1 or y1 - y0 < 1:
        raise ValueError(f"region {region} does not overlap the {w}x{h} frame")
    reach = 0.5 * float(patch_size_px) * np.sqrt(2.0) + 1.0
    shifted = LensGrid(
        (image_grid.origin_px[0] - x0, image_grid.origin_px[1] - y0),
        image_grid.pitch_px,
        image_grid.rotation_rad,
    )
    box = _lens_box(shifted, x1 - x0, y1 - y0, reach)
    if box is None:
        raise ValueError(
            f"no {patch_size_px:.2f} px patch fits inside region ({x0}, {y0}, {x1 - x0}, {y1 - y0})"
        )
    return box


def _check_raw(raw: NDArray[np.generic]) -> NDArray[np.generic]:
    arr = np.asarray(raw)
    if arr.ndim != 2:
        raise ValueError(f"raw frame must be a 2-D grey image, got shape {arr.shape}")
    return arr


def _seam_sums(img: NDArray[np.float32], n: int, axis: int) -> NDArray[np.float64]:
    """Residual sums and counts along ``axis``: (seam sum, seam count, inside sum, inside count).

    With ``d[x] = I[x+1] - I[x]`` the residual of pair ``x`` is
    ``|d[x] - (d[x-1] + d[x+1])/2|``: zero for content that is locally
    quadratic, whatever its slope. Pair ``x`` is a seam when ``x + 1`` is a
    multiple of ``n``; inside stencils are those whose three pairs avoid seams.
    NaN residuals are left out.
    """
    d = np.diff(img, axis=axis)
    if axis == 0:
        d = d.T  # a view: positions along the last axis
    m = d.shape[1]
    res = d[:, 1:-1] - 0.5 * (d[:, :-2] + d[:, 2:])
    np.abs(res, out=res)
    finite = np.isfinite(res)
    if not finite.all():
        res[~finite] = 0.0
    line_sum = res.sum(axis=0, dtype=np.float64)
    line_cnt = finite.sum(axis=0)
    pos = (np.arange(1, m - 1) + 1) % n
    seam = pos == 0
    inside = (pos != 0) & (pos != 1) & (pos != n - 1)
    return np.array(
        [
            line_sum[seam].sum(),
            line_cnt[seam].sum(),
            line_sum[inside].sum(),
            line_cnt[inside].sum(),
        ],
        dtype=np.float64,
    )


def seam_score(rendered: NDArray[np.generic], *, tile_px: int) -> float:
    """Seam-artefact score of a patch-rendered image: ~1 means no seams, larger is worse.

    For every pair of neighbouring pixels ``(x, x+1)`` along a row, take the
    difference ``d = I[x+1] - I[x]`` and its *discontinuity residual*
    ``|d - (d_left + d_right)/2|`` (``d_left``, ``d_right``: the differences of
    the pairs either side), likewise along columns. The score is the mean
    residual over the pairs that straddle a tile border (``x + 1`` a multiple of
    ``tile_px``) divided by the mean over pairs whose whole stencil lies inside
    a tile, both directions pooled. A seam-free render of micro-images of equal
    brightness has the same statistics at the borders as inside (score about
    1); content that jumps at the borders (a wrong patch size) raises it.
    Brightness steps between neighbouring patches (vignetting inside the
    micro-images) add a floor that dominates on flat content: a full
    5120×5120 frame of the 10 mm board scores ~4 at the seam-free patch size
    and ~32 at the ESIF ``p`` (``bench/bench_render.py``). Compare scores of
    the same frame and tile size only.

    Why not the plain gradient ratio ``mean |d| at seams / mean |d| inside``:
    a patch slightly too large repeats about one sample of content at each
    border, which *lowers* ``|d|`` there, so that ratio is smallest at
    ``p ≈ p_true·n/(n-1)``, not at ``p_true``. The residual is insensitive to the
    local slope. Content sharper than the sampling step still favours slight
    overlaps (repeated content hides an edge from the border pair): on
    unsmoothed renders of the sharp simulated checkerboards the minimum sat
    0.3–0.4 px above the seam-free patch size (more, up to 2.7 px, for a board
    period close to the tile period); :func:`seam_scan` smooths the raw frame
    first (σ = 1.5 px), which brought it within 0.2 px. NaNs are ignored;
    ``nan`` when the image has fewer than two tiles per axis or no variation
    inside tiles.
    """
    img = np.asarray(rendered, dtype=np.float32)
    n = int(tile_px)
    if img.ndim != 2 or n < 4:
        raise ValueError("seam_score needs a 2-D image and tile_px >= 4")
    h, w = img.shape
    if w < 2 * n or h < 2 * n:
        return float("nan")
    seam_sum, seam_cnt, in_sum, in_cnt = _seam_sums(img, n, 1) + _seam_sums(img, n, 0)
    if seam_cnt == 0 or in_cnt == 0 or not in_sum > 0:
        return float("nan")
    return float((seam_sum / seam_cnt) / (in_sum / in_cnt))


def seam_scan(
    raw: NDArray[np.generic],
    *,
    image_grid: LensGrid,
    patch_sizes_px: Sequence[float] | NDArray[np.floating],
    out_patch_px: int = 20,
    region: Region | None = None,
    smooth_px: float = 1.5,
) -> NDArray[np.float64]:
    """:func:`seam_score` of patch renders at each patch size (px), one fixed tile size.

    The raw frame is first smoothed with a Gaussian of standard deviation
    ``smooth_px`` sensor pixels (0: none) so that the score's minimum is not
    biased by edges sharper than the sampling step (see :func:`seam_score`);
    every render covers the same lenses (the box of the largest patch) with
    ``out_patch_px`` output pixels per patch. Returns one score per size.
    """
    sizes = np.asarray(patch_sizes_px, dtype=np.float64)
    if sizes.size == 0:
        return np.zeros(0)
    if not np.all(np.isfinite(sizes) & (sizes > 0)):
        raise ValueError("patch sizes must be positive numbers of pixels")
    arr = _check_raw(raw)
    box = render_box(
        arr.shape, image_grid=image_grid, patch_size_px=float(sizes.max()), region=region
    )
    # smooth once: the window of the largest patch holds every smaller one
    x0, y0, x1, y1 = _sample_window(arr.shape, image_grid, box, float(sizes.max()), 0.0)
    pad = int(np.ceil(4.0 * smooth_px)) + 2 if smooth_px > 0 else 0
    wx0, wy0 = max(0, x0 - pad), max(0, y0 - pad)
    win = np.ascontiguousarray(
        arr[wy0 : min(arr.shape[0], y1 + pad), wx0 : min(arr.shape[1], x1 + pad)],
        dtype=np.float32,
    )
    if smooth_px > 0:
        win = np.asarray(cv2.GaussianBlur(win, (0, 0), float(smooth_px)), dtype=np.float32)
    scores = np.empty(sizes.size)
    for k, p in enumerate(sizes):
        mx, my = patch_maps(image_grid, box, float(p), out_patch_px)
        mx -= np.float32(wx0)
        my -= np.float32(wy0)
        out = cv2.remap(win, mx, my, interpolation=cv2.INTER_LINEAR)
        scores[k] = seam_score(out, tile_px=out_patch_px)
    return scores


def best_patch_size(
    patch_sizes_px: Sequence[float] | NDArray[np.floating],
    scores: Sequence[float] | NDArray[np.floating],
) -> float:
    """Patch size (px) at the minimum of a seam scan, refined by a parabola through 3 points."""
    p = np.asarray(patch_sizes_px, dtype=np.float64)
    s = np.asarray(scores, dtype=np.float64)
    ok = np.isfinite(s)
    if not ok.any():
        return float("nan")
    p, s = p[ok], s[ok]
    order = np.argsort(p)
    p, s = p[order], s[order]
    k = int(np.argmin(s))
    if k == 0 or k == p.size - 1:
        return float(p[k])
    x, y = p[k - 1 : k + 2], s[k - 1 : k + 2]
    c2, c1, _ = np.polyfit(x, y, 2)
    if c2 <= 0:
        return float(p[k])
    return float(np.clip(-c1 / (2 * c2), x[0], x[2]))
