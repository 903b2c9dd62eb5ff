"""A compact view of ``results.json``: one line per calibration, one line per coverage quantity.

``python -m bench.focus.summary [results.json]`` (default
``out/bench/focus/results.json``). Accuracy lines show |error| per quantity
(``*`` marks a missed target, ``p`` a value taken from the data sheet, a
trailing ``σ`` an error over its reported sigma, used where a wrong data sheet
cannot be corrected); coverage lines show, per quantity, the seeds within 1
and 3 sigma, the RMS of error/sigma and the mean error.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path
from typing import Any

from bench.focus.cache import ROOT, read_json
from bench.focus.evaluate import RIM_PULL

COLUMNS = (
    ("focus-plane error", "focus mm"),
    ("a error", "a %"),
    ("b error", "b %"),
    ("worst per-frame p error", "p px"),
    ("F error", "F %"),
    ("f error", "f %"),
    ("rail zero error", "rail0 mm"),
    ("paper-route a error", "route a %"),
    ("paper-route b error", "route b %"),
    ("worst per-frame p error, measured", "p meas px"),
)


def _cell(row: dict[str, Any] | None) -> str:
    if row is None:
        return "-"
    value = row.get("value")
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return "n/a"
    unit = "σ" if row.get("unit") == "sigma" else ""
    prior = str(row.get("note") or "").startswith("taken from the data sheet")
    mark = "*" if row.get("ok") is False else ("p" if prior else "")
    return f"{value:.4f}{unit}{mark}"


def accuracy_lines(rows: list[dict[str, Any]]) -> list[str]:
    """One line per ``renderer config [priors]`` with the accuracy columns."""
    groups: dict[str, dict[str, dict[str, Any]]] = {}
    failed: list[str] = []
    for row in rows:
        name = str(row["name"])
        if " coverage [" in name or " repeats [" in name or "[" not in name:
            continue
        head, _, what = name.partition("]: ")
        head += "]"
        if "FAILED" in what:
            failed.append(f"{head}: {what} ({row.get('note')})")
            continue
        what = what.removesuffix(" / sigma")
        groups.setdefault(head, {})[what] = row
    width = max((len(h) for h in groups), default=10)
    lines = [" ".join([" " * width, *(f"{c[1]:>10}" for c in COLUMNS), "  fell back"])]
    for head, cells in groups.items():
        fell = cells.get("F and rail zero fell back to priors")
        extra = "" if fell is None else ("  yes" if fell.get("ok") else "  NO")
        lines.append(
            " ".join([head.ljust(width), *(f"{_cell(cells.get(c[0])):>10}" for c in COLUMNS)])
            + extra
        )
    return lines + failed


def repeat_lines(rows: list[dict[str, Any]]) -> list[str]:
    """Per accuracy sweep with repeats and quantity: mean error, its sd over seeds, RMS error."""
    table: dict[tuple[str, str], dict[str, str]] = {}
    for row in rows:
        name = str(row["name"])
        if " repeats [" not in name:
            continue
        head, _, what = name.partition("]: ")
        quantity, _, stat = what.partition(" error ")
        ok = "" if row.get("ok") is not False else "*"
        sign = "+" if stat == "mean" else ""
        table.setdefault((head + "]", quantity), {})[stat] = f"{row['value']:{sign}.4f}{ok}"
    if not table:
        return []
    return _table_lines(table, ("mean", "sd over seeds", "RMS"))


def _table_lines(table: dict[tuple[str, str], dict[str, str]], keys: tuple[str, ...]) -> list[str]:
    """A header of ``keys`` and one line per ``(head, quantity)`` with its cells."""
    width = max((len(h) + len(q) + 1 for h, q in table), default=10)
    lines = [" ".join([" " * width, *(f"{k:>14}" for k in keys)])]
    for (head, quantity), cells in table.items():
        label = f"{head} {quantity}".ljust(width)
        lines.append(" ".join([label, *(f"{cells.get(k, '-'):>14}" for k in keys)]))
    return lines


def coverage_lines(rows: list[dict[str, Any]]) -> list[str]:
    """Per renderer, data sheet and quantity: within 1 sigma, within 3 sigma, RMS z, mean, worst."""
    table: dict[tuple[str, str], dict[str, str]] = {}
    for row in rows:
        name = str(row["name"])
        if " coverage [" not in name or "seeds calibrated" in name or RIM_PULL in name:
            continue
        head, _, what = name.partition("]: ")
        quantity, _, stat = what.partition(" error ")
        cells = table.setdefault((head + "]", quantity), {})
        ok = "" if row.get("ok") is not False else "*"
        if stat.startswith("within"):
            cells[stat.split(" (")[0]] = f"{row.get('note', '').split(';')[0]}{ok}"
        elif stat == "RMS error/sigma":
            cells["rms z"] = f"{row['value']:.2f}"
        else:
            cells[stat] = f"{row['value']:+.4f}" if stat == "mean" else f"{row['value']:.4f}"
    return _table_lines(table, ("within 1 sigma", "within 3 sigma", "rms z", "mean", "worst"))


def rim_pull_lines(rows: list[dict[str, Any]]) -> list[str]:
    """Per renderer: the white pitch's error left after the calibration's rim term (mean,
    note with the pull and the term)."""
    found = [r for r in rows if RIM_PULL in str(r["name"])]
    if not found:
        return []
    width = max(len(str(r["name"]).partition(" [")[0]) for r in found)
    lines = [f"{'':{width}}  {RIM_PULL}"]
    for row in found:
        head = str(row["name"]).partition(" [")[0]
        lines.append(f"{head:{width}}  {row['value']:+.1e} ({row.get('note', '')})")
    return lines


def main(argv: list[str] | None = None) -> int:
    args = sys.argv[1:] if argv is None else argv
    path = Path(args[0]) if args else ROOT / "results.json"
    report = read_json(path)
    rows = report["rows"]
    print("\n".join(accuracy_lines(rows)))
    repeats = repeat_lines(rows)
    if repeats:
        print()
        print("\n".join(repeats))
    print()
    print("\n".join(coverage_lines(rows)))
    pulls = rim_pull_lines(rows)
    if pulls:
        print()
        print("\n".join(pulls))
    load = report.get("load_average_1min", {})
    print(
        f"\nload average (1 min) during the run: mean {load.get('mean', float('nan')):.1f}, "
        f"max {load.get('max', float('nan')):.1f} on {report.get('cpu_count')} CPUs; "
        f"wall time {report.get('wall_seconds', 0.0) / 60:.0f} min; commit {report.get('git_commit')}"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())
