"""One test per fault kind: the real driver against the emulator over a pty and TCP.

Each fault ends in the right typed error or in a documented recovery -- and
never in a wrong position being reported.
"""

from __future__ import annotations

import socket
import threading
import time
from collections.abc import Callable, Iterator

import pytest

from drivers import errors
from drivers.sim.zaber_emulator import ZaberEmulator
from drivers.zaber import ZaberAxis, ZaberAxisConfig, open_rail

SPEEDUP = 50.0
REPLY_TIMEOUT_S = 0.15
UM = 1e-3  # mm per um


def cfg(**extra: object) -> ZaberAxisConfig:
    values: dict[str, object] = {
        "name": "rail",
        "microstep_um": 0.1,
        "tolerance_um": 0.5,
        "timeout_scale": 1.0 / SPEEDUP,
        "timeout_margin_s": 0.3,
        "poll_interval_s": 0.002,
    }
    values.update(extra)
    return ZaberAxisConfig(**values)  # type: ignore[arg-type]


def wait_for(predicate: Callable[[], bool], timeout_s: float = 3.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        if time.monotonic() > deadline:
            raise AssertionError("condition not reached in time")
        time.sleep(0.002)


def sent(emu: ZaberEmulator, text: str) -> int:
    """How many commands containing ``text`` the emulator received."""
    return sum(text in line for line in emu.received)


@pytest.fixture(params=["pty", "tcp"])
def emu(request: pytest.FixtureRequest) -> Iterator[ZaberEmulator]:
    with ZaberEmulator(transport=request.param, speedup=SPEEDUP) as emulator:
        yield emulator


@pytest.fixture
def make_rail(emu: ZaberEmulator) -> Iterator[Callable[..., ZaberAxis]]:
    """Factory of connected, homed rails at 7 mm (config overrides as keywords)."""
    made: list[ZaberAxis] = []

    def make(**extra: object) -> ZaberAxis:
        axis = open_rail(emu.url, cfg(**extra), reply_timeout_s=REPLY_TIMEOUT_S, retries=2)
        made.append(axis)
        axis.home()
        axis.move_abs_mm(7.0)
        return axis

    yield make
    for axis in made:
        axis.close()


@pytest.fixture
def rail(make_rail: Callable[..., ZaberAxis]) -> ZaberAxis:
    return make_rail()


# --------------------------------------------------------------------------- dropped reply


def test_dropped_reply_to_a_query_is_retried(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    emu.drop_replies(1)
    assert rail.position_mm() == pytest.approx(7.0)
    assert rail.port.stats.retries >= 1


def test_dropped_reply_to_a_move_is_retried_and_lands_right(
    emu: ZaberEmulator, make_rail: Callable[..., ZaberAxis]
) -> None:
    # 0.5 mm/s: the 23 mm take 0.92 s, so the repeat (after 0.15 s) arrives mid-move
    rail = make_rail(speed_mm_s=0.5)
    emu.drop_replies(1, command="move abs")
    # the move is re-sent (idempotent target); the repeat interrupts the first (NI),
    # which the driver expects because it re-sent the command itself
    assert rail.move_abs_mm(30.0) == pytest.approx(30.0)
    assert sent(emu, "move abs 300000") >= 2
    assert "NI" in emu.snapshot().flags  # the interruption really happened
    assert emu.snapshot().position == 300000


def test_lost_reply_to_a_non_idempotent_command_is_never_resent(
    emu: ZaberEmulator, rail: ZaberAxis
) -> None:
    emu.drop_replies(1, command="move rel")
    with pytest.raises(errors.NoReply) as info:
        rail.port.request(1, 1, "move rel 1000", label="rail")
    assert "may or may not have been executed" in str(info.value)
    assert sent(emu, "move rel") == 1


# --------------------------------------------------------------------------- garbled byte


def test_garbled_reply_is_discarded_and_retried(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    emu.garble_replies(1, command="get pos")
    assert rail.move_abs_mm(12.0) == pytest.approx(12.0)
    assert rail.port.stats.garbled == 1 and rail.port.stats.retries >= 1


def test_device_answering_only_garbage(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    emu.garble_replies(None)
    with pytest.raises(errors.GarbledReply) as info:
        rail.position_mm()
    assert "rail" in str(info.value) and "baud rate" in info.value.hint
    assert rail.port.stats.garbled == 3  # every attempt


def test_something_else_answering_on_the_port() -> None:
    """A TCP peer that is not a Zaber device: one clear error naming port and hint."""
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    port = server.getsockname()[1]

    def chatter() -> None:
        conn, _ = server.accept()
        with conn:
            conn.settimeout(2.0)
            try:
                while conn.recv(100):
                    conn.sendall(b"HELLO from a modem\r\nOK\r\n")
            except OSError:
                pass

    thread = threading.Thread(target=chatter, daemon=True)
    thread.start()
    try:
        with pytest.raises(errors.GarbledReply) as info:
            open_rail(f"socket://127.0.0.1:{port}", cfg(), reply_timeout_s=0.1)
        assert f"127.0.0.1:{port}" in str(info.value) or "rail" in str(info.value)
    finally:
        server.close()
        thread.join(timeout=3.0)


# --------------------------------------------------------------------------- late reply


def test_late_reply_is_discarded_as_stale(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    emu.delay_replies(REPLY_TIMEOUT_S * 3, 1, command="get pos")
    assert rail.position_mm() == pytest.approx(7.0)  # answered by the retry
    wait_for(lambda: emu.stats.delayed_sent == 1)  # the late reply is now on the line
    assert rail.move_abs_mm(8.0) == pytest.approx(8.0)  # not confused by it
    assert rail.port.stats.stale >= 1


# --------------------------------------------------------------------------- dead device


def test_dead_device(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    emu.set_dead(1)
    with pytest.raises(errors.NoReply) as info:
        rail.move_abs_mm(20.0)
    assert "device 1" in str(info.value) and "powered" in info.value.hint
    assert "3 attempts" in str(info.value)
    assert emu.snapshot().position == 70000  # nothing moved
    emu.set_dead(1, False)
    assert rail.move_abs_mm(20.0) == pytest.approx(20.0)


def test_dead_device_at_connect() -> None:
    with ZaberEmulator(speedup=SPEEDUP) as emu:
        emu.set_dead(1)
        with pytest.raises(errors.NoReply):
            open_rail(emu.url, cfg(), reply_timeout_s=0.05)


# --------------------------------------------------------------------------- stuck BUSY


def test_stuck_busy_times_out_and_stops(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    emu.stick_next_move(1, 1)
    start = time.monotonic()
    with pytest.raises(errors.MotionTimeout) as info:
        rail.move_abs_mm(57.0)  # 50 mm: 2.6 s / 50 x 1.5 + 0.3 s margin = 0.38 s
    assert time.monotonic() - start < 5.0  # derived timeout, not the 300 s test limit
    assert "stop sent" in str(info.value)
    assert sent(emu, " stop") >= 1 and not emu.snapshot().busy
    # the position is known (the device reported it throughout): no re-home needed
    assert rail.is_homed()
    assert rail.position_mm() == pytest.approx(emu.snapshot().position * 0.1 * UM)
    assert rail.move_abs_mm(10.0) == pytest.approx(10.0)


# --------------------------------------------------------------------------- stall, limit


def test_stall(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    emu.stall_next_move(1, 1, at_fraction=0.5)
    with pytest.raises(errors.StageStalled) as info:
        rail.move_abs_mm(47.0)
    assert "FS" in info.value.flags and "rail" in str(info.value)
    assert emu.snapshot().flags == frozenset()  # reported once, then cleared on the device
    # the position is no longer trusted: no position, no move, until homed
    assert not rail.is_homed()
    with pytest.raises(errors.NotReferenced):
        rail.position_mm()
    with pytest.raises(errors.NotReferenced):
        rail.move_abs_mm(10.0)
    rail.home()
    assert rail.move_abs_mm(10.0) == pytest.approx(10.0)


@pytest.mark.parametrize("flag", ["WL", "FE"])
def test_limit_hit_mid_move(emu: ZaberEmulator, rail: ZaberAxis, flag: str) -> None:
    emu.limit_on_next_move(1, 1, at_fraction=0.3, flag=flag)
    with pytest.raises(errors.LimitHit) as info:
        rail.move_abs_mm(90.0)
    assert flag in info.value.flags
    assert not rail.is_homed()
    rail.home()
    assert rail.move_abs_mm(90.0) == pytest.approx(90.0)


# --------------------------------------------------------------------------- position drift


def test_drift_beyond_tolerance_is_a_position_mismatch(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    emu.drift_next_move(1, 1, microsteps=50)  # 5 um, tolerance 0.5 um
    with pytest.raises(errors.PositionMismatch) as info:
        rail.move_abs_mm(20.0)
    assert info.value.target_mm == pytest.approx(20.0)
    assert info.value.actual_mm == pytest.approx(20.005)
    assert info.value.actual_mm == pytest.approx(emu.snapshot().position * 0.1 * UM)
    assert rail.position_mm() == pytest.approx(20.005)  # the truth, not the target


def test_drift_within_tolerance_returns_the_read_back(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    emu.drift_next_move(1, 1, microsteps=3)  # 0.3 um
    assert rail.move_abs_mm(20.0) == pytest.approx(20.0003)


# --------------------------------------------------------------------------- disconnect


def test_disconnect_mid_move(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    emu.disconnect_on_next_move(1, 1, at_fraction=0.4)
    with pytest.raises(errors.ConnectionLost) as info:
        rail.move_abs_mm(80.0)
    assert isinstance(info.value, errors.PortUnavailable)
    assert emu.url in str(info.value) or "rail" in str(info.value)
    assert not rail.port.is_open
    with pytest.raises(errors.ConnectionLost, match="connection was lost"):
        rail.position_mm()  # no silent use of a dead port


def test_reconnect_after_disconnect_over_tcp() -> None:
    with ZaberEmulator(transport="tcp", speedup=SPEEDUP) as emu:
        axis = open_rail(emu.url, cfg(), reply_timeout_s=REPLY_TIMEOUT_S)
        axis.home()
        emu.disconnect_on_next_move(1, 1, at_fraction=0.4)
        with pytest.raises(errors.ConnectionLost):
            axis.move_abs_mm(80.0)
        wait_for(lambda: not emu.snapshot().busy)
        again = open_rail(emu.url, cfg(), reply_timeout_s=REPLY_TIMEOUT_S)
        try:
            # the device kept power: reference kept, and the position is what it reports
            assert again.is_homed()
            assert again.position_mm() == pytest.approx(80.0)
        finally:
            again.close()


# --------------------------------------------------------------------------- power cycle


def test_power_cycle_mid_move(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    emu.power_cycle_on_next_move(1, 1, at_fraction=0.5, off_s=0.05)
    with pytest.raises(errors.NotReferenced) as info:
        rail.move_abs_mm(80.0)
    assert "WR" in info.value.flags
    assert not rail.is_homed()
    with pytest.raises(errors.NotReferenced):
        rail.position_mm()
    rail.home()
    assert rail.move_abs_mm(80.0) == pytest.approx(80.0)


def test_power_cycle_while_idle_blocks_the_next_move(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    emu.power_cycle(1, off_s=0.05)
    wait_for(lambda: emu.is_powered(1))
    moves = sent(emu, "move abs")
    with pytest.raises(errors.NotReferenced):
        rail.move_abs_mm(15.0)
    assert sent(emu, "move abs") == moves  # refused before sending anything
    assert not rail.is_homed()


def test_home_recovers_from_a_fault_left_by_someone_else(
    emu: ZaberEmulator, rail: ZaberAxis
) -> None:
    emu.stall_next_move(1, 1, at_fraction=0.5)
    rail.port.request(1, 1, "move abs 200000")  # another client moves and stalls the axis
    wait_for(lambda: "FS" in emu.snapshot().flags)
    with pytest.raises(errors.StageStalled):
        rail.move_abs_mm(10.0)  # the stale fault is reported before moving
    rail.home()  # homing clears stale faults first, then succeeds
    assert rail.is_homed() and rail.move_abs_mm(10.0) == pytest.approx(10.0)


def test_lost_reference_hidden_behind_a_higher_warning(emu: ZaberEmulator, rail: ZaberAxis) -> None:
    """Replies show only the top flag: WT (temperature) outranks WR and must not hide it."""
    emu.set_flags(1, 1, "WT")
    assert rail.is_homed() and rail.position_mm() == pytest.approx(7.0)  # WT alone is harmless
    emu.power_cycle(1, off_s=0.01)
    wait_for(lambda: emu.is_powered(1))
    emu.set_flags(1, 1, "WT")
    assert emu.snapshot().flags == {"WT", "WR"}
    assert not rail.is_homed()
    with pytest.raises(errors.NotReferenced):
        rail.position_mm()
    with pytest.raises(errors.NotReferenced):
        rail.move_abs_mm(10.0)
