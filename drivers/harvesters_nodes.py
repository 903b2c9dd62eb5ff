"""GenICam features through harvesters: the genapi node map and the translation of errors.

Used by :class:`drivers.harvesters_camera.HarvestersCamera`.  The harvesters namespace
(``hv``: ``genapi``, ``gentl``, ``Harvester``, ``ImageAcquirer``, ``Callback``) is passed
in, so this module imports no camera library itself.

genicam/GenTL exceptions become typed camera errors (:func:`genicam_errors`): out of
range is ``InvalidSetting``, a feature not accessible now ``FeatureMissing``, a resource
in use or access denied ``CameraBusy``, I/O, invalid handle, closed, not initialised or
a genapi timeout ``CameraLost`` (the camera marks itself lost first), any other
genicam/GenTL error ``CameraError``; camera errors pass through unchanged.
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


@contextmanager
def genicam_errors(
    hv: types.SimpleNamespace, what: str, label: str, on_lost: Callable[[], None]
) -> Iterator[None]:
    """Translate genicam/GenTL exceptions raised inside the block into typed camera errors.

    Args:
        hv: the harvesters namespace.
        what: the feature (or operation) named in the error.
        label: the camera's label (``device`` of the error).
        on_lost: called before ``CameraLost`` is raised (the camera marks itself lost).
    """
    try:
        yield
    except CameraError:
        raise
    except hv.genapi.OutOfRangeException as exc:
        raise InvalidSetting(f"{what}: {exc}", device=label) from None
    except hv.genapi.AccessException as exc:
        raise FeatureMissing(
            f"{what} is not accessible now ({exc})", feature=what, device=label
        ) from None
    except (hv.gentl.ResourceInUseException, hv.gentl.AccessDeniedException) as exc:
        raise CameraBusy(f"{what}: {exc}", device=label) from None
    except (
        hv.gentl.IoException,
        hv.gentl.InvalidHandleException,
        hv.gentl.NotInitializedException,
        hv.gentl.ClosedException,
        hv.genapi.TimeoutException,
    ) as exc:
        on_lost()
        raise CameraLost(f"the camera stopped answering ({what}: {exc})", device=label) from None
    except (hv.gentl.GenericException, hv.genapi.GenericException) as exc:
        raise CameraError(f"{what}: {exc}", device=label) from None


class NodesOwner(Protocol):
    """What :class:`HarvestersNodes` needs of its camera."""

    label: str

    def _node_map(self) -> Any: ...

    def _gerrors(self, what: str) -> AbstractContextManager[None]: ...


class HarvestersNodes:
    """:class:`drivers.camera.NodeMap` on a genapi node map (the owner's, looked up per
    call, so a closed camera raises ``CameraLost``)."""

    def __init__(self, owner: NodesOwner, hv: types.SimpleNamespace) -> None:
        self._owner = owner
        self._hv = hv

    def _node(self, name: str) -> Any:
        node_map = self._owner._node_map()
        try:
            return node_map.get_node(name)
        except self._hv.genapi.LogicalErrorException:
            return None

    def _require(self, name: str) -> Any:
        node = self._node(name)
        if node is None:
            raise no_such_feature(name, device=self._owner.label)
        return node

    def is_available(self, name: str) -> bool:
        node = self._node(name)
        with self._owner._gerrors(name):
            return node is not None and bool(self._hv.genapi.is_available(node))

    def is_writable(self, name: str) -> bool:
        node = self._require(name)
        with self._owner._gerrors(name):
            return bool(self._hv.genapi.is_writable(node))

    def get(self, name: str) -> int | float | str | bool:
        node = self._require(name)
        with self._owner._gerrors(name):
            value = node.value
        return value if isinstance(value, int | float | str | bool) else str(value)

    def set(self, name: str, value: int | float | str | bool) -> None:
        node = self._require(name)
        with self._owner._gerrors(name):
            node.value = value

    def execute(self, name: str) -> None:
        node = self._require(name)
        with self._owner._gerrors(name):
            node.execute()

    def enum_entries(self, name: str) -> tuple[str, ...]:
        genapi = self._hv.genapi
        node = self._require(name)
        with self._owner._gerrors(name):
            return tuple(str(e.symbolic) for e in node.entries if genapi.is_available(e))

    def bounds(self, name: str) -> tuple[float, float]:
        node = self._require(name)
        with self._owner._gerrors(name):
            return float(node.min), float(node.max)

    def increment(self, name: str) -> float | None:
        genapi = self._hv.genapi
        node = self._require(name)
        with self._owner._gerrors(name):
            if isinstance(node, genapi.IInteger):
                return float(node.inc)
            if isinstance(node, genapi.IFloat) and node.has_inc():
                return float(node.inc)
        return None


__all__ = ["HarvestersNodes", "NodesOwner", "genicam_errors"]
