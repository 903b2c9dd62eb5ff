"""The sweeps of the focus benchmark and the data-sheet offsets they are calibrated with.

Four renderers write ``lfcal-sweep/1`` archives with a ``truth.json``:

* ``sim``: the project's simulator (``python -m station.cli simulate``, i.e.
  ``lfcal simulate``), Gaussian PSF, analytic pixel integration;
* ``indsim``: the independent analytic renderer (``bench/crosscheck/indsim.py``),
  PSF per ray on the board, 2×2 sub-pixels × N×N aperture cells;
* ``mcsim``: the Monte-Carlo ray tracer (``bench/mcsim``), 30 rays per point
  sample, 2×2 point samples per pixel, no PSF: the blur carries ray noise;
* ``wavesim``: the Fourier-optics renderer (``bench/wavesim``), every micro-image
  the board's exact image convolved with the defocused microlens pupil's incoherent
  PSF (scalar Fresnel optics), so that inside the diffraction-limited depth of focus
  a defocus moves light into the pattern's rings, as light does.

On each renderer three accuracy sweeps cover, together, what issue 10 asks
for: a focus plane between rail steps, a sweep that starts or ends about 8 mm
from the focus plane, a 2 mm step, a standard-corner-only window (F and the
rail zero must then fall back to the data sheet) and high noise. mcsim adds a
sweep of round microlenses (the usual MLA; the other sweeps' are square), two
sweeps with the microlenses' diffraction at 550 nm (its sinc² pattern is wider than
the defocus over most of a sweep, as in a real camera at f/12 and beyond; about 20 min
of rendering on 2 cores) and two controls: its 80 px sweep with the 2×2 point samples
jittered in every pixel, and with 4×4 jittered ones, instead of 2×2 at the same place in
every pixel (exact data sheet only; 1 and 3.5 min to render): they tell what the fixed
points cost. Each
two-corner sweep is calibrated with the exact data sheet and with four wrong
ones (issue 11: F ±2 %, f ±2 %, rail zero ±2 mm, alone and combined); the
standard-only sweep with the exact and the combined wrong data sheet.

The coverage sweeps are cheap (small windows, 31 frames 2 mm apart) and vary,
seed by seed, the noise and the phase of the rail steps against the focus
plane (the start moves by the golden-ratio fraction of a step): each is
calibrated with the exact data sheet and with one wrong one (the four
combinations in turn). A wrong data sheet is only a different manifest (the
frames are the same), so its archive shares the base render's images.

The random cameras (:func:`random_camera_config`, mcsim and wavesim) stand in for the
hidden renderers' cameras: each draws its own optics and sweep (lens pitch,
``Q0``, ``b``, ``F``, focus distance, step, direction, rotation, MLA and board
offsets) within the envelope README states, and its own sensor (electrons at
full light, read noise, black level, bit depth) and exposures below full scale, and
is calibrated like a coverage sweep. mcsim draws them at the issue's settings (30 rays
per point sample, 2×2 point samples at the same place in every pixel); wavesim draws
the same cameras in green light (550 nm), whose microlenses' diffraction (pattern scale
``λb/(Dδ)``, 1.3-5 px) is as wide as the defocus over much of a sweep.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from calibration.optics import image_distance

RENDERERS = ("sim", "indsim", "mcsim", "wavesim")


@dataclass(frozen=True)
class PriorOffset:
    """A data sheet off the rendered camera: F and f by a fraction, the rail zero by mm."""

    name: str
    slug: str
    main_focal_rel: float = 0.0
    mla_focal_rel: float = 0.0
    rail_zero_mm: float = 0.0

    @property
    def exact(self) -> bool:
        return self.main_focal_rel == 0.0 and self.mla_focal_rel == 0.0 and self.rail_zero_mm == 0.0


EXACT = PriorOffset("exact", "exact")
OFF = (
    PriorOffset("F+2%", "F+2pct", main_focal_rel=0.02),
    PriorOffset("f-2%", "f-2pct", mla_focal_rel=-0.02),
    PriorOffset("rail+2mm", "rail+2mm", rail_zero_mm=2.0),
    PriorOffset(
        "F-2%,f+2%,rail-2mm",
        "F-2pct_f+2pct_rail-2mm",
        main_focal_rel=-0.02,
        mla_focal_rel=0.02,
        rail_zero_mm=-2.0,
    ),
)
ALL_OFF = OFF[-1]
PRIOR_OFFSETS = {p.name: p for p in (EXACT, *OFF)}


@dataclass(frozen=True)
class SweepConfig:
    """One rendered sweep: renderer, its command-line options (without OUT and seed), seed."""

    renderer: str
    name: str
    args: tuple[str, ...]
    seed: int
    about: str
    priors: tuple[PriorOffset, ...] = (EXACT, *OFF)
    standard_only: bool = False
    coverage: bool = False


def _args(text: str) -> tuple[str, ...]:
    return tuple(text.split())


# cameras -------------------------------------------------------------------------------

INDSIM_SMALL = (
    "--width 2160 --height 480 --pp 1897.5,266.5 --F 25 --f 1.5 --D 0.125 --b 1.95 --u0 220.3 "
    "--theta-deg 0.35 --mla-offset=1.3,2.2 --board-offset=-0.25,0.15 --u-rail0 170 --direction 1"
)
"""The mcsim ``small`` camera drawn by indsim: 50 px lenses, focus at rail 50.3 mm."""

INDSIM_BETWEEN = (
    "--width 2400 --height 800 --pp 2040,439.5 --F 50 --f 2.0 --D 0.2 --b 2.4 --u0 400 "
    "--theta-deg=-0.35 --mla-offset=-0.9,0.6 --u-rail0 352.4 --direction 1"
)
"""bench_crosscheck's ``between`` camera: 80 px lenses, focus at rail 47.6 mm."""

INDSIM_PAPER_1024 = (
    "--width 1024 --height 1024 --pp 511.5,511.5 --F 35 --f 2.5 --D 0.25 --b 3.0 --u0 300 "
    "--theta-deg 0.2 --mla-offset=0.4,-1.1 --u-rail0 250 --direction 1"
)
"""The paper's camera through a 1024×1024 window: the standard corner only."""

ACCURACY: dict[str, tuple[SweepConfig, ...]] = {
    "sim": (
        SweepConfig(
            "sim",
            "rotated-end8",
            _args(
                "--preset rotated --width 2112 --height 640 --start-mm 0 --step-mm 1 --frames 61"
            ),
            1,
            "80 px lenses, focus at rail 52.37 mm (between steps), sweep ends 7.63 mm past it",
        ),
        SweepConfig(
            "sim",
            "noisy-2mm",
            _args("--preset noisy --width 2944 --height 1152 --start-mm 0 --step-mm 2 --frames 50"),
            2,
            "120 px lenses, low light and 12 e- read noise, 2 mm steps, focus at rail 49.55 mm",
        ),
        SweepConfig(
            "sim",
            "paper-standard",
            _args("--preset paper --width 1024 --height 1024 --frames 100"),
            3,
            "the paper's camera through a 1024x1024 window: standard corner only",
            priors=(EXACT, ALL_OFF),
            standard_only=True,
        ),
    ),
    "indsim": (
        SweepConfig(
            "indsim",
            "small-start8",
            _args(INDSIM_SMALL + " --start-mm 42 --step-mm 1 --frames 58"),
            11,
            "50 px lenses, focus at rail 50.3 mm (between steps), sweep starts 8.3 mm before it",
        ),
        SweepConfig(
            "indsim",
            "between-2mm-noisy",
            _args(
                INDSIM_BETWEEN + " --bit-depth 16 --photons 800 --read-noise 8"
                " --start-mm 0 --step-mm 2 --frames 50"
            ),
            12,
            "80 px lenses, 800 e- full light and 8 e- read noise, 2 mm steps, focus at rail 47.6 mm",
        ),
        SweepConfig(
            "indsim",
            "paper-standard",
            _args(INDSIM_PAPER_1024 + " --start-mm 20 --step-mm 1 --frames 61"),
            13,
            "the paper's camera through a 1024x1024 window: standard corner only",
            priors=(EXACT, ALL_OFF),
            standard_only=True,
        ),
    ),
    "mcsim": (
        SweepConfig(
            "mcsim",
            "between-end8",
            _args("--preset between --frames 59"),
            21,
            "80 px lenses, rail towards the camera, focus at rail 49.5 mm (between steps), "
            "sweep ends 8.5 mm past it",
        ),
        SweepConfig(
            "mcsim",
            "between-end8-j2",
            _args("--preset between --frames 59 --jitter"),
            21,
            "the between-end8 sweep (same seed) with its 2x2 point samples jittered in every "
            "pixel: a control, as many samples but no comb common to all pixels",
            priors=(EXACT,),
        ),
        SweepConfig(
            "mcsim",
            "between-end8-j4",
            _args("--preset between --frames 59 --subpixel 4 --jitter"),
            21,
            "the between-end8 sweep (same seed) with 4x4 jittered point samples per pixel: a "
            "control, the pixels sampled nearly as areas (the 2x2 fixed points of the other "
            "mcsim sweeps lock sharp corners to the pixel grid)",
            priors=(EXACT,),
        ),
        SweepConfig(
            "mcsim",
            "small-2mm-noisy",
            _args("--preset small --step-mm 2 --frames 50 --photons 1500 --read-noise 12"),
            22,
            "50 px lenses, 1500 e- full light and 12 e- read noise, 2 mm steps, focus at rail 50.3 mm",
        ),
        SweepConfig(
            "mcsim",
            "between-airy",
            _args("--preset between --frames 59 --airy-wavelength-um 0.55"),
            24,
            "the between-end8 sweep with the microlenses' diffraction at 550 nm (f/12.5: "
            "first zero 2.75 px, wider than the defocus over most of the sweep)",
        ),
        SweepConfig(
            "mcsim",
            "small-2mm-airy",
            _args("--preset small --step-mm 2 --frames 50 --airy-wavelength-um 0.55"),
            25,
            "50 px lenses at f/15.6 with diffraction at 550 nm (first zero 3.4 px), 2 mm steps",
        ),
        SweepConfig(
            "mcsim",
            "small-round",
            _args("--preset small --step-mm 2 --frames 50 --aperture circle"),
            26,
            "50 px round microlenses (a disc of diameter D in each square cell: the defocus "
            "kernel's RMS width is 0.87 of the square's), 2 mm steps",
        ),
        SweepConfig(
            "mcsim",
            "small-2mm-vignetted",
            _args(
                "--preset small --step-mm 2 --frames 50 "
                "--vignetting-stop-mm 12 --vignetting-diameter-mm 3"
            ),
            28,
            "50 px lenses, a rear stop 12 mm behind the main lens that cuts the micro-images "
            "from ~900 px off the axis (a quarter of each of the reference corner's), 2 mm steps",
        ),
        SweepConfig(
            "mcsim",
            "paper-standard",
            _args("--preset paper --corners standard --fit-frame"),
            23,
            "the paper's camera, only the standard corner rendered, frame fitted to it",
            priors=(EXACT, ALL_OFF),
            standard_only=True,
        ),
    ),
    "wavesim": (
        SweepConfig(
            "wavesim",
            "small-2mm",
            _args("--preset small --step-mm 2 --frames 50"),
            31,
            "50 px lenses at f/15.6 in green light (pattern scale λN = 3.4 px against at most "
            "1.5 px of geometric defocus at the sweep's ends), 2 mm steps, focus at rail 50.3 mm",
        ),
        SweepConfig(
            "wavesim",
            "between-end8-white",
            _args("--preset between --frames 59 --wavelengths-um 0.45,0.55,0.65"),
            32,
            "80 px lenses at f/12.5 in white light (450, 550, 650 nm), rail towards the camera, "
            "focus between steps, sweep ends 8.5 mm past it",
        ),
        SweepConfig(
            "wavesim",
            "paper-standard-start8",
            _args("--preset paper --corners standard --fit-frame --start-mm 42 --frames 58"),
            33,
            "the paper's camera (f/12, pattern scale 2.64 px), only the standard corner "
            "rendered, sweep starts 8 mm before the focus plane",
            priors=(EXACT, ALL_OFF),
            standard_only=True,
        ),
    ),
}

COVERAGE_CAMERA = {
    "sim": "--preset paper --width 2640 --height 960",
    "indsim": INDSIM_SMALL + " --nap 3",
    "mcsim": "--preset small",
    "wavesim": "--preset small",
}
"""The cheap two-corner cameras of the coverage sweeps (focus near rail 50 mm)."""

COVERAGE_FRAMES, COVERAGE_STEP_MM, COVERAGE_START_MM = 31, 2.0, 20.0
COVERAGE_SEED_BASE = 100
GOLDEN = (math.sqrt(5.0) - 1.0) / 2.0


def coverage_config(renderer: str, k: int) -> SweepConfig:
    """The ``k``-th coverage sweep of a renderer: its own seed and phase of the rail steps."""
    start = COVERAGE_START_MM + round((k * GOLDEN) % 1.0 * COVERAGE_STEP_MM, 3)
    sweep = f" --start-mm {start:g} --step-mm {COVERAGE_STEP_MM:g} --frames {COVERAGE_FRAMES}"
    return SweepConfig(
        renderer,
        f"coverage-s{k:02d}",
        _args(COVERAGE_CAMERA[renderer] + sweep),
        COVERAGE_SEED_BASE + k,
        f"coverage sweep {k}: {COVERAGE_FRAMES} frames {COVERAGE_STEP_MM:g} mm apart from rail "
        f"{start:g} mm",
        priors=(EXACT, OFF[k % len(OFF)]),
        coverage=True,
    )


def no_cos4_config(k: int) -> SweepConfig:
    """mcsim's ``k``-th coverage sweep with every ray counted alike (``--no-cos4``): a renderer
    that ignores the sensor's obliquity, so no angular shading pulls the rims or the corners
    and the calibration must find none. Same seed, noise draws and rail phase as
    :func:`coverage_config` ``("mcsim", k)``, for a paired comparison."""
    base = coverage_config("mcsim", k)
    return SweepConfig(
        "mcsim",
        f"nocos4-s{k:02d}",
        (*base.args, "--no-cos4"),
        base.seed,
        base.about + ", rays not weighed by cos⁴",
        priors=base.priors,
        coverage=True,
    )


RANDOM_CAMERA_SEED_BASE = 7000
RANDOM_SWEEP_MM = 60.0
RANDOM_MIN_BLUR_PX = 1.2
"""The random cameras' sweeps defocus at least this much (geometric blur diameter, px) at
their far end: the focus plane of a sweep that barely defocuses is refused, by design."""

PIXEL_MM = 0.0025


def _random_camera(rng: np.random.Generator) -> tuple[dict[str, float], float]:
    """One draw of a camera and sweep, and the geometric blur (px) at its farther end."""
    pitch_px = rng.uniform(60.0, 110.0)
    q0 = rng.uniform(0.15, 0.30)
    b = rng.uniform(1.6, 3.4)
    F = rng.uniform(25.0, 75.0)
    u0 = F * rng.uniform(6.0, 10.0)
    step = float(rng.choice([1.0, 1.5, 2.0]))
    focus_rail = rng.uniform(0.25, 0.75) * RANDOM_SWEEP_MM
    direction = int(rng.choice([1, -1]))
    camera = {
        "pitch_px": pitch_px,
        "Q0": q0,
        "b": b,
        "F": F,
        "u0": u0,
        "step": step,
        "focus_rail": focus_rail,
        "direction": direction,
        "theta": rng.uniform(-0.5, 0.5),
        "mla_x": rng.uniform(-4.0, 4.0),
        "mla_y": rng.uniform(-4.0, 4.0),
        "board_x": rng.uniform(-0.45, 0.45),
        "board_y": rng.uniform(-0.45, 0.45),
    }
    # OPTICS.md §1: Q(u) = b / (L - v(u)), L = v(u0) + b/Q0, blur = (D/δ)·|Q(u) - Q0|
    L = image_distance(u0, F) + b / q0
    ends = u0 - direction * focus_rail + direction * np.array([0.0, RANDOM_SWEEP_MM])
    q = b / (L - image_distance(ends, F))
    return camera, float(pitch_px * np.max(np.abs(q - q0)))


def _random_sensor(rng: np.random.Generator) -> dict[str, float | int]:
    """The sensor and exposure of a random camera: electrons at full light (log-uniform),
    read noise, black level, bit depth, and the board's and the white image's light as
    fractions of full scale (an operator exposes below it)."""
    return {
        "photons": float(np.exp(rng.uniform(np.log(3000.0), np.log(40000.0)))),
        "read_noise": rng.uniform(2.0, 8.0),
        "black_level": int(rng.choice([0, 0, 64])),
        "bit_depth": int(rng.choice([12, 12, 16])),
        "exposure": rng.uniform(0.6, 0.95),
        "white_exposure": rng.uniform(0.7, 0.95),
    }


RANDOM_RENDERERS = ("mcsim", "wavesim")
"""The renderers that draw random cameras: the same camera ``k`` on each."""


def random_camera_config(k: int, renderer: str = "mcsim") -> SweepConfig:
    """The ``k``-th random camera, redrawn until its sweep defocuses by at least
    :data:`RANDOM_MIN_BLUR_PX`; calibrated with the exact and one wrong data sheet.
    ``renderer`` (:data:`RANDOM_RENDERERS`): mcsim at 30 rays per point sample and 2×2
    fixed point samples, or wavesim (Fourier optics in green light) of the same camera."""
    if renderer not in RANDOM_RENDERERS:
        raise ValueError(f"random cameras are drawn by {RANDOM_RENDERERS}, not {renderer!r}")
    rng = np.random.default_rng(RANDOM_CAMERA_SEED_BASE + k)
    while True:
        c, blur_px = _random_camera(rng)
        if blur_px >= RANDOM_MIN_BLUR_PX:
            break
    sensor = _random_sensor(rng)
    f = c["b"] / (1.0 + c["Q0"])
    frames = int(round(RANDOM_SWEEP_MM / c["step"])) + 1
    u_rail0 = c["u0"] - c["direction"] * c["focus_rail"]
    samples = "--rays 30 --subpixel 2 " if renderer == "mcsim" else ""
    args = (
        f"--F {c['F']:.4f} --f {f:.5f} --D {c['pitch_px'] * PIXEL_MM:.6f} --b {c['b']:.5f} "
        f"--u0 {c['u0']:.3f} --theta-deg={c['theta']:.3f} "
        f"--mla-offset={c['mla_x']:.2f},{c['mla_y']:.2f} "
        f"--board-offset={c['board_x']:.3f},{c['board_y']:.3f} --u-rail0 {u_rail0:.3f} "
        f"--direction {c['direction']} --start-mm 0 --step-mm {c['step']:g} --frames {frames} "
        f"--fit-frame {samples}--corners both "
        f"--photons {sensor['photons']:.0f} --read-noise {sensor['read_noise']:.2f} "
        f"--black-level {sensor['black_level']} --bit-depth {sensor['bit_depth']} "
        f"--exposure {sensor['exposure']:.3f} --white-exposure {sensor['white_exposure']:.3f}"
    )
    about = (
        f"random camera {k}: {c['pitch_px']:.1f} px lenses, Q0 {c['Q0']:.3f}, b {c['b']:.2f} mm, "
        f"F {c['F']:.1f} mm, focus at u {c['u0']:.0f} mm (rail {c['focus_rail']:.1f}), "
        f"{frames} frames {c['step']:g} mm apart, direction {c['direction']:+d}, "
        f"MLA at {c['theta']:+.2f} deg, blur up to {blur_px:.1f} px; "
        f"{sensor['photons']:.0f} e- at full light, board at {sensor['exposure']:.2f} of it, "
        f"{sensor['bit_depth']} bit, black level {sensor['black_level']}"
    )
    return SweepConfig(
        renderer,
        f"random-c{k:02d}",
        _args(args),
        RANDOM_CAMERA_SEED_BASE + k,
        about,
        priors=(EXACT, OFF[k % len(OFF)]),
        coverage=True,
    )


REPEAT_SEED_STEP = 1000

PRINCIPAL_POINT_OPTION = {
    "sim": "--principal-point",
    "indsim": "--pp",
    "mcsim": "--pp",
    "wavesim": "--pp",
}
"""Each renderer's option that places the optical axis on the sensor (px)."""


def _option(args: tuple[str, ...], name: str) -> str | None:
    """The last value given to option ``name`` in ``args`` (``--x v`` or ``--x=v``)."""
    value = None
    for i, arg in enumerate(args):
        if arg == name and i + 1 < len(args):
            value = args[i + 1]
        elif arg.startswith(name + "="):
            value = arg[len(name) + 1 :]
    return value


def _rendered_frame(config: SweepConfig) -> tuple[tuple[float, float], int, int]:
    """The principal point (px) and the frame size ``config`` renders with, worked out by
    the renderer's own command line (mcsim's spec, ``lfcal simulate``'s preset; indsim's
    configs give ``--pp``, ``--width`` and ``--height``)."""
    if config.renderer in ("mcsim", "wavesim"):
        if config.renderer == "mcsim":
            from bench.mcsim.__main__ import parser
        else:
            from bench.wavesim.__main__ import parser
        from bench.mcsim.spec import build_spec
        from bench.wavesim.settings import split_options

        options = vars(parser().parse_args(["-", *config.args]))
        for name in ("out_dir", "force", "jobs"):
            options.pop(name)
        if config.renderer == "wavesim":
            options = split_options(options)[0]
        camera = build_spec(**options).camera
        x, y = camera.principal_point_px
        return (float(x), float(y)), int(camera.width), int(camera.height)
    if config.renderer == "sim":
        from station.cli import build_parser, simulated_preset

        args = build_parser().parse_args(["simulate", "-", *config.args])
        sensor = simulated_preset(args).camera.sensor
        return (float(sensor.pp[0]), float(sensor.pp[1])), int(sensor.width), int(sensor.height)
    given = _option(config.args, PRINCIPAL_POINT_OPTION[config.renderer])
    if given is None:
        raise ValueError(f"no principal point known for {config.renderer} {config.name}")
    x, y = (float(v) for v in given.split(","))
    size = (_option(config.args, "--width"), _option(config.args, "--height"))
    return (x, y), int(size[0] or 0), int(size[1] or 0)


def principal_point_px(config: SweepConfig) -> tuple[float, float]:
    """The principal point (px) ``config`` renders with (:func:`_rendered_frame`)."""
    return _rendered_frame(config)[0]


def placement_shift_px(k: int) -> tuple[float, float]:
    """The ``k``-th repeat's shift of the whole image against the pixel grid (px, each in
    [0, 1)): golden-ratio fractions, so that successive repeats spread over the pixel."""
    return round((k * GOLDEN) % 1.0, 3), round((k * GOLDEN * GOLDEN) % 1.0, 3)


def repeat_config(config: SweepConfig, k: int) -> SweepConfig:
    """The ``k``-th (1, 2, ...) repeat of an accuracy sweep: the same camera and sweep with
    another seed (noise, and ray noise for mcsim) and the whole image moved against the
    pixel grid by a fraction of a pixel (:func:`placement_shift_px`, through the principal
    point), calibrated with the exact data sheet. One seed's error is one draw: the repeats
    tell a bias from luck. The shift matters where the pixels sample the image unevenly
    (point samples): the errors that follow from where the corners fall on the pixels are
    the same for every seed of one placement."""
    (x, y), width, height = _rendered_frame(config)
    dx, dy = placement_shift_px(k)
    pp = f"{x + dx:.4f},{y + dy:.4f}"
    args = config.args
    if "--fit-frame" in args:  # mcsim: the fit would place the principal point again
        args = tuple(a for a in args if a != "--fit-frame")
        args += ("--width", str(width), "--height", str(height))
    return SweepConfig(
        config.renderer,
        f"{config.name}-s{k}",
        (*args, f"{PRINCIPAL_POINT_OPTION[config.renderer]}={pp}"),
        config.seed + REPEAT_SEED_STEP * k,
        f"{config.about} (repeat {k}, seed {config.seed + REPEAT_SEED_STEP * k}, "
        f"principal point {pp} px)",
        priors=(EXACT,),
        standard_only=config.standard_only,
    )


def quick_config(renderer: str) -> SweepConfig:
    """The quick run's accuracy sweep: the first coverage sweep with every data sheet."""
    base = coverage_config(renderer, 0)
    return SweepConfig(
        renderer, base.name, base.args, base.seed, base.about, priors=(EXACT, *OFF), coverage=False
    )
