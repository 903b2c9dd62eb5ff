"""Monochrome GenICam pixel formats: names, PFNC codes, bit depths and vectorized decoding.

Layouts (GenICam PFNC 2.x and the GigE Vision 2.x specification, "Pixel Formats"):

* ``Mono8``: one byte per pixel.
* ``Mono10``, ``Mono12``, ``Mono14``, ``Mono16``: one little-endian 16-bit word per
  pixel, the value in the low bits (``Mono12``: 0..4095).  A value above the declared
  depth (``0xFFF0`` in a Mono12 frame) is not a pixel: :class:`CorruptFrame`.
* ``Mono10p`` (PFNC "p" = packed, LSB first): the image is one continuous little-endian
  bit stream, 10 bits per pixel with no padding between lines; 4 pixels in 5 bytes,
  pixel k of a group is bits ``10k .. 10k+9`` of the 40-bit little-endian group.
* ``Mono12p``: the same with 12 bits: 2 pixels in 3 bytes,
  ``p0 = B0 | (B1 & 0x0F) << 8``, ``p1 = (B1 >> 4) | B2 << 4``.
* ``Mono12Packed`` (GigE Vision, not PFNC "p"): 2 pixels in 3 bytes, the 8 *most*
  significant bits of each pixel in bytes 0 and 2, both low nibbles in byte 1:
  ``p0 = B0 << 4 | (B1 & 0x0F)``, ``p1 = B2 << 4 | (B1 >> 4)``.
* ``Mono10Packed`` (GigE Vision): like Mono12Packed with 2-bit low parts:
  ``p0 = B0 << 2 | (B1 & 0x03)``, ``p1 = B2 << 2 | ((B1 >> 4) & 0x03)``.

Decoded frames are ``(height, width)`` arrays: uint8 for Mono8, uint16 (right-aligned
counts) for everything else.  Decoding is numpy only: a packed buffer is read as one
machine word per pixel group through a strided view (no Python loop, no per-byte
temporaries), so a 5120 x 5120 Mono12p frame decodes in tens of milliseconds
(``python -m bench camera`` prints the throughput per format).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from drivers.camera_errors import IncompleteFrame, InvalidSetting


@dataclass(frozen=True)
class MonoFormat:
    """One monochrome pixel format.

    Attributes:
        name: PFNC / GigE Vision name (``"Mono12p"``).
        code: PFNC code (bits 16..23: bits per pixel in the buffer).
        bit_depth: significant bits per pixel.
        group_bytes: bytes of one packing group (0 for unpacked formats).
        group_pixels: pixels of one packing group (0 for unpacked formats).
    """

    name: str
    code: int
    bit_depth: int
    group_bytes: int = 0
    group_pixels: int = 0

    @property
    def packed(self) -> bool:
        """True for the packed formats (several pixels share bytes)."""
        return self.group_bytes > 0

    @property
    def bits_per_pixel(self) -> int:
        """Bits one pixel occupies in the buffer (8, 10, 12 or 16)."""
        return (self.code >> 16) & 0xFF

    def buffer_bytes(self, pixels: int) -> int:
        """Bytes a frame of ``pixels`` pixels occupies (the last group may be partial)."""
        if not self.packed:
            return pixels * (1 if self.bit_depth == 8 else 2)
        return -(-pixels * self.bits_per_pixel // 8)

    @property
    def max_count(self) -> int:
        """Largest legal count (4095 for the 12-bit formats)."""
        return (1 << self.bit_depth) - 1


MONO_FORMATS: dict[str, MonoFormat] = {
    f.name: f
    for f in (
        MonoFormat("Mono8", 0x01080001, 8),
        MonoFormat("Mono10", 0x01100003, 10),
        MonoFormat("Mono12", 0x01100005, 12),
        MonoFormat("Mono14", 0x01100025, 14),
        MonoFormat("Mono16", 0x01100007, 16),
        MonoFormat("Mono10p", 0x010A0046, 10, 5, 4),
        MonoFormat("Mono12p", 0x010C0047, 12, 3, 2),
        MonoFormat("Mono10Packed", 0x010C0004, 10, 3, 2),
        MonoFormat("Mono12Packed", 0x010C0006, 12, 3, 2),
    )
}
"""The formats the drivers decode, by name."""

FORMATS_BY_CODE: dict[int, MonoFormat] = {f.code: f for f in MONO_FORMATS.values()}


class CorruptFrame(IncompleteFrame):
    """A frame whose pixel values cannot be right: a count above the declared bit depth
    (a Mono12 word of 0xFFF0), i.e. left-aligned data or a wrong PixelFormat."""

    default_hint = (
        "the camera's PixelFormat and data alignment (some cameras send MSB-aligned data "
        "in Mono10/Mono12 words; choose the packed format or Mono16 instead)"
    )


def mono_format(name: str) -> MonoFormat:
    """The :class:`MonoFormat` of ``name``; ``InvalidSetting`` for a format not decoded."""
    try:
        return MONO_FORMATS[name]
    except KeyError:
        raise InvalidSetting(
            f"pixel format {name!r} is not supported by the drivers",
            hint=f"use one of {', '.join(MONO_FORMATS)}",
        ) from None


def format_name(code_or_name: int | str) -> str:
    """PFNC name from a PFNC code (or pass a name through); unknown codes as hex."""
    if isinstance(code_or_name, str):
        return code_or_name
    known = FORMATS_BY_CODE.get(code_or_name)
    return known.name if known is not None else f"0x{code_or_name:08x}"


def _group_words(raw: np.ndarray, fmt: MonoFormat, groups: int) -> np.ndarray:
    """One little-endian machine word per packing group (uint32 for 3-byte groups, uint64
    for 5-byte groups), read through a strided view; the bytes past a group are masked
    off by the caller.  The last groups, whose word would read past the buffer, come
    from a small zero-padded copy."""
    word = np.dtype("<u4") if fmt.group_bytes <= 4 else np.dtype("<u8")
    stride = fmt.group_bytes
    inside = max(0, min(groups, (raw.size - word.itemsize) // stride + 1)) if raw.size else 0
    words = np.empty(groups, dtype=word)
    if inside:
        view = np.ndarray((inside,), dtype=word, buffer=raw, offset=0, strides=(stride,))
        words[:inside] = view
    if inside < groups:
        tail = np.zeros((groups - inside) * stride + word.itemsize, dtype=np.uint8)
        rest = raw[inside * stride : groups * stride]
        tail[: rest.size] = rest
        words[inside:] = np.ndarray(
            (groups - inside,), dtype=word, buffer=tail, offset=0, strides=(stride,)
        )
    return words


def unpack(raw: np.ndarray, fmt: MonoFormat, pixels: int) -> np.ndarray:
    """Decode ``pixels`` pixels of a packed format from the uint8 array ``raw`` (1-D uint16).

    ``raw`` must hold at least ``fmt.buffer_bytes(pixels)`` bytes.
    """
    per = fmt.group_pixels
    groups = -(-pixels // per)
    words = _group_words(raw, fmt, groups)
    out = np.empty(groups * per, dtype=np.uint16)
    if fmt.name in ("Mono10p", "Mono12p"):  # LSB-first bit stream
        bits = fmt.bit_depth
        mask = words.dtype.type(fmt.max_count)
        for k in range(per):
            out[k::per] = (words >> words.dtype.type(bits * k)) & mask
    else:  # GigE Vision Mono10Packed / Mono12Packed: high bits in bytes 0 and 2
        low_bits = fmt.bit_depth - 8
        low_mask = np.uint32((1 << low_bits) - 1)
        out[0::2] = ((words & np.uint32(0xFF)) << np.uint32(low_bits)) | (
            (words >> np.uint32(8)) & low_mask
        )
        out[1::2] = (((words >> np.uint32(16)) & np.uint32(0xFF)) << np.uint32(low_bits)) | (
            (words >> np.uint32(12)) & low_mask
        )
    return out[:pixels]


def decode_mono(
    data: bytes | memoryview | np.ndarray,
    *,
    width: int,
    height: int,
    pixel_format: str,
    device: str,
    frame_id: int | None = None,
    copy: bool = True,
    check_range: bool = True,
) -> np.ndarray:
    """Turn a transfer buffer into a ``(height, width)`` array (see the module notes).

    Raises ``InvalidSetting`` for a format the drivers do not decode, ``IncompleteFrame``
    if the buffer is shorter than the frame needs, :class:`CorruptFrame` when an
    unpacked Mono10/12/14 word exceeds the declared depth (``check_range``).  With
    ``copy=False`` and a writable uint8 array (already a private copy) an unpacked
    result may be a view of it.
    """
    fmt = mono_format(pixel_format)
    pixels = width * height
    need = fmt.buffer_bytes(pixels)
    raw = data.reshape(-1).view(np.uint8) if isinstance(data, np.ndarray) else None
    if raw is None:
        raw = np.frombuffer(data, dtype=np.uint8)
        copy = True
    if raw.size < need:
        raise IncompleteFrame(
            f"frame {frame_id} holds {raw.size} bytes, {width}x{height} {pixel_format} needs {need}",
            status="size-mismatch",
            frame_id=frame_id,
            device=device,
            hint="the payload size / ROI settings; a frame was cut short",
        )
    if fmt.packed:
        return unpack(raw, fmt, pixels).reshape(height, width)
    if fmt.bit_depth == 8:
        result = raw[:need].reshape(height, width)
    else:
        result = raw[:need].view("<u2").reshape(height, width).astype(np.uint16, copy=False)
    if copy or not result.flags.writeable or not result.flags.c_contiguous:
        result = result.copy()
    if check_range and 8 < fmt.bit_depth < 16:
        check_counts(result, fmt, device=device, frame_id=frame_id)
    return result


def check_counts(
    pixels: np.ndarray, fmt: MonoFormat, *, device: str, frame_id: int | None = None
) -> None:
    """Raise :class:`CorruptFrame` if any count exceeds ``fmt``'s bit depth."""
    top = int(pixels.max()) if pixels.size else 0
    if top <= fmt.max_count:
        return
    bad = int(np.count_nonzero(pixels > fmt.max_count))
    y, x = np.unravel_index(int(np.argmax(pixels > fmt.max_count)), pixels.shape)
    first = int(pixels[y, x])
    raise CorruptFrame(
        f"frame {frame_id}: {bad} {fmt.name} pixels exceed the {fmt.bit_depth}-bit range "
        f"0..{fmt.max_count} (first at x={x}, y={y}: 0x{first:04X} = {first}); "
        "not a valid frame",
        status="out-of-range",
        frame_id=frame_id,
        device=device,
    )


__all__ = [
    "FORMATS_BY_CODE",
    "MONO_FORMATS",
    "CorruptFrame",
    "MonoFormat",
    "check_counts",
    "decode_mono",
    "format_name",
    "mono_format",
    "unpack",
]
