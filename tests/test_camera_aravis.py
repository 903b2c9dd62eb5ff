"""The Aravis backend against a real GigE Vision stack: Aravis's fake camera on 127.0.0.1.

Every camera here is opened by address on the loopback interface; nothing runs GigE
Vision discovery.  The fake serves frames the test supplies, so each grab is checked
pixel for pixel against what was served.  Fakes hold a file lock on 127.0.0.1:3956, so
parallel pytest-xdist workers take turns.
"""

from __future__ import annotations

import ast
import pickle
import queue
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from drivers import aravis_camera
from drivers.camera import Camera, CameraSettings, Frame, Roi, create_camera, decode_mono
from drivers.camera_errors import (
    BackendUnavailable,
    CameraBusy,
    CameraError,
    CameraLost,
    CameraNotFound,
    CameraTimeout,
    FeatureMissing,
    IncompleteFrame,
    InvalidSetting,
)
from drivers.errors import DeviceError
from drivers.sim.fake_gige import FakeGigECamera, FrameRequest

try:
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis

    # Belt and braces: the drivers open cameras by unicast address and never use Aravis's
    # interface enumeration, but with every interface disabled even an accidental
    # arv_open_device / update_device_list here could not broadcast a discovery.
    for _i in range(Aravis.get_n_interfaces()):
        Aravis.disable_interface(Aravis.get_interface_id(_i))
    ARAVIS_ERROR = ""
except (ImportError, ValueError) as exc:  # pragma: no cover - the Makefile installs it
    ARAVIS_ERROR = f"Aravis 0.8 / PyGObject not importable: {exc}"

needs_aravis = pytest.mark.skipif(bool(ARAVIS_ERROR), reason=ARAVIS_ERROR)

ADDRESS = "127.0.0.1"
SERIAL = "SIM0505"
SENSOR = 512
MONO12 = 0x01100005
REG_PIXEL_FORMAT, REG_EXPOSURE_US = 0x128, 0x120
REG_TRIGGER_MODE, REG_TRIGGER_SOURCE = 0x300, 0x304


class RandomFrames:
    """Frame source: fresh random pixels of the requested size and format every frame."""

    def __init__(self, seed: int = 0) -> None:
        self.rng = np.random.default_rng(seed)

    def __call__(self, request: FrameRequest) -> np.ndarray:
        return self.rng.integers(
            0, request.max_count + 1, (request.height, request.width), dtype=request.dtype
        )


def next_block_id(block_id: int) -> int:
    """GigE Vision 1.x block ids are 16 bit and skip 0."""
    return (block_id % 65535) + 1


@pytest.fixture
def fake() -> Iterator[FakeGigECamera]:
    cam = FakeGigECamera(RandomFrames(), sensor_width=SENSOR, sensor_height=SENSOR, serial=SERIAL)
    cam.start()
    try:
        yield cam
    finally:
        cam.close()
    assert not cam.errors, cam.errors


@pytest.fixture
def camera(fake: FakeGigECamera) -> Iterator[aravis_camera.AravisCamera]:
    cam = aravis_camera.AravisCamera(ADDRESS, serial=SERIAL, frame_retention_ms=300)
    cam.open()
    try:
        yield cam
    finally:
        cam.close()


def assert_served(fake: FakeGigECamera, frame: Frame) -> None:
    """The frame's pixels are exactly the array the fake served under its block id."""
    served = fake.served_frame(frame.frame_id)
    assert served is not None, f"frame {frame.frame_id} was not served by the fake"
    assert frame.pixels.dtype == served.dtype
    assert frame.pixels.shape == served.shape
    assert np.array_equal(frame.pixels, served)


# --------------------------------------------------------------------------- no Aravis needed


def test_decode_mono_is_exact_and_rejects_short_buffers() -> None:
    counts = np.array([[0, 1, 4095], [2048, 7, 4094]], dtype=np.uint16)
    wire = counts.astype("<u2").tobytes()
    out = decode_mono(wire, width=3, height=2, pixel_format="Mono12", device="x")
    assert out.dtype == np.uint16 and out.flags.writeable and np.array_equal(out, counts)
    with pytest.raises(IncompleteFrame) as err:
        decode_mono(wire[:-2], width=3, height=2, pixel_format="Mono12", device="gige://x")
    assert err.value.status == "size-mismatch" and "gige://x" in str(err.value)


def test_errors_are_device_errors_that_name_the_device() -> None:
    err = CameraNotFound("nothing answers", device="gige://127.0.0.2")
    assert isinstance(err, CameraError) and isinstance(err, DeviceError)
    assert str(err).startswith("gige://127.0.0.2: nothing answers -- check: ")
    assert isinstance(InvalidSetting("x"), ValueError)
    assert isinstance(CameraTimeout("x"), TimeoutError)
    lost = pickle.loads(pickle.dumps(IncompleteFrame("bad", status="timeout", frame_id=9)))
    assert (lost.status, lost.frame_id) == ("timeout", 9)


def _imports(nodes: list[ast.stmt] | ast.Module) -> set[str]:
    walk = ast.walk(nodes) if isinstance(nodes, ast.Module) else nodes
    names: set[str] = set()
    for node in walk:
        if isinstance(node, ast.ImportFrom):
            names.add(node.module or "")
        elif isinstance(node, ast.Import):
            names.update(alias.name for alias in node.names)
    return names


def _production_driver_modules() -> list[Path]:
    """Every driver module outside ``drivers/sim`` (drivers/*.py and drivers/zaber/*.py)."""
    root = Path(__file__).resolve().parents[1] / "drivers"
    return sorted([*root.glob("*.py"), *(root / "zaber").glob("*.py")])


def test_production_modules_do_not_import_the_simulators() -> None:
    modules = _production_driver_modules()
    assert len(modules) > 20
    for path in modules:
        tree = ast.parse(path.read_text())
        assert not any(m.startswith("drivers.sim") for m in _imports(tree)), path.name
        top_level = _imports(tree.body)  # camera libraries only inside functions (lazy)
        assert not top_level & {"gi", "gi.repository", "harvesters.core", "genicam"}, path.name


def test_the_import_contracts_name_every_production_driver_module() -> None:
    """import-linter checks only the modules a contract names: a new driver module must
    be added to the two contracts that keep production drivers apart from the simulators
    and the calibration core (pyproject.toml)."""
    import tomllib

    pyproject = Path(__file__).resolve().parents[1] / "pyproject.toml"
    contracts = tomllib.loads(pyproject.read_text())["tool"]["importlinter"]["contracts"]
    named = [
        set(c["source_modules"])
        for c in contracts
        if c["type"] == "forbidden" and c["forbidden_modules"] in (["calibration"], ["drivers.sim"])
    ]
    assert len(named) == 2
    for path in _production_driver_modules():
        if path.parent.name == "zaber":
            module = "drivers.zaber"
        elif path.stem == "__init__":
            continue
        else:
            module = f"drivers.{path.stem}"
        for sources in named:
            assert module in sources, f"{module} is missing from an import-linter contract"


def test_missing_pygobject_raises_backend_unavailable(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "gi", None)
    monkeypatch.setattr(aravis_camera, "_GI", None)
    with pytest.raises(BackendUnavailable) as err:
        aravis_camera.AravisCamera(ADDRESS).open()
    assert "gir1.2-aravis-0.8" in str(err.value)


def test_serial_without_address_never_runs_discovery() -> None:
    cam = create_camera("aravis", serial=SERIAL)
    assert isinstance(cam, aravis_camera.AravisCamera)
    start = time.monotonic()
    with pytest.raises(CameraNotFound) as err:
        cam.open()
    assert time.monotonic() - start < 1.0  # refused before touching the network
    assert "discovery" in str(err.value) and "camera.address" in str(err.value)
    assert not cam.is_open


# --------------------------------------------------------------------------- real stack


@needs_aravis
def test_open_by_address_reads_the_node_map(
    camera: aravis_camera.AravisCamera, fake: FakeGigECamera
) -> None:
    assert isinstance(camera, Camera)
    info = camera.info()
    assert (info.vendor, info.model, info.serial) == ("lfcal", "GMAX0505 (simulated)", SERIAL)
    assert (info.sensor_width, info.sensor_height) == (SENSOR, SENSOR)
    assert {"Mono8", "Mono12"} <= set(info.supported_pixel_formats)
    assert info.exposure_limits_us == (10.0, 1_000_000.0) == camera.exposure_limits_us()
    assert info.gain_limits == (0.0, 24.0)
    assert info.backend == "aravis" and ADDRESS in info.device
    # software trigger set up through the SFNC features
    assert camera.read_feature("TriggerMode") == "On"
    assert camera.read_feature("TriggerSource") == "Software"
    assert fake.read_register(REG_TRIGGER_MODE) == 1
    assert fake.read_register(REG_TRIGGER_SOURCE) == 1


@needs_aravis
def test_grab_mono8_full_sensor_is_pixel_exact(
    camera: aravis_camera.AravisCamera, fake: FakeGigECamera
) -> None:
    applied = camera.configure(CameraSettings("Mono8", exposure_us=20_000, gain=0.0))
    assert applied == CameraSettings("Mono8", 20_000.0, 0.0, Roi(SENSOR, SENSOR))
    before = time.time_ns()
    frame = camera.grab(timeout_s=2.0)
    assert_served(fake, frame)
    assert frame.pixels.dtype == np.uint8 and frame.pixels.shape == (SENSOR, SENSOR)
    assert (frame.width, frame.height, frame.offset_x, frame.offset_y) == (SENSOR, SENSOR, 0, 0)
    assert (frame.pixel_format, frame.bit_depth, frame.max_count) == ("Mono8", 8, 255)
    assert (frame.exposure_us, frame.gain) == (20_000.0, 0.0)
    assert before - 1_000_000_000 < frame.host_timestamp_ns < time.time_ns() + 1_000_000_000
    assert frame.timestamp_ns > 0 and ADDRESS in frame.device
    # DeviceTemperature is read with every frame (a GVCP read of the camera's register)
    assert camera.info().has_temperature and frame.gain_feature == "Gain"
    for celsius in (36.75, 44.125):
        fake.set_temperature_c(celsius)
        assert camera.grab(timeout_s=2.0).temperature_c == celsius


@needs_aravis
def test_mono12_roi_exposure_gain_reach_the_camera(
    camera: aravis_camera.AravisCamera, fake: FakeGigECamera
) -> None:
    settings = CameraSettings("Mono12", exposure_us=2500.0, gain=6.5, roi=Roi(256, 128, 64, 32))
    assert camera.configure(settings) == settings
    assert fake.read_register(REG_PIXEL_FORMAT) == MONO12
    assert fake.read_register(REG_EXPOSURE_US) == 2500
    assert fake.read_gain_db() == 6.5
    frame = camera.grab(timeout_s=2.0)
    assert_served(fake, frame)
    assert frame.pixels.dtype == np.uint16 and frame.pixels.shape == (128, 256)
    assert (frame.offset_x, frame.offset_y, frame.bit_depth) == (64, 32, 12)
    assert int(frame.pixels.max()) <= 4095
    assert (frame.exposure_us, frame.gain) == (2500.0, 6.5)


@needs_aravis
def test_each_grab_returns_its_own_triggered_frame(
    camera: aravis_camera.AravisCamera, fake: FakeGigECamera
) -> None:
    camera.configure(CameraSettings("Mono8", roi=Roi(128, 64)))
    served_before = fake.served_count
    ids = []
    for _ in range(5):
        frame = camera.grab(timeout_s=2.0)
        assert_served(fake, frame)
        ids.append(frame.frame_id)
    # one frame per software trigger, nothing free-running in between
    assert fake.served_count - served_before == 5
    assert ids[1:] == [next_block_id(i) for i in ids[:-1]]


@needs_aravis
def test_frames_from_a_queue_arrive_unchanged() -> None:
    rng = np.random.default_rng(7)
    arrays = [rng.integers(0, 256, (96, 160), dtype=np.uint8) for _ in range(3)]
    frames: queue.Queue[np.ndarray] = queue.Queue()
    for a in arrays:
        frames.put(a)
    with FakeGigECamera(frames, sensor_width=160, sensor_height=96) as fake:
        with aravis_camera.AravisCamera(ADDRESS) as cam:
            got = [cam.grab(timeout_s=2.0).pixels for _ in arrays]
        assert not fake.errors
    for a, b in zip(arrays, got, strict=True):
        assert np.array_equal(a, b)


@needs_aravis
def test_rejected_settings_change_nothing(
    camera: aravis_camera.AravisCamera, fake: FakeGigECamera
) -> None:
    good = CameraSettings("Mono12", exposure_us=1000.0, gain=1.0, roi=Roi(64, 64, 8, 8))
    camera.configure(good)
    with pytest.raises(FeatureMissing) as err:
        camera.configure(CameraSettings("Mono10"))
    assert err.value.feature == "PixelFormat" and "Mono12" in err.value.offered
    assert "Mono10" in str(err.value) and ADDRESS in str(err.value)
    with pytest.raises(InvalidSetting, match="ExposureTime"):
        camera.configure(CameraSettings("Mono8", exposure_us=5.0))
    with pytest.raises(InvalidSetting, match="Gain"):
        camera.configure(CameraSettings("Mono8", gain=99.0))
    with pytest.raises(InvalidSetting, match="does not fit"):
        camera.configure(CameraSettings("Mono8", roi=Roi(SENSOR, 16, 1, 0)))
    with pytest.raises(InvalidSetting, match="not supported"):
        camera.configure(CameraSettings("RGB8"))
    with pytest.raises(FeatureMissing, match="no entry 'Mono12Packed'"):
        camera.configure(CameraSettings("Mono12Packed"))  # decoded, but not offered
    with pytest.raises(FeatureMissing, match="TriggerSource has no entry 'Line7'"):
        camera.configure(CameraSettings("Mono8", trigger="Line7"))
    assert camera.settings() == good
    assert fake.read_register(REG_PIXEL_FORMAT) == MONO12
    frame = camera.grab(timeout_s=2.0)
    assert frame.pixels.shape == (64, 64) and frame.pixel_format == "Mono12"


@needs_aravis
def test_no_frame_is_a_timeout_not_a_lost_camera(
    camera: aravis_camera.AravisCamera, fake: FakeGigECamera
) -> None:
    camera.configure(CameraSettings("Mono8", roi=Roi(64, 64)))
    fake.set_packet_loss(1.0)  # the camera answers but every stream packet is lost
    with pytest.raises(CameraTimeout) as err:
        camera.grab(timeout_s=0.4)
    assert ADDRESS in str(err.value)
    fake.set_packet_loss(0.0)
    assert_served(fake, camera.grab(timeout_s=2.0))


@needs_aravis
def test_damaged_frame_raises_incomplete_and_is_never_returned(
    camera: aravis_camera.AravisCamera, fake: FakeGigECamera
) -> None:
    camera.configure(CameraSettings("Mono8"))  # 512x512: 33 stream packets per frame
    fake.set_packet_loss(0.5)
    with pytest.raises(IncompleteFrame) as err:
        camera.grab(timeout_s=3.0)
    assert err.value.status in ("missing-packets", "timeout", "size-mismatch")
    assert ADDRESS in str(err.value)
    fake.set_packet_loss(0.0)
    frame = camera.grab(timeout_s=3.0)  # the damaged frame does not come back later
    assert_served(fake, frame)


@needs_aravis
def test_lost_camera_raises_then_grab_reconnects_when_it_is_back(
    camera: aravis_camera.AravisCamera, fake: FakeGigECamera
) -> None:
    settings = CameraSettings("Mono12", exposure_us=3000.0, gain=2.0, roi=Roi(96, 80, 16, 24))
    camera.configure(settings)
    assert_served(fake, camera.grab(timeout_s=2.0))
    fake.stop()  # unplugged
    with pytest.raises(CameraLost) as err:
        camera.grab(timeout_s=1.0)
    assert ADDRESS in str(err.value) and "check:" in str(err.value)
    assert camera.is_open
    start = time.monotonic()
    with pytest.raises(CameraLost, match="still not answering"):
        camera.grab(timeout_s=1.0)  # one bounded reopen attempt, camera still absent
    assert time.monotonic() - start < 2.0
    fake.start()  # plugged back in: a fresh camera with default settings
    frame = camera.grab(timeout_s=2.0)  # one automatic reopen, settings re-applied
    assert_served(fake, frame)
    assert frame.pixels.shape == (80, 96) and frame.pixel_format == "Mono12"
    assert fake.read_register(REG_EXPOSURE_US) == 3000 and fake.read_gain_db() == 2.0
    assert camera.settings() == settings


@needs_aravis
def test_reconnect_after_a_camera_reboot(
    camera: aravis_camera.AravisCamera, fake: FakeGigECamera
) -> None:
    camera.configure(CameraSettings("Mono8", roi=Roi(32, 32)))
    fake.stop()
    fake.start()  # rebooted between two grabs
    camera.reconnect(timeout_s=10.0)
    frame = camera.grab(timeout_s=2.0)
    assert_served(fake, frame)
    assert frame.pixels.shape == (32, 32)


@needs_aravis
def test_second_client_is_refused_while_the_first_has_control(
    camera: aravis_camera.AravisCamera, fake: FakeGigECamera
) -> None:
    other = aravis_camera.AravisCamera(ADDRESS)
    with pytest.raises(CameraBusy) as err:
        other.open()
    assert ADDRESS in str(err.value)
    assert_served(fake, camera.grab(timeout_s=2.0))  # the first client is undisturbed


@needs_aravis
def test_wrong_serial_at_the_address_is_not_found(fake: FakeGigECamera) -> None:
    cam = aravis_camera.AravisCamera(ADDRESS, serial="OTHER42")
    with pytest.raises(CameraNotFound) as err:
        cam.open()
    assert "OTHER42" in str(err.value) and SERIAL in str(err.value)
    assert not cam.is_open


@needs_aravis
def test_address_without_a_camera_is_not_found() -> None:
    cam = aravis_camera.AravisCamera("127.0.0.2")  # loopback, nothing listens there
    with pytest.raises(CameraNotFound) as err:
        cam.open()
    text = str(err.value)
    assert "127.0.0.2" in text and "no GigE Vision camera answers" in text and "check:" in text
    with pytest.raises(CameraError, match="not open"):
        cam.grab()


@needs_aravis
def test_full_5120_sensor_frame_is_pixel_exact() -> None:
    pattern = np.random.default_rng(3).integers(0, 256, (5120, 5120), dtype=np.uint8)

    def source(request: FrameRequest) -> np.ndarray:
        return pattern

    exact = 0
    with FakeGigECamera(source, sensor_width=5120, sensor_height=5120) as fake:
        with aravis_camera.AravisCamera(ADDRESS) as cam:
            assert (cam.info().sensor_width, cam.info().sensor_height) == (5120, 5120)
            cam.configure(CameraSettings("Mono8"))
            # at most 8 grabs (bounded): a saturated host drops UDP bursts of 26 MB frames
            for _ in range(8):
                try:
                    frame = cam.grab(timeout_s=5.0)
                except IncompleteFrame:
                    continue  # dropped packets: typed, never a partial frame
                assert frame.pixels.shape == (5120, 5120)
                assert np.array_equal(frame.pixels, pattern)
                exact += 1
                if exact == 2:
                    break
        assert not fake.errors
    assert exact == 2


def test_usb3_camera_by_serial_never_enables_gige_discovery(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """USB3 Vision by serial: the GigE Vision interface is disabled before Aravis looks
    for the device, so only the USB bus is enumerated (no packet on any network)."""
    import types

    import drivers.aravis_camera as module

    real = module._aravis()
    calls: list[str] = []

    class RecordingAravis:
        def __getattr__(self, name: str) -> object:
            return getattr(real.Aravis, name)

        def disable_interface(self, name: str) -> None:
            calls.append(f"disable {name}")
            real.Aravis.disable_interface(name)

        def enable_interface(self, name: str) -> None:
            calls.append(f"enable {name}")
            real.Aravis.enable_interface(name)

        class Camera:
            @staticmethod
            def new(name: str) -> object:
                calls.append(f"open {name}")
                return real.Aravis.Camera.new(name)

    fake_ns = types.SimpleNamespace(Aravis=RecordingAravis(), Gio=real.Gio, GLib=real.GLib)
    monkeypatch.setattr(module, "_aravis", lambda: fake_ns)
    camera = module.AravisCamera(serial="LFCAL-NO-SUCH-USB3", interface="usb3")
    assert camera.label == "usb3://LFCAL-NO-SUCH-USB3"
    with pytest.raises(CameraNotFound, match="no USB3 Vision camera 'LFCAL-NO-SUCH-USB3'"):
        camera.open()
    assert calls == ["disable GigEVision", "enable USB3Vision", "open LFCAL-NO-SUCH-USB3"]
