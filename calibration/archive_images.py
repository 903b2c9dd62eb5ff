"""The archive's images: 16-bit grey PNG decoding with a specific error for every defect,
encoding and SHA-256 checksums (:mod:`calibration.archive` is the archive)."""

from __future__ import annotations

import hashlib
import os
import struct
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from .archive_errors import (
    BitDepthError,
    CorruptImageError,
    MissingImageError,
    NotGrayscaleError,
    WrongImageSizeError,
)
from .png import PNG_SIGNATURE, decode_png_gray16, encode_png_gray16, png_chunks

_PNG_COLOUR_TYPES = {0: "grey", 2: "RGB", 3: "palette", 4: "grey + alpha", 6: "RGBA"}


# -------------------------------------------------------------------------- images


def png_header_problem(data: bytes) -> tuple[str | None, tuple[int, int, int, int] | None]:
    """Walk the PNG chunk structure: (problem or None, IHDR (width, height, bits, colour type))."""
    if not data.startswith(PNG_SIGNATURE):
        return "not a PNG file (bad signature)", None
    ihdr = None
    for chunk in png_chunks(data):
        if chunk.end > len(data):
            return f"truncated PNG (chunk {chunk.kind!r} runs past the end of the file)", ihdr
        if chunk.kind == b"IHDR":
            if chunk.end - chunk.start != 25:
                return "corrupt PNG (bad IHDR chunk)", None
            w, h, bits, colour = struct.unpack(">IIBB", chunk.payload(data)[:10])
            ihdr = (w, h, bits, colour)
        elif ihdr is None:
            return "corrupt PNG (first chunk is not IHDR)", None
        if chunk.kind == b"IEND":
            return None, ihdr
    return "truncated PNG (no IEND chunk)", ihdr


def decode_image(
    data: bytes,
    path: str | os.PathLike[str],
    *,
    expected_shape: tuple[int, int] | None,
    bit_depth: int,
) -> NDArray[np.uint16]:
    """Decode PNG bytes (``path`` is only used in messages); see :func:`read_image`."""
    problem, ihdr = png_header_problem(data)
    if problem is not None:
        raise CorruptImageError(path, problem)
    assert ihdr is not None
    width, height, bits, colour = ihdr
    if colour != 0:
        raise NotGrayscaleError(
            path, f"not a grayscale image (PNG colour type {_PNG_COLOUR_TYPES.get(colour, colour)})"
        )
    if expected_shape is not None and (height, width) != tuple(expected_shape):
        raise WrongImageSizeError(
            path,
            f"wrong size {width}×{height} px, expected {expected_shape[1]}×{expected_shape[0]} px",
        )
    if bits < 16 and bit_depth > bits:
        raise BitDepthError(
            path, f"{bits}-bit PNG cannot hold {bit_depth}-bit counts (a 16-bit PNG is needed)"
        )
    # the station's own frames by the fast path; any other PNG, or a damaged one, by OpenCV
    fast = decode_png_gray16(data)
    img = (
        fast
        if fast is not None
        else cv2.imdecode(np.frombuffer(data, dtype=np.uint8), cv2.IMREAD_UNCHANGED)
    )
    if img is None:
        raise CorruptImageError(path, "corrupt PNG (cannot be decoded)")
    if img.ndim != 2:
        raise NotGrayscaleError(path, f"not a grayscale image (decoded shape {img.shape})")
    out: NDArray[np.uint16] = img.astype(np.uint16, copy=False)
    limit = (1 << bit_depth) - 1
    peak = int(out.max()) if out.size else 0
    if peak > limit:
        n = int(np.count_nonzero(out > limit))
        raise BitDepthError(
            path,
            f"{n} pixel(s) exceed {limit} = 2^{bit_depth}−1 (max {peak}): wrong bit depth, "
            "or counts not right-aligned",
        )
    return out


def read_image(
    path: str | os.PathLike[str],
    *,
    expected_shape: tuple[int, int] | None,
    bit_depth: int,
) -> NDArray[np.uint16]:
    """Read a grey PNG as ``uint16`` counts of shape ``(height, width)``.

    ``expected_shape`` is ``(height, width)`` in px (None: not checked);
    ``bit_depth`` the camera's bits per pixel (values must be ≤ 2**bit_depth − 1).
    An 8-bit (or lower) PNG is accepted when ``bit_depth ≤ 8``.

    Raises :class:`MissingImageError`, :class:`CorruptImageError` (also truncated
    files), :class:`WrongImageSizeError`, :class:`BitDepthError`,
    :class:`NotGrayscaleError`.
    """
    p = Path(path)
    try:
        data = p.read_bytes()
    except FileNotFoundError:
        raise MissingImageError(p, "file not found") from None
    except IsADirectoryError:
        raise CorruptImageError(p, "is a directory, not a PNG file") from None
    except OSError as exc:
        raise CorruptImageError(p, f"cannot read: {exc.strerror or exc}") from exc
    return decode_image(data, p, expected_shape=expected_shape, bit_depth=bit_depth)


def encode_image(
    image: NDArray[Any],
    *,
    expected_shape: tuple[int, int] | None,
    bit_depth: int,
    compression: int = 1,
    name: str = "<image>",
) -> bytes:
    """Encode counts as a 16-bit grey PNG after checking shape, type and range.

    ``image`` must be a 2-D integer array of shape ``expected_shape`` (height,
    width) with values in ``0 .. 2**bit_depth − 1``; ``compression`` is the level of
    :func:`calibration.png.encode_png_gray16` (0: stored, 1: fast Huffman-only
    deflate, the default; the frames are noisy anyway).
    """
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise NotGrayscaleError(name, f"must be a 2-D grey image, got shape {arr.shape}")
    if not np.issubdtype(arr.dtype, np.integer):
        raise BitDepthError(name, f"must hold integer counts, got dtype {arr.dtype}")
    if expected_shape is not None and arr.shape != tuple(expected_shape):
        raise WrongImageSizeError(
            name,
            f"wrong size {arr.shape[1]}×{arr.shape[0]} px, "
            f"expected {expected_shape[1]}×{expected_shape[0]} px",
        )
    limit = (1 << bit_depth) - 1
    if arr.size:
        lo, hi = int(arr.min()), int(arr.max())
        if lo < 0 or hi > limit:
            raise BitDepthError(
                name, f"values {lo}..{hi} outside 0..{limit} = 2^{bit_depth}−1 (wrong bit depth?)"
            )
    return encode_png_gray16(arr, level=compression)


def sha256_hex(data: bytes) -> str:
    """SHA-256 of ``data`` as 64 lower-case hex digits."""
    return hashlib.sha256(data).hexdigest()


def file_sha256(path: str | os.PathLike[str]) -> str:
    """SHA-256 of a file's bytes as 64 lower-case hex digits (read in 1 MiB chunks)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        while chunk := fh.read(1 << 20):
            h.update(chunk)
    return h.hexdigest()
