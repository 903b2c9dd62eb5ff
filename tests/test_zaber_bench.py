"""bench.bench_serial runs and reports rows a bench runner can aggregate."""

from __future__ import annotations

from bench import bench_serial


def test_bench_serial_rows() -> None:
    rows = bench_serial.run(n=50)
    assert {tuple(sorted(r)) for r in rows} == {("name", "ok", "target", "unit", "value")}
    pty_median = next(r for r in rows if "pty, median" in r["name"])
    assert pty_median["unit"] == "ms" and pty_median["target"] == 1.0
    assert pty_median["value"] > 0 and isinstance(pty_median["ok"], bool)
    assert all(r["value"] > 0 for r in rows)
