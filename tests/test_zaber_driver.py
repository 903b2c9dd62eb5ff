"""The real Zaber driver against the emulator over a real pty and 127.0.0.1 TCP."""

from __future__ import annotations

import dataclasses
import threading
import time
from collections.abc import Callable, Iterator

import pytest
from zaber_support import axis_config

from drivers import errors
from drivers.axis import Axis, AxisLimits
from drivers.sim.zaber_emulator import AxisSpec, DeviceSpec, ZaberEmulator
from drivers.zaber import (
    XYStage,
    ZaberAxis,
    ZaberAxisConfig,
    ZaberPort,
    open_rail,
    open_xy_stage,
    protocol,
)

SPEEDUP = 50.0


def cfg(name: str = "rail", device: int = 1, axis: int = 1, **extra: object) -> ZaberAxisConfig:
    """Axis config whose motion timeouts match the emulator's speedup."""
    return axis_config(name, device, axis, speedup=SPEEDUP, **extra)


def wait_for(predicate: Callable[[], bool], timeout_s: float = 3.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        time.sleep(0.002)


@pytest.fixture(params=["pty", "tcp"])
def emu(request: pytest.FixtureRequest) -> Iterator[ZaberEmulator]:
    with ZaberEmulator(transport=request.param, speedup=SPEEDUP) as emulator:
        yield emulator


@pytest.fixture
def rail(emu: ZaberEmulator) -> Iterator[ZaberAxis]:
    axis = open_rail(emu.url, cfg(), reply_timeout_s=0.3)
    yield axis
    axis.close()


# --------------------------------------------------------------------------- normal operation


def test_connect_reads_identity_and_limits(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    assert isinstance(rail, Axis)
    ident = rail.identity()
    assert (ident.vendor, ident.serial, ident.firmware) == ("Zaber", "100001", "7.38")
    assert emu.url in ident.address and "device 1 axis 1" in ident.address
    assert rail.limits_mm() == AxisLimits(0.0, 100.0)
    assert not rail.is_homed()  # WR at power-up
    # every command the driver sent carried a valid checksum
    assert all(protocol.verify_checksum(line) for line in emu.received)


def test_refuses_to_move_until_homed(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    with pytest.raises(errors.NotReferenced) as info:
        rail.move_abs_mm(5.0)
    assert "rail" in str(info.value) and "home" in info.value.hint
    with pytest.raises(errors.NotReferenced):
        rail.position_mm()
    assert not any("move" in line for line in emu.received)


def test_home_move_and_read_back(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    rail.home()
    assert rail.is_homed() and rail.position_mm() == 0.0
    assert rail.move_abs_mm(42.5) == pytest.approx(42.5)
    assert emu.snapshot().position == 425000
    assert rail.position_mm() == pytest.approx(42.5)
    assert rail.move_abs_mm(0.00016) == pytest.approx(0.0002)  # rounded to a microstep
    assert rail.move_abs_mm(100.0) == pytest.approx(100.0)  # the limit itself is allowed
    assert not rail.is_busy()


def test_target_out_of_range_is_checked_before_sending(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    rail.home()
    sent = len(emu.received)
    for target in (-0.001, 100.001, float("nan"), float("inf")):
        with pytest.raises(errors.TargetOutOfRange):
            rail.move_abs_mm(target)
    assert len(emu.received) == sent


def test_soft_limits_and_speed_per_move_on_firmware_7(emu: ZaberEmulator) -> None:
    config = cfg(soft_limits_mm=(10.0, 60.0), speed_mm_s=5.0, accel_mm_s2=50.0)
    stored = (emu.setting(1, 1, "maxspeed"), emu.setting(1, 1, "accel"))
    axis = open_rail(emu.url, config)
    try:
        assert axis.limits_mm() == AxisLimits(10.0, 60.0)
        axis.home()
        with pytest.raises(errors.TargetOutOfRange):
            axis.move_abs_mm(61.0)
        assert axis.move_abs_mm(59.0) == pytest.approx(59.0)
        # 5 mm/s = 50000 microsteps/s -> 81920; 50 mm/s^2 -> 500000 microsteps/s^2 -> 82,
        # passed with the move (firmware >= 7.25); the stored settings are untouched
        assert (
            [c for c in emu.received if " move abs " in c][-1]
            .split(":")[0]
            .endswith("move abs 590000 81920 82")
        )
        assert (emu.setting(1, 1, "maxspeed"), emu.setting(1, 1, "accel")) == stored
        assert not any(" set maxspeed" in c or " set accel" in c for c in emu.received)
    finally:
        axis.close()


def test_speed_settings_written_and_restored_on_firmware_6() -> None:
    with ZaberEmulator(transport="pty", speedup=SPEEDUP, firmware=6) as emu:
        stored = (emu.setting(1, 1, "maxspeed"), emu.setting(1, 1, "accel"))
        axis = open_rail(emu.url, cfg(speed_mm_s=5.0, accel_mm_s2=50.0))
        try:
            assert axis.firmware == (6, 32)
            assert (emu.setting(1, 1, "maxspeed"), emu.setting(1, 1, "accel")) == (81920, 82)
            assert axis.changed_settings == {"maxspeed": stored[0], "accel": stored[1]}
            axis.home()
            assert axis.move_abs_mm(20.0) == pytest.approx(20.0)
            assert (
                [c for c in emu.received if " move abs " in c][-1]
                .split(":")[0]
                .endswith("move abs 200000")
            )
        finally:
            axis.close()
        assert (emu.setting(1, 1, "maxspeed"), emu.setting(1, 1, "accel")) == stored


def test_stop_from_another_thread_interrupts_the_move(emu: ZaberEmulator) -> None:
    rail = open_rail(emu.url, cfg(speed_mm_s=2.0))  # 99 mm take 1 s at speedup 50
    rail.home()
    outcome: list[BaseException] = []

    def mover() -> None:
        try:
            rail.move_abs_mm(99.0)
        except BaseException as exc:  # noqa: BLE001 - reported to the test thread
            outcome.append(exc)

    thread = threading.Thread(target=mover)
    thread.start()
    wait_for(lambda: emu.snapshot().busy and emu.snapshot().position > 50000)
    rail.stop()
    thread.join(timeout=5.0)
    assert len(outcome) == 1 and isinstance(outcome[0], errors.MoveInterrupted)
    stopped_at = rail.position_mm()  # position is still trusted after a stop
    assert 5.0 < stopped_at < 99.0
    assert stopped_at == pytest.approx(emu.snapshot().position * 1e-4)
    assert rail.move_abs_mm(20.0) == pytest.approx(20.0)
    rail.close()


def test_estop_halts_at_once(emu: ZaberEmulator) -> None:
    rail = open_rail(emu.url, cfg(speed_mm_s=2.0))
    rail.home()
    pending = rail.start_move_abs_mm(90.0)
    wait_for(lambda: emu.snapshot().position > 50000)
    rail.estop()
    assert not emu.snapshot().busy
    with pytest.raises(errors.MoveInterrupted):
        rail.finish(pending)
    rail.close()


def test_alerts_on_the_line_are_ignored(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    rail.port.request(1, 0, "set comm.alert 1")
    rail.home()
    rail.move_abs_mm(3.0)
    assert rail.move_abs_mm(4.0) == pytest.approx(4.0)
    wait_for(lambda: emu.stats.alerts >= 3)
    rail.position_mm()  # reads past the alerts
    assert rail.port.stats.alerts >= 2
    assert all(isinstance(a, protocol.Alert) for a in rail.port.alerts)


def test_shared_port_is_thread_safe(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    rail.home()
    rail.move_abs_mm(12.5)
    results: list[float] = []
    failures: list[BaseException] = []

    def poll() -> None:
        try:
            for _ in range(100):
                results.append(rail.position_mm())
        except BaseException as exc:  # noqa: BLE001
            failures.append(exc)

    threads = [threading.Thread(target=poll) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(timeout=10.0)
    assert failures == [] and results == [12.5] * 300


def test_config_validation_and_from_mapping() -> None:
    with pytest.raises(ValueError):
        ZaberAxisConfig(device=0)
    with pytest.raises(ValueError):
        ZaberAxisConfig(axis=10)
    with pytest.raises(ValueError):
        ZaberAxisConfig(microstep_um=0)
    with pytest.raises(ValueError):
        ZaberAxisConfig(soft_limits_mm=(5.0, 1.0))
    loaded = ZaberAxisConfig.from_mapping(
        {"name": "rail", "device": 2, "microstep_um": 0.047625, "soft_limits_mm": [0, 90]}
    )
    assert loaded.device == 2 and loaded.soft_limits_mm == (0.0, 90.0)
    with pytest.raises(ValueError, match="unknown"):
        ZaberAxisConfig.from_mapping({"devcie": 2})


def test_axis_must_be_connected() -> None:
    axis = ZaberAxis(ZaberPort("/dev/null-does-not-exist"), cfg())
    with pytest.raises(errors.DeviceError, match="not connected"):
        axis.move_abs_mm(1.0)


# --------------------------------------------------------------------------- XY stage


def _xy_configs(topology: str) -> tuple[list[DeviceSpec], ZaberAxisConfig, ZaberAxisConfig]:
    spec = AxisSpec(microstep_um=0.1, travel_mm=50.0)
    # slow enough (5 mm/s, i.e. 0.1 mm/ms at speedup 50) to see both axes move at once
    x, y = cfg("stage x", 1, 1, speed_mm_s=5.0), cfg("stage y", 1, 2, speed_mm_s=5.0)
    if topology == "one device, two axes":
        return [DeviceSpec(1, (spec, spec))], x, y
    y = cfg("stage y", 2, 1, speed_mm_s=5.0)
    return [DeviceSpec(1, (spec,)), DeviceSpec(2, (spec,), serial=2)], x, y


@pytest.mark.parametrize("topology", ["one device, two axes", "two devices, one chain"])
@pytest.mark.parametrize("transport", ["pty", "tcp"])
def test_xy_stage(topology: str, transport: str) -> None:
    devices, x_cfg, y_cfg = _xy_configs(topology)
    with ZaberEmulator(devices, transport=transport, speedup=SPEEDUP) as emu:  # type: ignore[arg-type]
        with open_xy_stage(emu.url, x_cfg, y_cfg) as xy:
            assert not xy.is_homed()
            with pytest.raises(errors.NotReferenced):
                xy.move_xy_mm(1.0, 1.0)
            xy.home()
            assert xy.is_homed() and xy.position_xy_mm() == (0.0, 0.0)
            assert xy.move_xy_mm(30.0, 12.5) == pytest.approx((30.0, 12.5))
            assert xy.move_xy_mm(10.0, 40.0) == pytest.approx((10.0, 40.0))
            assert xy.position_xy_mm() == pytest.approx((10.0, 40.0))
            with pytest.raises(errors.TargetOutOfRange):
                xy.move_xy_mm(10.0, 50.5)
            assert emu.snapshot(1, 1).position == 100000  # nothing moved


def test_xy_axes_move_at_the_same_time() -> None:
    devices, x_cfg, y_cfg = _xy_configs("one device, two axes")
    slow_x = dataclasses.replace(x_cfg, speed_mm_s=0.5)
    slow_y = dataclasses.replace(y_cfg, speed_mm_s=0.5)
    with ZaberEmulator(devices, speedup=SPEEDUP) as emu:
        with open_xy_stage(emu.url, slow_x, slow_y) as xy:
            xy.home()  # from 10 mm: 0.4 s
            # 10 mm at 0.5 mm/s: 0.4 s; y is started while x is still far from done
            start_x = xy.x.start_move_abs_mm(10.0)
            start_y = xy.y.start_move_abs_mm(10.0)
            assert emu.snapshot(1, 1).busy and emu.snapshot(1, 2).busy
            assert (xy.x.finish(start_x), xy.y.finish(start_y)) == pytest.approx((10.0, 10.0))


def test_xy_refuses_before_moving_anything_if_one_axis_is_not_homed() -> None:
    devices, x_cfg, y_cfg = _xy_configs("two devices, one chain")
    with ZaberEmulator(devices, speedup=SPEEDUP) as emu:
        with open_xy_stage(emu.url, x_cfg, y_cfg) as xy:
            xy.x.home()
            before = len(emu.received)
            with pytest.raises(errors.NotReferenced, match="stage y"):
                xy.move_xy_mm(5.0, 5.0)
            assert not any("move" in line for line in list(emu.received)[before:])


def test_home_refuses_while_moving(emu: ZaberEmulator) -> None:
    rail = open_rail(emu.url, cfg(speed_mm_s=5.0))
    try:
        rail.home()
        pending = rail.start_move_abs_mm(90.0)
        with pytest.raises(errors.DeviceBusy):
            rail.home()
        assert rail.finish(pending) == pytest.approx(90.0)
    finally:
        rail.close()


def test_xy_failure_on_one_axis_stops_the_other() -> None:
    devices, x_cfg, _ = _xy_configs("one device, two axes")
    y_cfg = cfg("stage y", 1, 2, speed_mm_s=1.0)  # y needs 0.8 s: still moving when x stalls
    with ZaberEmulator(devices, speedup=SPEEDUP) as emu:
        with open_xy_stage(emu.url, x_cfg, y_cfg) as xy:
            xy.home()
            emu.stall_next_move(1, 1, at_fraction=0.2)
            with pytest.raises(errors.StageStalled):
                xy.move_xy_mm(40.0, 40.0)
            y = emu.snapshot(1, 2)
            assert not y.busy and y.position < 400000  # y was stopped short of its target
            assert not xy.x.is_homed() and xy.y.is_homed()


def test_xy_rejects_the_same_axis_twice() -> None:
    port = ZaberPort("/dev/null")
    with pytest.raises(ValueError):
        XYStage(ZaberAxis(port, cfg("x")), ZaberAxis(port, cfg("y")))


# --------------------------------------------------------------------------- bad input


def test_port_that_does_not_exist() -> None:
    with pytest.raises(errors.PortUnavailable) as info:
        open_rail("/dev/ttyUSB-lfcal-nonexistent", cfg())
    message = str(info.value)
    assert "/dev/ttyUSB-lfcal-nonexistent" in message and "rail" in message
    assert "plugged" in info.value.hint


def test_tcp_port_with_nothing_listening() -> None:
    with ZaberEmulator(transport="tcp") as emu:
        url = emu.url
    with pytest.raises(errors.PortUnavailable) as info:
        open_rail(url, cfg())
    assert url in str(info.value)


def test_port_is_exclusive() -> None:
    with ZaberEmulator(transport="pty", speedup=SPEEDUP) as emu:
        first = open_rail(emu.url, cfg())
        try:
            with pytest.raises(errors.PortUnavailable) as info:
                open_rail(emu.url, cfg(name="second"))
            assert "another program" in info.value.hint
        finally:
            first.close()
        open_rail(emu.url, cfg()).close()  # free again once closed


def test_wrong_device_number_is_no_reply() -> None:
    with ZaberEmulator(speedup=SPEEDUP) as emu:
        with pytest.raises(errors.NoReply) as info:
            open_rail(emu.url, cfg(device=7), reply_timeout_s=0.1)
        assert "device 7" in str(info.value) and "device number" in info.value.hint


def test_wrong_axis_number_is_rejected_with_a_config_hint() -> None:
    with ZaberEmulator(speedup=SPEEDUP) as emu:
        with pytest.raises(errors.CommandRejected) as info:
            open_rail(emu.url, cfg(axis=2))
        assert info.value.reason == "BADAXIS" and "configuration" in info.value.hint
