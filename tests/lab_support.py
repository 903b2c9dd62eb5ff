"""Shared data of the lab tests (render, export, report; no tests here).

One calibrated simulated camera, made once and kept in pytest's cache directory
(``lfcal-lab-v2``; a lock file serialises the first build between test
processes):

- ``sweep/``: an ``lfcal-sweep/1`` archive of the ``rotated`` preset (F = 50,
  80 px lenses, MLA rotated 0.45°, off-centre principal point) on a 2000×800
  window, 12 frames 4 mm apart around the focus plane (u0 = 432.37 mm), and
  ``result.json``, its calibration by ``lfcal calibrate``;
- ``scene_u432.png``, ``scene_u400.png``: a textured scene (text, a Siemens
  star, cube faces: :func:`calibration.scene.text_scene`) in front of the same
  camera at the focus plane and at 400 mm, 16-bit PNG;
- ``other_camera.png``: a board frame of the same size from another camera
  (the ``paper`` preset: 100 px lenses, another MLA placement).

About 45 s the first time on 2 cores, then read from the cache.
"""

from __future__ import annotations

import fcntl
import json
import shutil
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from calibration.presets import get_preset, with_sweep
from calibration.scene import text_scene
from calibration.sim_sweep import fit_frame
from calibration.simulator import SimCamera, render_frame
from station.cli import main as lfcal

VERSION = "lfcal-lab-v2"
WIDTH, HEIGHT = 2000, 800
FOCUS_MM = 432.37
NEAR_MM = 400.0


@dataclass(frozen=True)
class LabData:
    """Paths of the cached lab data (see the module docstring)."""

    root: Path

    @property
    def sweep(self) -> Path:
        return self.root / "sweep"

    @property
    def result_path(self) -> Path:
        return self.root / "result.json"

    def result(self) -> dict[str, Any]:
        data: dict[str, Any] = json.loads(self.result_path.read_text(encoding="utf-8"))
        return data

    @property
    def truth(self) -> dict[str, Any]:
        data: dict[str, Any] = json.loads((self.sweep / "truth.json").read_text())
        return data

    def scene(self, u_mm: float) -> Path:
        return self.root / f"scene_u{u_mm:.0f}.png"

    @property
    def other_camera(self) -> Path:
        return self.root / "other_camera.png"


def lab_camera(principal_point_px: tuple[float, float]) -> SimCamera:
    """The simulated camera of the lab sweep (its board: the calibration board)."""
    return fit_frame(get_preset("rotated"), WIDTH, HEIGHT, principal_point_px).camera


def scene_camera(principal_point_px: tuple[float, float]) -> SimCamera:
    """The simulated camera of the lab sweep, looking at the text scene (3×3 rays a lens)."""
    return replace(lab_camera(principal_point_px), board=text_scene(), aperture_samples=3)


def _build(root: Path) -> None:
    work = root.with_name(root.name + ".partial")
    shutil.rmtree(work, ignore_errors=True)
    work.mkdir(parents=True)
    code = lfcal(
        [
            "simulate",
            str(work / "sweep"),
            "--preset",
            "rotated",
            "--frames",
            "12",
            "--start-mm",
            "30",
            "--step-mm",
            "4",
            "--width",
            str(WIDTH),
            "--height",
            str(HEIGHT),
            "--seed",
            "5",
        ]
    )
    assert code == 0
    assert lfcal(["calibrate", str(work / "sweep"), "--out", str(work / "result.json")]) == 0
    manifest = json.loads((work / "sweep" / "sweep.json").read_text())
    pp = tuple(float(v) for v in manifest["camera"]["principal_point_px"])
    cam = scene_camera((pp[0], pp[1]))
    for u in (FOCUS_MM, NEAR_MM):
        raw = render_frame(cam, object_distance_mm=u, seed=[3, int(u)])
        assert cv2.imwrite(str(work / f"scene_u{u:.0f}.png"), raw)
    other = fit_frame(with_sweep(get_preset("paper"), frames=1), WIDTH, HEIGHT).camera
    raw = render_frame(other, object_distance_mm=300.0, seed=9)
    assert cv2.imwrite(str(work / "other_camera.png"), raw)
    (work / "complete").write_text(VERSION)
    shutil.rmtree(root, ignore_errors=True)
    work.rename(root)


def lab_data(pytestconfig: pytest.Config) -> LabData:
    """The cached lab data, built on first use."""
    base = Path(pytestconfig.cache.mkdir("lfcal-lab"))
    root = base / VERSION
    with (base / "lock").open("w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        try:
            if not (root / "complete").is_file():
                _build(root)
        finally:
            fcntl.flock(lock, fcntl.LOCK_UN)
    return LabData(root)


def read_png(path: Path) -> np.ndarray:
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert image is not None, path
    return np.asarray(image)
