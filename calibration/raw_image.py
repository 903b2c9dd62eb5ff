"""Decoding raw frames that a lab brings to a calibration: 8- or 16-bit PNG or TIFF.

:func:`decode_raw` turns the bytes of an image file into a 2-D array of sensor
counts (``uint8``, ``uint16`` or ``float32``, as stored), and raises
:class:`RawImageError` with one line naming the problem (empty, not a PNG or
TIFF, truncated or damaged, no pixels). Colour images (a debayered export, say)
are converted to grey with OpenCV's luma weights; an alpha channel is dropped.
:func:`read_raw_file` does the same for a path.

Unlike :func:`calibration.archive.read_image` (the archive's own frames, whose
size and bit depth the manifest fixes), nothing is assumed about the size here:
the caller checks the frame against the calibration
(:func:`calibration.raw_render.check_frame`).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from .png import PNG_SIGNATURE, png_chunks

TIFF_MAGICS = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")


class RawImageError(ValueError):
    """The image cannot be used as a raw frame (the message says why, in one line)."""


def image_kind(data: bytes) -> str | None:
    """``"png"``, ``"tiff"`` or None, from the file's signature."""
    if data.startswith(PNG_SIGNATURE):
        return "png"
    if data[:4] in TIFF_MAGICS:
        return "tiff"
    return None


def decode_raw(data: bytes, *, name: str = "the image") -> NDArray[Any]:
    """A raw frame (2-D array of counts) from the bytes of a PNG or TIFF file.

    ``name`` is used in messages (a file name, ``"the uploaded image"``).
    Raises :class:`RawImageError`.
    """
    if not data:
        raise RawImageError(f"{name} is empty (0 bytes)")
    kind = image_kind(data)
    if kind is None:
        raise RawImageError(
            f"{name} is not a PNG or TIFF file (it starts with {data[:8]!r}); "
            "export the raw frame as an 8- or 16-bit grey PNG or TIFF"
        )
    if kind == "png":
        problem = png_problem(data)
        if problem is not None:
            raise RawImageError(f"{name} is a {problem}: copy it again from the camera")
    log = cv2.utils.logging
    level = log.getLogLevel()
    log.setLogLevel(log.LOG_LEVEL_ERROR)  # the message below says it in one line
    try:
        image = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    finally:
        log.setLogLevel(level)
    if image is None or image.size == 0:
        raise RawImageError(
            f"{name} is a damaged or truncated {kind.upper()} file ({len(data)} bytes): "
            "it cannot be decoded"
        )
    return _to_grey(np.asarray(image), name)


def read_raw_file(path: str | os.PathLike[str]) -> NDArray[Any]:
    """:func:`decode_raw` of a file; a missing or unreadable file is a :class:`RawImageError`."""
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise RawImageError(f"{p}: no such file") from None
    except IsADirectoryError:
        raise RawImageError(f"{p} is a directory, not an image file") from None
    except OSError as exc:
        raise RawImageError(f"{p}: cannot be read ({exc.strerror or exc})") from None
    return decode_raw(data, name=str(p))


def png_problem(data: bytes) -> str | None:
    """What is wrong with a PNG's chunk structure (None: intact).

    Walks every chunk (length, type, data, CRC-32) from the signature to ``IEND``:
    a chunk that runs past the end is a truncated file, a CRC mismatch a damaged
    one. Checked before decoding, so that libpng never sees (and never prints
    about) a broken file.
    """
    n = len(data)
    for k, chunk in enumerate(png_chunks(data)):
        if chunk.end > n:
            return f"truncated PNG file ({n} bytes; chunk {chunk.kind!r} needs {chunk.end})"
        if k == 0 and chunk.kind != b"IHDR":
            return "damaged PNG file (the first chunk is not IHDR)"
        if not chunk.crc_ok(data):
            kind = chunk.kind.decode("latin-1")
            return f"damaged PNG file (CRC error in chunk {kind} at byte {chunk.start})"
        if chunk.kind == b"IEND":
            return None
    return f"truncated PNG file ({n} bytes, no IEND chunk)"


def _to_grey(image: NDArray[Any], name: str) -> NDArray[Any]:
    if image.ndim == 2:
        return image
    if image.ndim == 3 and image.shape[2] in (3, 4):
        code = cv2.COLOR_BGRA2GRAY if image.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        return np.asarray(cv2.cvtColor(image, code))
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    raise RawImageError(f"{name} has an unsupported pixel layout {image.shape}")


__all__ = ["RawImageError", "decode_raw", "image_kind", "png_problem", "read_raw_file"]
