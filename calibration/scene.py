"""A textured scene for the simulator: text, a Siemens star and a cube face, not a checkerboard.

The seed paper shows what a calibration is for by rendering real scenes (its
Fig. 12: letters and a Rubik's cube) with the calibrated and with the designed
parameters. :class:`SceneBoard` puts such a scene in front of the simulated
camera: it is a :class:`calibration.board.Board` (the target the simulator
renders, ``SimCamera.board``) whose reflectance is a raster texture instead of
the analytic double checkerboard, so a scene frame goes through exactly the same
camera model (rays through every microlens aperture, main-lens vignetting, PSF,
pixel footprint, noise) as the calibration frames::

    cam = replace(camera, board=text_scene())
    raw = render_frame(cam, object_distance_mm=u)

Scene coordinates are the board's (mm, ``X`` along the sensor's x, ``Y`` along
its y, seen from the camera); texture texel ``[row, col]`` covers
``X = origin_x + col·texel_mm``, ``Y = origin_y + row·texel_mm``, so text drawn
upright in the array reads upright in an upright rendering. Outside the texture
the scene is a uniform grey (``outside``).

Integration over a pixel's footprint (a box of half width ``h``) and the PSF
(Gaussian ``σ``) is approximated by one Gaussian of the same variance,
``σ² + (2h)²/12``, applied to the texture once per ``(h, σ)`` (both are fixed
within a frame), then sampled bilinearly: close enough for a test scene (the
calibration never sees it). :meth:`SceneBoard.distance_to_edge_mm` is negative
everywhere, so the simulator traces every aperture ray of every pixel
(exact defocus blur, about 3× slower than a board frame).
"""

from __future__ import annotations

import argparse
import json
import sys
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from .board import Board
from .optics import CameraOptics
from .presets import get_preset
from .simulator import SimCamera, render_frame


def _empty_texture() -> NDArray[np.float32]:
    return np.full((2, 2), 0.5, dtype=np.float32)


@dataclass(frozen=True)
class SceneBoard(Board):
    """A raster-textured target (reflectances in [0, 1]); see the module docstring.

    Attributes:
        texture: reflectance per texel, ``[row, col]`` = ``[Y, X]``.
        texel_mm: texel size (mm).
        origin_mm: scene position ``(X, Y)`` (mm) of texel ``[0, 0]``.
        outside: reflectance outside the texture.
    """

    texture: NDArray[np.float32] = field(default_factory=_empty_texture, compare=False, repr=False)
    texel_mm: float = 0.02
    origin_mm: tuple[float, float] = (0.0, 0.0)
    outside: float = 0.5
    _filtered: dict[tuple[float, float], NDArray[np.float32]] = field(
        default_factory=dict, compare=False, repr=False
    )
    _lock: Any = field(default_factory=threading.Lock, compare=False, repr=False)

    def __post_init__(self) -> None:
        super().__post_init__()
        if self.texture.ndim != 2 or min(self.texture.shape) < 2:
            raise ValueError("the scene texture must be a 2-D array of at least 2x2 texels")
        if not self.texel_mm > 0:
            raise ValueError(f"texel size must be positive, got {self.texel_mm} mm")

    @property
    def extent_mm(self) -> tuple[float, float, float, float]:
        """``(X0, X1, Y0, Y1)`` covered by the texture (mm)."""
        h, w = self.texture.shape
        x0, y0 = self.origin_mm
        return (x0, x0 + (w - 1) * self.texel_mm, y0, y0 + (h - 1) * self.texel_mm)

    def distance_to_edge_mm(
        self, X: NDArray[np.floating], Y: NDArray[np.floating]
    ) -> NDArray[np.floating]:
        """Negative everywhere: every pixel is near texture detail (trace every ray)."""
        return np.full(np.broadcast_shapes(np.shape(X), np.shape(Y)), -1.0)

    def box_reflectance(
        self,
        X: NDArray[np.floating],
        Y: NDArray[np.floating],
        half_width_mm: float,
        blur_sigma_mm: float = 0.0,
    ) -> NDArray[np.floating]:
        """Mean reflectance over the box ``[X±h] × [Y±h]`` after a Gaussian blur ``σ`` (mm),
        approximated as described in the module docstring."""
        tex = self._filtered_texture(float(half_width_mm), float(blur_sigma_mm))
        h, w = tex.shape
        fx = (np.asarray(X, dtype=np.float64) - self.origin_mm[0]) / self.texel_mm
        fy = (np.asarray(Y, dtype=np.float64) - self.origin_mm[1]) / self.texel_mm
        fx, fy = np.broadcast_arrays(fx, fy)
        inside = (fx >= 0) & (fx <= w - 1) & (fy >= 0) & (fy <= h - 1)
        x0 = np.clip(np.floor(fx), 0, w - 2).astype(np.int64)
        y0 = np.clip(np.floor(fy), 0, h - 2).astype(np.int64)
        tx = np.clip(fx - x0, 0.0, 1.0)
        ty = np.clip(fy - y0, 0.0, 1.0)
        top = tex[y0, x0] * (1 - tx) + tex[y0, x0 + 1] * tx
        bottom = tex[y0 + 1, x0] * (1 - tx) + tex[y0 + 1, x0 + 1] * tx
        value = top * (1 - ty) + bottom * ty
        out = np.where(inside, value, self.outside)
        return out.astype(np.asarray(X).dtype if np.asarray(X).dtype.kind == "f" else np.float64)

    def _filtered_texture(self, half_width_mm: float, sigma_mm: float) -> NDArray[np.float32]:
        key = (round(half_width_mm, 9), round(sigma_mm, 9))
        with self._lock:
            cached = self._filtered.get(key)
            if cached is None:
                var_mm2 = sigma_mm**2 + (2.0 * half_width_mm) ** 2 / 12.0
                sigma_tx = float(np.sqrt(var_mm2)) / self.texel_mm
                tex = self.texture.astype(np.float32)
                if sigma_tx > 0.05:
                    tex = np.asarray(
                        cv2.GaussianBlur(tex, (0, 0), sigma_tx, borderType=cv2.BORDER_REPLICATE),
                        dtype=np.float32,
                    )
                self._filtered[key] = cached = tex
            return cached


def _draw_text(
    canvas: NDArray[np.float32], text: str, centre: tuple[int, int], cap_px: int
) -> None:
    """Dark upright text of cap height ``cap_px``, centred horizontally on ``centre``
    with its baseline at ``centre``'s row."""
    font = cv2.FONT_HERSHEY_DUPLEX
    (_, cap1), _ = cv2.getTextSize("H", font, 1.0, 1)
    scale = cap_px / cap1
    thickness = max(1, int(round(cap_px / 9)))
    (width, _), _ = cv2.getTextSize(text, font, scale, thickness)
    org = (int(centre[0] - width / 2), int(centre[1]))
    cv2.putText(canvas, text, org, font, scale, 0.06, thickness, cv2.LINE_AA)


def _siemens_star(
    canvas: NDArray[np.float32], centre: tuple[int, int], radius_px: int, spokes: int = 24
) -> None:
    cy, cx = centre[1], centre[0]
    yy, xx = np.mgrid[-radius_px : radius_px + 1, -radius_px : radius_px + 1]
    r = np.hypot(xx, yy)
    angle = np.arctan2(yy, xx)
    dark = (np.floor(angle / (2 * np.pi) * 2 * spokes) % 2 == 0) & (r <= radius_px)
    y0, x0 = cy - radius_px, cx - radius_px
    sub = canvas[y0 : y0 + 2 * radius_px + 1, x0 : x0 + 2 * radius_px + 1]
    sub[dark] = 0.06
    sub[(r <= radius_px) & ~dark] = 0.92


def _cube_face(
    canvas: NDArray[np.float32], top_left: tuple[int, int], size_px: int, rng: np.random.Generator
) -> None:
    """A 3×3 'Rubik's cube' face: squares of six grey levels with dark borders."""
    x0, y0 = top_left
    canvas[y0 : y0 + size_px, x0 : x0 + size_px] = 0.05
    cell = size_px / 3.0
    gap = max(1, int(round(cell * 0.08)))
    levels = np.array([0.95, 0.75, 0.6, 0.45, 0.3, 0.2], dtype=np.float32)
    for r in range(3):
        for c in range(3):
            ya, yb = int(y0 + r * cell) + gap, int(y0 + (r + 1) * cell) - gap
            xa, xb = int(x0 + c * cell) + gap, int(x0 + (c + 1) * cell) - gap
            canvas[ya:yb, xa:xb] = levels[rng.integers(0, levels.size)]


def text_scene(
    *,
    centre_mm: tuple[float, float] = (11.0, 0.0),
    size_mm: tuple[float, float] = (90.0, 80.0),
    texel_mm: float = 0.02,
    seed: int = 0,
) -> SceneBoard:
    """The test scene (mm, scene coordinates) around ``centre_mm``.

    Within ±15 × ±6 mm of the centre (the view of a 2000×800 px window of the
    ``rotated`` preset at its focus plane): the words LIGHT FIELD (cap height
    2.4 mm), three lines of smaller text (1.1 and 0.7 mm), a Siemens star
    (radius 2.2 mm, 24 spokes) and a 3×3 cube face (4 mm); around it, for larger
    frames, more text, stars and cube faces; everything on a mottled grey
    background. ``size_mm`` is the textured area; outside it the scene is grey.
    """
    w = int(round(size_mm[0] / texel_mm))
    h = int(round(size_mm[1] / texel_mm))
    rng = np.random.default_rng(seed)
    coarse = rng.standard_normal((h // 16 + 2, w // 16 + 2)).astype(np.float32)
    noise = np.asarray(
        cv2.GaussianBlur(
            cv2.resize(coarse, (w, h), interpolation=cv2.INTER_CUBIC), (0, 0), 0.3 / texel_mm
        ),
        dtype=np.float32,
    )
    noise /= max(float(noise.std()), 1e-6)
    canvas = np.clip(0.64 + 0.07 * noise, 0.4, 0.85).astype(np.float32)
    ox, oy = size_mm[0] / 2.0, size_mm[1] / 2.0  # the centre, from the top-left (mm)

    def px(dx_mm: float, dy_mm: float) -> tuple[int, int]:
        """Texel (col, row) at offset (dx, dy) mm from the scene centre."""
        return int(round((ox + dx_mm) / texel_mm)), int(round((oy + dy_mm) / texel_mm))

    def mm(value: float) -> int:
        return int(round(value / texel_mm))

    _draw_text(canvas, "LIGHT FIELD", px(0.5, -2.4), mm(2.4))
    _draw_text(canvas, "calibrated p vs designed p", px(0.5, -0.3), mm(1.1))
    _draw_text(canvas, "ESIF  Q = b/a  p = Q D/delta", px(0.5, 1.3), mm(0.7))
    _draw_text(canvas, "0123456789 abcdefghijklm", px(0.5, 2.6), mm(0.7))
    _draw_text(canvas, "nopqrstuvwxyz ABCDEFGHIJ", px(0.5, 3.9), mm(0.7))
    _siemens_star(canvas, px(11.5, 2.6), mm(2.2))
    _cube_face(canvas, px(-15.8, -1.0), mm(3.6), rng)
    # the periphery, for frames that see more of the scene
    for k, (dx, dy) in enumerate(((-22.0, -14.0), (22.0, -14.0), (-22.0, 14.0), (22.0, 14.0))):
        _siemens_star(canvas, px(dx, dy), mm(4.0), spokes=16 + 8 * (k % 2))
    for dx, dy in ((-4.0, -14.0), (-4.0, 12.0), (-34.0, 0.0), (30.0, 0.0)):
        _cube_face(canvas, px(dx - 3.0, dy - 3.0), mm(6.0), rng)
    _draw_text(canvas, "FOCUSED PLENOPTIC CAMERA", px(0.0, -24.0), mm(3.0))
    _draw_text(canvas, "GEORGIEV - LUMSDAINE RENDERING", px(0.0, 27.0), mm(2.5))
    origin = (centre_mm[0] - ox, centre_mm[1] - oy)
    return SceneBoard(texture=canvas, texel_mm=texel_mm, origin_mm=origin)


def camera_of_sweep(truth: dict[str, Any]) -> SimCamera:
    """The simulated camera of a sweep written by ``lfcal simulate``, from its ``truth.json``:
    the preset's camera with the sweep's optics, sensor window and principal point."""
    cam = get_preset(str(truth["preset"])).camera
    o, sensor = truth["optics"], truth["sensor"]
    optics = CameraOptics(
        F=o["F_mm"],
        f=o["f_mm"],
        D=o["D_mm"],
        delta=o["delta_mm"],
        b=o["b_mm"],
        L=o["L_mm"],
        aperture=o["aperture_mm"],
    )
    pp = sensor.get("principal_point_px")
    return replace(
        cam,
        optics=optics,
        sensor=replace(
            cam.sensor,
            width=int(sensor["width"]),
            height=int(sensor["height"]),
            principal_point_px=None if pp is None else (float(pp[0]), float(pp[1])),
        ),
    )


def main(argv: Sequence[str] | None = None) -> int:
    """``python -m calibration.scene SWEEP OUT.png --object-distance-mm U``: a raw frame of
    the text scene taken by the simulated camera of ``SWEEP`` (an ``lfcal simulate`` archive
    with its ``truth.json``), to try ``lfcal render`` on something that is not the board."""
    parser = argparse.ArgumentParser(prog="python -m calibration.scene", description=main.__doc__)
    parser.add_argument("sweep", help="an lfcal simulate archive (its truth.json gives the camera)")
    parser.add_argument("out", help="the raw frame to write (16-bit PNG)")
    parser.add_argument("--object-distance-mm", type=float, required=True, help="scene distance u")
    parser.add_argument(
        "--centre-mm", default=None, help="scene centre X,Y (mm) on the board plane"
    )
    parser.add_argument("--seed", type=int, default=0, help="noise seed")
    args = parser.parse_args(argv)
    try:
        truth = json.loads((Path(args.sweep) / "truth.json").read_text(encoding="utf-8"))
        camera = camera_of_sweep(truth)
        centre = (11.0, 0.0) if truth.get("preset") == "rotated" else (0.0, 0.0)
        if args.centre_mm:
            x, y = (float(v) for v in args.centre_mm.split(","))
            centre = (x, y)
        raw = render_frame(
            replace(camera, board=text_scene(centre_mm=centre)),
            object_distance_mm=args.object_distance_mm,
            seed=args.seed,
        )
    except (OSError, ValueError, KeyError) as exc:
        print(f"calibration.scene: {exc}", file=sys.stderr)
        return 2
    if not cv2.imwrite(args.out, raw):
        print(f"calibration.scene: cannot write {args.out}", file=sys.stderr)
        return 2
    print(
        f"wrote {args.out}: {raw.shape[1]}x{raw.shape[0]} px, scene at u = {args.object_distance_mm:g} mm"
    )
    return 0


__all__ = ["SceneBoard", "camera_of_sweep", "main", "text_scene"]


if __name__ == "__main__":
    sys.exit(main())
