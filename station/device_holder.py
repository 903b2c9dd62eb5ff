"""The station's devices as the one hardware worker holds them: opened, described, closed.

:class:`DeviceHolder` keeps the open ``StationDevices`` (or why they could not be
opened), their last description (identity, positions, homed state), and what the
sweep planner needs from them (the rail's travel, the camera's exposure range).
Whoever uses the devices holds :attr:`DeviceHolder.hw_lock`: the hardware worker
for a whole job, an HTTP request only to describe idle devices
(:meth:`DeviceHolder.describe_if_idle`), never waiting for a running job.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from typing import Any

from drivers.errors import DeviceError

REOPEN_INTERVAL_S = 5.0
"""Closed devices (after a fault) are tried again at most this often by
:meth:`DeviceHolder.describe_if_idle`."""


class DeviceHolder:
    """The devices opened by ``factory`` (a callable returning ``StationDevices``)."""

    def __init__(self, factory: Callable[[], Any]) -> None:
        self._factory = factory
        self.hw_lock = threading.Lock()
        """Held while the devices are used (by the hardware worker for a whole job)."""
        self.tried = threading.Event()
        """Set once the first attempt to open the devices has ended."""
        self.devices: Any | None = None
        """The open ``StationDevices``, None when closed."""
        self.error: str | None = None
        """Why the last opening failed (None after a success)."""
        self.described: dict[str, Any] = {}
        """The devices' last description (JSON-ready), kept while a job holds them."""
        self.rail_limits_mm: tuple[float, float] | None = None
        self.exposure_limits_us: tuple[float, float] | None = None
        self._last_open = 0.0

    @property
    def camera_serial(self) -> str | None:
        """The camera's serial number from the last description, if known."""
        serial = self.described.get("camera", {}).get("serial")
        return str(serial) if serial else None

    def ensure(self) -> Any:
        """The open devices, opened first if they are not (with :attr:`hw_lock` held).

        Raises what the factory raises (``DeviceError``, ``OSError``, ``ValueError``),
        after recording it in :attr:`error`.
        """
        if self.devices is None:
            self._last_open = time.monotonic()
            try:
                self.devices = self._factory()
                self.error = None
            except (DeviceError, OSError, ValueError) as exc:
                self.error = str(exc)
                raise
            try:
                self.described = self.devices.describe()
                lim = self.devices.rail.limits_mm()
                self.rail_limits_mm = (lim.min_mm, lim.max_mm)
                self.exposure_limits_us = self.devices.camera.exposure_limits_us()
            except DeviceError:
                pass
        return self.devices

    def close(self) -> None:
        """Close the devices (best effort; idempotent)."""
        devices, self.devices = self.devices, None
        if devices is not None:
            try:
                devices.close()
            except Exception:  # noqa: BLE001 - closing is best effort
                pass

    def describe_if_idle(self) -> dict[str, Any] | None:
        """Connection, identity, position and homed state (JSON-ready), or None when the
        devices are in use (:attr:`hw_lock` held elsewhere). Closed devices are tried
        again at most every :data:`REOPEN_INTERVAL_S`."""
        if not self.hw_lock.acquire(blocking=False):
            return None
        try:
            if self.devices is None and time.monotonic() - self._last_open >= REOPEN_INTERVAL_S:
                try:  # closed after a fault: are they back?
                    self.ensure()
                except Exception:  # noqa: BLE001 - reported below
                    pass
            if self.devices is None:
                return {"connected": False, "busy": False, "error": self.error}
            try:
                self.described = self.devices.describe()
            except DeviceError as exc:
                return {"connected": True, "busy": False, "error": str(exc)}
            return dict(self.described, connected=True, busy=False)
        finally:
            self.hw_lock.release()

    def describe_busy(self) -> dict[str, Any]:
        """The last description with ``busy: true`` (the devices belong to a job)."""
        return dict(self.described, connected=self.devices is not None, busy=True)
