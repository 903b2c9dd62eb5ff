"""Checked access to single GenICam features on a :class:`drivers.camera.NodeMap`.

The base of :class:`drivers.sfnc.SfncCamera`: every feature is checked to exist (and to
be writable) before it is used, an enumeration entry to be offered before it is set, and
a number to be within the feature's bounds (and, for integers, on its increment).  A
failed check raises :class:`FeatureMissing` or :class:`InvalidSetting` naming the
feature; :func:`no_such_feature`, :func:`missing_entry` and :func:`out_of_range` build
those errors, so that the backends' node maps and the simulated camera
(:mod:`drivers.sim.sim_camera`) word them the same way.

Numbers are in the feature's own unit (``ExposureTime``: µs, ``Gain``: dB, sizes and
offsets: sensor pixels); bounds are inclusive.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from drivers.camera import NodeMap
from drivers.camera_errors import FeatureMissing, InvalidSetting


def no_such_feature(name: str, *, device: str, hint: str | None = None) -> FeatureMissing:
    """The error for a feature ``name`` the camera does not offer (default hint: the
    class's)."""
    return FeatureMissing(
        f"the camera does not offer the GenICam feature {name!r}",
        feature=name,
        device=device,
        hint=hint,
    )


def missing_entry(
    name: str, entry: str, offered: tuple[str, ...], *, device: str, hint: str | None = None
) -> FeatureMissing:
    """The error for an enumeration ``name`` that has no ``entry`` (``offered``: its entries).

    The hint defaults to choosing one of the offered entries.
    """
    return FeatureMissing(
        f"{name} has no entry {entry!r}; offered: {', '.join(offered) or 'none'}",
        feature=name,
        value=entry,
        offered=offered,
        device=device,
        hint=hint if hint is not None else f"choose one of the offered {name} values",
    )


def out_of_range(name: str, value: float, lo: float, hi: float, *, device: str) -> InvalidSetting:
    """The error for ``name=value`` outside the inclusive range ``[lo, hi]`` (feature units)."""
    return InvalidSetting(
        f"{name}={value:g} is outside the camera's range [{lo:g}, {hi:g}]",
        device=device,
        hint=f"a {name} within [{lo:g}, {hi:g}]",
    )


@dataclass
class SfncFeatures:
    """Checked reads and writes of single features of a :class:`NodeMap`.

    Attributes:
        nodes: the remote device's node map.
        device: label used in error messages (``gige://127.0.0.1`` ...).
        feature_hint: where the operator can see the camera's features (error hint).
    """

    nodes: NodeMap
    device: str
    feature_hint: str = field(
        default="the camera's feature list (arv-tool-0.8 -a ADDRESS features)"
    )

    # -- checks -----------------------------------------------------------------------

    def has(self, name: str) -> bool:
        """True if the feature exists and is currently available."""
        return self.nodes.is_available(name)

    def require(self, name: str, *, writable: bool = False) -> None:
        """Raise :class:`FeatureMissing` unless ``name`` exists (and is writable)."""
        if not self.nodes.is_available(name):
            raise no_such_feature(name, device=self.device, hint=self.feature_hint)
        if writable and not self.nodes.is_writable(name):
            raise FeatureMissing(
                f"the GenICam feature {name!r} is not writable now",
                feature=name,
                device=self.device,
                hint="that acquisition is stopped and no other application controls the camera",
            )

    def check_enum(self, name: str, entry: str) -> None:
        """Raise unless the writable enumeration ``name`` offers ``entry``."""
        self.require(name, writable=True)
        offered = self.nodes.enum_entries(name)
        if entry not in offered:
            raise missing_entry(name, entry, offered, device=self.device)

    def set_enum(self, name: str, entry: str) -> None:
        """Set an enumeration after checking the feature and the entry exist."""
        self.check_enum(name, entry)
        if self.nodes.get(name) != entry:
            self.nodes.set(name, entry)

    def check_number(self, name: str, value: float, *, integer: bool = False) -> None:
        """Raise unless ``name`` is writable and ``value`` is within bounds (and on the
        increment, for integers)."""
        self.require(name, writable=True)
        lo, hi = self.nodes.bounds(name)
        if not lo <= value <= hi:
            raise out_of_range(name, value, lo, hi, device=self.device)
        if integer:
            inc = int(self.nodes.increment(name) or 1)
            if (int(value) - int(lo)) % inc:
                raise InvalidSetting(
                    f"{name}={int(value)} is not on the camera's increment {inc} (from {int(lo)})",
                    device=self.device,
                    hint=f"{name} = {int(lo)} + k*{inc}",
                )

    def set_number(self, name: str, value: float, *, integer: bool = False) -> None:
        """Set a numeric feature after checking existence, bounds and increment."""
        self.check_number(name, value, integer=integer)
        self.nodes.set(name, int(value) if integer else float(value))

    def read_string(self, name: str, default: str = "") -> str:
        """A string feature, or ``default`` if the camera does not offer it."""
        return str(self.nodes.get(name)) if self.has(name) else default

    # -- helpers of the configuration ----------------------------------------------------

    def _auto_off(self, name: str) -> None:
        """Switch an ``...Auto`` enumeration to ``Off`` when it is offered and writable."""
        if (
            self.has(name)
            and self.nodes.is_writable(name)
            and "Off" in self.nodes.enum_entries(name)
        ):
            self.set_enum(name, "Off")

    def _select_all(self, selector: str) -> None:
        """Set a selector (``GainSelector`` ...) to ``All`` when it offers it."""
        if self.has(selector) and "All" in self.nodes.enum_entries(selector):
            self.set_enum(selector, "All")


__all__ = ["SfncFeatures", "missing_entry", "no_such_feature", "out_of_range"]
