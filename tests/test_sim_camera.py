"""The simulated camera and bench: real emulator on a pty, real Zaber driver, real renderer.

Every frame is compared with a direct :func:`calibration.simulator.render_frame` at the
bench's true state (same seed: bit-exact), so the camera shows what the board's physical
position says, not what anyone asked for.  Frames are 600 x 400 px ROIs of the paper
preset's 5120 x 5120 sensor (about 0.3 s each); the emulator runs 50x faster than real
time.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator, Sequence

import numpy as np
import pytest
from numpy.typing import NDArray

from calibration.simulator import Roi as SimRoi
from calibration.simulator import render_frame
from drivers.axis import Axis
from drivers.camera import Camera, CameraSettings, Frame, Roi
from drivers.camera_errors import (
    CameraError,
    CameraLost,
    CameraNotFound,
    CameraTimeout,
    FeatureMissing,
    IncompleteFrame,
    InvalidSetting,
)
from drivers.sim.bench import BenchAxis, SimulatedBench, chain_specs
from drivers.sim.plenoptic_scene import PlenopticScene, scene_from_preset
from drivers.sim.sim_camera import SIM_PIXEL_FORMATS, Scene, SceneState, SimulatedCamera
from drivers.zaber import XYStage, ZaberAxis, ZaberAxisConfig, ZaberPort, open_rail, open_xy_stage

SPEEDUP = 50.0
ZERO_MM = 250.0
ALIGNMENT = (100.0, 100.0)
ROI = Roi(600, 400, 2260, 2360)  # around the principal point (2559.5, 2559.5)
SIM_ROI = SimRoi(ROI.offset_x, ROI.offset_y, ROI.width, ROI.height)
SEED = 7


def axis_cfg(name: str, device: int, axis: int, microstep_um: float) -> ZaberAxisConfig:
    return ZaberAxisConfig(
        name=name,
        device=device,
        axis=axis,
        microstep_um=microstep_um,
        tolerance_um=1.0,
        timeout_scale=1.0 / SPEEDUP,
        timeout_margin_s=1.0,
        poll_interval_s=0.002,
    )


@pytest.fixture(scope="module")
def scene() -> PlenopticScene:
    return scene_from_preset("paper")


@pytest.fixture
def bench(scene: PlenopticScene) -> Iterator[SimulatedBench]:
    with SimulatedBench(
        scene,
        zero_object_distance_mm=ZERO_MM,
        alignment_mm=ALIGNMENT,
        speedup=SPEEDUP,
        camera_seed=SEED,
    ) as b:
        yield b


@pytest.fixture
def stages(bench: SimulatedBench) -> Iterator[tuple[ZaberAxis, XYStage]]:
    """Rail (device 1) and XY stage (device 2) on the bench's pty, homed."""
    port = ZaberPort(bench.url, reply_timeout_s=0.5).open()
    rail = open_rail(port, axis_cfg("rail", 1, 1, 0.047625))
    xy = open_xy_stage(
        port,
        axis_cfg("stage x", 2, 1, 0.09921875),
        axis_cfg("stage y", 2, 2, 0.09921875),
    )
    rail.home()
    xy.home()
    yield rail, xy
    xy.close()
    rail.close()
    port.close()


@pytest.fixture
def cam(bench: SimulatedBench) -> Iterator[SimulatedCamera]:
    camera = bench.camera
    camera.open()
    camera.configure(CameraSettings("Mono12", roi=ROI))
    yield camera
    camera.close()


def direct(
    scene: PlenopticScene,
    frame: Frame,
    u_mm: float,
    offset_mm: tuple[float, float] = (0.0, 0.0),
    *,
    white: bool = False,
) -> NDArray[np.uint16]:
    """The simulator's own frame for ``frame``'s window and noise seed."""
    return render_frame(
        scene.camera,
        object_distance_mm=u_mm,
        board_offset_mm=offset_mm,
        white=white,
        roi=SimRoi(frame.offset_x, frame.offset_y, frame.width, frame.height),
        seed=[SEED, frame.frame_id],
    )


class StaticState:
    """A state source without any bench (for camera-only tests)."""

    def __init__(self, state: SceneState) -> None:
        self.state = state

    def __call__(self) -> SceneState:
        return self.state


@pytest.fixture
def white_cam(scene: PlenopticScene) -> Iterator[SimulatedCamera]:
    camera = SimulatedCamera(scene, StaticState(SceneState(300.0, white=True)), seed=SEED)
    with camera:
        camera.configure(CameraSettings("Mono12", roi=ROI))
        yield camera


# --------------------------------------------------------------------------- protocol


def test_satisfies_the_camera_protocol(cam: SimulatedCamera, scene: PlenopticScene) -> None:
    assert isinstance(cam, Camera)
    info = cam.info()
    assert (info.sensor_width, info.sensor_height) == scene.sensor_size_px == (5120, 5120)
    assert info.pixel_formats == SIM_PIXEL_FORMATS == info.supported_pixel_formats
    assert info.backend == "simulated" and "paper" in info.model and info.device == cam.label
    assert cam.exposure_limits_us() == info.exposure_limits_us
    assert cam.settings() == CameraSettings("Mono12", exposure_us=10000.0, gain=0.0, roi=ROI)


def test_requires_open(scene: PlenopticScene) -> None:
    camera = SimulatedCamera(scene, StaticState(SceneState(300.0)))
    assert not camera.is_open
    for call in (camera.info, camera.grab, camera.exposure_limits_us):
        with pytest.raises(CameraError, match="not open"):
            call()
    with pytest.raises(CameraError, match="not open"):
        camera.configure(CameraSettings("Mono12"))
    with camera:
        assert camera.is_open
    assert not camera.is_open
    camera.close()  # twice is fine


# --------------------------------------------------------------------------- physics


def test_frame_is_the_board_at_the_true_rail_position(
    bench: SimulatedBench,
    stages: tuple[ZaberAxis, XYStage],
    cam: SimulatedCamera,
    scene: PlenopticScene,
) -> None:
    rail, xy = stages
    assert isinstance(rail, Axis)
    xy.move_xy_mm(*ALIGNMENT)
    rail.move_abs_mm(37.5)
    rail_mm = rail.position_mm()  # read back through the driver: microstep-rounded
    x_mm, y_mm = xy.position_xy_mm()
    offset = (x_mm - ALIGNMENT[0], y_mm - ALIGNMENT[1])
    assert abs(rail_mm - 37.5) < 1e-4 and max(map(abs, offset)) < 1e-4

    frame = cam.grab()
    u = ZERO_MM + rail_mm
    assert cam.last_state == SceneState(u, offset, white=False)
    assert frame.pixels.shape == (400, 600) and frame.pixels.dtype == np.uint16
    np.testing.assert_array_equal(frame.pixels, direct(scene, frame, u, offset))

    rail.move_abs_mm(80.0)  # the camera follows the rail
    moved = cam.grab()
    u2 = ZERO_MM + rail.position_mm()
    assert cam.last_state is not None and cam.last_state.object_distance_mm == u2
    np.testing.assert_array_equal(moved.pixels, direct(scene, moved, u2, offset))
    assert not np.array_equal(moved.pixels, direct(scene, moved, u, offset))


def test_true_position_not_the_driver_belief(
    bench: SimulatedBench, cam: SimulatedCamera, scene: PlenopticScene
) -> None:
    # Before homing the driver knows no position, but the board is somewhere: at
    # power-up the emulated rail stands 10 mm from its home sensor.
    assert bench.rail_mm() == pytest.approx(10.0, abs=1e-4)
    frame = cam.grab()
    state = bench.scene_state()
    assert state.object_distance_mm == pytest.approx(ZERO_MM + 10.0, abs=1e-4)
    np.testing.assert_array_equal(
        frame.pixels, direct(scene, frame, state.object_distance_mm, state.board_offset_mm)
    )


def test_white_position_shows_the_light_area(
    bench: SimulatedBench,
    stages: tuple[ZaberAxis, XYStage],
    cam: SimulatedCamera,
    scene: PlenopticScene,
) -> None:
    rail, xy = stages
    rail.move_abs_mm(50.0)
    xy.move_xy_mm(300.0, 100.0)  # board moved 200 mm: plain light border on the axis
    frame = cam.grab()
    state = cam.last_state
    assert state is not None and state.white
    u = ZERO_MM + rail.position_mm()
    np.testing.assert_array_equal(frame.pixels, direct(scene, frame, u, white=True))
    xy.move_xy_mm(*ALIGNMENT)
    board = cam.grab()
    assert cam.last_state is not None and not cam.last_state.white
    assert board.pixels.mean() < 0.8 * frame.pixels.mean()  # dark squares in view


def test_white_rule_threshold(scene: PlenopticScene) -> None:
    bench = SimulatedBench(scene, alignment_mm=ALIGNMENT)  # not started: pure geometry
    assert bench.white_offset_mm == scene.board_half_extent_mm == 150.0
    assert not bench.is_white((150.0, 0.0)) and not bench.is_white((-20.0, -150.0))
    assert bench.is_white((150.01, 0.0)) and bench.is_white((0.0, -151.0))
    assert bench.board_offset_mm((300.0, 100.0)) == (200.0, 0.0)
    assert bench.object_distance_mm(42.0) == 292.0


def test_direction_minus_one_and_external_position_sources(scene: PlenopticScene) -> None:
    bench = SimulatedBench(
        scene, zero_object_distance_mm=400.0, direction=-1, rail=None, stage_x=None, stage_y=None
    )
    with pytest.raises(RuntimeError, match="no rail position source"):
        bench.scene_state()
    bench.use_rail_position(lambda: 30.0)
    bench.use_stage_position(lambda: (100.0, 100.0))
    assert bench.scene_state() == SceneState(370.0, (0.0, 0.0), white=False)
    with pytest.raises(RuntimeError, match="emulates no axis"):
        _ = bench.url


def test_source_errors_become_camera_errors(scene: PlenopticScene) -> None:
    def broken() -> SceneState:
        raise KeyError("rail")

    with SimulatedCamera(scene, broken) as camera:
        with pytest.raises(CameraError, match="cannot read the simulated bench"):
            camera.grab()
    with SimulatedCamera(scene, StaticState(SceneState(20.0))) as camera:  # u < F
        camera.configure(CameraSettings("Mono12", roi=ROI))
        with pytest.raises(CameraError, match="cannot be rendered") as err:
            camera.grab()
        assert "zero_object_distance_mm" in str(err.value)


def test_chain_layout() -> None:
    specs = chain_specs(
        [BenchAxis(1, 1), BenchAxis(2, 2, travel_mm=300.0), BenchAxis(2, 1, travel_mm=200.0)]
    )
    assert [s.address for s in specs] == [1, 2]
    assert [a.travel_mm for a in specs[1].axes] == [200.0, 300.0]
    with pytest.raises(ValueError, match="device 1 axis 1"):
        chain_specs([BenchAxis(1, 1), BenchAxis(1, 1)])


# --------------------------------------------------------------------------- settings


def test_roi_renders_only_the_window(scene: PlenopticScene) -> None:
    calls: list[tuple[int, int, int, int]] = []

    class Spy:
        name = scene.name
        sensor_size_px = scene.sensor_size_px
        bit_depth = scene.bit_depth
        board_half_extent_mm = scene.board_half_extent_mm

        def render(
            self,
            state: SceneState,
            *,
            roi: tuple[int, int, int, int],
            seed: Sequence[int],
            bit_depth: int,
            exposure_scale: float,
            gain_db: float,
        ) -> NDArray[np.uint16]:
            calls.append(roi)
            return scene.render(
                state,
                roi=roi,
                seed=seed,
                bit_depth=bit_depth,
                exposure_scale=exposure_scale,
                gain_db=gain_db,
            )

    spy: Scene = Spy()
    with SimulatedCamera(spy, StaticState(SceneState(300.0)), seed=SEED) as camera:
        applied = camera.configure(CameraSettings("Mono12", roi=Roi(64, 48, 5056, 5072)))
        assert applied.roi == Roi(64, 48, 5056, 5072)
        frame = camera.grab()
    assert calls == [(5056, 5072, 64, 48)]
    assert (frame.width, frame.height, frame.offset_x, frame.offset_y) == (64, 48, 5056, 5072)
    assert frame.pixels.shape == (48, 64)
    np.testing.assert_array_equal(frame.pixels, direct(scene, frame, 300.0))


@pytest.mark.parametrize(
    "roi",
    [Roi(600, 400, 4600, 0), Roi(600, 400, 0, 4800), Roi(5121, 10)],
    ids=["right", "bottom", "too-wide"],
)
def test_roi_outside_the_sensor_is_refused(white_cam: SimulatedCamera, roi: Roi) -> None:
    before = white_cam.settings()
    with pytest.raises(InvalidSetting, match="does not fit the 5120x5120 sensor"):
        white_cam.configure(CameraSettings("Mono12", roi=roi))
    assert white_cam.settings() == before


def test_no_roi_means_the_full_sensor(white_cam: SimulatedCamera) -> None:
    applied = white_cam.configure(CameraSettings("Mono12"))
    assert applied.roi == Roi(5120, 5120)
    assert applied.exposure_us == 10000.0 and applied.gain == 0.0  # None: unchanged


def test_pixel_formats(bench: SimulatedBench, cam: SimulatedCamera, scene: PlenopticScene) -> None:
    cam.configure(CameraSettings("Mono8", roi=ROI))
    mono8 = cam.grab()
    assert mono8.pixels.dtype == np.uint8 and (mono8.pixel_format, mono8.bit_depth) == ("Mono8", 8)
    state = bench.scene_state()  # nothing moves: the state of the grab
    native = direct(scene, mono8, state.object_distance_mm, state.board_offset_mm)
    np.testing.assert_array_equal(mono8.pixels, (native >> 4).astype(np.uint8))  # top 8 bits

    cam.configure(CameraSettings("Mono12", roi=ROI))
    mono12 = cam.grab()
    cam.configure(CameraSettings("Mono16", roi=ROI))
    mono16 = cam.grab()
    assert (mono12.pixels.dtype, mono12.bit_depth, mono12.max_count) == (np.uint16, 12, 4095)
    assert (mono16.pixels.dtype, mono16.bit_depth, mono16.max_count) == (np.uint16, 16, 65535)
    assert mono12.pixels.max() <= 4095 < mono16.pixels.max()
    # same light, 16x finer counts (right-aligned at 16 bits)
    ratio = float(mono16.pixels.mean()) / float(mono12.pixels.mean())
    assert ratio == pytest.approx(65535 / 4095, rel=0.01)


def test_unknown_and_unoffered_pixel_formats(white_cam: SimulatedCamera) -> None:
    before = white_cam.settings()
    with pytest.raises(InvalidSetting, match="not supported"):
        white_cam.configure(CameraSettings("RGB8"))
    with pytest.raises(FeatureMissing) as err:
        white_cam.configure(CameraSettings("Mono10"))
    assert err.value.feature == "PixelFormat" and err.value.offered == SIM_PIXEL_FORMATS
    assert white_cam.settings() == before


def signal(frame: Frame) -> float:
    """Mean counts above the black level (8 DN at 12 bits)."""
    return float(frame.pixels.mean()) - 8.0


def test_exposure_scales_the_signal_and_saturates(white_cam: SimulatedCamera) -> None:
    reference = white_cam.grab()
    assert reference.exposure_us == 10000.0
    white_cam.configure(CameraSettings("Mono12", exposure_us=5000.0, roi=ROI))
    half = white_cam.grab()
    assert half.exposure_us == 5000.0
    assert signal(half) / signal(reference) == pytest.approx(0.5, rel=0.01)
    white_cam.configure(CameraSettings("Mono12", exposure_us=40000.0, roi=ROI))
    long = white_cam.grab()
    assert long.pixels.max() == 4095  # saturated at the bit depth, never wrapped
    assert np.mean(long.pixels == 4095) > 0.3
    white_cam.configure(CameraSettings("Mono12", exposure_us=5000.0, gain=6.0, roi=ROI))
    gained = white_cam.grab()
    assert gained.gain == 6.0
    assert signal(gained) / signal(half) == pytest.approx(10 ** (6 / 20), rel=0.01)


@pytest.mark.parametrize(
    "settings, name",
    [
        (CameraSettings("Mono12", exposure_us=1.0), "ExposureTime"),
        (CameraSettings("Mono12", exposure_us=61e6), "ExposureTime"),
        (CameraSettings("Mono12", exposure_us=float("nan")), "ExposureTime"),
        (CameraSettings("Mono12", gain=-1.0), "Gain"),
        (CameraSettings("Mono12", gain=60.0), "Gain"),
    ],
)
def test_out_of_range_settings(
    white_cam: SimulatedCamera, settings: CameraSettings, name: str
) -> None:
    before = white_cam.settings()
    with pytest.raises(InvalidSetting, match=f"{name}=.* outside the camera's range"):
        white_cam.configure(settings)
    assert white_cam.settings() == before


# --------------------------------------------------------------------------- metadata, noise


def test_metadata(white_cam: SimulatedCamera) -> None:
    before = time.time_ns()
    frames = [white_cam.grab() for _ in range(3)]
    after = time.time_ns()
    assert [f.frame_id for f in frames] == [1, 2, 3]
    stamps = [f.timestamp_ns for f in frames]
    assert 0 < stamps[0] < stamps[1] < stamps[2]
    assert all(before <= f.host_timestamp_ns <= after for f in frames)
    f = frames[0]
    assert (f.pixel_format, f.exposure_us, f.gain, f.bit_depth) == ("Mono12", 10000.0, 0.0, 12)
    assert (f.width, f.height, f.offset_x, f.offset_y) == (600, 400, 2260, 2360)
    assert f.device == white_cam.label and f.pixels.flags.c_contiguous


def test_noise_is_seeded_by_seed_and_frame_id(scene: PlenopticScene) -> None:
    def first_two(seed: int) -> list[NDArray[np.uint16]]:
        with SimulatedCamera(scene, StaticState(SceneState(300.0)), seed=seed) as camera:
            camera.configure(CameraSettings("Mono12", roi=Roi(200, 100, 2460, 2510)))
            return [camera.grab().pixels for _ in range(2)]

    a, b, c = first_two(1), first_two(1), first_two(2)
    np.testing.assert_array_equal(a[0], b[0])
    np.testing.assert_array_equal(a[1], b[1])
    assert not np.array_equal(a[0], a[1])  # fresh noise every frame
    assert not np.array_equal(a[0], c[0])  # another seed, another noise


# --------------------------------------------------------------------------- faults


def test_injected_timeout_waits_then_raises(white_cam: SimulatedCamera) -> None:
    white_cam.fail_next_grabs("timeout")
    start = time.monotonic()
    with pytest.raises(CameraTimeout, match="0.2 s"):
        white_cam.grab(timeout_s=0.2)
    assert time.monotonic() - start >= 0.2
    assert white_cam.grab().frame_id == 2  # the timed-out trigger used id 1


def test_injected_incomplete_frame(white_cam: SimulatedCamera) -> None:
    white_cam.fail_next_grabs("incomplete", count=2)
    for expected_id in (1, 2):
        with pytest.raises(IncompleteFrame) as err:
            white_cam.grab()
        assert err.value.frame_id == expected_id and err.value.status == "missing-packets"
    assert white_cam.grab().frame_id == 3


def test_injected_loss_then_reopen(white_cam: SimulatedCamera) -> None:
    white_cam.fail_next_grabs("lost")
    with pytest.raises(CameraLost):
        white_cam.grab()
    assert white_cam.is_open
    assert white_cam.grab().pixels.shape == (400, 600)  # reopened once by the next grab
    with pytest.raises(ValueError, match="unknown fault"):
        white_cam.fail_next_grabs("melted")  # type: ignore[arg-type]


def test_unplug_and_replug(white_cam: SimulatedCamera, scene: PlenopticScene) -> None:
    white_cam.unplug()
    with pytest.raises(CameraLost, match="unplugged"):
        white_cam.grab()
    with pytest.raises(CameraLost, match="still unplugged"):
        white_cam.reconnect(timeout_s=0.1)
    timer = threading.Timer(0.1, white_cam.replug)
    timer.start()
    white_cam.reconnect(timeout_s=5.0)  # waits for the camera to come back
    timer.join()
    assert white_cam.grab().exposure_us == 10000.0  # settings kept
    other = SimulatedCamera(scene, StaticState(SceneState(300.0)))
    other.unplug()
    with pytest.raises(CameraNotFound):
        other.open()


def test_bad_timeout_is_refused(white_cam: SimulatedCamera) -> None:
    with pytest.raises(InvalidSetting):
        white_cam.grab(timeout_s=0)


def test_bench_close_is_idempotent(scene: PlenopticScene) -> None:
    bench = SimulatedBench(scene, speedup=SPEEDUP).start()
    url = bench.url
    assert url.startswith("/dev/")
    bench.camera.open()
    bench.close()
    bench.close()
    assert not bench.camera.is_open
