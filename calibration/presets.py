"""Named simulated cameras and sweeps.

- ``paper``: the seed paper's Zemax set-up (F=35, f=2.5, D=0.25, b=3, focus
  at u=300 on a rail step), 5120×5120 GMAX0505 sensor.
- ``rotated``: finer pitch (80 px), shorter microlens focal length, F=50,
  0.45° MLA rotation, off-centre principal point, focus between rail steps.
- ``noisy``: coarser pitch (120 px), f=3, F=40, rail counting towards the
  camera (direction -1), low light and high read noise, focus between steps.

Each preset gives a :class:`SimCamera` and a :class:`SweepPlan`.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from .board import Board
from .optics import optics_focused_at
from .simulator import SensorModel, SimCamera


@dataclass(frozen=True)
class SweepPlan:
    """Rail geometry and the sweep: ``u = zero_object_distance_mm + direction·rail_mm``."""

    zero_object_distance_mm: float
    direction: int
    start_mm: float = 0.0
    step_mm: float = 1.0
    frames: int = 100
    board_offset_mm: tuple[float, float] = (0.0, 0.0)

    def rail_positions_mm(self) -> list[float]:
        return [round(self.start_mm + k * self.step_mm, 9) for k in range(self.frames)]

    def object_distance_mm(self, rail_mm: float) -> float:
        return self.zero_object_distance_mm + self.direction * rail_mm


@dataclass(frozen=True)
class Preset:
    name: str
    description: str
    camera: SimCamera
    sweep: SweepPlan


def _paper() -> Preset:
    cam = SimCamera(
        optics=optics_focused_at(300.0, F=35.0, f=2.5, D=0.25, b=3.0),
        sensor=SensorModel(width=5120, height=5120),
        board=Board(),
        mla_rotation_deg=0.15,
        mla_offset_px=(1.3, -0.7),
        psf_sigma_px=0.4,
    )
    return Preset(
        "paper",
        "the seed paper's Zemax camera, focus at u = 300 mm (rail 50 mm)",
        cam,
        SweepPlan(zero_object_distance_mm=250.0, direction=1),
    )


def _rotated() -> Preset:
    cam = SimCamera(
        optics=optics_focused_at(432.37, F=50.0, f=2.0, D=0.2, b=2.45),
        sensor=SensorModel(
            width=5120,
            height=5120,
            principal_point_px=(2596.8, 2537.9),
            white_level_e=6000.0,
            read_noise_e=5.0,
        ),
        mla_rotation_deg=0.45,
        mla_offset_px=(-2.4, 3.1),
        psf_sigma_px=0.45,
    )
    return Preset(
        "rotated",
        "80 px pitch, F=50, 0.45 deg MLA rotation, off-centre principal "
        "point, focus at u = 432.37 mm (rail 52.37 mm)",
        cam,
        SweepPlan(zero_object_distance_mm=380.0, direction=1, board_offset_mm=(0.03, -0.02)),
    )


def _noisy() -> Preset:
    cam = SimCamera(
        optics=optics_focused_at(347.6, F=40.0, f=3.0, D=0.3, b=3.6),
        sensor=SensorModel(
            width=5120,
            height=5120,
            principal_point_px=(2514.0, 2587.75),
            white_level_e=2500.0,
            read_noise_e=12.0,
            black_level_dn=20.0,
        ),
        mla_rotation_deg=-0.3,
        mla_offset_px=(3.6, 1.9),
        psf_sigma_px=0.5,
    )
    return Preset(
        "noisy",
        "120 px pitch, f=3, F=40, rail direction -1, low light and high read "
        "noise, focus at u = 347.6 mm (rail 49.55 mm)",
        cam,
        SweepPlan(zero_object_distance_mm=397.15, direction=-1),
    )


_PRESETS = {"paper": _paper, "rotated": _rotated, "noisy": _noisy}


def preset_names() -> list[str]:
    return sorted(_PRESETS)


def get_preset(name: str) -> Preset:
    """The named preset; ``ValueError`` naming the known presets otherwise."""
    try:
        return _PRESETS[name]()
    except KeyError:
        raise ValueError(
            f"unknown preset {name!r}: choose one of {', '.join(preset_names())}"
        ) from None


def with_sweep(preset: Preset, **changes: object) -> Preset:
    return replace(preset, sweep=replace(preset.sweep, **changes))  # type: ignore[arg-type]
