"""Real-camera checks (GMAX0505 on GigE Vision), skipped by default.

Run on the station with the camera connected::

    LFCAL_CAMERA_ADDRESS=192.168.10.20 .venv/bin/python -m pytest -m hardware -s \\
        tests/test_camera_hardware.py

Environment:
    LFCAL_CAMERA_ADDRESS   camera IP (Aravis backend; opened by unicast, no discovery)
    LFCAL_CAMERA_SERIAL    optional: expected serial (checked at the address; harvesters:
                           the device to open)
    LFCAL_CAMERA_CTI       optional: GenTL producer .cti to test the harvesters backend
    LFCAL_CAMERA_SENSOR    optional: expected sensor "WIDTHxHEIGHT" (default 5120x5120)
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator

import numpy as np
import pytest

from drivers.camera import Camera, CameraSettings, Roi

pytestmark = pytest.mark.hardware

ADDRESS = os.environ.get("LFCAL_CAMERA_ADDRESS")
SERIAL = os.environ.get("LFCAL_CAMERA_SERIAL") or None
CTI = os.environ.get("LFCAL_CAMERA_CTI")
SENSOR = tuple(int(v) for v in os.environ.get("LFCAL_CAMERA_SENSOR", "5120x5120").split("x"))


@pytest.fixture(params=["aravis", "harvesters"])
def camera(request: pytest.FixtureRequest) -> Iterator[Camera]:
    cam: Camera
    if request.param == "aravis":
        if not ADDRESS:
            pytest.skip("set LFCAL_CAMERA_ADDRESS to the camera's IP address")
        from drivers.aravis_camera import AravisCamera

        cam = AravisCamera(ADDRESS, serial=SERIAL)
    else:
        if not CTI:
            pytest.skip("set LFCAL_CAMERA_CTI (and LFCAL_CAMERA_SERIAL) for harvesters")
        from drivers.harvesters_camera import HarvestersCamera

        cam = HarvestersCamera(CTI, serial=SERIAL)
    cam.open()
    try:
        yield cam
    finally:
        cam.close()


def test_identity_and_capabilities(camera: Camera) -> None:
    info = camera.info()
    print(f"\n{info}")
    assert (info.sensor_width, info.sensor_height) == SENSOR
    assert {"Mono8", "Mono12"} <= set(info.supported_pixel_formats)
    lo, hi = camera.exposure_limits_us()
    assert 0 < lo < 1000 < hi
    if SERIAL:
        assert info.serial == SERIAL


def test_full_frame_mono12_grab(camera: Camera) -> None:
    lo, _ = camera.exposure_limits_us()
    gain = camera.info().gain_limits
    settings = CameraSettings(
        "Mono12", exposure_us=max(lo, 10_000.0), gain=gain[0] if gain else None
    )
    applied = camera.configure(settings)
    assert applied.pixel_format == "Mono12" and applied.roi == Roi(*SENSOR)
    ids = []
    for _ in range(3):
        frame = camera.grab(timeout_s=5.0)
        assert frame.pixels.shape == (SENSOR[1], SENSOR[0]) and frame.pixels.dtype == np.uint16
        assert frame.bit_depth == 12 and int(frame.pixels.max()) <= 4095
        assert frame.exposure_us == pytest.approx(applied.exposure_us)
        ids.append(frame.frame_id)
    assert len(set(ids)) == 3


def test_roi_grab(camera: Camera) -> None:
    roi = Roi(1024, 512, 2048, 2048)
    camera.configure(CameraSettings("Mono8", roi=roi))
    frame = camera.grab(timeout_s=5.0)
    assert frame.pixels.shape == (512, 1024) and frame.pixels.dtype == np.uint8
    assert (frame.offset_x, frame.offset_y) == (2048, 2048)


def test_full_frame_grab_rate(camera: Camera) -> None:
    lo, _ = camera.exposure_limits_us()
    camera.configure(CameraSettings("Mono8", exposure_us=max(lo, 1000.0)))
    camera.grab(timeout_s=5.0)
    n = 10
    start = time.perf_counter()
    for _ in range(n):
        camera.grab(timeout_s=5.0)
    fps = n / (time.perf_counter() - start)
    print(f"\nsoftware-triggered full-frame Mono8 grab rate: {fps:.1f} fps")
    assert fps > 1.0
