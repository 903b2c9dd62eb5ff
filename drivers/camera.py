"""Camera interface, data types and the GenICam (SFNC) logic shared by the backends.

Conventions (all backends):

* Pixels: ``Frame.pixels`` is a C-contiguous ``(height, width)`` array, ``uint8`` for
  ``Mono8`` and ``uint16`` for the 10/12/14/16-bit formats.  Counts are right-aligned
  (a Mono12 pixel is 0..4095), exactly as the camera sent them: no scaling, no flip.
* Units: exposure in microseconds (SFNC ``ExposureTime``), gain in the camera's ``Gain``
  unit (dB for SFNC-compliant cameras), sizes and offsets in sensor pixels, timestamps in
  nanoseconds.
* Trigger: ``grab`` uses a software trigger (``TriggerSelector=FrameStart``,
  ``TriggerMode=On``, ``TriggerSource=Software``, execute ``TriggerSoftware``) and returns
  the frame of that trigger, never an older one.
* Features: only standard SFNC names are used, and each one is checked to exist (and to be
  writable) before use; a missing one raises :class:`FeatureMissing` naming it.
* Errors: see :mod:`drivers.camera_errors`.  A damaged frame raises ``IncompleteFrame``;
  a partial frame is never returned.
"""

from __future__ import annotations

import os
import types
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from typing import Protocol, Self, runtime_checkable

import numpy as np

from drivers.camera_errors import FeatureMissing, IncompleteFrame, InvalidSetting

#: Pixel formats the drivers decode, with their significant bits (PFNC names).
MONO_BIT_DEPTH: dict[str, int] = {
    "Mono8": 8,
    "Mono10": 10,
    "Mono12": 12,
    "Mono14": 14,
    "Mono16": 16,
}

#: PFNC codes of the supported formats (as found in GVSP leaders / GenTL buffer info).
PFNC_CODES: dict[str, int] = {
    "Mono8": 0x01080001,
    "Mono10": 0x01100003,
    "Mono12": 0x01100005,
    "Mono14": 0x01100025,
    "Mono16": 0x01100007,
}
PFNC_NAMES: dict[int, str] = {code: name for name, code in PFNC_CODES.items()}


def bit_depth(pixel_format: str) -> int:
    """Significant bits per pixel of a supported mono format (``"Mono12"`` -> 12)."""
    try:
        return MONO_BIT_DEPTH[pixel_format]
    except KeyError:
        raise InvalidSetting(
            f"pixel format {pixel_format!r} is not supported by the drivers",
            hint=f"use one of {', '.join(MONO_BIT_DEPTH)} (packed formats are not decoded)",
        ) from None


def bytes_per_pixel(pixel_format: str) -> int:
    """Bytes per pixel in the transfer buffer: 1 for Mono8, 2 for the unpacked >8-bit formats."""
    return 1 if bit_depth(pixel_format) == 8 else 2


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
        exposure_us: exposure time in microseconds (SFNC ``ExposureTime``).
        gain: analog gain in the camera's ``Gain`` unit (dB on SFNC cameras).
        roi: region of interest; ``None`` selects the full sensor.
    """

    pixel_format: str = "Mono8"
    exposure_us: float | None = None
    gain: float | None = None
    roi: Roi | None = None


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
        """Fire one software trigger and return its frame within ``timeout_s`` seconds."""
        ...

    def exposure_limits_us(self) -> tuple[float, float]:
        """(min, max) ``ExposureTime`` in µs for the current configuration."""
        ...

    def reconnect(self, timeout_s: float = 10.0) -> None:
        """Reopen a lost camera (retrying until ``timeout_s``) and re-apply the settings."""
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


#: Exposure features in order of preference: SFNC >= 2.0 name, then the SFNC 1.x name.
EXPOSURE_FEATURES = ("ExposureTime", "ExposureTimeAbs")


@dataclass
class SfncCamera:
    """SFNC feature logic on top of a :class:`NodeMap`, shared by the backends.

    Attributes:
        nodes: the remote device's node map.
        device: label used in error messages (``gige://127.0.0.1`` ...).
    """

    nodes: NodeMap
    device: str
    feature_hint: str = field(
        default="the camera's feature list (arv-tool-0.8 -a ADDRESS features)"
    )

    # -- checks -----------------------------------------------------------------------

    def has(self, name: str) -> bool:
        """True if the feature exists and is currently available."""
        return self.nodes.is_available(name)

    def require(self, name: str, *, writable: bool = False) -> None:
        """Raise :class:`FeatureMissing` unless ``name`` exists (and is writable)."""
        if not self.nodes.is_available(name):
            raise FeatureMissing(
                f"the camera does not offer the GenICam feature {name!r}",
                feature=name,
                device=self.device,
                hint=self.feature_hint,
            )
        if writable and not self.nodes.is_writable(name):
            raise FeatureMissing(
                f"the GenICam feature {name!r} is not writable now",
                feature=name,
                device=self.device,
                hint="that acquisition is stopped and no other application controls the camera",
            )

    def check_enum(self, name: str, entry: str) -> None:
        """Raise unless the writable enumeration ``name`` offers ``entry``."""
        self.require(name, writable=True)
        offered = self.nodes.enum_entries(name)
        if entry not in offered:
            raise FeatureMissing(
                f"{name} has no entry {entry!r}; offered: {', '.join(offered) or 'none'}",
                feature=name,
                value=entry,
                offered=offered,
                device=self.device,
                hint=f"choose one of the offered {name} values",
            )

    def set_enum(self, name: str, entry: str) -> None:
        """Set an enumeration after checking the feature and the entry exist."""
        self.check_enum(name, entry)
        if self.nodes.get(name) != entry:
            self.nodes.set(name, entry)

    def check_number(self, name: str, value: float, *, integer: bool = False) -> None:
        """Raise unless ``name`` is writable and ``value`` is within bounds (and on the
        increment, for integers)."""
        self.require(name, writable=True)
        lo, hi = self.nodes.bounds(name)
        if not lo <= value <= hi:
            raise InvalidSetting(
                f"{name}={value:g} is outside the camera's range [{lo:g}, {hi:g}]",
                device=self.device,
                hint=f"a {name} within [{lo:g}, {hi:g}]",
            )
        if integer:
            inc = int(self.nodes.increment(name) or 1)
            if (int(value) - int(lo)) % inc:
                raise InvalidSetting(
                    f"{name}={int(value)} is not on the camera's increment {inc} (from {int(lo)})",
                    device=self.device,
                    hint=f"{name} = {int(lo)} + k*{inc}",
                )

    def set_number(self, name: str, value: float, *, integer: bool = False) -> None:
        """Set a numeric feature after checking existence, bounds and increment."""
        self.check_number(name, value, integer=integer)
        self.nodes.set(name, int(value) if integer else float(value))

    # -- identity and limits ------------------------------------------------------------

    def read_string(self, name: str, default: str = "") -> str:
        """A string feature, or ``default`` if the camera does not offer it."""
        return str(self.nodes.get(name)) if self.has(name) else default

    def sensor_size(self) -> tuple[int, int]:
        """Full sensor (width, height): SensorWidth/Height, else WidthMax/HeightMax, else
        the upper bound of Width/Height."""
        for wname, hname in (("SensorWidth", "SensorHeight"), ("WidthMax", "HeightMax")):
            if self.has(wname) and self.has(hname):
                return int(self.nodes.get(wname)), int(self.nodes.get(hname))
        self.require("Width")
        self.require("Height")
        return int(self.nodes.bounds("Width")[1]), int(self.nodes.bounds("Height")[1])

    def exposure_feature(self) -> str | None:
        """The exposure feature the camera offers (SFNC name), or None."""
        return next((n for n in EXPOSURE_FEATURES if self.has(n)), None)

    def exposure_limits_us(self) -> tuple[float, float]:
        """(min, max) exposure in µs; raises ``FeatureMissing`` if no exposure feature."""
        name = self.exposure_feature()
        if name is None:
            raise FeatureMissing(
                "the camera offers no exposure control (ExposureTime)",
                feature="ExposureTime",
                device=self.device,
                hint=self.feature_hint,
            )
        lo, hi = self.nodes.bounds(name)
        return float(lo), float(hi)

    def gain_limits(self) -> tuple[float, float] | None:
        """(min, max) of ``Gain`` or None if the camera has no ``Gain`` feature."""
        if not self.has("Gain"):
            return None
        lo, hi = self.nodes.bounds("Gain")
        return float(lo), float(hi)

    def read_info(self, *, backend: str) -> CameraInfo:
        """Read identity and capabilities from the standard SFNC features."""
        self.require("PixelFormat")
        name = self.exposure_feature()
        return CameraInfo(
            vendor=self.read_string("DeviceVendorName"),
            model=self.read_string("DeviceModelName"),
            serial=self.read_string("DeviceSerialNumber") or self.read_string("DeviceID"),
            pixel_formats=self.nodes.enum_entries("PixelFormat"),
            sensor_width=self.sensor_size()[0],
            sensor_height=self.sensor_size()[1],
            exposure_limits_us=self.exposure_limits_us() if name else None,
            gain_limits=self.gain_limits(),
            device=self.device,
            backend=backend,
        )

    # -- configuration ------------------------------------------------------------------

    def setup_software_trigger(self) -> None:
        """Continuous acquisition, one frame per ``TriggerSoftware`` (SFNC FrameStart)."""
        if self.has("AcquisitionMode") and self.nodes.is_writable("AcquisitionMode"):
            self.set_enum("AcquisitionMode", "Continuous")
        if self.has("TriggerSelector") and "FrameStart" in self.nodes.enum_entries(
            "TriggerSelector"
        ):
            self.set_enum("TriggerSelector", "FrameStart")
        self.set_enum("TriggerMode", "On")
        self.set_enum("TriggerSource", "Software")
        self.require("TriggerSoftware")

    def current_roi(self) -> Roi:
        """The ROI in force (offsets read as 0 if the camera has no OffsetX/Y)."""
        ox = int(self.nodes.get("OffsetX")) if self.has("OffsetX") else 0
        oy = int(self.nodes.get("OffsetY")) if self.has("OffsetY") else 0
        return Roi(int(self.nodes.get("Width")), int(self.nodes.get("Height")), ox, oy)

    def _full_roi(self, roi: Roi | None) -> Roi:
        sensor_w, sensor_h = self.sensor_size()
        return roi if roi is not None else Roi(sensor_w, sensor_h)

    def _check_roi(self, roi: Roi) -> None:
        sensor_w, sensor_h = self.sensor_size()
        if roi.offset_x + roi.width > sensor_w or roi.offset_y + roi.height > sensor_h:
            raise InvalidSetting(
                f"ROI {roi} does not fit the {sensor_w}x{sensor_h} sensor",
                device=self.device,
                hint="offset + size <= sensor size",
            )
        for axis, offset in (("OffsetX", roi.offset_x), ("OffsetY", roi.offset_y)):
            if offset and not self.has(axis):
                raise FeatureMissing(
                    f"an ROI offset needs {axis}, which the camera does not offer",
                    feature=axis,
                    device=self.device,
                    hint="use a ROI at offset 0 or a camera with OffsetX/OffsetY",
                )
        for name, value in (("Width", roi.width), ("Height", roi.height)):
            self.require(name, writable=True)
            lo, _ = self.nodes.bounds(name)
            inc = int(self.nodes.increment(name) or 1)
            if value < lo or (value - int(lo)) % inc:
                raise InvalidSetting(
                    f"ROI {name.lower()} {value} is not a legal {name} "
                    f"(min {int(lo)}, increment {inc})",
                    device=self.device,
                    hint=f"{name} = {int(lo)} + k*{inc}",
                )
        for name, value in (("OffsetX", roi.offset_x), ("OffsetY", roi.offset_y)):
            if value:
                inc = int(self.nodes.increment(name) or 1)
                if value % inc:
                    raise InvalidSetting(
                        f"ROI {name} {value} is not a multiple of the camera's increment {inc}",
                        device=self.device,
                        hint=f"{name} = k*{inc}",
                    )

    def _apply_roi(self, roi: Roi) -> None:
        # Offsets to 0 first so that any width/height up to the sensor size is legal,
        # then the size, then the wanted offsets.
        for axis in ("OffsetX", "OffsetY"):
            if self.has(axis) and int(self.nodes.get(axis)) != 0:
                self.set_number(axis, 0, integer=True)
        self.set_number("Width", roi.width, integer=True)
        self.set_number("Height", roi.height, integer=True)
        if roi.offset_x:
            self.set_number("OffsetX", roi.offset_x, integer=True)
        if roi.offset_y:
            self.set_number("OffsetY", roi.offset_y, integer=True)

    def validate(self, settings: CameraSettings) -> None:
        """Check everything ``apply`` will write, before writing anything.

        Raises ``FeatureMissing`` (format/feature not offered) or ``InvalidSetting``.
        """
        bit_depth(settings.pixel_format)  # can the drivers decode it?
        self.check_enum("PixelFormat", settings.pixel_format)
        self._check_roi(self._full_roi(settings.roi))
        if settings.exposure_us is not None:
            name = self.exposure_feature()
            if name is None:
                self.exposure_limits_us()  # raises FeatureMissing
            else:
                self.check_number(name, settings.exposure_us)
        if settings.gain is not None:
            self.check_number("Gain", settings.gain)

    def _auto_off(self, name: str) -> None:
        if (
            self.has(name)
            and self.nodes.is_writable(name)
            and "Off" in self.nodes.enum_entries(name)
        ):
            self.set_enum(name, "Off")

    def apply(self, settings: CameraSettings) -> CameraSettings:
        """Validate, then apply ``settings`` (acquisition must be stopped); return the values
        read back from the camera."""
        self.validate(settings)
        self.set_enum("PixelFormat", settings.pixel_format)
        self._apply_roi(self._full_roi(settings.roi))
        name = self.exposure_feature()
        if settings.exposure_us is not None and name is not None:
            self._auto_off("ExposureAuto")
            self.set_number(name, settings.exposure_us)
        if settings.gain is not None:
            self._auto_off("GainAuto")
            self.set_number("Gain", settings.gain)
        return self.read_settings()

    def read_settings(self) -> CameraSettings:
        """The settings in force, read from the camera."""
        exposure_name = self.exposure_feature()
        return CameraSettings(
            pixel_format=str(self.nodes.get("PixelFormat")),
            exposure_us=float(self.nodes.get(exposure_name)) if exposure_name else None,
            gain=float(self.nodes.get("Gain")) if self.has("Gain") else None,
            roi=self.current_roi(),
        )


def decode_mono(
    data: bytes | memoryview | np.ndarray,
    *,
    width: int,
    height: int,
    pixel_format: str,
    device: str,
    frame_id: int | None = None,
    copy: bool = True,
) -> np.ndarray:
    """Turn a transfer buffer into a ``(height, width)`` array.

    Unpacked mono formats only: Mono8 -> uint8; Mono10/12/14/16 -> uint16 from
    little-endian 16-bit words (PFNC), counts right-aligned.  Raises ``IncompleteFrame``
    if the buffer is shorter than ``width * height`` pixels.  With ``copy=False`` and a
    writable uint8 array (already a private copy) the result is a view of it.
    """
    bpp = bytes_per_pixel(pixel_format)
    need = width * height * bpp
    raw = data.reshape(-1).view(np.uint8) if isinstance(data, np.ndarray) else None
    if raw is None:
        raw = np.frombuffer(data, dtype=np.uint8)
        copy = True
    if raw.size < need:
        raise IncompleteFrame(
            f"frame {frame_id} holds {raw.size} bytes, {width}x{height} {pixel_format} needs {need}",
            status="size-mismatch",
            frame_id=frame_id,
            device=device,
            hint="the payload size / ROI settings; a frame was cut short",
        )
    if bpp == 1:
        pixels = raw[:need].reshape(height, width)
    else:
        pixels = raw[:need].view("<u2").reshape(height, width).astype(np.uint16, copy=False)
    if copy or not pixels.flags.writeable or not pixels.flags.c_contiguous:
        pixels = pixels.copy()
    return pixels


def pixel_format_name(code_or_name: int | str) -> str:
    """PFNC name from a PFNC code (or pass a name through)."""
    if isinstance(code_or_name, str):
        return code_or_name
    return PFNC_NAMES.get(code_or_name, f"0x{code_or_name:08x}")


def create_camera(
    backend: str,
    *,
    address: str | None = None,
    serial: str | None = None,
    cti: str | os.PathLike[str] | None = None,
    allow_discovery: bool = False,
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

    The backend module is imported here, so its library is only needed when used.
    """
    if backend == "aravis":
        from drivers.aravis_camera import AravisCamera

        return AravisCamera(address, serial=serial, allow_discovery=allow_discovery)
    if backend == "harvesters":
        from drivers.harvesters_camera import HarvestersCamera

        if cti is None:
            raise ValueError('backend "harvesters" needs the GenTL producer path (cti)')
        return HarvestersCamera(cti, serial=serial, device_id=address)
    raise ValueError(f'unknown camera backend {backend!r}: "aravis" or "harvesters"')


__all__ = [
    "EXPOSURE_FEATURES",
    "MONO_BIT_DEPTH",
    "PFNC_CODES",
    "Camera",
    "CameraInfo",
    "CameraSettings",
    "Frame",
    "NodeMap",
    "Roi",
    "SfncCamera",
    "bit_depth",
    "bytes_per_pixel",
    "create_camera",
    "decode_mono",
    "pixel_format_name",
]
