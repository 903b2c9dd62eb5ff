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

:class:`SfncCamera` is built in layers, each in its own module: checked access to single
features (:mod:`drivers.sfnc_features`), identity, limits and temperature
(:mod:`drivers.sfnc_identity`), the ROI (:mod:`drivers.sfnc_roi`); trigger, flat-field,
transport and the whole configuration (validate, apply, read back) are here.
"""

from __future__ import annotations

from dataclasses import dataclass

from drivers import sfnc_roi
from drivers.camera import (
    SOFTWARE_TRIGGER,
    CameraSettings,
    Roi,
    TransportSettings,
    bit_depth,
)
from drivers.camera_errors import FeatureMissing, InvalidSetting
from drivers.sfnc_identity import (
    BLACK_LEVEL_FEATURES,
    EXPOSURE_FEATURES,
    GAIN_FEATURES,
    TEMPERATURE_SELECTORS,
    SfncIdentity,
)

#: On-camera flat-field / shading correction switches: (feature, value that means off).
FLAT_FIELD_FEATURES: tuple[tuple[str, str | bool], ...] = (
    ("FlatFieldCorrectionEnable", False),
    ("FlatFieldCorrection", "Off"),
    ("FFCEnable", False),
    ("ShadingEnable", False),
    ("flatfieldCorrectionMode", "Off"),
)


@dataclass
class SfncCamera(SfncIdentity):
    """SFNC feature logic on top of a :class:`NodeMap`, shared by the backends.

    The checks (:class:`drivers.sfnc_features.SfncFeatures`) and the identity, limits and
    temperature (:class:`drivers.sfnc_identity.SfncIdentity`) are inherited.

    Attributes:
        nodes: the remote device's node map.
        device: label used in error messages (``gige://127.0.0.1`` ...).
        feature_hint: where the operator can see the camera's features (error hint).
    """

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
        return sfnc_roi.current_roi(self)

    def validate(self, settings: CameraSettings) -> None:
        """Check everything ``apply`` will write, before writing anything.

        Raises ``FeatureMissing`` (format/feature not offered) or ``InvalidSetting``.
        """
        bit_depth(settings.pixel_format)  # can the drivers decode it?
        self.check_enum("PixelFormat", settings.pixel_format)
        sfnc_roi.check_roi(self, sfnc_roi.full_roi(self, settings.roi))
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

    def apply(self, settings: CameraSettings) -> CameraSettings:
        """Validate, then apply ``settings`` (acquisition must be stopped); return the values
        read back from the camera."""
        self.validate(settings)
        self.set_enum("PixelFormat", settings.pixel_format)
        sfnc_roi.apply_roi(self, sfnc_roi.full_roi(self, settings.roi))
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
    "TEMPERATURE_SELECTORS",
    "SfncCamera",
]
