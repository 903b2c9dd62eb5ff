"""The ESIF core on sweeps of an independent renderer (``bench/crosscheck/indsim.py``).

The core is judged on sweeps it was not developed against. ``indsim`` was written
from ``../shared/OPTICS.md`` alone, without the project's simulator; this
benchmark renders three 100-frame sweeps with it (cached under
``out/bench/crosscheck``: about 20 minutes each on 2 cores the first time),
calibrates them with ``calibrate_archive`` and compares with its ``truth.json``:

- ``paper``: the seed paper's optics, MLA 0.2° and (0.4, -1.1) px, 12 bit;
- ``between``: F=50, f=2, D=0.2 mm (80 px), b=2.4, focus at rail 47.6 mm (between
  steps), MLA -0.35°, principal point off the frame centre;
- ``noisy``: f=3, D=0.3 mm (120 px), b=3.6, rail direction -1, focus between steps,
  16 bit, 800 photo-electrons and 8 e- read noise, MLA 0.5°, board offset.

Targets as in ``bench_accuracy`` (issue 3). Not part of the default ``make bench``
set (it renders for an hour the first time): ``python -m bench crosscheck``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

from calibration.pipeline import calibrate_archive

CACHE = Path("out/bench/crosscheck")

SWEEPS: dict[str, list[str]] = {
    "paper": (
        "--width 3000 --height 1000 --pp 2520,499.5 --F 35 --f 2.5 --D 0.25 --b 3.0 --u0 300 "
        "--theta-deg 0.2 --mla-offset=0.4,-1.1 --u-rail0 250 --direction 1 --bit-depth 12 "
        "--photons 3000 --read-noise 3 --seed 1"
    ).split(),
    "between": (
        "--width 2400 --height 800 --pp 2040,439.5 --F 50 --f 2.0 --D 0.2 --b 2.4 --u0 400 "
        "--theta-deg=-0.35 --mla-offset=-0.9,0.6 --u-rail0 352.4 --direction 1 --bit-depth 12 "
        "--photons 3000 --read-noise 3 --seed 2"
    ).split(),
    "noisy": (
        "--width 3200 --height 1160 --pp 2580,579.5 --F 35 --f 3.0 --D 0.3 --b 3.6 --u0 302.3 "
        "--theta-deg 0.5 --mla-offset=-0.8,1.5 --board-offset=0.03,-0.02 --u-rail0 350 "
        "--direction -1 --bit-depth 16 --photons 800 --read-noise 8 --seed 3"
    ).split(),
}


def render(name: str, frames: int = 100) -> Path:
    """The cached sweep ``name`` (rendered by indsim in a subprocess when missing)."""
    path = CACHE / f"{name}_{frames}"
    done = path / ".complete"
    if done.is_file():
        return path
    step = 99.0 / max(frames - 1, 1)
    cmd = [sys.executable, "-m", "bench.crosscheck.indsim", str(path), "--frames", str(frames)]
    cmd += ["--start-mm", "0", "--step-mm", f"{step:g}", "--jobs", "2", *SWEEPS[name]]
    subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
    done.touch()
    return path


def evaluate(name: str, frames: int = 100) -> list[dict[str, Any]]:
    path = render(name, frames)
    truth = json.loads((path / "truth.json").read_text())
    t0 = time.perf_counter()
    result = calibrate_archive(path).to_dict()
    seconds = time.perf_counter() - t0
    p_true = {f["index"]: f["p_px"] for f in truth["frames"]}
    p_err = [
        abs(f["patch_size_px"] - p_true[f["index"]])
        for f in result["frames"]
        if f.get("patch_size_px") is not None
    ]
    image_pitch = truth["micro_image_grid"]["pitch_px"]
    rows = [
        ("a error", 100 * abs(result["a_mm"] / truth["a_f_mm"] - 1), "%", 0.05),
        ("b error", 100 * abs(result["b_mm"] / truth["b_mm"] - 1), "%", 0.05),
        ("focus plane error", abs(result["focus"]["object_distance_mm"] - truth["u0_mm"]), "mm", 1),
        ("worst p error (all frames)", max(p_err), "px", 0.05),
        (
            "micro-image pitch error",
            abs(result["mla"]["image_pitch_px"] - image_pitch),
            "px",
            None,
        ),
        (
            "MLA rotation error",
            abs(result["mla"]["rotation_deg"] - truth["theta_deg"]),
            "deg",
            None,
        ),
        (f"calibrate {len(result['frames'])} frames", seconds, "s", None),
    ]
    return [
        {
            "name": f"indsim {name}: {label}",
            "value": value,
            "unit": unit,
            "target": target,
            "ok": None if target is None else bool(value <= target),
        }
        for label, value, unit, target in rows
    ]


def run(names: tuple[str, ...] = ("paper", "between", "noisy")) -> list[dict[str, Any]]:
    rows: list[dict[str, Any]] = []
    for name in names:
        rows.extend(evaluate(name))
    return rows


if __name__ == "__main__":
    from bench.__main__ import print_table

    print_table(run(tuple(sys.argv[1:]) or ("paper", "between", "noisy")))
