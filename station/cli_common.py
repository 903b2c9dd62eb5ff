"""What the ``lfcal`` commands share: exit codes, :class:`UserError`, the progress bar
and the atomic JSON write (all importable from :mod:`station.cli` too).

Exit codes (the meaning of each is in :mod:`station.cli` and the README): 0 success,
1 internal error, 2 bad input, 3 calibration failed, 4 focus plane at the sweep's edge.
"""

from __future__ import annotations

import json
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

EXIT_OK = 0
EXIT_INTERNAL = 1
EXIT_BAD_INPUT = 2
EXIT_CALIBRATION_FAILED = 3
EXIT_FOCUS_AT_EDGE = 4


class UserError(Exception):
    """A problem the user can fix; printed as one line, exit code 2."""


def progress_bar(label: str) -> Callable[[int, int], None]:
    """A ``report(done, total)`` callback drawing ``label [####----] done/total  t s`` on
    stderr (elapsed seconds since this call; redrawn in place on a terminal, else one
    line every 10 items and at the first and the last)."""
    start = time.monotonic()

    def report(done: int, total: int) -> None:
        if not sys.stderr.isatty() and done not in (1, total) and done % 10:
            return
        elapsed = time.monotonic() - start
        width = 30
        filled = int(width * done / max(total, 1))
        bar = "#" * filled + "-" * (width - filled)
        end = "\n" if done == total or not sys.stderr.isatty() else "\r"
        print(
            f"{label} [{bar}] {done}/{total} {elapsed:6.1f} s", end=end, file=sys.stderr, flush=True
        )

    return report


def write_json(path: Path, data: dict[str, Any]) -> None:
    """Write ``data`` as indented JSON to ``path`` atomically (a temporary file next to it,
    then a rename); parent directories are created; ``UserError`` when it cannot."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp = path.with_name(f".{path.name}.tmp")
        tmp.write_text(json.dumps(data, indent=1, allow_nan=False) + "\n", encoding="utf-8")
        tmp.replace(path)
    except OSError as exc:
        raise UserError(f"cannot write {path}: {exc.strerror or exc}") from None


__all__ = [
    "EXIT_BAD_INPUT",
    "EXIT_CALIBRATION_FAILED",
    "EXIT_FOCUS_AT_EDGE",
    "EXIT_INTERNAL",
    "EXIT_OK",
    "UserError",
    "progress_bar",
    "write_json",
]
