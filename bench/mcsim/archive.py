"""Write an ``lfcal-sweep/1`` archive (OPTICS.md §5) and its ground truth.

``sweep.json`` is what a station would write: the manifest's optics and rail
zero are the *data-sheet* values (:class:`bench.mcsim.spec.Manifest`), which
may differ from the rendered camera. ``truth.json`` records the rendered
camera; ``render_log.json`` the cost of every image (and the vignetting stop,
so a log says which optics it timed).
"""

from __future__ import annotations

import json
from dataclasses import asdict
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import numpy.typing as npt

from bench.mcsim.camera import Camera
from bench.mcsim.render import RenderStats
from bench.mcsim.spec import SweepSpec

FORMAT = "lfcal-sweep/1"
GENERATOR = "mcsim"


def frame_file(index: int) -> str:
    return f"frames/{index:04d}.png"


def write_png(path: Path, counts: npt.NDArray[np.uint16]) -> None:
    """A 16-bit grey PNG of right-aligned counts."""
    if counts.dtype != np.uint16 or counts.ndim != 2:
        raise ValueError(f"expected a 2-D uint16 image, got {counts.dtype} {counts.shape}")
    path.parent.mkdir(parents=True, exist_ok=True)
    if not cv2.imwrite(str(path), counts):
        raise OSError(f"could not write {path}")


def manifest(spec: SweepSpec) -> dict[str, Any]:
    cam, m = spec.camera, spec.manifest
    optics: dict[str, Any] = {
        "main_focal_mm": m.main_focal_mm,
        "mla_focal_mm": m.mla_focal_mm,
        "mla_pitch_mm": cam.mla_pitch_mm,
    }
    rail: dict[str, Any] = {
        "zero_object_distance_mm": m.rail_zero_mm,
        "direction": spec.rail.direction,
    }
    if m.tolerances_mm is not None:
        optics["main_focal_tolerance_mm"] = m.tolerances_mm[0]
        optics["mla_focal_tolerance_mm"] = m.tolerances_mm[1]
        rail["zero_object_distance_tolerance_mm"] = m.tolerances_mm[2]
    return {
        "format": FORMAT,
        "generator": GENERATOR,
        "camera": {
            "width": cam.width,
            "height": cam.height,
            "pixel_pitch_mm": cam.pixel_mm,
            "bit_depth": spec.sensor.bit_depth,
            "principal_point_px": list(cam.principal_point_px),
        },
        "optics": optics,
        "board": {"square_mm": spec.board.square_mm, "reference_gap_mm": spec.board.gap_mm},
        "rail": rail,
        "white": "white.png",
        "frames": [
            {"index": k, "rail_mm": spec.rail.rail_mm(k), "file": frame_file(k)}
            for k in range(spec.rail.frames)
        ],
    }


def truth(spec: SweepSpec) -> dict[str, Any]:
    cam, rail, m = spec.camera, spec.rail, spec.manifest
    a_f = cam.a_focus_mm
    u0 = cam.u_focus_mm
    q0 = cam.sensor_distance_mm / a_f
    tolerances = m.tolerances_mm or (None, None, None)
    frames = []
    for k in range(rail.frames):
        u = rail.u_mm(k)
        q = cam.q(u)
        frames.append(
            {
                "index": k,
                "rail_mm": rail.rail_mm(k),
                "u_mm": u,
                "v_mm": cam.v_mm(u),
                "a_mm": cam.a_mm(u),
                "Q": q,
                "p_px": q * cam.lens_pitch_px,
                "defocus_blur_px": cam.defocus_blur_px(u),
            }
        )
    t = spec.trace
    return {
        "generator": GENERATOR,
        "F_mm": cam.main_focal_mm,
        "f_mm": cam.mla_focal_mm,
        "D_mm": cam.mla_pitch_mm,
        "pixel_pitch_mm": cam.pixel_mm,
        "b_mm": cam.sensor_distance_mm,
        "L_mm": cam.mla_distance_mm,
        "a_f_mm": a_f,
        "Q_focus": q0,
        "patch_size_px_focus": q0 * cam.lens_pitch_px,
        "u0_mm": u0,
        "focus_rail_mm": (u0 - rail.u_rail0_mm) / rail.direction,
        "u_rail0_mm": rail.u_rail0_mm,
        "direction": rail.direction,
        "width": cam.width,
        "height": cam.height,
        "principal_point_px": list(cam.principal_point_px),
        "main_aperture_diameter_mm": cam.main_aperture_mm,
        **vignetting_stop(cam),
        "lens_grid": {
            "origin_px": list(cam.lens_origin_px),
            "pitch_px": cam.lens_pitch_px,
            "theta_deg": cam.theta_deg,
        },
        "micro_image_grid": {
            "origin_px": list(cam.micro_image_origin_px),
            "pitch_px": cam.micro_image_pitch_px,
            "theta_deg": cam.theta_deg,
        },
        "board": {
            "square_mm": spec.board.square_mm,
            "reference_gap_mm": spec.board.gap_mm,
            "offset_mm": list(spec.board.offset_mm),
        },
        "render": {
            "preset": spec.preset,
            "rays_per_subpixel": t.rays,
            "subpixels_per_axis": t.subpixel,
            "subpixel_jitter": t.jitter,
            "white_rays_per_subpixel": spec.white_rays,
            "microlens_aperture": cam.microlens_aperture,
            "airy_wavelength_um": t.airy_wavelength_um,
            "spherical_mm": t.spherical_mm,
            "cos4_weighting": t.cos4,
            "gaussian_psf": None,
            "corners": list(spec.corners),
            "window_margin_micro_images": spec.margin,
            "seed": spec.seed,
            "noise": {
                "photons_full_light": spec.sensor.photons,
                "read_noise_e": spec.sensor.read_noise_e,
                "black_level": spec.sensor.black_level,
                "frame_exposure": spec.sensor.exposure,
                "white_exposure": spec.sensor.white_exposure,
                "bit_depth": spec.sensor.bit_depth,
            },
        },
        "manifest_priors": {
            "main_focal_mm": m.main_focal_mm,
            "mla_focal_mm": m.mla_focal_mm,
            "rail_zero_object_distance_mm": m.rail_zero_mm,
            "main_focal_tolerance_mm": tolerances[0],
            "mla_focal_tolerance_mm": tolerances[1],
            "rail_zero_object_distance_tolerance_mm": tolerances[2],
        },
        "frames": frames,
    }


def write_json(path: Path, data: dict[str, Any]) -> None:
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(json.dumps(data, indent=2) + "\n")
    tmp.replace(path)


def vignetting_stop(cam: Camera) -> dict[str, float | None]:
    """The second (vignetting) stop's position z and diameter, mm; None when absent."""
    return {
        "vignetting_stop_mm": cam.vignetting_stop_mm,
        "vignetting_diameter_mm": cam.vignetting_diameter_mm,
    }


def render_log(stats: list[RenderStats], camera: Camera | None = None) -> dict[str, Any]:
    """Cost of every image; with ``camera``, also the vignetting stop it was rendered with."""
    frames = [s for s in stats if s.u_mm is not None]
    rays = sum(s.rays for s in frames)
    cpu = sum(s.cpu_seconds for s in frames)
    return {
        **(vignetting_stop(camera) if camera is not None else {}),
        "frames_rays": rays,
        "frames_cpu_seconds": cpu,
        "frames_wall_seconds": sum(s.seconds for s in frames),
        "frames_rays_per_cpu_second": rays / cpu if cpu else 0.0,
        "cpu_seconds_per_frame": cpu / len(frames) if frames else 0.0,
        "images": [asdict(s) for s in sorted(stats, key=lambda s: s.index)],
    }
