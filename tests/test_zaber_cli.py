"""``lfcal emulate-stage`` (drivers.sim.emulate_stage_cli.main): in-process and as a process."""

from __future__ import annotations

import io
import os
import pathlib
import re
import signal
import socket
import subprocess
import sys
import threading
import time

import pytest

from drivers.sim import emulate_stage_cli
from drivers.zaber import ZaberAxisConfig, ZaberPort, open_rail

ROOT = pathlib.Path(__file__).resolve().parents[1]


def run_in_thread(
    argv: list[str],
) -> tuple[threading.Thread, threading.Event, list[str], list[int]]:
    stop = threading.Event()
    urls: list[str] = []
    codes: list[int] = []
    ready = threading.Event()

    def on_ready(url: str) -> None:
        urls.append(url)
        ready.set()

    def target() -> None:
        codes.append(emulate_stage_cli.main(argv, stop=stop, out=io.StringIO(), on_ready=on_ready))
        ready.set()

    thread = threading.Thread(target=target, daemon=True)
    thread.start()
    assert ready.wait(10.0), "emulator did not come up"
    return thread, stop, urls, codes


@pytest.mark.parametrize("argv", [["--pty"], ["--tcp", "0"], []])
def test_main_serves_a_chain(argv: list[str]) -> None:
    thread, stop, urls, codes = run_in_thread([*argv, "--devices", "2", "--axes", "2"])
    try:
        assert urls, f"main exited early with {codes}"
        if "--tcp" in argv:
            assert urls[0].startswith("socket://127.0.0.1:")
        else:
            assert urls[0].startswith("/dev/")
        with ZaberPort(urls[0]) as port:
            assert port.discover() == {1: "50081", 2: "50081"}
            assert port.request(2, 0, "get system.axiscount").data == "2"
    finally:
        stop.set()
        thread.join(timeout=5.0)
    assert codes == [0]


def test_options_reach_the_emulator() -> None:
    argv = ["--pty", "--microstep-um", "0.5", "--travel-mm", "50", "--speedup", "20"]
    thread, stop, urls, codes = run_in_thread(argv)
    try:
        rail = open_rail(
            urls[0], ZaberAxisConfig(name="rail", microstep_um=0.5, timeout_scale=0.05)
        )
        assert rail.limits_mm().max_mm == pytest.approx(50.0)
        rail.home()
        assert rail.move_abs_mm(25.0) == pytest.approx(25.0)
        rail.close()
    finally:
        stop.set()
        thread.join(timeout=5.0)
    assert codes == [0]


@pytest.mark.parametrize(
    "argv",
    [
        ["--pty", "--tcp", "0"],
        ["--devices", "0"],
        ["--devices", "100"],
        ["--axes", "0"],
        ["--speedup", "0"],
        ["--tcp", "70000"],
        ["--bogus"],
    ],
)
def test_bad_options_exit_with_usage_error(
    argv: list[str], capsys: pytest.CaptureFixture[str]
) -> None:
    with pytest.raises(SystemExit) as info:
        emulate_stage_cli.main(argv)
    assert info.value.code == 2
    assert "usage: lfcal emulate-stage" in capsys.readouterr().err


def test_port_in_use_is_reported(capsys: pytest.CaptureFixture[str]) -> None:
    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen(1)
        port = busy.getsockname()[1]
        code = emulate_stage_cli.main(["--tcp", str(port)], stop=threading.Event())
    assert code == 1 and "cannot serve" in capsys.readouterr().err


def test_standalone_process_serves_until_ctrl_c() -> None:
    env = dict(os.environ, PYTHONPATH=str(ROOT), PYTHONUNBUFFERED="1")
    proc = subprocess.Popen(
        [sys.executable, "-m", "drivers.sim.emulate_stage_cli", "--tcp", "0", "--speedup", "10"],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        assert proc.stdout is not None
        url = None
        deadline = time.monotonic() + 20.0
        while url is None and time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            match = re.search(r"serving on (\S+)", line)
            url = match.group(1) if match else None
        assert url and url.startswith("socket://127.0.0.1:"), (
            proc.stderr.read() if proc.stderr else ""
        )
        with ZaberPort(url) as port:
            assert port.request(1, 0, "get device.id").data == "50081"
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=10.0) == 0
        assert "emulator stopped" in proc.stdout.read()
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_firmware_6_option() -> None:
    thread, stop, urls, codes = run_in_thread(["--pty", "--firmware", "6", "--devices", "2"])
    try:
        with ZaberPort(urls[0]) as port:
            assert port.discover() == {1: "50081", 2: "50081"}  # found under "deviceid"
            assert port.request(1, 0, "get version").data == "6.32"
            assert port.request(1, 0, "get device.id").reject_reason == "BADCOMMAND"
            assert port.request(1, 0, "get deviceid").data == "50081"
    finally:
        stop.set()
        thread.join(timeout=5.0)
    assert codes == [0]
