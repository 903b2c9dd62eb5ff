"""Ready-made Zaber stages: the board rail (one axis) and the XY stage (two axes).

The XY stage is two :class:`ZaberAxis` sharing one :class:`ZaberPort`: either
one two-axis controller (same device, axes 1 and 2) or two single-axis devices
on one daisy chain (devices 1 and 2, axis 1 each) -- only the configs differ.

Typical use (units: mm)::

    rail = open_rail("/dev/ttyUSB0", ZaberAxisConfig(name="rail", microstep_um=0.047625))
    rail.home()
    rail.move_abs_mm(42.0)

    xy = open_xy_stage(
        "/dev/ttyUSB1",
        ZaberAxisConfig(name="stage x", device=1, axis=1, microstep_um=0.1984375),
        ZaberAxisConfig(name="stage y", device=1, axis=2, microstep_um=0.1984375),
    )
    xy.home()
    xy.move_xy_mm(10.0, 5.0)

XY stage daisy-chained behind the rail (one cable, one port shared)::

    port = ZaberPort("/dev/ttyUSB0").open()
    rail = open_rail(port, ZaberAxisConfig(name="rail", device=1, microstep_um=0.047625))
    xy = open_xy_stage(port, ZaberAxisConfig(name="x", device=2, axis=1, ...),
                       ZaberAxisConfig(name="y", device=2, axis=2, ...))
    ...
    port.close()
"""

from __future__ import annotations

from drivers.errors import DeviceError, NotReferenced
from drivers.zaber.axis import PendingMotion, ZaberAxis, ZaberAxisConfig
from drivers.zaber.port import BAUDRATE, ZaberPort


class XYStage:
    """Two Zaber axes moved together.

    Args:
        x, y: the two axes (connected or not; :meth:`connect` connects both).
        name: name used in messages.
        port: a port this stage owns and closes in :meth:`close`.
    """

    def __init__(
        self, x: ZaberAxis, y: ZaberAxis, *, name: str = "xy stage", port: ZaberPort | None = None
    ) -> None:
        cx, cy = x.config, y.config
        if x.port is y.port and (cx.device, cx.axis) == (cy.device, cy.axis):
            raise ValueError(
                f"{name}: x and y are the same axis (device {cx.device} axis {cx.axis})"
            )
        self._x, self._y = x, y
        self._name = name
        self._port = port

    @property
    def name(self) -> str:
        """Name used in messages."""
        return self._name

    @property
    def x(self) -> ZaberAxis:
        """The X axis."""
        return self._x

    @property
    def y(self) -> ZaberAxis:
        """The Y axis."""
        return self._y

    def connect(self) -> XYStage:
        """Connect both axes."""
        self._x.connect()
        self._y.connect()
        return self

    def close(self) -> None:
        """Close both axes (and the owned port)."""
        self._x.close()
        self._y.close()
        if self._port is not None:
            self._port.close()

    def __enter__(self) -> XYStage:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def is_homed(self) -> bool:
        """True if both axes are homed."""
        return self._x.is_homed() and self._y.is_homed()

    def home(self, timeout_s: float | None = None) -> None:
        """Home both axes at the same time and wait (``timeout_s`` s each; None = derived)."""
        first = self._x.start_home(timeout_s)
        try:
            second = self._y.start_home(timeout_s)
        except DeviceError:
            self._quiet_stop(self._x)
            raise
        self._finish_both(first, second)

    def move_xy_mm(
        self, x_mm: float, y_mm: float, timeout_s: float | None = None
    ) -> tuple[float, float]:
        """Move both axes at once to (``x_mm``, ``y_mm``); return the read-back position (mm).

        Both targets are checked before anything moves.  If one axis fails,
        the other is stopped and the first error is raised.
        """
        for axis, target in ((self._x, x_mm), (self._y, y_mm)):
            axis.check_target_mm(target)  # sends nothing
        for axis in (self._x, self._y):
            if not axis.is_homed():
                raise NotReferenced(
                    f"refusing to move to ({x_mm}, {y_mm}) mm: {axis.name} not homed",
                    device=axis.label,
                )
        first = self._x.start_move_abs_mm(x_mm, timeout_s)
        try:
            second = self._y.start_move_abs_mm(y_mm, timeout_s)
        except DeviceError:
            self._quiet_stop(self._x)
            raise
        return self._finish_both(first, second)

    def position_xy_mm(self) -> tuple[float, float]:
        """Current (x, y) position (mm); raises NotReferenced if an axis is not homed."""
        return self._x.position_mm(), self._y.position_mm()

    def stop(self) -> None:
        """Stop both axes (decelerated) and wait."""
        errors: list[DeviceError] = []
        for axis in (self._x, self._y):
            try:
                axis.stop()
            except DeviceError as exc:
                errors.append(exc)
        if errors:
            raise errors[0]

    def estop(self) -> None:
        """Emergency-stop both axes; does not wait."""
        errors: list[DeviceError] = []
        for axis in (self._x, self._y):
            try:
                axis.estop()
            except DeviceError as exc:
                errors.append(exc)
        if errors:
            raise errors[0]

    def _finish_both(self, first: PendingMotion, second: PendingMotion) -> tuple[float, float]:
        results: list[float] = []
        failure: DeviceError | None = None
        for axis, other, pending in ((self._x, self._y, first), (self._y, self._x, second)):
            try:
                results.append(axis.finish(pending))
            except DeviceError as exc:
                if failure is None:
                    failure = exc
                    self._quiet_stop(other)
                results.append(float("nan"))
        if failure is not None:
            raise failure
        return results[0], results[1]

    @staticmethod
    def _quiet_stop(axis: ZaberAxis) -> None:
        try:
            axis.stop()
        except DeviceError:
            pass


def _port_for(
    where: str | ZaberPort, name: str, reply_timeout_s: float, retries: int, baudrate: int
) -> tuple[ZaberPort, bool]:
    """(open port, owned) for a URL (a new port, owned) or a shared ZaberPort (not owned)."""
    if isinstance(where, ZaberPort):
        return where.open(), False
    port = ZaberPort(
        where, name=name, reply_timeout_s=reply_timeout_s, retries=retries, baudrate=baudrate
    )
    return port.open(), True


def open_rail(
    where: str | ZaberPort,
    config: ZaberAxisConfig,
    *,
    reply_timeout_s: float = 0.5,
    retries: int = 2,
    baudrate: int = BAUDRATE,
) -> ZaberAxis:
    """Connect the rail axis described by ``config``.

    ``where`` is a pyserial URL (a port is opened and owned by the axis) or a
    shared :class:`ZaberPort` (e.g. the XY stage on the same chain; the caller
    closes it).
    """
    port, owned = _port_for(where, config.name, reply_timeout_s, retries, baudrate)
    try:
        return ZaberAxis(port, config, owns_port=owned).connect()
    except BaseException:
        if owned:
            port.close()
        raise


def open_xy_stage(
    where: str | ZaberPort,
    x: ZaberAxisConfig,
    y: ZaberAxisConfig,
    *,
    name: str = "xy stage",
    reply_timeout_s: float = 0.5,
    retries: int = 2,
    baudrate: int = BAUDRATE,
) -> XYStage:
    """Connect both axes of an XY stage.

    ``where`` is a pyserial URL (a port is opened and owned by the stage) or a
    shared :class:`ZaberPort` (e.g. the rail's chain; the caller closes it).
    """
    port, owned = _port_for(where, name, reply_timeout_s, retries, baudrate)
    try:
        stage = XYStage(
            ZaberAxis(port, x), ZaberAxis(port, y), name=name, port=port if owned else None
        )
        return stage.connect()
    except BaseException:
        if owned:
            port.close()
        raise


__all__ = ["XYStage", "open_rail", "open_xy_stage"]
