"""What the simulated camera images, and how one of its frames is rendered.

:class:`SceneState` is the bench's physical state at one instant, :class:`Scene` the
renderer of raw counts (:class:`drivers.sim.plenoptic_scene.PlenopticScene` wraps the
calibration core's simulator), :data:`StateSource` what the camera asks for the state at
every grab.  :func:`render_frame` makes the :class:`Frame` of the state now: ``Mono12`` /
``Mono16`` are the scene digitized at 12 / 16 bits (counts right-aligned), ``Mono8`` the
top 8 bits of the sensor's native counts; exposure scales the signal relative to the
reference exposure (µs), gain (dB) the conversion gain; noise is seeded with
``[seed, frame_id]``.  Used by :class:`drivers.sim.sim_camera.SimulatedCamera`, which
re-exports these names.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from drivers.camera import CameraSettings, Frame, bit_depth
from drivers.camera_errors import CameraError


@dataclass(frozen=True)
class SceneState:
    """The physical state the camera images at one instant.

    Attributes:
        object_distance_mm: board-to-main-lens distance u (mm).
        board_offset_mm: where the board origin (standard corner) sits relative to the
            optical axis, in board X/Y (mm).
        white: True when the plain light area of the board fills the view (flat field).
    """

    object_distance_mm: float
    board_offset_mm: tuple[float, float] = (0.0, 0.0)
    white: bool = False


class Scene(Protocol):
    """What the simulated camera images: a sensor and a renderer of raw counts."""

    @property
    def name(self) -> str:
        """Short name of the scene (e.g. the simulator preset), used in the camera model."""
        ...

    @property
    def sensor_size_px(self) -> tuple[int, int]:
        """Full sensor ``(width, height)`` in px."""
        ...

    @property
    def bit_depth(self) -> int:
        """Native bits per pixel of the sensor's ADC."""
        ...

    @property
    def board_half_extent_mm(self) -> float:
        """Half-size of the board's patterned area (mm): beyond it the board is plain light."""
        ...

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
        """Raw counts of the window ``roi = (x, y, width, height)`` (px), right-aligned at
        ``bit_depth`` bits, with the signal scaled by ``exposure_scale`` (1 = reference
        exposure) and the conversion gain by ``gain_db`` (dB); noise seeded by ``seed``."""
        ...


StateSource = Callable[[], SceneState]
"""Returns the scene state now (called once per grab)."""


def render_frame(
    scene: Scene,
    state_source: StateSource,
    *,
    frame_id: int,
    settings: CameraSettings,
    timestamp_ns: int,
    seed: int,
    reference_exposure_us: float,
    temperature_c: Callable[[], float],
    label: str,
) -> tuple[Frame, SceneState]:
    """The frame of the state now, with ``settings`` (every field filled in), and that state.

    Args:
        scene: the renderer.
        state_source: called once for the state now.
        frame_id: the frame's id (noise seed ``[seed, frame_id]``).
        settings: pixel format, ROI (px), exposure (µs) and gain (dB) of the frame.
        timestamp_ns: the camera clock at the trigger (ns).
        seed: the camera's noise seed.
        reference_exposure_us: exposure (µs) at which the scene's white level holds.
        temperature_c: ``DeviceTemperature`` (°C), read once the frame is rendered.
        label: the camera's label (``device`` of the frame and of errors).

    Raises:
        CameraError: the state cannot be read, or the scene cannot be rendered there.
    """
    assert settings.roi is not None and settings.exposure_us is not None
    assert settings.gain is not None
    roi = settings.roi
    fmt = settings.pixel_format
    depth = bit_depth(fmt)
    native = scene.bit_depth
    render_depth = native if depth == 8 else depth
    try:
        state = state_source()
    except CameraError:
        raise
    except Exception as exc:  # a DeviceError of the bench, a KeyError ...
        raise CameraError(f"cannot read the simulated bench's state: {exc}", device=label) from exc
    try:
        counts = scene.render(
            state,
            roi=(roi.offset_x, roi.offset_y, roi.width, roi.height),
            seed=[seed, frame_id],
            bit_depth=render_depth,
            exposure_scale=settings.exposure_us / reference_exposure_us,
            gain_db=settings.gain,
        )
    except ValueError as exc:
        raise CameraError(
            f"the simulated scene cannot be rendered at {state}: {exc}",
            device=label,
            hint="the rail geometry (zero_object_distance_mm, direction) in the config",
        ) from exc
    if depth == 8:
        pixels: np.ndarray = (counts >> max(0, render_depth - 8)).astype(np.uint8)
    else:
        pixels = np.ascontiguousarray(counts, dtype=np.uint16)
    frame = Frame(
        pixels=pixels,
        frame_id=frame_id,
        timestamp_ns=timestamp_ns,
        host_timestamp_ns=time.time_ns(),
        exposure_us=settings.exposure_us,
        gain=settings.gain,
        pixel_format=fmt,
        width=roi.width,
        height=roi.height,
        offset_x=roi.offset_x,
        offset_y=roi.offset_y,
        bit_depth=depth,
        device=label,
        gain_feature="Gain",
        temperature_c=temperature_c(),
        flat_field="off",
    )
    return frame, state


__all__ = ["Scene", "SceneState", "StateSource", "render_frame"]
