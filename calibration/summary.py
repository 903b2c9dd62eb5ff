"""The types a calibration passes around: priors, options, per-frame summaries, errors.

:class:`SweepGeometry` holds the priors of a sweep (from its manifest or the
station configuration), :class:`FrameSummary` what one frame contributes,
:class:`CalibrationResult` the JSON-ready result; the errors carry the
command line's documented exit codes and, where there is one, the partial
result.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .archive import SweepManifest
from .board import Board
from .camera_model import Priors
from .corners import CornerOptions

DEFAULT_MAIN_FOCAL_TOLERANCE = 0.02
"""Default 1-sigma tolerance of the data-sheet main-lens focal length, relative."""

DEFAULT_MLA_FOCAL_TOLERANCE = 0.02
"""Default 1-sigma tolerance of the data-sheet microlens focal length, relative."""

DEFAULT_RAIL_ZERO_TOLERANCE_MM = 2.0
"""Default 1-sigma tolerance of the rail zero distance (mm): measured with a ruler."""


class CalibrationError(ValueError):
    """The sweep cannot be calibrated; ``exit_code`` is the CLI's documented code."""

    exit_code = 3

    def __init__(self, message: str, partial: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.partial = partial


class FocusAtEdgeError(CalibrationError):
    """The focus plane lies at the edge of the sweep (extend the rail range)."""

    exit_code = 4


class FocusNotDeterminedError(CalibrationError):
    """The blur does not change enough over the sweep to locate the focus plane."""

    exit_code = 4


class PriorError(CalibrationError):
    """The data-sheet values (priors) admit no thin-lens camera; the message names the prior."""

    exit_code = 2


@dataclass(frozen=True)
class SweepGeometry:
    """Priors from the manifest or station configuration (mm, px)."""

    width: int
    height: int
    pixel_pitch_mm: float
    principal_point_px: tuple[float, float]
    main_focal_mm: float
    mla_focal_mm: float
    mla_pitch_mm: float
    board: Board
    zero_object_distance_mm: float
    direction: int
    main_focal_tolerance_mm: float | None = None
    mla_focal_tolerance_mm: float | None = None
    zero_object_distance_tolerance_mm: float | None = None
    max_count: int | None = None
    """The sensor's full scale (counts, ``2**bit_depth − 1``): a pixel there is clipped."""

    @classmethod
    def from_manifest(cls, m: SweepManifest) -> SweepGeometry:
        return cls(
            main_focal_tolerance_mm=m.optics.main_focal_tolerance_mm,
            mla_focal_tolerance_mm=m.optics.mla_focal_tolerance_mm,
            zero_object_distance_tolerance_mm=m.rail.zero_object_distance_tolerance_mm,
            width=m.camera.width,
            height=m.camera.height,
            pixel_pitch_mm=m.camera.pixel_pitch_mm,
            principal_point_px=m.camera.pp,
            main_focal_mm=m.optics.main_focal_mm,
            mla_focal_mm=m.optics.mla_focal_mm,
            mla_pitch_mm=m.optics.mla_pitch_mm,
            board=Board(square_mm=m.board.square_mm, reference_gap_mm=m.board.reference_gap_mm),
            zero_object_distance_mm=m.rail.zero_object_distance_mm,
            direction=m.rail.direction,
            max_count=m.camera.max_count,
        )

    def tolerances(self) -> dict[str, float]:
        """1-sigma tolerances (mm) of the priors: the given ones, else the documented defaults."""
        return {
            "main_focal_mm": self.main_focal_tolerance_mm
            or DEFAULT_MAIN_FOCAL_TOLERANCE * self.main_focal_mm,
            "mla_focal_mm": self.mla_focal_tolerance_mm
            or DEFAULT_MLA_FOCAL_TOLERANCE * self.mla_focal_mm,
            "rail_zero_object_distance_mm": self.zero_object_distance_tolerance_mm
            or DEFAULT_RAIL_ZERO_TOLERANCE_MM,
        }

    def priors(self) -> Priors:
        """The data-sheet values with their tolerances, as the camera model takes them."""
        tol = self.tolerances()
        return Priors(
            main_focal_mm=self.main_focal_mm,
            main_focal_tolerance_mm=tol["main_focal_mm"],
            mla_focal_mm=self.mla_focal_mm,
            mla_focal_tolerance_mm=tol["mla_focal_mm"],
            rail_zero_object_distance_mm=self.zero_object_distance_mm,
            rail_zero_tolerance_mm=tol["rail_zero_object_distance_mm"],
            direction=self.direction,
        )

    @property
    def lens_pitch_px(self) -> float:
        """``D/δ``: lens-centre pitch on the sensor (px)."""
        return self.mla_pitch_mm / self.pixel_pitch_mm

    def to_dict(self) -> dict[str, Any]:
        """The priors a calibration used (JSON-ready): recorded with every result."""
        return {
            "camera": {
                "width": self.width,
                "height": self.height,
                "pixel_pitch_mm": self.pixel_pitch_mm,
                "principal_point_px": list(self.principal_point_px),
            },
            "optics": {
                "main_focal_mm": self.main_focal_mm,
                "mla_focal_mm": self.mla_focal_mm,
                "mla_pitch_mm": self.mla_pitch_mm,
                "lens_pitch_px": self.lens_pitch_px,
                "main_focal_tolerance_mm": self.tolerances()["main_focal_mm"],
                "mla_focal_tolerance_mm": self.tolerances()["mla_focal_mm"],
            },
            "board": {
                "square_mm": self.board.square_mm,
                "reference_gap_mm": self.board.reference_gap_mm,
            },
            "rail": {
                "zero_object_distance_mm": self.zero_object_distance_mm,
                "direction": self.direction,
                "zero_object_distance_tolerance_mm": self.tolerances()[
                    "rail_zero_object_distance_mm"
                ],
            },
        }

    def object_distance_mm(self, rail_mm: float) -> float:
        return self.zero_object_distance_mm + self.direction * rail_mm

    def rail_mm(self, object_distance_mm: float) -> float:
        return (object_distance_mm - self.zero_object_distance_mm) / self.direction


@dataclass(frozen=True)
class CalibrationOptions:
    """Options of the whole calibration (keyword-only tuning, sensible defaults)."""

    interior_fraction: float = 0.8
    corner: CornerOptions = field(default_factory=CornerOptions)
    min_frames: int = 5


@dataclass
class FrameSummary:
    """What one frame contributes (JSON-ready through :meth:`to_dict`)."""

    index: int
    rail_mm: float
    object_distance_mm: float
    Q: float = float("nan")
    Q_se: float = float("nan")
    Q_eq3: float = float("nan")
    Ls_px: float = float("nan")
    Lr_px: float = float("nan")
    edge_width_px: float = float("nan")
    edge_spread_px: float = float("nan")
    standard: dict[str, Any] | None = None
    reference: dict[str, Any] | None = None
    corners: dict[str, list[list[float]]] = field(default_factory=dict)
    esf: dict[str, dict[str, Any]] = field(default_factory=dict)
    rejected: dict[str, int] = field(default_factory=dict)
    error: str = ""

    def to_dict(self, *, with_corners: bool = True, with_esf: bool = True) -> dict[str, Any]:
        d = dict(self.__dict__)
        if not with_corners:
            d.pop("corners")
        if not with_esf:
            d.pop("esf")
        return _json_clean(d)


@dataclass
class CalibrationResult:
    """The calibration of one sweep (JSON-ready through :meth:`to_dict`)."""

    data: dict[str, Any]

    def to_dict(self) -> dict[str, Any]:
        return self.data


def _json_clean(obj: Any) -> Any:
    """Floats that are not finite become None (JSON has no NaN); numpy scalars become Python."""
    if isinstance(obj, dict):
        return {str(k): _json_clean(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_json_clean(v) for v in obj]
    if isinstance(obj, np.generic):
        obj = obj.item()
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return obj
