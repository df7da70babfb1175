"""The lock-in's phase convention and angle wrapping, written once (degrees; no ROS).

The phase of an output (X, Y) is the lag behind the reference: ``atan2(-Y, X)``; the scalar forms
use ``math`` (what the nodes compute per output), the array forms numpy, so each path gives the
same bits as before it was shared.
"""

from __future__ import annotations

import math

import numpy as np


def phase_deg(x: float, y: float) -> float:
    """The phase [deg] of one lock-in output (X, Y) [m]: the lag behind the reference."""
    return math.degrees(math.atan2(-y, x))


def phases_deg(x, y) -> np.ndarray:
    """The phases [deg] of arrays of lock-in outputs X, Y [m]."""
    return np.degrees(np.arctan2(-np.asarray(y), np.asarray(x)))


def wrap_deg(angle):
    """Angle [deg] wrapped to [-180, 180): a float for a number, an array for an array."""
    if isinstance(angle, (int, float)):
        return (angle + 180.0) % 360.0 - 180.0
    return (np.asarray(angle) + 180.0) % 360.0 - 180.0
