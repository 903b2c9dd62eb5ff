"""GenICam cameras through a GenTL producer (.cti) with harvesters, software-triggered.

The producer is given by path (``camera.cti`` in the station config).  The camera is
chosen from the producer's device list by serial number (``DeviceInfo.serial_number``)
or device id (``DeviceInfo.id_``); with neither, the producer must list exactly one
device.  Listing devices is the producer's own enumeration: for a GigE Vision producer
that is a discovery on the producer's interfaces, which is the producer's business (the
station only ever asks for its list once per open).

``harvesters`` and ``genicam`` are imported on first use.  A .cti that is missing, not a
shared library, or a library that is not a GenTL producer raises ``ProducerLoadError``
before harvesters is handed the file (loading a non-producer library crashes genicam).

``harvesters`` silently drops incomplete buffers; this driver watches its
``INCOMPLETE_BUFFER`` event so that a damaged frame raises ``IncompleteFrame`` instead of
looking like a timeout.
"""

from __future__ import annotations

import ctypes
import logging
import os
import threading
import time
import types
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np

from drivers.camera import (
    SOFTWARE_TRIGGER,
    CameraContext,
    CameraInfo,
    CameraSettings,
    Frame,
    TransportSettings,
    bit_depth,
    decode_mono,
)
from drivers.camera_errors import (
    BackendUnavailable,
    CameraBusy,
    CameraError,
    CameraLost,
    CameraNotFound,
    CameraTimeout,
    FeatureMissing,
    IncompleteFrame,
    InvalidSetting,
    ProducerLoadError,
)
from drivers.pixels import mono_format
from drivers.sfnc import SfncCamera

log = logging.getLogger(__name__)

#: Entry points every GenTL producer exports (GenTL standard, C interface).
GENTL_SYMBOLS = (
    "GCInitLib",
    "GCCloseLib",
    "TLOpen",
    "TLUpdateInterfaceList",
    "IFOpenDevice",
    "DevOpenDataStream",
    "DSQueueBuffer",
    "DSStartAcquisition",
)

_HV: types.SimpleNamespace | None = None

# A GenTL producer can be initialised once per process: a second Harvester on the same
# .cti lists no device, and its reset would close the producer under the first one.
_PRODUCERS_IN_USE: dict[Path, HarvestersCamera] = {}
_PRODUCERS_LOCK = threading.Lock()


def _harvesters() -> types.SimpleNamespace:
    """Import harvesters and genicam on first use."""
    global _HV
    if _HV is None:
        try:
            from genicam import genapi, gentl
            from harvesters.core import Callback, Harvester, ImageAcquirer
        except ImportError as exc:
            raise BackendUnavailable(f"harvesters/genicam cannot be imported: {exc}") from exc
        _HV = types.SimpleNamespace(
            genapi=genapi,
            gentl=gentl,
            Harvester=Harvester,
            ImageAcquirer=ImageAcquirer,
            Callback=Callback,
        )
    return _HV


def check_producer(cti: Path, *, device: str) -> None:
    """Raise ``ProducerLoadError`` unless ``cti`` is a loadable GenTL producer."""
    if not cti.exists():
        raise ProducerLoadError(f"GenTL producer file {cti} does not exist", device=device)
    if not cti.is_file():
        raise ProducerLoadError(f"GenTL producer path {cti} is not a file", device=device)
    try:
        lib = ctypes.CDLL(str(cti), mode=os.RTLD_LAZY | os.RTLD_LOCAL)
    except OSError as exc:
        raise ProducerLoadError(
            f"{cti} does not load as a shared library: {exc}", device=device
        ) from None
    missing = [name for name in GENTL_SYMBOLS if not hasattr(lib, name)]
    if missing:
        raise ProducerLoadError(
            f"{cti} is a shared library but not a GenTL producer (no {', '.join(missing)})",
            device=device,
        )


class _HarvestersNodes:
    """:class:`drivers.camera.NodeMap` on a genapi node map."""

    def __init__(self, owner: HarvestersCamera) -> None:
        self._owner = owner

    def _node(self, name: str) -> Any:
        hv = _harvesters()
        node_map = self._owner._node_map()
        try:
            return node_map.get_node(name)
        except hv.genapi.LogicalErrorException:
            return None

    def _require(self, name: str) -> Any:
        node = self._node(name)
        if node is None:
            raise FeatureMissing(
                f"the camera does not offer the GenICam feature {name!r}",
                feature=name,
                device=self._owner.label,
            )
        return node

    def is_available(self, name: str) -> bool:
        node = self._node(name)
        with self._owner._gerrors(name):
            return node is not None and bool(_harvesters().genapi.is_available(node))

    def is_writable(self, name: str) -> bool:
        node = self._require(name)
        with self._owner._gerrors(name):
            return bool(_harvesters().genapi.is_writable(node))

    def get(self, name: str) -> int | float | str | bool:
        node = self._require(name)
        with self._owner._gerrors(name):
            value = node.value
        return value if isinstance(value, int | float | str | bool) else str(value)

    def set(self, name: str, value: int | float | str | bool) -> None:
        node = self._require(name)
        with self._owner._gerrors(name):
            node.value = value

    def execute(self, name: str) -> None:
        node = self._require(name)
        with self._owner._gerrors(name):
            node.execute()

    def enum_entries(self, name: str) -> tuple[str, ...]:
        genapi = _harvesters().genapi
        node = self._require(name)
        with self._owner._gerrors(name):
            return tuple(str(e.symbolic) for e in node.entries if genapi.is_available(e))

    def bounds(self, name: str) -> tuple[float, float]:
        node = self._require(name)
        with self._owner._gerrors(name):
            return float(node.min), float(node.max)

    def increment(self, name: str) -> float | None:
        genapi = _harvesters().genapi
        node = self._require(name)
        with self._owner._gerrors(name):
            if isinstance(node, genapi.IInteger):
                return float(node.inc)
            if isinstance(node, genapi.IFloat) and node.has_inc():
                return float(node.inc)
        return None


class HarvestersCamera(CameraContext):
    """A GenICam camera through a GenTL producer with harvesters, software-triggered.

    Args:
        cti: path of the GenTL producer file (.cti).
        serial: serial number of the camera in the producer's device list.
        device_id: device id in the producer's list (used when no serial is given).
        n_buffers: buffers announced to the producer (default: ``transport.buffer_count``).
        transport: streaming parameters: buffer count, and the GenICam transport features
            the camera offers (``GevSCPSPacketSize``, ``DeviceLinkThroughputLimit``); the
            socket buffer and packet timing belong to the producer's own configuration.

    Implements :class:`drivers.camera.Camera`.
    """

    backend = "harvesters"

    def __init__(
        self,
        cti: str | os.PathLike[str],
        *,
        serial: str | None = None,
        device_id: str | None = None,
        n_buffers: int | None = None,
        transport: TransportSettings | None = None,
    ) -> None:
        self.transport = transport or TransportSettings()
        n_buffers = self.transport.buffer_count if n_buffers is None else n_buffers
        if n_buffers < 1:
            raise ValueError("n_buffers >= 1")
        self.cti = Path(cti)
        self.serial = serial
        self.device_id = device_id
        self.n_buffers = n_buffers
        #: Start-up notes on transport settings the camera does not offer.
        self.warnings: list[str] = []
        which = serial or device_id
        self.label = f"gentl://{self.cti}" + (f"#{which}" if which else "")
        self._lock = threading.RLock()
        self._harvester: Any = None
        self._ia: Any = None
        self._sfnc: SfncCamera | None = None
        self._info: CameraInfo | None = None
        self._applied: CameraSettings | None = None
        self._requested: CameraSettings | None = None
        self._incomplete = 0
        self._lost = False

    # ------------------------------------------------------------------ lifecycle

    @property
    def is_open(self) -> bool:
        """True between ``open()`` and ``close()`` (also while the camera is lost)."""
        return self._sfnc is not None or self._lost

    def open(self) -> None:
        """Load the producer, open the device, set up the software trigger."""
        with self._lock:
            if self.is_open:
                return
            self._open_session()

    def close(self) -> None:
        """Stop acquisition, release the device and unload the producer."""
        with self._lock:
            self._release()
            self._lost = False

    def temperature_c(self) -> float | None:
        """``DeviceTemperature`` (°C) now; None without one (or when closed)."""
        sfnc = self._sfnc
        return None if sfnc is None else sfnc.temperature_c()

    def info(self) -> CameraInfo:
        """Identity and capabilities, read at open."""
        with self._lock:
            self._require_open()
            assert self._info is not None
            return self._info

    def exposure_limits_us(self) -> tuple[float, float]:
        """(min, max) ``ExposureTime`` in µs; ``FeatureMissing`` if the camera has none."""
        with self._lock:
            return self._session().exposure_limits_us()

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Stop acquisition, apply ``settings``, return the values read back."""
        with self._lock:
            bit_depth(settings.pixel_format)
            sfnc = self._session()
            self._stop()
            try:
                self._applied = sfnc.apply(settings)
            except (FeatureMissing, InvalidSetting):
                self._applied = sfnc.read_settings()
                raise
            self._requested = settings
            return self._applied

    def read_feature(self, name: str) -> int | float | str | bool:
        """Current value of any GenICam feature (diagnostics); ``FeatureMissing`` if absent."""
        with self._lock:
            sfnc = self._session()
            sfnc.require(name)
            return sfnc.nodes.get(name)

    def settings(self) -> CameraSettings:
        """The settings in force (as read back after the last configure/open)."""
        with self._lock:
            self._require_open()
            assert self._applied is not None
            return self._applied

    def grab(self, timeout_s: float = 5.0) -> Frame:
        """Return the next frame within ``timeout_s`` s: fire one software trigger first,
        or (hardware trigger) wait for the frame the trigger line starts.

        Raises ``CameraTimeout``, ``IncompleteFrame`` or ``CameraLost`` (the next grab
        then reopens the camera once).
        """
        if timeout_s <= 0:
            raise InvalidSetting(f"timeout_s must be > 0, not {timeout_s}", device=self.label)
        with self._lock:
            sfnc = self._session()
            self._start()
            self._drain_stale()
            incomplete_before = self._incomplete
            trigger = self._applied.trigger if self._applied else SOFTWARE_TRIGGER
            if trigger == SOFTWARE_TRIGGER:
                sfnc.nodes.execute("TriggerSoftware")
            deadline = time.monotonic() + timeout_s
            buffer = None
            while buffer is None and self._incomplete == incomplete_before:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                with self._gerrors("fetch"):
                    buffer = self._ia.try_fetch(timeout=remaining)
            if buffer is None:
                if self._incomplete != incomplete_before:
                    raise IncompleteFrame(
                        "the producer delivered an incomplete buffer",
                        status="incomplete",
                        device=self.label,
                    )
                raise CameraTimeout(
                    f"no frame within {timeout_s:g} s after the software trigger"
                    if trigger == SOFTWARE_TRIGGER
                    else f"no frame within {timeout_s:g} s: no pulse on trigger line {trigger}?",
                    device=self.label,
                )
            try:
                return self._to_frame(buffer)
            finally:
                buffer.queue()

    def reconnect(self, timeout_s: float = 10.0) -> None:
        """Reopen the camera (retrying until ``timeout_s``) and re-apply the settings."""
        deadline = time.monotonic() + timeout_s
        with self._lock:
            self._mark_lost()
            while True:
                try:
                    self._reopen_once()
                    return
                except CameraLost:
                    if time.monotonic() >= deadline:
                        raise
                threading.Event().wait(min(0.2, max(0.0, deadline - time.monotonic())))

    # ------------------------------------------------------------------ internals

    def _require_open(self) -> None:
        if not self.is_open:
            raise CameraError("the camera is not open; call open() first", device=self.label)

    def _session(self) -> SfncCamera:
        self._require_open()
        if self._lost:
            self._reopen_once()
        assert self._sfnc is not None
        return self._sfnc

    def _node_map(self) -> Any:
        if self._ia is None:
            raise CameraLost("the camera connection is closed", device=self.label)
        return self._ia.remote_device.node_map

    @contextmanager
    def _gerrors(self, what: str) -> Iterator[None]:
        """Translate genicam/GenTL exceptions into typed camera errors."""
        hv = _harvesters()
        try:
            yield
        except CameraError:
            raise
        except hv.genapi.OutOfRangeException as exc:
            raise InvalidSetting(f"{what}: {exc}", device=self.label) from None
        except hv.genapi.AccessException as exc:
            raise FeatureMissing(
                f"{what} is not accessible now ({exc})", feature=what, device=self.label
            ) from None
        except (hv.gentl.ResourceInUseException, hv.gentl.AccessDeniedException) as exc:
            raise CameraBusy(f"{what}: {exc}", device=self.label) from None
        except (
            hv.gentl.IoException,
            hv.gentl.InvalidHandleException,
            hv.gentl.NotInitializedException,
            hv.gentl.ClosedException,
            hv.genapi.TimeoutException,
        ) as exc:
            self._mark_lost()
            raise CameraLost(
                f"the camera stopped answering ({what}: {exc})", device=self.label
            ) from None
        except (hv.gentl.GenericException, hv.genapi.GenericException) as exc:
            raise CameraError(f"{what}: {exc}", device=self.label) from None

    def _claim_producer(self) -> None:
        key = self.cti.resolve()
        with _PRODUCERS_LOCK:
            holder = _PRODUCERS_IN_USE.get(key)
            if holder is not None and holder is not self:
                raise CameraBusy(
                    f"the GenTL producer {self.cti} is already in use by {holder.label} "
                    "in this process",
                    device=self.label,
                    hint="close the other camera first; one producer serves one camera object",
                )
            _PRODUCERS_IN_USE[key] = self

    def _unclaim_producer(self) -> None:
        with _PRODUCERS_LOCK:
            if _PRODUCERS_IN_USE.get(self.cti.resolve()) is self:
                del _PRODUCERS_IN_USE[self.cti.resolve()]

    def _open_session(self) -> None:
        hv = _harvesters()
        check_producer(self.cti, device=self.label)
        self._claim_producer()
        try:
            self._open_device(hv)
        except BaseException:
            self._unclaim_producer()
            raise

    def _open_device(self, hv: types.SimpleNamespace) -> None:
        harvester = hv.Harvester()
        try:
            harvester.add_file(str(self.cti))
            harvester.update()
            infos = list(harvester.device_info_list)
            chosen = self._choose(infos)
            try:
                ia = harvester.create(chosen)
            except hv.gentl.GenericException as exc:
                if isinstance(
                    exc, hv.gentl.ResourceInUseException | hv.gentl.AccessDeniedException
                ):
                    raise CameraBusy(
                        f"the device is already open elsewhere ({exc})", device=self.label
                    ) from None
                raise CameraNotFound(
                    f"the device cannot be opened: {exc}", device=self.label
                ) from None
        except BaseException:
            harvester.reset()
            raise
        self._harvester, self._ia = harvester, ia
        try:
            ia.num_buffers = max(self.n_buffers, int(ia.min_num_buffers))
            owner = self

            class _Incomplete(hv.Callback):  # type: ignore[name-defined]
                def emit(self, context: object = None) -> None:
                    owner._incomplete += 1

            ia.add_callback(hv.ImageAcquirer.Events.INCOMPLETE_BUFFER, _Incomplete())
            self._sfnc = SfncCamera(
                _HarvestersNodes(self), self.label, feature_hint="the camera's GenICam features"
            )
            self.warnings = self._sfnc.apply_transport(self.transport)
            self._sfnc.setup_software_trigger()
            self._info = self._sfnc.read_info(backend=self.backend)
            if self._requested is not None:
                self._applied = self._sfnc.apply(self._requested)
            else:
                self._applied = self._sfnc.read_settings()
        except BaseException:
            self._release()
            raise
        self._lost = False

    def _choose(self, infos: list[Any]) -> Any:
        listed = ", ".join(f"{i.id_} (serial {i.serial_number})" for i in infos) or "none"
        if not infos:
            raise CameraNotFound(
                "the GenTL producer lists no device",
                device=self.label,
                hint="that the camera is connected and powered, and that the producer is the "
                "one for this camera's interface",
            )
        if self.serial is not None:
            found = [i for i in infos if i.serial_number == self.serial]
            key = f"serial {self.serial!r}"
        elif self.device_id is not None:
            found = [i for i in infos if i.id_ == self.device_id]
            key = f"id {self.device_id!r}"
        else:
            found, key = infos, "any device"
        if len(found) != 1:
            raise CameraNotFound(
                f"{len(found)} devices match {key}; the producer lists: {listed}",
                device=self.label,
                hint="camera.serial (or the device id) in the station config",
            )
        return found[0]

    def _release(self) -> None:
        ia, harvester = self._ia, self._harvester
        self._ia = self._harvester = None
        self._sfnc = None
        for action in (
            (lambda: ia.destroy()) if ia is not None else None,
            (lambda: harvester.reset()) if harvester is not None else None,
        ):
            if action is None:
                continue
            try:
                action()
            except Exception as exc:  # the device may be gone; release what we can
                log.warning("%s: release failed: %s", self.label, exc)
        self._unclaim_producer()

    def _mark_lost(self) -> None:
        self._lost = True
        self._release()

    def _reopen_once(self) -> None:
        try:
            self._open_session()
        except (CameraNotFound, CameraLost, CameraBusy) as exc:
            self._lost = True
            raise CameraLost(
                f"the camera is still not available ({exc.message})", device=self.label
            ) from None
        log.info("%s: reconnected", self.label)

    def _start(self) -> None:
        if not self._ia.is_acquiring():
            with self._gerrors("AcquisitionStart"):
                self._ia.start()

    def _stop(self) -> None:
        if self._ia is not None and self._ia.is_acquiring():
            with self._gerrors("AcquisitionStop"):
                self._ia.stop()

    def _drain_stale(self) -> None:
        """Requeue frames of earlier triggers so the next fetch is this trigger's frame."""
        while True:
            with self._gerrors("fetch"):
                old = self._ia.try_fetch(timeout=1e-3)
            if old is None:
                return
            old.queue()

    def _to_frame(self, buffer: Any) -> Frame:
        module = buffer.module
        frame_id = int(module.frame_id)
        with self._gerrors("buffer"):
            complete = bool(module.is_complete())
            component = buffer.payload.components[0] if buffer.payload.components else None
        if not complete or component is None:
            raise IncompleteFrame(
                f"frame {frame_id} is incomplete or holds no image",
                status="incomplete",
                frame_id=frame_id,
                device=self.label,
            )
        pixel_format = str(component.data_format)
        try:
            depth = bit_depth(pixel_format)
        except InvalidSetting:
            raise CameraError(
                f"frame {frame_id} is {pixel_format}, which the drivers do not decode",
                device=self.label,
                hint="configure a Mono8/10/12/14/16 or Mono10p/12p/12Packed pixel format",
            ) from None
        width, height = int(component.width), int(component.height)
        applied = self._applied
        if applied is not None and applied.pixel_format != pixel_format:
            log.warning(
                "%s: configured %s but the producer delivers %s",
                self.label,
                applied.pixel_format,
                pixel_format,
            )
        if mono_format(pixel_format).packed:
            # our own unpacking of the bytes on the wire (harvesters' expansion of the same
            # buffer is the reference it is tested against)
            with self._gerrors("buffer"):
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
            device=self.label,
            frame_id=frame_id,
        )
        return Frame(
            pixels=pixels,
            frame_id=frame_id,
            timestamp_ns=int(buffer.timestamp_ns),
            host_timestamp_ns=time.time_ns(),
            exposure_us=applied.exposure_us if applied else None,
            gain=applied.gain if applied else None,
            pixel_format=pixel_format,
            width=width,
            height=height,
            offset_x=int(component.x_offset),
            offset_y=int(component.y_offset),
            bit_depth=depth,
            device=self.label,
            gain_feature=self._info.gain_feature if self._info else None,
            black_level=applied.black_level if applied else None,
            temperature_c=self._sfnc.temperature_c() if self._sfnc else None,
            trigger=applied.trigger if applied else SOFTWARE_TRIGGER,
            flat_field=applied.flat_field if applied else None,
        )


__all__ = ["GENTL_SYMBOLS", "HarvestersCamera", "check_producer"]
