"""Station configuration: pydantic v2 models loaded from a TOML file.

Sections (every key is optional unless marked *required*)::

    [camera]         backend "simulated" | "aravis" | "harvesters", exposure, ROI, ...
    [rail]           the board rail (Zaber ASCII or emulated) and its geometry
                     (zero_object_distance_mm *required*, direction)
    [xy_stage]       the XY stage that puts the board corner on the lens axis
    [optics]         priors F, f, D, δ (and optional designed b, a for comparison)
    [board]          square size s and reference gap Cr
    [sweep]          default sweep (start/stop/step on the rail, frame limit)
    [storage]        data directory, job database (SQLite file or PostgreSQL URL),
                     station id, object storage of the archives ([storage.s3])
    [server]         HTTP service (host, port, API keys, CORS, body limit)

Emulated hardware: ``driver = "emulated"`` (rail and/or XY stage) makes the
station start its built-in Zaber ASCII emulator on a pseudo-terminal and talk
to it with the same Zaber driver; ``port`` must then be left out. An XY stage
without ``port`` sits on the rail's chain (real or emulated).

:func:`load_config` reports **all** problems at once as :class:`ConfigError`
(``problems``: ``(file, key, reason)`` triples): TOML syntax errors (with line
and column), unknown keys, wrong types, out-of-range values and cross-field
problems. Relative paths are resolved against the config file's directory.
``LFCAL_API_KEYS`` (comma/whitespace separated) adds API keys to
``server.api_keys``.

Units: mm, µm (``_um``), s, µs (``_us``), px as the names say.
"""

from __future__ import annotations

import difflib
import ipaddress
import math
import os
import re
import sys
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, Literal, NamedTuple, TextIO

from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    PrivateAttr,
    Strict,
    ValidationError,
    ValidationInfo,
    field_validator,
    model_validator,
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


class _Model(BaseModel):
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


class RoiConfig(_Model):
    """Sensor region of interest (px), applied by the camera."""

    width: int = Field(gt=0, description="ROI width (px)")
    height: int = Field(gt=0, description="ROI height (px)")
    offset_x: int = Field(default=0, ge=0, description="left edge of the ROI on the sensor (px)")
    offset_y: int = Field(default=0, ge=0, description="top edge of the ROI on the sensor (px)")


class TransportConfig(_Model):
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


class CameraConfig(_Model):
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


class _ZaberLink(_Model):
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


class RailConfig(_ZaberLink):
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


class StageAxisConfig(_Model):
    """One XY-stage axis: where it is on the chain and its travel (mm)."""

    device: int = Field(ge=1, le=99, description="Zaber device number")
    axis: int = Field(ge=1, le=9, description="axis number on that device")
    min_mm: float = Field(default=0.0, description="lowest allowed position (mm)")
    max_mm: float = Field(default=300.0, description="highest allowed position (mm)")


class StagePosition(_Model):
    """A named XY-stage position (mm)."""

    x_mm: float = Field(description="x axis position (mm)")
    y_mm: float = Field(description="y axis position (mm)")


class XYStageConfig(_ZaberLink):
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


class OpticsConfig(_Model):
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


class BoardConfig(_Model):
    """``[board]``: the double checkerboard (OPTICS.md §3)."""

    square_mm: float = Field(default=10.0, gt=0, description="square side s (mm)")
    reference_gap_mm: float = Field(default=0.1, gt=0, description="reference-corner gap Cr (mm)")


# ------------------------------------------------------------------------- sweep


class SweepConfig(_Model):
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


class S3Config(_Model):
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


class StorageConfig(_Model):
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


class ServerConfig(_Model):
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


# ------------------------------------------------------------------------- station


class StationConfig(_Model):
    """The whole station configuration (see the module docstring)."""

    camera: CameraConfig = Field(default_factory=lambda: CameraConfig())
    rail: RailConfig
    xy_stage: XYStageConfig = Field(default_factory=lambda: XYStageConfig())
    optics: OpticsConfig = Field(default_factory=lambda: OpticsConfig())
    board: BoardConfig = Field(default_factory=lambda: BoardConfig())
    sweep: SweepConfig = Field(default_factory=lambda: SweepConfig())
    storage: StorageConfig = Field(default_factory=lambda: StorageConfig())
    server: ServerConfig = Field(default_factory=lambda: ServerConfig())

    _source: Path | None = PrivateAttr(default=None)

    @model_validator(mode="after")
    def _cross_fields(self, info: ValidationInfo) -> StationConfig:
        if (info.context or {}).get("skip_cross_checks"):
            return self
        problems = cross_field_problems(dict(self))
        if problems:
            raise ValueError("; ".join(f"{key}: {reason}" for key, reason in problems))
        return self

    @property
    def source(self) -> Path | None:
        """The file this configuration was loaded from (None if built in code)."""
        return self._source

    @property
    def xy_shares_rail_chain(self) -> bool:
        """True when the XY stage is on the rail's serial chain (same port or both emulated)."""
        return _shares_chain(self.rail, self.xy_stage)

    @property
    def xy_stage_port(self) -> str | None:
        """The XY stage's port, the rail's when omitted (None: emulated)."""
        return self.xy_stage.port if self.xy_stage.port is not None else self.rail.port

    def manifest_header(
        self,
        *,
        width: int,
        height: int,
        bit_depth: int | None = None,
        principal_point_px: tuple[float, float] | None = None,
    ) -> dict[str, Any]:
        """An ``lfcal-sweep/1`` manifest header (no frames) for frames of ``width × height`` px."""
        camera: dict[str, Any] = {
            "width": width,
            "height": height,
            "pixel_pitch_mm": self.optics.pixel_pitch_mm,
            "bit_depth": bit_depth if bit_depth is not None else self.camera.bit_depth,
        }
        if principal_point_px is not None:
            camera["principal_point_px"] = [
                float(principal_point_px[0]),
                float(principal_point_px[1]),
            ]
        return {
            "format": "lfcal-sweep/1",
            "camera": camera,
            "optics": {
                "main_focal_mm": self.optics.main_focal_mm,
                "mla_focal_mm": self.optics.mla_focal_mm,
                "mla_pitch_mm": self.optics.mla_pitch_mm,
                **_given(
                    main_focal_tolerance_mm=self.optics.main_focal_tolerance_mm,
                    mla_focal_tolerance_mm=self.optics.mla_focal_tolerance_mm,
                ),
            },
            "board": {
                "square_mm": self.board.square_mm,
                "reference_gap_mm": self.board.reference_gap_mm,
            },
            "rail": {
                "zero_object_distance_mm": self.rail.zero_object_distance_mm,
                "direction": self.rail.direction,
                **_given(
                    zero_object_distance_tolerance_mm=self.rail.zero_object_distance_tolerance_mm
                ),
            },
            "white": "white.png",
            "frames": [],
        }


def _given(**values: float | None) -> dict[str, float]:
    """The keyword arguments that are set (optional manifest keys are written only then)."""
    return {k: v for k, v in values.items() if v is not None}


SECTIONS: dict[str, type[_Model]] = {
    "camera": CameraConfig,
    "rail": RailConfig,
    "xy_stage": XYStageConfig,
    "optics": OpticsConfig,
    "board": BoardConfig,
    "sweep": SweepConfig,
    "storage": StorageConfig,
    "server": ServerConfig,
}


# ------------------------------------------------------------ cross-field checks


def _shares_chain(rail: RailConfig, xy: XYStageConfig) -> bool:
    if xy.port is None:
        return rail.driver == xy.driver
    return xy.driver == rail.driver == "zaber" and xy.port == rail.port


def api_key_problems(keys: list[str], key_name: str) -> list[tuple[str, str]]:
    """Problems of a list of API keys, as ``(key, reason)`` with ``key_name[i]`` keys."""
    out: list[tuple[str, str]] = []
    seen: set[str] = set()
    for i, k in enumerate(keys):
        where = f"{key_name}[{i}]"
        if len(k) < MIN_API_KEY_LENGTH:
            out.append(
                (where, f"API key too short ({len(k)} characters, need ≥ {MIN_API_KEY_LENGTH})")
            )
        elif re.search(r"\s", k):
            out.append((where, "API key must not contain whitespace"))
        elif k in seen:
            out.append((where, "duplicate API key"))
        seen.add(k)
    return out


def _is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


class _Problems:
    """Collects cross-field problems, dropping those that depend on keys known to be invalid.

    ``invalid`` holds dotted keys whose values failed validation and were replaced
    by defaults to check the rest; a problem whose ``deps`` (or key) is at or
    below one of them would be about the default, not the file, and is dropped.
    """

    def __init__(self, invalid: frozenset[str] = frozenset()) -> None:
        self.invalid = invalid
        self.items: list[tuple[str, str]] = []

    def _tainted(self, key: str) -> bool:
        return any(key == k or key.startswith((k + ".", k + "[")) for k in self.invalid)

    def add(self, key: str, reason: str, *deps: str) -> None:
        if not any(self._tainted(k) for k in (key, *deps)):
            self.items.append((key, reason))


def cross_field_problems(
    sections: Mapping[str, Any], invalid: frozenset[str] = frozenset()
) -> list[tuple[str, str]]:
    """Problems that involve several keys, as ``(key, reason)``.

    ``sections`` maps section names to validated section models; a missing or
    None section (it could not be validated) skips the checks that need it.
    ``invalid``: dotted keys that failed validation (their defaults were used).
    """
    out = _Problems(invalid)
    cam: CameraConfig | None = sections.get("camera")
    rail: RailConfig | None = sections.get("rail")
    xy: XYStageConfig | None = sections.get("xy_stage")
    optics: OpticsConfig | None = sections.get("optics")
    board: BoardConfig | None = sections.get("board")
    sweep: SweepConfig | None = sections.get("sweep")
    storage: StorageConfig | None = sections.get("storage")
    server: ServerConfig | None = sections.get("server")
    if cam is not None:
        _camera_problems(out, cam)
    if rail is not None:
        _link_problems(out, "rail", rail)
        if rail.min_mm >= rail.max_mm:
            out.add(
                "rail.max_mm",
                f"must exceed rail.min_mm ({rail.min_mm:g}), got {rail.max_mm:g}",
                "rail.min_mm",
            )
    if xy is not None:
        _xy_problems(out, xy, rail)
    if optics is not None:
        _optics_problems(out, optics)
    if board is not None and board.reference_gap_mm >= board.square_mm:
        out.add(
            "board.reference_gap_mm",
            f"must be smaller than board.square_mm ({board.square_mm:g}), "
            f"got {board.reference_gap_mm:g}",
            "board.square_mm",
        )
    if sweep is not None:
        _sweep_problems(out, sweep, rail, optics)
    if storage is not None:
        if storage.data_dir.exists() and not storage.data_dir.is_dir():
            out.add("storage.data_dir", f"{storage.data_dir} exists and is not a directory")
        path = storage.database_path
        if path is not None and path.is_dir():
            out.add("storage.database", f"{path} is a directory, not a file")
    if server is not None:
        _server_problems(out, server)
    return out.items


def _camera_problems(out: _Problems, cam: CameraConfig) -> None:
    given = cam.model_fields_set
    if cam.backend == "simulated":
        from calibration.presets import preset_names

        if cam.preset not in preset_names():
            out.add(
                "camera.preset",
                f"unknown preset {cam.preset!r}: choose one of {', '.join(preset_names())}",
            )
        for key in ("address", "serial", "cti"):
            if key in given:
                out.add(
                    f"camera.{key}",
                    'not used with backend = "simulated" (set backend = "aravis" or "harvesters")',
                    "camera.backend",
                )
        if cam.trigger != "software":
            out.add("camera.trigger", 'the simulated camera has only "software"')
    else:
        for key in ("preset", "seed", "principal_point_px", "frame_cache"):
            if key in given:
                out.add(f"camera.{key}", 'only used with backend = "simulated"', "camera.backend")
        if cam.interface == "usb3" and cam.backend != "aravis":
            out.add("camera.interface", 'only used with backend = "aravis"', "camera.backend")
        if cam.interface == "usb3" and cam.serial is None:
            out.add(
                "camera.serial",
                'field required (interface = "usb3" opens the camera by serial)',
                "camera.interface",
            )
        if cam.backend == "aravis" and cam.address is None and cam.serial is None:
            out.add(
                "camera.address",
                'field required (backend = "aravis" needs address or serial)',
                "camera.backend",
                "camera.serial",
            )
        if cam.backend == "harvesters":
            if cam.cti is None:
                out.add(
                    "camera.cti",
                    'field required (backend = "harvesters" needs the GenTL .cti file)',
                    "camera.backend",
                )
            elif not cam.cti.is_file():
                out.add("camera.cti", f"file not found: {cam.cti}")
    size_deps = ("camera.width", "camera.height", "camera.backend", "camera.preset")
    width, height = cam.sensor_size_px
    if cam.roi is not None:
        r = cam.roi
        if r.offset_x + r.width > width:
            out.add(
                "camera.roi.width",
                f"ROI columns {r.offset_x}..{r.offset_x + r.width - 1} "
                f"leave the {width} px wide sensor",
                *size_deps,
            )
        if r.offset_y + r.height > height:
            out.add(
                "camera.roi.height",
                f"ROI rows {r.offset_y}..{r.offset_y + r.height - 1} "
                f"leave the {height} px high sensor",
                *size_deps,
            )
    if cam.principal_point_px is not None:
        x, y = cam.principal_point_px
        if not (0 <= x <= width - 1 and 0 <= y <= height - 1):
            out.add(
                "camera.principal_point_px",
                f"({x:g}, {y:g}) is outside the {width}×{height} px sensor",
                *size_deps,
            )


def _link_problems(out: _Problems, name: str, link: _ZaberLink) -> None:
    if link.driver == "zaber" and link.port is None and name == "rail":
        out.add(
            f"{name}.port",
            'field required (driver = "zaber" needs a port such as /dev/ttyUSB0 or '
            "socket://host:port)",
            f"{name}.driver",
        )
    if link.driver == "emulated" and link.port is not None:
        out.add(
            f"{name}.port",
            'not used with driver = "emulated" (the station starts the emulator on a pty); '
            'remove it or set driver = "zaber"',
            f"{name}.driver",
        )


def _xy_problems(out: _Problems, xy: XYStageConfig, rail: RailConfig | None) -> None:
    _link_problems(out, "xy_stage", xy)
    if xy.driver == "zaber" and xy.port is None and rail is not None and rail.driver != "zaber":
        out.add(
            "xy_stage.port",
            "field required (the rail is emulated, so the XY stage cannot share its chain)",
            "xy_stage.driver",
            "rail.driver",
        )
    for name, ax in (("x", xy.x), ("y", xy.y)):
        if ax.min_mm >= ax.max_mm:
            out.add(
                f"xy_stage.{name}.max_mm",
                f"must exceed xy_stage.{name}.min_mm ({ax.min_mm:g}), got {ax.max_mm:g}",
            )
    if (xy.x.device, xy.x.axis) == (xy.y.device, xy.y.axis):
        out.add(
            "xy_stage.y",
            f"same device {xy.y.device} axis {xy.y.axis} as xy_stage.x",
            "xy_stage.x",
        )
    if rail is not None and _shares_chain(rail, xy):
        chain_deps = ("rail.device", "rail.axis", "rail.port", "rail.driver", "xy_stage.port")
        for name, ax in (("x", xy.x), ("y", xy.y)):
            if (ax.device, ax.axis) == (rail.device, rail.axis):
                out.add(
                    f"xy_stage.{name}",
                    f"device {ax.device} axis {ax.axis} is the rail's (same chain)",
                    *chain_deps,
                )
    for pos_name in ("alignment", "white"):
        pos: StagePosition = getattr(xy, pos_name)
        for name, ax, value in (("x", xy.x, pos.x_mm), ("y", xy.y, pos.y_mm)):
            if not ax.min_mm <= value <= ax.max_mm:
                out.add(
                    f"xy_stage.{pos_name}.{name}_mm",
                    f"{value:g} is outside the {name} travel {ax.min_mm:g}..{ax.max_mm:g} mm",
                    f"xy_stage.{name}",
                )


def _optics_problems(out: _Problems, optics: OpticsConfig) -> None:
    if optics.mla_pitch_mm <= optics.pixel_pitch_mm:
        out.add(
            "optics.mla_pitch_mm",
            f"must exceed optics.pixel_pitch_mm ({optics.pixel_pitch_mm:g}), "
            f"got {optics.mla_pitch_mm:g}",
            "optics.pixel_pitch_mm",
        )
    if optics.designed_b_mm is not None and optics.designed_b_mm <= optics.mla_focal_mm:
        out.add(
            "optics.designed_b_mm",
            f"must exceed optics.mla_focal_mm ({optics.mla_focal_mm:g}) in Keplerian mode, "
            f"got {optics.designed_b_mm:g}",
            "optics.mla_focal_mm",
        )


def _sweep_problems(
    out: _Problems, sweep: SweepConfig, rail: RailConfig | None, optics: OpticsConfig | None
) -> None:
    if sweep.stop_mm < sweep.start_mm:
        out.add(
            "sweep.stop_mm",
            f"must not be below sweep.start_mm ({sweep.start_mm:g}), got {sweep.stop_mm:g}",
            "sweep.start_mm",
        )
        return
    if sweep.frame_count > sweep.max_frames:
        out.add(
            "sweep.step_mm",
            f"gives {sweep.frame_count} frames, more than sweep.max_frames = {sweep.max_frames}",
            "sweep.start_mm",
            "sweep.stop_mm",
            "sweep.max_frames",
        )
    if rail is None or rail.min_mm >= rail.max_mm:
        return
    for key in ("start_mm", "stop_mm"):
        value = getattr(sweep, key)
        if not rail.min_mm <= value <= rail.max_mm:
            out.add(
                f"sweep.{key}",
                f"{value:g} is outside the rail limits {rail.min_mm:g}..{rail.max_mm:g} mm",
                "rail.min_mm",
                "rail.max_mm",
            )
    if optics is not None:
        u = min(rail.object_distance_mm(sweep.start_mm), rail.object_distance_mm(sweep.stop_mm))
        if u <= optics.main_focal_mm:
            out.add(
                "rail.zero_object_distance_mm",
                f"the sweep reaches object distance {u:g} mm, not beyond the main focal "
                f"length {optics.main_focal_mm:g} mm (check rail.direction)",
                "rail.direction",
                "sweep.start_mm",
                "sweep.stop_mm",
                "optics.main_focal_mm",
            )


def _server_problems(out: _Problems, server: ServerConfig) -> None:
    for key, reason in api_key_problems(server.api_keys, "server.api_keys"):
        out.add(key, reason)
    for i, origin in enumerate(server.cors_origins):
        if origin != "*" and not re.match(r"^https?://[^/\s?#]+$", origin):
            out.add(
                f"server.cors_origins[{i}]",
                f"must be an origin like http://host:port (no path) or *, got {origin!r}",
            )
    if not _is_loopback(server.host) and not server.api_keys:
        out.add(
            "server.api_keys",
            f"required when server.host ({server.host}) is not a loopback address "
            f"(or set ${ENV_API_KEYS})",
            "server.host",
        )


# --------------------------------------------------------------------- loading


class ConfigProblem(NamedTuple):
    """One problem: the file (or ``$LFCAL_API_KEYS``), the dotted key, and why."""

    file: str
    key: str
    reason: str

    def __str__(self) -> str:
        return (
            f"{self.file}: {self.key}: {self.reason}" if self.key else f"{self.file}: {self.reason}"
        )


def format_problems(problems: list[ConfigProblem]) -> list[str]:
    """One line per problem: ``config/lab.toml: rail.port: field required``."""
    return [str(p) for p in problems]


class ConfigError(ValueError):
    """The configuration is invalid; ``problems`` lists every problem found."""

    def __init__(self, problems: list[ConfigProblem]) -> None:
        self.problems = list(problems)
        super().__init__("\n".join(format_problems(self.problems)))

    def format_problems(self) -> list[str]:
        """One line per problem: ``file: key: reason``."""
        return format_problems(self.problems)


def _show(value: Any) -> str:
    text = repr(value)
    if isinstance(value, bool):
        text = str(value).lower()
    elif isinstance(value, dict):
        text = "a table"
    elif isinstance(value, list):
        text = "an array" if len(text) > 40 else text
    return text if len(text) <= 60 else text[:57] + "..."


def _dotted(loc: tuple[int | str, ...]) -> str:
    out = ""
    for part in loc:
        if isinstance(part, int):
            out += f"[{part}]"
        else:
            out += ("." if out else "") + str(part)
    return out


def _model_at(loc: tuple[int | str, ...]) -> type[BaseModel] | None:
    """The model class whose keys live at ``loc`` (for "did you mean" hints)."""
    model: type[BaseModel] = StationConfig
    for part in loc:
        if isinstance(part, int):
            return None
        field = model.model_fields.get(part)
        if field is None:
            return None
        candidates = [field.annotation, *getattr(field.annotation, "__args__", ())]
        nested = [c for c in candidates if isinstance(c, type) and issubclass(c, BaseModel)]
        if not nested:
            return None
        model = nested[0]
    return model


def _reason(err: Mapping[str, Any]) -> str:
    kind = err["type"]
    loc = tuple(err["loc"])
    if kind == "missing":
        return "field required"
    if kind == "extra_forbidden":
        model = _model_at(loc[:-1])
        what = "unknown section" if len(loc) == 1 else "unknown key"
        if model is not None:
            close = difflib.get_close_matches(str(loc[-1]), list(model.model_fields), n=1)
            if close:
                return f"{what} (did you mean {close[0]!r}?)"
            return f"{what} (known: {', '.join(model.model_fields)})"
        return what
    msg = str(err["msg"])
    msg = msg.removeprefix("Value error, ")
    msg = re.sub(r"^Input should be", "must be", msg)
    msg = msg[:1].lower() + msg[1:]
    return f"{msg}, got {_show(err.get('input'))}"


def _toml_problem(file: str, exc: tomllib.TOMLDecodeError) -> ConfigProblem:
    text = str(exc)
    m = re.search(r"\(at line (\d+), column (\d+)\)", text)
    if m:
        message = text[: m.start()].strip()
        return ConfigProblem(file, f"line {m[1]}, column {m[2]}", f"TOML syntax error: {message}")
    return ConfigProblem(file, "", f"TOML syntax error: {text}")


def env_api_keys(env: Mapping[str, str]) -> list[str]:
    """API keys from ``$LFCAL_API_KEYS`` (separated by commas and/or whitespace)."""
    return [k for k in re.split(r"[,\s]+", env.get(ENV_API_KEYS, "")) if k]


_PLACEHOLDERS: dict[tuple[str, str], Any] = {("rail", "zero_object_distance_mm"): 1000.0}
"""Stand-ins for invalid required keys, so that the other checks of the section still run."""


def _partial_sections(
    data: Mapping[str, Any], errors: list[Any], context: dict[str, Any]
) -> tuple[dict[str, Any], frozenset[str]]:
    """Validate each section again without its invalid keys (defaults take their place).

    Returns the sections that then validate (None for the others) and the dotted
    keys that were dropped, so that cross-field checks can still run on the rest.
    """
    dropped: dict[str, set[str]] = {name: set() for name in SECTIONS}
    dead: set[str] = set()
    for e in errors:
        loc = tuple(e["loc"])
        if loc and loc[0] in SECTIONS:
            if len(loc) == 1:
                dead.add(str(loc[0]))
            else:
                dropped[str(loc[0])].add(str(loc[1]))
    sections: dict[str, Any] = {}
    for name, model in SECTIONS.items():
        raw = data.get(name, {})
        if name in dead or not isinstance(raw, Mapping):
            sections[name] = None
            continue
        cleaned = {k: v for k, v in raw.items() if k not in dropped[name]}
        for key in dropped[name]:
            if (name, key) in _PLACEHOLDERS:
                cleaned[key] = _PLACEHOLDERS[(name, key)]
        try:
            sections[name] = model.model_validate(cleaned, context=context)
        except ValidationError:
            sections[name] = None
    invalid = frozenset(f"{name}.{key}" for name, keys in dropped.items() for key in keys)
    return sections, invalid


def load_config(
    path: str | os.PathLike[str], *, env: Mapping[str, str] | None = None
) -> StationConfig:
    """Load and validate a station TOML file.

    Relative paths resolve against the file's directory; ``$LFCAL_API_KEYS``
    (from ``env``, default ``os.environ``) is added to ``server.api_keys``.
    Raises :class:`ConfigError` listing every problem.
    """
    env = os.environ if env is None else env
    file = str(path)
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise ConfigError([ConfigProblem(file, "", "file not found")]) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError([ConfigProblem(file, "", f"cannot read: {exc}")]) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError([_toml_problem(file, exc)]) from None

    problems: list[ConfigProblem] = []
    extra_keys = env_api_keys(env)
    env_problems = api_key_problems(extra_keys, ENV_API_KEYS)
    problems += [ConfigProblem("environment", key, reason) for key, reason in env_problems]
    server = data.get("server")
    if extra_keys and not env_problems and (server is None or isinstance(server, dict)):
        server = dict(server or {})
        file_keys = server.get("api_keys", [])
        if isinstance(file_keys, list):
            server["api_keys"] = file_keys + [k for k in extra_keys if k not in file_keys]
            data["server"] = server

    context = {"base_dir": p.resolve().parent, "skip_cross_checks": True}
    config: StationConfig | None = None
    errors: list[Any] = []
    try:
        config = StationConfig.model_validate(data, context=context)
    except ValidationError as exc:
        errors = exc.errors(include_url=False)
        problems += [ConfigProblem(file, _dotted(tuple(e["loc"])), _reason(e)) for e in errors]
    if config is not None:
        sections, invalid = dict(config), frozenset[str]()
    else:
        sections, invalid = _partial_sections(data, errors, context)
    problems += [ConfigProblem(file, k, r) for k, r in cross_field_problems(sections, invalid)]
    if problems or config is None:
        raise ConfigError(problems)
    config._source = p
    return config


def with_frame_cache(
    config: StationConfig, cache_dir: str | os.PathLike[str] | None
) -> StationConfig:
    """``config`` with ``[camera] frame_cache = cache_dir`` (what ``--sim-frame-cache DIR``
    does); unchanged when ``cache_dir`` is None or the camera is not simulated."""
    if cache_dir is None or config.camera.backend != "simulated":
        return config
    camera = config.camera.model_copy(update={"frame_cache": Path(cache_dir).absolute()})
    return config.model_copy(update={"camera": camera})


def load_config_or_report(
    path: str | os.PathLike[str], command: str, err: TextIO
) -> StationConfig | None:
    """:func:`load_config`, or None after writing ``COMMAND: PATH: invalid
    configuration`` and one indented line per problem to ``err``."""
    try:
        return load_config(path)
    except ConfigError as exc:
        err.write(f"{command}: {path}: invalid configuration\n")
        for line in exc.format_problems():
            err.write(f"  {line}\n")
        return None


def check_config_file(path: str | os.PathLike[str]) -> list[str]:
    """Problems of a config file, one formatted line each (empty when valid)."""
    try:
        load_config(path)
    except ConfigError as exc:
        return exc.format_problems()
    return []


def summary(config: StationConfig) -> str:
    """A one-line description of a configuration (for ``lfcal config check``)."""
    cam = config.camera
    w, h = cam.sensor_size_px
    if cam.backend == "simulated":
        camera = f"camera simulated (preset {cam.preset}, {w}×{h} px)"
    else:
        camera = f"camera {cam.backend} {cam.address or cam.serial} ({cam.pixel_format})"
    rail = config.rail
    rail_port = rail.port if rail.driver == "zaber" else "emulated"
    xy_port = (
        "rail's chain" if config.xy_shares_rail_chain else (config.xy_stage.port or "emulated")
    )
    sw = config.sweep
    return (
        f"{camera}; rail {rail_port} {rail.min_mm:g}..{rail.max_mm:g} mm "
        f"(u = {rail.zero_object_distance_mm:g} {'+' if rail.direction > 0 else '-'} rail mm); "
        f"xy_stage on {xy_port}; sweep {sw.start_mm:g}..{sw.stop_mm:g} mm step {sw.step_mm:g} mm "
        f"({sw.frame_count} frames); data {config.storage.data_dir}; "
        f"server {config.server.host}:{config.server.port} "
        f"({len(config.server.api_keys)} API key{'s' if len(config.server.api_keys) != 1 else ''})"
    )


def config_check_main(path: str | os.PathLike[str]) -> int:
    """``lfcal config check FILE``: print ``OK: …`` (stdout) or one line per problem
    (stderr); return the exit code 0 (valid) or 2 (invalid)."""
    try:
        config = load_config(path)
    except ConfigError as exc:
        for line in exc.format_problems():
            print(line, file=sys.stderr)
        return 2
    print(f"OK: {path}: {summary(config)}")
    return 0
