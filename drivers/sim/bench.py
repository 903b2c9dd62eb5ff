"""The simulated bench: emulated Zaber rail and XY stage plus a simulated camera.

:class:`SimulatedBench` starts a :class:`~drivers.sim.zaber_emulator.ZaberEmulator` on a
pseudo-terminal (the rail and the XY stage on one chain; the station drives them with
the real Zaber driver through :attr:`SimulatedBench.url`) and builds a
:class:`~drivers.sim.sim_camera.SimulatedCamera` whose every frame shows the board at
the axes' **true** positions, read from the emulator (not from the driver):

* object distance ``u = zero_object_distance_mm + direction · rail_mm`` (OPTICS.md §4),
  ``rail_mm`` the rail's physical position from its home sensor (mm);
* board offset = XY-stage position − ``alignment_mm`` (mm; stage x moves the board
  along board X, stage y along board Y): at the alignment position the standard corner
  (0, 0) is on the optical axis;
* **white rule**: when ``max(|offset x|, |offset y|) > white_offset_mm`` (default: the
  scene's board half-extent, 150 mm) the point on the optical axis lies in the board's
  plain light border and the frame is the flat-field (white) image; otherwise the
  board is rendered at that offset.  (A real white position must also keep the
  patterned area out of the field of view, up to ~55 mm around the axis for the full
  GMAX0505 sensor at u = 350 mm; the default white position, 200 mm from the
  alignment, does for the simulated 2816 px window.)

Axes that are not emulated (a real rail in front of a simulated camera) can feed the
scene from any position source: :meth:`SimulatedBench.use_rail_position`,
:meth:`SimulatedBench.use_stage_position`.

Typical use (units: mm)::

    with SimulatedBench(scene, zero_object_distance_mm=250.0, speedup=20.0) as bench:
        rail = open_rail(bench.url, ZaberAxisConfig(name="rail", microstep_um=0.047625))
        rail.home(); rail.move_abs_mm(50.0)
        with bench.camera as cam:
            frame = cam.grab()          # the board at u = 300 mm
"""

from __future__ import annotations

import math
import os
import threading
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType

from drivers.sim.sim_camera import Scene, SceneState, SimulatedCamera
from drivers.sim.zaber_emulator import AxisSpec, DeviceSpec, ZaberEmulator


@dataclass(frozen=True)
class BenchAxis:
    """One emulated axis: its address on the chain and its mechanics.

    Attributes:
        device: Zaber device number (1-99).
        axis: axis number on the device (1-9).
        microstep_um: size of one microstep (µm).
        travel_mm: travel from the home sensor (mm).
        speed_mm_s: initial maximum speed (mm/s).
        accel_mm_s2: initial acceleration (mm/s²).
        start_mm: physical position at power-up (mm from home; unknown to the driver).
    """

    device: int
    axis: int
    microstep_um: float = 0.1
    travel_mm: float = 100.0
    speed_mm_s: float = 20.0
    accel_mm_s2: float = 200.0
    start_mm: float = 10.0

    def spec(self) -> AxisSpec:
        """The emulator's description of this axis; the travel is rounded *up* to whole
        microsteps, so that ``travel_mm`` itself is reachable."""
        usteps = math.ceil(self.travel_mm * 1000.0 / self.microstep_um - 1e-6)
        return AxisSpec(
            microstep_um=self.microstep_um,
            travel_mm=usteps * self.microstep_um / 1000.0,
            speed_mm_s=self.speed_mm_s,
            accel_mm_s2=self.accel_mm_s2,
            start_mm=self.start_mm,
        )


DEFAULT_RAIL = BenchAxis(device=1, axis=1, microstep_um=0.047625, travel_mm=100.0)
DEFAULT_STAGE_X = BenchAxis(device=2, axis=1, microstep_um=0.09921875, travel_mm=300.0)
DEFAULT_STAGE_Y = BenchAxis(device=2, axis=2, microstep_um=0.09921875, travel_mm=300.0)


def chain_specs(axes: list[BenchAxis]) -> list[DeviceSpec]:
    """Emulator devices holding ``axes``; axis numbers not in use get a default axis.

    Raises ValueError if two axes share a device and axis number.
    """
    by_device: dict[int, dict[int, AxisSpec]] = {}
    for ax in axes:
        slots = by_device.setdefault(ax.device, {})
        if ax.axis in slots:
            raise ValueError(f"two bench axes on device {ax.device} axis {ax.axis}")
        slots[ax.axis] = ax.spec()
    return [
        DeviceSpec(
            address=device,
            axes=tuple(slots.get(n, AxisSpec()) for n in range(1, max(slots) + 1)),
            serial=100000 + device,
        )
        for device, slots in sorted(by_device.items())
    ]


class SimulatedBench:
    """Emulated rail and XY stage on one pty chain, and a camera that looks at them.

    Args:
        scene: what the camera images (None: no camera, motion only).
        zero_object_distance_mm: object distance u at rail position 0 (mm).
        direction: +1 (rail position grows away from the camera) or -1.
        rail: the emulated rail axis (None: not emulated, see :meth:`use_rail_position`).
        stage_x, stage_y: the emulated XY-stage axes (None: not emulated).
        alignment_mm: XY-stage position (mm) putting the standard corner on the axis.
        white_offset_mm: board offset (mm) beyond which frames are flat fields
            (default: the scene's board half-extent).
        speedup: the emulated motion runs this many times faster than real time.
        camera_seed: noise seed of the camera.
        reference_exposure_us: exposure (µs) at which the scene's white level holds.
        frame_cache: directory where the camera keeps and reuses its rendered frames.
    """

    def __init__(
        self,
        scene: Scene | None = None,
        *,
        zero_object_distance_mm: float = 250.0,
        direction: int = 1,
        rail: BenchAxis | None = DEFAULT_RAIL,
        stage_x: BenchAxis | None = DEFAULT_STAGE_X,
        stage_y: BenchAxis | None = DEFAULT_STAGE_Y,
        alignment_mm: tuple[float, float] = (100.0, 100.0),
        white_offset_mm: float | None = None,
        speedup: float = 1.0,
        camera_seed: int = 0,
        reference_exposure_us: float = 10000.0,
        frame_cache: str | os.PathLike[str] | None = None,
    ) -> None:
        if direction not in (1, -1):
            raise ValueError(f"direction must be +1 or -1, got {direction}")
        if (stage_x is None) != (stage_y is None):
            raise ValueError("emulate both XY-stage axes or neither")
        self.zero_object_distance_mm = float(zero_object_distance_mm)
        self.direction = direction
        self.rail = rail
        self.stage_x = stage_x
        self.stage_y = stage_y
        self.alignment_mm = (float(alignment_mm[0]), float(alignment_mm[1]))
        if white_offset_mm is None:
            white_offset_mm = scene.board_half_extent_mm if scene is not None else 150.0
        self.white_offset_mm = float(white_offset_mm)
        self.speedup = float(speedup)
        axes = [ax for ax in (rail, stage_x, stage_y) if ax is not None]
        self._emulator = (
            ZaberEmulator(chain_specs(axes), transport="pty", speedup=speedup) if axes else None
        )
        self._rail_source: Callable[[], float] | None = None
        self._stage_source: Callable[[], tuple[float, float]] | None = None
        self._lock = threading.Lock()
        self._camera = (
            SimulatedCamera(
                scene,
                self.scene_state,
                seed=camera_seed,
                reference_exposure_us=reference_exposure_us,
                frame_cache=frame_cache,
                principal_point_px=getattr(scene, "principal_point_px", None),
            )
            if scene is not None
            else None
        )

    # ------------------------------------------------------------------ lifecycle

    def start(self) -> SimulatedBench:
        """Start the emulator on a new pty (idempotent).  Raises OSError without ptys."""
        if self._emulator is not None:
            self._emulator.start()
        return self

    def close(self) -> None:
        """Close the camera and stop the emulator (idempotent)."""
        if self._camera is not None:
            self._camera.close()
        if self._emulator is not None:
            self._emulator.stop()

    def __enter__(self) -> SimulatedBench:
        return self.start()

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()

    # ------------------------------------------------------------------ parts

    @property
    def emulator(self) -> ZaberEmulator:
        """The Zaber emulator (fault injection, snapshots).  RuntimeError if none."""
        if self._emulator is None:
            raise RuntimeError("this bench emulates no axis")
        return self._emulator

    @property
    def url(self) -> str:
        """The pty path the Zaber driver opens (``/dev/pts/N``)."""
        return self.emulator.url

    @property
    def camera(self) -> SimulatedCamera:
        """The simulated camera (not opened).  RuntimeError if the bench has no scene."""
        if self._camera is None:
            raise RuntimeError("this bench has no simulated camera (no scene)")
        return self._camera

    def use_rail_position(self, source: Callable[[], float] | None) -> None:
        """Take the rail position (mm) from ``source`` instead of the emulator (None: back)."""
        with self._lock:
            self._rail_source = source

    def use_stage_position(self, source: Callable[[], tuple[float, float]] | None) -> None:
        """Take the XY-stage position (mm) from ``source`` instead of the emulator."""
        with self._lock:
            self._stage_source = source

    # ------------------------------------------------------------------ true state

    def _true_mm(self, ax: BenchAxis) -> float:
        snapshot = self.emulator.snapshot(ax.device, ax.axis)
        return snapshot.physical * ax.microstep_um / 1000.0

    def rail_mm(self) -> float:
        """The rail's true position (mm from its home sensor), moving or not."""
        with self._lock:
            source = self._rail_source
        if source is not None:
            return float(source())
        if self.rail is None:
            raise RuntimeError("the rail is not emulated and no rail position source is set")
        return self._true_mm(self.rail)

    def stage_xy_mm(self) -> tuple[float, float]:
        """The XY stage's true position (mm from its home sensors)."""
        with self._lock:
            source = self._stage_source
        if source is not None:
            x, y = source()
            return (float(x), float(y))
        if self.stage_x is None or self.stage_y is None:
            raise RuntimeError("the XY stage is not emulated and no position source is set")
        return (self._true_mm(self.stage_x), self._true_mm(self.stage_y))

    def object_distance_mm(self, rail_mm: float | None = None) -> float:
        """Object distance u (mm) at ``rail_mm`` (default: the rail's true position)."""
        rail = self.rail_mm() if rail_mm is None else rail_mm
        return self.zero_object_distance_mm + self.direction * rail

    def board_offset_mm(
        self, stage_xy_mm: tuple[float, float] | None = None
    ) -> tuple[float, float]:
        """Board offset (mm) = stage position − alignment position."""
        x, y = self.stage_xy_mm() if stage_xy_mm is None else stage_xy_mm
        return (x - self.alignment_mm[0], y - self.alignment_mm[1])

    def is_white(self, board_offset_mm: tuple[float, float]) -> bool:
        """True when the optical axis sees the board's plain light border (the white rule)."""
        return max(abs(board_offset_mm[0]), abs(board_offset_mm[1])) > self.white_offset_mm

    def scene_state(self) -> SceneState:
        """What the camera sees now (read from the true axis positions)."""
        u_mm = self.object_distance_mm()
        offset = self.board_offset_mm()
        return SceneState(
            object_distance_mm=u_mm,
            board_offset_mm=offset,
            white=self.is_white(offset),
        )


__all__ = [
    "DEFAULT_RAIL",
    "DEFAULT_STAGE_X",
    "DEFAULT_STAGE_Y",
    "BenchAxis",
    "SimulatedBench",
    "chain_specs",
]
