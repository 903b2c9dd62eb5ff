"""The plenoptic simulator as the scene of the simulated camera.

:class:`PlenopticScene` adapts :func:`calibration.simulator.render_frame` to the
:class:`drivers.sim.sim_camera.Scene` protocol.  It is the only place where the
simulated twins use the calibration core (its simulator): the import-linter layers
contract makes that one exception for ``drivers.sim``, and production drivers stay
independent of ``calibration`` (a forbidden contract).

With the reference exposure, no gain and the sensor's native bit depth a render is
exactly ``render_frame(camera, object_distance_mm=u, board_offset_mm=offset,
white=white, roi=Roi(x, y, w, h), seed=seed)``.  Otherwise the sensor model is changed
first: ``white_level_e`` times the exposure scale, ``full_well_e`` divided by the gain
factor ``10^(gain_db/20)``, and for another bit depth ``bit_depth`` with the black level
scaled to the new full scale.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from calibration.simulator import Roi as SimRoi
from calibration.simulator import SimCamera, render_frame


class _State(Protocol):
    """What :meth:`PlenopticScene.render` reads from :class:`drivers.sim.sim_camera.SceneState`."""

    @property
    def object_distance_mm(self) -> float: ...
    @property
    def board_offset_mm(self) -> tuple[float, float]: ...
    @property
    def white(self) -> bool: ...


@dataclass(frozen=True)
class PlenopticScene:
    """A simulated plenoptic camera looking at the calibration board.

    Attributes:
        camera: the simulator's camera (optics, sensor, MLA, board).
        name: short name (the preset), shown in the camera model.
        threads: rendering threads (None: the simulator's default).
    """

    camera: SimCamera
    name: str = "simulated"
    threads: int | None = None

    @property
    def sensor_size_px(self) -> tuple[int, int]:
        """Full sensor ``(width, height)`` in px."""
        return (self.camera.sensor.width, self.camera.sensor.height)

    @property
    def principal_point_px(self) -> tuple[float, float]:
        """Where the optical axis meets the full sensor (x, y) in px."""
        x, y = self.camera.sensor.pp
        return (float(x), float(y))

    @property
    def bit_depth(self) -> int:
        """Native ADC bits of the simulated sensor."""
        return self.camera.sensor.bit_depth

    @property
    def board_half_extent_mm(self) -> float:
        """Half-size (mm) of the board's patterned area; beyond it the board is light."""
        return self.camera.board.half_extent_mm

    def sensor_for(self, *, bit_depth: int, exposure_scale: float, gain_db: float) -> SimCamera:
        """The simulator camera with the sensor adjusted for these settings."""
        sensor = self.camera.sensor
        changes: dict[str, Any] = {}
        if exposure_scale != 1.0:
            changes["white_level_e"] = sensor.white_level_e * exposure_scale
        if gain_db != 0.0:
            changes["full_well_e"] = sensor.full_well_e / 10.0 ** (gain_db / 20.0)
        if bit_depth != sensor.bit_depth:
            changes["bit_depth"] = bit_depth
            changes["black_level_dn"] = (
                sensor.black_level_dn * ((1 << bit_depth) - 1) / sensor.max_count
            )
        return self.camera.with_sensor(**changes) if changes else self.camera

    def render(
        self,
        state: _State,
        *,
        roi: tuple[int, int, int, int],
        seed: Sequence[int],
        bit_depth: int,
        exposure_scale: float,
        gain_db: float,
    ) -> NDArray[np.uint16]:
        """Raw counts of the window ``roi = (x, y, width, height)`` (px) for ``state``."""
        cam = self.sensor_for(bit_depth=bit_depth, exposure_scale=exposure_scale, gain_db=gain_db)
        x, y, width, height = roi
        return render_frame(
            cam,
            object_distance_mm=state.object_distance_mm,
            white=state.white,
            board_offset_mm=state.board_offset_mm,
            roi=SimRoi(x, y, width, height),
            seed=list(seed),
            threads=self.threads,
        )


def scene_from_preset(
    preset: str,
    *,
    width: int | None = None,
    height: int | None = None,
    principal_point_px: tuple[float, float] | None = None,
) -> PlenopticScene:
    """The named simulator preset on a ``width × height`` sensor (default: the preset's).

    Without a principal point, a smaller sensor places it so that both board corners
    stay in view over the preset's sweep when they fit
    (:func:`calibration.sim_sweep.fit_frame`).  Raises ``ValueError`` for an unknown
    preset or an impossible sensor.
    """
    from calibration.presets import get_preset
    from calibration.sim_sweep import fit_frame

    fitted = fit_frame(get_preset(preset), width, height, principal_point_px)
    return PlenopticScene(fitted.camera, name=preset)


__all__ = ["PlenopticScene", "scene_from_preset"]
