"""The signals the Nanonis server reports (Signals.NamesGet): index, name with unit, where the
value comes from, and the image channel it records.

The index is the signal's "RT index", the one Signals.ValGet, Scan.BufferSet, Scan.FrameDataGrab
and ZSpectr.ChsSet take. Z is at 14, as on the Nanonis AFMs that lab scripts are written for
(``FrameDataGrab(14, 1)``); the current and bias at 0 and 1 are listed but not modelled (afm_ros
is an AFM without a tunnelling junction: reading them answers an error that says so). Units are
SI; the excitation is the drive force [N] (a real controller reports the shaker's voltage).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from afm_ros.formats.channels import CHANNELS, FM_CHANNELS


@dataclass(frozen=True)
class Signal:
    """One signal: ``index``, ``name`` as Nanonis lists it (with the unit), ``unit``, the key of
    :meth:`afm_ros.client.Microscope.signals` it reads ('' = not modelled), the image channel it
    records ('' = none), and its range (max, min) in its unit."""

    index: int
    name: str
    unit: str
    key: str
    channel: str
    high: float
    low: float

    @property
    def file_name(self) -> str:
        """The name in an .sxm file's channel table (no unit, spaces as _)."""
        return self.name.rsplit(" (", 1)[0].replace(" ", "_")


# (name, unit, signals() key, image channel, max, min)
_TABLE = (
    ("Current", "A", "", "", 1e-6, -1e-6),
    ("Bias", "V", "", "", 10.0, -10.0),
    ("X", "m", "x_m", "", 1e-3, -1e-3),
    ("Y", "m", "y_m", "", 1e-3, -1e-3),
    ("Amplitude", "m", "amplitude_m", "amplitude", 1e-6, 0.0),
    ("Phase", "deg", "phase_deg", "phase", 180.0, -180.0),
    ("Frequency Shift", "Hz", "frequency_shift_Hz", "frequency_shift", 1e6, -1e6),
    ("Excitation", "N", "drive_N", "drive", 1e-3, 0.0),
    ("Deflection", "m", "deflection_m", "", 1e-6, -1e-6),
    ("Amplitude Error", "m", "amplitude_error_m", "amplitude_error", 1e-6, -1e-6),
    ("Dissipation", "J", "", "dissipation", 1e-15, -1e-15),
    ("Frequency Shift Error", "Hz", "", "frequency_shift_error", 1e6, -1e6),
    ("Phase Error", "deg", "", "phase_error", 180.0, -180.0),
    ("Oscillation Frequency", "Hz", "frequency_Hz", "", 1e8, 0.0),
    ("Z", "m", "z_m", "height", 1e-4, -1e-4),
    ("Motor Z", "m", "motor_m", "", 0.1, -0.1),
    ("Time", "s", "t_s", "", 1e9, 0.0),
)
SIGNALS = tuple(
    Signal(i, f"{name} ({unit})", unit, key, channel, high, low)
    for i, (name, unit, key, channel, high, low) in enumerate(_TABLE)
)
BY_CHANNEL = {s.channel: s for s in SIGNALS if s.channel}
Z_INDEX = 14
NAMES = [s.name for s in SIGNALS]


def signal(index: int) -> Signal:
    """The signal of ``index``; ValueError naming the range otherwise."""
    if not 0 <= index < len(SIGNALS):
        raise ValueError(f"signal index {index}: the signals are 0-{len(SIGNALS) - 1}")
    return SIGNALS[index]


def value(index: int, values: dict) -> float:
    """The value of signal ``index`` in ``values`` (what Microscope.signals() returned); NaN for
    a signal this mode does not have (the frequency shift in tapping mode) or an image-only
    channel; ValueError for the current and bias, which are not modelled."""
    s = signal(index)
    if s.index in (0, 1):
        raise ValueError(
            f"{s.name} is not modelled: afm_ros emulates an AFM without a tunnelling junction"
        )
    v = values.get(s.key) if s.key else None
    return math.nan if v is None else float(v)


def image_channels(mode: str) -> tuple:
    """The image channels a frame of ``mode`` ('am' or 'fm') has."""
    return FM_CHANNELS if mode == "fm" else CHANNELS


SOURCES = {
    "": "not modelled (an error says so)",
    "x_m": "the tip's commanded x (on the scan's path while scanning)",
    "y_m": "the tip's commanded y",
    "amplitude_m": "the oscillation amplitude, the newest lock-in output",
    "phase_deg": "its phase (the tune sets the free phase to 90 deg)",
    "frequency_shift_Hz": "FM: the PLL's frequency shift (NaN in AM)",
    "drive_N": "the drive force amplitude (AM: fixed; FM: the amplitude controller's)",
    "deflection_m": "the newest measured deflection sample (the raw stream)",
    "amplitude_error_m": "setpoint - amplitude (AM: the z loop's; FM: the amplitude loop's)",
    "frequency_Hz": "the drive (AM) or PLL oscillator (FM) frequency",
    "z_m": "the z piezo (higher: retracted)",
    "motor_m": "the coarse motor's position",
    "t_s": "the simulated time",
}


def signal_table() -> str:
    """The Markdown table of the signals (docs/nanonis.md), generated from :data:`SIGNALS`."""
    rows = [
        "| index | name | live value (Signals.ValGet) | image channel | range (max, min) |",
        "|---|---|---|---|---|",
    ]
    for s in SIGNALS:
        live = SOURCES[s.key] if s.key or s.index in (0, 1) else "image only (NaN live)"
        rows.append(
            f"| {s.index} | {s.name} | {live} | {s.channel or '-'} | {s.high:g}, {s.low:g} |"
        )
    return "\n".join(rows) + "\n"
