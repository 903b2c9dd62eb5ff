"""A :class:`Frame` out of a GenICam backend's delivered image, shared by the backends.

Used by :mod:`drivers.aravis_frames` and :mod:`drivers.harvesters_frames`: the check that
the delivered pixel format is one the drivers decode, and the frame's metadata from the
settings in force (exposure in µs, gain in the unit of ``info.gain_feature``, black level,
trigger, flat-field state).  Timestamps are in ns, sizes and offsets in sensor pixels.
"""

from __future__ import annotations

import numpy as np

from drivers.camera import SOFTWARE_TRIGGER, CameraInfo, CameraSettings, Frame, bit_depth
from drivers.camera_errors import CameraError, InvalidSetting


def delivered_bit_depth(pixel_format: str, *, frame_id: int, label: str) -> int:
    """Significant bits of a delivered PFNC ``pixel_format``; ``CameraError`` (naming the
    frame) for a format the drivers do not decode."""
    try:
        return bit_depth(pixel_format)
    except InvalidSetting:
        raise CameraError(
            f"frame {frame_id} is {pixel_format}, which the drivers do not decode",
            device=label,
            hint="configure a Mono8/10/12/14/16 or Mono10p/12p/12Packed pixel format",
        ) from None


def settings_frame(
    pixels: np.ndarray,
    *,
    frame_id: int,
    timestamp_ns: int,
    host_timestamp_ns: int,
    pixel_format: str,
    width: int,
    height: int,
    offset_x: int,
    offset_y: int,
    depth: int,
    applied: CameraSettings | None,
    info: CameraInfo | None,
    temperature_c: float | None,
    label: str,
) -> Frame:
    """The :class:`Frame` of decoded ``pixels``, with the metadata of the settings in
    force (``applied``, None before the first read-back) and ``info.gain_feature``."""
    return Frame(
        pixels=pixels,
        frame_id=frame_id,
        timestamp_ns=timestamp_ns,
        host_timestamp_ns=host_timestamp_ns,
        exposure_us=applied.exposure_us if applied else None,
        gain=applied.gain if applied else None,
        pixel_format=pixel_format,
        width=width,
        height=height,
        offset_x=offset_x,
        offset_y=offset_y,
        bit_depth=depth,
        device=label,
        gain_feature=info.gain_feature if info else None,
        black_level=applied.black_level if applied else None,
        temperature_c=temperature_c,
        trigger=applied.trigger if applied else SOFTWARE_TRIGGER,
        flat_field=applied.flat_field if applied else None,
    )


__all__ = ["delivered_bit_depth", "settings_frame"]
