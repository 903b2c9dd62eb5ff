"""What the station does when a device fails: the bounded retry policy and frame checks.

:func:`rule_for` maps every error a sweep step can meet to a :class:`RetryRule`
(first match in :data:`POLICY` wins). Retries are **per step** and bounded;
when they are used up -- or the rule says ``fail`` -- the job fails with the
error's own message (which names the device and what to check) and keeps
every frame already captured. ``resume`` continues it later.

=========================== ========== ===== =================================================
error                       action     extra why
=========================== ========== ===== =================================================
ConnectionLost,             fail       0     the serial link or port is gone: re-plugging and
PortUnavailable                              reopening the chain is the operator's job
NoReply                     retry      1     the port already re-sent idempotent commands
                                             twice; one more step attempt (after 0.5 s)
                                             rides out a busy or rebooting controller; a dead
                                             device fails the job
GarbledReply (ChecksumError) retry     2     noise on the line; every command the station
                                             sends in a step (get, move abs, home) is
                                             idempotent
NotReferenced               rehome     1     the stage lost its reference (power glitch):
                                             home, then repeat the step; captured frames
                                             carry read-back positions, so none is affected
StageStalled, LimitHit      fail       0     mechanical (obstruction, load, limit sensor):
                                             moving again unattended could damage the set-up
MotionTimeout               retry      1     stuck BUSY: the driver has sent stop and the
                                             position is read back, so the move is repeated
PositionMismatch            retry      1     idle off target (slip, drift): re-command the
                                             target once; twice off is a real fault
MoveInterrupted, DeviceBusy retry      1     something else moved or stopped the axis
TargetOutOfRange,           fail       0     configuration / programming errors: repeating
CommandRejected, DeviceFault                 cannot help
CameraTimeout,              retry      2     a lost trigger or dropped packets: grab again
IncompleteFrame                              (the rail has not moved)
CameraLost                  reconnect  1     reopen the camera (``reconnect``), grab again
FrameRejected               retry      1     a blank or saturated frame: grab once more, then
                                             fail with the numbers (lighting, lens cap,
                                             exposure)
any other DeviceError       fail       0
=========================== ========== ===== =================================================

Disk problems are never retried: :class:`calibration.archive.DiskFull` is raised
before anything is written and fails the job at once.

:func:`check_frame` is the per-frame sanity check (blank, saturated), on a
4× subsample so it costs about a millisecond for a 3000×1000 frame.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np
from numpy.typing import NDArray

from drivers.camera_errors import CameraError, CameraLost, CameraTimeout, IncompleteFrame
from drivers.errors import (
    CommandRejected,
    DeviceBusy,
    DeviceError,
    DeviceFault,
    GarbledReply,
    LimitHit,
    MotionTimeout,
    MoveInterrupted,
    NoReply,
    NotReferenced,
    PortUnavailable,
    PositionMismatch,
    StageStalled,
    TargetOutOfRange,
)


class Action(StrEnum):
    """What to do before repeating a failed operation."""

    RETRY = "retry"
    REHOME = "rehome"
    RECONNECT = "reconnect"
    FAIL = "fail"


@dataclass(frozen=True)
class RetryRule:
    """How one kind of error is handled.

    Attributes:
        action: what to do before repeating (``fail``: do not repeat).
        extra_attempts: how many times the operation may be repeated per step.
        delay_s: wait before repeating (s).
        why: the reason for this rule (documentation, and in logs).
    """

    action: Action
    extra_attempts: int
    delay_s: float
    why: str


class FrameRejected(DeviceError):
    """A frame failed the sanity check (blank or saturated).

    Attributes:
        kind: ``"blank"`` or ``"saturated"``.
    """

    default_hint = "lighting, the lens cap, the exposure and gain settings"

    def __init__(self, message: str, *, kind: str, device: str = "camera") -> None:
        self.kind = kind
        super().__init__(message, device=device)


_FAIL = RetryRule(Action.FAIL, 0, 0.0, "not safe or not useful to repeat")

POLICY: tuple[tuple[type[BaseException], RetryRule], ...] = (
    (PortUnavailable, RetryRule(Action.FAIL, 0, 0.0, "link gone; reopening needs the operator")),
    (NoReply, RetryRule(Action.RETRY, 1, 0.5, "port re-sent twice already; once more")),
    (GarbledReply, RetryRule(Action.RETRY, 2, 0.05, "line noise; step commands are idempotent")),
    (NotReferenced, RetryRule(Action.REHOME, 1, 0.0, "reference lost: home and repeat")),
    (StageStalled, RetryRule(Action.FAIL, 0, 0.0, "mechanical stall: operator must check")),
    (LimitHit, RetryRule(Action.FAIL, 0, 0.0, "limit sensor: operator must check")),
    (MotionTimeout, RetryRule(Action.RETRY, 1, 0.1, "stuck busy; driver stopped the axis")),
    (PositionMismatch, RetryRule(Action.RETRY, 1, 0.0, "off target; re-command once")),
    (MoveInterrupted, RetryRule(Action.RETRY, 1, 0.0, "interrupted move; repeat once")),
    (DeviceBusy, RetryRule(Action.RETRY, 1, 0.1, "axis busy; wait idle and repeat once")),
    (TargetOutOfRange, _FAIL),
    (CommandRejected, _FAIL),
    (DeviceFault, _FAIL),
    (CameraTimeout, RetryRule(Action.RETRY, 2, 0.0, "lost trigger or frame: grab again")),
    (IncompleteFrame, RetryRule(Action.RETRY, 2, 0.0, "dropped packets: grab again")),
    (CameraLost, RetryRule(Action.RECONNECT, 1, 0.0, "reopen the camera and grab again")),
    (FrameRejected, RetryRule(Action.RETRY, 1, 0.0, "blank/saturated frame: grab once more")),
    (CameraError, _FAIL),
    (DeviceError, _FAIL),
)
"""Ordered (error class, rule) pairs; the first ``isinstance`` match applies."""


def rule_for(error: BaseException) -> RetryRule:
    """The rule for ``error`` (fail for anything not listed)."""
    for cls, rule in POLICY:
        if isinstance(error, cls):
            return rule
    return _FAIL


# --------------------------------------------------------------------------- frame checks

BLANK_FRACTION = 0.02
"""A frame whose 99.9th percentile is below this fraction of full scale is blank."""

SATURATED_FRACTION = 0.01
"""A frame with more than this fraction of pixels at full scale is saturated."""


@dataclass(frozen=True)
class FrameStats:
    """Cheap statistics of a frame (counts), from a subsample.

    Attributes:
        p999: 99.9th percentile (counts).
        mean: mean (counts).
        saturated_fraction: fraction of pixels at full scale.
        full_scale: largest count of the bit depth.
    """

    p999: float
    mean: float
    saturated_fraction: float
    full_scale: int


def frame_stats(pixels: NDArray[np.integer], bit_depth: int, *, stride: int = 4) -> FrameStats:
    """Statistics of ``pixels`` on every ``stride``-th row and column."""
    sub = np.ascontiguousarray(pixels[::stride, ::stride])
    full = (1 << bit_depth) - 1
    flat = sub.reshape(-1)
    k = max(0, int(flat.size * 0.999) - 1)
    p999 = float(np.partition(flat, k)[k]) if flat.size else 0.0
    return FrameStats(
        p999=p999,
        mean=float(flat.mean()) if flat.size else 0.0,
        saturated_fraction=float(np.count_nonzero(flat >= full)) / max(flat.size, 1),
        full_scale=full,
    )


def check_frame(
    pixels: NDArray[np.integer], bit_depth: int, *, what: str, device: str = "camera"
) -> FrameStats:
    """Raise :class:`FrameRejected` if the frame is blank or saturated; return its stats.

    ``what`` names the frame in the message (``"frame 7 at 35.000 mm"``).
    """
    stats = frame_stats(pixels, bit_depth)
    if stats.p999 < BLANK_FRACTION * stats.full_scale:
        raise FrameRejected(
            f"{what} is blank: 99.9 % of its pixels are below {stats.p999:.0f} counts "
            f"(full scale {stats.full_scale}, mean {stats.mean:.1f})",
            kind="blank",
            device=device,
        )
    if stats.saturated_fraction > SATURATED_FRACTION:
        raise FrameRejected(
            f"{what} is saturated: {100 * stats.saturated_fraction:.1f} % of its pixels at "
            f"full scale ({stats.full_scale}); reduce the exposure or gain",
            kind="saturated",
            device=device,
        )
    return stats


__all__ = [
    "BLANK_FRACTION",
    "POLICY",
    "SATURATED_FRACTION",
    "Action",
    "FrameRejected",
    "FrameStats",
    "RetryRule",
    "check_frame",
    "frame_stats",
    "rule_for",
]
