"""The GenTL producer (.cti) of :class:`drivers.harvesters_camera.HarvestersCamera`.

Checking that a file is a producer before genicam loads it (loading a library that is
not one crashes genicam), keeping one camera object per producer in this process, and
opening the chosen device of the producer's list.  The harvesters namespace (``hv``) is
passed in, so this module imports no camera library itself.

A device is chosen by serial number (``DeviceInfo.serial_number``), else by device id
(``DeviceInfo.id_``); with neither, the producer must list exactly one device.  Listing
devices is the producer's own enumeration (for a GigE Vision producer a discovery on the
producer's interfaces), asked for once per open.
"""

from __future__ import annotations

import ctypes
import os
import threading
import types
from pathlib import Path
from typing import Any, Protocol

from drivers.camera_errors import CameraBusy, CameraNotFound, ProducerLoadError

#: Entry points every GenTL producer exports (GenTL standard, C interface).
GENTL_SYMBOLS = (
    "GCInitLib",
    "GCCloseLib",
    "TLOpen",
    "TLUpdateInterfaceList",
    "IFOpenDevice",
    "DevOpenDataStream",
    "DSQueueBuffer",
    "DSStartAcquisition",
)


class ProducerUser(Protocol):
    """A camera object that holds a producer (named in the ``CameraBusy`` of another)."""

    label: str


# A GenTL producer can be initialised once per process: a second Harvester on the same
# .cti lists no device, and its reset would close the producer under the first one.
_PRODUCERS_IN_USE: dict[Path, ProducerUser] = {}
_PRODUCERS_LOCK = threading.Lock()


def check_producer(cti: Path, *, device: str) -> None:
    """Raise ``ProducerLoadError`` unless ``cti`` is a loadable GenTL producer."""
    if not cti.exists():
        raise ProducerLoadError(f"GenTL producer file {cti} does not exist", device=device)
    if not cti.is_file():
        raise ProducerLoadError(f"GenTL producer path {cti} is not a file", device=device)
    try:
        lib = ctypes.CDLL(str(cti), mode=os.RTLD_LAZY | os.RTLD_LOCAL)
    except OSError as exc:
        raise ProducerLoadError(
            f"{cti} does not load as a shared library: {exc}", device=device
        ) from None
    missing = [name for name in GENTL_SYMBOLS if not hasattr(lib, name)]
    if missing:
        raise ProducerLoadError(
            f"{cti} is a shared library but not a GenTL producer (no {', '.join(missing)})",
            device=device,
        )


def claim_producer(cti: Path, user: ProducerUser) -> None:
    """Register ``user`` as the one camera object on the producer ``cti``; ``CameraBusy``
    if another one holds it."""
    key = cti.resolve()
    with _PRODUCERS_LOCK:
        holder = _PRODUCERS_IN_USE.get(key)
        if holder is not None and holder is not user:
            raise CameraBusy(
                f"the GenTL producer {cti} is already in use by {holder.label} in this process",
                device=user.label,
                hint="close the other camera first; one producer serves one camera object",
            )
        _PRODUCERS_IN_USE[key] = user


def unclaim_producer(cti: Path, user: ProducerUser) -> None:
    """Free the producer ``cti`` if ``user`` holds it."""
    with _PRODUCERS_LOCK:
        if _PRODUCERS_IN_USE.get(cti.resolve()) is user:
            del _PRODUCERS_IN_USE[cti.resolve()]


def choose_device(
    infos: list[Any], *, serial: str | None, device_id: str | None, label: str
) -> Any:
    """The one entry of the producer's device list with ``serial`` (else ``device_id``;
    with neither, the only entry); ``CameraNotFound`` naming the listed devices otherwise."""
    listed = ", ".join(f"{i.id_} (serial {i.serial_number})" for i in infos) or "none"
    if not infos:
        raise CameraNotFound(
            "the GenTL producer lists no device",
            device=label,
            hint="that the camera is connected and powered, and that the producer is the "
            "one for this camera's interface",
        )
    if serial is not None:
        found = [i for i in infos if i.serial_number == serial]
        key = f"serial {serial!r}"
    elif device_id is not None:
        found = [i for i in infos if i.id_ == device_id]
        key = f"id {device_id!r}"
    else:
        found, key = infos, "any device"
    if len(found) != 1:
        raise CameraNotFound(
            f"{len(found)} devices match {key}; the producer lists: {listed}",
            device=label,
            hint="camera.serial (or the device id) in the station config",
        )
    return found[0]


def open_device(
    hv: types.SimpleNamespace,
    cti: Path,
    *,
    serial: str | None,
    device_id: str | None,
    label: str,
) -> tuple[Any, Any]:
    """Load the producer, list its devices once, open the chosen one: ``(Harvester,
    ImageAcquirer)``.  ``CameraBusy`` if the device is open elsewhere, ``CameraNotFound``
    if it is not listed or does not open; the Harvester is reset on failure."""
    harvester = hv.Harvester()
    try:
        harvester.add_file(str(cti))
        harvester.update()
        infos = list(harvester.device_info_list)
        chosen = choose_device(infos, serial=serial, device_id=device_id, label=label)
        try:
            ia = harvester.create(chosen)
        except hv.gentl.GenericException as exc:
            if isinstance(exc, hv.gentl.ResourceInUseException | hv.gentl.AccessDeniedException):
                raise CameraBusy(
                    f"the device is already open elsewhere ({exc})", device=label
                ) from None
            raise CameraNotFound(f"the device cannot be opened: {exc}", device=label) from None
    except BaseException:
        harvester.reset()
        raise
    return harvester, ia


__all__ = [
    "GENTL_SYMBOLS",
    "check_producer",
    "choose_device",
    "claim_producer",
    "open_device",
    "unclaim_producer",
]
