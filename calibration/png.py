"""A fast, lossless 16-bit greyscale PNG encoder (numpy + zlib).

The station writes every raw frame of a sweep as a 16-bit grey PNG
(OPTICS.md §5) while the next frame is being taken, so the encoder's CPU time
competes with the analysis and the HTTP server on a 2-core machine. OpenCV's
PNG writer spends about 190 ms on a 3000×1000 frame at zlib level 1 (row
filters chosen per row, the default deflate strategy); this one takes about
100 ms for a smaller file: the PNG "Sub" filter for every row (vectorized over
the whole image) followed by deflate with Huffman coding only, which is what
compresses noisy sensor counts (12 significant bits in 16, dark gaps between
micro-images) while skipping the string matching that finds little in noise.
``level=0`` stores the rows uncompressed (about 15 ms, 2 bytes per pixel).

The output is a standard PNG (IHDR, one IDAT, IEND) that every reader decodes
bit-exactly; it carries no gamma or colour chunks: pixel values are counts.
:func:`decode_png_gray16` reads such PNGs back about twice as fast as OpenCV (the
archive's frames are decoded for every calibration); other PNGs are left to OpenCV.
"""

from __future__ import annotations

import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any, cast

import numpy as np
from isal import isal_zlib
from numpy.typing import NDArray

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
_FILTER_NONE = 0
_FILTER_SUB = 1
_INFLATE_ERRORS: tuple[type[Exception], ...] = (cast(type[Exception], isal_zlib.error), ValueError)
"""What ISA-L's inflate raises on a damaged stream (its stub declares ``error`` an instance)."""


def _chunk(kind: bytes, data: bytes) -> bytes:
    crc = zlib.crc32(data, zlib.crc32(kind)) & 0xFFFFFFFF
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", crc)


def encode_png_gray16(image: NDArray[Any], *, level: int = 1) -> bytes:
    """PNG bytes of a 2-D array of counts in ``0..65535`` (stored as 16-bit grey).

    Args:
        image: 2-D array (height, width) of non-negative integers below 2**16.
        level: 0 stores the rows unfiltered and uncompressed (fastest); 1 filters
            each row with "Sub" and deflates with Huffman coding only (fast, the
            station's default); 2..9 filter with "Sub" and deflate at that zlib
            level with the default strategy (slower, a little smaller).
    """
    arr = np.asarray(image)
    if arr.ndim != 2:
        raise ValueError(f"a PNG image here is 2-D, got shape {arr.shape}")
    if not 0 <= level <= 9:
        raise ValueError(f"level must be 0..9, got {level}")
    height, width = arr.shape
    # big-endian 16-bit samples, as PNG stores them, one filter-type byte before each row
    samples = np.ascontiguousarray(arr, dtype=">u2").view(np.uint8).reshape(height, 2 * width)
    rows = np.empty((height, 2 * width + 1), dtype=np.uint8)
    if level == 0:
        rows[:, 0] = _FILTER_NONE
        rows[:, 1:] = samples
        compressor = zlib.compressobj(0)
    else:
        # Sub: each byte minus the byte one pixel (2 bytes) to its left, modulo 256
        rows[:, 0] = _FILTER_SUB
        rows[:, 1:3] = samples[:, :2]
        np.subtract(samples[:, 2:], samples[:, :-2], out=rows[:, 3:])
        strategy = zlib.Z_HUFFMAN_ONLY if level == 1 else zlib.Z_DEFAULT_STRATEGY
        compressor = zlib.compressobj(level, zlib.DEFLATED, 15, 9, strategy)
    idat = compressor.compress(rows.data) + compressor.flush()  # no copy of the rows
    header = struct.pack(">IIBBBBB", width, height, 16, 0, 0, 0, 0)  # 16-bit grey, no interlace
    return PNG_SIGNATURE + _chunk(b"IHDR", header) + _chunk(b"IDAT", idat) + _chunk(b"IEND", b"")


@dataclass(frozen=True)
class PngChunk:
    """One chunk of a PNG file: its type and byte offsets in the file, ``start`` at its
    length field and ``end`` past its CRC (beyond the file's end when it is truncated)."""

    kind: bytes
    start: int
    end: int

    def payload(self, data: bytes) -> memoryview:
        """The chunk's data (without length, type and CRC)."""
        return memoryview(data)[self.start + 8 : self.end - 4]

    def crc_ok(self, data: bytes) -> bool:
        """Whether the CRC-32 over the chunk's type and data matches the one it carries."""
        (crc,) = struct.unpack_from(">I", data, self.end - 4)
        return bool(isal_zlib.crc32(memoryview(data)[self.start + 4 : self.end - 4]) == crc)


def png_chunks(data: bytes) -> Iterator[PngChunk]:
    """The chunks after the signature, in file order, up to ``IEND``.

    Stops when the next chunk's 8-byte header does not fit in ``data`` (no ``IEND``: the
    caller sees the loop end without it); a chunk that runs past the end is yielded
    (``end > len(data)``) and is the last. Neither the signature nor the CRCs are checked.
    """
    pos = len(PNG_SIGNATURE)
    while pos + 8 <= len(data):
        length, kind = struct.unpack_from(">I4s", data, pos)
        chunk = PngChunk(kind, pos, pos + 12 + length)
        yield chunk
        if chunk.end > len(data) or kind == b"IEND":
            return
        pos = chunk.end


def _simple_chunks(data: bytes) -> tuple[tuple[int, ...], bytes] | None:
    """IHDR's fields and the joined IDAT payload, or None when a chunk runs past the end,
    the IHDR or an IDAT chunk fails its CRC, or IEND is missing."""
    header, idat = None, []
    for chunk in png_chunks(data):
        if chunk.end > len(data):
            return None
        if chunk.kind in (b"IHDR", b"IDAT"):
            if not chunk.crc_ok(data):
                return None
            body = chunk.payload(data)
            if chunk.kind == b"IDAT":
                idat.append(body)
            elif len(body) == 13:
                header = struct.unpack(">IIBBBBB", body)
            else:
                return None
        elif chunk.kind == b"IEND":
            return (header, b"".join(idat)) if header is not None else None
    return None


def decode_png_gray16(data: bytes) -> NDArray[np.uint16] | None:
    """The counts ``(height, width)`` of a PNG as :func:`encode_png_gray16` writes it, or None.

    Decodes 16-bit grey, non-interlaced PNGs whose rows are stored unfiltered or
    with "Sub" (the station's frames) about twice as fast as a general reader
    (ISA-L's inflate; "Sub" undone by a running sum per byte lane). Returns None for
    any other PNG (other bit depths, colour types or row filters) and for a damaged
    one (a CRC mismatch, a bad deflate stream, the wrong amount of data): the caller
    hands those to a general reader, which decodes or diagnoses them.
    """
    if not data.startswith(PNG_SIGNATURE):
        return None
    chunks = _simple_chunks(data)
    if chunks is None:
        return None
    (width, height, bits, colour, compression, filtering, interlace), stream = chunks
    if (bits, colour, compression, filtering, interlace) != (16, 0, 0, 0, 0):
        return None
    try:
        raw = isal_zlib.decompress(stream)
    except _INFLATE_ERRORS:
        return None
    row_bytes = 2 * width + 1
    if width == 0 or height == 0 or len(raw) != height * row_bytes:
        return None
    rows = np.frombuffer(raw, dtype=np.uint8).reshape(height, row_bytes)
    kinds = rows[:, 0]
    if np.any(kinds > _FILTER_SUB):
        return None
    samples = rows[:, 1:].reshape(height, width, 2)
    # Sub: each byte plus the decoded byte one pixel (2 bytes) to its left, modulo 256
    if np.all(kinds == _FILTER_SUB):
        samples = np.cumsum(samples, axis=1, dtype=np.uint8)
    elif np.any(kinds == _FILTER_SUB):
        sub = kinds == _FILTER_SUB
        samples = samples.copy()
        samples[sub] = np.cumsum(samples[sub], axis=1, dtype=np.uint8)
    return samples.view(">u2")[:, :, 0].astype(np.uint16)


__all__ = ["PNG_SIGNATURE", "PngChunk", "decode_png_gray16", "encode_png_gray16", "png_chunks"]
