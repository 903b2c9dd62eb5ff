"""The 16-bit grey PNG encoder and fast decoder against the PNG specification and OpenCV."""

from __future__ import annotations

import struct
import zlib

import cv2
import numpy as np
import pytest
from numpy.testing import assert_array_equal

from calibration.archive_images import decode_image
from calibration.png import decode_png_gray16, encode_png_gray16

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"  # PNG specification, section 5.2


def chunks(data: bytes) -> list[tuple[bytes, bytes]]:
    """(type, payload) of every chunk; asserts the signature and every CRC."""
    assert data[:8] == PNG_SIGNATURE
    out, pos = [], 8
    while pos < len(data):
        (length,) = struct.unpack(">I", data[pos : pos + 4])
        kind, payload = data[pos + 4 : pos + 8], data[pos + 8 : pos + 8 + length]
        (crc,) = struct.unpack(">I", data[pos + 8 + length : pos + 12 + length])
        assert crc == zlib.crc32(kind + payload) & 0xFFFFFFFF, kind
        out.append((kind, payload))
        pos += 12 + length
    return out


def decode_by_the_spec(data: bytes) -> np.ndarray:
    """A minimal decoder written from the PNG specification (filters None and Sub)."""
    parts = chunks(data)
    assert [k for k, _ in parts] == [b"IHDR", b"IDAT", b"IEND"]
    width, height, depth, colour, comp, filt, interlace = struct.unpack(">IIBBBBB", parts[0][1])
    assert (depth, colour, comp, filt, interlace) == (16, 0, 0, 0, 0)
    raw = np.frombuffer(zlib.decompress(parts[1][1]), dtype=np.uint8).reshape(height, -1)
    out = np.empty((height, 2 * width), dtype=np.uint8)
    for y in range(height):
        kind, line = raw[y, 0], raw[y, 1:].astype(np.int64)
        if kind == 0:
            out[y] = line
        elif kind == 1:  # Sub: add the reconstructed byte one pixel (2 bytes) to the left
            rec = line.copy()
            for x in range(2, rec.size):
                rec[x] = (rec[x] + rec[x - 2]) % 256
            out[y] = rec
        else:
            raise AssertionError(f"unexpected filter {kind}")
    return out.view(">u2").reshape(height, width).astype(np.uint16)


@pytest.mark.parametrize("level", [0, 1, 6])
def test_round_trip_is_exact_in_both_decoders(level: int) -> None:
    rng = np.random.default_rng(level)
    image = rng.integers(0, 4096, size=(37, 53), dtype=np.uint16)
    image[0, :5] = [0, 65535, 1, 256, 65280]  # byte carries in the Sub filter
    data = encode_png_gray16(image, level=level)
    assert_array_equal(decode_by_the_spec(data), image)
    back = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    assert back.dtype == np.uint16
    assert_array_equal(back, image)


def test_sizes_and_layouts() -> None:
    for image in (
        np.array([[7]], dtype=np.uint16),  # 1x1
        np.arange(5, dtype=np.int64).reshape(5, 1) * 1000,  # one column, int64 input
        (np.arange(24, dtype=np.uint16).reshape(4, 6) * 2000)[:, ::2],  # not contiguous
        np.full((3, 4), 255, dtype=np.uint8),  # 8-bit counts stored as 16 bit
    ):
        data = encode_png_gray16(image, level=1)
        assert_array_equal(decode_by_the_spec(data), image.astype(np.uint16))


def test_level_one_compresses_noisy_12_bit_counts() -> None:
    rng = np.random.default_rng(0)
    image = rng.poisson(800.0, size=(200, 300)).astype(np.uint16)  # shot noise, 12-bit range
    stored, fast = (len(encode_png_gray16(image, level=k)) for k in (0, 1))
    assert stored > image.nbytes  # 2 bytes a pixel plus the framing
    assert fast < 0.75 * stored


def test_bad_input_is_refused() -> None:
    with pytest.raises(ValueError, match="2-D"):
        encode_png_gray16(np.zeros((2, 2, 3), dtype=np.uint16))
    with pytest.raises(ValueError, match="level"):
        encode_png_gray16(np.zeros((2, 2), dtype=np.uint16), level=10)


def _chunk(kind: bytes, payload: bytes) -> bytes:
    return (
        struct.pack(">I", len(payload))
        + kind
        + payload
        + struct.pack(">I", zlib.crc32(kind + payload))
    )


def _png(header: bytes, idat: list[bytes]) -> bytes:
    body = b"".join(_chunk(b"IDAT", part) for part in idat)
    return PNG_SIGNATURE + _chunk(b"IHDR", header) + body + _chunk(b"IEND", b"")


@pytest.mark.parametrize("level", [0, 1, 6])
def test_fast_decoder_reads_what_the_encoder_writes(level: int) -> None:
    rng = np.random.default_rng(10 + level)
    image = rng.integers(0, 65536, size=(29, 41), dtype=np.uint16)
    image[0, :5] = [0, 65535, 1, 256, 65280]  # byte carries in the Sub filter
    assert_array_equal(decode_png_gray16(encode_png_gray16(image, level=level)), image)


def test_fast_decoder_mixed_filters_and_split_data() -> None:
    """Rows alternately unfiltered and "Sub", the deflate stream split over three IDAT chunks:
    the PNG specification allows both."""
    rng = np.random.default_rng(3)
    image = rng.integers(0, 65536, size=(6, 9), dtype=np.uint16)
    samples = image.astype(">u2").view(np.uint8).reshape(6, 18)
    rows = []
    for y in range(6):
        if y % 2:
            sub = samples[y].copy()
            sub[2:] = samples[y, 2:] - samples[y, :-2]  # modulo 256 (uint8)
            rows.append(b"\x01" + sub.tobytes())
        else:
            rows.append(b"\x00" + samples[y].tobytes())
    stream = zlib.compress(b"".join(rows))
    third = len(stream) // 3
    parts = [stream[:third], stream[third : 2 * third], stream[2 * third :]]
    data = _png(struct.pack(">IIBBBBB", 9, 6, 16, 0, 0, 0, 0), parts)
    assert_array_equal(decode_with_opencv(data), image)
    assert_array_equal(decode_png_gray16(data), image)


def decode_with_opencv(data: bytes) -> np.ndarray:
    """OpenCV's reading of ``data``: the peer the fast path must agree with."""
    return cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)


def test_fast_decoder_leaves_other_pngs_to_a_general_reader() -> None:
    rng = np.random.default_rng(4)
    image = (rng.poisson(900.0, size=(40, 50)) + np.arange(50) * 40).astype(np.uint16)
    # at level 9 libpng chooses each row's filter: Up and Paeth rows among them
    ok, general = cv2.imencode(".png", image, [cv2.IMWRITE_PNG_COMPRESSION, 9])
    assert ok
    filters = np.frombuffer(zlib.decompress(chunks(general.tobytes())[1][1]), np.uint8)
    assert np.any(filters.reshape(40, -1)[:, 0] > 1)
    assert decode_png_gray16(general.tobytes()) is None
    # ... which the archive's reader then decodes with OpenCV
    read = decode_image(general.tobytes(), "g.png", expected_shape=(40, 50), bit_depth=16)
    assert_array_equal(read, image)
    ok, eight = cv2.imencode(".png", (image >> 4).astype(np.uint8))
    assert decode_png_gray16(eight.tobytes()) is None  # 8-bit
    ok, colour = cv2.imencode(".png", np.dstack([image] * 3))
    assert decode_png_gray16(colour.tobytes()) is None  # RGB
    assert decode_png_gray16(b"GIF89a" + bytes(20)) is None


def test_fast_decoder_refuses_damage() -> None:
    image = np.arange(12 * 10, dtype=np.uint16).reshape(12, 10) * 500
    data = bytearray(encode_png_gray16(image, level=1))
    idat = data.index(b"IDAT")
    damaged = bytearray(data)
    damaged[idat + 10] ^= 0xFF  # a flipped byte: the IDAT CRC no longer matches
    assert decode_png_gray16(bytes(damaged)) is None
    stream = zlib.compress(np.zeros(12 * 21, np.uint8).tobytes())
    header = struct.pack(">IIBBBBB", 10, 12, 16, 0, 0, 0, 0)
    assert decode_png_gray16(_png(header, [stream[:-6]])) is None  # cut deflate stream
    short = zlib.compress(np.zeros(11 * 21, np.uint8).tobytes())
    assert decode_png_gray16(_png(header, [short])) is None  # one row missing
    assert decode_png_gray16(bytes(data[:-12])) is None  # no IEND
    assert decode_png_gray16(bytes(data)) is not None
