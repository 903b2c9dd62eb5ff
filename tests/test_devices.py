"""``open_devices`` and ``lfcal devices`` against real components.

The simulated station (config/simulated.toml with a 600 x 400 px sensor) runs the
Zaber emulator on a real pty behind the real Zaber driver; the failure cases use real
ports and sockets on 127.0.0.1: a device path that does not exist, a TCP port nobody
listens on, an emulator chain without the XY stage's device, a server that answers
garbage, an Aravis camera address with nothing behind it (unicast only: no GigE
discovery) and GenTL producers that are missing or not producers.
"""

from __future__ import annotations

import ast
import io
import re
import socket
import socketserver
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from calibration.simulator import Roi as SimRoi
from calibration.simulator import render_frame
from drivers.axis import Axis
from drivers.camera import Camera
from drivers.camera_errors import CameraNotFound, ProducerLoadError
from drivers.errors import GarbledReply, NoReply, PortUnavailable
from drivers.sim.bench import SimulatedBench
from drivers.sim.zaber_emulator import AxisSpec, DeviceSpec, ZaberEmulator
from drivers.zaber import XYStage
from station.config import StationConfig, load_config
from station.devices import DevicesError, StationDevices, open_devices
from station.devices_cli import devices_main

ROOT = Path(__file__).resolve().parents[1]
SPEEDUP = 50.0


def simulated_toml(tmp_path: Path, **replace: str) -> Path:
    """config/simulated.toml with a 600 x 400 px sensor, storage in ``tmp_path``."""
    text = (ROOT / "config" / "simulated.toml").read_text(encoding="utf-8")
    subs = {
        r"^width = \d+": "width = 600",
        r"^height = \d+": "height = 400",
        r'^data_dir = ".*"': 'data_dir = "data"',
        r'^database = ".*"': 'database = "data/lfcal.sqlite3"',
        **replace,
    }
    for pattern, value in subs.items():
        text, n = re.subn(pattern, value, text, count=1, flags=re.MULTILINE)
        assert n == 1, pattern
    path = tmp_path / "station.toml"
    path.write_text(text, encoding="utf-8")
    return path


def rail_on(port: str) -> dict[str, str]:
    """Replacements putting the rail (and the XY stage, on its chain) on a real port."""
    return {
        r'^driver = "emulated"\ndevice = 1': f'driver = "zaber"\nport = "{port}"\ndevice = 1',
        r'^driver = "emulated"       # no port': 'driver = "zaber"          # no port',
    }


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as sock:
        sock.bind(("127.0.0.1", 0))
        return int(sock.getsockname()[1])


@pytest.fixture
def config(tmp_path: Path) -> StationConfig:
    return load_config(simulated_toml(tmp_path))


@pytest.fixture
def devices(config: StationConfig) -> Iterator[StationDevices]:
    with open_devices(config, emulator_speedup=SPEEDUP) as opened:
        yield opened


# --------------------------------------------------------------------------- simulated station


def test_open_simulated_station(devices: StationDevices, config: StationConfig) -> None:
    assert isinstance(devices.camera, Camera)
    assert isinstance(devices.rail, Axis)
    assert isinstance(devices.xy, XYStage)
    assert isinstance(devices.bench, SimulatedBench)
    # one emulated chain: rail device 1, XY device 2, both through the same pty
    ident = devices.rail.identity()
    assert ident.address == f"{devices.bench.url} device 1 axis 1"
    assert devices.xy.x.identity().address == f"{devices.bench.url} device 2 axis 1"
    assert devices.rail.is_homed() and devices.xy.is_homed()  # home_on_connect = true
    assert devices.camera_settings.pixel_format == "Mono12"
    assert devices.camera_settings.exposure_us == config.camera.exposure_us
    assert devices.camera.info().sensor_width == 600
    assert devices.object_distance_mm() == config.rail.zero_object_distance_mm


def test_describe(devices: StationDevices) -> None:
    info = devices.describe()
    rail, xy, cam = info["rail"], info["xy_stage"], info["camera"]
    assert rail["homed"] is True and rail["position_mm"] == 0.0
    assert rail["object_distance_mm"] == 250.0 and rail["limits_mm"] == [0.0, 100.0]
    assert rail["identity"]["vendor"] == "Zaber" and rail["identity"]["serial"] == "100001"
    assert xy["homed"] is True and xy["position_mm"] == [0.0, 0.0]
    assert xy["board_offset_mm"] == [-100.0, -100.0]
    assert xy["x"]["identity"]["address"].endswith("device 2 axis 1")
    assert cam["model"] == "plenoptic simulator (paper)" and cam["backend"] == "simulated"
    assert cam["roi"] == {"width": 600, "height": 400, "offset_x": 0, "offset_y": 0}
    assert cam["pixel_format"] == "Mono12" and cam["sensor_px"] == [600, 400]
    sim = info["simulation"]
    assert sim["scene"]["object_distance_mm"] == 250.0 and sim["scene"]["white"] is False
    assert not any("error" in entry for entry in (rail, xy, cam))


def test_describe_reports_a_broken_device_without_failing(devices: StationDevices) -> None:
    assert devices.bench is not None
    emulator = devices.bench.emulator
    emulator.set_dead(2)  # the XY stage stops answering
    info = devices.describe()
    assert "error" in info["xy_stage"] and "no reply" in info["xy_stage"]["error"]
    assert "error" not in info["rail"] and "error" not in info["camera"]
    emulator.set_dead(2, False)


def test_frames_follow_the_stages(devices: StationDevices, config: StationConfig) -> None:
    """The orchestrator's recipe: move, grab; white image: XY to the white position, grab."""
    bench = devices.bench
    assert bench is not None
    scene_cam = bench.camera._scene.camera  # the simulator camera behind the scene
    align, white = config.xy_stage.alignment, config.xy_stage.white
    devices.xy.move_xy_mm(align.x_mm, align.y_mm)
    devices.rail.move_abs_mm(20.0)
    frame = devices.camera.grab(config.camera.timeout_s)
    x, y = devices.xy.position_xy_mm()
    offset = (x - align.x_mm, y - align.y_mm)
    u = devices.object_distance_mm()
    expected = render_frame(
        scene_cam,
        object_distance_mm=u,
        board_offset_mm=offset,
        roi=SimRoi(0, 0, 600, 400),
        seed=[config.camera.seed, frame.frame_id],
    )
    np.testing.assert_array_equal(frame.pixels, expected)

    devices.xy.move_xy_mm(white.x_mm, white.y_mm)
    white_frame = devices.camera.grab(config.camera.timeout_s)
    assert bench.camera.last_state is not None and bench.camera.last_state.white
    expected_white = render_frame(
        scene_cam,
        object_distance_mm=u,
        white=True,
        roi=SimRoi(0, 0, 600, 400),
        seed=[config.camera.seed, white_frame.frame_id],
    )
    np.testing.assert_array_equal(white_frame.pixels, expected_white)


def test_close_releases_everything(config: StationConfig) -> None:
    devices = open_devices(config, home=False, emulator_speedup=SPEEDUP)
    assert not devices.rail.is_homed()  # home=False overrides home_on_connect
    devices.close()
    devices.close()
    assert not devices.camera.is_open
    assert not devices.rail.port.is_open  # type: ignore[attr-defined]
    assert not devices.xy.x.port.is_open  # the shared chain's port


def test_simulated_camera_in_front_of_real_stages(tmp_path: Path) -> None:
    """Real (here: TCP-emulated) stages, simulated camera: the scene follows the drivers."""
    axes = (AxisSpec(microstep_um=0.047625), AxisSpec(microstep_um=0.09921875, travel_mm=300.0))
    chain = [DeviceSpec(address=1, axes=axes[:1]), DeviceSpec(address=2, axes=(axes[1],) * 2)]
    with ZaberEmulator(chain, transport="tcp", speedup=SPEEDUP) as emulator:
        config = load_config(simulated_toml(tmp_path, **rail_on(emulator.url)))
        with open_devices(config) as devices:  # homes, at the emulator's speed
            assert devices.bench is not None and devices.bench.rail is None
            devices.rail.move_abs_mm(30.0)
            devices.camera.grab()
            state = devices.bench.camera.last_state
            assert state is not None
            assert state.object_distance_mm == 250.0 + devices.rail.position_mm()
            assert state.board_offset_mm == (-100.0, -100.0)  # XY homed at (0, 0)


def test_production_code_never_imports_drivers_sim() -> None:
    """No module of station/ or web/ imports drivers.sim, and none but the device
    factory's backend table names it (the simulation is a configuration-selected backend)."""
    for path in sorted((ROOT / "station").glob("*.py")) + sorted((ROOT / "web").glob("*.py")):
        text = path.read_text(encoding="utf-8")
        tree = ast.parse(text)
        for node in ast.walk(tree):
            if isinstance(node, ast.ImportFrom):
                assert not (node.module or "").startswith("drivers.sim"), path.name
            if isinstance(node, ast.Import):
                assert not any(a.name.startswith("drivers.sim") for a in node.names), path.name
        if path.name not in ("devices.py", "cli.py"):
            assert "drivers.sim" not in text, path.name
        # no simulation parameter in any signature or call (the CLI option only sets a key)
        assert "sim_frame_cache=" not in text and "sim_frame_cache:" not in text, path.name
        assert "sim_scene" not in text and "sim_cache" not in text, path.name
    code = (
        "import sys, station.devices, station.devices_cli\n"
        "loaded = [m for m in sys.modules if m.startswith('drivers.sim')]\n"
        "assert not loaded, loaded\n"
    )
    subprocess.run([sys.executable, "-c", code], check=True, cwd=ROOT, timeout=60)


# --------------------------------------------------------------------------- lfcal devices


def run_main(path: Path, **kwargs: Any) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    code = devices_main(path, out=out, err=err, **kwargs)
    return code, out.getvalue(), err.getvalue()


def test_devices_main_prints_the_table(tmp_path: Path) -> None:
    code, out, err = run_main(simulated_toml(tmp_path))
    assert code == 0 and err == ""
    lines = out.splitlines()
    assert lines[0].split()[:3] == ["device", "identity", "position"]
    rows = {line.split("  ")[0].strip(): line for line in lines[2:6]}
    assert set(rows) == {"rail", "xy stage x", "xy stage y", "camera"}
    assert "Zaber device id 50081" in rows["rail"] and "device 1 axis 1" in rows["rail"]
    assert "unknown" in rows["rail"] and re.search(r"\bno\b", rows["rail"])  # not homed
    assert "plenoptic simulator (paper)" in rows["camera"]
    assert "600x400+0+0" in rows["camera"] and "Mono12" in rows["camera"]
    assert "simulated bench on /dev/" in out


def test_devices_main_can_home(tmp_path: Path) -> None:
    code, out, _ = run_main(simulated_toml(tmp_path), home=True)  # real-time emulator
    assert code == 0
    rail = next(line for line in out.splitlines() if line.startswith("rail"))
    assert "0.000 mm (u = 250.000 mm)" in rail and re.search(r"\byes\b", rail)


def test_devices_main_reports_a_bad_config(tmp_path: Path) -> None:
    path = simulated_toml(tmp_path, **{r"^exposure_us = .*$": 'exposure_us = "long"'})
    code, out, err = run_main(path)
    assert code == 2 and out == ""
    assert err.startswith("FAILED config: ") and "camera.exposure_us" in err


# --------------------------------------------------------------------------- failures


def test_rail_port_that_does_not_exist(tmp_path: Path) -> None:
    path = simulated_toml(tmp_path, **rail_on("/dev/ttyDOESNOTEXIST"))
    with pytest.raises(DevicesError) as info:
        open_devices(load_config(path))
    failures = info.value.failures
    assert set(failures) == {"rail", "xy_stage"}
    rail = failures["rail"]
    assert isinstance(rail, PortUnavailable)
    assert "/dev/ttyDOESNOTEXIST" in str(rail) and "port path" in rail.hint
    assert "rail's chain" in str(failures["xy_stage"])
    assert set(info.value.opened) == {"camera"}  # it opened, then was closed again

    code, out, err = run_main(path)
    assert code == 2
    lines = err.splitlines()
    assert len(lines) == 2  # one line per failing device
    assert lines[0].startswith("FAILED rail: cannot open port /dev/ttyDOESNOTEXIST")
    assert "-- check: the port path" in lines[0]
    assert lines[1].startswith("FAILED xy stage: ")
    assert "plenoptic simulator" in out  # the camera that did open is still shown


def test_tcp_port_with_nothing_listening(tmp_path: Path) -> None:
    url = f"socket://127.0.0.1:{free_tcp_port()}"
    path = simulated_toml(tmp_path, **rail_on(url))
    code, _, err = run_main(path)
    assert code == 2
    rail_line = err.splitlines()[0]
    assert rail_line.startswith(f"FAILED rail: cannot open port {url}")
    assert "refused" in rail_line.lower() and "server" in rail_line


def test_a_device_that_answers_nothing(tmp_path: Path) -> None:
    # the chain holds the rail (device 1) only: the XY stage's device 2 never answers
    with ZaberEmulator([DeviceSpec(address=1)], transport="tcp") as emulator:
        path = simulated_toml(tmp_path, **rail_on(emulator.url))
        with pytest.raises(DevicesError) as info:
            open_devices(load_config(path), home=False)
    assert set(info.value.failures) == {"xy_stage"}
    error = info.value.failures["xy_stage"]
    assert isinstance(error, NoReply)
    assert "xy stage x (zaber device 2 axis 1 on socket://127.0.0.1:" in str(error)
    assert "device number" in error.hint
    assert set(info.value.opened) == {"camera", "rail"}


class _Garbage(socketserver.StreamRequestHandler):
    def handle(self) -> None:
        while self.rfile.readline():
            self.wfile.write(b"!!!garbage@@\r\n")


@pytest.fixture
def garbage_server() -> Iterator[str]:
    server = socketserver.ThreadingTCPServer(("127.0.0.1", 0), _Garbage)
    server.daemon_threads = True
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"socket://127.0.0.1:{server.server_address[1]}"
    server.shutdown()
    server.server_close()


def test_a_device_that_answers_garbage(tmp_path: Path, garbage_server: str) -> None:
    path = simulated_toml(tmp_path, **rail_on(garbage_server))
    with pytest.raises(DevicesError) as info:
        open_devices(load_config(path))
    rail = info.value.failures["rail"]
    assert isinstance(rail, GarbledReply)
    assert "no valid reply" in str(rail) and "garbage" in str(rail)
    assert "baud rate" in rail.hint


def camera_toml(tmp_path: Path, camera: str) -> Path:
    """simulated.toml with another [camera] section (the stages stay emulated)."""
    text = simulated_toml(tmp_path).read_text(encoding="utf-8")
    start, end = text.index("[camera]"), text.index("[rail]")
    path = tmp_path / "camera.toml"
    path.write_text(text[:start] + "[camera]\n" + camera + "\n\n" + text[end:], encoding="utf-8")
    return path


try:
    import gi

    gi.require_version("Aravis", "0.8")
    from gi.repository import Aravis

    for _i in range(Aravis.get_n_interfaces()):  # no interface may ever enumerate
        Aravis.disable_interface(Aravis.get_interface_id(_i))
    ARAVIS_ERROR = ""
except (ImportError, ValueError) as exc:  # pragma: no cover - installed by the Makefile
    ARAVIS_ERROR = f"Aravis 0.8 / PyGObject not importable: {exc}"


@pytest.mark.skipif(bool(ARAVIS_ERROR), reason=ARAVIS_ERROR)
def test_camera_address_without_a_camera(tmp_path: Path) -> None:
    from drivers.sim.fake_gige import _AddressLock

    lock = _AddressLock("127.0.0.1")  # no fake GigE camera may start there meanwhile
    lock.acquire(120.0)
    try:
        path = camera_toml(tmp_path, 'backend = "aravis"\naddress = "127.0.0.1"')
        start = time.monotonic()
        with pytest.raises(DevicesError) as info:
            open_devices(load_config(path), home=False)
        assert time.monotonic() - start < 5.0  # a unicast ping, no GVCP retry storm
        code, _, err = run_main(path)
    finally:
        lock.release()
    assert set(info.value.failures) == {"camera"}
    error = info.value.failures["camera"]
    assert isinstance(error, CameraNotFound)
    assert "gige://127.0.0.1" in str(error) and "no GigE Vision camera answers" in str(error)
    assert set(info.value.opened) == {"rail", "xy_stage"}
    assert code == 2
    assert err.startswith("FAILED camera: gige://127.0.0.1: no GigE Vision camera answers")


def test_missing_cti_is_a_config_error(tmp_path: Path) -> None:
    path = camera_toml(tmp_path, 'backend = "harvesters"\ncti = "missing/producer.cti"')
    code, _, err = run_main(path)
    assert code == 2
    assert err.startswith("FAILED config: ") and "camera.cti" in err and "file not found" in err


@pytest.mark.parametrize("kind", ["deleted", "not-a-producer"])
def test_cti_that_does_not_load(tmp_path: Path, kind: str) -> None:
    pytest.importorskip("harvesters.core")
    cti = tmp_path / "producer.cti"
    cti.write_text("not a shared library\n", encoding="utf-8")
    config = load_config(camera_toml(tmp_path, 'backend = "harvesters"\ncti = "producer.cti"'))
    if kind == "deleted":
        cti.unlink()  # vanished between the config check and the open
    with pytest.raises(DevicesError) as info:
        open_devices(config, home=False)
    assert set(info.value.failures) == {"camera"}
    error = info.value.failures["camera"]
    assert isinstance(error, ProducerLoadError)
    expected = "does not exist" if kind == "deleted" else "does not load as a shared library"
    assert expected in str(error) and str(cti) in str(error)
    assert "camera.cti" in error.hint


def test_frame_cache_is_a_key_of_the_simulated_camera(tmp_path: Path) -> None:
    """``[camera] frame_cache``: the simulated camera keeps and reuses its renders."""
    cache = tmp_path / "frames"
    path = simulated_toml(tmp_path, **{r"^seed = 0": f'seed = 0\nframe_cache = "{cache}"'})
    config = load_config(path)
    assert config.camera.frame_cache == cache
    with open_devices(config, emulator_speedup=SPEEDUP) as devices:
        scene = devices.camera.scene  # type: ignore[attr-defined]
        first = devices.camera.grab()
        second = devices.camera.grab()  # same bench state: read from the cache
        assert (scene.misses, scene.hits) == (1, 1)
        np.testing.assert_array_equal(first.pixels, second.pixels)
    assert len(list(cache.glob("*.npy"))) == 1
