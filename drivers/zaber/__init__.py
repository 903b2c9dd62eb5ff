"""Zaber ASCII-protocol stage drivers (motorized rail and XY stage).

Public API::

    from drivers.zaber import ZaberAxisConfig, open_rail, open_xy_stage
    rail = open_rail("/dev/ttyUSB0", ZaberAxisConfig(name="rail", microstep_um=0.047625))

See :mod:`drivers.zaber.stage` for the XY stage and :mod:`drivers.zaber.port`
for the transport.
"""

from drivers.zaber.axis import PendingMotion, ZaberAxis, ZaberAxisConfig
from drivers.zaber.port import PortStats, ZaberPort
from drivers.zaber.stage import XYStage, open_rail, open_xy_stage

__all__ = [
    "PendingMotion",
    "PortStats",
    "XYStage",
    "ZaberAxis",
    "ZaberAxisConfig",
    "ZaberPort",
    "open_rail",
    "open_xy_stage",
]
