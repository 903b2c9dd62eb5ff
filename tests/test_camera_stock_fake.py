"""Our Aravis driver against Aravis's own stock fake camera, a GenICam device we did not write.

``arv-fake-gv-camera-0.8`` (Debian ``aravis-tools``) runs as a separate process on
127.0.0.1 with its stock GenICam XML: an SFNC 1.x camera with ``ExposureTimeAbs``,
``GainRaw`` only (0..10, no ``Gain``), ``DeviceID`` as its serial, a
``TriggerSource`` with ``Line0`` and ``Software``.  It is opened by address (unicast;
nothing here runs discovery), configured (exposure, gain, ROI), grabbed, and used for
the hardware-trigger configuration.  Only one fake can own the GVCP port of an address,
so the fixture takes the same inter-process lock as :mod:`drivers.sim.fake_gige`.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from collections.abc import Iterator

import numpy as np
import pytest

from drivers.camera import CameraSettings, Roi, TransportSettings
from drivers.camera_errors import CameraTimeout, InvalidSetting

pytest.importorskip("gi")
from drivers.aravis_camera import AravisCamera  # noqa: E402
from drivers.gige_host import (  # noqa: E402
    can_open_packet_sockets,
    gvcp_ping,
    rmem_max_bytes,
    socket_buffer_warning,
)
from drivers.sim.fake_gige import _AddressLock  # noqa: E402

FAKE = shutil.which("arv-fake-gv-camera-0.8")
pytestmark = pytest.mark.skipif(FAKE is None, reason="aravis-tools is not installed")
ADDRESS = "127.0.0.1"
SERIAL = "LFCAL-STOCK-1"


@pytest.fixture(scope="module")
def stock_fake() -> Iterator[subprocess.Popen[bytes]]:
    lock = _AddressLock(ADDRESS)
    lock.acquire(timeout_s=120.0)
    assert FAKE is not None
    process = subprocess.Popen(
        [FAKE, "-i", ADDRESS, "-s", SERIAL],
        stdout=subprocess.DEVNULL,
        stderr=subprocess.DEVNULL,
    )
    try:
        deadline = time.monotonic() + 15.0
        while not gvcp_ping(ADDRESS, timeout_s=0.2):
            assert process.poll() is None, "arv-fake-gv-camera-0.8 exited"
            assert time.monotonic() < deadline, "the stock fake camera did not come up"
        yield process
    finally:
        process.terminate()
        try:
            process.wait(timeout=5.0)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait(timeout=5.0)
        lock.release()


@pytest.fixture
def camera(stock_fake: subprocess.Popen[bytes]) -> Iterator[AravisCamera]:
    with AravisCamera(ADDRESS, serial=SERIAL) as cam:
        yield cam


def test_identity_and_sfnc1_features(camera: AravisCamera) -> None:
    info = camera.info()
    assert (info.vendor, info.model, info.serial) == ("Aravis", "Fake", SERIAL)
    assert info.gain_feature == "GainRaw" and info.gain_limits == (0.0, 10.0)
    assert info.exposure_limits_us is not None
    assert {"Mono8", "Mono16"} <= set(info.supported_pixel_formats)


def test_configure_exposure_gainraw_roi_and_grab(camera: AravisCamera) -> None:
    applied = camera.configure(
        CameraSettings("Mono8", exposure_us=20_000.0, gain=5.0, roi=Roi(256, 128, 64, 32))
    )
    assert applied.exposure_us == 20_000.0 and applied.gain == 5.0
    assert applied.roi == Roi(256, 128, 64, 32) and applied.trigger == "software"
    # the camera itself holds the values: read through its own SFNC 1.x features
    assert camera.read_feature("ExposureTimeAbs") == 20_000.0
    assert camera.read_feature("GainRaw") == 5
    assert (camera.read_feature("Width"), camera.read_feature("OffsetY")) == (256, 32)
    frame = camera.grab(timeout_s=5.0)
    assert frame.pixels.shape == (128, 256) and frame.pixels.dtype == np.uint8
    assert (frame.offset_x, frame.offset_y) == (64, 32)
    assert frame.metadata()["gain_feature"] == "GainRaw"
    assert frame.metadata()["gain"] == 5.0 and frame.metadata()["exposure_us"] == 20_000.0
    assert int(frame.pixels.max()) > int(frame.pixels.min())  # the fake's test pattern
    wide = camera.configure(CameraSettings("Mono16", roi=Roi(64, 16)))
    assert wide.pixel_format == "Mono16"
    frame16 = camera.grab(timeout_s=5.0)
    assert frame16.pixels.dtype == np.uint16 and frame16.bit_depth == 16


def test_gainraw_only_camera_refuses_a_fractional_or_too_large_gain(camera: AravisCamera) -> None:
    with pytest.raises(InvalidSetting, match="GainRaw only"):
        camera.configure(CameraSettings("Mono8", gain=2.5))
    with pytest.raises(InvalidSetting, match=r"GainRaw=11 is outside"):
        camera.configure(CameraSettings("Mono8", gain=11.0))


def test_hardware_trigger_line_configuration(camera: AravisCamera) -> None:
    applied = camera.configure(
        CameraSettings("Mono8", roi=Roi(64, 64), trigger="Line0", trigger_activation="RisingEdge")
    )
    assert applied.trigger == "Line0" and applied.trigger_activation == "RisingEdge"
    assert camera.read_feature("TriggerSource") == "Line0"
    assert camera.read_feature("TriggerMode") == "On"
    assert camera.read_feature("TriggerSelector") == "FrameStart"
    # no pulse on Line0 and no software trigger sent: no frame, a timeout naming the line
    with pytest.raises(CameraTimeout, match="trigger line Line0"):
        camera.grab(timeout_s=0.5)
    back = camera.configure(CameraSettings("Mono8", roi=Roi(64, 64)))
    assert back.trigger == "software" and camera.read_feature("TriggerSource") == "Software"
    assert camera.grab(timeout_s=5.0).pixels.shape == (64, 64)


def test_transport_settings_and_the_rmem_max_warning(stock_fake: subprocess.Popen[bytes]) -> None:
    rmem_max = rmem_max_bytes()
    assert rmem_max is not None and rmem_max > 0
    transport = TransportSettings(
        packet_size=1400, buffer_count=5, socket_buffer_bytes=2 * rmem_max
    )
    with AravisCamera(ADDRESS, transport=transport) as cam:
        cam.configure(CameraSettings("Mono8", roi=Roi(128, 128)))
        frame = cam.grab(timeout_s=5.0)
        assert frame.pixels.shape == (128, 128)
        assert cam._camera.gv_get_packet_size() == 1400
        assert any("net.core.rmem_max" in w for w in cam.warnings), cam.warnings
    assert socket_buffer_warning(1000, 2000) is None
    text = socket_buffer_warning(8_000_000, 212_992)
    assert text is not None and "net.core.rmem_max = 212992" in text and "8000000" in text


def _packet_socket_inodes_of_this_process() -> set[str]:
    """Inodes of this process's sockets that the kernel lists as AF_PACKET sockets."""
    ours = set()
    for fd in os.listdir("/proc/self/fd"):
        try:
            target = os.readlink(f"/proc/self/fd/{fd}")
        except OSError:
            continue
        if target.startswith("socket:["):
            ours.add(target[len("socket:[") : -1])
    with open("/proc/net/packet") as table:
        packet = {line.split()[-1] for line in table.readlines()[1:] if line.split()}
    return ours & packet


@pytest.mark.parametrize("packet_socket", [None, False, True])
def test_the_stream_receiver_is_the_udp_socket_unless_it_cannot_hold_a_frame(
    stock_fake: subprocess.Popen[bytes], packet_socket: bool | None
) -> None:
    """Aravis reads every packet on the interface as GVSP while it sets its AF_PACKET
    ring up; a stray one can hold a buffer and cost a frame, so the ring is used only
    when asked for, or for frames the default socket buffer cannot hold (not 4 KiB)."""
    if packet_socket and not can_open_packet_sockets():
        pytest.skip("the AF_PACKET ring needs CAP_NET_RAW")
    with AravisCamera(ADDRESS, transport=TransportSettings(packet_socket=packet_socket)) as cam:
        cam.configure(CameraSettings("Mono8", roi=Roi(64, 64)))
        assert cam.grab(timeout_s=5.0).pixels.shape == (64, 64)
        rings = _packet_socket_inodes_of_this_process()
        assert bool(rings) == bool(packet_socket), rings
