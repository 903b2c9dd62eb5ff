"""The time of the emulated Zaber chain: scaled motion time and a queue of timed actions.

Two time bases: motion runs in *scaled* seconds (real seconds since the clock started,
times ``speedup``), so a move lasts its kinematic duration divided by ``speedup``; the
actions of the queue (a motion that settles, a late reply, an injected fault) are due
at *real* :func:`time.monotonic` times.  Not thread-safe: the emulator calls it with its
lock held and runs the due actions from its serving thread.
"""

from __future__ import annotations

import heapq
import itertools
import time
from collections.abc import Callable
from dataclasses import dataclass, field


@dataclass(order=True)
class _Event:
    when: float  # real (monotonic) seconds
    seq: int  # ties run in scheduling order
    action: Callable[[], None] = field(compare=False)


class EmulatorClock:
    """Scaled motion time and the actions due at real times.

    Args:
        speedup: motion runs this many times faster than real time (positive).
        wake: called whenever an action is scheduled, so that a thread waiting for the
            next due action looks again at :meth:`seconds_to_next`.

    Raises:
        ValueError: a ``speedup`` that is not positive.
    """

    def __init__(self, speedup: float, wake: Callable[[], None]) -> None:
        if speedup <= 0:
            raise ValueError("speedup must be positive")
        self.speedup = float(speedup)
        self._wake = wake
        self._t0 = time.monotonic()
        self._events: list[_Event] = []
        self._seq = itertools.count()

    def now(self) -> float:
        """Scaled (motion) time in seconds."""
        return (time.monotonic() - self._t0) * self.speedup

    def real_time(self, scaled: float) -> float:
        """The :func:`time.monotonic` time at which scaled time reaches ``scaled``."""
        return self._t0 + scaled / self.speedup

    def schedule(self, real_when: float, action: Callable[[], None]) -> None:
        """Run ``action`` once :func:`time.monotonic` reaches ``real_when`` (see :meth:`run_due`)."""
        heapq.heappush(self._events, _Event(real_when, next(self._seq), action))
        self._wake()

    def run_due(self) -> None:
        """Run the actions that are due, earliest first (those they schedule too, once due)."""
        while self._events and self._events[0].when <= time.monotonic():
            heapq.heappop(self._events).action()

    def seconds_to_next(self, longest: float) -> float:
        """Real seconds until the next action is due (0 if overdue), at most ``longest``."""
        if not self._events:
            return longest
        return min(longest, max(0.0, self._events[0].when - time.monotonic()))
