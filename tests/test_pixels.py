"""Pixel-format decoding: bit-exact against harvesters' own unpacking, and the spec layouts.

The reference is the unpacking code that ships with harvesters
(``harvesters.util.pfnc``: the ``expand`` of each pixel-format proxy, written by the
harvesters authors from the GenICam PFNC); it is run on the same random buffers as
ours.  The layouts are also pinned with bytes worked out by hand from the PFNC / GigE
Vision definitions, so a shared misreading would not pass either.
"""

from __future__ import annotations

import numpy as np
import pytest

from drivers.camera import bit_depth, pixel_format_name
from drivers.camera_errors import IncompleteFrame, InvalidSetting
from drivers.pixels import MONO_FORMATS, CorruptFrame, decode_mono, mono_format

harvesters_pfnc = pytest.importorskip("harvesters.util.pfnc")

PACKED = ("Mono10p", "Mono12p", "Mono10Packed", "Mono12Packed")


def reference(name: str, raw: np.ndarray) -> np.ndarray:
    """harvesters' expansion of ``raw`` (whole packing groups only)."""
    proxy = harvesters_pfnc.Dictionary.get_proxy(symbolic=name)
    return np.asarray(proxy.expand(raw.copy()), dtype=np.uint16)


@pytest.mark.parametrize("name", PACKED)
@pytest.mark.parametrize(("width", "height"), [(64, 48), (5120, 4), (1000, 3)])
def test_packed_formats_match_harvesters_bit_exactly(name: str, width: int, height: int) -> None:
    fmt = mono_format(name)
    rng = np.random.default_rng(width * height + len(name))
    raw = rng.integers(0, 256, fmt.buffer_bytes(width * height), dtype=np.uint8)
    ours = decode_mono(raw, width=width, height=height, pixel_format=name, device="t")
    theirs = reference(name, raw)[: width * height].reshape(height, width)
    assert ours.dtype == np.uint16 and ours.shape == (height, width)
    np.testing.assert_array_equal(ours, theirs)
    assert int(ours.max()) <= fmt.max_count


@pytest.mark.parametrize("name", PACKED)
def test_packed_extremes_match_harvesters(name: str) -> None:
    fmt = mono_format(name)
    for value in (0x00, 0xFF, 0xAA, 0x55):
        raw = np.full(fmt.buffer_bytes(40), value, dtype=np.uint8)
        ours = decode_mono(raw, width=8, height=5, pixel_format=name, device="t").ravel()
        np.testing.assert_array_equal(ours, reference(name, raw)[:40])


def test_mono12p_and_mono12packed_layouts_from_the_specifications() -> None:
    # pixels 0xABC and 0x123
    # PFNC Mono12p (LSB first): B0 = BC, B1 = 3A (p1 low nibble 3, p0 high nibble A), B2 = 12
    pfnc = np.array([0xBC, 0x3A, 0x12], dtype=np.uint8)
    # GigE Vision Mono12Packed: B0 = AB (p0 high 8), B1 = 3C (p1 low nibble 3, p0 low C), B2 = 12
    gige = np.array([0xAB, 0x3C, 0x12], dtype=np.uint8)
    for name, raw in (("Mono12p", pfnc), ("Mono12Packed", gige)):
        out = decode_mono(raw, width=2, height=1, pixel_format=name, device="t")
        assert out.tolist() == [[0xABC, 0x123]], name
    # the two 12-bit packings really differ: each read as the other gives other pixels
    assert decode_mono(gige, width=2, height=1, pixel_format="Mono12p", device="t").tolist() != [
        [0xABC, 0x123]
    ]


def test_mono10p_layout_from_the_specification() -> None:
    # pixels 0x3FF, 0x001, 0x200, 0x155 as one little-endian 40-bit word
    pixels = [0x3FF, 0x001, 0x200, 0x155]
    word = sum(p << (10 * k) for k, p in enumerate(pixels))
    raw = np.frombuffer(word.to_bytes(5, "little"), dtype=np.uint8)
    out = decode_mono(raw, width=4, height=1, pixel_format="Mono10p", device="t")
    assert out.tolist() == [pixels]


def test_packed_frame_with_a_partial_last_group() -> None:
    # 3 Mono10p pixels use 30 bits: 4 bytes; the group's 4th pixel is not part of the frame
    raw = np.frombuffer((0x155 | 0x2AA << 10 | 0x3FF << 20).to_bytes(4, "little"), np.uint8)
    out = decode_mono(raw, width=3, height=1, pixel_format="Mono10p", device="t")
    assert out.tolist() == [[0x155, 0x2AA, 0x3FF]]


def test_unpacked_words_are_little_endian_and_range_checked() -> None:
    words = np.array([0, 1, 4095, 0x0ABC], dtype="<u2")
    out = decode_mono(words.tobytes(), width=2, height=2, pixel_format="Mono12", device="t")
    assert out.tolist() == [[0, 1], [4095, 0x0ABC]]
    bad = np.array([0, 1, 0xFFF0, 7], dtype="<u2").tobytes()
    with pytest.raises(CorruptFrame, match=r"0xFFF0 = 65520") as info:
        decode_mono(bad, width=2, height=2, pixel_format="Mono12", device="gige://x", frame_id=9)
    assert info.value.status == "out-of-range" and isinstance(info.value, IncompleteFrame)
    with pytest.raises(CorruptFrame):
        decode_mono(
            np.array([1024], "<u2").tobytes(), width=1, height=1, pixel_format="Mono10", device="t"
        )
    # Mono16 uses every bit
    full = decode_mono(
        np.array([65535], "<u2").tobytes(), width=1, height=1, pixel_format="Mono16", device="t"
    )
    assert full.tolist() == [[65535]]


def test_short_buffers_and_unknown_formats_are_refused() -> None:
    fmt = mono_format("Mono12p")
    raw = np.zeros(fmt.buffer_bytes(100) - 1, dtype=np.uint8)
    with pytest.raises(IncompleteFrame, match="needs 150"):
        decode_mono(raw, width=10, height=10, pixel_format="Mono12p", device="t")
    with pytest.raises(InvalidSetting, match="not supported"):
        decode_mono(b"", width=1, height=1, pixel_format="RGB8", device="t")


def test_format_table_matches_harvesters_codes_and_depths() -> None:
    for name, fmt in MONO_FORMATS.items():
        assert harvesters_pfnc.dict_by_names[name] == fmt.code, name
        assert pixel_format_name(fmt.code) == name
        assert bit_depth(name) == fmt.bit_depth
