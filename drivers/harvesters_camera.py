"""GenICam cameras through a GenTL producer (.cti) with harvesters, software-triggered.

The producer is given by path (``camera.cti`` in the station config).  The camera is
chosen from the producer's device list by serial number (``DeviceInfo.serial_number``)
or device id (``DeviceInfo.id_``); with neither, the producer must list exactly one
device.  Listing devices is the producer's own enumeration: for a GigE Vision producer
that is a discovery on the producer's interfaces, which is the producer's business (the
station only ever asks for its list once per open).

``harvesters`` and ``genicam`` are imported on first use.  A .cti that is missing, not a
shared library, or a library that is not a GenTL producer raises ``ProducerLoadError``
before harvesters is handed the file (loading a non-producer library crashes genicam).

``harvesters`` silently drops incomplete buffers; this driver watches its
``INCOMPLETE_BUFFER`` event so that a damaged frame raises ``IncompleteFrame`` instead of
looking like a timeout.

The producer file's check, the one-camera-per-producer rule and the choice of the device
are in :mod:`drivers.gentl_producer`; the node map and the genicam errors in
:mod:`drivers.harvesters_nodes`; how a buffer becomes a :class:`Frame` in
:mod:`drivers.harvesters_frames`.  Opening, identity, configuration and the reconnect
loop are shared with the Aravis backend (:class:`drivers.genicam_camera.GenICamCamera`).
"""

from __future__ import annotations

import logging
import os
import time
import types
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

from drivers.camera import Frame, TransportSettings
from drivers.camera_errors import (
    BackendUnavailable,
    CameraLost,
    IncompleteFrame,
)
from drivers.genicam_camera import GenICamCamera
from drivers.gentl_producer import (
    GENTL_SYMBOLS,
    check_producer,
    claim_producer,
    open_device,
    unclaim_producer,
)
from drivers.harvesters_frames import buffer_to_frame
from drivers.harvesters_nodes import HarvestersNodes, genicam_errors
from drivers.sfnc import SfncCamera

log = logging.getLogger(__name__)

_HV: types.SimpleNamespace | None = None


def _harvesters() -> types.SimpleNamespace:
    """Import harvesters and genicam on first use."""
    global _HV
    if _HV is None:
        try:
            from genicam import genapi, gentl
            from harvesters.core import Callback, Harvester, ImageAcquirer
        except ImportError as exc:
            raise BackendUnavailable(f"harvesters/genicam cannot be imported: {exc}") from exc
        _HV = types.SimpleNamespace(
            genapi=genapi,
            gentl=gentl,
            Harvester=Harvester,
            ImageAcquirer=ImageAcquirer,
            Callback=Callback,
        )
    return _HV


class HarvestersCamera(GenICamCamera):
    """A GenICam camera through a GenTL producer with harvesters, software-triggered.

    Args:
        cti: path of the GenTL producer file (.cti).
        serial: serial number of the camera in the producer's device list.
        device_id: device id in the producer's list (used when no serial is given).
        n_buffers: buffers announced to the producer (default: ``transport.buffer_count``).
        transport: streaming parameters: buffer count, and the GenICam transport features
            the camera offers (``GevSCPSPacketSize``, ``DeviceLinkThroughputLimit``); the
            socket buffer and packet timing belong to the producer's own configuration.

    Implements :class:`drivers.camera.Camera`.
    """

    backend = "harvesters"

    def __init__(
        self,
        cti: str | os.PathLike[str],
        *,
        serial: str | None = None,
        device_id: str | None = None,
        n_buffers: int | None = None,
        transport: TransportSettings | None = None,
    ) -> None:
        self.transport = transport or TransportSettings()
        n_buffers = self.transport.buffer_count if n_buffers is None else n_buffers
        if n_buffers < 1:
            raise ValueError("n_buffers >= 1")
        self.cti = Path(cti)
        self.serial = serial
        self.device_id = device_id
        self.n_buffers = n_buffers
        which = serial or device_id
        super().__init__(f"gentl://{self.cti}" + (f"#{which}" if which else ""))
        self._harvester: Any = None
        self._ia: Any = None
        self._incomplete = 0

    # ------------------------------------------------------------------ lifecycle

    def close(self) -> None:
        """Stop acquisition, release the device and unload the producer."""
        with self._lock:
            self._release()
            self._lost = False

    def grab(self, timeout_s: float = 5.0) -> Frame:
        """Return the next frame within ``timeout_s`` s: fire one software trigger first,
        or (hardware trigger) wait for the frame the trigger line starts.

        Raises ``CameraTimeout``, ``IncompleteFrame`` or ``CameraLost`` (the next grab
        then reopens the camera once).
        """
        self._check_timeout(timeout_s)
        with self._lock:
            sfnc = self._session()
            self._start()
            self._drain_stale()
            incomplete_before = self._incomplete
            trigger = self._fire_trigger(sfnc)
            deadline = time.monotonic() + timeout_s
            buffer = None
            while buffer is None and self._incomplete == incomplete_before:
                remaining = deadline - time.monotonic()
                if remaining <= 0:
                    break
                with self._gerrors("fetch"):
                    buffer = self._ia.try_fetch(timeout=remaining)
            if buffer is None:
                if self._incomplete != incomplete_before:
                    raise IncompleteFrame(
                        "the producer delivered an incomplete buffer",
                        status="incomplete",
                        device=self.label,
                    )
                raise self._no_frame(timeout_s, trigger)
            try:
                return buffer_to_frame(
                    buffer,
                    applied=self._applied,
                    info=self._info,
                    temperature_c=self.temperature_c,
                    label=self.label,
                    gerrors=self._gerrors,
                )
            finally:
                buffer.queue()

    # ------------------------------------------------------------------ internals

    def _node_map(self) -> Any:
        if self._ia is None:
            raise CameraLost("the camera connection is closed", device=self.label)
        return self._ia.remote_device.node_map

    def _gerrors(self, what: str) -> AbstractContextManager[None]:
        """Translate genicam/GenTL exceptions into typed camera errors."""
        return genicam_errors(_harvesters(), what, self.label, self._mark_lost)

    def _open_session(self) -> None:
        hv = _harvesters()
        check_producer(self.cti, device=self.label)
        claim_producer(self.cti, self)
        try:
            self._open_device(hv)
        except BaseException:
            unclaim_producer(self.cti, self)
            raise

    def _open_device(self, hv: types.SimpleNamespace) -> None:
        self._harvester, self._ia = open_device(
            hv, self.cti, serial=self.serial, device_id=self.device_id, label=self.label
        )
        ia = self._ia
        try:
            ia.num_buffers = max(self.n_buffers, int(ia.min_num_buffers))
            owner = self

            class _Incomplete(hv.Callback):  # type: ignore[name-defined]
                def emit(self, context: object = None) -> None:
                    owner._incomplete += 1

            ia.add_callback(hv.ImageAcquirer.Events.INCOMPLETE_BUFFER, _Incomplete())
            self._sfnc = SfncCamera(
                HarvestersNodes(self, hv), self.label, feature_hint="the camera's GenICam features"
            )
            self.warnings = self._sfnc.apply_transport(self.transport)
            self._set_up_session(self._sfnc)
        except BaseException:
            self._release()
            raise
        self._lost = False

    def _release(self) -> None:
        ia, harvester = self._ia, self._harvester
        self._ia = self._harvester = None
        self._sfnc = None
        for action in (
            (lambda: ia.destroy()) if ia is not None else None,
            (lambda: harvester.reset()) if harvester is not None else None,
        ):
            if action is None:
                continue
            try:
                action()
            except Exception as exc:  # the device may be gone; release what we can
                log.warning("%s: release failed: %s", self.label, exc)
        unclaim_producer(self.cti, self)

    def _mark_lost(self) -> None:
        self._lost = True
        self._release()

    def _reopen_once(self) -> None:
        self._open_again("the camera is still not available")
        log.info("%s: reconnected", self.label)

    def _start(self) -> None:
        if not self._ia.is_acquiring():
            with self._gerrors("AcquisitionStart"):
                self._ia.start()

    def _stop_acquisition(self) -> None:
        if self._ia is not None and self._ia.is_acquiring():
            with self._gerrors("AcquisitionStop"):
                self._ia.stop()

    def _drain_stale(self) -> None:
        """Requeue frames of earlier triggers so the next fetch is this trigger's frame."""
        while True:
            with self._gerrors("fetch"):
                old = self._ia.try_fetch(timeout=1e-3)
            if old is None:
                return
            old.queue()


__all__ = ["GENTL_SYMBOLS", "HarvestersCamera", "check_producer"]
