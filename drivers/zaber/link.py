"""One Zaber axis's end of the chain: requests addressed to it, and its status and flags.

:class:`AxisLink` sends commands to the device and axis named in a
:class:`~drivers.zaber.config.ZaberAxisConfig` through a (possibly shared)
:class:`~drivers.zaber.port.ZaberPort`, raises rejected commands as typed errors naming
the axis, and holds the queries every other part of the driver is built on: the status
poll (``get pos``: busy/idle, the highest-precedence warning flag, the position in
microsteps) and the full warning-flag list.  Values here are raw device units.
"""

from __future__ import annotations

from drivers.errors import CommandRejected, DeviceError
from drivers.zaber import protocol
from drivers.zaber.config import ZaberAxisConfig
from drivers.zaber.port import ZaberPort
from drivers.zaber.protocol import Reply

#: Flags of lower precedence than WR: when a reply shows one of them, WR is not set.
_BELOW_WR = frozenset(protocol.WARNING_PRIORITY[protocol.WARNING_PRIORITY.index("WR") + 1 :])


class AxisLink:
    """Requests to one axis (``config.device``/``config.axis``) through ``port``.

    Args:
        port: the chain's transport (may be shared by several axes).
        config: the axis's name and address.
    """

    def __init__(self, port: ZaberPort, config: ZaberAxisConfig) -> None:
        self._port = port
        self._cfg = config

    @property
    def port(self) -> ZaberPort:
        """The transport the requests go through."""
        return self._port

    @property
    def label(self) -> str:
        """Name plus address, as used in error messages."""
        return f"{self._cfg.name} (zaber device {self._cfg.device} axis {self._cfg.axis} on {self._port.url})"

    def request(self, text: str, *, axis: int | None = None, retry: bool | None = None) -> Reply:
        """Send ``text`` to the axis (``axis=0``: to its device) and return the reply.

        ``retry`` None: re-sent only if idempotent (see :meth:`ZaberPort.request`).
        A rejection raises :class:`CommandRejected` (for BADAXIS/DEVICEONLY with a hint
        at the configured numbers); transport failures raise the port's errors.
        """
        cfg = self._cfg
        reply = self._port.request(
            cfg.device, cfg.axis if axis is None else axis, text, label=self.label, retry=retry
        )
        if reply.rejected:
            error = protocol.rejection_error(reply, command=text, device=self.label)
            if error.reason in ("BADAXIS", "DEVICEONLY"):
                error.hint = (
                    f"the device ({cfg.device}) and axis ({cfg.axis}) numbers in the configuration"
                )
            raise error
        return reply

    def get_int(self, setting: str) -> int:
        """An integer setting of the axis (raw device units)."""
        return self.request(f"get {setting}").data_int()

    def get_optional(self, setting: str, *, axis: int | None = None) -> str | None:
        """A setting's value, or None when the device rejects it (unknown to this firmware,
        or not available on this axis: identity extras must not stop a connect)."""
        try:
            return self.request(f"get {setting}", axis=axis).data
        except CommandRejected:
            return None

    def get_named(
        self, names: tuple[str, str], *, axis: int, firmware: tuple[int, int]
    ) -> str | None:
        """A setting firmware 7 renamed, ``names`` = (firmware 6 name, firmware 7 name):
        the name of ``firmware``'s series first, then the other."""
        ordered = names if firmware < (7, 0) else (names[1], names[0])
        for name in ordered:
            value = self.get_optional(name, axis=axis)
            if value is not None:
                return value
        return None

    def status(self) -> Reply:
        """The status poll (``get pos``): busy/idle, shown flag, position (microsteps)."""
        return self.request("get pos")

    def has_reference(self, status: Reply) -> bool:
        """False if WR is set.  A reply shows only the highest-precedence flag, so when
        the shown flag outranks WR (e.g. WT, WV) the full list is read."""
        shown = status.warning
        if shown == "WR":
            return False
        if shown == protocol.NO_WARNING or shown in _BELOW_WR:
            return True
        return "WR" not in self.warnings()

    def warnings(self) -> frozenset[str]:
        """All warning flags active on the axis (``warnings``)."""
        return protocol.parse_warnings_data(self.request("warnings").data)

    def clear_warnings(self) -> frozenset[str]:
        """Clear the clearable flags (``warnings clear``, never re-sent); returns the
        flags that were active."""
        reply = self.request("warnings clear", retry=False)
        return protocol.parse_warnings_data(reply.data)

    def quiet_stop(self) -> None:
        """Send ``stop``, ignoring any DeviceError (used while another error is raised)."""
        try:
            self.request("stop")
        except DeviceError:
            pass


__all__ = ["AxisLink"]
