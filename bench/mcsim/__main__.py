"""``python -m bench.mcsim OUT_DIR [options]``: render an lfcal-sweep/1 archive.

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

from bench.mcsim.presets import DEFAULT_PRESET, PRESETS
from bench.mcsim.render_cli import render_main
from bench.mcsim.spec import SweepSpec, build_spec
from bench.mcsim.sweep import render_sweep


def _floats(count: int) -> Any:
    def parse(text: str) -> tuple[float, ...]:
        parts = text.split(",")
        if len(parts) != count:
            raise argparse.ArgumentTypeError(f"expected {count} comma-separated numbers: {text!r}")
        try:
            return tuple(float(p) for p in parts)
        except ValueError:
            raise argparse.ArgumentTypeError(f"not numbers: {text!r}") from None

    return parse


def parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m bench.mcsim",
        description="Brute-force Monte-Carlo ray tracer of a focused plenoptic camera "
        "looking at the double-checkerboard board; writes an lfcal-sweep/1 archive.",
        allow_abbrev=False,
    )
    p.add_argument("out_dir", type=Path, help="archive directory to write")
    p.add_argument("--preset", choices=sorted(PRESETS), help=f"default {DEFAULT_PRESET}")
    p.add_argument("--force", action="store_true", help="replace a previous render in OUT_DIR")
    p.add_argument("--jobs", type=int, default=1, help="processes rendering frames")
    g = p.add_argument_group("camera")
    g.add_argument("--width", type=int)
    g.add_argument("--height", type=int)
    g.add_argument("--pp", type=_floats(2), help="principal point X,Y px")
    g.add_argument(
        "--fit-frame",
        dest="fit_frame",
        action="store_const",
        const=True,
        help="size the frame to just hold every window of the sweep",
    )
    g.add_argument("--F", dest="main_focal_mm", type=float, help="main-lens focal, mm")
    g.add_argument("--f", dest="mla_focal_mm", type=float, help="microlens focal, mm")
    g.add_argument("--D", dest="mla_pitch_mm", type=float, help="microlens pitch, mm")
    g.add_argument("--pixel", dest="pixel_mm", type=float, help="pixel pitch, mm")
    g.add_argument("--b", dest="b_mm", type=float, help="MLA-to-sensor distance, mm")
    g.add_argument("--L", dest="L_mm", type=float, help="main-lens-to-MLA distance, mm")
    g.add_argument("--u0", dest="u0_mm", type=float, help="focus-plane object distance, mm")
    g.add_argument("--theta-deg", dest="theta_deg", type=float)
    g.add_argument(
        "--mla-offset",
        dest="mla_offset",
        type=_floats(2),
        help="lens (0,0) projected centre minus principal point X,Y px",
    )
    g.add_argument(
        "--main-aperture-mm",
        dest="main_aperture_mm",
        type=float,
        help="main aperture diameter (default L*D/b)",
    )
    g.add_argument("--aperture", choices=("square", "circle"), help="microlens aperture")
    g.add_argument(
        "--vignetting-stop-mm",
        dest="vignetting_stop_mm",
        type=float,
        metavar="Z",
        help="mechanical vignetting: a second circular stop centred on the axis at z = Z mm "
        "(main lens at 0, MLA at L): 0 < Z < L between the main lens and the MLA, Z < 0 "
        "in front of the main lens (the board must stay beyond it); rays outside it are "
        "blocked. Needs --vignetting-diameter-mm (default: no second stop)",
    )
    g.add_argument(
        "--vignetting-diameter-mm",
        dest="vignetting_diameter_mm",
        type=float,
        metavar="A_V",
        help="diameter of the --vignetting-stop-mm stop, mm",
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
    g = p.add_argument_group("sampling")
    g.add_argument("--rays", type=int, help="rays per sample point (default 30)")
    g.add_argument("--subpixel", type=int, help="N: NxN sample points per pixel (default 2)")
    g.add_argument("--jitter", action="store_const", const=True, help="jitter sample points")
    g.add_argument(
        "--white-rays",
        dest="white_rays",
        type=int,
        help="rays per sample point of the white image (default --rays)",
    )
    g.add_argument("--airy-wavelength-um", dest="airy_wavelength_um", type=float)
    g.add_argument(
        "--spherical-mm",
        dest="spherical_mm",
        type=float,
        help="main-lens longitudinal spherical aberration at the rim, mm",
    )
    g.add_argument(
        "--no-cos4",
        dest="cos4",
        action="store_const",
        const=False,
        help="count every ray alike (no cos⁴ of its angle at the sensor)",
    )
    g.add_argument("--corners", choices=("standard", "both"))
    g.add_argument("--margin", type=float, help="micro-images beyond the predicted spread")
    g.add_argument("--seed", type=int)
    g = p.add_argument_group("sensor")
    g.add_argument("--bit-depth", dest="bit_depth", type=int)
    g.add_argument("--photons", type=float, help="electrons at full light (signal 1)")
    g.add_argument("--read-noise", dest="read_noise_e", type=float, help="e- rms")
    g.add_argument("--black-level", dest="black_level", type=int, help="counts")
    g.add_argument(
        "--exposure",
        type=float,
        help="board frames' light (full light = 1; > 1.05 saturates)",
    )
    g.add_argument(
        "--white-exposure",
        dest="white_exposure",
        type=float,
        help="the white image's light (full light = 1; > 1 saturates)",
    )
    g = p.add_argument_group("data sheet in the manifest (default: the truth)")
    g.add_argument("--manifest-main-focal-mm", dest="manifest_main_focal_mm", type=float)
    g.add_argument("--manifest-mla-focal-mm", dest="manifest_mla_focal_mm", type=float)
    g.add_argument("--manifest-rail-zero-mm", dest="manifest_rail_zero_mm", type=float)
    g.add_argument(
        "--manifest-tolerances",
        dest="manifest_tolerances",
        type=_floats(3),
        help="F_TOL_MM,f_TOL_MM,RAIL_TOL_MM",
    )
    return p


def main(argv: list[str] | None = None) -> int:
    return render_main("mcsim", vars(parser().parse_args(argv)), build_spec, render_sweep, _summary)


def _summary(spec: SweepSpec, log: dict[str, Any]) -> str:
    return (
        f"{spec.rail.frames} frames {spec.camera.width}x{spec.camera.height}, "
        f"{log['wall_seconds']:.1f} s wall, {log['cpu_seconds_per_frame']:.2f} CPU-s/frame, "
        f"{log['frames_rays_per_cpu_second'] / 1e6:.1f} M rays/CPU-s"
    )


if __name__ == "__main__":
    sys.exit(main())
