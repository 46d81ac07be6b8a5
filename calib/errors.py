"""Exceptions raised for bad input. All derive from ValueError."""


class RigError(ValueError):
    """A rig (or rig file) is malformed; the message names the sensor and the field."""


class CalibrationError(ValueError):
    """A calibration cannot be computed from the given data."""
