"""The host-side GigE Vision rules of :mod:`drivers.gige_host` (no camera needed)."""

from __future__ import annotations

from drivers.camera import TransportSettings
from drivers.gige_host import can_open_packet_sockets, use_packet_ring


def test_the_automatic_receiver_takes_the_ring_only_for_frames_the_socket_cannot_hold() -> None:
    auto = TransportSettings()
    may = can_open_packet_sockets()
    assert not use_packet_ring(auto, 4096, 212_992)
    assert not use_packet_ring(auto, 53_248, 212_992)
    assert use_packet_ring(auto, 53_249, 212_992) == may
    assert use_packet_ring(auto, 26_214_400, 212_992) == may
    assert use_packet_ring(auto, 26_214_400, None) == may  # rmem_default unknown
    asked = TransportSettings(socket_buffer_bytes=64_000_000)  # the socket was asked for
    assert not use_packet_ring(asked, 26_214_400, 212_992)
    assert use_packet_ring(TransportSettings(packet_socket=True), 4096, 212_992)
    assert not use_packet_ring(TransportSettings(packet_socket=False), 26_214_400, 212_992)
