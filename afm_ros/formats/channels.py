"""The image channels of a frame, their units and the two scan directions; the grey scale of an
image.

The names every image file (.gwy, .sxm), message (``scanner/image/<channel>/<direction>``) and
dataset store uses; the instrument's blocks (:mod:`afm_ros.core.imaging`) fill them.
"""

from __future__ import annotations

import numpy as np

CHANNELS = ("height", "amplitude", "phase", "amplitude_error", "dissipation")
# FM-AFM frames (afm_ros.core.fm): the PLL's frequency shift, the amplitude controller's drive and
# the dissipation from it, the amplitude and phase error the loops leave, and the z loop's df error
FM_CHANNELS = (
    "height",
    "frequency_shift",
    "drive",
    "dissipation",
    "amplitude",
    "phase_error",
    "frequency_shift_error",
)
UNITS = {
    "height": "m",
    "amplitude": "m",
    "phase": "deg",
    "amplitude_error": "m",
    "dissipation": "J",
    "frequency_shift": "Hz",
    "drive": "N",
    "phase_error": "deg",
    "frequency_shift_error": "Hz",
}
DIRECTIONS = ("trace", "retrace")
IMAGE_TAIL_CUT = 0.02  # fraction of an image's pixels clipped at each end of its grey scale


def tail_cut_limits(values: np.ndarray, fraction: float = IMAGE_TAIL_CUT) -> tuple[float, float]:
    """(low, high): the finite values of rank ``k`` from either end of ``values``, ``k =
    floor(fraction
    * n)`` for ``n`` finite values (the plain minimum and maximum below 1 / fraction values), so a
    few spikes do not set a grey or colour scale; (nan, nan) without a finite value."""
    values = np.asarray(values).ravel()
    values = values[np.isfinite(values)]
    n = values.size
    if n == 0:
        return float("nan"), float("nan")
    k = int(fraction * n)
    ordered = np.partition(values, (k, n - 1 - k))
    return float(ordered[k]), float(ordered[n - 1 - k])
