"""Typed errors raised by the camera drivers (Aravis and harvesters backends).

Every error is a :class:`drivers.errors.DeviceError`: it carries ``device`` (how the camera
was addressed: ``gige://ADDRESS``, ``gentl://CTI_PATH#SERIAL`` ...) and ``hint`` (what the
operator should check), and its message names both, so a log line alone says which camera
failed and what to look at.

Hierarchy::

    CameraError
    ├── BackendUnavailable   Aravis / PyGObject / harvesters not importable
    ├── ProducerLoadError    a GenTL producer (.cti) that does not load
    ├── CameraNotFound       nothing answers at the address / serial not listed
    ├── CameraBusy           another application controls the camera
    ├── FeatureMissing       a GenICam feature / enum entry is not offered (or read-only)
    ├── InvalidSetting       a value out of range or not on the increment (also ValueError)
    ├── CameraTimeout        the camera answers but delivered no frame in time
    ├── IncompleteFrame      a frame arrived damaged (missing packets, wrong size ...)
    └── CameraLost           the camera stopped answering during a session
"""

from __future__ import annotations

from drivers.errors import DeviceError


class CameraError(DeviceError):
    """Base class of all camera errors (a :class:`drivers.errors.DeviceError`).

    Args:
        message: what went wrong, in one sentence.
        device: how the camera was addressed (``gige://ADDRESS``, ``gentl://CTI#SERIAL``).
        hint: what the operator should check; the class default when omitted.
    """

    default_hint = "the camera's power, network cable, IP configuration and the station config"

    def __init__(self, message: str, *, device: str = "", hint: str | None = None) -> None:
        super().__init__(message, device=device, hint=hint)


class BackendUnavailable(CameraError, ImportError):
    """The camera library (Aravis through PyGObject, or harvesters/genicam) cannot be imported."""

    default_hint = (
        "apt-get install gir1.2-aravis-0.8 libgirepository1.0-dev libcairo2-dev pkg-config, "
        "then pip install 'pygobject>=3.42,<3.51' (Aravis) or pip install harvesters genicam==1.5.0"
    )


class ProducerLoadError(CameraError):
    """A GenTL producer file (.cti) is missing or does not load as a producer."""

    default_hint = (
        "the camera.cti path, that the file is the vendor's 64-bit Linux GenTL producer and that "
        "its own libraries are installed (ldd FILE.cti)"
    )


class CameraNotFound(CameraError):
    """No camera answers at the configured address, or the serial is not in the device list."""

    default_hint = (
        "the camera's power and link LED, the cable, that the camera IP is in the subnet of "
        "the host's camera interface, and that no firewall blocks UDP port 3956"
    )


class CameraBusy(CameraError):
    """The camera answers but another application holds its control channel."""

    default_hint = (
        "that no other program (arv-viewer, a vendor viewer, another station process) has the "
        "camera open; a crashed client releases it after its heartbeat timeout (~3 s)"
    )


class FeatureMissing(CameraError):
    """A GenICam feature (or an enumeration entry of it) is not offered by the camera.

    Attributes:
        feature: the SFNC feature name (e.g. ``"ExposureTime"``).
        value: the requested enumeration entry, if the feature exists but the entry does not.
        offered: the entries the camera does offer, when known.
    """

    default_hint = (
        "the camera's feature list (arv-tool-0.8 -a ADDRESS features) and the camera settings"
    )

    def __init__(
        self,
        message: str,
        *,
        feature: str,
        value: str | None = None,
        offered: tuple[str, ...] = (),
        device: str = "",
        hint: str | None = None,
    ) -> None:
        self.feature = feature
        self.value = value
        self.offered = offered
        super().__init__(message, device=device, hint=hint)


class InvalidSetting(CameraError, ValueError):
    """A requested value is outside the camera's limits or not on its increment."""

    default_hint = "the [camera] settings against the camera's limits (CameraInfo)"


class CameraTimeout(CameraError, TimeoutError):
    """The camera is reachable but no frame arrived within the timeout."""

    default_hint = (
        "the trigger settings (TriggerMode/TriggerSource), that the exposure is shorter than "
        "the timeout, and the network (packet size / jumbo frames, firewall on the stream port)"
    )


class IncompleteFrame(CameraError):
    """A frame arrived incomplete or malformed; no partial frame is ever returned.

    Attributes:
        status: the transport's buffer status (e.g. ``"missing-packets"``, ``"timeout"``).
        frame_id: the frame (block) id of the damaged frame, when known.
    """

    default_hint = (
        "packet loss: the packet size against the link MTU (jumbo frames), the NIC's receive "
        "buffers and the cable; an inter-packet delay (GevSCPD) helps on busy links"
    )

    def __init__(
        self,
        message: str,
        *,
        status: str,
        frame_id: int | None = None,
        device: str = "",
        hint: str | None = None,
    ) -> None:
        self.status = status
        self.frame_id = frame_id
        super().__init__(message, device=device, hint=hint)


class CameraLost(CameraError):
    """The camera stopped answering (unplugged, powered off, rebooted, control taken over)."""

    default_hint = (
        "the camera's power and cable; when it is back the next grab reconnects once, "
        "or call reconnect()"
    )


__all__ = [
    "BackendUnavailable",
    "CameraBusy",
    "CameraError",
    "CameraLost",
    "CameraNotFound",
    "CameraTimeout",
    "FeatureMissing",
    "IncompleteFrame",
    "InvalidSetting",
    "ProducerLoadError",
]
