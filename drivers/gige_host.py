"""GigE Vision seen from the host: unicast GVCP probes, the kernel's socket-buffer
limits, and the choice of Aravis's stream receiver.

Nothing here broadcasts: :func:`gvcp_read_register` sends one unicast READREG to a
known address.  The receive buffer of a UDP socket is capped at ``net.core.rmem_max``
and starts at ``net.core.rmem_default``; Aravis can instead read the stream through an
``AF_PACKET`` ring (:func:`use_packet_ring`).
"""

from __future__ import annotations

import ipaddress
import socket
import struct
import threading
import time

from drivers.camera import TransportSettings

GVCP_PORT = 3956
"""The GigE Vision control port (UDP)."""
GVBS_CONTROL_CHANNEL_PRIVILEGE = 0x0A00
"""Bootstrap register: who controls the device (bits 0-1 non-zero: controlled)."""


def resolve_ipv4(address: str) -> str | None:
    """IPv4 literal for an address or host name; None if it does not resolve."""
    try:
        return str(ipaddress.IPv4Address(address))
    except ValueError:
        pass
    try:
        infos = socket.getaddrinfo(address, GVCP_PORT, socket.AF_INET, socket.SOCK_DGRAM)
    except (socket.gaierror, UnicodeError):
        return None
    return str(infos[0][4][0]) if infos else None


def gvcp_read_register(ip: str, address: int, timeout_s: float = 0.5, tries: int = 3) -> int | None:
    """Read one bootstrap register of the GigE Vision device at ``ip``; None if no answer.

    One unicast GVCP READREG command to ``ip``:3956 per try (never a broadcast); devices
    answer reads from any application, even while another one controls them.  Used to
    tell "camera absent" or "controlled by someone else" in well under Aravis's 2.5 s of
    GVCP retries.
    """
    request_id = 0x4C46
    packet = struct.pack(">BBHHHI", 0x42, 0x01, 0x0080, 4, request_id, address)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.connect((ip, GVCP_PORT))
        except OSError:
            return None
        for _ in range(tries):
            deadline = time.monotonic() + timeout_s / tries
            try:
                sock.send(packet)
                while (remaining := deadline - time.monotonic()) > 0:
                    sock.settimeout(remaining)
                    ack = sock.recv(64)
                    if len(ack) >= 12:
                        status, answer, _length, ack_id, value = struct.unpack(">HHHHI", ack[:12])
                        if answer == 0x0081 and ack_id == request_id and status == 0:
                            return int(value)
            except ConnectionRefusedError:  # ICMP port unreachable: nothing listens
                threading.Event().wait(max(0.0, deadline - time.monotonic()))
            except OSError:  # timeout
                pass
    return None


def gvcp_ping(ip: str, timeout_s: float = 0.5, tries: int = 3) -> bool:
    """True if a GigE Vision device answers at ``ip`` (see :func:`gvcp_read_register`)."""
    return gvcp_read_register(ip, 0x0000, timeout_s, tries) is not None


RMEM_DEFAULT_PATH = "/proc/sys/net/core/rmem_default"
RMEM_MAX_PATH = "/proc/sys/net/core/rmem_max"


def _sysctl_int(path: str) -> int | None:
    """The first integer of a ``/proc/sys`` file, None if unreadable."""
    try:
        with open(path, encoding="ascii") as handle:
            return int(handle.read().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def rmem_max_bytes(path: str = RMEM_MAX_PATH) -> int | None:
    """The kernel's cap on a socket receive buffer (``net.core.rmem_max``), None if unknown."""
    return _sysctl_int(path)


def rmem_default_bytes() -> int | None:
    """A new socket's receive buffer (``net.core.rmem_default``), None if unknown."""
    return _sysctl_int(RMEM_DEFAULT_PATH)


def socket_buffer_warning(wanted_bytes: int, rmem_max: int | None) -> str | None:
    """The start-up warning when ``net.core.rmem_max`` caps a wanted socket buffer."""
    if rmem_max is None or wanted_bytes <= rmem_max:
        return None
    return (
        f"the GVSP socket buffer is capped at net.core.rmem_max = {rmem_max} bytes, "
        f"{wanted_bytes} wanted: frames may lose packets; raise it with "
        f"'sysctl -w net.core.rmem_max={wanted_bytes}' (and in /etc/sysctl.d/ to keep it)"
    )


def can_open_packet_sockets() -> bool:
    """True when this process may open ``AF_PACKET`` sockets (``CAP_NET_RAW``), the
    test Aravis itself makes before it uses its packet ring."""
    try:
        probe = socket.socket(socket.AF_PACKET, socket.SOCK_RAW, socket.htons(0x0003))
    except (OSError, AttributeError):
        return False
    probe.close()
    return True


def use_packet_ring(
    transport: TransportSettings, payload_bytes: int, rmem_default: int | None
) -> bool:
    """Whether Aravis should receive a GigE stream through its ``AF_PACKET`` ring.

    ``transport.packet_socket`` True/False decides.  None (automatic): the UDP socket
    when one frame burst fits in a quarter of the socket's default receive buffer
    (``net.core.rmem_default``: Aravis sizes the buffer only once the first frame has
    started, and the kernel charges an 8 KiB datagram about 16 KiB), or when
    ``socket_buffer_bytes`` asks for the socket; otherwise the ring if the process has
    ``CAP_NET_RAW``.  The socket is filtered by port in the kernel; while Aravis 0.8
    sets its ring up, it reads every packet on the interface as stream data for a moment.
    """
    if transport.packet_socket is not None:
        return transport.packet_socket
    if transport.socket_buffer_bytes is not None:
        return False
    if rmem_default is not None and 4 * payload_bytes <= rmem_default:
        return False
    return can_open_packet_sockets()


def local_address_for(ip: str) -> str | None:
    """Address of the local interface the kernel routes ``ip`` through (sends nothing)."""
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as sock:
        try:
            sock.connect((ip, GVCP_PORT))
        except OSError:
            return None
        return str(sock.getsockname()[0])
