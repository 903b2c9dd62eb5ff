"""Tests of calibration.archive: the lfcal-sweep/1 reader, validator and writers (real files)."""

from __future__ import annotations

import copy
import json
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from calibration.archive import (
    FORMAT,
    ArchiveError,
    ArchiveExistsError,
    BitDepthError,
    CorruptImageError,
    DiskFull,
    DuplicateFrameError,
    MissingImageError,
    NotGrayscaleError,
    SweepArchive,
    SweepManifest,
    SweepWriter,
    WrongImageSizeError,
    manifest_from_header,
    read_image,
    read_manifest,
    sha256_hex,
    validate_manifest,
)

W, H, BITS = 48, 32, 12


def header(**extra: Any) -> dict[str, Any]:
    """A small manifest header (no frames) like the simulator's ``manifest_header``."""
    out: dict[str, Any] = {
        "format": FORMAT,
        "camera": {"width": W, "height": H, "pixel_pitch_mm": 0.0025, "bit_depth": BITS},
        "optics": {"main_focal_mm": 35.0, "mla_focal_mm": 2.5, "mla_pitch_mm": 0.25},
        "board": {"square_mm": 10.0, "reference_gap_mm": 0.1},
        "rail": {"zero_object_distance_mm": 250.0, "direction": 1},
        "white": "white.png",
        "frames": [],
    }
    out.update(extra)
    return out


def image(seed: int, bits: int = BITS) -> np.ndarray:
    rng = np.random.default_rng(seed)
    img = rng.integers(0, 1 << bits, size=(H, W), dtype=np.uint16)
    img[0, 0], img[-1, -1] = 0, (1 << bits) - 1  # both ends of the range
    return img


def write_sweep(root: Path, n: int = 3, **header_extra: Any) -> Path:
    with SweepWriter.create(root, header(**header_extra)) as w:
        w.write_white(image(100))
        for i in range(n):
            w.add_frame(i, float(i), image(i), exposure_us=1000 + i)
    return root


def valid_manifest() -> dict[str, Any]:
    m = header()
    m["camera"]["principal_point_px"] = [23.5, 15.5]
    m["frames"] = [
        {"index": 0, "rail_mm": 0.0, "file": "frames/0000.png"},
        {"index": 1, "rail_mm": 1.0, "file": "frames/0001.png"},
    ]
    return m


def write_png(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(".png", img)
    assert ok
    path.write_bytes(buf.tobytes())


# ------------------------------------------------------------------ round trip


def test_round_trip_is_pixel_exact(tmp_path: Path) -> None:
    root = write_sweep(tmp_path / "sweep", n=3)
    arc = SweepArchive.open(root)
    m = arc.manifest
    assert (m.camera.width, m.camera.height, m.camera.bit_depth) == (W, H, BITS)
    assert m.camera.pp == ((W - 1) / 2, (H - 1) / 2)  # absent -> sensor centre
    assert m.indices == [0, 1, 2] and len(arc) == 3
    assert [f.file for f in m.frames] == ["frames/0000.png", "frames/0001.png", "frames/0002.png"]
    assert m.frames[2].extra == {"exposure_us": 1002}
    white = arc.white()
    assert white.dtype == np.uint16 and np.array_equal(white, image(100))
    for entry, img in arc:
        assert img.dtype == np.uint16 and img.shape == (H, W)
        assert np.array_equal(img, image(entry.index))
        assert entry.sha256 == sha256_hex((root / entry.file).read_bytes())
    assert np.array_equal(arc.frame(1), image(1))
    check = arc.check()
    assert check.ok and check.good_indices == [0, 1, 2] and check.problems() == []
    # the PNG itself is 16-bit grey with right-aligned counts
    raw = cv2.imread(str(root / "frames/0001.png"), cv2.IMREAD_UNCHANGED)
    assert raw is not None
    assert raw.dtype == np.uint16 and raw.ndim == 2 and int(raw.max()) == (1 << BITS) - 1


def test_manifest_on_disk_follows_the_format(tmp_path: Path) -> None:
    root = write_sweep(tmp_path / "s", n=1)
    obj = json.loads((root / "sweep.json").read_text())
    assert obj["format"] == "lfcal-sweep/1"
    assert obj["white"] == "white.png" and (root / "white.png").is_file()
    assert obj["frames"][0]["index"] == 0 and obj["frames"][0]["file"] == "frames/0000.png"
    assert validate_manifest(obj) == []


def test_object_distance_and_principal_point() -> None:
    m = SweepManifest.from_dict(valid_manifest())
    assert m.camera.pp == (23.5, 15.5)
    assert m.object_distance_mm(10.0) == 260.0
    obj = valid_manifest()
    obj["rail"]["direction"] = -1
    assert SweepManifest.from_dict(obj).object_distance_mm(10.0) == 240.0


def test_simulator_header_is_accepted() -> None:
    from calibration.presets import get_preset
    from calibration.sim_sweep import manifest_header

    m = manifest_from_header(manifest_header(get_preset("paper")))
    assert m.camera.width == 5120 and m.frames == []
    assert m.extra["simulated"] == {"preset": "paper"}


# ------------------------------------------------------------------ validation

CASES: list[tuple[str, Any, str]] = [
    ("format", "lfcal-sweep/2", "format: must be"),
    ("camera.width", 0, "camera.width: must be a positive integer"),
    ("camera.height", 12.5, "camera.height: must be a positive integer"),
    ("camera.pixel_pitch_mm", -0.0025, "camera.pixel_pitch_mm: must be a positive number"),
    ("camera.bit_depth", "12", 'camera.bit_depth: must be an integer 1..16, got "12"'),
    ("camera.bit_depth", 17, "camera.bit_depth: must be an integer 1..16, got 17"),
    ("camera.principal_point_px", [1.0], "camera.principal_point_px: must be [x, y]"),
    ("optics.main_focal_mm", 0, "optics.main_focal_mm: must be a positive number"),
    ("optics.mla_focal_mm", "2.5", "optics.mla_focal_mm: must be a positive number"),
    ("optics.mla_pitch_mm", None, "optics.mla_pitch_mm: must be a positive number"),
    ("board.square_mm", -10, "board.square_mm: must be a positive number"),
    ("board.reference_gap_mm", 20.0, "board.reference_gap_mm: must be smaller than"),
    ("rail.zero_object_distance_mm", "250", "rail.zero_object_distance_mm: must be a positive"),
    ("rail.direction", 2, "rail.direction: must be 1 or -1, got 2"),
    ("rail.direction", True, "rail.direction: must be 1 or -1, got true"),
    ("white", "/abs/white.png", "white: must be a relative POSIX path"),
    ("white", "../white.png", "white: must not leave the archive"),
    ("white_sha256", "abc", "white_sha256: must be 64 hex digits"),
    ("frames", {}, "frames: must be an array"),
    ("frames.0", 5, "frames[0]: must be an object"),
    ("frames.0.index", -1, "frames[0].index: must be a non-negative integer"),
    ("frames.1.index", 0, "frames[1].index: duplicate index 0"),
    ("frames.0.rail_mm", "1", "frames[0].rail_mm: must be a finite number"),
    ("frames.0.rail_mm", float("nan"), "frames[0].rail_mm: must be a finite number"),
    ("frames.1.file", "frames/0000.png", "frames[1].file: duplicate file"),
    ("frames.0.file", "white.png", "frames[0].file: is the white image"),
    ("frames.0.sha256", "xyz", "frames[0].sha256: must be 64 hex digits"),
]


def _set(obj: dict[str, Any], dotted: str, value: Any) -> None:
    *parents, last = dotted.split(".")
    node: Any = obj
    for key in parents:
        node = node[int(key)] if key.isdigit() else node[key]
    if last.isdigit():
        node[int(last)] = value
    else:
        node[last] = value


@pytest.mark.parametrize(("key", "value", "message"), CASES)
def test_each_problem_names_its_key(key: str, value: Any, message: str) -> None:
    obj = valid_manifest()
    _set(obj, key, value)
    problems = validate_manifest(obj)
    assert any(p.startswith(message) for p in problems), problems
    assert len(problems) == 1, problems


@pytest.mark.parametrize(
    "path", ["format", "camera", "camera.width", "optics.mla_pitch_mm", "rail.direction", "white"]
)
def test_missing_keys_are_reported(path: str) -> None:
    obj = valid_manifest()
    *parents, last = path.split(".")
    node: Any = obj
    for k in parents:
        node = node[k]
    del node[last]
    assert any(p.startswith(f"{path}: required key missing") for p in validate_manifest(obj))


def test_read_manifest_reports_all_problems_at_once(tmp_path: Path) -> None:
    obj = valid_manifest()
    obj["camera"]["bit_depth"] = "12"
    obj["rail"]["direction"] = 0
    del obj["optics"]
    obj["frames"][1]["index"] = 0
    (tmp_path / "sweep.json").write_text(json.dumps(obj))
    with pytest.raises(ArchiveError) as err:
        read_manifest(tmp_path)
    assert isinstance(err.value, ValueError)
    keys = [p.split(":")[0] for p in err.value.problems]
    assert keys == ["camera.bit_depth", "optics", "rail.direction", "frames[1].index"]
    for p in err.value.problems:
        assert p in str(err.value)


def test_not_an_object_and_bad_json_and_missing_file(tmp_path: Path) -> None:
    assert validate_manifest([1, 2]) == ["<root>: must be a JSON object, got [1, 2]"]
    (tmp_path / "sweep.json").write_text('{"format": "lfcal-sweep/1",\n "camera": }')
    with pytest.raises(ArchiveError, match="invalid JSON at line 2 column"):
        read_manifest(tmp_path / "sweep.json")
    with pytest.raises(ArchiveError, match="file not found"):
        read_manifest(tmp_path / "nowhere")


def test_empty_frames_list_is_valid() -> None:
    assert validate_manifest(header()) == []


# ------------------------------------------------------------------ images


def test_read_image_accepts_8_bit_png_for_8_bit_camera(tmp_path: Path) -> None:
    img8 = image(3, bits=8).astype(np.uint8)
    write_png(tmp_path / "a.png", img8)
    out = read_image(tmp_path / "a.png", expected_shape=(H, W), bit_depth=8)
    assert out.dtype == np.uint16 and np.array_equal(out, img8)
    with pytest.raises(BitDepthError, match="8-bit PNG cannot hold 12-bit"):
        read_image(tmp_path / "a.png", expected_shape=(H, W), bit_depth=12)


def test_corrupt_png(tmp_path: Path) -> None:
    (tmp_path / "junk.png").write_bytes(b"this is not a png at all")
    with pytest.raises(CorruptImageError, match="not a PNG"):
        read_image(tmp_path / "junk.png", expected_shape=(H, W), bit_depth=BITS)
    # valid structure, damaged compressed data
    write_png(tmp_path / "ok.png", image(1))
    data = bytearray((tmp_path / "ok.png").read_bytes())
    idat = data.index(b"IDAT") + 4
    data[idat : idat + 40] = bytes(40)
    (tmp_path / "bad.png").write_bytes(bytes(data))
    with pytest.raises(CorruptImageError):
        read_image(tmp_path / "bad.png", expected_shape=(H, W), bit_depth=BITS)


def test_truncated_png(tmp_path: Path) -> None:
    write_png(tmp_path / "ok.png", image(1))
    data = (tmp_path / "ok.png").read_bytes()
    for cut in (len(data) // 2, len(data) - 6):
        (tmp_path / "t.png").write_bytes(data[:cut])
        with pytest.raises(CorruptImageError, match="truncated"):
            read_image(tmp_path / "t.png", expected_shape=(H, W), bit_depth=BITS)


def test_wrong_size(tmp_path: Path) -> None:
    write_png(tmp_path / "a.png", image(1))
    with pytest.raises(WrongImageSizeError, match=f"wrong size {W}×{H} px, expected 40×{H} px"):
        read_image(tmp_path / "a.png", expected_shape=(H, 40), bit_depth=BITS)


def test_bit_depth_exceeded(tmp_path: Path) -> None:
    img = image(1)
    img[5, 5] = 5000  # > 4095
    write_png(tmp_path / "a.png", img)
    with pytest.raises(BitDepthError, match="1 pixel\\(s\\) exceed 4095"):
        read_image(tmp_path / "a.png", expected_shape=(H, W), bit_depth=12)
    assert read_image(tmp_path / "a.png", expected_shape=(H, W), bit_depth=16)[5, 5] == 5000


def test_not_grayscale(tmp_path: Path) -> None:
    rgb = np.zeros((H, W, 3), np.uint16)
    write_png(tmp_path / "rgb.png", rgb)
    with pytest.raises(NotGrayscaleError, match="RGB"):
        read_image(tmp_path / "rgb.png", expected_shape=(H, W), bit_depth=BITS)


def test_missing_image(tmp_path: Path) -> None:
    with pytest.raises(MissingImageError) as err:
        read_image(tmp_path / "nope.png", expected_shape=(H, W), bit_depth=BITS)
    assert isinstance(err.value, FileNotFoundError) and "nope.png" in str(err.value)


# ------------------------------------------------------------------ reader check


def test_missing_frame_file_is_reported_and_good_frames_remain(tmp_path: Path) -> None:
    root = write_sweep(tmp_path / "s", n=4)
    (root / "frames/0002.png").unlink()
    arc = SweepArchive.open(root)
    check = arc.check()
    assert not check.ok
    assert check.frames == {2: ["frames/0002.png: file not found"]}
    assert check.good_indices == [0, 1, 3] and check.white == []
    assert check.problems() == ["frame 2: frames/0002.png: file not found"]
    with pytest.raises(MissingImageError):
        arc.frame(2)
    assert [e.index for e, _ in arc.iter_frames(skip_bad=True)] == [0, 1, 3]
    with pytest.raises(MissingImageError):
        list(arc)


def test_check_reports_checksum_mismatch_and_damaged_files(tmp_path: Path) -> None:
    root = write_sweep(tmp_path / "s", n=3)
    write_png(root / "frames/0001.png", image(77))  # valid PNG, other content
    data = (root / "white.png").read_bytes()
    (root / "white.png").write_bytes(data[: len(data) // 2])
    write_png(root / "frames/0042.png", image(5))  # stray file
    check = SweepArchive.open(root).check()
    assert check.good_indices == [0, 2]
    assert len(check.frames[1]) == 1 and "frames/0001.png: SHA-256 mismatch" in check.frames[1][0]
    assert any("SHA-256 mismatch" in p for p in check.white)
    assert any("truncated" in p for p in check.white)
    assert check.unlisted == ["frames/0042.png"]
    fast = SweepArchive.open(root).check(decode=False)
    assert fast.good_indices == [0, 2]


def test_check_without_checksums_still_decodes(tmp_path: Path) -> None:
    root = write_sweep(tmp_path / "s", n=2)
    obj = json.loads((root / "sweep.json").read_text())
    for f in obj["frames"]:
        del f["sha256"]
    (root / "sweep.json").write_text(json.dumps(obj))
    img = image(0)
    img[0, 1] = 4096
    write_png(root / "frames/0000.png", img)
    check = SweepArchive.open(root).check()
    assert list(check.frames) == [0] and "exceed 4095" in check.frames[0][0]


# ------------------------------------------------------------------ unknown keys


def test_unknown_keys_are_preserved(tmp_path: Path) -> None:
    obj = valid_manifest()
    obj["station"] = {"job": 17}
    obj["camera"]["serial"] = "ABC123"
    obj["optics"]["designed_b_mm"] = 3.0
    obj["rail"]["port"] = "/dev/ttyUSB0"
    obj["frames"][0]["stage_xy_mm"] = [1.0, 2.0]
    m = SweepManifest.from_dict(copy.deepcopy(obj))
    assert m.extra == {"station": {"job": 17}} and m.camera.extra == {"serial": "ABC123"}
    assert m.to_dict() == obj

    # a writer keeps the header's unknown keys and adds its own per frame
    job = tmp_path / "job"
    hdr = copy.deepcopy(obj)
    hdr["frames"] = []
    w = SweepWriter.in_place(job, hdr)
    w.add_frame(4, 4.0, image(4), timestamp="2024-01-01T00:00:00Z")
    on_disk = json.loads((job / "sweep.json").read_text())
    assert on_disk["station"] == {"job": 17} and on_disk["camera"]["serial"] == "ABC123"
    assert on_disk["optics"]["designed_b_mm"] == 3.0 and on_disk["rail"]["port"] == "/dev/ttyUSB0"
    assert on_disk["frames"][0]["timestamp"] == "2024-01-01T00:00:00Z"
    # resuming and appending keeps everything
    w2 = SweepWriter.resume(job)
    w2.add_frame(5, 5.0, image(5))
    again = read_manifest(job)
    assert again.extra == {"station": {"job": 17}} and again.indices == [4, 5]
    assert again.frames[0].extra == {"timestamp": "2024-01-01T00:00:00Z"}


# ------------------------------------------------------------------ writers


class Interrupted(Exception):
    pass


def test_staged_writer_interrupted_leaves_nothing_complete(tmp_path: Path) -> None:
    final = tmp_path / "sweep"
    with pytest.raises(Interrupted), SweepWriter.create(final, header()) as w:
        w.write_white(image(100))
        w.add_frame(0, 0.0, image(0))
        raise Interrupted
    assert not final.exists()
    assert list(tmp_path.iterdir()) == []  # staging removed


def test_staged_writer_killed_without_cleanup_looks_incomplete(tmp_path: Path) -> None:
    final = tmp_path / "sweep"
    w = SweepWriter.create(final, header())
    w.write_white(image(100))
    w.add_frame(0, 0.0, image(0))
    # the process dies here: no commit, no abort
    assert not final.exists()
    (partial,) = tmp_path.iterdir()
    assert partial.name.startswith(".sweep.partial-")
    assert not (partial / "sweep.json").exists()
    with pytest.raises(ArchiveError):
        SweepArchive.open(final)
    with pytest.raises(ArchiveError):
        SweepArchive.open(partial)
    w.commit()
    assert SweepArchive.open(final).check().ok and not partial.exists()


def test_commit_requires_white(tmp_path: Path) -> None:
    w = SweepWriter.create(tmp_path / "s", header())
    w.add_frame(0, 0.0, image(0))
    with pytest.raises(ArchiveError, match="white image was not written"):
        w.commit()
    w.abort()
    assert list(tmp_path.iterdir()) == []
    with pytest.raises(ArchiveError), SweepWriter.create(tmp_path / "s", header()) as w2:
        w2.add_frame(0, 0.0, image(0))
    assert list(tmp_path.iterdir()) == []  # a failed commit on exit leaves nothing behind


def test_refuses_to_overwrite_unless_asked(tmp_path: Path) -> None:
    root = write_sweep(tmp_path / "s", n=2)
    with pytest.raises(ArchiveExistsError):
        SweepWriter.create(root, header())
    with SweepWriter.create(root, header(note="second"), overwrite=True) as w:
        w.write_white(image(200))
        w.add_frame(7, 7.0, image(7))
    arc = SweepArchive.open(root)
    assert arc.indices == [7] and arc.manifest.extra == {"note": "second"}
    assert not (root / "frames/0000.png").exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["s"]
    other = tmp_path / "other"
    other.mkdir()
    (other / "notes.txt").write_text("keep me")
    with pytest.raises(ArchiveExistsError, match="not an archive"):
        SweepWriter.create(other, header(), overwrite=True)
    with pytest.raises(ArchiveExistsError):
        SweepWriter.in_place(root, header())


def test_in_place_manifest_lists_only_complete_frames(tmp_path: Path) -> None:
    job = tmp_path / "job-1"
    w = SweepWriter.in_place(job, header())
    assert read_manifest(job).frames == []  # manifest exists from the start
    for i in range(3):
        rec = w.add_frame(i, 0.5 * i, image(i), stage_x_mm=1.0)
        assert rec.file == f"frames/{i:04d}.png"
        assert rec.sha256 == sha256_hex((job / rec.file).read_bytes())
        m = read_manifest(job)
        assert m.indices == list(range(i + 1))
        assert SweepArchive.open(job).check().good_indices == list(range(i + 1))
    w.write_white(image(100))
    assert w.commit() == job
    assert SweepArchive.open(job).check().ok
    assert not [p for p in job.rglob(".*")]  # no temporary files left


def test_duplicate_index_refused(tmp_path: Path) -> None:
    job = tmp_path / "job"
    w = SweepWriter.in_place(job, header())
    w.add_frame(0, 0.0, image(0))
    before = (job / "sweep.json").read_bytes()
    frame_before = (job / "frames/0000.png").read_bytes()
    with pytest.raises(DuplicateFrameError):
        w.add_frame(0, 1.0, image(9))
    assert (job / "sweep.json").read_bytes() == before
    assert (job / "frames/0000.png").read_bytes() == frame_before
    with pytest.raises(DuplicateFrameError):
        SweepWriter.resume(job).add_frame(0, 0.0, image(0))
    staged = SweepWriter.create(tmp_path / "s", header())
    staged.add_frame(3, 0.0, image(3))
    with pytest.raises(DuplicateFrameError):
        staged.add_frame(3, 0.0, image(3))
    staged.abort()


def test_bad_frames_are_not_recorded(tmp_path: Path) -> None:
    job = tmp_path / "job"
    w = SweepWriter.in_place(job, header())
    too_bright = image(1)
    too_bright[1, 1] = 4096
    with pytest.raises(BitDepthError):
        w.add_frame(0, 0.0, too_bright)
    with pytest.raises(WrongImageSizeError):
        w.add_frame(0, 0.0, np.zeros((H, W + 1), np.uint16))
    with pytest.raises(BitDepthError, match="integer counts"):
        w.add_frame(0, 0.0, np.zeros((H, W), np.float32))
    with pytest.raises(ValueError, match="reserved"):
        w.add_frame(0, 0.0, image(0), file="x.png")
    assert read_manifest(job).frames == [] and list((job / "frames").iterdir()) == []
    w.add_frame(0, 0.0, image(0))  # the index is still free
    assert read_manifest(job).indices == [0]


def test_disk_full_is_reported_before_writing(tmp_path: Path) -> None:
    job = tmp_path / "job"
    w = SweepWriter.in_place(job, header())
    w.add_frame(0, 0.0, image(0))
    before = (job / "sweep.json").read_bytes()
    w.reserve_bytes = 1 << 62  # no disk has that much free space
    with pytest.raises(DiskFull) as err:
        w.add_frame(1, 1.0, image(1))
    assert err.value.path == job / "frames/0001.png"
    assert err.value.needed_bytes > 1 << 62 and err.value.free_bytes < err.value.needed_bytes
    assert "frames/0001.png" in str(err.value) and str(err.value.needed_bytes) in str(err.value)
    assert isinstance(err.value, OSError)
    assert (job / "sweep.json").read_bytes() == before
    assert sorted(p.name for p in (job / "frames").iterdir()) == ["0000.png"]
    w.reserve_bytes = 0
    w.add_frame(1, 1.0, image(1))
    assert read_manifest(job).indices == [0, 1]


def test_simulated_sweep_round_trip(tmp_path: Path) -> None:
    """The simulator's frames and header go through the writer and come back unchanged."""
    from calibration.presets import get_preset, with_sweep
    from calibration.sim_sweep import fit_frame, iter_frames, manifest_header, render_white

    preset = with_sweep(fit_frame(get_preset("paper"), 256, 192), frames=3, start_mm=49.0)
    frames = list(iter_frames(preset))
    with SweepWriter.create(tmp_path / "sim", manifest_header(preset)) as w:
        w.write_white(render_white(preset))
        for index, rail, img in frames:
            w.add_frame(index, rail, img)
    arc = SweepArchive.open(tmp_path / "sim")
    assert arc.check().ok and arc.manifest.extra == {"simulated": {"preset": "paper"}}
    assert [e.rail_mm for e in arc.manifest.frames] == [49.0, 50.0, 51.0]
    assert arc.manifest.object_distance_mm(50.0) == 300.0
    for (index, _, img), (entry, back) in zip(frames, arc, strict=True):
        assert entry.index == index and np.array_equal(back, img)
