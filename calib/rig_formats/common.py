"""What the rig formats share (calib.rig_formats)."""

from __future__ import annotations

from calib.rig import Rig

EXTRAS = (
    ("radiometry", "radiometry"),
    ("range_correction", "range correction"),
    ("uncertainty", "uncertainty"),
)
"""A sensor's parts beyond geometry: (attribute, words), none of which a format holds."""


def extras_lost(rig: Rig, why: str) -> list[str]:
    """One ``lost`` line per sensor part of :data:`EXTRAS` the rig has: "<words> of
    <sensor>: <why>"."""
    return [
        f"{words} of {name}: {why}"
        for name, s in rig.sensors.items()
        for attr, words in EXTRAS
        if getattr(s, attr) is not None
    ]
