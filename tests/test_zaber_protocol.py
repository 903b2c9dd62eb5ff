"""Zaber ASCII protocol bytes against the spec: checksums, formatting, parsing, flags."""

from __future__ import annotations

import ast
import pathlib
import pickle

import pytest

from drivers import errors
from drivers.zaber import protocol
from drivers.zaber.protocol import Alert, Command, Info, Reply

# --------------------------------------------------------------------------- checksum


@pytest.mark.parametrize(
    ("line", "expected"),
    [
        # test vectors from Zaber's own zaber.serial library tests
        ("@01 0 OK IDLE -- 0", 0x8D),
        ("@01 0 OK IDLE -- 7z", 0x0C),
        ("@1 3 9 OK IDLE -- 0", 0x61),
    ],
)
def test_checksum_matches_zaber_vectors(line: str, expected: int) -> None:
    # the start character is excluded from the sum
    assert protocol.checksum(line[1:]) == expected
    assert protocol.with_checksum(line) == f"{line}:{expected:02X}"
    assert protocol.verify_checksum(f"{line}:{expected:02X}")


def test_checksum_is_twos_complement_of_byte_sum() -> None:
    body = "1 1 12 move abs 10000"
    cc = protocol.checksum(body)
    assert (sum(body.encode()) + cc) % 256 == 0
    assert protocol.checksum(body.encode()) == cc
    assert protocol.checksum("") == 0


def test_verify_checksum_rejects_wrong_and_missing() -> None:
    assert not protocol.verify_checksum("@01 0 OK IDLE -- 0:8E")
    assert not protocol.verify_checksum("@01 0 OK IDLE -- 0")
    assert protocol.split_checksum("@01 0 OK IDLE -- 0") == ("@01 0 OK IDLE -- 0", None)
    assert protocol.split_checksum("@01 0 OK IDLE -- 0:8d") == ("@01 0 OK IDLE -- 0", 0x8D)


# --------------------------------------------------------------------------- commands


def test_format_command_bytes() -> None:
    line = protocol.format_command(1, 1, "move abs 10000", message_id=12)
    body = "1 1 12 move abs 10000"
    assert line == f"/{body}:{protocol.checksum(body):02X}\n".encode()
    assert protocol.format_command(2, 0, "get pos", checksum=False) == b"/2 0 get pos\n"
    assert protocol.format_command(1, 1, "", checksum=False) == b"/1 1\n"
    # whitespace is normalized to single spaces
    assert protocol.format_command(1, 1, "  get   pos ", checksum=False) == b"/1 1 get pos\n"
    assert Command(3, 2, 7, "home").encode(checksum=False) == b"/3 2 7 home\n"


@pytest.mark.parametrize(
    ("device", "axis", "message_id", "text"),
    [
        (100, 0, None, "get pos"),
        (-1, 0, None, "get pos"),
        (1, 10, None, "get pos"),
        (1, 1, 100, "get pos"),
        (1, 1, None, "get pos:12"),
        (1, 1, None, "get\npos"),
        (1, 1, None, "set a/b 1"),
    ],
)
def test_format_command_rejects_bad_input(
    device: int, axis: int, message_id: int | None, text: str
) -> None:
    with pytest.raises(ValueError):
        protocol.format_command(device, axis, text, message_id=message_id)


def test_parse_command_optional_fields_and_terminators() -> None:
    assert protocol.parse_command("/get pos\r\n") == (Command(0, 0, None, "get pos"), False)
    assert protocol.parse_command(b"/1 home\n") == (Command(1, 0, None, "home"), False)
    assert protocol.parse_command("/1 2 move rel -5") == (Command(1, 2, None, "move rel -5"), False)
    assert protocol.parse_command("/1 2 -- get pos") == (Command(1, 2, None, "get pos"), False)
    assert protocol.parse_command("/1 1") == (Command(1, 1, None, ""), False)
    wire = protocol.format_command(4, 1, "move abs 5", message_id=42)
    assert protocol.parse_command(wire) == (Command(4, 1, 42, "move abs 5"), True)
    # leading noise before the '/' is ignored, as by a device
    assert protocol.parse_command("xx/1 1 get pos")[0] == Command(1, 1, None, "get pos")


def test_parse_command_errors() -> None:
    wire = protocol.format_command(1, 1, "get pos", message_id=3).decode()
    corrupted = wire.replace("pos", "poz")
    with pytest.raises(errors.ChecksumError):
        protocol.parse_command(corrupted)
    with pytest.raises(protocol.CommandSyntaxError) as info:
        protocol.parse_command("/1 2 123 get pos")
    assert (info.value.reason, info.value.device, info.value.axis) == ("BADMESSAGEID", 1, 2)
    with pytest.raises(protocol.CommandSyntaxError):
        protocol.parse_command("get pos")


@pytest.mark.parametrize(
    ("text", "idempotent"),
    [
        ("get pos", True),
        ("set maxspeed 100", True),
        ("home", True),
        ("move abs 1000", True),
        ("move max", True),
        ("stop", True),
        ("estop", True),
        ("", True),
        ("warnings", True),
        ("move rel 1000", False),
        ("move vel 1000", False),
        ("warnings clear", False),
        ("system reset", False),
    ],
)
def test_retry_policy(text: str, idempotent: bool) -> None:
    assert protocol.is_idempotent(text) is idempotent


# --------------------------------------------------------------------------- replies


def test_parse_reply_fields() -> None:
    reply = protocol.parse_message("@04 2 12 OK BUSY -- 123\r\n")
    assert reply == Reply(4, 2, 12, False, True, "--", "123", False)
    assert (reply.flag, reply.status, reply.data_int()) == ("OK", "BUSY", 123)
    no_id = protocol.parse_message("@01 0 OK IDLE WR 0")
    assert isinstance(no_id, Reply) and no_id.message_id is None and no_id.warning == "WR"
    rejected = protocol.parse_message("@01 1 3 RJ IDLE -- BADDATA")
    assert isinstance(rejected, Reply) and rejected.rejected
    assert rejected.reject_reason == "BADDATA"
    multi = protocol.parse_message("@01 0 OK IDLE -- 10 -20")
    assert isinstance(multi, Reply) and multi.data_ints() == [10, -20]


def test_parse_reply_with_checksum_roundtrip() -> None:
    wire = protocol.format_reply(1, 1, message_id=5, busy=True, warning="NI", data="42")
    assert wire.endswith(b"\r\n")
    reply = protocol.parse_message(wire, require_checksum=True)
    assert reply == Reply(1, 1, 5, False, True, "NI", "42", True)
    assert protocol.format_reply(1, 0, checksum=False) == b"@01 0 OK IDLE -- 0\r\n"
    assert protocol.format_reply(1, 0) == b"@01 0 OK IDLE -- 0:8D\r\n"


def test_parse_info_and_alert() -> None:
    info = protocol.parse_message("#01 0 12 Visit www.zaber.com")
    assert info == Info(1, 0, 12, "Visit www.zaber.com")
    alert = protocol.parse_message("!01 1 IDLE --")
    assert alert == Alert(1, 1, False, "--", "")
    wire = protocol.format_alert(2, 1, warning="FS")
    assert protocol.parse_message(wire, require_checksum=True) == Alert(2, 1, False, "FS", "")


@pytest.mark.parametrize(
    "line",
    [
        "",
        "hello",
        "%33 A OK I AM A BANANA",
        "@01 0 OK IDLE --",  # no data field
        "@01 0 OK IDLE -- ",
        "@0x 0 OK IDLE -- 0",
        "@01 0 OK SLEEPY -- 0",
        "@01 0 MAYBE IDLE -- 0",
        "@01 0 OK IDLE ?? 0",
        "@01 0 OK IDLE -- 0\x00",
        "!01 1 SOMETIMES --",
        "@01",
    ],
)
def test_parse_garbled(line: str) -> None:
    with pytest.raises(errors.GarbledReply):
        protocol.parse_message(line)


def test_parse_checksum_errors() -> None:
    with pytest.raises(errors.ChecksumError):
        protocol.parse_message("@01 0 OK IDLE -- 0:8E")
    with pytest.raises(errors.ChecksumError):
        protocol.parse_message("@01 0 OK IDLE -- 0", require_checksum=True)
    with pytest.raises(errors.GarbledReply):
        protocol.parse_message(b"@01 0 OK IDLE -- \xff0")
    # ChecksumError is a GarbledReply: callers can catch either
    assert issubclass(errors.ChecksumError, errors.GarbledReply)


def test_data_int_on_non_numeric_is_garbled() -> None:
    reply = protocol.parse_message("@01 0 OK IDLE -- abc")
    assert isinstance(reply, Reply)
    with pytest.raises(errors.GarbledReply):
        reply.data_int()
    with pytest.raises(errors.GarbledReply):
        reply.data_ints()


# --------------------------------------------------------------------------- flags


def test_warning_precedence_and_parsing() -> None:
    assert protocol.highest_warning([]) == "--"
    assert protocol.highest_warning(["NI", "WR", "FS"]) == "FS"
    assert protocol.highest_warning(["NI", "WR"]) == "WR"
    assert protocol.parse_warnings_data("02 FS WR") == frozenset({"FS", "WR"})
    assert protocol.parse_warnings_data("00") == frozenset()
    with pytest.raises(errors.GarbledReply):
        protocol.parse_warnings_data("03 FS")
    assert "stalled" in protocol.describe_flags(["FS"])


@pytest.mark.parametrize(
    ("flags", "expected"),
    [
        ({"FS"}, errors.StageStalled),
        ({"FS", "WR", "NI"}, errors.StageStalled),
        ({"FE"}, errors.LimitHit),
        ({"WL"}, errors.LimitHit),
        ({"FQ"}, errors.DeviceFault),
        ({"FD"}, errors.DeviceFault),
        ({"WR"}, errors.NotReferenced),
        ({"WR", "NI"}, errors.NotReferenced),
        ({"NI"}, errors.MoveInterrupted),
    ],
)
def test_flags_map_to_typed_errors(flags: set[str], expected: type[errors.DeviceError]) -> None:
    error = protocol.error_for_flags(flags, device="rail", context="moving")
    assert type(error) is expected
    assert isinstance(error, errors.MotionError) and error.flags == frozenset(flags)
    assert "rail" in str(error) and "moving" in str(error)


def test_harmless_and_ignored_flags() -> None:
    assert protocol.error_for_flags(set(), device="d", context="c") is None
    assert protocol.error_for_flags({"WT", "WV", "NC", "NU"}, device="d", context="c") is None
    assert protocol.error_for_flags({"NI"}, device="d", context="c", ignore={"NI"}) is None


def test_rejection_error() -> None:
    reply = protocol.parse_message("@01 1 RJ IDLE -- BADAXIS")
    assert isinstance(reply, Reply)
    error = protocol.rejection_error(reply, command="get pos", device="rail")
    assert isinstance(error, errors.CommandRejected)
    assert (error.reason, error.command) == ("BADAXIS", "get pos")
    assert "axis number" in str(error)
    assert set(protocol.REJECT_REASONS) >= {"BADDATA", "BADCOMMAND", "BADAXIS", "DEVICEONLY"}


# --------------------------------------------------------------------------- units


def test_speed_and_accel_units() -> None:
    # maxspeed = microsteps/s x 1.6384; accel = microsteps/s^2 x 1.6384 / 10000
    assert protocol.speed_to_data(10000) == 16384
    assert protocol.data_to_speed(16384) == pytest.approx(10000)
    assert protocol.accel_to_data(1_000_000) == 164
    assert protocol.data_to_accel(protocol.accel_to_data(2e6)) == pytest.approx(2e6, rel=1e-3)


def test_move_duration() -> None:
    # trapezoid: 10 units at 1 unit/s, accel 1 unit/s^2 -> 10 + 1 s
    assert protocol.move_duration_s(10, 1, 1) == pytest.approx(11.0)
    # triangle: 1 unit, v 10, a 1 -> 2 * sqrt(1)
    assert protocol.move_duration_s(-1, 10, 1) == pytest.approx(2.0)
    assert protocol.move_duration_s(0, 1, 1) == 0.0
    assert protocol.move_duration_s(5, 1, 0) == pytest.approx(5.0)


# --------------------------------------------------------------------------- errors


def test_device_error_is_generic_and_subclassable() -> None:
    class CameraError(errors.DeviceError):
        default_hint = "the camera cable"

    error = CameraError("no frames", device="cam0")
    assert str(error) == "cam0: no frames -- check: the camera cable"
    assert isinstance(error, errors.DeviceError)
    plain = errors.NoReply("no reply", device="rail", hint="the power")
    assert str(plain) == "rail: no reply -- check: the power"
    assert isinstance(errors.ConnectionLost("x"), errors.PortUnavailable)
    assert isinstance(errors.TargetOutOfRange("x"), ValueError)
    mismatch = errors.PositionMismatch("off", target_mm=1.0, actual_mm=1.1, tolerance_mm=0.001)
    assert (mismatch.target_mm, mismatch.actual_mm) == (1.0, 1.1)


def test_errors_survive_pickling_with_their_attributes() -> None:
    rejected = errors.CommandRejected("no", reason="BADDATA", command="move abs 5", device="rail")
    copy = pickle.loads(pickle.dumps(rejected))
    assert type(copy) is errors.CommandRejected and str(copy) == str(rejected)
    assert (copy.reason, copy.command, copy.device) == ("BADDATA", "move abs 5", "rail")
    stalled = errors.StageStalled("stall", device="rail", flags={"FS"})
    assert pickle.loads(pickle.dumps(stalled)).flags == frozenset({"FS"})
    off = errors.PositionMismatch("off", target_mm=1.0, actual_mm=1.1, tolerance_mm=0.001)
    assert pickle.loads(pickle.dumps(off)).actual_mm == 1.1


def test_production_code_never_imports_sim() -> None:
    root = pathlib.Path(__file__).resolve().parents[1]
    offenders = []
    for package in ("drivers", "station", "calibration", "web"):
        for path in (root / package).rglob("*.py"):
            if "sim" in path.relative_to(root).parts[:2]:
                continue
            tree = ast.parse(path.read_text(encoding="utf-8"))
            for node in ast.walk(tree):
                names: list[str] = []
                if isinstance(node, ast.Import):
                    names = [alias.name for alias in node.names]
                elif isinstance(node, ast.ImportFrom) and node.module:
                    names = [node.module]
                if any(n == "drivers.sim" or n.startswith("drivers.sim.") for n in names):
                    offenders.append(str(path.relative_to(root)))
    # station/cli.py may wire the emulate-stage subcommand, lazily, for the CLI only
    offenders = [p for p in offenders if p != "station/cli.py"]
    assert offenders == []
