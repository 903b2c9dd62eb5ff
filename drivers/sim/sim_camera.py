"""A simulated camera implementing :class:`drivers.camera.Camera`, for tests and demos.

:class:`SimulatedCamera` renders, on every :meth:`~SimulatedCamera.grab`, the raw frame
of the board's *current* physical state, read from a state source (normally
:meth:`drivers.sim.bench.SimulatedBench.scene_state`, which reads the emulated rail and
XY stage).  It follows the same contract as the Aravis and harvesters backends:

* pixel formats ``Mono8``, ``Mono12``, ``Mono16``.  An unsupported name (``"RGB8"``)
  raises ``InvalidSetting`` (as :func:`drivers.camera.bit_depth` does for the backends);
  a decodable format the camera does not offer (``"Mono10"``) raises ``FeatureMissing``;
* ``Mono12`` / ``Mono16``: the scene is digitized at 12 / 16 bits, counts right-aligned
  (0..4095 / 0..65535; with the presets' 12-bit sensors Mono12 is exactly the
  simulator's ``render_frame``).  ``Mono8``: the top 8 bits of the sensor's native
  counts (``counts >> (native_bits - 8)``);
* exposure scales the signal: the scene's white level holds at ``reference_exposure_us``
  and is proportional to ``exposure_us`` (shot noise follows; counts saturate at the
  bit depth).  Gain (dB) scales the conversion gain by ``10^(gain/20)`` (read noise is
  in electrons, before the gain).  Limits: exposure ``exposure_limits_us``, gain
  ``gain_limits_db``; outside them ``InvalidSetting``;
* ROI: ``offset + size <= sensor`` or ``InvalidSetting``; only the window is rendered;
* noise is seeded with ``[seed, frame_id]``: reproducible, independent of grab order;
* metadata: ``frame_id`` counts from 1 (64-bit, no wrap), ``timestamp_ns`` is the
  camera clock (ns since :meth:`~SimulatedCamera.open`), ``host_timestamp_ns`` the host
  wall clock, plus exposure, gain, pixel format, ROI and bit depth.

The camera knows nothing about plenoptic optics: what it sees is a :class:`Scene`
(:class:`drivers.sim.plenoptic_scene.PlenopticScene` wraps ``calibration.simulator``),
injected by the caller.  With ``frame_cache=DIR`` (``[camera] frame_cache``) the camera
keeps its rendered frames on disk and reuses them for the same bench state
(:class:`drivers.sim.frame_cache.CachedScene`): the cache is the simulated camera's own
business, nothing outside it knows.  :class:`Scene`, :class:`SceneState`,
:data:`StateSource` and the rendering of one frame are in :mod:`drivers.sim.scene`
(re-exported here); the error wording of the checks is the GenICam backends'
(:mod:`drivers.sfnc_features`, :mod:`drivers.sfnc_roi`).

Trigger: software only (``trigger="software"``; a line trigger raises
``FeatureMissing``).  ``DeviceTemperature``: :attr:`SimulatedCamera.sensor_temperature_c`
(°C, settable), recorded in every frame like a real camera's.

Fault hooks for tests (each one consumed by the next grabs)::

    cam.fail_next_grabs("timeout")      # CameraTimeout after waiting timeout_s
    cam.fail_next_grabs("incomplete")   # IncompleteFrame (status "missing-packets")
    cam.fail_next_grabs("lost")         # CameraLost; the next grab reopens once
    cam.unplug() / cam.replug()         # absent: open/grab/reconnect fail until replugged

Rendering time is not counted against ``timeout_s`` (the simulator is much slower than
the camera it stands for; a full 5120 x 5120 frame takes seconds).
"""

from __future__ import annotations

import math
import os
import threading
import time
from collections import deque
from typing import Literal

from drivers.camera import (
    SOFTWARE_TRIGGER,
    CameraContext,
    CameraInfo,
    CameraSettings,
    Frame,
    Roi,
    bit_depth,
)
from drivers.camera_errors import (
    CameraError,
    CameraLost,
    CameraNotFound,
    CameraTimeout,
    IncompleteFrame,
    InvalidSetting,
)
from drivers.sfnc_features import missing_entry, out_of_range
from drivers.sfnc_roi import check_roi_fits
from drivers.sim.scene import Scene, SceneState, StateSource, render_frame

SIM_PIXEL_FORMATS: tuple[str, ...] = ("Mono8", "Mono12", "Mono16")
"""Pixel formats the simulated camera offers."""

FaultKind = Literal["timeout", "incomplete", "lost"]


class SimulatedCamera(CameraContext):
    """A software-triggered camera whose frames come from a :class:`Scene`.

    Args:
        scene: the renderer and its sensor.
        state: called at every grab for the current physical state of the bench.
        seed: noise seed; frame ``n`` uses ``[seed, n]``.
        reference_exposure_us: exposure (µs) at which the scene's white level holds.
        exposure_limits_us: (min, max) exposure (µs).
        gain_limits_db: (min, max) gain (dB).
        serial: ``DeviceSerialNumber`` reported by :meth:`info`.
        frame_cache: directory where rendered frames are kept and reused (None: none).
        principal_point_px: the scene's principal point (px, full sensor), reported in
            :meth:`info` (a real camera does not know it).

    Implements :class:`drivers.camera.Camera`.
    """

    backend = "simulated"
    vendor = "lfcal"

    def __init__(
        self,
        scene: Scene,
        state: StateSource,
        *,
        seed: int = 0,
        reference_exposure_us: float = 10000.0,
        exposure_limits_us: tuple[float, float] = (10.0, 60e6),
        gain_limits_db: tuple[float, float] = (0.0, 48.0),
        serial: str | None = None,
        frame_cache: str | os.PathLike[str] | None = None,
        principal_point_px: tuple[float, float] | None = None,
    ) -> None:
        if not reference_exposure_us > 0:
            raise ValueError("reference_exposure_us must be positive")
        lo, hi = exposure_limits_us
        if not 0 < lo <= reference_exposure_us <= hi:
            raise ValueError("exposure limits must satisfy 0 < min <= reference <= max")
        if not gain_limits_db[0] <= 0.0 <= gain_limits_db[1]:
            raise ValueError("gain limits must include 0 dB")
        if frame_cache is not None:
            from drivers.sim.frame_cache import CachedScene

            scene = CachedScene(scene, frame_cache)
        self._scene = scene
        self._state = state
        self.principal_point_px = principal_point_px
        #: ``DeviceTemperature`` (°C) of the simulated sensor, recorded with every frame.
        self.sensor_temperature_c = 38.5
        self.seed = seed
        self.reference_exposure_us = float(reference_exposure_us)
        self._exposure_limits = (float(lo), float(hi))
        self._gain_limits = (float(gain_limits_db[0]), float(gain_limits_db[1]))
        self.serial = serial or f"SIM-{scene.name}-{seed}"
        self.label = f"sim://{scene.name}"
        self._lock = threading.RLock()  # settings and state
        self._grab_lock = threading.Lock()  # serializes grabs (rendering is slow)
        self._open = False
        self._lost = False
        self._present = True
        self._t0_ns = 0
        self._frame_id = 0
        self._faults: deque[FaultKind] = deque()
        width, height = scene.sensor_size_px
        self._settings = CameraSettings(
            pixel_format="Mono12",
            exposure_us=self.reference_exposure_us,
            gain=0.0,
            roi=Roi(width, height),
        )
        #: The scene state of the last frame rendered (None before the first grab).
        self.last_state: SceneState | None = None

    # ------------------------------------------------------------------ lifecycle

    @property
    def is_open(self) -> bool:
        """True between ``open()`` and ``close()`` (also while the camera is lost)."""
        return self._open

    def open(self) -> None:
        """ "Connect" to the camera; raises CameraNotFound while it is unplugged."""
        with self._lock:
            if self._open:
                return
            if not self._present:
                raise CameraNotFound("the simulated camera is unplugged", device=self.label)
            self._open = True
            self._lost = False
            self._t0_ns = time.monotonic_ns()

    def close(self) -> None:
        """Release the camera.  Safe to call twice."""
        with self._lock:
            self._open = False
            self._lost = False

    # ------------------------------------------------------------------ Camera interface

    def temperature_c(self) -> float | None:
        """The simulated sensor's ``DeviceTemperature`` (°C)."""
        return self.sensor_temperature_c

    def info(self) -> CameraInfo:
        """Identity and capabilities."""
        with self._lock:
            self._require_open()
            width, height = self._scene.sensor_size_px
            return CameraInfo(
                vendor=self.vendor,
                model=f"plenoptic simulator ({self._scene.name})",
                serial=self.serial,
                pixel_formats=SIM_PIXEL_FORMATS,
                sensor_width=width,
                sensor_height=height,
                exposure_limits_us=self._exposure_limits,
                gain_limits=self._gain_limits,
                device=self.label,
                backend=self.backend,
                gain_feature="Gain",
                has_temperature=True,
                principal_point_px=self.principal_point_px,
            )

    @property
    def scene(self) -> Scene:
        """What the camera renders (a :class:`~drivers.sim.frame_cache.CachedScene` when
        frames are cached)."""
        return self._scene

    def exposure_limits_us(self) -> tuple[float, float]:
        """(min, max) exposure in µs."""
        with self._lock:
            self._require_open()
            return self._exposure_limits

    def settings(self) -> CameraSettings:
        """The settings in force (every field filled in)."""
        with self._lock:
            self._require_open()
            return self._settings

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Check everything, then apply ``settings``; return the settings in force.

        Raises ``InvalidSetting`` (unsupported pixel format, ROI outside the sensor,
        exposure or gain out of range) or ``FeatureMissing`` (a decodable format this
        camera does not offer).  Nothing is applied when a check fails.
        """
        with self._lock:
            bit_depth(settings.pixel_format)  # InvalidSetting for formats nobody decodes
            self._require_open()
            if settings.pixel_format not in SIM_PIXEL_FORMATS:
                raise missing_entry(
                    "PixelFormat", settings.pixel_format, SIM_PIXEL_FORMATS, device=self.label
                )
            width, height = self._scene.sensor_size_px
            roi = settings.roi if settings.roi is not None else Roi(width, height)
            check_roi_fits(roi, width, height, device=self.label)
            exposure = self._settings.exposure_us
            if settings.exposure_us is not None:
                exposure = self._check_range(
                    "ExposureTime", settings.exposure_us, self._exposure_limits
                )
            gain = self._settings.gain
            if settings.gain is not None:
                gain = self._check_range("Gain", settings.gain, self._gain_limits)
            if settings.trigger != SOFTWARE_TRIGGER:
                raise missing_entry(
                    "TriggerSource",
                    settings.trigger,
                    ("Software",),
                    device=self.label,
                    hint='the simulated camera has the software trigger only: trigger = "software"',
                )
            self._settings = CameraSettings(
                pixel_format=settings.pixel_format, exposure_us=exposure, gain=gain, roi=roi
            )
            return self._settings

    def grab(self, timeout_s: float = 5.0) -> Frame:
        """Render and return the frame of the bench's current state.

        Raises:
            CameraTimeout, IncompleteFrame, CameraLost: injected faults (see the module).
            CameraError: the scene cannot be rendered (e.g. u <= F) or its state not read.
        """
        if not timeout_s > 0:
            raise InvalidSetting(f"timeout_s must be > 0, not {timeout_s}", device=self.label)
        with self._grab_lock:  # one trigger at a time; info()/settings() stay available
            with self._lock:
                self._require_open()
                if not self._present:
                    self._lost = True
                    raise CameraLost("the simulated camera is unplugged", device=self.label)
                self._lost = False  # a lost camera that is back is reopened by this grab
                fault = self._faults.popleft() if self._faults else None
                if fault == "lost":
                    self._lost = True
                    raise CameraLost(
                        "the camera stopped answering (injected fault)", device=self.label
                    )
                self._frame_id += 1
                frame_id = self._frame_id
                settings = self._settings
                timestamp_ns = time.monotonic_ns() - self._t0_ns  # the trigger instant
            if fault == "timeout":
                threading.Event().wait(timeout_s)
                raise CameraTimeout(
                    f"no frame within {timeout_s:g} s after the software trigger (injected)",
                    device=self.label,
                )
            if fault == "incomplete":
                raise IncompleteFrame(
                    f"frame {frame_id} arrived with missing packets (injected)",
                    status="missing-packets",
                    frame_id=frame_id,
                    device=self.label,
                )
            return self._render(frame_id, settings, timestamp_ns)

    def reconnect(self, timeout_s: float = 10.0) -> None:
        """Reopen the camera, waiting up to ``timeout_s`` for it to be plugged in again.

        Raises ``CameraLost`` if it is still unplugged at the deadline.
        """
        deadline = time.monotonic() + timeout_s
        while True:
            with self._lock:
                self._require_open()
                if self._present:
                    self._lost = False
                    return
            if time.monotonic() >= deadline:
                raise CameraLost(
                    f"the simulated camera is still unplugged after {timeout_s:g} s",
                    device=self.label,
                )
            threading.Event().wait(min(0.05, max(0.0, deadline - time.monotonic())))

    # ------------------------------------------------------------------ fault hooks

    def fail_next_grabs(self, kind: FaultKind, count: int = 1) -> None:
        """Make the next ``count`` grabs fail with ``kind`` (queued after earlier faults)."""
        if kind not in ("timeout", "incomplete", "lost"):
            raise ValueError(f"unknown fault kind {kind!r}")
        with self._lock:
            self._faults.extend([kind] * count)

    def unplug(self) -> None:
        """The camera disappears: grabs raise CameraLost, open raises CameraNotFound."""
        with self._lock:
            self._present = False

    def replug(self) -> None:
        """The camera is back: the next grab (or :meth:`reconnect`) reopens it."""
        with self._lock:
            self._present = True

    # ------------------------------------------------------------------ internals

    def _require_open(self) -> None:
        if not self._open:
            raise CameraError("the camera is not open; call open() first", device=self.label)

    def _check_range(self, name: str, value: float, limits: tuple[float, float]) -> float:
        lo, hi = limits
        if not (math.isfinite(value) and lo <= value <= hi):
            raise out_of_range(name, value, lo, hi, device=self.label)
        return float(value)

    def _render(self, frame_id: int, settings: CameraSettings, timestamp_ns: int) -> Frame:
        """The frame of the state now, with ``settings``; ``timestamp_ns``: the trigger."""
        frame, state = render_frame(
            self._scene,
            self._state,
            frame_id=frame_id,
            settings=settings,
            timestamp_ns=timestamp_ns,
            seed=self.seed,
            reference_exposure_us=self.reference_exposure_us,
            temperature_c=lambda: self.sensor_temperature_c,
            label=self.label,
        )
        self.last_state = state
        return frame


__all__ = [
    "SIM_PIXEL_FORMATS",
    "FaultKind",
    "Scene",
    "SceneState",
    "SimulatedCamera",
    "StateSource",
]
