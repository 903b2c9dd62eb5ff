"""``lfcal devices --config FILE``: open every device and show what the station sees.

Prints one table row per device (rail, each XY-stage axis, camera): identity, position,
homed state, camera model, ROI and pixel format; exits 0.  When the configuration is
invalid or a device fails, prints one line per problem / failing device on stderr
(``FAILED rail: ... -- check: ...``), still shows the devices that did open, and exits 2.

The command does not move anything unless asked to home (``home=True``); an unhomed
Zaber axis shows its position as ``unknown``.

``--check`` (``check=True``) adds the bring-up report of :mod:`station.bringup`: one
``PASS``/``FAIL`` line per check (identity and firmware, settings read back, a short
move of each axis with its read-back error, a test grab with its counts and
temperature); it homes and moves the stages.  Exit 2 on any FAIL.
"""

from __future__ import annotations

import os
import sys
from typing import Any, TextIO

from station.config import ConfigError, load_config
from station.devices import ROLE_NAMES, ROLES, DevicesError, open_devices, position_text

EXIT_OK = 0
EXIT_FAILED = 2

COLUMNS = ("device", "identity", "position", "homed", "camera model", "ROI", "pixel format")


def _one_line(text: str) -> str:
    return " ".join(text.split())


def _axis_row(label: str, entry: dict[str, Any]) -> list[str]:
    if "error" in entry:
        return [label, f"ERROR: {_one_line(entry['error'])}", "-", "-", "-", "-", "-"]
    ident = entry["identity"]
    identity = (
        f"{ident['vendor']} {ident['model']} SN {ident['serial']} fw {ident['firmware']} "
        f"@ {ident['address']}"
    )
    position = position_text(entry.get("position_mm"))
    if entry.get("object_distance_mm") is not None:
        position += f" (u = {entry['object_distance_mm']:.3f} mm)"
    return [label, identity, position, "yes" if entry["homed"] else "no", "-", "-", "-"]


def _camera_row(entry: dict[str, Any]) -> list[str]:
    if "error" in entry:
        return ["camera", f"ERROR: {_one_line(entry['error'])}", "-", "-", "-", "-", "-"]
    roi = entry.get("roi")
    roi_text = f"{roi['width']}x{roi['height']}+{roi['offset_x']}+{roi['offset_y']}" if roi else "-"
    identity = f"{entry['vendor']} SN {entry['serial']} @ {entry['device']} ({entry['backend']})"
    return [
        "camera",
        identity,
        "-",
        "-",
        entry["model"],
        roi_text,
        entry.get("pixel_format") or "-",
    ]


def device_rows(description: dict[str, Any]) -> list[list[str]]:
    """Table rows (see :data:`COLUMNS`) of a ``describe()``-style dictionary."""
    rows: list[list[str]] = []
    if "rail" in description:
        rows.append(_axis_row("rail", description["rail"]))
    xy = description.get("xy_stage")
    if xy is not None:
        for key in ("x", "y"):
            if key in xy:
                rows.append(_axis_row(f"xy stage {key}", xy[key]))
        if "x" not in xy and "error" in xy:
            rows.append(_axis_row("xy stage", xy))
    if "camera" in description:
        rows.append(_camera_row(description["camera"]))
    return rows


def format_table(description: dict[str, Any]) -> str:
    """A readable, aligned table of the devices in ``description``."""
    rows = device_rows(description)
    table = [list(COLUMNS), *rows]
    widths = [max(len(row[i]) for row in table) for i in range(len(COLUMNS))]
    lines = ["  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)) for row in table]
    lines.insert(1, "  ".join("-" * w for w in widths))
    sim = description.get("simulation")
    if sim:
        scene = sim.get("scene", {})
        if "object_distance_mm" in scene:
            lines.append(
                f"simulated bench on {sim.get('emulator', '-')}: the camera sees the board at "
                f"u = {scene['object_distance_mm']:.3f} mm, offset "
                f"({scene['board_offset_mm'][0]:.3f}, {scene['board_offset_mm'][1]:.3f}) mm"
                + (" (white: plain light area)" if scene.get("white") else "")
            )
    return "\n".join(line.rstrip() for line in lines)


def failure_line(role: str, message: str) -> str:
    """``FAILED <device>: <message>`` on one line (the device named once)."""
    name = ROLE_NAMES.get(role, role)
    text = _one_line(message)
    return f"FAILED {text}" if text.startswith(name) else f"FAILED {name}: {text}"


def failure_lines(description: dict[str, Any]) -> list[str]:
    """One failure line per device of ``description`` that has an error."""
    out = []
    for role in ROLES:
        entry = description.get(role)
        if entry is not None and "error" in entry:
            out.append(failure_line(role, entry["error"]))
    return out


def devices_main(
    config_path: str | os.PathLike[str],
    *,
    home: bool = False,
    check: bool = False,
    out: TextIO | None = None,
    err: TextIO | None = None,
) -> int:
    """Run ``lfcal devices --config FILE``; return the exit code (0 all fine, 2 failures).

    Args:
        config_path: the station configuration (TOML).
        home: home the stages first (moves them); default: no motion.
        check: run the bring-up report after the table (homes and moves the stages).
        out, err: streams for the table and the failure lines (default stdout, stderr).
    """
    out = out or sys.stdout
    err = err or sys.stderr
    try:
        config = load_config(config_path)
    except ConfigError as exc:
        for line in exc.format_problems():
            print(f"FAILED config: {line}", file=err)
        return EXIT_FAILED
    try:
        devices = open_devices(config, home=home)
    except DevicesError as exc:
        if exc.opened:
            print(format_table(exc.opened), file=out)
        for role, error in exc.failures.items():
            print(failure_line(role, str(error)), file=err)
        return EXIT_FAILED
    with devices:
        description = devices.describe()
        print(format_table(description), file=out)
        failures = failure_lines(description)
        for line in failures:
            print(line, file=err)
        if check:
            from station.bringup import bring_up_report

            report = bring_up_report(devices, config)
            print("", file=out)
            print("bring-up check:", file=out)
            for entry in report:
                print(str(entry), file=out)
            failed = sum(not entry.ok for entry in report)
            print(
                f"{len(report) - failed} passed, {failed} failed"
                if failed
                else f"all {len(report)} checks passed",
                file=out,
            )
            if failed:
                return EXIT_FAILED
    return EXIT_FAILED if failures else EXIT_OK


__all__ = [
    "COLUMNS",
    "device_rows",
    "devices_main",
    "failure_line",
    "failure_lines",
    "format_table",
]
