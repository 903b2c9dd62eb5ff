"""GigE Vision cameras through Aravis 0.8 (PyGObject), software-triggered.

Opening never runs GigE Vision discovery (which broadcasts on every interface):

* ``AravisCamera(address="192.168.10.20")`` talks unicast to that address only: the
  ``ArvGvDevice`` is built directly from the camera address and the local interface
  address the kernel routes to it (found with a UDP ``connect``, which sends nothing).
* ``AravisCamera(address=..., serial="SN")`` does the same and then checks that the
  camera's ``DeviceSerialNumber`` is ``SN`` (a swapped camera gives ``CameraNotFound``).
* ``AravisCamera(serial="SN", interface="usb3")`` opens a USB3 Vision camera by serial
  (or Aravis device id): the GigE Vision interface is disabled first
  (``arv_disable_interface("GigEVision")``, ``arv_enable_interface("USB3Vision")``), so
  finding it enumerates the USB bus only and sends nothing on any network.
* ``AravisCamera(serial="SN", allow_discovery=True)`` (or an address that is an Aravis
  device name) goes through ``arv_camera_new`` with GigE Vision enabled, i.e. discovery:
  only for a dedicated camera network, never the default.

Transport (:class:`drivers.camera.TransportSettings`, ``[camera.transport]``): GVSP packet
size, inter-packet delay (``GevSCPD``), ``DeviceLinkThroughputLimit`` (USB3: the
bandwidth limit), buffer count, frame retention, packet resend and the receive socket
buffer.  The kernel caps a socket buffer at ``net.core.rmem_max``; when that is smaller
than the buffer asked for (by default two frames), a warning naming ``net.core.rmem_max``
is logged at open and kept in :attr:`AravisCamera.warnings` (``lfcal devices --check``
prints it): a 26 MB frame burst into a 208 KiB buffer loses packets.

``gi`` is imported on first use, so ``drivers`` imports without Aravis installed; a
missing library raises :class:`BackendUnavailable` at ``open()``.

Grabbing: ``grab`` stops nothing between frames; acquisition runs continuously with
``TriggerMode=On``/``TriggerSource=Software`` and each call drops any stale buffer, fires
``TriggerSoftware`` and waits for the frame.  A buffer whose status is not ``SUCCESS``
(missing packets, frame-retention timeout, size mismatch) raises ``IncompleteFrame``.
When the camera stops answering (or reboots and drops our control channel), ``grab``
raises ``CameraLost`` and the next ``grab`` makes one bounded reopen attempt (a camera
still absent costs a 0.6 s ping); ``reconnect`` retries until a deadline.  The last
settings are re-applied after a reopen.

Aravis 0.8 GVCP timing is fixed: a command to an absent camera fails after 5 tries of
500 ms (about 2.5 s), so detecting a lost camera during a grab takes that long.  Opening
and reopening first send one unicast GVCP read (:func:`gvcp_ping`), so an absent camera
is reported within about a second.

How a camera is opened (no discovery), its transport and its stream are set up is in
:mod:`drivers.aravis_connect`; how a stream buffer becomes a :class:`Frame`, in
:mod:`drivers.aravis_frames`.
"""

from __future__ import annotations

import logging
import threading
import time
import types
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from drivers.aravis_connect import (
    connect,
    drop_all,
    open_stream,
    setup_transport,
)
from drivers.aravis_frames import buffer_to_frame, pop_frame_buffer
from drivers.camera import (
    SOFTWARE_TRIGGER,
    CameraContext,
    CameraInfo,
    CameraSettings,
    Frame,
    TransportSettings,
    bit_depth,
)
from drivers.camera_errors import (
    BackendUnavailable,
    CameraBusy,
    CameraError,
    CameraLost,
    CameraNotFound,
    CameraTimeout,
    FeatureMissing,
    InvalidSetting,
)
from drivers.gige_host import (
    GVBS_CONTROL_CHANNEL_PRIVILEGE,
    gvcp_ping,
)
from drivers.sfnc import SfncCamera

log = logging.getLogger(__name__)

# GLib error codes (ArvDeviceError, ArvGcError in Aravis 0.8).
_DEVICE_NOT_CONNECTED, _DEVICE_TRANSFER, _DEVICE_TIMEOUT = 2, 4, 5
_DEVICE_FEATURE_NOT_FOUND, _DEVICE_NOT_CONTROLLER, _DEVICE_ACCESS_DENIED = 1, 10, 17
_GC_OUT_OF_RANGE, _GC_NODE_NOT_FOUND, _GC_ENTRY_NOT_FOUND, _GC_READ_ONLY = 4, 7, 8, 10

_GI: types.SimpleNamespace | None = None


def _aravis() -> types.SimpleNamespace:
    """Import Aravis 0.8 through PyGObject on first use (Aravis, Gio, GLib)."""
    global _GI
    if _GI is None:
        try:
            import gi

            gi.require_version("Aravis", "0.8")
            from gi.repository import Aravis, Gio, GLib
        except (ImportError, ValueError) as exc:
            raise BackendUnavailable(
                f"Aravis 0.8 cannot be imported through PyGObject: {exc}"
            ) from exc
        _GI = types.SimpleNamespace(Aravis=Aravis, Gio=Gio, GLib=GLib)
    return _GI


class _AravisNodes:
    """:class:`drivers.camera.NodeMap` on an ``ArvDevice``.

    It holds its owner, not the device, so that dropping the owner's device really
    releases it (a traceback keeping this object alive keeps no GigE session open).
    """

    def __init__(self, owner: AravisCamera) -> None:
        self._owner = owner

    @property
    def _dev(self) -> Any:
        device = self._owner._device
        if device is None:
            raise CameraLost("the camera connection is closed", device=self._owner.label)
        return device

    def _node(self, name: str) -> Any:
        with self._owner._gerrors(name):
            return self._dev.get_feature(name)

    def _kind(self, name: str) -> str:
        ar = _aravis().Aravis
        node = self._node(name)
        if node is None:
            raise FeatureMissing(
                f"the camera does not offer the GenICam feature {name!r}",
                feature=name,
                device=self._owner.label,
            )
        for kind, cls in (
            ("enum", ar.GcEnumeration),
            ("bool", ar.GcBoolean),
            ("float", ar.GcFloat),
            ("int", ar.GcInteger),
            ("str", ar.GcString),
            ("command", ar.GcCommand),
        ):
            if isinstance(node, cls):
                return kind
        return "unknown"

    def is_available(self, name: str) -> bool:
        if self._node(name) is None:
            return False
        with self._owner._gerrors(name):
            return bool(self._dev.is_feature_available(name))

    def is_writable(self, name: str) -> bool:
        ar = _aravis().Aravis
        with self._owner._gerrors(name):
            mode = self._dev.get_feature_access_mode(name)
        return mode in (ar.GcAccessMode.RW, ar.GcAccessMode.WO)

    def get(self, name: str) -> int | float | str | bool:
        kind = self._kind(name)
        with self._owner._gerrors(name):
            if kind in ("enum", "str"):
                return str(self._dev.get_string_feature_value(name))
            if kind == "bool":
                return bool(self._dev.get_boolean_feature_value(name))
            if kind == "float":
                return float(self._dev.get_float_feature_value(name))
            if kind == "int":
                return int(self._dev.get_integer_feature_value(name))
        raise FeatureMissing(
            f"{name} cannot be read as a value", feature=name, device=self._owner.label
        )

    def set(self, name: str, value: int | float | str | bool) -> None:
        kind = self._kind(name)
        with self._owner._gerrors(name):
            if kind in ("enum", "str"):
                self._dev.set_string_feature_value(name, str(value))
            elif kind == "bool":
                self._dev.set_boolean_feature_value(name, bool(value))
            elif kind == "float":
                self._dev.set_float_feature_value(name, float(value))
            elif kind == "int":
                self._dev.set_integer_feature_value(name, int(value))
            else:
                raise FeatureMissing(
                    f"{name} cannot be set", feature=name, device=self._owner.label
                )

    def execute(self, name: str) -> None:
        with self._owner._gerrors(name):
            self._dev.execute_command(name)

    def enum_entries(self, name: str) -> tuple[str, ...]:
        with self._owner._gerrors(name):
            return tuple(self._dev.dup_available_enumeration_feature_values_as_strings(name) or ())

    def bounds(self, name: str) -> tuple[float, float]:
        kind = self._kind(name)
        with self._owner._gerrors(name):
            if kind == "float":
                lo, hi = self._dev.get_float_feature_bounds(name)
            else:
                lo, hi = self._dev.get_integer_feature_bounds(name)
        return float(lo), float(hi)

    def increment(self, name: str) -> float | None:
        kind = self._kind(name)
        with self._owner._gerrors(name):
            if kind == "int":
                return float(self._dev.get_integer_feature_increment(name))
            if kind == "float":
                inc = float(self._dev.get_float_feature_increment(name))
                return inc if inc > 0 else None
        return None


class AravisCamera(CameraContext):
    """A GenICam camera through Aravis 0.8 (GigE Vision), software-triggered.

    Args:
        address: camera IPv4 address or host name (opened by unicast, no discovery).
        serial: expected ``DeviceSerialNumber``; with ``address`` it is checked; alone it
            needs ``interface="usb3"`` or ``allow_discovery``.
        allow_discovery: allow Aravis device discovery (GigE Vision broadcast on every
            interface) for a serial or device name without address.  Off by default.
        interface: ``"gige"`` or ``"usb3"`` (USB3 Vision by serial, GigE Vision disabled).
        transport: streaming parameters; the keyword arguments below override it.
        packet_size: GVSP packet size in bytes; default 8192 on loopback, otherwise the
            size Aravis negotiates with the camera (``gv_auto_packet_size``).
        frame_retention_ms: how long Aravis waits for the missing packets of a frame
            before declaring it incomplete (2000 ms suits 50 MB frames).
        n_buffers: stream buffers queued to Aravis.
        packet_resend: ask the camera to resend lost packets (if it supports it).

    Implements :class:`drivers.camera.Camera`.
    """

    backend = "aravis"

    def __init__(
        self,
        address: str | None = None,
        *,
        serial: str | None = None,
        allow_discovery: bool = False,
        interface: str = "gige",
        transport: TransportSettings | None = None,
        packet_size: int | None = None,
        frame_retention_ms: float | None = None,
        n_buffers: int | None = None,
        packet_resend: bool | None = None,
    ) -> None:
        if interface not in ("gige", "usb3"):
            raise ValueError(f'interface must be "gige" or "usb3", not {interface!r}')
        if address is None and serial is None:
            raise ValueError("AravisCamera needs an address, a serial, or both")
        if interface == "usb3" and serial is None and address is None:
            raise ValueError("a USB3 Vision camera is opened by serial")
        base = transport or TransportSettings()
        self.transport = TransportSettings(
            packet_size=packet_size if packet_size is not None else base.packet_size,
            packet_delay_ns=base.packet_delay_ns,
            throughput_limit_bps=base.throughput_limit_bps,
            buffer_count=n_buffers if n_buffers is not None else base.buffer_count,
            socket_buffer_bytes=base.socket_buffer_bytes,
            frame_retention_ms=(
                frame_retention_ms if frame_retention_ms is not None else base.frame_retention_ms
            ),
            packet_resend=packet_resend if packet_resend is not None else base.packet_resend,
            packet_socket=base.packet_socket,
        )
        if self.transport.buffer_count < 1 or self.transport.frame_retention_ms <= 0:
            raise ValueError("n_buffers >= 1 and frame_retention_ms > 0")
        self.address = address
        self.serial = serial
        self.allow_discovery = allow_discovery
        self.interface = interface
        if interface == "usb3":
            self.label = f"usb3://{serial or address}"
        else:
            self.label = f"gige://{address}" if address else f"aravis://{serial}"
            if address and serial:
                self.label += f" (serial {serial})"
        #: Start-up warnings (socket buffer capped by net.core.rmem_max, transport notes).
        self.warnings: list[str] = []

        self._lock = threading.RLock()
        self._device: Any = None
        self._camera: Any = None
        self._stream: Any = None
        self._signal_id: int | None = None
        self._payload = 0
        self._streaming = False
        self._sfnc: SfncCamera | None = None
        self._info: CameraInfo | None = None
        self._applied: CameraSettings | None = None
        self._requested: CameraSettings | None = None
        self._lost = False
        self._control_lost = threading.Event()
        self._disposers: list[threading.Thread] = []
        self._ip: str | None = None

    # ------------------------------------------------------------------ lifecycle

    @property
    def is_open(self) -> bool:
        """True between ``open()`` and ``close()`` (also while the camera is lost)."""
        return self._sfnc is not None or self._lost

    def open(self) -> None:
        """Connect, take control, read the camera info and set up the software trigger."""
        with self._lock:
            if self.is_open:
                return
            self._open_session()

    def close(self) -> None:
        """Stop acquisition and release the camera (control channel, stream)."""
        with self._lock:
            if self._streaming and self._camera is not None:
                try:
                    with self._gerrors("AcquisitionStop"):
                        self._camera.stop_acquisition()
                except CameraError:
                    pass  # already marked lost, disposed in the background
            self._streaming = False
            objects = [self._stream, self._camera, self._device]
            self._disconnect_signal()
            self._stream = self._camera = self._device = None
            self._sfnc = None
            self._lost = False
            drop_all(objects)

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
        """(min, max) ``ExposureTime`` in µs, read from the camera now."""
        with self._lock:
            return self._session().exposure_limits_us()

    def configure(self, settings: CameraSettings) -> CameraSettings:
        """Stop acquisition, apply ``settings``, return the values read back.

        Raises ``FeatureMissing`` for a pixel format or feature the camera does not offer
        and ``InvalidSetting`` for out-of-range values.  The settings are re-applied
        automatically after a reconnect.
        """
        with self._lock:
            bit_depth(settings.pixel_format)
            sfnc = self._session()
            self._stop_streaming()
            try:
                self._applied = sfnc.apply(settings)
            except (FeatureMissing, InvalidSetting):
                self._applied = sfnc.read_settings()  # partly applied: record what is in force
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
        """Return the next frame: fire one software trigger first, or (hardware trigger)
        wait for the frame the trigger line starts.

        Args:
            timeout_s: seconds to wait for the frame after the trigger.

        Raises:
            CameraTimeout: the camera answers but sent no frame in time.
            IncompleteFrame: the frame arrived damaged (never returned partially).
            CameraLost: the camera stopped answering; the next grab reopens it once.
        """
        if timeout_s <= 0:
            raise InvalidSetting(f"timeout_s must be > 0, not {timeout_s}", device=self.label)
        with self._lock:
            self._session()
            self._ensure_streaming()
            self._drain_stale()
            assert self._sfnc is not None
            trigger = self._applied.trigger if self._applied else SOFTWARE_TRIGGER
            if trigger == SOFTWARE_TRIGGER:
                self._sfnc.nodes.execute("TriggerSoftware")
            buffer = pop_frame_buffer(
                _aravis(), self._stream, time.monotonic() + timeout_s, self._gerrors, self.label
            )
            if buffer is None:
                if self._probe_lost():
                    self._mark_lost()
                    raise CameraLost(
                        "the camera stopped answering while waiting for a frame", device=self.label
                    )
                raise CameraTimeout(
                    f"no frame within {timeout_s:g} s after the software trigger"
                    if trigger == SOFTWARE_TRIGGER
                    else f"no frame within {timeout_s:g} s: no pulse on trigger line {trigger}?",
                    device=self.label,
                )
            try:
                return buffer_to_frame(
                    _aravis(),
                    buffer,
                    applied=self._applied,
                    info=self._info,
                    temperature_c=self._sfnc.temperature_c() if self._sfnc else None,
                    label=self.label,
                )
            finally:
                if self._stream is not None:
                    self._stream.push_buffer(buffer)

    def reconnect(self, timeout_s: float = 10.0) -> None:
        """Reopen the camera, retrying until ``timeout_s``; settings are re-applied.

        Raises ``CameraLost`` if the camera is still not answering at the deadline.
        """
        deadline = time.monotonic() + timeout_s
        with self._lock:
            if not self._lost:
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
        """The live session, reopening once if the camera was lost or rebooted."""
        self._require_open()
        if not self._lost and self._control_lost.is_set():
            log.warning("%s: control channel lost (camera rebooted?); reopening", self.label)
            self._mark_lost()
        if self._lost:
            self._reopen_once()
        assert self._sfnc is not None
        return self._sfnc

    @contextmanager
    def _gerrors(self, feature: str) -> Iterator[None]:
        """Translate Aravis GLib errors into typed camera errors."""
        glib = _aravis().GLib
        try:
            yield
        except glib.Error as exc:
            domain, code, text = exc.domain, exc.code, exc.message
            if domain == "arv-device-error-quark":
                if code in (_DEVICE_TIMEOUT, _DEVICE_NOT_CONNECTED, _DEVICE_TRANSFER):
                    self._mark_lost()
                    raise CameraLost(
                        f"the camera stopped answering ({feature}: {text})", device=self.label
                    ) from None
                if code == _DEVICE_FEATURE_NOT_FOUND:
                    raise FeatureMissing(
                        f"the camera does not offer {feature!r} ({text})",
                        feature=feature,
                        device=self.label,
                    ) from None
                if code in (_DEVICE_NOT_CONTROLLER, _DEVICE_ACCESS_DENIED):
                    raise CameraBusy(
                        f"the camera refused {feature} ({text}): control was taken over",
                        device=self.label,
                    ) from None
            elif domain == "arv-gc-error-quark":
                if code in (_GC_NODE_NOT_FOUND, _GC_ENTRY_NOT_FOUND, _GC_READ_ONLY):
                    raise FeatureMissing(
                        f"{feature}: {text}", feature=feature, device=self.label
                    ) from None
                if code == _GC_OUT_OF_RANGE:
                    raise InvalidSetting(f"{feature}: {text}", device=self.label) from None
            raise CameraError(f"{feature}: {text} ({domain} {code})", device=self.label) from None

    def _open_session(self) -> None:
        ar = _aravis()
        self._control_lost.clear()
        conn = connect(
            ar,
            address=self.address,
            serial=self.serial,
            interface=self.interface,
            allow_discovery=self.allow_discovery,
            label=self.label,
        )
        self._device, self._camera = conn.device, conn.camera
        if conn.ip is not None:
            self._ip = conn.ip
        try:
            self._signal_id = self._device.connect("control-lost", self._on_control_lost)
            self.warnings = setup_transport(ar, conn, self.transport, self.label, self._gerrors)
            self._sfnc = SfncCamera(_AravisNodes(self), self.label)
            no_packet_size = TransportSettings(
                packet_size=None,
                throughput_limit_bps=self.transport.throughput_limit_bps
                if not self._camera.is_uv_device()
                else None,
            )
            self.warnings += self._sfnc.apply_transport(no_packet_size)
            if self.address and self.serial:
                found = self._sfnc.read_string("DeviceSerialNumber") or self._sfnc.read_string(
                    "DeviceID"
                )
                if found != self.serial:
                    raise CameraNotFound(
                        f"the camera at {self._ip} has serial {found!r}, not {self.serial!r}",
                        device=self.label,
                        hint="camera.address and camera.serial in the station config",
                    )
            self._sfnc.setup_software_trigger()
            self._info = self._sfnc.read_info(backend=self.backend)
            if self._requested is not None:
                self._applied = self._sfnc.apply(self._requested)
            else:
                self._applied = self._sfnc.read_settings()
        except BaseException:
            objects = [self._stream, self._camera, self._device]
            self._disconnect_signal()
            self._stream = self._camera = self._device = None
            self._sfnc = None
            drop_all(objects)
            raise
        self._lost = False

    def _on_control_lost(self, *_args: object) -> None:
        """Aravis heartbeat thread: the camera no longer lists us as controller."""
        self._control_lost.set()

    def _disconnect_signal(self) -> None:
        if self._signal_id is not None and self._device is not None:
            self._device.disconnect(self._signal_id)
        self._signal_id = None

    def _ensure_streaming(self) -> None:
        if self._streaming:
            return
        with self._gerrors("PayloadSize"):
            payload = int(self._camera.get_payload())
        if self._stream is None or payload != self._payload:
            self._stream = None
            self._stream, warnings = open_stream(
                _aravis(),
                self._camera,
                self._device,
                self.transport,
                payload,
                self.label,
                self._gerrors,
            )
            for warning in warnings:
                if warning not in self.warnings:
                    log.warning("%s: %s", self.label, warning)
                    self.warnings.append(warning)
            self._payload = payload
        with self._gerrors("AcquisitionStart"):
            self._camera.start_acquisition()
        self._streaming = True

    def _stop_streaming(self) -> None:
        if self._streaming:
            self._streaming = False
            with self._gerrors("AcquisitionStop"):
                self._camera.stop_acquisition()

    def _drain_stale(self) -> None:
        """Requeue buffers of earlier triggers so the next pop is this trigger's frame."""
        while (old := self._stream.try_pop_buffer()) is not None:
            self._stream.push_buffer(old)

    def _probe_lost(self) -> bool:
        """After a frame timeout: is the camera gone (or no longer ours)?"""
        if self._control_lost.is_set():
            return True
        ar = _aravis()
        if not isinstance(self._device, ar.Aravis.GvDevice):
            return False
        if not self._device.is_controller():
            return True
        try:
            ccp = self._device.read_register(GVBS_CONTROL_CHANNEL_PRIVILEGE)
        except ar.GLib.Error:
            return True
        return (int(ccp) & 0x3) == 0

    def _mark_lost(self) -> None:
        """Forget the session; its objects are released on a background thread because
        their finalizers write to the absent camera (several GVCP timeouts)."""
        self._lost = True
        self._streaming = False
        objects = [o for o in (self._stream, self._camera, self._device) if o is not None]
        self._disconnect_signal()
        self._stream = self._camera = self._device = None
        self._sfnc = None
        if objects:
            disposer = threading.Thread(
                target=drop_all, args=(objects,), name="aravis-release", daemon=True
            )
            disposer.start()
            self._disposers.append(disposer)

    def _reopen_once(self) -> None:
        """One bounded attempt to reopen a lost camera."""
        if self._ip is not None and not gvcp_ping(self._ip, timeout_s=0.6):
            raise CameraLost("the camera is still not answering", device=self.label)
        # The old session must be gone before a new one takes control: its finalizer
        # releases the control channel, which would otherwise drop the new session.
        deadline = time.monotonic() + 15.0
        while self._disposers:
            self._disposers[0].join(timeout=max(0.0, deadline - time.monotonic()))
            self._disposers.pop(0)
        try:
            self._open_session()
        except (CameraNotFound, CameraLost, CameraBusy) as exc:
            self._lost = True
            raise CameraLost(
                f"the camera is not available again yet ({exc.message})",
                device=self.label,
            ) from None
        log.info("%s: reconnected", self.label)


__all__ = ["AravisCamera"]
