"""Named cameras and sweeps (``--preset NAME``; any option overrides them).

Frame sizes and principal points were computed with
:func:`bench.mcsim.frame_fit.fit_frame` for both corners and the default
margin over the preset's whole sweep, so the frames just hold both corners'
windows (a test checks it). Overriding the sweep can move a window off the
frame; the renderer then says so (or use ``--fit-frame``).

* ``paper``: the seed paper's Zemax set-up (OPTICS.md §1): F = 35, f = 2.5,
  D = 0.25, δ = 2.5 µm (100 px lenses, ~105.5 px micro-images), b = 3,
  focus plane u0 = 300 (L = 54.6226), rail 250..349 mm in 1 mm steps, MLA
  rotated 0.2°. a_f = 15, Q0 = 0.2, p = 20 px; ~7 micro-images per corner.
* ``between``: F = 50, f = 2, D = 0.2 (80 px lenses), b = 2.5 (a_f = 10,
  Q0 = 0.25, p = 20 px), focus plane at u0 = 400.5 mm, halfway between two
  rail steps; the rail runs towards the camera (direction −1, u = 450..351);
  MLA at −0.3° and offset, board off-centre by a fraction of a millimetre, the
  principal point off the frame's centre (it is placed by the fit).
* ``small``: F = 25, f = 1.5, D = 0.125 (50 px lenses, ~52.8 px micro-images),
  b = 1.95 (a_f = 6.5, Q0 = 0.3, p = 15 px), focus plane u0 = 220.3
  (between steps), rail 170..269 mm; fast coverage runs (many seeds).
"""

from __future__ import annotations

from typing import Any

DEFAULT_PRESET = "paper"

PRESETS: dict[str, dict[str, Any]] = {
    "paper": {
        "width": 3024,
        "height": 1232,
        "pp": (2405.5, 620.5),
        "main_focal_mm": 35.0,
        "mla_focal_mm": 2.5,
        "mla_pitch_mm": 0.25,
        "pixel_mm": 0.0025,
        "b_mm": 3.0,
        "u0_mm": 300.0,
        "theta_deg": 0.2,
        "mla_offset": (2.6, -1.8),
        "board_offset": (0.0, 0.0),
        "u_rail0_mm": 250.0,
        "direction": 1,
        "start_mm": 0.0,
        "step_mm": 1.0,
        "frames": 100,
    },
    "between": {
        "width": 2304,
        "height": 816,
        "pp": (1984.5, 401.5),
        "main_focal_mm": 50.0,
        "mla_focal_mm": 2.0,
        "mla_pitch_mm": 0.2,
        "pixel_mm": 0.0025,
        "b_mm": 2.5,
        "u0_mm": 400.5,
        "theta_deg": -0.3,
        "mla_offset": (-3.2, 1.4),
        "board_offset": (0.4, -0.3),
        "u_rail0_mm": 450.0,
        "direction": -1,
        "start_mm": 0.0,
        "step_mm": 1.0,
        "frames": 100,
    },
    "small": {
        "width": 2160,
        "height": 480,
        "pp": (1897.5, 266.5),
        "main_focal_mm": 25.0,
        "mla_focal_mm": 1.5,
        "mla_pitch_mm": 0.125,
        "pixel_mm": 0.0025,
        "b_mm": 1.95,
        "u0_mm": 220.3,
        "theta_deg": 0.35,
        "mla_offset": (1.3, 2.2),
        "board_offset": (-0.25, 0.15),
        "u_rail0_mm": 170.0,
        "direction": 1,
        "start_mm": 0.0,
        "step_mm": 1.0,
        "frames": 100,
    },
}
