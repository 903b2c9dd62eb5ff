"""Serial round-trip overhead of the Zaber driver against the emulator.

Measures ``get pos`` request -> matching reply (message id, checksum verified)
through :class:`drivers.zaber.ZaberPort` over a real pseudo-terminal, and over
TCP on 127.0.0.1 for comparison.  This is the software overhead the station
pays per status poll; on a real 115200-baud line the wire adds ~3 ms for a
~40-byte exchange.  Target: median <= 1 ms over the pty.

Run: ``python -m bench.bench_serial [--n 2000]``.
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Any

from drivers.sim.emulator_links import Transport
from drivers.sim.zaber_emulator import ZaberEmulator
from drivers.zaber import ZaberPort

TARGET_MEDIAN_MS = 1.0


def _round_trips_ms(transport: Transport, n: int, warmup: int = 100) -> list[float]:
    with ZaberEmulator(transport=transport) as emulator:
        with ZaberPort(emulator.url) as port:
            port.enable_checksums(1)
            for _ in range(warmup):
                port.request(1, 1, "get pos")
            samples = []
            for _ in range(n):
                start = time.perf_counter()
                port.request(1, 1, "get pos")
                samples.append((time.perf_counter() - start) * 1000.0)
            return samples


def _p95(samples: list[float]) -> float:
    return statistics.quantiles(samples, n=20, method="inclusive")[-1]


def run(n: int = 2000) -> list[dict[str, Any]]:
    """Rows: name, value, unit, target (None = informative), ok (None = no target)."""
    rows: list[dict[str, Any]] = []
    for transport in ("pty", "tcp"):
        samples = _round_trips_ms(transport, n)
        median = statistics.median(samples)
        target = TARGET_MEDIAN_MS if transport == "pty" else None
        rows.append(
            {
                "name": f"zaber get pos round trip, {transport}, median",
                "value": median,
                "unit": "ms",
                "target": target,
                "ok": None if target is None else bool(median <= target),
            }
        )
        rows.append(
            {
                "name": f"zaber get pos round trip, {transport}, p95",
                "value": _p95(samples),
                "unit": "ms",
                "target": None,
                "ok": None,
            }
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m bench.bench_serial", description=__doc__)
    parser.add_argument("--n", type=int, default=2000, help="round trips per transport")
    args = parser.parse_args(argv)
    rows = run(args.n)
    width = max(len(r["name"]) for r in rows)
    print(f"{'benchmark'.ljust(width)}  {'value':>8}  unit  {'target':>8}  ok")
    for r in rows:
        target = "" if r["target"] is None else f"<= {r['target']:g}"
        ok = "" if r["ok"] is None else ("yes" if r["ok"] else "NO")
        print(f"{r['name'].ljust(width)}  {r['value']:8.3f}  {r['unit']:<4}  {target:>8}  {ok}")
    return 0 if all(r["ok"] is not False for r in rows) else 1


if __name__ == "__main__":
    raise SystemExit(main())
