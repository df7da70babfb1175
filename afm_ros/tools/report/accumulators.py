"""Bounded accumulators of the report: time tables, min/max envelopes, settling and window
means."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afm_ros.formats.chunk_layout import ChunkHeader

ENVELOPE_BINS = 2000  # bins of a whole-session min/max envelope
TABLE_CAP = (
    1 << 18
)  # rows of a time table (clock, chunk receive times, series times) or median sample


class StrideTable:
    """Every ``stride``-th row of a stream (plus its last row), at most ``cap`` rows.

    Starts with stride 1; when full, every second row is dropped and the stride doubles, so the
    rows stay evenly spaced over the stream. Exact (every row) while the stream has <= cap rows.
    """

    def __init__(self, dtypes, cap: int = TABLE_CAP):
        self.cols = [np.empty(min(cap, 1024), dtype=d) for d in dtypes]
        self.cap = cap
        self.n = 0
        self.stride = 1
        self.seen = 0
        self.last = None

    def add(self, *row) -> None:
        if self.seen % self.stride == 0:
            if self.n == self.cap:
                for c in self.cols:
                    c[: self.n // 2] = c[0 : self.n : 2]
                self.n //= 2
                self.stride *= 2
            if self.seen % self.stride == 0:
                if self.n == self.cols[0].shape[0]:
                    self.cols = [np.resize(c, min(self.cap, 2 * c.shape[0])) for c in self.cols]
                for c, v in zip(self.cols, row):
                    c[self.n] = v
                self.n += 1
        self.last = row
        self.seen += 1

    def arrays(self) -> list[np.ndarray]:
        out = [c[: self.n].copy() for c in self.cols]
        if self.seen and (self.seen - 1) % self.stride:
            out = [np.append(c, np.array([v], dtype=c.dtype)) for c, v in zip(out, self.last)]
        return out


class TimeMapTable:
    """(log_time ns, simulated time s) points for the time mapping, at most ``cap`` of them.

    Every point is kept until the table is full; then the table becomes a simplified polyline
    (swinging-door): a point is dropped only if the straight line between its kept neighbours
    passes within ``tol`` [s] of it, so pauses and rate changes (corners) stay; when full again,
    ``tol`` doubles and the kept points are simplified once more. Interpolating the table differs
    from interpolating every point by at most ``error_bound`` (the sum of the tolerances, < 2 tol).
    """

    TOL0 = 1e-6  # [s] first tolerance once the table is full

    def __init__(self, cap: int = TABLE_CAP):
        self.cap = cap
        self.x = np.empty(min(cap, 1024), dtype=np.int64)
        self.y = np.empty(min(cap, 1024))
        self.n = 0
        self.seen = 0
        self.tol = 0.0
        self.error_bound = 0.0
        self._pending = None  # last point seen but not kept (tol > 0)
        self._lo, self._hi = (
            -math.inf,
            math.inf,
        )  # slopes from the last kept point that cover the dropped ones

    def _keep(self, x, y) -> None:
        if self.n == self.x.shape[0]:
            size = min(self.cap + 1, 2 * self.n)
            self.x, self.y = np.resize(self.x, size), np.resize(self.y, size)
        self.x[self.n], self.y[self.n] = x, y
        self.n += 1

    def add(self, x: int, y: float) -> None:
        self.seen += 1
        self._add(x, y)
        if self.n >= self.cap:
            self._shrink()

    def _add(self, x, y) -> None:
        if self.tol == 0.0 or self.n == 0 or self.tol == math.inf:
            self._keep(x, y)
            return
        ax, ay = int(self.x[self.n - 1]), float(self.y[self.n - 1])
        dx = x - ax
        if dx > 0:
            lo = max(self._lo, (y - self.tol - ay) / dx)
            hi = min(self._hi, (y + self.tol - ay) / dx)
            if (
                lo <= hi
            ):  # one line from the last kept point covers every dropped point and this one
                self._lo, self._hi, self._pending = lo, hi, (x, y)
                return
        if self._pending is not None:  # the previous point becomes a corner; start again from it
            self._keep(*self._corner())
            self._pending = None
            self._lo, self._hi = -math.inf, math.inf
            self._add(x, y)
        else:  # not after the last kept point (unsorted receive times): keep it as it is
            self._keep(x, y)

    def _shrink(self) -> None:
        x, y = self.arrays()
        tol = self.tol
        while (
            True
        ):  # simplify the kept points with a doubled tolerance until half the table is free
            tol = max(2.0 * tol, self.TOL0)
            self.tol, self.n, self._pending, self._lo, self._hi = tol, 0, None, -math.inf, math.inf
            for xi, yi in zip(x.tolist(), y.tolist()):
                self._add(xi, yi)
            if self.n + 1 <= self.cap // 2:
                self.error_bound += (
                    tol  # the kept points were within the old bound, now within tol of them
                )
                return
            if tol > 1.0:  # not a time map (e.g. unsorted receive times): every second point
                x, y = self.arrays()
                keep = np.unique(np.r_[np.arange(0, x.size, 2), x.size - 1])
                self.n, self._pending = keep.size, None
                self.x[: self.n], self.y[: self.n] = x[keep], y[keep]
                self.tol, self.error_bound = math.inf, math.inf
                return

    def _corner(self) -> tuple[int, float]:
        """The pending point moved (by <= tol) onto a line from the last kept point that passes
        within tol of every point dropped since."""
        ax, ay = int(self.x[self.n - 1]), float(self.y[self.n - 1])
        px, py = self._pending
        slope = min(max((py - ay) / (px - ax), self._lo), self._hi)
        return px, ay + slope * (px - ax)

    def arrays(self) -> list[np.ndarray]:
        x, y = self.x[: self.n].copy(), self.y[: self.n].copy()
        if self._pending is not None:
            px, py = self._corner()
            x, y = np.append(x, px), np.append(y, py)
        return [x, y]


class Envelope:
    """A trace for a figure: every sample while short, else min/max in fixed time bins."""

    def __init__(
        self, t_lo: float, t_hi: float, bins: int = ENVELOPE_BINS, raw_cap: int = 2 * ENVELOPE_BINS
    ):
        self.t_lo, self.bins, self.raw_cap = t_lo, bins, raw_cap
        self.width = (t_hi - t_lo) / bins if t_hi > t_lo else 1.0
        self.raw: list | None = []
        self.raw_n = 0
        self.lo = self.hi = None

    def add(self, t: np.ndarray, v: np.ndarray) -> None:
        if self.raw is not None:
            self.raw.append((np.array(t, dtype=float), np.array(v, dtype=float)))
            self.raw_n += t.shape[0]
            if self.raw_n > self.raw_cap:
                raw, self.raw = self.raw, None
                self.lo = np.full(self.bins, np.nan)
                self.hi = np.full(self.bins, np.nan)
                for tt, vv in raw:
                    self._bin(tt, vv)
            return
        self._bin(t, v)

    def _bin(self, t, v):
        if t.shape[0] == 0:
            return
        b = np.clip(((t - self.t_lo) / self.width).astype(np.int64), 0, self.bins - 1)
        if b[0] == b[-1] and (b == b[0]).all():  # the usual chunk: all in one bin
            k = b[0]
            self.lo[k] = np.fmin(self.lo[k], np.fmin.reduce(v))  # fmin/fmax ignore NaN
            self.hi[k] = np.fmax(self.hi[k], np.fmax.reduce(v))
            return
        step = np.diff(b)
        if (step >= 0).all():  # time-ordered (every chunk): one reduction per run of equal bins
            starts = np.concatenate(([0], np.flatnonzero(step) + 1))
            k = b[starts]
            self.lo[k] = np.fmin(self.lo[k], np.fmin.reduceat(v, starts))
            self.hi[k] = np.fmax(self.hi[k], np.fmax.reduceat(v, starts))
        else:
            np.fmin.at(self.lo, b, v)
            np.fmax.at(self.hi, b, v)

    def add_chunk(
        self,
        header: ChunkHeader,
        v: np.ndarray,
        t_start: float,
        t_end: float,
        mn: float,
        mx: float,
    ) -> None:
        """A sample chunk (times t_start + i dt) with its min and max already known."""
        if self.raw is None:
            b0 = min(max(int((t_start - self.t_lo) / self.width), 0), self.bins - 1)
            b1 = min(max(int((t_end - self.t_lo) / self.width), 0), self.bins - 1)
            if b0 == b1:
                self.lo[b0] = np.fmin(self.lo[b0], mn)
                self.hi[b0] = np.fmax(self.hi[b0], mx)
                return
        self.add(header.times(v.shape[0]), v)

    @property
    def is_raw(self) -> bool:
        return self.raw is not None

    def draw(self, ax, scale: float) -> None:
        """On ``ax``, times scale: every point when kept raw, else the min/max band."""
        if self.is_raw:
            t, v = self.points()
            ax.plot(t, v * scale, lw=0.9)
        else:
            tb, lo, hi = self.bands()
            ax.fill_between(
                tb, lo * scale, hi * scale, color="C0", alpha=0.8, lw=0.3, edgecolor="C0"
            )

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        if not self.raw:
            return np.empty(0), np.empty(0)
        return np.concatenate([r[0] for r in self.raw]), np.concatenate([r[1] for r in self.raw])

    def bands(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(bin centre times, min, max); empty bins are NaN."""
        t = self.t_lo + (np.arange(self.bins) + 0.5) * self.width
        return t, self.lo, self.hi


class SettlingTracker:
    """Settling time in O(1): time from the first sample after engaging to the sample after the
    last one outside the band (0 if never outside, None if outside at the end)."""

    def __init__(self, setpoint: float, band: float):
        self.setpoint, self.band = setpoint, band
        self.ever_outside = False
        self.last_outside = False
        self.t_after = None

    def add(self, t: np.ndarray, a: np.ndarray) -> None:
        if t.shape[0] == 0:
            return
        out = np.abs(a - self.setpoint) > self.band
        hits = np.flatnonzero(out)
        if hits.size:
            self.ever_outside = True
            k = hits[-1]
            if k < t.shape[0] - 1:
                self.t_after, self.last_outside = float(t[k + 1]), False
            else:
                self.last_outside = True
        elif self.last_outside:
            self.t_after, self.last_outside = float(t[0]), False

    def result(self, t_first: float):
        if not self.ever_outside:
            return 0.0
        return None if self.last_outside else self.t_after - t_first


@dataclass
class WindowMean:
    """Running sum of finite values (and of squared deviations from ``center``)."""

    center: float = 0.0
    n: int = 0
    total: float = 0.0
    dev: float = 0.0  # sum of (v - center)
    sq: float = 0.0  # sum of (v - center)^2

    def add(self, v: np.ndarray) -> None:
        if v.shape[0]:
            d = v - self.center
            self.n += v.shape[0]
            self.total += float(np.sum(v))
            self.dev += float(np.sum(d))
            self.sq += float(np.sum(d * d))

    def mean(self):
        return self.total / self.n if self.n else None

    def rms_about(self, value: float):
        """sqrt(mean((v - value)^2)), exact when value == center."""
        if not self.n:
            return None
        s = value - self.center
        return math.sqrt(max(0.0, self.sq / self.n - 2.0 * s * self.dev / self.n + s * s))
