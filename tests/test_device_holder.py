"""The devices as the hardware worker holds them (station/device_holder.py), on the
simulated station's real devices: a simulated camera and the Zaber emulator on a pty,
opened through the same factory the station uses."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_devices import SPEEDUP, simulated_toml

from drivers.errors import DeviceError
from station import device_holder
from station.config import load_config
from station.device_holder import DeviceHolder
from station.devices import open_devices


def test_devices_that_fail_to_open_say_why_and_are_opened_when_back(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    config = load_config(simulated_toml(tmp_path))
    attempts: list[int] = []

    def factory() -> object:
        attempts.append(1)
        if len(attempts) == 1:
            raise DeviceError("no answer on /dev/ttyUSB0", device="rail")
        return open_devices(config, emulator_speedup=SPEEDUP)

    holder = DeviceHolder(factory)
    with holder.hw_lock, pytest.raises(DeviceError):
        holder.ensure()
    assert holder.devices is None and "no answer on /dev/ttyUSB0" in str(holder.error)
    # asked again at once: reported, not reopened (at most every REOPEN_INTERVAL_S)
    assert holder.describe_if_idle() == {
        "connected": False,
        "busy": False,
        "error": holder.error,
    }
    assert len(attempts) == 1
    monkeypatch.setattr(device_holder, "REOPEN_INTERVAL_S", 0.0)
    try:
        info = holder.describe_if_idle()
        assert len(attempts) == 2
        assert info is not None and info["connected"] is True and info["busy"] is False
        assert holder.error is None
        assert holder.rail_limits_mm == (config.rail.min_mm, config.rail.max_mm)
        assert holder.exposure_limits_us is not None
        low, high = holder.exposure_limits_us
        assert 0 < low < config.camera.exposure_us < high
        # while a job holds the devices, a request gets the last description, marked busy
        with holder.hw_lock:
            assert holder.describe_if_idle() is None
            busy = holder.describe_busy()
        assert busy["busy"] is True and busy["connected"] is True
        assert {k: v for k, v in busy.items() if k != "busy"} == {
            k: v for k, v in info.items() if k != "busy"
        }
        assert holder.ensure() is holder.devices  # already open: the same devices
        assert len(attempts) == 2
    finally:
        holder.close()
    holder.close()  # idempotent
    assert holder.devices is None
    assert holder.describe_busy()["connected"] is False
