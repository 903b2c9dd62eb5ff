"""Simulator speed and memory: one 3000x1000 and one 5120x5120 frame (issue 2 targets).

Each render runs in a fresh subprocess so that its peak memory (max RSS) is its own.
Targets on 2 cores: 3000x1000 <= 3 s, 5120x5120 <= 30 s, peak memory <= 2 GB.
Run: ``python -m bench.bench_simulator``.
"""

from __future__ import annotations

import json
import subprocess
import sys
from typing import Any

_CHILD = r"""
import json, resource, sys, time
from calibration.presets import get_preset
from calibration.sim_sweep import fit_frame
from calibration.simulator import render_frame
w, h = int(sys.argv[1]), int(sys.argv[2])
preset = fit_frame(get_preset("paper"), w, h)
u = preset.sweep.object_distance_mm(20.0)  # defocused: the slow path for every edge pixel
render_frame(preset.camera, object_distance_mm=u, seed=0)  # warm-up (imports, caches)
t0 = time.perf_counter()
render_frame(preset.camera, object_distance_mm=u, seed=1)
seconds = time.perf_counter() - t0
rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
print(json.dumps({"seconds": seconds, "rss_mb": rss_mb}))
"""


def _measure(width: int, height: int) -> dict[str, float]:
    out = subprocess.run(
        [sys.executable, "-c", _CHILD, str(width), str(height)],
        check=True,
        capture_output=True,
        text=True,
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def run() -> list[dict[str, Any]]:
    rows = []
    peak = 0.0
    for (w, h), target in (((3000, 1000), 3.0), ((5120, 5120), 30.0)):
        m = _measure(w, h)
        peak = max(peak, m["rss_mb"])
        rows.append(
            {
                "name": f"simulator: render one {w}x{h} frame",
                "value": m["seconds"],
                "unit": "s",
                "target": target,
                "ok": m["seconds"] <= target,
            }
        )
    rows.append(
        {
            "name": "simulator: peak memory (max RSS)",
            "value": peak / 1024.0,
            "unit": "GB",
            "target": 2.0,
            "ok": peak / 1024.0 <= 2.0,
        }
    )
    return rows


if __name__ == "__main__":
    from bench.__main__ import print_table

    print_table(run())
