"""The Zaber emulator answers like a device: raw bytes over a real pty and 127.0.0.1 TCP."""

from __future__ import annotations

import socket
import time
from collections.abc import Callable, Iterator

import pytest
import serial

from drivers.sim.zaber_emulator import AxisSpec, DeviceSpec, ZaberEmulator
from drivers.zaber import protocol

SPEEDUP = 50.0


def wait_for(predicate: Callable[[], bool], timeout_s: float = 3.0) -> None:
    """Wait until ``predicate()`` holds; fail after ``timeout_s``."""
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        time.sleep(0.002)


class Line:
    """A bare pyserial connection speaking raw bytes (no driver involved)."""

    def __init__(self, url: str) -> None:
        self.ser = serial.serial_for_url(url, baudrate=115200, timeout=0.02)
        self.buf = b""

    def send(self, data: str | bytes) -> None:
        self.ser.write(data.encode() if isinstance(data, str) else data)

    def read_line(self, timeout_s: float = 2.0) -> str:
        deadline = time.monotonic() + timeout_s
        while b"\n" not in self.buf:
            if time.monotonic() > deadline:
                raise AssertionError(f"no line within {timeout_s} s (buffer {self.buf!r})")
            self.buf += self.ser.read(self.ser.in_waiting or 1)
        line, _, self.buf = self.buf.partition(b"\n")
        assert line.endswith(b"\r"), "devices terminate replies with CR LF"
        return line[:-1].decode()

    def ask(self, text: str) -> str:
        self.send(text)
        return self.read_line()

    def close(self) -> None:
        self.ser.close()


CHAIN = [
    DeviceSpec(1, (AxisSpec(microstep_um=0.1, travel_mm=100.0),)),
    DeviceSpec(2, (AxisSpec(), AxisSpec()), device_id=30222, serial=777),
]


@pytest.fixture(params=["pty", "tcp"])
def emu(request: pytest.FixtureRequest) -> Iterator[ZaberEmulator]:
    """The chain over each transport."""
    with ZaberEmulator(CHAIN, transport=request.param, speedup=SPEEDUP) as emulator:
        yield emulator


@pytest.fixture
def line(emu: ZaberEmulator) -> Iterator[Line]:
    conn = Line(emu.url)
    yield conn
    conn.close()


@pytest.fixture
def pty_line() -> Iterator[Line]:
    """Raw line to the chain over a pty only (for the long tables: TCP close costs 0.3 s)."""
    with ZaberEmulator(CHAIN, transport="pty", speedup=SPEEDUP) as emulator:
        conn = Line(emulator.url)
        yield conn
        conn.close()


def test_reply_format_exact_bytes(line: Line) -> None:
    # checksums are off at power-up (device default); CR, LF or CRLF terminate commands
    assert line.ask("/1 1 get limit.max\n") == "@01 1 OK IDLE WR 1000000"
    assert line.ask("/1 1 12 get limit.min\r\n") == "@01 1 12 OK IDLE WR 0"
    assert line.ask("/1 0 get device.id\r") == "@01 0 OK IDLE WR 50081"
    assert line.ask("/1\n") == "@01 0 OK IDLE WR 0"


def test_checksums_on_replies_and_commands(line: Line) -> None:
    assert line.ask("/1 0 set comm.checksum 1\n") == protocol.with_checksum("@01 0 OK IDLE WR 0")
    reply = line.ask(protocol.format_command(1, 1, "get pos", message_id=7).decode())
    assert protocol.verify_checksum(reply)
    assert reply == protocol.with_checksum("@01 1 7 OK IDLE WR 0")
    # a command with a wrong checksum is discarded without a reply: the next reply is for "9"
    wrong = (protocol.checksum("1 1 8 get pos") + 1) % 256
    line.send(f"/1 1 8 get pos:{wrong:02X}\n")
    line.send(protocol.format_command(1, 1, "get pos", message_id=9))
    assert line.read_line().startswith("@01 1 9 OK")


@pytest.mark.parametrize(
    ("command", "reason"),
    [
        ("/1 1 fly away", "BADCOMMAND"),
        ("/1 1 get nonsense", "BADCOMMAND"),
        ("/1 1 get", "BADCOMMAND"),
        ("/1 1 move sideways 5", "BADCOMMAND"),
        ("/1 1 move abs", "BADDATA"),
        ("/1 1 move abs ten", "BADDATA"),
        ("/1 1 move abs 1000001", "BADDATA"),
        ("/1 1 move abs -1", "BADDATA"),
        ("/1 1 move rel -5", "BADDATA"),
        ("/1 1 set maxspeed 0", "BADDATA"),
        ("/1 0 set device.id 5", "BADDATA"),
        ("/1 0 set comm.checksum 2", "BADDATA"),
        ("/1 1 home now", "BADDATA"),
        ("/1 1 warnings maybe", "BADDATA"),
        ("/1 2 get pos", "BADAXIS"),
        ("/1 1 get system.serial", "DEVICEONLY"),
        ("/1 1 set comm.alert 1", "DEVICEONLY"),
        ("/1 1 system reset", "DEVICEONLY"),
    ],
)
def test_rejections_like_a_device(pty_line: Line, command: str, reason: str) -> None:
    reply = protocol.parse_message(pty_line.ask(command + "\n"))
    assert isinstance(reply, protocol.Reply)
    assert reply.rejected and reply.data == reason
    assert reply.device == 1


def test_bad_message_id(pty_line: Line) -> None:
    assert pty_line.ask("/1 1 123 get pos\n") == "@01 0 RJ IDLE WR BADMESSAGEID"


def test_broadcast_and_multi_axis(line: Line) -> None:
    line.send("/0 0 5 get device.id\n")
    assert [line.read_line(), line.read_line()] == [
        "@01 0 5 OK IDLE WR 50081",
        "@02 0 5 OK IDLE WR 30222",
    ]
    assert line.ask("/2 0 get system.axiscount\n") == "@02 0 OK IDLE WR 2"
    assert line.ask("/2 0 get limit.max\n") == "@02 0 OK IDLE WR 1000000 1000000"
    assert line.ask("/2 0 get system.serial\n") == "@02 0 OK IDLE WR 777"
    assert line.ask("/3 0 get pos\n/1 0 get pos\n") == "@01 0 OK IDLE WR 0"  # no device 3


def test_home_clears_wr_and_busy_lasts_as_long_as_the_move(emu: ZaberEmulator, line: Line) -> None:
    spec = AxisSpec()  # 20 mm/s, 200 mm/s^2, 0.1 um microsteps, starts at 10 mm physically
    assert line.ask("/1 1 home\n").startswith("@01 1 OK BUSY WR")
    wait_for(lambda: not emu.snapshot(1, 1).busy)
    assert line.ask("/1 1 get pos\n") == "@01 1 OK IDLE -- 0"
    # 50 mm at 20 mm/s with 200 mm/s^2: 2.5 s + 0.1 s in real time -> / speedup
    expected_s = protocol.move_duration_s(50.0, spec.speed_mm_s, spec.accel_mm_s2) / SPEEDUP
    start = time.monotonic()
    assert line.ask("/1 1 move abs 500000\n") == "@01 1 OK BUSY -- 0"
    wait_for(lambda: not protocol.parse_message(line.ask("/1 1 get pos\n")).busy)  # type: ignore[union-attr]
    elapsed = time.monotonic() - start
    assert expected_s * 0.8 <= elapsed <= expected_s + 1.0  # upper bound: polling under load
    assert line.ask("/1 1 get pos\n") == "@01 1 OK IDLE -- 500000"


def test_stop_decelerates_and_sets_ni(emu: ZaberEmulator, line: Line) -> None:
    line.ask("/1 1 set pos 0\n")  # reference without homing
    line.ask("/1 1 set maxspeed 40960\n")  # 2.5 mm/s (25000 usteps/s x 1.6384): 0.7 s move
    line.ask("/1 1 set accel 33\n")  # 20 mm/s^2: the stop lasts 0.25 s / speedup
    line.ask("/1 1 move abs 900000\n")
    wait_for(lambda: emu.snapshot(1, 1).position > 100000)
    assert line.ask("/1 1 stop\n").startswith("@01 1 OK BUSY NI")
    wait_for(lambda: not emu.snapshot(1, 1).busy)
    snap = emu.snapshot(1, 1)
    assert 100000 < snap.position < 900000 and "NI" in snap.flags
    assert line.ask("/1 1 warnings\n") == "@01 1 OK IDLE NI 01 NI"
    # like the firmware, NI survives a new, good move until "warnings clear"
    assert line.ask("/1 1 move abs 0\n") == "@01 1 OK BUSY NI 0"
    wait_for(lambda: not emu.snapshot(1, 1).busy, timeout_s=5.0)
    assert line.ask("/1 1 get pos\n") == "@01 1 OK IDLE NI 0"
    assert line.ask("/1 1 warnings clear\n") == "@01 1 OK IDLE -- 01 NI"
    assert line.ask("/1 1 warnings\n") == "@01 1 OK IDLE -- 00"


def test_warnings_clear_lists_then_clears(emu: ZaberEmulator, line: Line) -> None:
    line.ask("/1 1 set pos 0\n")
    emu.stall_next_move(1, 1, 0.5)
    line.ask("/1 1 move abs 1000\n")
    wait_for(lambda: "FS" in emu.snapshot(1, 1).flags)
    # the list shows what was active; the flag field shows the state after clearing
    assert line.ask("/1 1 warnings clear\n") == "@01 1 OK IDLE -- 01 FS"
    assert line.ask("/1 1 warnings\n") == "@01 1 OK IDLE -- 00"
    assert emu.snapshot(1, 1).position == 500


def test_alert_when_move_completes(emu: ZaberEmulator, line: Line) -> None:
    line.ask("/1 0 set comm.alert 1\n")
    line.ask("/1 1 set pos 0\n")
    assert line.ask("/1 1 move abs 2000\n") == "@01 1 OK BUSY -- 0"
    assert line.read_line() == "!01 1 IDLE --"
    assert emu.stats.alerts == 1


def test_power_cycle_loses_position(emu: ZaberEmulator, line: Line) -> None:
    line.ask("/1 1 set pos 0\n")
    line.ask("/1 1 move abs 3000\n")
    wait_for(lambda: not emu.snapshot(1, 1).busy)
    physical = emu.snapshot(1, 1).physical
    emu.power_cycle(1, off_s=0.5)
    assert not emu.is_powered(1) and emu.snapshot(1, 1).flags == {"WR"}
    # while off, device 1 answers nothing: the next line is device 2's reply
    line.send("/1 1 get pos\n/2 0 get pos\n")
    assert line.read_line().startswith("@02 0 OK")
    wait_for(lambda: emu.is_powered(1))
    assert line.ask("/1 1 get pos\n") == "@01 1 OK IDLE WR 0"
    assert emu.snapshot(1, 1).physical == pytest.approx(physical)  # it did not move


def test_tcp_binds_loopback_and_serves_one_client() -> None:
    with ZaberEmulator(transport="tcp") as emu:
        address = emu.bound_address
        assert address is not None and address[0] == "127.0.0.1"
        assert emu.url == f"socket://127.0.0.1:{address[1]}"
        first = Line(emu.url)
        assert first.ask("/1 0 get device.id\n").endswith("50081")
        with socket.create_connection(("127.0.0.1", address[1]), timeout=2.0) as second:
            second.settimeout(2.0)
            assert second.recv(100) == b""  # the line is taken: closed at once
        first.close()
        again = Line(emu.url)  # after the first client leaves, a new one is served
        assert again.ask("/1 0 get device.id\n").endswith("50081")
        again.close()


def test_pty_is_raw_and_start_stop_are_clean() -> None:
    emu = ZaberEmulator(transport="pty")
    with pytest.raises(RuntimeError):
        _ = emu.url
    emu.start()
    emu.start()  # idempotent
    assert emu.url.startswith("/dev/")
    conn = Line(emu.url)
    # no echo of the command: the first line back is the reply
    assert conn.ask("/1 0 get device.id\n") == "@01 0 OK IDLE WR 50081"
    conn.close()
    emu.stop()
    emu.stop()  # idempotent


def test_bad_configuration_rejected() -> None:
    with pytest.raises(ValueError):
        ZaberEmulator([DeviceSpec(1), DeviceSpec(1)])
    with pytest.raises(ValueError):
        ZaberEmulator(speedup=0)
    with pytest.raises(ValueError):
        ZaberEmulator(transport="usb")  # type: ignore[arg-type]
