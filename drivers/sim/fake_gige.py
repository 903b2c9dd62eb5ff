"""A fake GigE Vision camera on the loopback interface, for tests, benchmarks and demos.

It is Aravis's own GigE Vision simulator (``ArvGvFakeCamera``, the class behind
``arv-fake-gv-camera-0.8``) running in this process: a real GVCP control channel on
``127.0.0.1:3956`` and a real GVSP stream, so a client goes through the whole Aravis
GigE Vision stack.  What this module adds:

* a GenICam XML generated at run time from the installed library's own fake-camera XML
  (``arv_fake_camera_get_genicam_xml``), patched with the SFNC features the station uses:
  ``ExposureTime`` (µs), ``Gain`` (dB, an IEEE double register), ``DeviceSerialNumber``,
  a ``Mono12`` ``PixelFormat`` entry (:mod:`drivers.sim.fake_gige_xml`), and the sensor
  size (5120 x 5120 by default, smaller for tests);
* frames supplied by the caller: a callable ``FrameRequest -> np.ndarray`` or a
  ``queue.Queue`` of arrays; the fill callback copies them byte for byte into the GVSP
  payload, so a test can check that the pixels received are exactly the pixels served;
* ``stop()`` / ``start()`` to simulate an unplugged / re-plugged camera.

The callback is installed with ctypes on the C object (the PyGObject binding of
``arv_fake_camera_set_fill_pattern`` crashes with Aravis 0.8.26), so this module uses
ctypes throughout (:mod:`drivers.sim.fake_gige_lib`) and does not need PyGObject at all.

Only one fake camera can listen on an address (the GVCP port 3956 is fixed by the
protocol), so a fake holds an inter-process file lock for its address from ``start()`` to
``close()``: fakes in parallel test workers (pytest-xdist) take turns instead of clashing.
It binds to 127.0.0.1 only and never sends discovery packets.  Only one client can control
it at a time (GigE Vision control channel privilege).

Production code must never import ``drivers.sim``.

Run it by hand (for ``arv-tool-0.8 -a 127.0.0.1`` or the station)::

    python -m drivers.sim.fake_gige --width 5120 --height 5120
"""

from __future__ import annotations

import argparse
import atexit
import ctypes
import fcntl
import os
import queue
import tempfile
import threading
import time
import weakref
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from drivers.sim.fake_gige_lib import (
    GVBS_MANUFACTURER_NAME,
    GVBS_MODEL_NAME,
    GVCP_PORT,
    PIXEL_FORMATS,
    REG_EXPOSURE_US,
    REG_GAIN_DB,
    REG_HEIGHT,
    REG_SENSOR_HEIGHT,
    REG_SENSOR_WIDTH,
    REG_TEMPERATURE_C,
    REG_WIDTH,
    FillPatternCallback,
    aravis_lib,
)
from drivers.sim.fake_gige_xml import library_genicam_xml, patch_genicam_xml

DEFAULT_ADDRESS = "127.0.0.1"


@dataclass(frozen=True)
class FrameRequest:
    """What the camera is about to send; a frame source returns the matching array.

    Attributes:
        frame_id: GigE Vision block id of the frame (16 bit, wraps, never 0).
        width, height, offset_x, offset_y: region in pixels.
        pixel_format: ``"Mono8"``, ``"Mono12"`` or ``"Mono16"``.
        exposure_us: ExposureTime register value, µs.
    """

    frame_id: int
    width: int
    height: int
    offset_x: int
    offset_y: int
    pixel_format: str
    exposure_us: int

    @property
    def dtype(self) -> type[np.unsignedinteger]:
        """numpy dtype a source must return: uint8 for Mono8, uint16 otherwise."""
        return np.uint8 if self.pixel_format == "Mono8" else np.uint16

    @property
    def max_count(self) -> int:
        """Largest legal count for the format (4095 for Mono12)."""
        return {"Mono8": 255, "Mono12": 4095}.get(self.pixel_format, 65535)


FrameSource = Callable[[FrameRequest], np.ndarray] | queue.Queue


def ramp_frame(request: FrameRequest) -> np.ndarray:
    """Default source: a diagonal ramp ``(x + y + frame_id) mod (max + 1)``."""
    y, x = np.ogrid[: request.height, : request.width]
    values = (x + request.offset_x + y + request.offset_y + request.frame_id) % (
        request.max_count + 1
    )
    return values.astype(request.dtype)


_RUNNING: weakref.WeakSet[FakeGigECamera] = weakref.WeakSet()


@atexit.register
def _stop_all() -> None:
    """Stop simulators left running, before the interpreter they call back into is gone."""
    for cam in list(_RUNNING):
        cam.stop()


# --------------------------------------------------------------------------- the camera


@dataclass(frozen=True)
class ServedFrame:
    """A frame the fake sent: its GigE Vision block id and the exact array served."""

    frame_id: int
    pixels: np.ndarray


class _AddressLock:
    """Inter-process lock on the fake camera's address (the GVCP port is fixed)."""

    def __init__(self, address: str) -> None:
        self.path = Path(tempfile.gettempdir()) / f"lfcal-fake-gige-{address}-{GVCP_PORT}.lock"
        self._fd: int | None = None

    def acquire(self, timeout_s: float) -> None:
        """Take the lock, waiting up to ``timeout_s`` seconds for the fake holding it."""
        if self._fd is not None:
            return
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o666)
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                self._fd = fd
                return
            except BlockingIOError:
                if time.monotonic() > deadline:
                    os.close(fd)
                    raise TimeoutError(
                        f"another fake GigE camera holds {self.path} for more than {timeout_s} s"
                    ) from None
                threading.Event().wait(0.05)

    def release(self) -> None:
        """Give the lock back (no-op when not held)."""
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None


class FakeGigECamera:
    """A GigE Vision camera served on ``address`` (127.0.0.1) by Aravis's GvFakeCamera.

    Args:
        frames: frame source: a callable ``FrameRequest -> ndarray`` or a ``queue.Queue``
            of arrays (taken one per frame; an empty queue is an error).  Default:
            :func:`ramp_frame`.  Arrays are ``(height, width)``, uint8 for Mono8, uint16
            for Mono12/Mono16; a wrong shape or dtype is recorded in :attr:`errors` and a
            black frame is sent.
        sensor_width, sensor_height: sensor size in pixels (the GMAX0505 is 5120 x 5120).
        serial: ``DeviceSerialNumber`` (at most 15 characters).
        model, vendor: ``DeviceModelName`` and ``DeviceVendorName``.
        exposure_limits_us: (min, max) of ``ExposureTime``.
        gain_limits_db: (min, max) of ``Gain``.
        address: IPv4 address to listen on; must be a local loopback address.
        trigger_poll_hz: how often the simulator checks for a software trigger.
        keep_served: how many served frames :attr:`served` keeps.
        lock_timeout_s: how long ``start`` waits for another fake on the same address.

    Use as a context manager; ``stop()``/``start()`` simulate unplugging the camera while
    keeping the address reserved.
    """

    def __init__(
        self,
        frames: FrameSource | None = None,
        *,
        sensor_width: int = 5120,
        sensor_height: int = 5120,
        serial: str = "SIM0505",
        model: str = "GMAX0505 (simulated)",
        vendor: str = "lfcal",
        exposure_limits_us: tuple[float, float] = (10.0, 1_000_000.0),
        gain_limits_db: tuple[float, float] = (0.0, 24.0),
        address: str = DEFAULT_ADDRESS,
        trigger_poll_hz: float = 1000.0,
        keep_served: int = 4,
        lock_timeout_s: float = 120.0,
    ) -> None:
        if not address.startswith("127."):
            raise ValueError("the fake GigE camera only listens on a loopback address")
        if len(serial) >= 16 or len(model) >= 32 or len(vendor) >= 32:
            raise ValueError("serial < 16, model and vendor < 32 characters")
        self.frames: FrameSource = frames if frames is not None else ramp_frame
        self.sensor_width = sensor_width
        self.sensor_height = sensor_height
        self.serial = serial
        self.model = model
        self.vendor = vendor
        self.address = address
        self.trigger_poll_hz = trigger_poll_hz
        self.lock_timeout_s = lock_timeout_s
        self.exposure_limits_us = exposure_limits_us
        self.gain_limits_db = gain_limits_db
        self.genicam_xml = patch_genicam_xml(
            library_genicam_xml(),
            exposure_limits_us=exposure_limits_us,
            gain_limits_db=gain_limits_db,
        )
        self.served: deque[ServedFrame] = deque(maxlen=keep_served)
        self.errors: list[str] = []
        self._served_count = 0
        self._served_cond = threading.Condition()
        self._lock = _AddressLock(address)
        self._xml_path: str | None = None
        self._gv: int | None = None
        self._fake: int | None = None
        self._callback = FillPatternCallback(self._fill)
        self._zero_cache: dict[int, np.ndarray] = {}

    # -- lifecycle ------------------------------------------------------------------------

    @property
    def running(self) -> bool:
        """True while the camera answers on its address."""
        return self._gv is not None

    @property
    def served_count(self) -> int:
        """Number of frames sent since construction."""
        return self._served_count

    def start(self) -> None:
        """Reserve the address (waiting for other fakes) and start answering on it."""
        if self._gv is not None:
            return
        self._lock.acquire(self.lock_timeout_s)
        lib = aravis_lib()
        if self._xml_path is None:
            fd, self._xml_path = tempfile.mkstemp(prefix="lfcal-fake-gige-", suffix=".xml")
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                f.write(self.genicam_xml)
        gv = lib.arv_gv_fake_camera_new_full(
            self.address.encode(), self.serial.encode(), self._xml_path.encode()
        )
        if not gv or not lib.arv_gv_fake_camera_is_running(gv):
            if gv:
                lib.g_object_unref(gv)
            raise RuntimeError(
                f"the fake GigE camera cannot listen on {self.address}:{GVCP_PORT} "
                "(another GigE Vision simulator such as arv-fake-gv-camera-0.8 running?)"
            )
        fake = lib.arv_gv_fake_camera_get_fake_camera(gv)
        self._gv, self._fake = gv, fake
        for reg, value in (
            (REG_SENSOR_WIDTH, self.sensor_width),
            (REG_SENSOR_HEIGHT, self.sensor_height),
            (REG_WIDTH, self.sensor_width),
            (REG_HEIGHT, self.sensor_height),
            (REG_EXPOSURE_US, int(max(self.exposure_limits_us[0], 10_000))),
        ):
            lib.arv_fake_camera_write_register(fake, reg, value)
        self._write_string(GVBS_MANUFACTURER_NAME, self.vendor, 32)
        self._write_string(GVBS_MODEL_NAME, self.model, 32)
        gain = np.array([self.gain_limits_db[0]], dtype=">f8").tobytes()
        lib.arv_fake_camera_write_memory(fake, REG_GAIN_DB, len(gain), gain)
        lib.arv_fake_camera_set_trigger_frequency(fake, float(self.trigger_poll_hz))
        lib.arv_fake_camera_set_fill_pattern(fake, self._callback, None)
        _RUNNING.add(self)

    def stop(self) -> None:
        """Stop answering (like an unplugged camera); the address stays reserved."""
        gv, self._gv, self._fake = self._gv, None, None
        _RUNNING.discard(self)
        if gv is not None:
            aravis_lib().g_object_unref(gv)  # joins the simulator thread; ctypes releases the GIL

    def close(self) -> None:
        """Stop, release the address and remove the temporary XML file."""
        self.stop()
        self._lock.release()
        if self._xml_path is not None:
            Path(self._xml_path).unlink(missing_ok=True)
            self._xml_path = None

    def __enter__(self) -> FakeGigECamera:
        self.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    # -- fault injection / inspection ------------------------------------------------------

    def set_packet_loss(self, ratio: float) -> None:
        """Drop this fraction of GVSP packets (0..1) from now on (no resend support)."""
        if self._gv is None:
            raise RuntimeError("the fake camera is stopped")
        aravis_lib().g_object_set(
            ctypes.c_void_p(self._gv), b"gvsp-lost-ratio", ctypes.c_double(ratio), None
        )

    def read_register(self, address: int) -> int:
        """A 32-bit register of the simulated device (for tests)."""
        if self._fake is None:
            raise RuntimeError("the fake camera is stopped")
        value = ctypes.c_uint32()
        aravis_lib().arv_fake_camera_read_register(self._fake, address, ctypes.byref(value))
        return value.value

    def read_gain_db(self) -> float:
        """The ``Gain`` value the client wrote, dB."""
        if self._fake is None:
            raise RuntimeError("the fake camera is stopped")
        hi, lo = self.read_register(REG_GAIN_DB), self.read_register(REG_GAIN_DB + 4)
        return float(np.frombuffer(((hi << 32) | lo).to_bytes(8, "big"), dtype=">f8")[0])

    def set_temperature_c(self, celsius: float) -> None:
        """Set what ``DeviceTemperature`` reads (°C)."""
        if self._fake is None:
            raise RuntimeError("the fake camera is stopped")
        word = int.from_bytes(np.array([celsius], dtype=">f8").tobytes(), "big")
        aravis_lib().arv_fake_camera_write_register(self._fake, REG_TEMPERATURE_C, word >> 32)
        aravis_lib().arv_fake_camera_write_register(
            self._fake, REG_TEMPERATURE_C + 4, word & 0xFFFFFFFF
        )

    def served_frame(self, frame_id: int) -> np.ndarray | None:
        """The array served with this block id, if still kept."""
        for served in reversed(self.served):
            if served.frame_id == frame_id:
                return served.pixels
        return None

    def wait_served(self, count: int, timeout_s: float) -> bool:
        """Wait until at least ``count`` frames were sent since construction."""
        with self._served_cond:
            return self._served_cond.wait_for(lambda: self._served_count >= count, timeout_s)

    # -- internals -------------------------------------------------------------------------

    def _write_string(self, address: int, text: str, size: int) -> None:
        raw = text.encode()[: size - 1].ljust(size, b"\0")
        aravis_lib().arv_fake_camera_write_memory(self._fake, address, size, raw)

    def _next_array(self, request: FrameRequest) -> np.ndarray:
        if isinstance(self.frames, queue.Queue):
            try:
                return np.asarray(self.frames.get_nowait())
            except queue.Empty:
                raise ValueError("the frame queue is empty") from None
        return np.asarray(self.frames(request))

    def _fill(
        self, buffer: int, _data: int, exposure_us: int, _gain: int, pixel_format: int
    ) -> None:
        """Fill callback, run on the simulator's thread for every frame it sends."""
        lib = aravis_lib()
        try:
            name = PIXEL_FORMATS.get(pixel_format)
            request = FrameRequest(
                frame_id=int(lib.arv_buffer_get_frame_id(buffer)),
                width=lib.arv_buffer_get_image_width(buffer),
                height=lib.arv_buffer_get_image_height(buffer),
                offset_x=lib.arv_buffer_get_image_x(buffer),
                offset_y=lib.arv_buffer_get_image_y(buffer),
                pixel_format=name or f"0x{pixel_format:08x}",
                exposure_us=int(exposure_us),
            )
            nbytes = request.width * request.height * ((pixel_format >> 16) & 0xFF) // 8
            dest = lib.arv_buffer_get_data(buffer, None)
            try:
                if name is None:
                    raise ValueError(f"the fake serves Mono8/12/16, not {request.pixel_format}")
                pixels = self._next_array(request)
                if pixels.shape != (request.height, request.width) or pixels.dtype != request.dtype:
                    raise ValueError(
                        f"frame {request.frame_id}: source gave {pixels.dtype}{pixels.shape}, "
                        f"expected {np.dtype(request.dtype)}({request.height}, {request.width})"
                    )
                wire = np.ascontiguousarray(pixels, dtype=pixels.dtype.newbyteorder("<"))
                ctypes.memmove(dest, wire.ctypes.data, nbytes)
            except Exception as exc:  # reported to the test, never into C
                self.errors.append(str(exc))
                ctypes.memset(dest, 0, nbytes)
                pixels = np.zeros((request.height, request.width), dtype=request.dtype)
            self.served.append(ServedFrame(request.frame_id, pixels))
        except Exception as exc:  # pragma: no cover - last resort inside a C callback
            self.errors.append(f"fill callback failed: {exc!r}")
        with self._served_cond:
            self._served_count += 1
            self._served_cond.notify_all()


def main(argv: list[str] | None = None) -> None:
    """Serve a fake camera until interrupted (ramp frames)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--width", type=int, default=5120, help="sensor width, px")
    parser.add_argument("--height", type=int, default=5120, help="sensor height, px")
    parser.add_argument("--serial", default="SIM0505")
    parser.add_argument("--address", default=DEFAULT_ADDRESS, help="loopback address")
    args = parser.parse_args(argv)
    with FakeGigECamera(
        sensor_width=args.width, sensor_height=args.height, serial=args.serial, address=args.address
    ) as cam:
        print(f"fake GigE camera {cam.serial} on {cam.address}:{GVCP_PORT}; Ctrl-C stops it")
        try:
            threading.Event().wait()
        except KeyboardInterrupt:
            pass


if __name__ == "__main__":
    main()
