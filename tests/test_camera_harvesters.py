"""The harvesters backend against a real GenTL producer: TLSimu.cti shipped by genicam 1.5.0.

TLSimu is a software simulator (no network): its mono device serves Mono8 frames up to
4096 x 4096 whose pixels are ``(x + y + frame_id) mod 256``, so every grab is checked
pixel for pixel.  It has no ExposureTime, Gain or OffsetX/Y, which exercises the
"feature missing" paths.
"""

from __future__ import annotations

import _ctypes
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from drivers import harvesters_camera
from drivers.camera import Camera, CameraSettings, Frame, Roi, create_camera
from drivers.camera_errors import (
    BackendUnavailable,
    CameraBusy,
    CameraNotFound,
    CameraTimeout,
    FeatureMissing,
    InvalidSetting,
    ProducerLoadError,
)
from drivers.harvesters_camera import HarvestersCamera

try:
    import genicam
    from harvesters.core import Harvester  # noqa: F401

    TLSIMU = Path(genicam.__file__).parent / "TLSimu.cti"
    SKIP = "" if TLSIMU.is_file() else f"{TLSIMU} missing (genicam==1.5.0 ships it)"
except ImportError as exc:  # pragma: no cover - a project dependency
    TLSIMU = Path("TLSimu.cti")
    SKIP = f"harvesters/genicam not importable: {exc}"

pytestmark = pytest.mark.skipif(bool(SKIP), reason=SKIP)

SERIAL = "SN_InterfaceA_0"  # TLSimuMono on the producer's first interface


def tlsimu_pattern(frame: Frame) -> np.ndarray:
    """What TLSimu's mono device sends: ``(x + y + frame_id) mod 256``."""
    y = np.arange(frame.height, dtype=np.uint16)[:, None]
    x = np.arange(frame.width, dtype=np.uint16)[None, :]
    return ((x + y + (frame.frame_id % 256)) & 0xFF).astype(np.uint8)


@pytest.fixture
def camera() -> Iterator[HarvestersCamera]:
    cam = HarvestersCamera(TLSIMU, serial=SERIAL)
    cam.open()
    try:
        yield cam
    finally:
        cam.close()


def test_open_by_serial_reads_the_node_map(camera: HarvestersCamera) -> None:
    assert isinstance(camera, Camera) and camera.is_open
    info = camera.info()
    assert (info.vendor, info.model) == ("EMVA_D", "TLSimu")
    assert (info.sensor_width, info.sensor_height) == (4096, 4096)  # Width/Height maxima
    assert "Mono8" in info.supported_pixel_formats and "Mono12" in info.pixel_formats
    assert info.exposure_limits_us is None and info.gain_limits is None
    assert info.backend == "harvesters" and str(TLSIMU) in info.device and SERIAL in info.device
    assert camera.read_feature("TriggerMode") == "On"
    assert camera.read_feature("TriggerSource") == "Software"
    assert camera.read_feature("AcquisitionMode") == "Continuous"


def test_open_by_device_id_and_close_twice() -> None:
    cam = HarvestersCamera(TLSIMU, device_id="TLSimuMono")
    with pytest.raises(CameraNotFound, match="2 devices match id 'TLSimuMono'"):
        cam.open()  # two interfaces list a TLSimuMono: the id is ambiguous
    cam = HarvestersCamera(TLSIMU, device_id="TLSimuMono", serial="SN_InterfaceB_0")
    with cam:
        assert cam.grab(timeout_s=2.0).pixels.shape == (512, 512)
    cam.close()
    assert not cam.is_open


def test_software_triggered_frames_are_pixel_exact(camera: HarvestersCamera) -> None:
    ids = []
    for _ in range(3):
        frame = camera.grab(timeout_s=2.0)
        assert frame.pixels.dtype == np.uint8 and frame.pixels.shape == (512, 512)
        assert np.array_equal(frame.pixels, tlsimu_pattern(frame))
        assert (frame.pixel_format, frame.bit_depth, frame.offset_x, frame.offset_y) == (
            "Mono8",
            8,
            0,
            0,
        )
        ids.append(frame.frame_id)
    assert ids == list(range(ids[0], ids[0] + 3))  # one frame per trigger


def test_roi_and_the_largest_frame(camera: HarvestersCamera) -> None:
    applied = camera.configure(CameraSettings("Mono8", roi=Roi(256, 128)))
    assert applied.roi == Roi(256, 128) and applied.pixel_format == "Mono8"
    frame = camera.grab(timeout_s=2.0)
    assert frame.pixels.shape == (128, 256) and np.array_equal(frame.pixels, tlsimu_pattern(frame))
    camera.configure(CameraSettings("Mono8"))  # full "sensor": 4096 x 4096
    frame = camera.grab(timeout_s=5.0)
    assert frame.pixels.shape == (4096, 4096)
    assert np.array_equal(frame.pixels, tlsimu_pattern(frame))


def test_missing_features_and_bad_values_are_typed(camera: HarvestersCamera) -> None:
    camera.configure(CameraSettings("Mono8", roi=Roi(128, 64)))
    with pytest.raises(FeatureMissing) as err:
        camera.configure(CameraSettings("Mono8", exposure_us=1000.0))
    assert err.value.feature == "ExposureTime" and str(TLSIMU) in str(err.value)
    with pytest.raises(FeatureMissing) as err:
        camera.exposure_limits_us()
    assert err.value.feature == "ExposureTime"
    with pytest.raises(FeatureMissing, match="'Gain'"):
        camera.configure(CameraSettings("Mono8", gain=1.0))
    with pytest.raises(FeatureMissing, match="OffsetX"):
        camera.configure(CameraSettings("Mono8", roi=Roi(64, 64, 8, 0)))
    with pytest.raises(FeatureMissing, match="PixelFormat has no entry 'Mono14'"):
        camera.configure(CameraSettings("Mono14"))
    with pytest.raises(InvalidSetting, match="increment 4"):
        camera.configure(CameraSettings("Mono8", roi=Roi(250, 64)))
    with pytest.raises(FeatureMissing):
        camera.read_feature("ExposureTime")
    assert camera.settings().roi == Roi(128, 64)  # nothing was changed
    assert camera.grab(timeout_s=2.0).pixels.shape == (64, 128)


def test_delivered_format_is_reported_as_delivered(camera: HarvestersCamera) -> None:
    # TLSimu accepts PixelFormat=Mono12 but keeps sending Mono8: the frame says so.
    assert camera.configure(CameraSettings("Mono12", roi=Roi(64, 32))).pixel_format == "Mono12"
    frame = camera.grab(timeout_s=2.0)
    assert (frame.pixel_format, frame.pixels.dtype, frame.bit_depth) == ("Mono8", np.uint8, 8)


def test_a_trigger_that_never_fires_times_out(
    camera: HarvestersCamera, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert camera._sfnc is not None
    monkeypatch.setattr(camera._sfnc.nodes, "execute", lambda name: None)
    with pytest.raises(CameraTimeout, match="no frame within 0.3 s"):
        camera.grab(timeout_s=0.3)
    monkeypatch.undo()
    frame = camera.grab(timeout_s=2.0)  # and no stale frame comes back afterwards
    assert np.array_equal(frame.pixels, tlsimu_pattern(frame))


def test_reconnect_reopens_and_keeps_settings(camera: HarvestersCamera) -> None:
    camera.configure(CameraSettings("Mono8", roi=Roi(96, 48)))
    camera.reconnect(timeout_s=5.0)
    assert camera.settings().roi == Roi(96, 48)
    assert camera.grab(timeout_s=2.0).pixels.shape == (48, 96)


def test_unknown_serial_lists_what_the_producer_has() -> None:
    with pytest.raises(CameraNotFound) as err:
        HarvestersCamera(TLSIMU, serial="NOPE").open()
    assert "serial 'NOPE'" in str(err.value) and SERIAL in str(err.value)


def test_one_producer_serves_one_camera_object(camera: HarvestersCamera) -> None:
    with pytest.raises(CameraBusy, match="already in use"):
        HarvestersCamera(TLSIMU, serial="SN_InterfaceB_0").open()
    assert camera.grab(timeout_s=2.0).pixels.shape == (512, 512)


@pytest.mark.parametrize("kind", ["missing", "directory", "not-a-library", "not-a-producer"])
def test_bad_producer_file_raises_producer_load_error(kind: str, tmp_path: Path) -> None:
    if kind == "missing":
        cti = tmp_path / "absent.cti"
    elif kind == "directory":
        cti = tmp_path
    elif kind == "not-a-library":
        cti = tmp_path / "text.cti"
        cti.write_text("this is not a GenTL producer\n")
    else:
        cti = Path(_ctypes.__file__)  # a real shared library without GenTL entry points
    with pytest.raises(ProducerLoadError) as err:
        HarvestersCamera(cti).open()
    assert str(cti) in str(err.value) and "check:" in str(err.value)


def test_missing_harvesters_raises_backend_unavailable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "harvesters.core", None)
    monkeypatch.setattr(harvesters_camera, "_HV", None)
    with pytest.raises(BackendUnavailable):
        HarvestersCamera(TLSIMU, serial=SERIAL).open()


def test_create_camera_from_configuration_values() -> None:
    cam = create_camera("harvesters", cti=TLSIMU, serial=SERIAL)
    assert isinstance(cam, HarvestersCamera)
    with cam:
        frame = cam.grab(timeout_s=2.0)
        assert np.array_equal(frame.pixels, tlsimu_pattern(frame))
    with pytest.raises(ValueError, match="cti"):
        create_camera("harvesters", serial=SERIAL)
    with pytest.raises(ValueError, match="unknown camera backend"):
        create_camera("simulated")
