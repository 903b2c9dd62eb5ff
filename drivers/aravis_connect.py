"""Opening an Aravis camera without discovery, its transport and its stream.

Used by :class:`drivers.aravis_camera.AravisCamera` (its module docstring says how a
camera is found and why discovery is off). The Aravis namespace (``ar``: the
``Aravis``, ``Gio`` and ``GLib`` modules of PyGObject) is passed in, so this module
imports no camera library itself; ``gerrors`` is the camera's translation of GLib
errors into typed camera errors (:data:`drivers.genicam_camera.GErrors`).
"""

from __future__ import annotations

import ipaddress
import logging
import threading
import types
from dataclasses import dataclass
from typing import Any

from drivers.camera import TransportSettings
from drivers.camera_errors import CameraBusy, CameraNotFound
from drivers.genicam_camera import GErrors
from drivers.gige_host import (
    GVBS_CONTROL_CHANNEL_PRIVILEGE,
    gvcp_read_register,
    local_address_for,
    resolve_ipv4,
    rmem_default_bytes,
    rmem_max_bytes,
    socket_buffer_warning,
    use_packet_ring,
)

log = logging.getLogger(__name__)

USB3_INTERFACE = "USB3Vision"
GIGE_INTERFACE = "GigEVision"

SOCKET_BUFFER_FRAMES = 2
"""Receive socket buffer of the UDP receiver, in frames (see :func:`open_stream`)."""
LOOPBACK_PACKET_SIZE = 8192
"""GVSP packet size used on loopback (no MTU limit there; 8192 keeps 50 MB frames fast)."""


@dataclass
class Connection:
    """An opened camera: the ``ArvDevice``, the ``ArvCamera`` on it and, for a GigE Vision
    camera opened by address, its IPv4 address (None otherwise)."""

    device: Any
    camera: Any
    ip: str | None = None


def drop_all(objects: list[Any]) -> None:
    """Release GObjects (their finalizers talk to the camera and may block for seconds)."""
    while objects:
        objects.pop()


def connect(
    ar: types.SimpleNamespace,
    *,
    address: str | None,
    serial: str | None,
    interface: str,
    allow_discovery: bool,
    label: str,
) -> Connection:
    """Create the ``ArvDevice`` and ``ArvCamera``: unicast to an address, USB3 Vision by
    serial with GigE Vision disabled, or (only with ``allow_discovery``) Aravis's own
    lookup of a name. Raises ``CameraNotFound`` or ``CameraBusy``."""
    if interface == "usb3":
        return _connect_usb3(ar, serial or address, label)
    ip = resolve_ipv4(address) if address else None
    if ip is None:
        name = address or serial
        if not allow_discovery:
            raise CameraNotFound(
                f"{name!r} is not an IPv4 address or host name; opening a camera by serial "
                "or device name needs GigE Vision discovery, which broadcasts on every "
                "network interface and is disabled",
                device=label,
                hint="set camera.address to the camera's IP (serial is then verified), "
                "or allow_discovery=True on a dedicated camera network",
            )
        try:
            camera = ar.Aravis.Camera.new(name)
        except ar.GLib.Error as exc:
            raise CameraNotFound(
                f"no camera named {name!r} found ({exc.message})", device=label
            ) from None
        return Connection(camera.get_device(), camera)
    local = local_address_for(ip)
    if local is None:
        raise CameraNotFound(
            f"no network interface routes to {ip}",
            device=label,
            hint="the host's camera interface is up and in the camera's subnet",
        )
    privilege = gvcp_read_register(ip, GVBS_CONTROL_CHANNEL_PRIVILEGE, timeout_s=1.0, tries=4)
    if privilege is None:
        raise CameraNotFound(f"no GigE Vision camera answers at {ip}", device=label)
    if privilege & 0x3:
        raise CameraBusy(
            f"the camera at {ip} answers but another application controls it", device=label
        )
    try:
        device = ar.Aravis.GvDevice.new(
            ar.Gio.InetAddress.new_from_string(local), ar.Gio.InetAddress.new_from_string(ip)
        )
    except ar.GLib.Error as exc:
        raise CameraNotFound(
            f"no GigE Vision camera answers at {ip} ({exc.message})", device=label
        ) from None
    if not device.is_controller():
        threading.Thread(target=drop_all, args=([device],), daemon=True).start()
        raise CameraBusy(
            f"the camera at {ip} answers but another application controls it", device=label
        )
    return Connection(device, ar.Aravis.Camera.new_with_device(device), ip)


def control_is_lost(ar: types.SimpleNamespace, device: Any) -> bool:
    """After a frame timeout: does the GigE Vision camera on ``device`` no longer list us
    as its controller, or no longer answer a read of its control channel privilege?
    (False for a device that is not GigE Vision.)"""
    if not isinstance(device, ar.Aravis.GvDevice):
        return False
    if not device.is_controller():
        return True
    try:
        ccp = device.read_register(GVBS_CONTROL_CHANNEL_PRIVILEGE)
    except ar.GLib.Error:
        return True
    return (int(ccp) & 0x3) == 0


def _connect_usb3(ar: types.SimpleNamespace, name: str | None, label: str) -> Connection:
    """Open a USB3 Vision camera by serial / device id with GigE Vision disabled."""
    assert name is not None
    ar.Aravis.disable_interface(GIGE_INTERFACE)  # before anything enumerates devices
    ar.Aravis.enable_interface(USB3_INTERFACE)
    try:
        camera = ar.Aravis.Camera.new(name)
    except ar.GLib.Error as exc:
        raise CameraNotFound(
            f"no USB3 Vision camera {name!r} on this host ({exc.message})",
            device=label,
            hint="the USB cable (a USB 3 port), the camera serial (camera.serial), and "
            "read/write access to the USB device (udev rule for the camera's vendor id)",
        ) from None
    return Connection(camera.get_device(), camera)


def setup_transport(
    ar: types.SimpleNamespace,
    conn: Connection,
    transport: TransportSettings,
    label: str,
    gerrors: GErrors,
) -> list[str]:
    """Packet size, inter-packet delay, throughput limit (GigE and USB3 Vision); the
    warnings (a setting the camera does not offer)."""
    camera, warnings = conn.camera, []
    if camera.is_uv_device():
        if transport.throughput_limit_bps is not None:
            with gerrors("DeviceLinkThroughputLimit"):
                if camera.uv_is_bandwidth_control_available():
                    camera.uv_set_bandwidth(int(transport.throughput_limit_bps))
                else:
                    warnings.append("USB3 bandwidth control not offered")
        return warnings
    if not isinstance(conn.device, ar.Aravis.GvDevice):
        return warnings
    size = transport.packet_size
    if size is None and conn.ip is not None and ipaddress.IPv4Address(conn.ip).is_loopback:
        size = LOOPBACK_PACKET_SIZE
    with gerrors("GevSCPSPacketSize"):
        if size is not None:
            camera.gv_set_packet_size(int(size))
            camera.gv_set_packet_size_adjustment(ar.Aravis.GvPacketSizeAdjustment.NEVER)
        else:
            try:
                camera.gv_auto_packet_size()
            except ar.GLib.Error as exc:  # keep the camera's packet size
                log.warning("%s: packet size negotiation failed: %s", label, exc.message)
    if transport.packet_delay_ns is not None:
        with gerrors("GevSCPD"):
            camera.gv_set_packet_delay(int(transport.packet_delay_ns))
    return warnings


def open_stream(
    ar: types.SimpleNamespace,
    camera: Any,
    device: Any,
    transport: TransportSettings,
    payload: int,
    label: str,
    gerrors: GErrors,
) -> tuple[Any, list[str]]:
    """A stream of ``camera`` (on ``device``) for frames of ``payload`` bytes with ``transport.buffer_count`` buffers
    queued, and the warnings (a socket buffer the kernel caps).

    GigE Vision: the packet ring (``PACKET_MMAP``) when
    :func:`drivers.gige_host.use_packet_ring` allows it, else a UDP socket whose receive
    buffer is as configured, else two frames and never below the default (the kernel
    charges a datagram more than its payload: an 8 KiB packet takes a 16 KiB buffer on
    loopback, so Aravis's AUTO size of one frame drops the end of a burst; the default
    208 KiB overflows on a 26-52 MB frame burst); frame retention and packet resend as
    configured.
    """
    arv, warnings = ar.Aravis, []
    with gerrors("stream"):
        ring = False
        rmem_default = rmem_default_bytes()
        if isinstance(device, arv.GvDevice):
            ring = use_packet_ring(transport, payload, rmem_default)
            device.set_stream_options(
                arv.GvStreamOption.NONE if ring else arv.GvStreamOption.PACKET_SOCKET_DISABLED
            )
        stream = camera.create_stream(None, None)
        if isinstance(stream, arv.GvStream):
            stream.set_property("frame-retention", int(transport.frame_retention_ms * 1000))
            if not ring:
                wanted = transport.socket_buffer_bytes or max(
                    SOCKET_BUFFER_FRAMES * payload, rmem_default or 0
                )
                stream.set_property("socket-buffer", arv.GvStreamSocketBuffer.FIXED)
                stream.set_property("socket-buffer-size", int(wanted))
                warning = socket_buffer_warning(wanted, rmem_max_bytes())
                if warning is not None:
                    warnings.append(warning)
            stream.set_property(
                "packet-resend",
                arv.GvStreamPacketResend.ALWAYS
                if transport.packet_resend
                else arv.GvStreamPacketResend.NEVER,
            )
        for _ in range(transport.buffer_count):
            stream.push_buffer(arv.Buffer.new_allocate(payload))
    return stream, warnings
