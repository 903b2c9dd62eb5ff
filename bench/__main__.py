"""Run the benchmarks and print one table: ``python -m bench [names...]``.

Names: simulator, mla, accuracy, speed, render, lab, serial, camera, station, web, fleet
(the default: all of them), crosscheck (the core on an independent
renderer's sweeps; not in the default set, it renders for an hour the first
time) and focus (focus plane, a, b, priors and uncertainty coverage on three
renderers; not in the default set, it renders for hours the first time; options
with ``python -m bench.bench_focus --help``). Each module ``bench.bench_<name>``
exposes ``run() -> list[dict]`` with rows ``name, value, unit, target, ok`` (and
an optional ``note``, printed under the table).
"""

from __future__ import annotations

import importlib
import sys
from typing import Any

ALL = (
    "simulator",
    "mla",
    "accuracy",
    "speed",
    "render",
    "lab",
    "serial",
    "camera",
    "station",
    "web",
    "fleet",
)


def print_table(rows: list[dict[str, Any]]) -> None:
    if not rows:
        print("no benchmark rows")
        return
    w = max(len(str(r["name"])) for r in rows)
    print(f"{'benchmark'.ljust(w)}  {'value':>12}  {'unit':<5} {'target':>10}  ok")
    print("-" * (w + 40))
    for r in rows:
        target = "" if r.get("target") is None else f"{r['target']:g}"
        ok = "" if r.get("ok") is None else ("yes" if r["ok"] else "NO")
        print(
            f"{str(r['name']).ljust(w)}  {float(r['value']):12.4f}  {str(r['unit']):<5} "
            f"{target:>10}  {ok}"
        )
    notes = [r for r in rows if r.get("note") and r.get("ok") is False]
    if notes:
        print("\nnotes on failed rows:")
        for r in notes:
            print(f"  {r['name']}: {r['note']}")


def main(argv: list[str]) -> int:
    names = argv or list(ALL)
    rows: list[dict[str, Any]] = []
    for name in names:
        try:
            module = importlib.import_module(f"bench.bench_{name}")
        except ModuleNotFoundError:
            print(f"(no benchmark {name!r})", file=sys.stderr)
            continue
        print(f"running {name} ...", file=sys.stderr, flush=True)
        rows.extend(module.run())
    print_table(rows)
    return 0 if all(r.get("ok") is not False for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
