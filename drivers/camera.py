"""Camera interface, data types and the GenICam (SFNC) logic shared by the backends.

Conventions (all backends):

* Pixels: ``Frame.pixels`` is a C-contiguous ``(height, width)`` array, ``uint8`` for
  ``Mono8`` and ``uint16`` for the 10/12/14/16-bit formats.  Counts are right-aligned
  (a Mono12 pixel is 0..4095), exactly as the camera sent them: no scaling, no flip.
* Pixel formats: Mono8, Mono10/12/14/16 (16-bit words) and the packed Mono10p, Mono12p,
  Mono10Packed, Mono12Packed, decoded by :mod:`drivers.pixels` (with a range check).
* Units: exposure in microseconds (SFNC ``ExposureTime``, or the SFNC 1.x
  ``ExposureTimeAbs``), gain in the unit of the camera's gain feature (``Gain``: dB on
  SFNC cameras; a camera with only ``GainRaw`` takes raw device units: ``Frame.gain_feature``
  says which), black level in the unit of ``BlackLevel`` (or ``BlackLevelRaw``), sizes and
  offsets in sensor pixels, timestamps in nanoseconds, temperatures in °C.
* Trigger: ``trigger="software"`` (default): ``grab`` fires ``TriggerSoftware``
  (``TriggerSelector=FrameStart``, ``TriggerMode=On``, ``TriggerSource=Software``) and
  returns the frame of that trigger, never an older one.  ``trigger="Line1"`` (any
  ``TriggerSource`` entry): the frame is started by that hardware line; ``grab`` drops
  older frames and waits for the next one.
* Features: only standard SFNC names are used, and each one is checked to exist (and to be
  writable) before use; a missing one raises :class:`FeatureMissing` naming it.
* Errors: see :mod:`drivers.camera_errors`.  A damaged frame raises ``IncompleteFrame``;
  a partial frame is never returned.
"""

from __future__ import annotations

import os
import types
from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import Protocol, Self, runtime_checkable

import numpy as np

from drivers.camera_errors import InvalidSetting
from drivers.pixels import MONO_FORMATS, decode_mono, format_name, mono_format

#: Pixel formats the drivers decode, with their significant bits (PFNC names).
MONO_BIT_DEPTH: dict[str, int] = {name: f.bit_depth for name, f in MONO_FORMATS.items()}

#: PFNC codes of the supported formats (as found in GVSP leaders / GenTL buffer info).
PFNC_CODES: dict[str, int] = {name: f.code for name, f in MONO_FORMATS.items()}

#: Trigger value that means "one software trigger per grab" (anything else is a line).
SOFTWARE_TRIGGER = "software"


def bit_depth(pixel_format: str) -> int:
    """Significant bits per pixel of a supported mono format (``"Mono12p"`` -> 12)."""
    return mono_format(pixel_format).bit_depth


def pixel_format_name(code_or_name: int | str) -> str:
    """PFNC name from a PFNC code (or pass a name through)."""
    return format_name(code_or_name)


# --------------------------------------------------------------------------- data types


@dataclass(frozen=True)
class Roi:
    """Region of interest in sensor pixels; (offset_x, offset_y) is the top-left corner."""

    width: int
    height: int
    offset_x: int = 0
    offset_y: int = 0

    def __post_init__(self) -> None:
        if self.width <= 0 or self.height <= 0 or self.offset_x < 0 or self.offset_y < 0:
            raise InvalidSetting(f"invalid ROI {self}: sizes must be > 0 and offsets >= 0")


@dataclass(frozen=True)
class CameraSettings:
    """What ``configure`` applies.  ``None`` means "leave the camera's current value".

    Attributes:
        pixel_format: PFNC name, one of :data:`MONO_BIT_DEPTH`.
        exposure_us: exposure time in microseconds (``ExposureTime`` / ``ExposureTimeAbs``).
        gain: analog gain in the unit of the camera's gain feature (``Gain`` in dB, else
            ``GainRaw`` in device units).
        roi: region of interest; ``None`` selects the full sensor.
        black_level: ``BlackLevel`` (else ``BlackLevelRaw``) value.
        trigger: ``"software"`` or the ``TriggerSource`` line (``"Line1"``).
        trigger_activation: ``TriggerActivation`` for a line trigger (``"RisingEdge"``);
            None leaves the camera's.
        flat_field: ``"off"``: switch on-camera flat-field (shading) correction off when
            the camera has it; ``"leave"``: leave it.  Read back: ``"on"`` or ``"off"``
            (also for a camera without such a correction).
    """

    pixel_format: str = "Mono8"
    exposure_us: float | None = None
    gain: float | None = None
    roi: Roi | None = None
    black_level: float | None = None
    trigger: str = SOFTWARE_TRIGGER
    trigger_activation: str | None = None
    flat_field: str = "off"


@dataclass(frozen=True)
class TransportSettings:
    """Streaming parameters (``[camera.transport]``); ``None`` leaves the default.

    Attributes:
        packet_size: GigE Vision stream packet size in bytes (``GevSCPSPacketSize``;
            jumbo frames: up to 9000 with an MTU of 9000).  None: negotiated.
        packet_delay_ns: inter-packet delay in ns (``GevSCPD``, converted to ticks).
        throughput_limit_bps: ``DeviceLinkThroughputLimit`` in bytes/s (mode switched On);
            USB3 Vision through Aravis: the bandwidth limit.
        buffer_count: stream buffers queued to the driver.
        socket_buffer_bytes: the host's receive buffer for the GVSP socket (Aravis);
            None: two frames, never below ``net.core.rmem_default``.  The kernel caps
            it at ``net.core.rmem_max``.
        frame_retention_ms: how long missing packets are waited for (Aravis).
        packet_resend: ask the camera to resend lost packets.
        packet_socket: Aravis GigE Vision: receive through a memory-mapped ``AF_PACKET``
            ring (needs ``CAP_NET_RAW``; no ``net.core.rmem_max`` cap) instead of the UDP
            socket.  None (automatic): the socket for frames that fit in a quarter of the
            default socket buffer (``net.core.rmem_default``), the ring for larger ones when the
            process may open it.  While Aravis 0.8 sets the ring up, every packet on the
            interface is read as stream data for a moment, and a stray packet can cost
            the next frame (seen on a busy loopback).
    """

    packet_size: int | None = None
    packet_delay_ns: int | None = None
    throughput_limit_bps: int | None = None
    buffer_count: int = 3
    socket_buffer_bytes: int | None = None
    frame_retention_ms: float = 2000.0
    packet_resend: bool = True
    packet_socket: bool | None = None


@dataclass(frozen=True)
class CameraInfo:
    """Identity and capabilities of an opened camera.

    Attributes:
        vendor, model, serial: ``DeviceVendorName``, ``DeviceModelName``, ``DeviceSerialNumber``.
        pixel_formats: every ``PixelFormat`` entry the camera offers (PFNC names).
        sensor_width, sensor_height: full sensor size in pixels.
        exposure_limits_us: (min, max) of ``ExposureTime`` in µs, ``None`` if not offered.
        gain_limits: (min, max) of ``Gain``, ``None`` if not offered.
        device: how the camera was addressed (``gige://127.0.0.1``, ``gentl://x.cti#SN``).
        backend: ``"aravis"`` or ``"harvesters"``.
        firmware: ``DeviceFirmwareVersion`` (else ``DeviceVersion``), "" if not offered.
        gain_feature: ``"Gain"``, ``"GainRaw"`` or None (no gain control).
        has_temperature: the camera offers ``DeviceTemperature``.
        principal_point_px: the optical axis on the full sensor (px) when the camera
            knows it (a simulated camera does; real ones: None).
    """

    vendor: str
    model: str
    serial: str
    pixel_formats: tuple[str, ...]
    sensor_width: int
    sensor_height: int
    exposure_limits_us: tuple[float, float] | None
    gain_limits: tuple[float, float] | None
    device: str
    backend: str
    firmware: str = ""
    gain_feature: str | None = None
    has_temperature: bool = False
    principal_point_px: tuple[float, float] | None = None

    @property
    def supported_pixel_formats(self) -> tuple[str, ...]:
        """The offered formats that the drivers can decode."""
        return tuple(f for f in self.pixel_formats if f in MONO_BIT_DEPTH)


@dataclass(frozen=True, eq=False)
class Frame:
    """One image and its metadata.

    Attributes:
        pixels: ``(height, width)`` array, uint8 (Mono8) or uint16 (>8 bit), right-aligned.
        frame_id: the transport's frame / block id (wraps; GigE Vision 1.x ids are 16 bit).
        timestamp_ns: device timestamp converted to nanoseconds (0 if the camera gives none).
        host_timestamp_ns: host wall clock (``time.time_ns`` epoch) when the frame arrived.
        exposure_us: exposure time in µs in force for this frame (``None`` if not offered).
        gain: gain in force for this frame (``None`` if not offered).
        pixel_format: PFNC name of the delivered data.
        width, height, offset_x, offset_y: delivered region in sensor pixels.
        bit_depth: significant bits per pixel (8, 10, 12, 14 or 16).
        device: the camera's address / id, as in :attr:`CameraInfo.device`.
        gain_feature: the feature ``gain`` was read from (``"Gain"`` dB, ``"GainRaw"``).
        black_level: black level in force (None if not offered).
        temperature_c: ``DeviceTemperature`` (°C) read right after the frame arrived.
        trigger: ``"software"`` or the trigger line that started the frame.
        flat_field: on-camera flat-field correction in force: ``"off"`` or ``"on"``.
    """

    pixels: np.ndarray
    frame_id: int
    timestamp_ns: int
    host_timestamp_ns: int
    exposure_us: float | None
    gain: float | None
    pixel_format: str
    width: int
    height: int
    offset_x: int
    offset_y: int
    bit_depth: int
    device: str = ""
    gain_feature: str | None = None
    black_level: float | None = None
    temperature_c: float | None = None
    trigger: str = SOFTWARE_TRIGGER
    flat_field: str | None = None

    def metadata(self) -> dict[str, object]:
        """What the camera applied for this frame, JSON-ready (keys with a value only):
        ``exposure_us``, ``gain``, ``gain_feature``, ``black_level``, ``temperature_c``,
        ``pixel_format``, ``bit_depth``, ``trigger``, ``flat_field``."""
        out: dict[str, object] = {}
        for key in (
            "exposure_us",
            "gain",
            "gain_feature",
            "black_level",
            "temperature_c",
            "pixel_format",
            "bit_depth",
            "trigger",
            "flat_field",
        ):
            value = getattr(self, key)
            if value is not None:
                out[key] = value
        return out

    @property
    def max_count(self) -> int:
        """Largest possible pixel count for the bit depth (4095 for Mono12)."""
        return (1 << self.bit_depth) - 1


# --------------------------------------------------------------------------- interface


class CameraContext(ABC):
    """``with camera:`` opens the camera and closes it on exit (shared by the backends)."""

    @abstractmethod
    def open(self) -> None:
        """Connect to the camera."""

    @abstractmethod
    def close(self) -> None:
        """Release the camera."""

    def __enter__(self) -> Self:
        self.open()
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: types.TracebackType | None,
    ) -> None:
        self.close()


@runtime_checkable
class Camera(Protocol):
    """What the station uses from a camera.  Both backends implement it.

    Usage::

        with AravisCamera(address="192.168.10.2") as cam:
            cam.configure(CameraSettings("Mono12", exposure_us=5000, gain=0.0))
            frame = cam.grab(timeout_s=2.0)
    """

    @property
    def is_open(self) -> bool: ...

    def open(self) -> None:
        """Connect to the camera, take control, set up the software trigger."""
        ...

    def close(self) -> None:
        """Stop acquisition and release the camera.  Safe to call twice."""
        ...

    def __enter__(self) -> Self: ...

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: types.TracebackType | None,
    ) -> None: ...

    def info(self) -> CameraInfo:
        """Identity and capabilities (read once at open)."""
        ...

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Apply settings; return what the camera actually applied (read back)."""
        ...

    def grab(self, timeout_s: float = 5.0) -> Frame:
        """Return the next frame within ``timeout_s`` s (software trigger: fire one first)."""
        ...

    def exposure_limits_us(self) -> tuple[float, float]:
        """(min, max) ``ExposureTime`` in µs for the current configuration."""
        ...

    def reconnect(self, timeout_s: float = 10.0) -> None:
        """Reopen a lost camera (retrying until ``timeout_s``) and re-apply the settings."""
        ...

    def temperature_c(self) -> float | None:
        """``DeviceTemperature`` now (°C), or None when the camera has none or it cannot be read."""
        ...


# --------------------------------------------------------------------------- GenICam nodes


class NodeMap(Protocol):
    """Minimal typed access to a GenICam node map, implemented by each backend.

    Transport failures inside these calls are raised as the backend's typed errors
    (``CameraLost`` ...); a feature that does not exist makes ``is_available`` false.
    """

    def is_available(self, name: str) -> bool: ...
    def is_writable(self, name: str) -> bool: ...
    def get(self, name: str) -> int | float | str | bool: ...
    def set(self, name: str, value: int | float | str | bool) -> None: ...
    def execute(self, name: str) -> None: ...
    def enum_entries(self, name: str) -> tuple[str, ...]: ...
    def bounds(self, name: str) -> tuple[float, float]: ...
    def increment(self, name: str) -> float | None: ...


def create_camera(
    backend: str,
    *,
    address: str | None = None,
    serial: str | None = None,
    cti: str | os.PathLike[str] | None = None,
    allow_discovery: bool = False,
    interface: str = "gige",
    transport: TransportSettings | None = None,
) -> Camera:
    """Build (not open) a camera from configuration values.

    Args:
        backend: ``"aravis"`` (GigE Vision through Aravis) or ``"harvesters"`` (GenTL).
        address: aravis: camera IPv4 address or host name; harvesters: device id in the
            producer's list (optional).
        serial: camera serial number; aravis: checked against the camera at ``address``.
        cti: harvesters: path of the GenTL producer (.cti).
        allow_discovery: aravis only: allow GigE Vision discovery (broadcast) to find a
            camera by serial without address.  Off by default.
        interface: aravis only: ``"gige"`` (by address) or ``"usb3"`` (USB3 Vision by
            serial, with the GigE Vision interface disabled: no network traffic).
        transport: streaming parameters (``[camera.transport]``).

    The backend module is imported here, so its library is only needed when used.
    """
    if backend == "aravis":
        from drivers.aravis_camera import AravisCamera

        return AravisCamera(
            address,
            serial=serial,
            allow_discovery=allow_discovery,
            interface=interface,
            transport=transport,
        )
    if backend == "harvesters":
        from drivers.harvesters_camera import HarvestersCamera

        if cti is None:
            raise ValueError('backend "harvesters" needs the GenTL producer path (cti)')
        return HarvestersCamera(cti, serial=serial, device_id=address, transport=transport)
    raise ValueError(f'unknown camera backend {backend!r}: "aravis" or "harvesters"')


__all__ = [
    "MONO_BIT_DEPTH",
    "PFNC_CODES",
    "SOFTWARE_TRIGGER",
    "Camera",
    "CameraInfo",
    "CameraSettings",
    "Frame",
    "NodeMap",
    "Roi",
    "TransportSettings",
    "bit_depth",
    "create_camera",
    "decode_mono",
    "pixel_format_name",
]
