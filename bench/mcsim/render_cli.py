"""The command-line flow the file renderers share (mcsim, wavesim): check the options, refuse
an output directory that holds anything but a previous render (replaced only with
``--force``), render with progress on stderr, print one summary line (``OUT: summary``)."""

from __future__ import annotations

import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any, TypeVar

from bench.mcsim.camera import OpticsError
from bench.mcsim.sweep import ARCHIVE_ENTRIES, COMPLETE, clear_archive

Spec = TypeVar("Spec")


def render_main(
    prog: str,
    args: dict[str, Any],
    build: Callable[..., Spec],
    render: Callable[[Spec, Path, int, Callable[[str], None]], dict[str, Any]],
    summary: Callable[[Spec, dict[str, Any]], str],
) -> int:
    """Exit status of rendering ``args`` (the parsed options with ``out_dir``, ``force`` and
    ``jobs``): 2 for impossible options, 1 for an occupied or unwritable directory."""
    out_dir: Path = args.pop("out_dir")
    force: bool = args.pop("force")
    jobs: int = args.pop("jobs")
    try:
        spec = build(**args)
    except OpticsError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    if jobs < 1:
        print(f"{prog}: error: --jobs must be >= 1", file=sys.stderr)
        return 2
    if out_dir.exists() and any(out_dir.iterdir()):
        foreign = sorted(
            p.name for p in out_dir.iterdir() if p.name not in (*ARCHIVE_ENTRIES, COMPLETE)
        )
        if foreign or not force:
            what = (
                f"holds {', '.join(foreign)}"
                if foreign
                else "holds a previous render (use --force)"
            )
            print(f"{prog}: error: {out_dir} {what}", file=sys.stderr)
            return 1
        clear_archive(out_dir)
    try:
        log = render(spec, out_dir, jobs, lambda line: print(line, file=sys.stderr, flush=True))
    except OSError as exc:
        print(f"{prog}: error: writing {out_dir}: {exc}", file=sys.stderr)
        return 1
    print(f"{out_dir}: {summary(spec, log)}")
    return 0
