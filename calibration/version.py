"""The installed lfcal-station version, recorded with results and served by ``/healthz``."""

from __future__ import annotations

from importlib.metadata import PackageNotFoundError, version

DISTRIBUTION = "lfcal-station"


def software_version() -> str:
    """The installed distribution's version, ``0+unknown`` when run from an uninstalled tree."""
    try:
        return version(DISTRIBUTION)
    except PackageNotFoundError:
        return "0+unknown"


__all__ = ["DISTRIBUTION", "software_version"]
