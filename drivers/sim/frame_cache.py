"""Simulation only: a frame cache for the simulated camera, so repeated sweeps are fast.

The plenoptic renderer takes ~1 s for a 1200×400 frame and ~4 s for 3000×1000.
:class:`CachedScene` wraps a scene (:class:`drivers.sim.plenoptic_scene.PlenopticScene`) and keeps
each rendered frame on disk (``.npy``), keyed by everything the picture depends
on: the simulator camera (optics, sensor, MLA, board), the bench state the
camera sees (object distance to 0.1 µm, board offset to 0.1 µm, white or not),
the ROI, bit depth, exposure and gain. The same bench state therefore gives
the same frame, noise included (the noise seed is derived from the key rather
than from the frame counter); any other state -- a drifted rail, another
exposure -- is rendered afresh. The simulated camera uses it when its configuration
says so (``[camera] frame_cache = "DIR"``, or ``--sim-frame-cache DIR`` on the command
line, which sets that key); real cameras are never affected.

Files are written atomically (temporary file, rename), so several processes
can share one cache directory.
"""

from __future__ import annotations

import hashlib
import os
import secrets
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from drivers.sim.sim_camera import Scene


class CachedScene:
    """A scene whose renders are cached in ``cache_dir`` (see the module docstring).

    Args:
        scene: the real scene (renders on a cache miss).
        cache_dir: directory of the ``.npy`` files (created).
    """

    def __init__(self, scene: Scene, cache_dir: str | os.PathLike[str]) -> None:
        self.scene = scene
        self.cache_dir = Path(cache_dir)
        self.cache_dir.mkdir(parents=True, exist_ok=True)
        what = getattr(scene, "camera", scene)  # the simulator camera: optics, sensor, MLA
        self._camera_key = hashlib.sha256(repr(what).encode()).hexdigest()[:16]
        self.hits = 0
        self.misses = 0

    @property
    def camera(self) -> Any:
        """The simulator camera of the wrapped scene."""
        return getattr(self.scene, "camera", None)

    @property
    def name(self) -> str:
        return self.scene.name

    @property
    def sensor_size_px(self) -> tuple[int, int]:
        return self.scene.sensor_size_px

    @property
    def bit_depth(self) -> int:
        return self.scene.bit_depth

    @property
    def board_half_extent_mm(self) -> float:
        return self.scene.board_half_extent_mm

    def key(
        self,
        state: Any,
        roi: tuple[int, int, int, int],
        bit_depth: int,
        exposure_scale: float,
        gain_db: float,
    ) -> str:
        """Cache key of a render (hex)."""
        ox, oy = state.board_offset_mm
        parts = (
            self._camera_key,
            f"u={state.object_distance_mm:.4f}",
            f"off={ox:.4f},{oy:.4f}",
            f"white={bool(state.white)}",
            f"roi={roi}",
            f"bits={bit_depth}",
            f"exp={exposure_scale:.6g}",
            f"gain={gain_db:.6g}",
        )
        return hashlib.sha256("|".join(parts).encode()).hexdigest()[:32]

    def render(
        self,
        state: Any,
        *,
        roi: tuple[int, int, int, int],
        seed: Sequence[int],
        bit_depth: int,
        exposure_scale: float,
        gain_db: float,
    ) -> NDArray[np.uint16]:
        """The cached frame of this state, rendered (and stored) on a miss."""
        key = self.key(state, roi, bit_depth, exposure_scale, gain_db)
        path = self.cache_dir / f"{key}.npy"
        try:
            image = np.load(path)
            self.hits += 1
            return np.ascontiguousarray(image, dtype=np.uint16)
        except (OSError, ValueError):
            pass
        self.misses += 1
        image = self.scene.render(
            state,
            roi=roi,
            seed=[0, int(key[:8], 16)],
            bit_depth=bit_depth,
            exposure_scale=exposure_scale,
            gain_db=gain_db,
        )
        tmp = path.with_name(f".{key}.{secrets.token_hex(4)}.npy")
        try:
            np.save(tmp, image)
            os.replace(tmp, path)
        except OSError:
            tmp.unlink(missing_ok=True)
        return image


__all__ = ["CachedScene"]
