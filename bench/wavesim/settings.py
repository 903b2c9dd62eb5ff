"""wavesim's own options and the render spec (mcsim's :class:`SweepSpec` plus the wave optics).

Options beyond mcsim's (``bench.mcsim.spec``): ``wavelengths_um`` (µm, equal
weights; default 0.55), ``oversample`` (cells per pixel and axis, default 8),
``rings`` (kernel half-width in diffraction units λb/D beyond the geometric
blur, default 8) and ``pupil_rows`` (the vignetting quadrature, default 32).
mcsim's ray-tracer options (``rays``, ``subpixel``, ``jitter``,
``white_rays``, ``airy_wavelength_um``, ``spherical_mm``) mean nothing here and
are refused.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from bench.mcsim.camera import OpticsError
from bench.mcsim.spec import SweepSpec, build_spec

RAY_OPTIONS = ("rays", "subpixel", "jitter", "white_rays", "airy_wavelength_um", "spherical_mm")
WAVE_DEFAULTS: dict[str, Any] = {
    "wavelengths_um": (0.55,),
    "oversample": 8,
    "rings": 8.0,
    "pupil_rows": 32,
}


@dataclass(frozen=True)
class WaveSettings:
    """Wavelengths (µm, equal weights), cells per pixel, kernel rings, vignetting rows."""

    wavelengths_um: tuple[float, ...] = (0.55,)
    oversample: int = 8
    rings: float = 8.0
    pupil_rows: int = 32

    @property
    def wavelengths_mm(self) -> tuple[float, ...]:
        return tuple(w * 1e-3 for w in self.wavelengths_um)

    def check(self) -> None:
        if not self.wavelengths_um or not all(w > 0 for w in self.wavelengths_um):
            raise OpticsError("wavelengths must be > 0 um (at least one)")
        if not 1 <= self.oversample <= 16:
            raise OpticsError(f"oversample must be 1..16 (got {self.oversample})")
        if not self.rings > 0:
            raise OpticsError(f"rings must be > 0 (got {self.rings:g})")
        if self.pupil_rows < 4:
            raise OpticsError(f"pupil rows must be >= 4 (got {self.pupil_rows})")


@dataclass(frozen=True)
class WaveSpec:
    """Everything one wavesim sweep needs: mcsim's sweep spec and the wave settings."""

    sweep: SweepSpec
    wave: WaveSettings


def split_options(options: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """(mcsim options, wave options with defaults filled in); refuses ray-tracer options."""
    given = {k: v for k, v in options.items() if v is not None}
    refused = sorted(set(given) & set(RAY_OPTIONS))
    if refused:
        raise OpticsError(f"not a wavesim option (ray tracer only): {', '.join(refused)}")
    wave = {k: given.pop(k, WAVE_DEFAULTS[k]) for k in WAVE_DEFAULTS}
    wave["wavelengths_um"] = tuple(float(w) for w in wave["wavelengths_um"])
    return given, wave


def build_wave_spec(**options: Any) -> WaveSpec:
    """The wavesim spec of flat options; :class:`OpticsError` for impossible ones."""
    mcsim_options, wave_options = split_options(options)
    wave = WaveSettings(
        wavelengths_um=wave_options["wavelengths_um"],
        oversample=int(wave_options["oversample"]),
        rings=float(wave_options["rings"]),
        pupil_rows=int(wave_options["pupil_rows"]),
    )
    wave.check()
    return WaveSpec(build_spec(**mcsim_options), wave)
