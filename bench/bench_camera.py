"""Camera grab rate through the real GenICam stacks, without hardware.

* Aravis: full 5120 x 5120 Mono8 frames (26 MB) from the fake GigE Vision camera on
  127.0.0.1 (``drivers.sim.fake_gige``), software-triggered one by one through
  :class:`drivers.aravis_camera.AravisCamera` (GVCP trigger, GVSP stream with 8192-byte
  packets, numpy frame).  Target: >= 8 frames/s.  Every frame is checked to be the
  served pattern, so the rate counts correct frames only.
* harvesters: 4096 x 4096 Mono8 frames from the TLSimu GenTL producer (informative).
* decoding (:mod:`drivers.pixels`): a 5120 x 5120 frame of each packed format (Mono10p,
  Mono12p, Mono12Packed) and of Mono12 (16-bit words with the range check), in MB/s
  of wire data and ms per frame; harvesters' own unpacking of the same buffer beside
  it.  Target: a packed frame decodes in <= 200 ms (well inside a sweep step).

Run: ``python -m bench.bench_camera [--frames 30]``.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path
from typing import Any

import numpy as np

from drivers.camera import CameraSettings

TARGET_FPS = 8.0
SENSOR = 5120


def _aravis_rows(frames: int) -> list[dict[str, Any]]:
    from drivers.aravis_camera import AravisCamera
    from drivers.sim.fake_gige import FakeGigECamera, FrameRequest

    pattern = np.random.default_rng(0).integers(0, 256, (SENSOR, SENSOR), dtype=np.uint8)

    def source(request: FrameRequest) -> np.ndarray:
        return pattern

    with FakeGigECamera(source, sensor_width=SENSOR, sensor_height=SENSOR) as fake:
        with AravisCamera("127.0.0.1") as cam:
            cam.configure(CameraSettings("Mono8"))
            for _ in range(2):  # warm-up: stream creation, first-frame latency
                cam.grab(timeout_s=5.0)
            exact = 0
            start = time.perf_counter()
            for _ in range(frames):
                frame = cam.grab(timeout_s=5.0)
                exact += int(np.array_equal(frame.pixels, pattern))
            elapsed = time.perf_counter() - start
        errors = list(fake.errors)
    fps = frames / elapsed
    mbytes = SENSOR * SENSOR / 1e6
    return [
        {
            "name": f"aravis grab {SENSOR}x{SENSOR} Mono8, loopback fake GigE",
            "value": fps,
            "unit": "fps",
            "target": TARGET_FPS,
            "ok": bool(fps >= TARGET_FPS),
        },
        {
            "name": "aravis stream throughput",
            "value": fps * mbytes,
            "unit": "MB/s",
            "target": None,
            "ok": None,
        },
        {
            "name": "aravis frames pixel-exact",
            "value": exact / frames,
            "unit": "frac",
            "target": 1.0,
            "ok": bool(exact == frames and not errors),
        },
    ]


def _harvesters_rows(frames: int) -> list[dict[str, Any]]:
    import genicam

    from drivers.camera import Roi
    from drivers.harvesters_camera import HarvestersCamera

    cti = Path(genicam.__file__).parent / "TLSimu.cti"
    with HarvestersCamera(cti, serial="SN_InterfaceA_0") as cam:
        cam.configure(CameraSettings("Mono8", roi=Roi(4096, 4096)))
        cam.grab(timeout_s=5.0)
        start = time.perf_counter()
        for _ in range(frames):
            cam.grab(timeout_s=5.0)
        elapsed = time.perf_counter() - start
    return [
        {
            "name": "harvesters grab 4096x4096 Mono8, TLSimu",
            "value": frames / elapsed,
            "unit": "fps",
            "target": None,
            "ok": None,
        }
    ]


DECODE_TARGET_MS = 200.0


def _best_ms(action: Any, repeats: int) -> float:
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        action()
        best = min(best, time.perf_counter() - start)
    return best * 1000.0


def _decode_rows(repeats: int = 5) -> list[dict[str, Any]]:
    from harvesters.util.pfnc import Dictionary

    from drivers.pixels import decode_mono, mono_format

    rows: list[dict[str, Any]] = []
    rng = np.random.default_rng(1)
    for name in ("Mono10p", "Mono12p", "Mono12Packed", "Mono12"):
        fmt = mono_format(name)
        nbytes = fmt.buffer_bytes(SENSOR * SENSOR)
        if fmt.packed:
            raw = rng.integers(0, 256, nbytes, dtype=np.uint8)
        else:
            raw = rng.integers(0, 4096, SENSOR * SENSOR, dtype=np.uint16).view(np.uint8)
        ms = _best_ms(
            lambda raw=raw, name=name: decode_mono(
                raw, width=SENSOR, height=SENSOR, pixel_format=name, device="bench"
            ),
            repeats,
        )
        rows.append(
            {
                "name": f"decode {name} {SENSOR}x{SENSOR} ({nbytes / 1e6:.1f} MB)",
                "value": ms,
                "unit": "ms",
                "target": None,
                "ok": bool(ms <= DECODE_TARGET_MS),
            }
        )
        rows.append(
            {
                "name": f"decode {name} throughput",
                "value": nbytes / 1e6 / (ms / 1000.0),
                "unit": "MB/s",
                "target": None,
                "ok": None,
            }
        )
        if fmt.packed:
            proxy = Dictionary.get_proxy(symbolic=name)
            ref_ms = _best_ms(lambda raw=raw, proxy=proxy: proxy.expand(raw), 2)
            rows.append(
                {
                    "name": f"  harvesters' expand of the same {name} buffer",
                    "value": ref_ms,
                    "unit": "ms",
                    "target": None,
                    "ok": None,
                }
            )
    return rows


def run(frames: int = 30) -> list[dict[str, Any]]:
    """Rows: name, value, unit, target (None = informative), ok (None = no target)."""
    return _decode_rows() + _aravis_rows(frames) + _harvesters_rows(frames)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.bench_camera", description=__doc__)
    parser.add_argument("--frames", type=int, default=30, help="timed grabs per backend")
    args = parser.parse_args(argv)
    rows = run(args.frames)
    width = max(len(r["name"]) for r in rows)
    print(f"{'benchmark'.ljust(width)}  {'value':>8}  unit  {'target':>8}  ok")
    for r in rows:
        target = "" if r["target"] is None else f">= {r['target']:g}"
        ok = "" if r["ok"] is None else ("yes" if r["ok"] else "NO")
        print(f"{r['name'].ljust(width)}  {r['value']:8.2f}  {r['unit']:<4}  {target:>8}  {ok}")
    return 0 if all(r["ok"] is not False for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
