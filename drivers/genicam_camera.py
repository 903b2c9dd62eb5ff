"""What the GenICam backends (Aravis, harvesters) share: the camera on an SFNC session.

:class:`GenICamCamera` implements the :class:`drivers.camera.Camera` methods that do
not depend on the camera library: opening, identity, limits, configuration, feature
reads and the reconnect loop, on top of the backend's :class:`drivers.sfnc.SfncCamera`
(the *session*, present while the camera is open and answering).  A backend
(:class:`drivers.aravis_camera.AravisCamera`,
:class:`drivers.harvesters_camera.HarvestersCamera`) opens and releases the session,
stops acquisition, grabs, and translates its library's errors (``_gerrors``).

Conventions:

* every public method holds the camera's lock (an ``RLock``);
* a camera that stopped answering is *lost*: it stays open (``is_open``), its session is
  dropped, and the next call that needs the session makes one bounded reopen attempt
  (``_reopen_once``) before using it; :meth:`GenICamCamera.reconnect` retries until a
  deadline (s, ``time.monotonic``), 0.2 s apart;
* the settings last asked for are re-applied after a reopen (by the backend's
  ``_open_session``); :meth:`GenICamCamera.settings` is what the camera read back.
"""

from __future__ import annotations

import threading
import time
from abc import abstractmethod
from collections.abc import Callable
from contextlib import AbstractContextManager

from drivers.camera import (
    SOFTWARE_TRIGGER,
    CameraContext,
    CameraInfo,
    CameraSettings,
    bit_depth,
)
from drivers.camera_errors import (
    CameraBusy,
    CameraError,
    CameraLost,
    CameraNotFound,
    CameraTimeout,
    FeatureMissing,
    InvalidSetting,
)
from drivers.sfnc import SfncCamera

GErrors = Callable[[str], AbstractContextManager[None]]
"""The camera's translation of its library's errors for an operation named by a feature."""


class GenICamCamera(CameraContext):
    """The library-independent part of a GenICam camera backend.

    Args:
        label: how the camera is addressed, used in every error and log line
            (``gige://127.0.0.1``, ``gentl://x.cti#SN``).

    A subclass sets ``backend`` and implements ``close``, ``grab``, ``_open_session``,
    ``_stop_acquisition``, ``_mark_lost``, ``_reopen_once`` and ``_gerrors``.
    """

    backend: str

    def __init__(self, label: str) -> None:
        self.label = label
        #: Start-up warnings and notes (transport settings not applied, socket buffer
        #: capped by net.core.rmem_max), for the log and ``lfcal devices --check``.
        self.warnings: list[str] = []
        self._lock = threading.RLock()
        self._sfnc: SfncCamera | None = None
        self._info: CameraInfo | None = None
        self._applied: CameraSettings | None = None
        self._requested: CameraSettings | None = None
        self._lost = False

    # ------------------------------------------------------------------ Camera interface

    @property
    def is_open(self) -> bool:
        """True between ``open()`` and ``close()`` (also while the camera is lost)."""
        return self._sfnc is not None or self._lost

    def open(self) -> None:
        """Connect, take control, read the camera info and set up the software trigger."""
        with self._lock:
            if self.is_open:
                return
            self._open_session()

    def temperature_c(self) -> float | None:
        """``DeviceTemperature`` (°C) now; None without one (or when closed)."""
        sfnc = self._sfnc
        return None if sfnc is None else sfnc.temperature_c()

    def info(self) -> CameraInfo:
        """Identity and capabilities, read at open."""
        with self._lock:
            self._require_open()
            assert self._info is not None
            return self._info

    def exposure_limits_us(self) -> tuple[float, float]:
        """(min, max) ``ExposureTime`` in µs, read from the camera now; ``FeatureMissing``
        if the camera has none."""
        with self._lock:
            return self._session().exposure_limits_us()

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Stop acquisition, apply ``settings``, return the values read back.

        Raises ``FeatureMissing`` for a pixel format or feature the camera does not offer
        and ``InvalidSetting`` for out-of-range values.  The settings are re-applied
        automatically after a reconnect.
        """
        with self._lock:
            bit_depth(settings.pixel_format)
            sfnc = self._session()
            self._stop_acquisition()
            try:
                self._applied = sfnc.apply(settings)
            except (FeatureMissing, InvalidSetting):
                self._applied = sfnc.read_settings()  # partly applied: record what is in force
                raise
            self._requested = settings
            return self._applied

    def read_feature(self, name: str) -> int | float | str | bool:
        """Current value of any GenICam feature (diagnostics); ``FeatureMissing`` if absent."""
        with self._lock:
            sfnc = self._session()
            sfnc.require(name)
            return sfnc.nodes.get(name)

    def settings(self) -> CameraSettings:
        """The settings in force (as read back after the last configure/open)."""
        with self._lock:
            self._require_open()
            assert self._applied is not None
            return self._applied

    def reconnect(self, timeout_s: float = 10.0) -> None:
        """Reopen the camera, retrying until ``timeout_s``; settings are re-applied.

        Raises ``CameraLost`` if the camera is still not answering at the deadline.
        """
        deadline = time.monotonic() + timeout_s
        with self._lock:
            self._drop_for_reconnect()
            while True:
                try:
                    self._reopen_once()
                    return
                except CameraLost:
                    if time.monotonic() >= deadline:
                        raise
                threading.Event().wait(min(0.2, max(0.0, deadline - time.monotonic())))

    # ------------------------------------------------------------------ for the backends

    def _require_open(self) -> None:
        if not self.is_open:
            raise CameraError("the camera is not open; call open() first", device=self.label)

    def _session(self) -> SfncCamera:
        """The live session, reopening once if the camera was lost."""
        self._require_open()
        self._notice_loss()
        if self._lost:
            self._reopen_once()
        assert self._sfnc is not None
        return self._sfnc

    def _set_up_session(self, sfnc: SfncCamera) -> None:
        """The end of opening: software trigger, identity, and the settings last asked for
        applied again (else the camera's read back)."""
        sfnc.setup_software_trigger()
        self._info = sfnc.read_info(backend=self.backend)
        if self._requested is not None:
            self._applied = sfnc.apply(self._requested)
        else:
            self._applied = sfnc.read_settings()

    def _open_again(self, failure: str) -> None:
        """Open the session of a lost camera; when it is not back (not found, lost, busy),
        stay lost and raise ``CameraLost`` (``failure``, then the reason)."""
        try:
            self._open_session()
        except (CameraNotFound, CameraLost, CameraBusy) as exc:
            self._lost = True
            raise CameraLost(f"{failure} ({exc.message})", device=self.label) from None

    def _notice_loss(self) -> None:
        """Mark the session lost when the backend learnt so between calls (default: no-op)."""

    def _drop_for_reconnect(self) -> None:
        """Forget the session before :meth:`reconnect` reopens it (default: mark it lost)."""
        self._mark_lost()

    def _check_timeout(self, timeout_s: float) -> None:
        """``InvalidSetting`` unless the grab timeout (s) is positive."""
        if timeout_s <= 0:
            raise InvalidSetting(f"timeout_s must be > 0, not {timeout_s}", device=self.label)

    def _fire_trigger(self, sfnc: SfncCamera) -> str:
        """Execute ``TriggerSoftware`` when the software trigger is in force; the trigger
        in force (``"software"`` or the line)."""
        trigger = self._applied.trigger if self._applied else SOFTWARE_TRIGGER
        if trigger == SOFTWARE_TRIGGER:
            sfnc.nodes.execute("TriggerSoftware")
        return trigger

    def _no_frame(self, timeout_s: float, trigger: str) -> CameraTimeout:
        """The error for a grab that saw no frame within ``timeout_s`` (s)."""
        return CameraTimeout(
            f"no frame within {timeout_s:g} s after the software trigger"
            if trigger == SOFTWARE_TRIGGER
            else f"no frame within {timeout_s:g} s: no pulse on trigger line {trigger}?",
            device=self.label,
        )

    @abstractmethod
    def _open_session(self) -> None:
        """Connect, build the session (``_sfnc``, ``_info``, ``_applied``) and clear ``_lost``;
        release everything again on failure."""

    @abstractmethod
    def _stop_acquisition(self) -> None:
        """Stop acquisition if it runs (before features that need it stopped are written)."""

    @abstractmethod
    def _mark_lost(self) -> None:
        """Set ``_lost`` and drop the session (the camera stopped answering)."""

    @abstractmethod
    def _reopen_once(self) -> None:
        """One bounded attempt to reopen a lost camera; ``CameraLost`` if it fails."""

    @abstractmethod
    def _gerrors(self, feature: str) -> AbstractContextManager[None]:
        """Translate the library's errors during an operation on ``feature`` into typed
        camera errors (marking the camera lost when it stopped answering)."""


__all__ = ["GErrors", "GenICamCamera"]
