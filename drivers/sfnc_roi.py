"""The region of interest of a GenICam camera: ``Width``, ``Height``, ``OffsetX``, ``OffsetY``.

Used by :class:`drivers.sfnc.SfncCamera`.  Sizes and offsets are in sensor pixels, the
offset is the top-left corner, and ``offset + size <= sensor size``
(:func:`check_roi_fits`, which the simulated camera uses too).  A camera without
``OffsetX``/``OffsetY`` takes ROIs at offset 0 only; sizes must be at least the feature's
minimum and on its increment (counted from the minimum), offsets on their increment.
"""

from __future__ import annotations

from drivers.camera import Roi
from drivers.camera_errors import FeatureMissing, InvalidSetting
from drivers.sfnc_identity import SfncIdentity


def check_roi_fits(roi: Roi, sensor_width: int, sensor_height: int, *, device: str) -> None:
    """Raise ``InvalidSetting`` unless ``roi`` lies on the ``sensor_width x sensor_height``
    sensor (px)."""
    if roi.offset_x + roi.width > sensor_width or roi.offset_y + roi.height > sensor_height:
        raise InvalidSetting(
            f"ROI {roi} does not fit the {sensor_width}x{sensor_height} sensor",
            device=device,
            hint="offset + size <= sensor size",
        )


def current_roi(sfnc: SfncIdentity) -> Roi:
    """The ROI in force (offsets read as 0 if the camera has no OffsetX/Y)."""
    ox = int(sfnc.nodes.get("OffsetX")) if sfnc.has("OffsetX") else 0
    oy = int(sfnc.nodes.get("OffsetY")) if sfnc.has("OffsetY") else 0
    return Roi(int(sfnc.nodes.get("Width")), int(sfnc.nodes.get("Height")), ox, oy)


def full_roi(sfnc: SfncIdentity, roi: Roi | None) -> Roi:
    """``roi``, or the full sensor for None."""
    sensor_w, sensor_h = sfnc.sensor_size()
    return roi if roi is not None else Roi(sensor_w, sensor_h)


def check_roi(sfnc: SfncIdentity, roi: Roi) -> None:
    """Raise ``InvalidSetting`` / ``FeatureMissing`` unless the camera can take ``roi``."""
    sensor_w, sensor_h = sfnc.sensor_size()
    check_roi_fits(roi, sensor_w, sensor_h, device=sfnc.device)
    for axis, offset in (("OffsetX", roi.offset_x), ("OffsetY", roi.offset_y)):
        if offset and not sfnc.has(axis):
            raise FeatureMissing(
                f"an ROI offset needs {axis}, which the camera does not offer",
                feature=axis,
                device=sfnc.device,
                hint="use a ROI at offset 0 or a camera with OffsetX/OffsetY",
            )
    for name, value in (("Width", roi.width), ("Height", roi.height)):
        sfnc.require(name, writable=True)
        lo, _ = sfnc.nodes.bounds(name)
        inc = int(sfnc.nodes.increment(name) or 1)
        if value < lo or (value - int(lo)) % inc:
            raise InvalidSetting(
                f"ROI {name.lower()} {value} is not a legal {name} "
                f"(min {int(lo)}, increment {inc})",
                device=sfnc.device,
                hint=f"{name} = {int(lo)} + k*{inc}",
            )
    for name, value in (("OffsetX", roi.offset_x), ("OffsetY", roi.offset_y)):
        if value:
            inc = int(sfnc.nodes.increment(name) or 1)
            if value % inc:
                raise InvalidSetting(
                    f"ROI {name} {value} is not a multiple of the camera's increment {inc}",
                    device=sfnc.device,
                    hint=f"{name} = k*{inc}",
                )


def apply_roi(sfnc: SfncIdentity, roi: Roi) -> None:
    """Write ``roi`` (checked by :func:`check_roi` first)."""
    # Offsets to 0 first so that any width/height up to the sensor size is legal,
    # then the size, then the wanted offsets.
    for axis in ("OffsetX", "OffsetY"):
        if sfnc.has(axis) and int(sfnc.nodes.get(axis)) != 0:
            sfnc.set_number(axis, 0, integer=True)
    sfnc.set_number("Width", roi.width, integer=True)
    sfnc.set_number("Height", roi.height, integer=True)
    if roi.offset_x:
        sfnc.set_number("OffsetX", roi.offset_x, integer=True)
    if roi.offset_y:
        sfnc.set_number("OffsetY", roi.offset_y, integer=True)


__all__ = ["apply_roi", "check_roi", "check_roi_fits", "current_roi", "full_roi"]
