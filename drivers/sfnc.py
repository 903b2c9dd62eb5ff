"""SFNC feature logic shared by the camera backends (on top of a :class:`NodeMap`).

Feature names (GenICam SFNC), each checked to exist before use, with the fallbacks
older cameras need:

* exposure: ``ExposureTime`` (µs), else the SFNC 1.x ``ExposureTimeAbs``;
* gain: ``Gain`` (dB), else ``GainRaw`` (device units, an integer); ``GainSelector``
  is set to ``All`` when offered;
* black level: ``BlackLevel``, else ``BlackLevelRaw`` (``BlackLevelSelector=All``);
* temperature: ``DeviceTemperature`` (°C), with ``DeviceTemperatureSelector=Sensor``
  when offered, read per frame;
* trigger: ``TriggerSelector=FrameStart``, ``TriggerMode=On``, ``TriggerSource``
  ``Software`` or a line (``Line1``...), ``TriggerActivation`` for lines;
* flat-field (shading) correction, which vendors name differently (none is SFNC):
  :data:`FLAT_FIELD_FEATURES`; switched off when asked (the white image must be the
  sensor's raw response) and its state recorded with every frame;
* transport: ``GevSCPSPacketSize``, ``GevSCPD``, ``DeviceLinkThroughputLimitMode`` /
  ``DeviceLinkThroughputLimit`` (see :class:`drivers.camera.TransportSettings`).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

from drivers.camera import (
    SOFTWARE_TRIGGER,
    CameraInfo,
    CameraSettings,
    NodeMap,
    Roi,
    TransportSettings,
    bit_depth,
)
from drivers.camera_errors import CameraError, FeatureMissing, InvalidSetting

log = logging.getLogger(__name__)

GAIN_FEATURES = ("Gain", "GainRaw")
BLACK_LEVEL_FEATURES = ("BlackLevel", "BlackLevelRaw")
#: On-camera flat-field / shading correction switches: (feature, value that means off).
FLAT_FIELD_FEATURES: tuple[tuple[str, str | bool], ...] = (
    ("FlatFieldCorrectionEnable", False),
    ("FlatFieldCorrection", "Off"),
    ("FFCEnable", False),
    ("ShadingEnable", False),
    ("flatfieldCorrectionMode", "Off"),
)
TEMPERATURE_SELECTORS = ("Sensor", "Mainboard", "Device")


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

    def gain_feature(self) -> str | None:
        """``"Gain"`` (dB), else ``"GainRaw"`` (device units), else None."""
        return next((n for n in GAIN_FEATURES if self.has(n)), None)

    def black_level_feature(self) -> str | None:
        """``"BlackLevel"``, else ``"BlackLevelRaw"``, else None."""
        return next((n for n in BLACK_LEVEL_FEATURES if self.has(n)), None)

    def gain_limits(self) -> tuple[float, float] | None:
        """(min, max) of the gain feature, or None if the camera has no gain control."""
        name = self.gain_feature()
        if name is None:
            return None
        lo, hi = self.nodes.bounds(name)
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
            firmware=self.read_string("DeviceFirmwareVersion") or self.read_string("DeviceVersion"),
            gain_feature=self.gain_feature(),
            has_temperature=self.has("DeviceTemperature"),
        )

    # -- per-frame read-outs --------------------------------------------------------------

    def select_temperature_sensor(self) -> None:
        """``DeviceTemperatureSelector`` = the sensor (or the first offered fallback)."""
        if not self.has("DeviceTemperatureSelector"):
            return
        offered = self.nodes.enum_entries("DeviceTemperatureSelector")
        choice = next((t for t in TEMPERATURE_SELECTORS if t in offered), None)
        if choice is not None and self.nodes.is_writable("DeviceTemperatureSelector"):
            self.set_enum("DeviceTemperatureSelector", choice)

    def temperature_c(self) -> float | None:
        """``DeviceTemperature`` in °C, or None when the camera has none or the read fails
        (a temperature must never cost a frame)."""
        try:
            if not self.has("DeviceTemperature"):
                return None
            return float(self.nodes.get("DeviceTemperature"))
        except (CameraError, TypeError, ValueError) as exc:
            log.debug("%s: DeviceTemperature not read: %s", self.device, exc)
            return None

    # -- configuration ------------------------------------------------------------------

    def setup_trigger(self, trigger: str = SOFTWARE_TRIGGER, activation: str | None = None) -> None:
        """Continuous acquisition, one frame per trigger (SFNC ``FrameStart``).

        ``trigger`` is ``"software"`` (``TriggerSoftware`` per grab) or a
        ``TriggerSource`` entry such as ``"Line1"`` (raises ``FeatureMissing`` listing
        the offered sources when the camera has no such line).
        """
        if self.has("AcquisitionMode") and self.nodes.is_writable("AcquisitionMode"):
            self.set_enum("AcquisitionMode", "Continuous")
        if self.has("TriggerSelector") and "FrameStart" in self.nodes.enum_entries(
            "TriggerSelector"
        ):
            self.set_enum("TriggerSelector", "FrameStart")
        source = "Software" if trigger == SOFTWARE_TRIGGER else trigger
        self.check_enum("TriggerSource", source)
        self.set_enum("TriggerMode", "On")
        self.set_enum("TriggerSource", source)
        if source == "Software":
            self.require("TriggerSoftware")
        elif activation is not None:
            self.set_enum("TriggerActivation", activation)

    def setup_software_trigger(self) -> None:
        """Continuous acquisition, one frame per ``TriggerSoftware`` (SFNC FrameStart)."""
        self.setup_trigger(SOFTWARE_TRIGGER)

    def current_trigger(self) -> str:
        """``"software"`` or the trigger line in force."""
        if not self.has("TriggerSource"):
            return SOFTWARE_TRIGGER
        source = str(self.nodes.get("TriggerSource"))
        return SOFTWARE_TRIGGER if source == "Software" else source

    def flat_field_state(self) -> str:
        """On-camera flat-field correction: ``"off"``, ``"on"`` or ``"absent"``."""
        for name, off in FLAT_FIELD_FEATURES:
            if self.has(name):
                return "off" if self.nodes.get(name) == off else "on"
        return "absent"

    def switch_flat_field_off(self) -> None:
        """Switch every offered flat-field correction off (the white image must be raw)."""
        for name, off in FLAT_FIELD_FEATURES:
            if self.has(name) and self.nodes.get(name) != off:
                if not self.nodes.is_writable(name):
                    raise FeatureMissing(
                        f"on-camera flat-field correction ({name}) is on and not writable",
                        feature=name,
                        device=self.device,
                        hint="switch it off in the camera's configuration tool, or set "
                        'camera.flat_field = "leave" to record it as on',
                    )
                self.nodes.set(name, off)

    def apply_transport(self, transport: TransportSettings) -> list[str]:
        """Set the GenICam transport features the camera offers; returns notes on what
        could not be applied (for the start-up log and ``lfcal devices --check``)."""
        notes: list[str] = []
        if transport.packet_size is not None and self.has("GevSCPSPacketSize"):
            self.set_number("GevSCPSPacketSize", transport.packet_size, integer=True)
        if transport.throughput_limit_bps is not None:
            if self.has("DeviceLinkThroughputLimit"):
                if self.has("DeviceLinkThroughputLimitMode"):
                    self.set_enum("DeviceLinkThroughputLimitMode", "On")
                self.set_number(
                    "DeviceLinkThroughputLimit", transport.throughput_limit_bps, integer=True
                )
            else:
                notes.append("DeviceLinkThroughputLimit not offered: throughput limit not set")
        return notes

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
            gain = self.gain_feature()
            if gain is None:
                self.require("Gain")  # raises FeatureMissing naming the SFNC feature
            else:
                raw = gain.endswith("Raw")
                if raw and settings.gain != int(settings.gain):
                    raise InvalidSetting(
                        f"the camera offers GainRaw only (integer device units); "
                        f"gain {settings.gain:g} is not an integer",
                        device=self.device,
                        hint="camera.gain as a whole number of the camera's GainRaw units",
                    )
                self.check_number(gain, settings.gain, integer=raw)
        if settings.black_level is not None:
            black = self.black_level_feature()
            if black is None:
                self.require("BlackLevel")
            else:
                self.check_number(black, settings.black_level, integer=black.endswith("Raw"))
        source = "Software" if settings.trigger == SOFTWARE_TRIGGER else settings.trigger
        self.check_enum("TriggerSource", source)
        if source != "Software" and settings.trigger_activation is not None:
            self.check_enum("TriggerActivation", settings.trigger_activation)
        if settings.flat_field not in ("off", "leave"):
            raise InvalidSetting(
                f"flat_field must be 'off' or 'leave', not {settings.flat_field!r}",
                device=self.device,
            )

    def _auto_off(self, name: str) -> None:
        if (
            self.has(name)
            and self.nodes.is_writable(name)
            and "Off" in self.nodes.enum_entries(name)
        ):
            self.set_enum(name, "Off")

    def _select_all(self, selector: str) -> None:
        if self.has(selector) and "All" in self.nodes.enum_entries(selector):
            self.set_enum(selector, "All")

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
        gain = self.gain_feature()
        if settings.gain is not None and gain is not None:
            self._auto_off("GainAuto")
            self._select_all("GainSelector")
            self.set_number(gain, settings.gain, integer=gain.endswith("Raw"))
        black = self.black_level_feature()
        if settings.black_level is not None and black is not None:
            self._auto_off("BlackLevelAuto")
            self._select_all("BlackLevelSelector")
            self.set_number(black, settings.black_level, integer=black.endswith("Raw"))
        if settings.flat_field == "off":
            self.switch_flat_field_off()
        self.setup_trigger(settings.trigger, settings.trigger_activation)
        self.select_temperature_sensor()
        return self.read_settings()

    def read_settings(self) -> CameraSettings:
        """The settings in force, read from the camera."""
        exposure_name = self.exposure_feature()
        gain_name = self.gain_feature()
        black_name = self.black_level_feature()
        trigger = self.current_trigger()
        activation = (
            str(self.nodes.get("TriggerActivation"))
            if trigger != SOFTWARE_TRIGGER and self.has("TriggerActivation")
            else None
        )
        return CameraSettings(
            pixel_format=str(self.nodes.get("PixelFormat")),
            exposure_us=float(self.nodes.get(exposure_name)) if exposure_name else None,
            gain=float(self.nodes.get(gain_name)) if gain_name else None,
            roi=self.current_roi(),
            black_level=float(self.nodes.get(black_name)) if black_name else None,
            trigger=trigger,
            trigger_activation=activation,
            # read back: "on" or "off" ("absent" counts as off: nothing is corrected)
            flat_field="on" if self.flat_field_state() == "on" else "off",
        )


__all__ = [
    "BLACK_LEVEL_FEATURES",
    "EXPOSURE_FEATURES",
    "FLAT_FIELD_FEATURES",
    "GAIN_FEATURES",
    "SfncCamera",
]
