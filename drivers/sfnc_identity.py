"""Identity, limits and per-frame read-outs of a GenICam camera (SFNC names).

Part of :class:`drivers.sfnc.SfncCamera`.  Feature names, each checked to exist before
use, with the fallbacks older cameras need:

* identity: ``DeviceVendorName``, ``DeviceModelName``, ``DeviceSerialNumber`` (else
  ``DeviceID``), ``DeviceFirmwareVersion`` (else ``DeviceVersion``), ``PixelFormat``;
* sensor size (px): ``SensorWidth``/``SensorHeight``, else ``WidthMax``/``HeightMax``,
  else the upper bound of ``Width``/``Height``;
* exposure (µs): ``ExposureTime``, else the SFNC 1.x ``ExposureTimeAbs``;
* gain: ``Gain`` (dB), else ``GainRaw`` (device units, an integer);
* black level: ``BlackLevel``, else ``BlackLevelRaw``;
* temperature (°C): ``DeviceTemperature``, with ``DeviceTemperatureSelector=Sensor``
  (else the first of :data:`TEMPERATURE_SELECTORS` offered), read per frame.
"""

from __future__ import annotations

import logging

from drivers.camera import CameraInfo
from drivers.camera_errors import CameraError, FeatureMissing
from drivers.sfnc_features import SfncFeatures

log = logging.getLogger(__name__)

GAIN_FEATURES = ("Gain", "GainRaw")
BLACK_LEVEL_FEATURES = ("BlackLevel", "BlackLevelRaw")
TEMPERATURE_SELECTORS = ("Sensor", "Mainboard", "Device")

#: Exposure features in order of preference: SFNC >= 2.0 name, then the SFNC 1.x name.
EXPOSURE_FEATURES = ("ExposureTime", "ExposureTimeAbs")


class SfncIdentity(SfncFeatures):
    """What the camera is and what it can do, read from the standard SFNC features."""

    # -- identity and limits ------------------------------------------------------------

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


__all__ = [
    "BLACK_LEVEL_FEATURES",
    "EXPOSURE_FEATURES",
    "GAIN_FEATURES",
    "TEMPERATURE_SELECTORS",
    "SfncIdentity",
]
