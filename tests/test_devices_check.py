"""``lfcal devices --check``: the bring-up report, on the simulated station and on a
firmware-6 chain reached over 127.0.0.1 TCP (the real driver, a real socket)."""

from __future__ import annotations

import io
import re
from pathlib import Path

from test_devices import SPEEDUP, rail_on, simulated_toml

from drivers.sim.zaber_emulator import AxisSpec, DeviceSpec, ZaberEmulator
from station.devices_cli import devices_main


def run_check(path: Path) -> tuple[int, list[str], str]:
    out, err = io.StringIO(), io.StringIO()
    code = devices_main(path, check=True, out=out, err=err)
    report = out.getvalue().split("bring-up check:\n", 1)[-1].splitlines()
    return code, report, err.getvalue()


def line(report: list[str], subject: str) -> str:
    found = [entry for entry in report if re.match(rf"(PASS|FAIL) {subject}:", entry)]
    assert len(found) == 1, (subject, report)
    return found[0]


def test_check_passes_on_the_simulated_station(tmp_path: Path) -> None:
    code, report, err = run_check(simulated_toml(tmp_path))
    assert code == 0, (report, err)
    assert report[-1] == "all 13 checks passed"
    for axis in ("rail", "xy stage x", "xy stage y"):
        assert line(report, f"{axis} identity").startswith("PASS")
        assert "firmware 7.38" in line(report, f"{axis} identity")
        settings = line(report, f"{axis} settings")
        assert settings.startswith("PASS") and "configured speed: per-move" in settings
        move = line(report, f"{axis} move")
        error_um = float(re.search(r"read-back error ([0-9.]+) um", move).group(1))  # type: ignore[union-attr]
        assert move.startswith("PASS") and error_um <= 2.0
    grab = line(report, "camera grab")
    assert grab.startswith("PASS camera grab: 600x400 Mono12 (12 bit)")
    assert "temperature 38.5 C" in grab
    assert "PixelFormat Mono12, exposure 10000 us, Gain 0 dB" in line(report, "camera settings")


def test_check_reports_fw6_identity_short_travel_and_saturation(tmp_path: Path) -> None:
    rail = AxisSpec(microstep_um=0.047625, travel_mm=50.0)  # the config expects 0..100 mm
    stage = AxisSpec(microstep_um=0.09921875, travel_mm=300.0)
    chain = [
        DeviceSpec(address=1, axes=(rail,), firmware=6, device_id=43211),
        DeviceSpec(address=2, axes=(stage, stage), firmware=6),
    ]
    with ZaberEmulator(chain, transport="tcp", speedup=SPEEDUP) as emulator:
        replace = {**rail_on(emulator.url), r"^exposure_us = [0-9.]+": "exposure_us = 400000.0"}
        code, report, _ = run_check(simulated_toml(tmp_path, **replace))
    assert code == 2
    identity = line(report, "rail identity")
    assert (
        identity.startswith("PASS")
        and "device id 43211" in identity
        and "firmware 6.32" in identity
    )
    settings = line(report, "rail settings")
    assert settings.startswith("FAIL") and "does NOT cover the configured 0..100 mm" in settings
    assert "configured speed: written" in settings  # no per-move speed before 7.25
    assert line(report, "rail move").startswith("PASS")  # within the 0..50 mm it has
    assert line(report, "xy stage x settings").startswith("PASS")
    grab = line(report, "camera grab")
    assert grab.startswith("FAIL") and "saturated" in grab
    assert report[-1] == "11 passed, 2 failed"
