"""Frames out of Aravis stream buffers: the image bytes, the buffer's checks, :class:`Frame`.

Used by :class:`drivers.aravis_camera.AravisCamera`; the Aravis namespace (``ar``: the
``Aravis``, ``Gio`` and ``GLib`` modules of PyGObject) is passed in, so this module
imports no camera library itself.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import time
import types
from typing import Any

import numpy as np

from drivers.camera import CameraInfo, CameraSettings, Frame, decode_mono, pixel_format_name
from drivers.camera_errors import IncompleteFrame
from drivers.genicam_camera import GErrors
from drivers.genicam_frames import delivered_bit_depth, settings_frame

log = logging.getLogger(__name__)


class _ImageCopier:
    """Copies an ArvBuffer's image into a numpy array with one memcpy.

    PyGObject's ``get_image_data()`` first copies the data into a ``bytes`` object, an
    extra 26 MB copy per 5120 x 5120 frame; the C function is called directly instead on
    the buffer's GObject pointer (``__gpointer__``).  Falls back to the PyGObject call.
    """

    def __init__(self) -> None:
        lib = ctypes.CDLL(ctypes.util.find_library("aravis-0.8") or "libaravis-0.8.so.0")
        self._image_data = lib.arv_buffer_get_image_data
        self._image_data.restype = ctypes.c_void_p
        self._image_data.argtypes = [ctypes.c_void_p, ctypes.POINTER(ctypes.c_size_t)]
        self._pointer = ctypes.PYFUNCTYPE(ctypes.c_void_p, ctypes.py_object, ctypes.c_char_p)(
            ("PyCapsule_GetPointer", ctypes.pythonapi)
        )

    def copy(self, buffer: Any) -> np.ndarray:
        size = ctypes.c_size_t()
        data = self._image_data(self._pointer(buffer.__gpointer__, None), ctypes.byref(size))
        out = np.empty(size.value, dtype=np.uint8)
        if data and size.value:
            ctypes.memmove(out.ctypes.data, data, size.value)
        return out


_COPIER: _ImageCopier | None = None


def image_array(buffer: Any) -> np.ndarray | bytes:
    """The image bytes of an ArvBuffer, as a private uint8 array when possible."""
    global _COPIER
    try:
        if _COPIER is None:
            _COPIER = _ImageCopier()
        return _COPIER.copy(buffer)
    except (AttributeError, OSError, TypeError, ValueError):
        return bytes(buffer.get_image_data())


def pop_frame_buffer(
    ar: types.SimpleNamespace, stream: Any, deadline: float, gerrors: GErrors, label: str
) -> Any:
    """The next buffer of ``stream`` that holds a frame, or None at ``deadline``
    (``time.monotonic()`` seconds).

    Aravis hands back an untouched buffer (status ``CLEARED``) when a datagram that is
    not a frame start reaches the stream port (e.g. a stray late packet on a reused
    port); such a buffer carries no frame and is requeued.
    """
    cleared = ar.Aravis.BufferStatus.CLEARED
    while (remaining := deadline - time.monotonic()) > 0:
        with gerrors("stream"):
            buffer = stream.timeout_pop_buffer(max(1, int(remaining * 1e6)))
        if buffer is None or buffer.get_status() != cleared:
            return buffer
        log.debug("%s: ignoring a buffer that holds no frame", label)
        stream.push_buffer(buffer)
    return None


def buffer_to_frame(
    ar: types.SimpleNamespace,
    buffer: Any,
    *,
    applied: CameraSettings | None,
    info: CameraInfo | None,
    temperature_c: float | None,
    label: str,
) -> Frame:
    """The :class:`Frame` an ArvBuffer holds, decoded to counts.

    Raises ``IncompleteFrame`` for a buffer whose status is not ``SUCCESS`` or that
    carries no image, ``CameraError`` for a pixel format the drivers do not decode.
    ``applied`` (the settings in force) and ``info`` fill the exposure, gain, black
    level, trigger and flat-field fields.
    """
    arv = ar.Aravis
    frame_id = int(buffer.get_frame_id())
    status = buffer.get_status()
    if status != arv.BufferStatus.SUCCESS:
        raise IncompleteFrame(
            f"frame {frame_id} arrived incomplete ({status.value_nick})",
            status=str(status.value_nick),
            frame_id=frame_id,
            device=label,
        )
    if buffer.get_payload_type() not in (
        arv.BufferPayloadType.IMAGE,
        arv.BufferPayloadType.EXTENDED_CHUNK_DATA,
    ):
        raise IncompleteFrame(
            f"frame {frame_id} carries no image ({buffer.get_payload_type().value_nick})",
            status="not-an-image",
            frame_id=frame_id,
            device=label,
        )
    pixel_format = pixel_format_name(int(buffer.get_image_pixel_format()))
    width, height = int(buffer.get_image_width()), int(buffer.get_image_height())
    depth = delivered_bit_depth(pixel_format, frame_id=frame_id, label=label)
    pixels = decode_mono(
        image_array(buffer),
        width=width,
        height=height,
        pixel_format=pixel_format,
        device=label,
        frame_id=frame_id,
        copy=False,
    )
    return settings_frame(
        pixels,
        frame_id=frame_id,
        timestamp_ns=int(buffer.get_timestamp()),
        host_timestamp_ns=int(buffer.get_system_timestamp()) or time.time_ns(),
        pixel_format=pixel_format,
        width=width,
        height=height,
        offset_x=int(buffer.get_image_x()),
        offset_y=int(buffer.get_image_y()),
        depth=depth,
        applied=applied,
        info=info,
        temperature_c=temperature_c,
        label=label,
    )
