"""Conformance against a Zaber implementation we did not write, and firmware 6/7 behaviour.

Zaber's official ``zaber-motion`` library (its protocol engine is Zaber's native
library, bundled in the wheel) drives our emulator over TCP on 127.0.0.1, for both
firmware profiles: device detection, the identity setting under the series' own name,
home, move, stop (which zaber-motion follows with ``warnings clear``), move again and
read the position; on firmware 7 also the per-move speed arguments our driver uses.

Then our driver against the firmware behaviours a lab meets on day one: a firmware-6
identity, the NI flag a stop leaves (kept by the device until ``warnings clear``), and
the stored settings (``comm.checksum``, ``maxspeed``, ``accel``) left as found.
"""

from __future__ import annotations

import time
from collections.abc import Iterator

import pytest
from zaber_support import axis_config

from drivers import errors
from drivers.sim.zaber_emulator import AxisSpec, DeviceSpec, ZaberEmulator
from drivers.zaber import ZaberAxisConfig, open_rail

zaber_motion = pytest.importorskip("zaber_motion")
from zaber_motion import BadCommandException, BadDataException  # noqa: E402
from zaber_motion.ascii import Connection  # noqa: E402

SPEEDUP = 20.0
#: Two devices: a one-axis rail and a two-axis XY controller.
CHAIN = (
    DeviceSpec(1, (AxisSpec(),), device_id=50081, serial=1111),
    DeviceSpec(2, (AxisSpec(), AxisSpec()), device_id=30222, serial=2222),
)
IDENTITY_SETTING = {6: "deviceid", 7: "device.id"}


@pytest.fixture(params=[6, 7], ids=["fw6", "fw7"])
def emu(request: pytest.FixtureRequest) -> Iterator[ZaberEmulator]:
    with ZaberEmulator(CHAIN, transport="tcp", speedup=SPEEDUP, firmware=request.param) as e:
        yield e


@pytest.fixture
def connection(emu: ZaberEmulator) -> Iterator[Connection]:
    address = emu.bound_address
    assert address is not None and address[0] == "127.0.0.1"
    with Connection.open_tcp(address[0], address[1]) as conn:
        yield conn


def wait_until(predicate: object, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():  # type: ignore[operator]
        assert time.monotonic() < deadline, "condition not reached in time"
        time.sleep(0.005)


# --------------------------------------------------------------------------- zaber-motion


def test_zaber_motion_detects_the_chain_and_reads_identity(
    emu: ZaberEmulator, connection: Connection
) -> None:
    firmware = emu.firmware(1)
    devices = connection.detect_devices(identify_devices=False)
    assert [d.device_address for d in devices] == [1, 2]
    own, other = IDENTITY_SETTING[firmware], IDENTITY_SETTING[13 - firmware]
    assert connection.generic_command(f"get {own}", device=1).data == "50081"
    assert connection.generic_command(f"get {own}", device=2).data == "30222"
    with pytest.raises(BadCommandException):
        connection.generic_command(f"get {other}", device=1)
    version = connection.generic_command("get version", device=1).data
    assert version.startswith(f"{firmware}.")
    # a device-level get of an axis setting answers one value per axis, in order
    positions = connection.generic_command("get pos", device=2).data.split()
    assert len(positions) == 2
    # zaber-motion sends checksums on every command; the emulator verified them all
    assert emu.stats.bad_checksum == 0
    assert all(":" in line for line in emu.received if line.startswith("/1 "))


def test_zaber_motion_home_move_stop_move_again(emu: ZaberEmulator, connection: Connection) -> None:
    axis = connection.get_device(1).get_axis(1)
    axis.home()
    assert axis.get_position() == 0
    axis.move_absolute(800000, wait_until_idle=False)  # 80 mm: 4 s / 20 at 20 mm/s
    wait_until(lambda: emu.snapshot(1, 1).position > 50000)
    axis.stop()
    stopped = axis.get_position()
    assert 50000 < stopped < 800000
    # zaber-motion clears the NI the stop raised; the emulator kept it until then
    sent = [line.split(" ", 3)[-1].split(":")[0] for line in emu.received if "/1 1 " in line]
    assert sent[sent.index("stop") + 1] == "warnings clear"
    assert "NI" not in emu.snapshot(1, 1).flags
    axis.move_absolute(200000)
    assert axis.get_position() == 200000
    assert emu.snapshot(1, 1).position == 200000
    assert axis.warnings.get_flags() == set()


def test_zaber_motion_move_with_speed_arguments(emu: ZaberEmulator, connection: Connection) -> None:
    axis = connection.get_device(1).get_axis(1)
    axis.home()
    if emu.firmware(1) == 6:
        with pytest.raises(BadDataException):  # no per-move speed before firmware 7.25
            axis.move_absolute(300000, velocity=50000, acceleration=100)
        assert emu.snapshot(1, 1).position == 0
    else:
        axis.move_absolute(300000, velocity=50000, acceleration=100)
        assert axis.get_position() == 300000


def test_our_driver_after_zaber_motion_left_the_chain(emu: ZaberEmulator) -> None:
    """The same emulator, now our driver: identity under the firmware's own name."""
    firmware = emu.firmware(1)
    address = emu.bound_address
    assert address is not None
    rail = open_rail(
        f"socket://127.0.0.1:{address[1]}",
        ZaberAxisConfig(name="rail", timeout_scale=1 / SPEEDUP, poll_interval_s=0.002),
    )
    try:
        identity = rail.identity()
        assert identity.model.startswith("device id 50081")
        assert identity.serial == "1111" and identity.firmware.startswith(f"{firmware}.")
        asked = [line for line in emu.received if " get " in line and "id" in line]
        assert any(f"get {IDENTITY_SETTING[firmware]}" in line for line in asked)
        assert not any(f"get {IDENTITY_SETTING[13 - firmware]}" in line for line in asked)
    finally:
        rail.close()


# --------------------------------------------------------------------------- our driver


@pytest.mark.parametrize("firmware", [6, 7])
def test_ni_after_stop_does_not_fail_the_next_good_move(firmware: int) -> None:
    with ZaberEmulator(transport="pty", speedup=SPEEDUP, firmware=firmware) as emu:
        rail = open_rail(emu.url, axis_config(speedup=SPEEDUP))
        try:
            rail.home()
            pending = rail.start_move_abs_mm(80.0)
            wait_until(lambda: emu.snapshot().position > 50000)
            rail.stop()
            with pytest.raises(errors.MoveInterrupted):
                rail.finish(pending)
            # the driver cleared NI after the stop, as the firmware requires
            commands = [line.split(" ", 3)[-1].split(":")[0] for line in emu.received]
            assert "warnings clear" in commands[commands.index("stop") :]
            assert "NI" not in emu.snapshot().flags
            assert rail.move_abs_mm(30.0) == pytest.approx(30.0)
            # an NI left by someone else (another program's stop) is stale, not ours
            emu.set_flags(1, 1, "NI")
            assert rail.move_abs_mm(40.0) == pytest.approx(40.0)
            assert "NI" not in emu.snapshot().flags
        finally:
            rail.close()


def test_interruption_during_our_move_is_still_reported() -> None:
    with ZaberEmulator(transport="pty", speedup=SPEEDUP) as emu:
        rail = open_rail(emu.url, axis_config(speedup=SPEEDUP))
        try:
            rail.home()
            pending = rail.start_move_abs_mm(80.0)
            wait_until(lambda: emu.snapshot().position > 50000)
            emu.stop_axis(1, 1)  # another program (or the stop button) stops the axis
            with pytest.raises(errors.MoveInterrupted):
                rail.finish(pending)
        finally:
            rail.close()


def test_firmware_6_identity_and_settings_left_as_found() -> None:
    spec = DeviceSpec(1, (AxisSpec(),), device_id=44123, serial=98765, firmware=6)
    with ZaberEmulator([spec], transport="pty", speedup=SPEEDUP) as emu:
        stored = (emu.setting(1, 1, "maxspeed"), emu.setting(1, 1, "accel"))
        assert not emu.device_checksum(1)
        rail = open_rail(emu.url, axis_config(speedup=SPEEDUP, speed_mm_s=5.0, accel_mm_s2=50.0))
        try:
            identity = rail.identity()
            assert identity.model == "device id 44123, peripheral id 70245"
            assert (identity.serial, identity.firmware) == ("98765", "6.32")
            assert emu.device_checksum(1)  # replies checksummed while we work
            rail.home()
            assert rail.move_abs_mm(12.5) == pytest.approx(12.5)
        finally:
            rail.close()
        assert not emu.device_checksum(1)
        assert (emu.setting(1, 1, "maxspeed"), emu.setting(1, 1, "accel")) == stored
        assert not any("device.id" in line for line in emu.received)


def test_firmware_7_connect_writes_no_setting() -> None:
    with ZaberEmulator(transport="pty", speedup=SPEEDUP, firmware=7, checksum=True) as emu:
        rail = open_rail(emu.url, axis_config(speedup=SPEEDUP, speed_mm_s=5.0, accel_mm_s2=50.0))
        try:
            rail.home()
            rail.move_abs_mm(10.0)
        finally:
            rail.close()
        assert not any(" set " in line for line in emu.received), list(emu.received)
        assert emu.device_checksum(1)
