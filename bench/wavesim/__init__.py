"""wavesim: a renderer of a focused plenoptic camera by incoherent scalar wave optics.

A fourth renderer, written from ``OPTICS.md`` and the geometry, board, window,
sensor and archive modules of :mod:`bench.mcsim` (not its tracer or diffraction
samplers, nor the calibration core or the other renderers). The other renderers
blur a geometric image with the *in-focus* diffraction pattern; inside a
microlens's diffraction-limited depth of focus real light does something else
(defocus moves energy from the pattern's core into its rings), and wavesim
forms every micro-image from the defocused pupil of its microlens instead.
``python -m bench.wavesim OUT_DIR [options]`` writes an ``lfcal-sweep/1``
archive (OPTICS.md §5) plus ``truth.json`` and ``render_log.json``;
:func:`cached_sweep` renders one into ``out/bench/wavesim/<name>/`` once.

Modules: ``psf`` (pupils, the FFT PSFs), ``kernel`` (a frame's polychromatic,
truncated kernel on the cell grid), ``coverage`` (exact board area coverage),
``vignetting`` (cos⁴ and the main-aperture pupil fraction V), ``micro`` (one
micro-image), ``render`` (frames, white image, sensor counts), ``sweep``
(archive, parallel sweep, cache), ``settings`` (options), ``__main__`` (CLI).

Physics (thin lenses, paraxial, scalar, incoherent, Fresnel)
-------------------------------------------------------------
* Geometric image: sensor point s of lens m (centre projected along z) sees,
  along the chief ray through the lens centre, the main-image point
  ``r = m - (s - m)·a/b`` (a = a(u), OPTICS.md §1), i.e. board point
  ``P = -r·u/v``: upright inside the micro-image, scale u·a/(v·b). The board's
  mean reflectance over every cell of a grid of ``--oversample`` (default 8)
  cells per pixel and axis is computed exactly (1-D interval overlaps, the map
  being a scale and shift): no edge aliasing (a test: sub-pixel board shifts
  move the measured edge by the shift within 2e-5 px).
* Blur: the incoherent PSF of the microlens pupil (square of side D turned with
  the grid, or a disc of diameter D: ``--aperture``) with the defocus phase
  ``exp(iπ|ξ|²(1/b - 1/b')/λ)``, 1/a + 1/b' = 1/f, computed by FFT (1-D and
  separable for the square, 2-D for the disc), area-binned to the cells,
  truncated at ``rings`` (default 8) diffraction units λb/D beyond the
  geometric blur's half-diagonal (+2 px) and renormalised: the far rings
  dropped hold ~2.2 % of the energy for the square pupil (~1.6 % for the disc),
  reported per frame. It is shift-invariant within a frame: one kernel per
  frame, one FFT convolution per micro-image over its pixels' bounding box plus
  the kernel's half-width (nothing wraps). Polychromatic:
  ``--wavelengths-um 0.45,0.55,0.65`` (equal weights; default 0.55).
  Its λ → 0 limit is the uniform image of the pupil, diameter D·b·|1/a_f - 1/a|
  (OPTICS.md's blur; a test checks it to 0.1 % of the step).
* Radiometry: the convolved image times ``cos⁴θ·V(s)``; θ is the chief ray's
  angle (mcsim averages cos⁴ over the pupil's rays: 0.14 % apart for
  ``small``); V is the fraction of the pupil area whose ray from s, bent by the
  thin microlens, passes the main aperture A (and the optional second stop,
  ``--vignetting-stop-mm``/``--vignetting-diameter-mm``), integrated exactly
  along pupil rows and over 32 rows. V is applied after the convolution: at the
  micro-image rim this is an approximation (the true PSF there is that of the
  partly vignetted pupil, space-variant); the interior, where V = 1, is exact
  within the Fresnel, scalar, thin-lens model. cos⁴·V is evaluated on 2×2
  sub-cells per pixel (V varies over ~10 px), then every pixel is the mean of
  its cells (box pixels, fill factor 1). Signal 1 = a reflectance-1 board on
  the axis, as in mcsim.
* Not modelled: crosstalk (light of a lens landing in a neighbour's pixels; the
  kernel's truncated rings), main-lens aberrations and diffraction, obliquity
  factors beyond cos⁴, coherence, polarisation.
* White image: a uniform board (0.95) convolved with a unit-sum PSF is uniform,
  so it is 0.95·cos⁴·V per pixel (2×2 points), over the whole frame.
* Frames: only the corner windows (mcsim's ``corner_windows``, ``lens_pixels``,
  nearest-micro-image-centre ownership); noise and quantisation by mcsim's
  ``expose`` with its per-image generators (seed, 1, frame) and (seed, 0).

Options: mcsim's camera, board, rail, window and sensor options and presets
(``--preset small|between|paper``); its ray-tracer options are refused.
Speed: ``--preset small --start-mm 20 --frames 31 --step-mm 2 --jobs 2``
renders in about 2.5 minutes on 2 shared cores (see README_SECTION.md).
"""

from bench.wavesim.settings import build_wave_spec
from bench.wavesim.sweep import cached_sweep, render_sweep

__all__ = ["build_wave_spec", "cached_sweep", "render_sweep"]
