"""The sections of the station configuration (``[camera]``, ``[rail]``, ...): pydantic v2 models.

Each model validates its own keys (types, ranges, units in the names: mm, µm
``_um``, s, µs ``_us``, px); problems that involve several keys are
:mod:`station.config_checks`', and :mod:`station.config` loads the file.
"""

from __future__ import annotations

import math
import os
import re
from pathlib import Path
from typing import Annotated, Literal

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    Strict,
    ValidationInfo,
    field_validator,
)

ENV_API_KEYS = "LFCAL_API_KEYS"
"""Environment variable whose API keys are added to ``server.api_keys``."""

MIN_API_KEY_LENGTH = 16
GMAX0505_SIZE_PX = 5120
"""Sensor width and height (px) of the GMAX0505, the default for real cameras."""

PixelFormat = Literal[
    "Mono8",
    "Mono10",
    "Mono12",
    "Mono14",
    "Mono16",
    "Mono10p",
    "Mono12p",
    "Mono10Packed",
    "Mono12Packed",
]
PIXEL_FORMAT_BITS: dict[str, int] = {
    "Mono8": 8,
    "Mono10": 10,
    "Mono12": 12,
    "Mono14": 14,
    "Mono16": 16,
    "Mono10p": 10,
    "Mono12p": 12,
    "Mono10Packed": 10,
    "Mono12Packed": 12,
}
ZABER_BAUD_RATES = (9600, 19200, 38400, 57600, 115200)
_PYSERIAL_SCHEMES = ("socket", "rfc2217", "loop", "spy", "alt", "hwgrep", "cp2110")

LooseTuple2 = Annotated[tuple[float, float], Strict(False)]
LoosePath = Annotated[Path, Strict(False)]


class ConfigSection(BaseModel):
    """Base of every section: unknown keys are errors, types are strict (no "12" for 12)."""

    model_config = ConfigDict(extra="forbid", strict=True, validate_default=False)


def _resolve_path(value: Path | None, info: ValidationInfo) -> Path | None:
    """Expand ``~`` and make a relative path absolute against ``context["base_dir"]``."""
    if value is None:
        return None
    value = value.expanduser()
    base = (info.context or {}).get("base_dir")
    if base is not None and not value.is_absolute():
        value = Path(os.path.normpath(Path(base) / value))
    return value


# --------------------------------------------------------------------------- camera


class RoiConfig(ConfigSection):
    """Sensor region of interest (px), applied by the camera."""

    width: int = Field(gt=0, description="ROI width (px)")
    height: int = Field(gt=0, description="ROI height (px)")
    offset_x: int = Field(default=0, ge=0, description="left edge of the ROI on the sensor (px)")
    offset_y: int = Field(default=0, ge=0, description="top edge of the ROI on the sensor (px)")


class TransportConfig(ConfigSection):
    """``[camera.transport]``: streaming of 25-52 MB frames (GigE Vision / USB3 Vision)."""

    packet_size: int | None = Field(
        default=None,
        ge=576,
        le=16384,
        description="GigE stream packet size (bytes; 9000 with jumbo frames); none: negotiated",
    )
    packet_delay_ns: int | None = Field(
        default=None, ge=0, le=10_000_000, description="GigE inter-packet delay GevSCPD (ns)"
    )
    throughput_limit_bps: int | None = Field(
        default=None,
        gt=0,
        description="DeviceLinkThroughputLimit (bytes/s); USB3 through Aravis: bandwidth limit",
    )
    buffer_count: int = Field(default=3, ge=1, le=64, description="stream buffers")
    socket_buffer_bytes: int | None = Field(
        default=None,
        gt=0,
        description="aravis GigE: receive socket buffer (bytes); none: two frames; "
        "capped by net.core.rmem_max (a warning at start-up says so)",
    )
    frame_retention_ms: float = Field(
        default=2000.0, gt=0, le=60000, description="aravis: wait for missing packets (ms)"
    )
    packet_resend: bool = Field(default=True, description="ask the camera to resend lost packets")
    packet_socket: bool | None = Field(
        default=None,
        description="aravis GigE: AF_PACKET ring receiver (needs CAP_NET_RAW); none: for "
        "frames larger than a quarter of net.core.rmem_default",
    )


class CameraConfig(ConfigSection):
    """``[camera]``: which camera and how it is exposed."""

    backend: Literal["simulated", "aravis", "harvesters"] = Field(
        default="simulated",
        description="simulated renderer, Aravis (GigE/USB3 Vision) or Harvesters",
    )
    interface: Literal["gige", "usb3"] = Field(
        default="gige",
        description='aravis: "gige" (opened by address) or "usb3" (USB3 Vision by serial, '
        "with GigE Vision discovery disabled)",
    )
    address: str | None = Field(
        default=None,
        min_length=1,
        description="aravis/harvesters: camera IP address or device name",
    )
    serial: str | None = Field(default=None, min_length=1, description="camera serial number")
    cti: LoosePath | None = Field(
        default=None,
        description="harvesters: GenTL producer file (.cti), relative to the config file",
    )
    pixel_format: PixelFormat = Field(
        default="Mono12",
        description="GenICam PixelFormat (Mono8/10/12/14/16, packed Mono10p, Mono12p, "
        "Mono10Packed, Mono12Packed); sets the bit depth",
    )
    exposure_us: float = Field(default=10000.0, gt=0, le=60e6, description="exposure time (µs)")
    gain: float = Field(
        default=0.0,
        ge=0,
        le=100000,
        description="analogue gain: dB (SFNC Gain); device units on a GainRaw-only camera",
    )
    black_level: float | None = Field(
        default=None, description="BlackLevel (or BlackLevelRaw); none: leave the camera's"
    )
    trigger: str = Field(
        default="software",
        min_length=1,
        pattern=r"^(software|[A-Za-z][A-Za-z0-9_]*)$",
        description='"software" (one TriggerSoftware per frame) or a TriggerSource line '
        '("Line1") that starts each frame',
    )
    trigger_activation: str | None = Field(
        default=None,
        min_length=1,
        description='line trigger: TriggerActivation ("RisingEdge"); none: the camera\'s',
    )
    flat_field: Literal["off", "leave"] = Field(
        default="off",
        description='on-camera flat-field correction: "off" (switched off; the white image '
        'must be raw) or "leave" (left as it is, recorded per frame)',
    )
    transport: TransportConfig = Field(
        default_factory=TransportConfig, description="streaming parameters"
    )
    frame_cache: LoosePath | None = Field(
        default=None,
        description="simulated: keep rendered frames in this directory (relative to the "
        "config file) and reuse them for the same bench state",
    )
    roi: RoiConfig | None = Field(
        default=None, description="region of interest (px); none: full sensor"
    )
    timeout_s: float = Field(default=5.0, gt=0, le=600, description="frame grab timeout (s)")
    preset: str = Field(default="paper", min_length=1, description="simulated: camera preset name")
    width: int | None = Field(
        default=None,
        gt=0,
        le=65536,
        description="sensor width (px); simulated: default the preset's, real: 5120 (GMAX0505)",
    )
    height: int | None = Field(
        default=None,
        gt=0,
        le=65536,
        description="sensor height (px); simulated: default the preset's, real: 5120 (GMAX0505)",
    )
    principal_point_px: LooseTuple2 | None = Field(
        default=None,
        description="simulated: principal point (x, y) in px; default: placed by the simulator",
    )
    seed: int = Field(default=0, ge=0, description="simulated: noise seed")

    @field_validator("cti", "frame_cache", mode="after")
    @classmethod
    def _resolve_cti(cls, value: Path | None, info: ValidationInfo) -> Path | None:
        return _resolve_path(value, info)

    @property
    def bit_depth(self) -> int:
        """Bits per pixel delivered by the camera (from ``pixel_format``)."""
        return PIXEL_FORMAT_BITS[self.pixel_format]

    @property
    def sensor_size_px(self) -> tuple[int, int]:
        """Sensor ``(width, height)`` in px (simulated: from the preset when not given)."""
        if self.width is not None and self.height is not None:
            return (self.width, self.height)
        default = (GMAX0505_SIZE_PX, GMAX0505_SIZE_PX)
        if self.backend == "simulated":
            try:
                from calibration.presets import get_preset

                sensor = get_preset(self.preset).camera.sensor
                default = (sensor.width, sensor.height)
            except ValueError:
                pass
        return (self.width or default[0], self.height or default[1])


# ---------------------------------------------------------------------- motion


class ZaberLinkConfig(ConfigSection):
    """Settings shared by the rail and the XY stage (Zaber ASCII protocol)."""

    driver: Literal["zaber", "emulated"] = Field(
        default="emulated",
        description='"zaber": real devices on `port`; "emulated": the station starts its '
        "Zaber emulator on a pty (leave `port` out)",
    )
    port: str | None = Field(
        default=None,
        min_length=1,
        description="pyserial URL: /dev/ttyUSB0, COM3, socket://host:port, rfc2217://host:port",
    )
    baud_rate: int = Field(
        default=115200, description="serial baud rate (Zaber ASCII default 115200)"
    )
    microstep_um: float = Field(
        default=0.047625,
        gt=0,
        le=1000,
        description="size of one microstep (µm), from the device's data",
    )
    max_speed_mm_s: float = Field(default=10.0, gt=0, le=1000, description="maximum speed (mm/s)")
    accel_mm_s2: float = Field(default=50.0, gt=0, le=100000, description="acceleration (mm/s²)")
    position_tolerance_um: float = Field(
        default=5.0,
        gt=0,
        le=10000,
        description="largest accepted read-back error after a move (µm)",
    )
    settle_s: float = Field(
        default=0.2, ge=0, le=60, description="wait after a move before a frame (s)"
    )
    home_on_connect: bool = Field(
        default=True, description="home the axes when the station connects"
    )

    @field_validator("baud_rate", mode="after")
    @classmethod
    def _baud(cls, value: int) -> int:
        if value not in ZABER_BAUD_RATES:
            raise ValueError(f"must be one of {', '.join(map(str, ZABER_BAUD_RATES))}")
        return value

    @field_validator("port", mode="after")
    @classmethod
    def _port(cls, value: str | None) -> str | None:
        if value is not None and (why := port_problem(value)):
            raise ValueError(why)
        return value


def port_problem(url: str) -> str | None:
    """Why ``url`` is not a usable pyserial port or URL (None if it looks fine)."""
    if url != url.strip() or not url:
        return f"must not be empty or have surrounding spaces, got {url!r}"
    if "://" in url:
        scheme, rest = url.split("://", 1)
        if scheme not in _PYSERIAL_SCHEMES:
            return (
                f"unknown pyserial URL scheme {scheme!r} (use a device path or one of "
                f"{', '.join(s + '://' for s in _PYSERIAL_SCHEMES)})"
            )
        if scheme in ("socket", "rfc2217") and not re.match(r"^[^:/?#]+:\d{1,5}([/?].*)?$", rest):
            return f"{scheme}:// needs host:port, got {url!r}"
    return None


class RailConfig(ZaberLinkConfig):
    """``[rail]``: the motorized rail carrying the board along the optical axis.

    Object distance ``u = zero_object_distance_mm + direction·rail_mm`` (OPTICS.md §4).
    """

    device: int = Field(default=1, ge=1, le=99, description="Zaber device number on the chain")
    axis: int = Field(default=1, ge=1, le=9, description="axis number on that device")
    min_mm: float = Field(default=0.0, description="lowest allowed rail position (mm)")
    max_mm: float = Field(default=100.0, description="highest allowed rail position (mm)")
    zero_object_distance_mm: float = Field(
        gt=0, description="board-to-main-lens distance u at rail position 0 (mm), measured"
    )
    direction: Literal[1, -1] = Field(
        default=1, description="+1: rail position increases away from the camera; -1: towards it"
    )
    zero_object_distance_tolerance_mm: float | None = Field(
        default=None,
        gt=0,
        description=(
            "how well zero_object_distance_mm is known, 1 sigma (mm); the calibration measures "
            "it from the sweep and uses this only where the sweep cannot (default 2 mm)"
        ),
    )

    def object_distance_mm(self, rail_mm: float) -> float:
        """Object distance u (mm) at rail position ``rail_mm`` (mm)."""
        return self.zero_object_distance_mm + self.direction * rail_mm


class StageAxisConfig(ConfigSection):
    """One XY-stage axis: where it is on the chain and its travel (mm)."""

    device: int = Field(ge=1, le=99, description="Zaber device number")
    axis: int = Field(ge=1, le=9, description="axis number on that device")
    min_mm: float = Field(default=0.0, description="lowest allowed position (mm)")
    max_mm: float = Field(default=300.0, description="highest allowed position (mm)")


class StagePosition(ConfigSection):
    """A named XY-stage position (mm)."""

    x_mm: float = Field(description="x axis position (mm)")
    y_mm: float = Field(description="y axis position (mm)")


class XYStageConfig(ZaberLinkConfig):
    """``[xy_stage]``: positions the board laterally.

    ``port`` omitted: the stage is on the rail's chain (real or emulated).
    """

    x: StageAxisConfig = Field(
        default_factory=lambda: StageAxisConfig(device=2, axis=1),
        description="x axis (parallel to the sensor x axis)",
    )
    y: StageAxisConfig = Field(
        default_factory=lambda: StageAxisConfig(device=2, axis=2),
        description="y axis (parallel to the sensor y axis)",
    )
    alignment: StagePosition = Field(
        default_factory=lambda: StagePosition(x_mm=100.0, y_mm=100.0),
        description="puts the standard board corner (0, 0) on the optical axis (mm)",
    )
    white: StagePosition = Field(
        default_factory=lambda: StagePosition(x_mm=300.0, y_mm=100.0),
        description="puts the board's plain light area (|X| or |Y| > 150 mm) in view (mm)",
    )


# ---------------------------------------------------------------- optics, board


class OpticsConfig(ConfigSection):
    """``[optics]``: design priors (mm); the calibration measures b and a itself."""

    main_focal_mm: float = Field(default=35.0, gt=0, description="main-lens focal length F (mm)")
    mla_focal_mm: float = Field(default=2.5, gt=0, description="microlens focal length f (mm)")
    mla_pitch_mm: float = Field(default=0.25, gt=0, description="microlens pitch D (mm)")
    main_focal_tolerance_mm: float | None = Field(
        default=None,
        gt=0,
        description=(
            "how well main_focal_mm is known, 1 sigma (mm); the calibration measures F from "
            "the sweep and uses this only where the sweep cannot (default 2 % of F)"
        ),
    )
    mla_focal_tolerance_mm: float | None = Field(
        default=None,
        gt=0,
        description=(
            "how well mla_focal_mm is known, 1 sigma (mm); the calibration measures f from "
            "the sweep and uses this only where the sweep cannot (default 2 % of f)"
        ),
    )
    pixel_pitch_mm: float = Field(default=0.0025, gt=0, description="sensor pixel pitch δ (mm)")
    designed_b_mm: float | None = Field(
        default=None, gt=0, description="designed MLA-to-sensor distance b (mm), for comparison"
    )
    designed_a_mm: float | None = Field(
        default=None,
        gt=0,
        description="designed focus distance a in front of the MLA (mm), for comparison",
    )


class BoardConfig(ConfigSection):
    """``[board]``: the double checkerboard (OPTICS.md §3)."""

    square_mm: float = Field(default=10.0, gt=0, description="square side s (mm)")
    reference_gap_mm: float = Field(default=0.1, gt=0, description="reference-corner gap Cr (mm)")


# ------------------------------------------------------------------------- sweep


class SweepConfig(ConfigSection):
    """``[sweep]``: default sweep along the rail (rail positions, mm)."""

    start_mm: float = Field(default=0.0, description="first rail position (mm)")
    stop_mm: float = Field(default=99.0, description="last rail position (mm), inclusive")
    step_mm: float = Field(default=1.0, gt=0, description="rail step between frames (mm)")
    max_frames: int = Field(
        default=2000, gt=0, le=100000, description="refuse sweeps with more frames"
    )
    settle_s: float | None = Field(
        default=None, ge=0, le=60, description="wait after each move (s); default: rail.settle_s"
    )
    exposure_us: float | None = Field(
        default=None, gt=0, le=60e6, description="exposure during the sweep (µs); default: camera's"
    )

    @property
    def frame_count(self) -> int:
        """Number of frames from start to stop (inclusive) in steps of ``step_mm``."""
        if self.stop_mm < self.start_mm:
            return 0
        return int(math.floor((self.stop_mm - self.start_mm) / self.step_mm + 1e-9)) + 1

    def positions_mm(self) -> list[float]:
        """Rail positions (mm) of the sweep, rounded to 1 nm."""
        return [round(self.start_mm + k * self.step_mm, 6) for k in range(self.frame_count)]


# ----------------------------------------------------------------- storage, server


STATION_ID_PATTERN = r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$"
_POSTGRES_SCHEMES = ("postgresql://", "postgres://", "postgresql+psycopg://")


class S3Config(ConfigSection):
    """``[storage.s3]``: the S3-compatible object store of ``archive_url``. Keys left out
    come from the usual AWS environment variables and files (``AWS_ENDPOINT_URL``,
    ``AWS_ACCESS_KEY_ID``, ``AWS_SECRET_ACCESS_KEY``, ``AWS_DEFAULT_REGION``,
    ``AWS_PROFILE``, ``~/.aws/credentials``)."""

    endpoint_url: str | None = Field(
        default=None,
        pattern=r"^https?://[^\s/]+(/.*)?$",
        description="endpoint of a non-AWS server, e.g. http://minio.lab:9000",
    )
    region: str | None = Field(default=None, min_length=1, description="region name")
    access_key_id: str | None = Field(default=None, min_length=1, repr=False)
    secret_access_key: str | None = Field(default=None, min_length=1, repr=False)
    connect_timeout_s: float = Field(default=5.0, gt=0, le=120, description="per attempt (s)")
    upload_retry_s: float = Field(
        default=2.0, gt=0, le=600, description="wait between upload attempts during an outage (s)"
    )


class StorageConfig(ConfigSection):
    """``[storage]``: where sweeps and the job database live (relative to the config file).

    ``database`` is a SQLite file (one station, nothing to install) or a
    ``postgresql://user:password@host:port/dbname`` URL (several stations on one
    database, each running only its own jobs: ``station_id``). ``archive_url``
    (``s3://bucket/prefix``) uploads every archive to object storage after the
    frames are written locally (``[storage.s3]``).
    """

    data_dir: LoosePath = Field(
        default=Path("data"), description="directory of sweep archives and results"
    )
    database: str | LoosePath = Field(
        default=Path("data/lfcal.sqlite3"),
        description="SQLite database file, or a postgresql:// URL",
    )
    station_id: str | None = Field(
        default=None,
        pattern=STATION_ID_PATTERN,
        description="this station's name in a shared database (default: $LFCAL_STATION_ID "
        "or the host name)",
    )
    archive_url: str | None = Field(
        default=None,
        pattern=r"^s3://[a-z0-9][a-z0-9.-]{1,61}[a-z0-9](/[^\s]*)?$",
        description="upload archives to s3://bucket/prefix (frames are written locally first)",
    )
    keep_local_archives: bool = Field(
        default=True,
        description="keep the local copy of an archive once it is uploaded and verified",
    )
    archive_cache_dir: LoosePath | None = Field(
        default=None,
        description="where archives read from object storage are kept (default "
        "data_dir/archive-cache)",
    )
    s3: S3Config = Field(default_factory=lambda: S3Config())

    @field_validator("data_dir", "archive_cache_dir", mode="after")
    @classmethod
    def _resolve(cls, value: Path | None, info: ValidationInfo) -> Path | None:
        return _resolve_path(value, info)

    @field_validator("database", mode="after")
    @classmethod
    def _resolve_database(cls, value: str | Path, info: ValidationInfo) -> str | Path | None:
        text = str(value)
        if text.lower().startswith(_POSTGRES_SCHEMES):
            return text
        if "://" in text:
            raise ValueError(
                "must be a SQLite file path or a postgresql:// URL, got a "
                f"{text.split('://', 1)[0]}:// URL"
            )
        return _resolve_path(Path(value), info)

    @property
    def postgres(self) -> bool:
        """The job database is a PostgreSQL server."""
        return isinstance(self.database, str)

    @property
    def database_path(self) -> Path | None:
        """The SQLite file (None for PostgreSQL)."""
        return None if isinstance(self.database, str) else self.database

    @property
    def cache_dir(self) -> Path:
        """Local cache of archives read from object storage."""
        return self.archive_cache_dir or self.data_dir / "archive-cache"


class ServerConfig(ConfigSection):
    """``[server]``: the HTTP service."""

    host: str = Field(default="127.0.0.1", min_length=1, description="address to listen on")
    port: int = Field(default=8000, ge=1, le=65535, description="TCP port")
    api_keys: list[str] = Field(
        default_factory=list,
        repr=False,
        description=f"accepted API keys (≥ {MIN_API_KEY_LENGTH} characters); "
        f"${ENV_API_KEYS} adds more",
    )
    read_only_requires_key: bool = Field(
        default=False, description="also require an API key for read-only requests"
    )
    cors_origins: list[str] = Field(
        default_factory=list, description="allowed CORS origins, e.g. http://localhost:5173"
    )
    max_body_bytes: int = Field(
        default=1_048_576, gt=0, le=1 << 30, description="largest accepted request body (bytes)"
    )
