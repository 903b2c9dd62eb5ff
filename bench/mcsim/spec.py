"""Everything one sweep render needs, built from flat options (CLI or keyword form).

Option names (the CLI's ``--flag`` in brackets):

* camera: ``width``, ``height`` [--width, --height], ``pp`` (x, y) px [--pp],
  ``main_focal_mm`` [--F], ``mla_focal_mm`` [--f], ``mla_pitch_mm`` [--D],
  ``pixel_mm`` [--pixel], ``b_mm`` [--b], ``L_mm`` [--L] or ``u0_mm`` [--u0]
  (the focus-plane object distance; L = v(u0) + a_f), ``theta_deg``,
  ``mla_offset`` (px of lens (0, 0)'s projected centre from the principal point),
  ``main_aperture_mm`` (default L·D/b), ``aperture`` (microlens: square|circle),
  ``vignetting_stop_mm`` [--vignetting-stop-mm] and ``vignetting_diameter_mm``
  [--vignetting-diameter-mm] (a second circular stop at z = Z, both or neither),
  ``fit_frame`` (size the frame and place the principal point to just hold the
  windows of the whole sweep);
* board: ``square_mm``, ``gap_mm``, ``board_offset`` (mm);
* rail: ``u_rail0_mm``, ``direction``, ``frames``, ``start_mm``, ``step_mm``;
* sampling: ``rays``, ``subpixel``, ``jitter``, ``white_rays``,
  ``airy_wavelength_um``, ``spherical_mm``, ``cos4`` (False [--no-cos4]: rays not weighed
  by their angle), ``corners`` (standard|both),
  ``margin`` (micro-images beyond the predicted spread), ``seed``;
* sensor: ``bit_depth``, ``photons``, ``read_noise_e``, ``black_level``,
  ``exposure`` (the board frames' light), ``white_exposure`` (the white image's);
* data sheet written to the manifest (the render uses the truth):
  ``manifest_main_focal_mm``, ``manifest_mla_focal_mm``, ``manifest_rail_zero_mm``,
  ``manifest_tolerances`` (F, f, rail-zero tolerances in mm).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from bench.mcsim.board import Board
from bench.mcsim.camera import Camera, OpticsError
from bench.mcsim.frame_fit import fit_frame
from bench.mcsim.presets import DEFAULT_PRESET, PRESETS
from bench.mcsim.sensor import SensorSettings
from bench.mcsim.trace import TraceSettings

DEFAULTS: dict[str, Any] = {
    "width": None,
    "height": None,
    "pp": None,
    "theta_deg": 0.0,
    "mla_offset": (0.0, 0.0),
    "main_aperture_mm": None,
    "aperture": "square",
    "vignetting_stop_mm": None,
    "vignetting_diameter_mm": None,
    "fit_frame": False,
    "square_mm": 10.0,
    "gap_mm": 0.1,
    "board_offset": (0.0, 0.0),
    "direction": 1,
    "start_mm": 0.0,
    "step_mm": 1.0,
    "frames": 100,
    "rays": 30,
    "subpixel": 2,
    "jitter": False,
    "white_rays": None,
    "airy_wavelength_um": None,
    "spherical_mm": 0.0,
    "cos4": True,
    "corners": "both",
    "margin": 1.5,
    "seed": 0,
    "bit_depth": 12,
    "photons": 20000.0,
    "read_noise_e": 5.0,
    "black_level": 0,
    "exposure": 1.0,
    "white_exposure": 1.0,
    "manifest_main_focal_mm": None,
    "manifest_mla_focal_mm": None,
    "manifest_rail_zero_mm": None,
    "manifest_tolerances": None,
}
OPTION_NAMES = frozenset(DEFAULTS) | {
    "preset",
    "main_focal_mm",
    "mla_focal_mm",
    "mla_pitch_mm",
    "pixel_mm",
    "b_mm",
    "L_mm",
    "u0_mm",
    "u_rail0_mm",
}
CORNER_SETS = {"standard": ("standard",), "both": ("standard", "reference")}


@dataclass(frozen=True)
class Rail:
    """Object distance ``u = u_rail0 + direction·rail_mm`` at each frame's rail position."""

    u_rail0_mm: float
    direction: int
    start_mm: float
    step_mm: float
    frames: int

    def rail_mm(self, index: int) -> float:
        return round(self.start_mm + index * self.step_mm, 9)

    def u_mm(self, index: int) -> float:
        return self.u_rail0_mm + self.direction * self.rail_mm(index)


@dataclass(frozen=True)
class Manifest:
    """Data-sheet values the manifest announces (may differ from the rendered camera)."""

    main_focal_mm: float
    mla_focal_mm: float
    rail_zero_mm: float
    tolerances_mm: tuple[float, float, float] | None


@dataclass(frozen=True)
class SweepSpec:
    preset: str
    camera: Camera
    board: Board
    rail: Rail
    trace: TraceSettings
    sensor: SensorSettings
    corners: tuple[str, ...]
    margin: float
    white_rays: int
    seed: int
    manifest: Manifest

    @property
    def u_values_mm(self) -> list[float]:
        return [self.rail.u_mm(k) for k in range(self.rail.frames)]


def merged_options(options: dict[str, Any]) -> dict[str, Any]:
    """Defaults, then the preset's values, then the given options (None = not given)."""
    given = {k: v for k, v in options.items() if v is not None}
    unknown = set(given) - OPTION_NAMES
    if unknown:
        raise TypeError(f"unknown mcsim option(s): {', '.join(sorted(unknown))}")
    preset = given.get("preset", DEFAULT_PRESET)
    if preset not in PRESETS:
        raise OpticsError(f"unknown preset {preset!r} (choose from {', '.join(PRESETS)})")
    if "L_mm" in given and "u0_mm" in given:
        raise OpticsError("give L or u0, not both")
    merged = {**DEFAULTS, **PRESETS[preset], **given, "preset": preset}
    if ("width" in given or "height" in given) and "pp" not in given:
        merged["pp"] = None  # a preset's principal point belongs to the preset's frame
    if "L_mm" in given:
        merged.pop("u0_mm", None)
    elif "u0_mm" in merged:
        merged.pop("L_mm", None)
    return merged


def build_spec(**options: Any) -> SweepSpec:
    """The sweep spec of the given options; :class:`OpticsError` for impossible optics."""
    o = merged_options(options)
    F, f, b = float(o["main_focal_mm"]), float(o["mla_focal_mm"]), float(o["b_mm"])
    D, pixel = float(o["mla_pitch_mm"]), float(o["pixel_mm"])
    if not (F > 0 and f > 0 and b > 0 and D > 0 and pixel > 0):
        raise OpticsError("F, f, b, D and the pixel pitch must all be > 0 mm")
    if b <= f:
        raise OpticsError(f"b ({b:g} mm) must exceed f ({f:g} mm): no sharp virtual image")
    a_f = 1.0 / (1.0 / f - 1.0 / b)
    if "L_mm" in o:
        L = float(o["L_mm"])
    else:
        u0 = float(o["u0_mm"])
        if u0 <= F:
            raise OpticsError(f"focus plane u0 = {u0:g} mm <= F = {F:g} mm: no real image")
        L = u0 * F / (u0 - F) + a_f
    if o["corners"] not in CORNER_SETS:
        raise OpticsError(f"corners must be 'standard' or 'both' (got {o['corners']!r})")
    if o["aperture"] not in ("square", "circle"):
        raise OpticsError(f"aperture must be 'square' or 'circle' (got {o['aperture']!r})")
    if int(o["direction"]) not in (1, -1):
        raise OpticsError(f"direction must be +1 or -1 (got {o['direction']})")
    if int(o["frames"]) < 1 or int(o["rays"]) < 1 or int(o["subpixel"]) < 1:
        raise OpticsError("frames, rays and subpixel must be >= 1")
    rail = Rail(
        float(o["u_rail0_mm"]),
        int(o["direction"]),
        float(o["start_mm"]),
        float(o["step_mm"]),
        int(o["frames"]),
    )
    aperture_mm = float(o["main_aperture_mm"]) if o["main_aperture_mm"] else L * D / b
    board = Board(float(o["square_mm"]), float(o["gap_mm"]), _pair(o["board_offset"]))
    corners = CORNER_SETS[o["corners"]]
    offset = _pair(o["mla_offset"])
    stop_z = _optional_float(o["vignetting_stop_mm"])
    stop_d = _optional_float(o["vignetting_diameter_mm"])

    def camera_of(width: int, height: int, pp: tuple[float, float]) -> Camera:
        return Camera(
            width=width,
            height=height,
            pixel_mm=pixel,
            principal_point_px=pp,
            main_focal_mm=F,
            mla_focal_mm=f,
            mla_pitch_mm=D,
            sensor_distance_mm=b,
            mla_distance_mm=L,
            theta_deg=float(o["theta_deg"]),
            lens_origin_px=(pp[0] + offset[0], pp[1] + offset[1]),
            main_aperture_mm=aperture_mm,
            microlens_aperture=o["aperture"],
            vignetting_stop_mm=stop_z,
            vignetting_diameter_mm=stop_d,
        )

    trial = camera_of(1, 1, (0.0, 0.0))
    trial.check([rail.u_mm(k) for k in range(rail.frames)])
    if o["fit_frame"] or o["width"] is None or o["height"] is None:
        u_values = [rail.u_mm(k) for k in range(rail.frames)]
        width, height, pp = fit_frame(trial, board, u_values, corners, float(o["margin"]))
    else:
        width, height = int(o["width"]), int(o["height"])
        pp = _pair(o["pp"]) if o["pp"] is not None else ((width - 1) / 2.0, (height - 1) / 2.0)
    camera = camera_of(width, height, pp)
    camera.check([rail.u_mm(k) for k in range(rail.frames)])
    if not abs(float(o["spherical_mm"])) < F / 2:
        raise OpticsError(f"spherical aberration must be below F/2 = {F / 2:g} mm in size")
    if o["airy_wavelength_um"] is not None and not float(o["airy_wavelength_um"]) >= 0:
        raise OpticsError("the Airy wavelength must be >= 0 um")
    trace = TraceSettings(
        rays=int(o["rays"]),
        subpixel=int(o["subpixel"]),
        jitter=bool(o["jitter"]),
        airy_wavelength_um=float(o["airy_wavelength_um"]) if o["airy_wavelength_um"] else None,
        spherical_mm=float(o["spherical_mm"]),
        cos4=bool(o["cos4"]),
    )
    sensor = SensorSettings(
        int(o["bit_depth"]),
        float(o["photons"]),
        float(o["read_noise_e"]),
        int(o["black_level"]),
        float(o["exposure"]),
        float(o["white_exposure"]),
    )
    try:
        sensor.check()
    except ValueError as exc:
        raise OpticsError(str(exc)) from None
    tolerances = o["manifest_tolerances"]
    manifest = Manifest(
        main_focal_mm=float(o["manifest_main_focal_mm"] or F),
        mla_focal_mm=float(o["manifest_mla_focal_mm"] or f),
        rail_zero_mm=float(
            o["manifest_rail_zero_mm"]
            if o["manifest_rail_zero_mm"] is not None
            else rail.u_rail0_mm
        ),
        tolerances_mm=tuple(float(t) for t in tolerances) if tolerances else None,  # type: ignore[arg-type]
    )
    white_rays = int(o["white_rays"]) if o["white_rays"] else trace.rays
    return SweepSpec(
        preset=o["preset"],
        camera=camera,
        board=board,
        rail=rail,
        trace=trace,
        sensor=sensor,
        corners=corners,
        margin=float(o["margin"]),
        white_rays=white_rays,
        seed=int(o["seed"]),
        manifest=manifest,
    )


def _optional_float(value: Any) -> float | None:
    return None if value is None else float(value)


def _pair(value: Any) -> tuple[float, float]:
    x, y = value
    return (float(x), float(y))
