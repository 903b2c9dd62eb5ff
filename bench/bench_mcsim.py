"""Speed of the Monte-Carlo renderer (bench.mcsim): ``python -m bench mcsim``.

For every preset (30 rays per sample point, 2×2 sample points, both corners)
it renders the white image and three frames spread over the sweep, measures
CPU time (robust on a shared machine) and projects a 100-frame sweep on two
cores: (white + 100 · frame CPU time) / 2. Targets from issue 10: ~50-60 px
micro-images ≤ 15 min, 80 px ≤ 15 min, the paper's 100 px lenses ≤ 45 min.
"""

from __future__ import annotations

import time
from typing import Any

from bench.mcsim.render import WHITE, render_image
from bench.mcsim.spec import build_spec

TARGET_MIN = {"small": 15.0, "between": 15.0, "paper": 45.0}


def _cpu(spec: Any, index: int) -> tuple[float, int]:
    start = time.process_time()
    _, stats = render_image(spec, index)
    return time.process_time() - start, stats.rays


def run(presets: tuple[str, ...] = ("small", "between", "paper")) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    for name in presets:
        spec = build_spec(preset=name)
        white_cpu, _ = _cpu(spec, WHITE)
        frames = spec.rail.frames
        samples = [0, frames // 2, frames - 1]
        cpu = rays = 0.0
        for index in samples:
            seconds, traced = _cpu(spec, index)
            cpu += seconds
            rays += traced
        per_frame = cpu / len(samples)
        sweep_min = (white_cpu + 100 * per_frame) / 2 / 60
        rows += [
            {
                "name": f"mcsim {name}: rays per CPU-second",
                "value": rays / cpu / 1e6,
                "unit": "M/s",
                "target": None,
                "ok": None,
            },
            {
                "name": f"mcsim {name}: CPU time per frame",
                "value": per_frame,
                "unit": "s",
                "target": None,
                "ok": None,
            },
            {
                "name": f"mcsim {name}: 100-frame sweep on 2 cores",
                "value": sweep_min,
                "unit": "min",
                "target": TARGET_MIN[name],
                "ok": sweep_min <= TARGET_MIN[name],
            },
        ]
    return rows


if __name__ == "__main__":
    from bench.__main__ import print_table

    print_table(run())
