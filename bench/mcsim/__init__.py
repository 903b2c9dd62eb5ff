"""mcsim: a brute-force Monte-Carlo ray tracer of a focused plenoptic camera.

A third renderer, written from ``OPTICS.md`` alone (none of the project's
calibration core or other renderers was read or imported), so that the
calibration can be tested on image formation it was not developed with.
``python -m bench.mcsim OUT_DIR [options]`` writes an ``lfcal-sweep/1`` archive
(OPTICS.md §5) plus ``truth.json`` and ``render_log.json``;
:func:`cached_sweep` renders one into ``out/bench/mcsim/<name>/`` once.

Modules: ``camera`` (geometry, thin-lens relations, lattices), ``board`` (the
double checkerboard), ``trace`` (the ray tracer), ``diffraction`` (microlens
diffraction samplers), ``windows`` (corner windows snapped to micro-images),
``frame_fit`` (frame sizes), ``sensor`` (noise, quantisation), ``render``
(white image and frames), ``archive`` (JSON and PNG writers), ``sweep``
(parallel sweep, cache), ``presets``, ``spec`` (options -> render spec),
``__main__`` (CLI).

Physics and conventions, and why
--------------------------------
* Thin lenses, traced exactly (not paraxially approximated beyond the thin-lens
  model itself): main lens at z = 0 (focal F, circular aperture of diameter
  A = L·D/b unless overridden: OPTICS.md's f-number matching), MLA at z = L,
  sensor at z = L + b, board at z = −u. Rays are traced backwards from point
  samples on the sensor, through a uniformly random point of the pixel's own
  microlens aperture (square of side D, fill factor 1, or a disc of diameter
  D), refracted by that ideal thin lens (deflection −h/f, h the height from the
  lens centre), to the main-lens plane, where rays outside A/2 are dropped
  (this makes the vignetting and the soft micro-image rims), refracted by the
  thin main lens (−x0/F) and intersected with the board plane.
* Pixel ownership (OPTICS.md §2): a pixel belongs to the lens whose micro-image
  centre (the main-lens centre projected through the lens centre, (L+b)/L
  farther from the principal point than the lens centre) is nearest. Light from
  neighbouring lenses is not traced (no crosstalk).
* Board (OPTICS.md §3): X along the sensor's x, Y along its y; board point
  (X, Y) sits at lateral position (X, Y) + board offset from the optical axis,
  so a zero offset puts the standard corner on the axis. The main lens inverts
  the scene by itself (no hand-made flip): the tests check that inside a
  micro-image the board appears upright and that lens m images main-image
  point r at m + (m − r)·b/a.
* Radiometry: each ray is weighted by cos⁴θ, θ its angle to the axis between
  MLA and sensor. With aperture points drawn uniformly in area this is the
  exact irradiance estimator for a Lambertian board (radiance is conserved
  through thin lenses; dE = L·cos⁴θ·dA/b²), so vignetting comes out of the
  geometry rather than from a fitted law. A pixel's signal is the mean over all
  its rays (2×2 sample points × 30 rays by default) of reflectance·cos⁴θ, with
  0 for blocked rays. No Gaussian PSF; the blur carries Monte-Carlo noise.
  ``--no-cos4`` counts every ray that passes alike (a renderer that ignores the
  sensor's obliquity: no angular shading anywhere, flat micro-image plateaus).
* Sample points: the centres of an N×N grid of sub-cells of the pixel
  (``--subpixel N``), or uniformly jittered inside each sub-cell (``--jitter``).
* Diffraction (``--airy-wavelength-um``): every ray's landing point on the
  sensor is displaced by a random draw from the in-focus Fraunhofer pattern of
  the microlens aperture at f-number b/D: the Airy pattern for a circular
  aperture, the separable sinc² pattern (its exact counterpart) for the default
  square aperture, each truncated at 99 % of the energy. In a backward tracer
  this is the same as displacing the sensor point before tracing (the pattern
  is symmetric): the image is the geometric image convolved with the
  diffraction pattern, exact at focus and the usual approximation out of focus.
* Spherical aberration (``--spherical-mm S``): the main lens's focal length
  depends on the ray's height ρ on it, F(ρ) = F − S·(ρ/(A/2))². S is the
  longitudinal aberration of a rim ray for an object at infinity (S > 0: the
  under-corrected aberration of a simple positive lens); for a finite object
  the focus shift is S·(v/F)²·(ρ/(A/2))² to first order.
* Mechanical vignetting (``--vignetting-stop-mm Z --vignetting-diameter-mm
  A_v``): a second circular stop, centred on the axis at z = Z (0 < Z < L:
  between the main lens and the MLA; Z < 0: in front of the main lens, the
  board beyond it), blocks every ray whose lateral position on its plane lies
  outside A_v/2 (the straight ray from the MLA point to x0 behind the lens, the
  refracted ray with its object-side slope in front of it). Far off axis it
  cuts micro-images into "cat's eyes": a rear stop on their side towards the
  axis, a front stop on the side away from it (its image through the main lens
  lies in front of the lens). Default: no second stop (renders unchanged).
* Sensor: the full-light signal (a reflectance-1 board on the axis) gives
  ``--photons`` electrons and maps to full scale; Poisson shot noise, Gaussian
  read noise (e−), black level, rounding and clipping to the bit depth
  (right-aligned counts in 16-bit PNGs).
* Windows (speed): frames render only the micro-images whose centres lie within
  (N/2 + margin) micro-image pitches (default margin 1.5) of where the chief
  ray of the standard corner (0, 0) and, with ``--corners both``, of the
  reference corner (2s, 0) meets the sensor (−X·(L+b)/u from the principal
  point; N = (a/b)(L+b)/(L−a)), every pixel of each such micro-image, so no
  window edge cuts a micro-image. All other pixels get 0 signal plus sensor
  noise. The white image (uniform reflectance 0.95) covers every pixel with the
  same tracer, with ``--white-rays`` rays per sample point (default: ``--rays``).
* Pixels whose every possible ray (the lens aperture mapped onto the main-lens
  plane, widened by the pixel and the largest diffraction offset) misses the
  main aperture are set to 0 without tracing; this changes nothing (a test
  traces them by brute force) and saves the dark corners of each cell.
* Random numbers: every frame draws everything (jitter, rays, diffraction,
  noise) from a generator seeded by (seed, 1, frame index), the white image
  from (seed, 0): renders are reproducible and independent of ``--jobs``.

Presets (``--preset``, options override): ``paper`` (the default), ``between``,
``small``; see :mod:`bench.mcsim.presets`.
"""

from bench.mcsim.spec import build_spec
from bench.mcsim.sweep import cached_sweep, render_sweep

__all__ = ["build_spec", "cached_sweep", "render_sweep"]
