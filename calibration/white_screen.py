"""Screens of a white (flat-field) image before and during the MLA fit.

:func:`validate_white` refuses what cannot be a white image of this camera (wrong shape
or dtype, too small for the lattice fit, NaN, uniform); :func:`check_white` refuses
micro-images that do not look like a flat field's (too many dark ones: a lens cap or a
board frame; too many unevenly lit: a scene). Both raise ``ValueError`` with a
specific message.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
from numpy.typing import NDArray

MIN_PERIODS = 4
"""The white image must span this many micro-image pitches per axis."""


def validate_white(white: NDArray[Any], lens_pitch_px: float) -> NDArray[Any]:
    img = np.asarray(white)
    if img.ndim != 2:
        raise ValueError(f"white image must be 2-D (a single grey channel), got shape {img.shape}")
    if not (np.issubdtype(img.dtype, np.integer) or np.issubdtype(img.dtype, np.floating)):
        raise ValueError(f"white image has unsupported dtype {img.dtype}")
    if not math.isfinite(lens_pitch_px) or lens_pitch_px < 4:
        raise ValueError(f"lens_pitch_px = {lens_pitch_px} must be a finite number >= 4 px")
    need = int(math.ceil(MIN_PERIODS * 1.2 * lens_pitch_px))
    if min(img.shape) < need:
        raise ValueError(
            f"white image {img.shape[1]}x{img.shape[0]} px is too small: the lattice fit needs "
            f"at least {need} px in each dimension ({MIN_PERIODS} micro-images of "
            f"~{lens_pitch_px:.1f} px per axis)"
        )
    if np.issubdtype(img.dtype, np.floating) and not np.isfinite(img).all():
        raise ValueError("white image contains NaN or infinite values")
    sub = img[::4, ::4]
    lo, hi = float(sub.min()), float(sub.max())
    if hi <= lo:
        raise ValueError(
            f"white image is uniform (every pixel = {lo:g}): black, saturated or blank, "
            "not a flat-field image"
        )
    return img


def check_white(
    dead: NDArray[np.bool_],
    spread: NDArray[np.float64],
    max_dark_fraction: float,
    max_nonflat_fraction: float,
) -> None:
    """``ValueError`` unless the micro-images look like those of a flat field."""
    dark = float(np.mean(dead))
    if dark > max_dark_fraction:
        raise ValueError(
            f"not a white (flat-field) image: {100 * dark:.0f}% of the micro-images are dark "
            "(a board frame, a lens cap or a dark frame?)"
        )
    lit = spread[~dead]
    if lit.size == 0:
        return
    typical = float(np.median(lit))
    nonflat = float(np.mean(lit > max(3.0 * typical, 0.05)))
    if typical > 0.1 or nonflat > max_nonflat_fraction:
        raise ValueError(
            f"not a white (flat-field) image: {100 * max(nonflat, float(typical > 0.1)):.0f}% "
            f"of the micro-images are not uniformly lit (median variation {100 * typical:.1f}%; "
            "a board or scene frame?)"
        )
