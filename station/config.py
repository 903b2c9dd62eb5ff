"""Station configuration: pydantic v2 models loaded from a TOML file.

The sections' models are in :mod:`station.config_sections`, the checks that involve
several keys in :mod:`station.config_checks`; this module holds the whole
:class:`StationConfig` and loads, reports and summarizes a file.

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
import os
import re
import sys
import tomllib
from collections.abc import Mapping
from pathlib import Path
from typing import Any, NamedTuple, TextIO

from pydantic import (
    BaseModel,
    Field,
    PrivateAttr,
    ValidationError,
    ValidationInfo,
    model_validator,
)

from .config_checks import api_key_problems, cross_field_problems, shares_chain
from .config_sections import (
    ENV_API_KEYS,
    BoardConfig,
    CameraConfig,
    ConfigSection,
    OpticsConfig,
    RailConfig,
    ServerConfig,
    StorageConfig,
    SweepConfig,
    XYStageConfig,
)


class StationConfig(ConfigSection):
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
        return shares_chain(self.rail, self.xy_stage)

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


SECTIONS: dict[str, type[ConfigSection]] = {
    "camera": CameraConfig,
    "rail": RailConfig,
    "xy_stage": XYStageConfig,
    "optics": OpticsConfig,
    "board": BoardConfig,
    "sweep": SweepConfig,
    "storage": StorageConfig,
    "server": ServerConfig,
}


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
