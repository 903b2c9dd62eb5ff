"""Simulated sweeps: frame window placement, ground truth, and frame generation.

``truth`` holds every ground-truth quantity a test or benchmark compares with
(format ``lfcal-truth/1``): optics (b, L, a_f, A), the focus plane (object
distance and rail position), Q and p per frame, the lens and micro-image
lattices, and the true sensor position of the standard and reference corners
in every micro-image that shows them.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterator
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from .archive import SweepWriter
from .presets import Preset
from .simulator import SimCamera, corner_images_px, render_frame


def corner_extent_px(cam: SimCamera, preset: Preset) -> tuple[float, float, float, float]:
    """Extent (min x, max x, min y, max y) of both corners' images relative to the pp over the sweep."""
    xs: list[float] = []
    ys: list[float] = []
    big = cam.with_sensor(width=20000, height=20000, principal_point_px=(9999.5, 9999.5))
    for rail in preset.sweep.rail_positions_mm():
        u = preset.sweep.object_distance_mm(rail)
        for corner in (cam.board.standard_corner_mm, cam.board.reference_corner_mm):
            for p in corner_images_px(big, corner, u, preset.sweep.board_offset_mm):
                xs.append(float(p["x"]) - 9999.5)
                ys.append(float(p["y"]) - 9999.5)
    return min(xs), max(xs), min(ys), max(ys)


def fit_frame(
    preset: Preset,
    width: int | None = None,
    height: int | None = None,
    principal_point_px: tuple[float, float] | None = None,
) -> Preset:
    """The preset with a sensor of ``width × height``.

    Without an explicit principal point, a smaller frame places it so that the
    images of both corners over the whole sweep are in view when they fit
    (centred in the needed window), else keeps the preset's offset from centre.
    """
    cam = preset.camera
    w = width or cam.sensor.width
    h = height or cam.sensor.height
    if principal_point_px is None:
        if (w, h) == (cam.sensor.width, cam.sensor.height):
            principal_point_px = cam.sensor.pp
        else:
            x0, x1, y0, y1 = corner_extent_px(cam, preset)
            margin = 0.5 * cam.optics.image_pitch_px
            ppx = (w - 1) / 2.0 - (x0 + x1) / 2.0
            ppy = (h - 1) / 2.0 - (y0 + y1) / 2.0
            if x1 - x0 + 2 * margin > w:  # cannot see both: keep the standard corner centred
                ppx = (w - 1) / 2.0
            if y1 - y0 + 2 * margin > h:
                ppy = (h - 1) / 2.0
            principal_point_px = (round(ppx * 2) / 2.0, round(ppy * 2) / 2.0)
    new_cam = cam.with_sensor(width=w, height=h, principal_point_px=principal_point_px)
    return replace(preset, camera=new_cam)


def frame_seed(seed: int, index: int) -> list[int]:
    """Per-frame noise seed: reproducible and independent of the frame order."""
    return [seed, index]


def white_seed(seed: int) -> list[int]:
    return [seed, 1_000_000]


def render_white(preset: Preset, seed: int = 0) -> NDArray[np.uint16]:
    """The flat-field image, rendered at the middle of the sweep."""
    rails = preset.sweep.rail_positions_mm()
    u = preset.sweep.object_distance_mm(rails[len(rails) // 2])
    return render_frame(preset.camera, object_distance_mm=u, white=True, seed=white_seed(seed))


def iter_frames(preset: Preset, seed: int = 0) -> Iterator[tuple[int, float, NDArray[np.uint16]]]:
    """``(index, rail_mm, raw frame)`` for every rail position of the sweep."""
    for index, rail in enumerate(preset.sweep.rail_positions_mm()):
        u = preset.sweep.object_distance_mm(rail)
        yield (
            index,
            rail,
            render_frame(
                preset.camera,
                object_distance_mm=u,
                board_offset_mm=preset.sweep.board_offset_mm,
                seed=frame_seed(seed, index),
            ),
        )


def truth(preset: Preset, seed: int = 0) -> dict[str, Any]:
    """Every ground-truth quantity of the simulated sweep (JSON-ready)."""
    cam = preset.camera
    o = cam.optics
    sweep = preset.sweep
    lens = cam.lens_grid
    img = cam.image_grid
    u0 = o.u0
    frames = []
    for index, rail in enumerate(sweep.rail_positions_mm()):
        u = sweep.object_distance_mm(rail)
        a = float(o.a(u))
        frames.append(
            {
                "index": index,
                "rail_mm": rail,
                "object_distance_mm": u,
                "a_mm": a,
                "Q": float(o.Q(u)),
                "patch_size_px": float(o.patch_px(u)),
                "blur_px": float(o.blur_px(u)),
                "corners": {
                    "standard": corner_images_px(
                        cam, cam.board.standard_corner_mm, u, sweep.board_offset_mm
                    ),
                    "reference": corner_images_px(
                        cam, cam.board.reference_corner_mm, u, sweep.board_offset_mm
                    ),
                },
            }
        )
    return {
        "format": "lfcal-truth/1",
        "preset": preset.name,
        "seed": seed,
        "optics": {
            "F_mm": o.F,
            "f_mm": o.f,
            "D_mm": o.D,
            "delta_mm": o.delta,
            "b_mm": o.b,
            "L_mm": o.L,
            "aperture_mm": o.aperture,
            "a_f_mm": o.a_f,
        },
        "a_mm": o.a_f,
        "b_mm": o.b,
        "Q": o.Q_focus,
        "patch_size_px": float(o.patch_px(u0)),
        "focus": {
            "object_distance_mm": u0,
            "rail_mm": (u0 - sweep.zero_object_distance_mm) / sweep.direction,
        },
        "sensor": {
            "width": cam.sensor.width,
            "height": cam.sensor.height,
            "principal_point_px": list(cam.sensor.pp),
            "bit_depth": cam.sensor.bit_depth,
            "white_level_e": cam.sensor.white_level_e,
            "read_noise_e": cam.sensor.read_noise_e,
            "black_level_dn": cam.sensor.black_level_dn,
        },
        "mla": {
            "lens_origin_px": list(lens.origin_px),
            "lens_pitch_px": lens.pitch_px,
            "image_origin_px": list(img.origin_px),
            "image_pitch_px": img.pitch_px,
            "rotation_deg": cam.mla_rotation_deg,
            "image_disc_radius_px": 0.5 * o.lens_pitch_px,
        },
        "board": {
            "square_mm": cam.board.square_mm,
            "reference_gap_mm": cam.board.reference_gap_mm,
            "offset_mm": list(sweep.board_offset_mm),
        },
        "psf_sigma_px": cam.psf_sigma_px,
        "rail": {
            "zero_object_distance_mm": sweep.zero_object_distance_mm,
            "direction": sweep.direction,
        },
        "frames": frames,
    }


@dataclass(frozen=True)
class DataSheet:
    """What the manifest claims when it differs from the rendered camera (mm; None: the truth).

    A lab's data sheet is off by a few percent and its ruler by a millimetre
    or two: this renders one camera and describes it with other values, and
    optionally states their 1-sigma tolerances.
    """

    main_focal_mm: float | None = None
    mla_focal_mm: float | None = None
    rail_zero_mm: float | None = None
    main_focal_tolerance_mm: float | None = None
    mla_focal_tolerance_mm: float | None = None
    rail_zero_tolerance_mm: float | None = None

    def apply(self, manifest: dict[str, Any]) -> dict[str, Any]:
        """The manifest with these values (and tolerances) in place of the true ones."""
        optics, rail = dict(manifest["optics"]), dict(manifest["rail"])
        for key, value in (
            ("main_focal_mm", self.main_focal_mm),
            ("mla_focal_mm", self.mla_focal_mm),
            ("main_focal_tolerance_mm", self.main_focal_tolerance_mm),
            ("mla_focal_tolerance_mm", self.mla_focal_tolerance_mm),
        ):
            if value is not None:
                optics[key] = value
        if self.rail_zero_mm is not None:
            rail["zero_object_distance_mm"] = self.rail_zero_mm
        if self.rail_zero_tolerance_mm is not None:
            rail["zero_object_distance_tolerance_mm"] = self.rail_zero_tolerance_mm
        return {**manifest, "optics": optics, "rail": rail}


def manifest_header(preset: Preset, datasheet: DataSheet | None = None) -> dict[str, Any]:
    """The ``lfcal-sweep/1`` manifest of a simulated sweep, without its frames."""
    header = _true_header(preset)
    return header if datasheet is None else datasheet.apply(header)


def _true_header(preset: Preset) -> dict[str, Any]:
    cam = preset.camera
    o = cam.optics
    return {
        "format": "lfcal-sweep/1",
        "camera": {
            "width": cam.sensor.width,
            "height": cam.sensor.height,
            "pixel_pitch_mm": o.delta,
            "bit_depth": cam.sensor.bit_depth,
            "principal_point_px": list(cam.sensor.pp),
        },
        "optics": {"main_focal_mm": o.F, "mla_focal_mm": o.f, "mla_pitch_mm": o.D},
        "board": {"square_mm": cam.board.square_mm, "reference_gap_mm": cam.board.reference_gap_mm},
        "rail": {
            "zero_object_distance_mm": preset.sweep.zero_object_distance_mm,
            "direction": preset.sweep.direction,
        },
        "white": "white.png",
        "frames": [],
        "simulated": {"preset": preset.name},
    }


def write_sweep(
    out_dir: str | Path,
    preset: Preset,
    *,
    seed: int = 0,
    overwrite: bool = False,
    progress: Callable[[int, int], None] | None = None,
    datasheet: DataSheet | None = None,
) -> Path:
    """Render the preset's sweep into an ``lfcal-sweep/1`` archive plus ``truth.json``.

    ``datasheet`` puts other (data-sheet) values than the rendered camera's
    in the manifest; ``truth.json`` always holds the true ones. Everything is
    staged in a hidden sibling directory and renamed at the end, so an
    interrupted run never leaves a complete-looking archive.
    """
    writer = SweepWriter.create(out_dir, manifest_header(preset, datasheet), overwrite=overwrite)
    try:
        writer.write_white(render_white(preset, seed))
        total = preset.sweep.frames
        for index, rail, image in iter_frames(preset, seed):
            u = preset.sweep.object_distance_mm(rail)
            writer.add_frame(index, rail, image, object_distance_mm=u)
            if progress is not None:
                progress(index + 1, total)
        truth_text = json.dumps(truth(preset, seed), indent=1) + "\n"
        (writer.work_dir / "truth.json").write_text(truth_text, encoding="utf-8")
        return writer.commit()
    except BaseException:
        writer.abort()
        raise
