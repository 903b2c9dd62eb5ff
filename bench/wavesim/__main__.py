"""``python -m bench.wavesim OUT_DIR [options]``: render an lfcal-sweep/1 archive by wave optics.

Exit status: 0 rendered, 2 bad options or impossible optics (one line on
stderr), 1 OUT_DIR holds something other than a previous render (or a
previous render without ``--force``) or writing failed.
Negative pairs need the ``=`` form: ``--mla-offset=-3,2``, ``--board-offset=-0.5,0``.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from bench.mcsim.__main__ import _floats
from bench.mcsim.presets import DEFAULT_PRESET, PRESETS
from bench.mcsim.render_cli import render_main
from bench.wavesim.settings import WaveSpec, build_wave_spec
from bench.wavesim.sweep import render_sweep


def _wavelengths(text: str) -> tuple[float, ...]:
    try:
        values = tuple(float(p) for p in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"not numbers: {text!r}") from None
    if not values or not all(v > 0 for v in values):
        raise argparse.ArgumentTypeError(f"wavelengths must be > 0 um: {text!r}")
    return values


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m bench.wavesim",
        description="Incoherent scalar wave-optics (Fresnel, FFT) renderer of a focused "
        "plenoptic camera looking at the double-checkerboard board; writes an "
        "lfcal-sweep/1 archive.",
        allow_abbrev=False,
    )
    p.add_argument("out_dir", type=Path, help="archive directory to write")
    p.add_argument("--preset", choices=sorted(PRESETS), help=f"default {DEFAULT_PRESET}")
    p.add_argument("--force", action="store_true", help="replace a previous render in OUT_DIR")
    p.add_argument("--jobs", type=int, default=1, help="processes rendering frames")
    g = p.add_argument_group("wave optics")
    g.add_argument(
        "--wavelengths-um",
        dest="wavelengths_um",
        type=_wavelengths,
        help="comma-separated wavelengths, equal weights (default 0.55)",
    )
    g.add_argument("--oversample", type=int, help="cells per pixel and axis (default 8)")
    g.add_argument("--rings", type=float, help="kernel half-width beyond the blur, λb/D units")
    g = p.add_argument_group("camera")
    g.add_argument("--width", type=int)
    g.add_argument("--height", type=int)
    g.add_argument("--pp", type=_floats(2), help="principal point X,Y px")
    g.add_argument("--fit-frame", dest="fit_frame", action="store_const", const=True)
    g.add_argument("--F", dest="main_focal_mm", type=float, help="main-lens focal, mm")
    g.add_argument("--f", dest="mla_focal_mm", type=float, help="microlens focal, mm")
    g.add_argument("--D", dest="mla_pitch_mm", type=float, help="microlens pitch, mm")
    g.add_argument("--pixel", dest="pixel_mm", type=float, help="pixel pitch, mm")
    g.add_argument("--b", dest="b_mm", type=float, help="MLA-to-sensor distance, mm")
    g.add_argument("--L", dest="L_mm", type=float, help="main-lens-to-MLA distance, mm")
    g.add_argument("--u0", dest="u0_mm", type=float, help="focus-plane object distance, mm")
    g.add_argument("--theta-deg", dest="theta_deg", type=float)
    g.add_argument("--mla-offset", dest="mla_offset", type=_floats(2), help="X,Y px")
    g.add_argument("--main-aperture-mm", dest="main_aperture_mm", type=float)
    g.add_argument("--aperture", choices=("square", "circle"), help="microlens aperture")
    g.add_argument("--vignetting-stop-mm", dest="vignetting_stop_mm", type=float, metavar="Z")
    g.add_argument(
        "--vignetting-diameter-mm", dest="vignetting_diameter_mm", type=float, metavar="A_V"
    )
    g = p.add_argument_group("board and rail")
    g.add_argument("--square-mm", dest="square_mm", type=float)
    g.add_argument("--gap-mm", dest="gap_mm", type=float, help="reference gap Cr")
    g.add_argument("--board-offset", dest="board_offset", type=_floats(2), help="X,Y mm")
    g.add_argument("--u-rail0", dest="u_rail0_mm", type=float, help="u at rail 0, mm")
    g.add_argument("--direction", type=int, choices=(1, -1))
    g.add_argument("--frames", type=int)
    g.add_argument("--start-mm", dest="start_mm", type=float, help="first rail position")
    g.add_argument("--step-mm", dest="step_mm", type=float, help="rail step")
    g.add_argument("--corners", choices=("standard", "both"))
    g.add_argument("--margin", type=float, help="micro-images beyond the predicted spread")
    g.add_argument("--seed", type=int)
    g = p.add_argument_group("sensor")
    g.add_argument("--bit-depth", dest="bit_depth", type=int)
    g.add_argument("--photons", type=float, help="electrons at full light (signal 1)")
    g.add_argument("--read-noise", dest="read_noise_e", type=float, help="e- rms")
    g.add_argument("--black-level", dest="black_level", type=int, help="counts")
    g.add_argument("--exposure", type=float, help="board frames' light (full light = 1)")
    g.add_argument("--white-exposure", dest="white_exposure", type=float)
    g = p.add_argument_group("data sheet in the manifest (default: the truth)")
    g.add_argument("--manifest-main-focal-mm", dest="manifest_main_focal_mm", type=float)
    g.add_argument("--manifest-mla-focal-mm", dest="manifest_mla_focal_mm", type=float)
    g.add_argument("--manifest-rail-zero-mm", dest="manifest_rail_zero_mm", type=float)
    g.add_argument("--manifest-tolerances", dest="manifest_tolerances", type=_floats(3))
    return p


def main(argv: list[str] | None = None) -> int:
    args: dict[str, Any] = vars(parser().parse_args(argv))
    return render_main("wavesim", args, build_wave_spec, render_sweep, _summary)


def _summary(ws: WaveSpec, log: dict[str, Any]) -> str:
    cam = ws.sweep.camera
    return (
        f"{ws.sweep.rail.frames} frames {cam.width}x{cam.height}, "
        f"{log['wall_seconds']:.1f} s wall, {log['cpu_seconds_per_frame']:.2f} CPU-s/frame"
    )


if __name__ == "__main__":
    sys.exit(main())
