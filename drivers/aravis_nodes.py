"""GenICam features of an Aravis device: the node map and the translation of GLib errors.

Used by :class:`drivers.aravis_camera.AravisCamera`.  As in :mod:`drivers.aravis_connect`,
the Aravis namespace (``ar``: the ``Aravis``, ``Gio`` and ``GLib`` modules of PyGObject)
is passed in, so this module imports no camera library itself.

GLib errors of Aravis 0.8 (``ArvDeviceError``, ``ArvGcError``) become typed camera errors
(:func:`glib_errors`): a device that stops answering (timeout, not connected, transfer)
is ``CameraLost``, a missing node or enumeration entry or a read-only feature
``FeatureMissing``, a value out of range ``InvalidSetting``, a refused write because
another application took control ``CameraBusy``, anything else ``CameraError``.
"""

from __future__ import annotations

import types
from collections.abc import Callable, Iterator
from contextlib import AbstractContextManager, contextmanager
from typing import Any, Protocol

from drivers.camera_errors import (
    CameraBusy,
    CameraError,
    CameraLost,
    FeatureMissing,
    InvalidSetting,
)
from drivers.sfnc_features import no_such_feature

# GLib error codes (ArvDeviceError, ArvGcError in Aravis 0.8).
_DEVICE_NOT_CONNECTED, _DEVICE_TRANSFER, _DEVICE_TIMEOUT = 2, 4, 5
_DEVICE_FEATURE_NOT_FOUND, _DEVICE_NOT_CONTROLLER, _DEVICE_ACCESS_DENIED = 1, 10, 17
_GC_OUT_OF_RANGE, _GC_NODE_NOT_FOUND, _GC_ENTRY_NOT_FOUND, _GC_READ_ONLY = 4, 7, 8, 10


@contextmanager
def glib_errors(glib: Any, feature: str, label: str, on_lost: Callable[[], None]) -> Iterator[None]:
    """Translate Aravis GLib errors raised inside the block into typed camera errors.

    Args:
        glib: the ``GLib`` module of PyGObject.
        feature: the feature (or operation) named in the error.
        label: the camera's label (``device`` of the error).
        on_lost: called before ``CameraLost`` is raised (the camera marks itself lost).
    """
    try:
        yield
    except glib.Error as exc:
        domain, code, text = exc.domain, exc.code, exc.message
        if domain == "arv-device-error-quark":
            if code in (_DEVICE_TIMEOUT, _DEVICE_NOT_CONNECTED, _DEVICE_TRANSFER):
                on_lost()
                raise CameraLost(
                    f"the camera stopped answering ({feature}: {text})", device=label
                ) from None
            if code == _DEVICE_FEATURE_NOT_FOUND:
                raise FeatureMissing(
                    f"the camera does not offer {feature!r} ({text})",
                    feature=feature,
                    device=label,
                ) from None
            if code in (_DEVICE_NOT_CONTROLLER, _DEVICE_ACCESS_DENIED):
                raise CameraBusy(
                    f"the camera refused {feature} ({text}): control was taken over",
                    device=label,
                ) from None
        elif domain == "arv-gc-error-quark":
            if code in (_GC_NODE_NOT_FOUND, _GC_ENTRY_NOT_FOUND, _GC_READ_ONLY):
                raise FeatureMissing(f"{feature}: {text}", feature=feature, device=label) from None
            if code == _GC_OUT_OF_RANGE:
                raise InvalidSetting(f"{feature}: {text}", device=label) from None
        raise CameraError(f"{feature}: {text} ({domain} {code})", device=label) from None


class NodesOwner(Protocol):
    """What :class:`AravisNodes` needs of its camera."""

    label: str
    _device: Any

    def _gerrors(self, feature: str) -> AbstractContextManager[None]: ...


class AravisNodes:
    """:class:`drivers.camera.NodeMap` on an ``ArvDevice``.

    It holds its owner, not the device, so that dropping the owner's device really
    releases it (a traceback keeping this object alive keeps no GigE session open).
    """

    def __init__(self, owner: NodesOwner, ar: types.SimpleNamespace) -> None:
        self._owner = owner
        self._ar = ar

    @property
    def _dev(self) -> Any:
        device = self._owner._device
        if device is None:
            raise CameraLost("the camera connection is closed", device=self._owner.label)
        return device

    def _node(self, name: str) -> Any:
        with self._owner._gerrors(name):
            return self._dev.get_feature(name)

    def _kind(self, name: str) -> str:
        ar = self._ar.Aravis
        node = self._node(name)
        if node is None:
            raise no_such_feature(name, device=self._owner.label)
        for kind, cls in (
            ("enum", ar.GcEnumeration),
            ("bool", ar.GcBoolean),
            ("float", ar.GcFloat),
            ("int", ar.GcInteger),
            ("str", ar.GcString),
            ("command", ar.GcCommand),
        ):
            if isinstance(node, cls):
                return kind
        return "unknown"

    def is_available(self, name: str) -> bool:
        if self._node(name) is None:
            return False
        with self._owner._gerrors(name):
            return bool(self._dev.is_feature_available(name))

    def is_writable(self, name: str) -> bool:
        ar = self._ar.Aravis
        with self._owner._gerrors(name):
            mode = self._dev.get_feature_access_mode(name)
        return mode in (ar.GcAccessMode.RW, ar.GcAccessMode.WO)

    def get(self, name: str) -> int | float | str | bool:
        kind = self._kind(name)
        with self._owner._gerrors(name):
            if kind in ("enum", "str"):
                return str(self._dev.get_string_feature_value(name))
            if kind == "bool":
                return bool(self._dev.get_boolean_feature_value(name))
            if kind == "float":
                return float(self._dev.get_float_feature_value(name))
            if kind == "int":
                return int(self._dev.get_integer_feature_value(name))
        raise FeatureMissing(
            f"{name} cannot be read as a value", feature=name, device=self._owner.label
        )

    def set(self, name: str, value: int | float | str | bool) -> None:
        kind = self._kind(name)
        with self._owner._gerrors(name):
            if kind in ("enum", "str"):
                self._dev.set_string_feature_value(name, str(value))
            elif kind == "bool":
                self._dev.set_boolean_feature_value(name, bool(value))
            elif kind == "float":
                self._dev.set_float_feature_value(name, float(value))
            elif kind == "int":
                self._dev.set_integer_feature_value(name, int(value))
            else:
                raise FeatureMissing(
                    f"{name} cannot be set", feature=name, device=self._owner.label
                )

    def execute(self, name: str) -> None:
        with self._owner._gerrors(name):
            self._dev.execute_command(name)

    def enum_entries(self, name: str) -> tuple[str, ...]:
        with self._owner._gerrors(name):
            return tuple(self._dev.dup_available_enumeration_feature_values_as_strings(name) or ())

    def bounds(self, name: str) -> tuple[float, float]:
        kind = self._kind(name)
        with self._owner._gerrors(name):
            if kind == "float":
                lo, hi = self._dev.get_float_feature_bounds(name)
            else:
                lo, hi = self._dev.get_integer_feature_bounds(name)
        return float(lo), float(hi)

    def increment(self, name: str) -> float | None:
        kind = self._kind(name)
        with self._owner._gerrors(name):
            if kind == "int":
                return float(self._dev.get_integer_feature_increment(name))
            if kind == "float":
                inc = float(self._dev.get_float_feature_increment(name))
                return inc if inc > 0 else None
        return None


__all__ = ["AravisNodes", "NodesOwner", "glib_errors"]
