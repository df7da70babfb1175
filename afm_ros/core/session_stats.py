"""Running statistics of a session (no ROS import): what the instrument's summary and the report
say.

All times are simulated seconds, amplitudes and z in metres, phases in degrees. Memory does not
grow with the session: windows keep sums, the rolling window keeps 10 ms bins of its span.

:class:`SetpointHistory` follows the setpoint actually in force, reconstructed from the data
(every lock-in output's amplitude plus the z controller's error at the same output,
``setpoint = amplitude + (setpoint - amplitude)``), so a live change (``afm_ctl set``, ``ros2 param
set``, Foxglove) is placed at the simulated time it took effect, and each change gets its own
settling time.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


@dataclass
class WindowStats:
    """Running mean/std of lock-in amplitude [m] and phase [deg], and mean z [m], over [t0, t1)
    simulated."""

    t0: float
    t1: float
    n: int = 0
    mean_a: float = 0.0
    m2_a: float = 0.0
    sum_phase: float = 0.0
    nz: int = 0
    sum_z: float = 0.0

    def add_outputs(self, t: np.ndarray, a: np.ndarray, p: np.ndarray) -> None:
        sel = (t >= self.t0) & (t < self.t1)
        for ai, pi in zip(a[sel].tolist(), p[sel].tolist()):
            self.n += 1
            d = ai - self.mean_a
            self.mean_a += d / self.n
            self.m2_a += d * (ai - self.mean_a)
            self.sum_phase += pi

    def add_z(self, t: float, z: float) -> None:
        if self.t0 <= t < self.t1:
            self.nz += 1
            self.sum_z += z

    @property
    def amplitude(self) -> float:
        return self.mean_a if self.n else math.nan

    @property
    def amplitude_std(self) -> float:
        return math.sqrt(self.m2_a / self.n) if self.n else math.nan

    @property
    def phase(self) -> float:
        return self.sum_phase / self.n if self.n else math.nan

    @property
    def z(self) -> float:
        return self.sum_z / self.nz if self.nz else math.nan


class RollingStats:
    """Amplitude/phase/z statistics over the most recent ``span`` simulated seconds, in 10 ms bins
    (bounded memory for a session of any length), from ``t0`` [s] on; same properties as
    :class:`WindowStats`."""

    BIN_S = 0.01

    def __init__(self, span: float, t0: float = -math.inf):
        self.span = span
        self.t0 = t0
        self.bins: dict[int, list] = {}  # bin -> [n, sum da, sum da^2, sum phase, nz, sum z]
        self.ref: float | None = (
            None  # amplitudes are summed relative to the first one (precision)
        )

    def _bin(self, t: float) -> list:
        k = int(math.floor(t / self.BIN_S))
        b = self.bins.get(k)
        if b is None:
            b = self.bins[k] = [0, 0.0, 0.0, 0.0, 0, 0.0]
            oldest = k - int(math.ceil(self.span / self.BIN_S))
            for old in [j for j in self.bins if j <= oldest]:
                del self.bins[old]
        return b

    def add_outputs(self, t: np.ndarray, a: np.ndarray, p: np.ndarray) -> None:
        sel = t >= self.t0
        for ti, ai, pi in zip(t[sel].tolist(), a[sel].tolist(), p[sel].tolist()):
            if self.ref is None:
                self.ref = ai
            b = self._bin(ti)
            d = ai - self.ref
            b[0] += 1
            b[1] += d
            b[2] += d * d
            b[3] += pi

    def add_z(self, t: float, z: float) -> None:
        if t < self.t0:
            return
        b = self._bin(t)
        b[4] += 1
        b[5] += z

    def _sum(self, i: int) -> float:
        return sum(b[i] for b in self.bins.values())

    @property
    def n(self) -> int:
        return int(self._sum(0))

    @property
    def amplitude(self) -> float:
        n = self._sum(0)
        return self.ref + self._sum(1) / n if n else math.nan

    @property
    def amplitude_std(self) -> float:
        n = self._sum(0)
        return math.sqrt(max(0.0, self._sum(2) / n - (self._sum(1) / n) ** 2)) if n else math.nan

    @property
    def phase(self) -> float:
        n = self._sum(0)
        return self._sum(3) / n if n else math.nan

    @property
    def z(self) -> float:
        nz = self._sum(4)
        return self._sum(5) / nz if nz else math.nan


@dataclass
class SettlingTracker:
    """Simulated time from ``t_enable`` until |A - setpoint| <= band for good (incremental); None:
    not settled."""

    t_enable: float
    setpoint: float
    band: float
    inside_since: float | None = None
    ever_outside: bool = False

    def add(self, t: np.ndarray, a: np.ndarray) -> None:
        sel = t >= self.t_enable
        for ti, ai in zip(t[sel].tolist(), a[sel].tolist()):
            if abs(ai - self.setpoint) > self.band or not math.isfinite(ai):
                self.ever_outside = True
                self.inside_since = None
            elif self.inside_since is None:
                self.inside_since = ti

    @property
    def settling_time(self) -> float | None:
        if not self.ever_outside:
            return 0.0
        return None if self.inside_since is None else self.inside_since - self.t_enable


# a reconstructed setpoint differs from the one in force by round-off only
SETPOINT_TOLERANCE_M = 1e-15


@dataclass
class SetpointChange:
    """A setpoint in force from ``time_s`` [s] on: ``old_m`` -> ``new_m`` [m] and its settling."""

    time_s: float
    old_m: float
    new_m: float
    settling: SettlingTracker

    def as_dict(self) -> dict:
        return {
            "time_s": self.time_s,
            "old_m": self.old_m,
            "new_m": self.new_m,
            "settling_time_s": self.settling.settling_time,
            "band_m": self.settling.band,
        }


@dataclass
class SetpointHistory:
    """Setpoint segments from ``t_enable`` on: the engage setpoint, then each live change.

    ``band_fraction`` x setpoint is each segment's settling band; ``on_change(change)`` is called
    for each change found and ``on_settled(change, t)`` when the amplitude enters the band of a
    changed setpoint at ``t`` [s] (again, if it left it), e.g. to restart the hold statistics
    there."""

    t_enable: float
    setpoint: float
    band_fraction: float
    on_change: object = None
    on_settled: object = None
    changes: list = field(default_factory=list)  # SetpointChange after the engage one

    def __post_init__(self):
        self.engage = SettlingTracker(
            self.t_enable, self.setpoint, self.band_fraction * self.setpoint
        )

    @property
    def current(self) -> SettlingTracker:
        return self.changes[-1].settling if self.changes else self.engage

    def add(self, t: np.ndarray, amplitude: np.ndarray, error: np.ndarray) -> None:
        """Lock-in outputs (time [s], amplitude [m]) and the z controller's error [m] at the same
        outputs."""
        sel = t >= self.t_enable
        t, a = t[sel], amplitude[sel]
        s = a + error[sel]
        start = 0
        while True:
            off = np.flatnonzero(
                np.isfinite(s[start:]) & (np.abs(s[start:] - self.setpoint) > SETPOINT_TOLERANCE_M)
            )
            if not off.size:
                break
            i = start + int(off[0])
            self._add_current(t[start:i], a[start:i])
            new = float(s[i])
            change = SetpointChange(
                float(t[i]),
                self.setpoint,
                new,
                SettlingTracker(float(t[i]), new, self.band_fraction * new),
            )
            self.changes.append(change)
            self.setpoint = new
            start = i
            if self.on_change is not None:
                self.on_change(change)
        self._add_current(t[start:], a[start:])

    def _add_current(self, t: np.ndarray, a: np.ndarray) -> None:
        tracker = self.current
        before = tracker.inside_since
        tracker.add(t, a)
        if (
            self.changes
            and self.on_settled is not None
            and tracker.inside_since is not None
            and tracker.inside_since != before
        ):
            self.on_settled(self.changes[-1], tracker.inside_since)


@dataclass
class FmWindow:
    """Running mean and spread of the FM loop's outputs over [t0, t1) simulated [s]: df [Hz], drive
    [N], amplitude [m] and phase error [deg] (:class:`afm_ros.core.fm.FMOutputs` batches)."""

    t0: float
    t1: float
    n: int = 0
    sums: np.ndarray = field(default_factory=lambda: np.zeros(4))
    squares: np.ndarray = field(default_factory=lambda: np.zeros(4))

    NAMES = ("df", "drive", "amplitude", "phase_error")

    def add(self, t, df, drive, amplitude, phase_error) -> None:
        t = np.asarray(t, dtype=float)
        sel = (t >= self.t0) & (t < self.t1)
        if not sel.any():
            return
        block = np.array(
            [np.asarray(v, dtype=float)[sel] for v in (df, drive, amplitude, phase_error)]
        )
        self.n += int(sel.sum())
        self.sums += block.sum(axis=1)
        self.squares += (block * block).sum(axis=1)

    def mean(self, name: str) -> float:
        return float(self.sums[self.NAMES.index(name)] / self.n) if self.n else math.nan

    def std(self, name: str) -> float:
        if self.n < 2:
            return math.nan
        i = self.NAMES.index(name)
        m = self.sums[i] / self.n
        return float(math.sqrt(max(self.squares[i] / self.n - m * m, 0.0) * self.n / (self.n - 1)))
