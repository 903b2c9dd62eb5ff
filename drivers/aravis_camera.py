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
:mod:`drivers.aravis_frames`; its GenICam features and the GLib errors, in
:mod:`drivers.aravis_nodes`.  Opening, identity, configuration and the reconnect loop are
shared with the harvesters backend (:class:`drivers.genicam_camera.GenICamCamera`).
"""

from __future__ import annotations

import dataclasses
import logging
import threading
import time
import types
from contextlib import AbstractContextManager
from typing import Any

from drivers.aravis_connect import (
    connect,
    control_is_lost,
    drop_all,
    open_stream,
    setup_transport,
)
from drivers.aravis_frames import buffer_to_frame, pop_frame_buffer
from drivers.aravis_nodes import AravisNodes, glib_errors
from drivers.camera import Frame, TransportSettings
from drivers.camera_errors import (
    BackendUnavailable,
    CameraError,
    CameraLost,
    CameraNotFound,
)
from drivers.genicam_camera import GenICamCamera
from drivers.gige_host import gvcp_ping
from drivers.sfnc import SfncCamera

log = logging.getLogger(__name__)

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


class AravisCamera(GenICamCamera):
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
        self.transport = dataclasses.replace(
            base,
            packet_size=packet_size if packet_size is not None else base.packet_size,
            buffer_count=n_buffers if n_buffers is not None else base.buffer_count,
            frame_retention_ms=(
                frame_retention_ms if frame_retention_ms is not None else base.frame_retention_ms
            ),
            packet_resend=packet_resend if packet_resend is not None else base.packet_resend,
        )
        if self.transport.buffer_count < 1 or self.transport.frame_retention_ms <= 0:
            raise ValueError("n_buffers >= 1 and frame_retention_ms > 0")
        self.address = address
        self.serial = serial
        self.allow_discovery = allow_discovery
        self.interface = interface
        if interface == "usb3":
            label = f"usb3://{serial or address}"
        else:
            label = f"gige://{address}" if address else f"aravis://{serial}"
            if address and serial:
                label += f" (serial {serial})"
        super().__init__(label)
        self._device: Any = None
        self._camera: Any = None
        self._stream: Any = None
        self._signal_id: int | None = None
        self._payload = 0
        self._streaming = False
        self._control_lost = threading.Event()
        self._disposers: list[threading.Thread] = []
        self._ip: str | None = None

    # ------------------------------------------------------------------ lifecycle

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
            objects = self._detach()
            self._lost = False
            drop_all(objects)

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
        self._check_timeout(timeout_s)
        with self._lock:
            self._session()
            self._ensure_streaming()
            self._drain_stale()
            assert self._sfnc is not None
            trigger = self._fire_trigger(self._sfnc)
            buffer = pop_frame_buffer(
                _aravis(), self._stream, time.monotonic() + timeout_s, self._gerrors, self.label
            )
            if buffer is None:
                if self._probe_lost():
                    self._mark_lost()
                    raise CameraLost(
                        "the camera stopped answering while waiting for a frame", device=self.label
                    )
                raise self._no_frame(timeout_s, trigger)
            try:
                return buffer_to_frame(
                    _aravis(),
                    buffer,
                    applied=self._applied,
                    info=self._info,
                    temperature_c=self.temperature_c(),
                    label=self.label,
                )
            finally:
                if self._stream is not None:
                    self._stream.push_buffer(buffer)

    # ------------------------------------------------------------------ internals

    def _notice_loss(self) -> None:
        """The Aravis heartbeat saw the control channel lost (camera rebooted?)."""
        if not self._lost and self._control_lost.is_set():
            log.warning("%s: control channel lost (camera rebooted?); reopening", self.label)
            self._mark_lost()

    def _drop_for_reconnect(self) -> None:
        if not self._lost:
            self._mark_lost()

    def _gerrors(self, feature: str) -> AbstractContextManager[None]:
        """Translate Aravis GLib errors into typed camera errors."""
        return glib_errors(_aravis().GLib, feature, self.label, self._mark_lost)

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
            self._sfnc = SfncCamera(AravisNodes(self, ar), self.label)
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
            self._set_up_session(self._sfnc)
        except BaseException:
            drop_all(self._detach())
            raise
        self._lost = False

    def _on_control_lost(self, *_args: object) -> None:
        """Aravis heartbeat thread: the camera no longer lists us as controller."""
        self._control_lost.set()

    def _detach(self) -> list[Any]:
        """Forget the session (stream, camera, device, in that order; the control-lost
        signal disconnected); the caller releases the returned objects."""
        objects = [self._stream, self._camera, self._device]
        if self._signal_id is not None and self._device is not None:
            self._device.disconnect(self._signal_id)
        self._signal_id = None
        self._stream = self._camera = self._device = None
        self._sfnc = None
        return objects

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

    def _stop_acquisition(self) -> None:
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
        return self._control_lost.is_set() or control_is_lost(_aravis(), self._device)

    def _mark_lost(self) -> None:
        """Forget the session; its objects are released on a background thread because
        their finalizers write to the absent camera (several GVCP timeouts)."""
        self._lost = True
        self._streaming = False
        objects = [o for o in self._detach() if o is not None]
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
        self._open_again("the camera is not available again yet")
        log.info("%s: reconnected", self.label)


__all__ = ["AravisCamera"]
