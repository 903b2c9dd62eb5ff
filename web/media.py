"""Images and files served by the API: frame previews, plots, rendered images, the archive zip.

Pure helpers on files and result dicts; the routes (:mod:`web.routes_media`) add
HTTP. Plots and rendered images of a finished job never change, so they are
kept in a small in-memory cache (:class:`BytesCache`).
"""

from __future__ import annotations

import threading
import zipfile
from collections import OrderedDict
from collections.abc import Callable, Hashable, Iterator
from pathlib import Path
from typing import Any

import cv2
import numpy as np
from numpy.typing import NDArray

from calibration.export_model import designed_patch_px as designed_patch_from_optics
from calibration.lens_grid import LensGrid
from calibration.plots import render_png
from calibration.rendering import render_patches, seamless_patch_px
from calibration.report_archive import focus_frame_index as nearest_focus_frame
from station.config import StationConfig

ZIP_CHUNK = 1 << 20


class MediaError(ValueError):
    """The image cannot be made (the route answers 409 with the message)."""


class BytesCache:
    """A small thread-safe LRU cache of bytes (plots, rendered images)."""

    def __init__(self, max_items: int = 64) -> None:
        self._items: OrderedDict[Hashable, bytes] = OrderedDict()
        self._lock = threading.Lock()
        self._max = max_items

    def get_or_make(self, key: Hashable, make: Callable[[], bytes]) -> bytes:
        """The cached bytes for ``key``, made (outside the lock) on a miss."""
        with self._lock:
            data = self._items.get(key)
            if data is not None:
                self._items.move_to_end(key)
                return data
        data = make()
        with self._lock:
            self._items[key] = data
            while len(self._items) > self._max:
                self._items.popitem(last=False)
        return data


def read_raw(path: Path) -> NDArray[Any]:
    """A recorded frame (grey PNG, 8 or 16 bit) as an array; :class:`MediaError` if unreadable."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise MediaError(f"the frame file {path.name} cannot be read")
    if image.ndim == 3:
        image = cv2.cvtColor(image, cv2.COLOR_BGR2GRAY)
    return np.asarray(image)


def preview_png(path: Path, max_width: int) -> bytes:
    """A frame downscaled to at most ``max_width`` px wide (area average), 8-bit stretched PNG."""
    raw = read_raw(path)
    h, w = raw.shape
    if w > max_width:
        new_h = max(1, round(h * max_width / w))
        raw = cv2.resize(raw.astype(np.float32), (max_width, new_h), interpolation=cv2.INTER_AREA)
    return render_png(None, raw)


def designed_patch_px(config: StationConfig) -> float:
    """The ESIF patch size ``p = Q·D/δ`` (px) of the designed optics.

    ``Q = b/a`` from ``optics.designed_b_mm`` and ``optics.designed_a_mm`` (or,
    without it, the microlens's thin-lens conjugate ``a = f·b/(b − f)``).
    """
    o = config.optics
    if o.designed_b_mm is None:
        raise MediaError(
            "the configuration has no designed optics: set [optics] designed_b_mm "
            "(and optionally designed_a_mm) to render with the designed patch size"
        )
    try:
        return designed_patch_from_optics(
            b_mm=o.designed_b_mm,
            a_mm=o.designed_a_mm,
            f_mm=o.mla_focal_mm,
            D_mm=o.mla_pitch_mm,
            delta_mm=o.pixel_pitch_mm,
        )
    except ValueError as exc:
        raise MediaError(f"impossible designed optics: {exc}") from None


def focus_frame_index(result: dict[str, Any]) -> int:
    """The frame whose rail position is nearest the focus plane (else the middle frame)."""
    try:
        return nearest_focus_frame(result)
    except ValueError as exc:
        raise MediaError(str(exc)) from None


def image_grid(result: dict[str, Any]) -> tuple[LensGrid, float, float]:
    """The micro-image lattice of a result, with the lens and micro-image pitches (px)."""
    mla = result.get("mla") or {}
    grid = mla.get("image_grid") or {}
    try:
        lattice = LensGrid(
            (float(grid["origin_px"][0]), float(grid["origin_px"][1])),
            float(grid["pitch_px"]),
            float(np.radians(grid["rotation_deg"])),
        )
        return lattice, float(mla["lens_pitch_px"]), float(mla["image_pitch_px"])
    except (KeyError, TypeError, IndexError, ValueError):
        raise MediaError("the result has no micro-image grid (mla.image_grid)") from None


def rendered_png(
    raw: NDArray[Any], result: dict[str, Any], patch_px: float, *, upright: bool = True
) -> bytes:
    """Patch-render ``raw`` with the ESIF patch size ``patch_px`` (converted to the
    seam-free rendering patch); PNG bytes, upright (the board as seen) by default."""
    lattice, lens_pitch, image_pitch = image_grid(result)
    patch = seamless_patch_px(patch_px, lens_pitch_px=lens_pitch, image_pitch_px=image_pitch)
    if not patch > 0:
        raise MediaError(f"the rendering patch size is {patch:g} px; nothing to render")
    try:
        image = render_patches(raw, image_grid=lattice, patch_size_px=patch)
    except ValueError as exc:
        raise MediaError(f"cannot render the frame: {exc}") from None
    if upright:
        image = np.rot90(image, 2)
    return render_png(None, image)


def archive_files(directory: Path) -> list[Path]:
    """Every file of an archive directory, sorted (hidden and ``.tmp`` files left out)."""
    out = []
    for path in sorted(directory.rglob("*")):
        rel = path.relative_to(directory)
        if not path.is_file() or any(p.startswith(".") for p in rel.parts):
            continue
        if path.suffix == ".tmp":
            continue
        out.append(path)
    return out


class _Sink:
    """A write-only stream that hands its bytes on in pieces (for streaming zip files)."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []

    def write(self, data: bytes) -> int:
        self.parts.append(bytes(data))
        return len(data)

    def flush(self) -> None:
        pass

    def close(self) -> None:
        pass

    def take(self) -> bytes:
        data = b"".join(self.parts)
        self.parts.clear()
        return data


def zip_stream(directory: Path, root_name: str) -> Iterator[bytes]:
    """The files of ``directory`` as a zip (stored, not deflated: PNGs are compressed),
    produced piece by piece with bounded memory; entries under ``root_name/``."""
    sink = _Sink()
    with zipfile.ZipFile(sink, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as zf:
        for path in archive_files(directory):
            arcname = f"{root_name}/{path.relative_to(directory).as_posix()}"
            size = path.stat().st_size
            info = zipfile.ZipInfo.from_file(path, arcname)
            with path.open("rb") as src, zf.open(info, "w", force_zip64=size > 1 << 31) as dst:
                while chunk := src.read(ZIP_CHUNK):
                    dst.write(chunk)
                    if data := sink.take():
                        yield data
            if data := sink.take():
                yield data
    if data := sink.take():
        yield data


__all__ = [
    "BytesCache",
    "MediaError",
    "archive_files",
    "designed_patch_px",
    "focus_frame_index",
    "image_grid",
    "preview_png",
    "read_raw",
    "rendered_png",
    "zip_stream",
]
