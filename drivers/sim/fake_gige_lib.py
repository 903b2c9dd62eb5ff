"""The libaravis fake camera as C sees it: register map, pixel format codes, ctypes binding.

:mod:`drivers.sim.fake_gige` drives Aravis's GigE Vision simulator (``ArvGvFakeCamera``)
through these few C entry points.  The binding uses ctypes rather than PyGObject because
the PyGObject binding of ``arv_fake_camera_set_fill_pattern`` crashes with Aravis 0.8.26.
The libraries are loaded on first use (:func:`aravis_lib`), not at import.
"""

from __future__ import annotations

import ctypes
import ctypes.util
from typing import Any

#: PFNC codes (bits 16..23 hold the bits per pixel in the buffer).
PIXEL_FORMATS: dict[int, str] = {
    0x01080001: "Mono8",
    0x01100005: "Mono12",
    0x01100007: "Mono16",
}
MONO12 = 0x01100005

# Registers of ArvFakeCamera (arvfakecamera.h) and of the GigE Vision bootstrap.
REG_WIDTH = 0x100
REG_HEIGHT = 0x104
REG_SENSOR_HEIGHT = 0x118
REG_SENSOR_WIDTH = 0x11C
REG_EXPOSURE_US = 0x120
REG_X_OFFSET = 0x130
REG_Y_OFFSET = 0x134
GVBS_MANUFACTURER_NAME = 0x48
GVBS_MODEL_NAME = 0x68
#: Device-specific area of the 64 KiB fake register space, unused by Aravis: the Gain value.
REG_GAIN_DB = 0xB000
#: ... and the DeviceTemperature value (IEEE double, °C), set by the test.
REG_TEMPERATURE_C = 0xB008

#: UDP port of the GigE Vision control channel (GVCP), fixed by the protocol.
GVCP_PORT = 3956

#: C type of the fill-pattern callback: ``(ArvBuffer *, user data, exposure (µs), gain,
#: PFNC pixel format) -> None``.
FillPatternCallback = ctypes.CFUNCTYPE(
    None, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32, ctypes.c_uint32, ctypes.c_uint32
)


class AravisLib:
    """The few libaravis / libgobject entry points used, with their C signatures."""

    def __init__(self) -> None:
        name = ctypes.util.find_library("aravis-0.8") or "libaravis-0.8.so.0"
        try:
            arv = ctypes.CDLL(name)
            gobject = ctypes.CDLL(ctypes.util.find_library("gobject-2.0") or "libgobject-2.0.so.0")
        except OSError as exc:  # pragma: no cover - depends on the machine
            raise RuntimeError(
                f"Aravis library not found ({exc}); apt-get install gir1.2-aravis-0.8"
            ) from exc
        vp, u32, cp = ctypes.c_void_p, ctypes.c_uint32, ctypes.c_char_p
        sig: dict[str, tuple[object, list[object]]] = {
            "arv_fake_camera_new": (vp, [cp]),
            "arv_fake_camera_get_genicam_xml": (vp, [vp, ctypes.POINTER(ctypes.c_size_t)]),
            "arv_gv_fake_camera_new_full": (vp, [cp, cp, cp]),
            "arv_gv_fake_camera_is_running": (ctypes.c_int, [vp]),
            "arv_gv_fake_camera_get_fake_camera": (vp, [vp]),
            "arv_fake_camera_write_register": (ctypes.c_int, [vp, u32, u32]),
            "arv_fake_camera_read_register": (ctypes.c_int, [vp, u32, ctypes.POINTER(u32)]),
            "arv_fake_camera_write_memory": (ctypes.c_int, [vp, u32, u32, vp]),
            "arv_fake_camera_set_trigger_frequency": (None, [vp, ctypes.c_double]),
            "arv_fake_camera_set_fill_pattern": (None, [vp, FillPatternCallback, vp]),
            "arv_buffer_get_image_width": (ctypes.c_int, [vp]),
            "arv_buffer_get_image_height": (ctypes.c_int, [vp]),
            "arv_buffer_get_image_x": (ctypes.c_int, [vp]),
            "arv_buffer_get_image_y": (ctypes.c_int, [vp]),
            "arv_buffer_get_frame_id": (ctypes.c_uint64, [vp]),
            "arv_buffer_get_data": (vp, [vp, ctypes.POINTER(ctypes.c_size_t)]),
        }
        for fname, (restype, argtypes) in sig.items():
            fn = getattr(arv, fname)
            fn.restype = restype
            fn.argtypes = argtypes
            setattr(self, fname, fn)
        self.g_object_unref = gobject.g_object_unref
        self.g_object_unref.argtypes = [vp]
        self.g_object_unref.restype = None
        # g_object_set is variadic: only the fixed argument types are declared.
        self.g_object_set = gobject.g_object_set
        self.g_object_set.restype = None

    def __getattr__(self, name: str) -> Any:  # for type checkers only
        raise AttributeError(name)


_LIB: AravisLib | None = None


def aravis_lib() -> AravisLib:
    """The process-wide binding, loading libaravis and libgobject on the first call."""
    global _LIB
    if _LIB is None:
        _LIB = AravisLib()
    return _LIB
