"""Pixels the sensor clipped: at its full scale, next to another one that is.

A sensor clips where the light exceeds its full scale (``2**bit_depth − 1``
counts): a bright region then reads flat at that value. A single pixel at full
scale among lower ones is a defect (stuck or hot), not clipping, and is not
counted: a defective pixel would otherwise make every edge it touches, and a white
image with a few of them, look overexposed.

A white image is refused (:class:`OverexposedWhiteError`) when more than
:data:`WHITE_CLIPPED_LIMIT` of its lit pixels are clipped: its micro-images are then
discs with flat tops, whose centres, pitch and shading the calibration would read as
if they were not clipped (mcsim's 50 px camera, 2026-12-05/06: 20 % of the lit pixels
clipped changed nothing measurable, 57 % moved the pitch by -6.7e-5 and b by -0.21 % at
12 sigma with nothing but a warning).
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray


def clipped_at(
    image: NDArray[Any], rows: NDArray[np.integer], columns: NDArray[np.integer], clip: float
) -> NDArray[np.bool_]:
    """Whether each pixel ``image[rows, columns]`` (any shape of index arrays) is clipped:
    at ``clip`` counts or above with at least one of its four neighbours there too."""
    height, width = image.shape
    at_clip = image[rows, columns] >= clip
    if not at_clip.any():
        return at_clip
    r, c = rows[at_clip], columns[at_clip]
    neighbour = np.zeros(r.shape, dtype=bool)
    for dr, dc in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        rr, cc = r + dr, c + dc
        inside = (rr >= 0) & (rr < height) & (cc >= 0) & (cc < width)
        hit = np.zeros(r.shape, dtype=bool)
        hit[inside] = image[rr[inside], cc[inside]] >= clip
        neighbour |= hit
    out = np.zeros(at_clip.shape, dtype=bool)
    out[at_clip] = neighbour
    return out


WHITE_CLIPPED_LIMIT = 0.05
"""The largest fraction of a white image's lit pixels that may be clipped. A flat field is
exposed below full scale; this leaves room for a few bright micro-images' tops."""


class OverexposedWhiteError(ValueError):
    """The white image is clipped over more than :data:`WHITE_CLIPPED_LIMIT` of its lit
    pixels (the message gives the fraction and the full scale, and what to do)."""


def check_white_exposure(white: NDArray[Any], max_count: float) -> float:
    """The white image's clipped fraction (:func:`clipped_fraction`);
    :class:`OverexposedWhiteError` when it exceeds :data:`WHITE_CLIPPED_LIMIT`."""
    fraction = clipped_fraction(white, max_count)
    if fraction > WHITE_CLIPPED_LIMIT:
        raise OverexposedWhiteError(
            f"the white image is overexposed: {100 * fraction:.1f} % of its lit pixels are at "
            f"full scale ({max_count:.0f} counts), more than {100 * WHITE_CLIPPED_LIMIT:.0f} %; "
            "its micro-images' centres, pitch (and so b) and shading would be measured on "
            "clipped discs: record the white image again with a lower exposure or gain"
        )
    return fraction


def clipped_fraction(white: NDArray[Any], max_count: float) -> float:
    """The fraction of the white image's lit pixels (above half its 99.9th percentile) that
    are clipped (:func:`clipped_at`): 0 for a white exposed below full scale ``max_count``."""
    img = np.asarray(white)
    if not img.max() >= max_count:
        return 0.0
    # the lit level from a sample of the pixels (a full-size white has 26 M of them)
    step = max(1, int(np.sqrt(img.size / 1e6)))
    lit = img > 0.5 * float(np.percentile(img[::step, ::step], 99.9))
    n_lit = int(np.count_nonzero(lit))
    if not n_lit:
        return 0.0
    rows, columns = np.nonzero(img >= max_count)
    clipped = clipped_at(img, rows, columns, max_count)
    return float(np.count_nonzero(clipped)) / n_lit
