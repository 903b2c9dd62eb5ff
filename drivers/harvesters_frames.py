"""Frames out of harvesters buffers: the buffer's checks, the pixels, :class:`Frame`.

Used by :class:`drivers.harvesters_camera.HarvestersCamera`; imports no camera library
itself.  Packed formats (Mono10p, Mono12p, Mono12Packed ...) are unpacked from the bytes
on the wire by :func:`drivers.camera.decode_mono` (harvesters' own expansion of the same
buffer is the reference it is tested against); the others are taken as harvesters
delivers them.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.camera import CameraInfo, CameraSettings, Frame, decode_mono
from drivers.camera_errors import IncompleteFrame
from drivers.genicam_camera import GErrors
from drivers.genicam_frames import delivered_bit_depth, settings_frame
from drivers.pixels import mono_format

log = logging.getLogger(__name__)


def buffer_to_frame(
    buffer: Any,
    *,
    applied: CameraSettings | None,
    info: CameraInfo | None,
    temperature_c: Callable[[], float | None],
    label: str,
    gerrors: GErrors,
) -> Frame:
    """The :class:`Frame` a harvesters buffer holds, decoded to counts.

    Raises ``IncompleteFrame`` for an incomplete buffer or one without an image component,
    ``CameraError`` for a pixel format the drivers do not decode.  ``applied`` (the
    settings in force) and ``info`` fill the metadata; ``temperature_c`` (°C) is read last,
    after the host timestamp.
    """
    module = buffer.module
    frame_id = int(module.frame_id)
    with gerrors("buffer"):
        complete = bool(module.is_complete())
        component = buffer.payload.components[0] if buffer.payload.components else None
    if not complete or component is None:
        raise IncompleteFrame(
            f"frame {frame_id} is incomplete or holds no image",
            status="incomplete",
            frame_id=frame_id,
            device=label,
        )
    pixel_format = str(component.data_format)
    depth = delivered_bit_depth(pixel_format, frame_id=frame_id, label=label)
    width, height = int(component.width), int(component.height)
    if applied is not None and applied.pixel_format != pixel_format:
        log.warning(
            "%s: configured %s but the producer delivers %s",
            label,
            applied.pixel_format,
            pixel_format,
        )
    if mono_format(pixel_format).packed:
        # our own unpacking of the bytes on the wire (harvesters' expansion of the same
        # buffer is the reference it is tested against)
        with gerrors("buffer"):
            data = np.frombuffer(
                component._buffer.raw_buffer, dtype=np.uint8, offset=component.data_offset
            )
    else:
        data = np.asarray(component.data)
    pixels = decode_mono(
        data,
        width=width,
        height=height,
        pixel_format=pixel_format,
        device=label,
        frame_id=frame_id,
    )
    return settings_frame(
        pixels,
        frame_id=frame_id,
        timestamp_ns=int(buffer.timestamp_ns),
        host_timestamp_ns=time.time_ns(),
        pixel_format=pixel_format,
        width=width,
        height=height,
        offset_x=int(component.x_offset),
        offset_y=int(component.y_offset),
        depth=depth,
        applied=applied,
        info=info,
        temperature_c=temperature_c(),
        label=label,
    )


__all__ = ["buffer_to_frame"]
