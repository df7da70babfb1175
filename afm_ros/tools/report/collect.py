"""Pass 2: the chunks one at a time and the series in batches into the bounded accumulators
(:class:`Collector`), and the setpoint-tracking numbers from them."""

from __future__ import annotations

import math
from collections import OrderedDict, deque
from pathlib import Path

import numpy as np

from afm_ros.formats.chunk_layout import cdr_chunk
from afm_ros.formats.mcap_io import SessionScan, read_session
from afm_ros.tools.report.accumulators import Envelope, SettlingTracker, StrideTable, WindowMean
from afm_ros.tools.report.cdr import (
    amplitude_phase,
    cdr_batch,
    cdr_float64,
    cdr_vector3_stamped,
    decode_image,
)
from afm_ros.tools.report.plan import Plan
from afm_ros.tools.report.session import (
    STAMP_LAG_CAP,
    ChunkStream,
    ForceDistance,
    ImageTopic,
    ReportError,
    SessionData,
    bad_message,
    nth,
)
from afm_ros.tools.report.survey import BATCH_ROLES, CHUNK_ROLES, FM_ROLE, SCALAR_ROLES

SETTLING_BAND = 0.02  # |amplitude - setpoint| <= 2 % of the setpoint counts as settled
MAX_SCATTER_POINTS = 200_000
ZOOM_PERIODS = 5
SERIES_RAW_POINTS = 20_000  # a series this short is plotted sample by sample
ZOOM_CAP = (
    1 << 20
)  # samples kept for the zoomed view (only a restart of the time axis can fill it)
PENDING_CAP = (
    1 << 20
)  # samples waiting for their partner (deflection<->force, amplitude<->xy, error)
SERIES_BATCH = 4096  # series messages handled together
# an image is reduced to at most this many pixels per side for the figure
DISPLAY_MAX_PIXELS = 1024


def _keep_image(it: ImageTopic, data) -> None:
    """Pass 2: decode the chosen image of ``it``, keep its statistics (over every pixel) and the
    image itself reduced to at most DISPLAY_MAX_PIXELS per side (every k-th row and column)."""
    arr = decode_image(data)
    finite = np.isfinite(arr)
    values = arr[finite]
    it.stats = {
        "lines_acquired": int(finite.all(axis=1).sum()),
        "rows": arr.shape[0],
        "columns": arr.shape[1],
        "finite": int(values.size),
    }
    if values.size:
        it.stats.update(
            min=float(values.min()), median=float(np.median(values)), max=float(values.max())
        )
    step = -(-max(arr.shape) // DISPLAY_MAX_PIXELS)
    it.stats["display_step"] = step
    it.array = arr[::step, ::step].copy() if step > 1 else arr


class Collector:
    """Feeds every message of the chosen topics into the bounded accumulators."""

    def __init__(self, data: SessionData, plan: Plan, tracking_only: bool = False):
        self.data, self.plan, self.tracking_only = data, plan, tracking_only
        sp = plan.setpoint
        self.sp = sp
        self.band = SETTLING_BAND * abs(sp) if sp is not None else None
        self.free = WindowMean()
        self.before_n = 0
        self.tail = WindowMean(center=sp if sp is not None else 0.0)
        self.after_n = 0
        self.ta0 = None
        self.tail_lo = plan.tail_lo_est
        # one settling tracker per segment: from engaging, and from every later setpoint change
        self.seg_starts = np.array([t for t, _, _ in plan.segments])
        self.settling = [SettlingTracker(v, SETTLING_BAND * abs(v)) for _, v, _ in plan.segments]
        self.seg_first: list = [None] * len(plan.segments)  # first amplitude time in each segment
        self.contact = {"phase": WindowMean(), "z_piezo": WindowMean()}
        self.median = StrideTable((np.float64,))
        self.pending: dict[str, list] = {
            r: [] for r in SCALAR_ROLES
        }  # (log_time, value) not yet handled
        self.batched: dict[str, list] = {
            r: [] for r in SCALAR_ROLES
        }  # (t, values) from batches not yet handled
        self.stamps: dict[str, deque] = {
            r: deque()
            for r in (("amplitude",) if tracking_only else ("amplitude", "phase"))
            if r in data.series and data.series[r].stamped and data.series[r].batch is None
        }
        self.amp_hist = (
            np.empty(0),
            np.empty(0),
        )  # recent amplitude (t, a) for the error interpolation
        # (t, value) of error samples in the window, waiting for amplitude
        self.err_wait: list = []
        self.err_wait_n = 0
        self.fd = (
            ForceDistance() if (data.deflection is not None and data.force is not None) else None
        )
        self.pend_d: OrderedDict = OrderedDict()
        self.pend_f: OrderedDict = OrderedDict()
        self.pend_samples = 0
        self.zoom = {}
        if not tracking_only:
            for s in (data.deflection, data.force):
                if s is not None and s.samples:
                    s.envelope = Envelope(s.t_min, s.t_max)
                    if math.isfinite(s.drive_frequency) and s.drive_frequency > 0:
                        span = ZOOM_PERIODS / s.drive_frequency
                    else:
                        span = (s.t_last - s.t_first) * 0.01
                    self.zoom[s.topic] = (s.t_last - span, deque(), [0])
            for role, s in data.series.items():
                if role in SCALAR_ROLES and s.count:
                    if s.batch is not None:
                        lo, hi = s.batch.t_min, s.batch.t_max
                    elif s.stamped:
                        lo, hi = data.series["xy"].stamp_min, data.series["xy"].stamp_max
                    else:
                        lo, hi = (
                            float(plan.map(s.min_log)),
                            float(plan.map(s.max_log)),
                        )  # the mapping is monotonic
                    s.envelope = Envelope(lo, hi, raw_cap=SERIES_RAW_POINTS)

    # chunks
    def chunk(self, role: str, stream: ChunkStream, data: bytes) -> None:
        header, v = cdr_chunk(data)
        n = v.shape[0]
        if n == 0:
            return
        mn, mx = float(v.min()), float(v.max())
        finite = math.isfinite(mn) and math.isfinite(mx)
        if not finite:  # NaN propagates into min/max, inf shows in one of them
            bad = ~np.isfinite(v)
            stream.non_finite += int(bad.sum())
            v = np.where(bad, np.nan, v)
            mn, mx = float(np.fmin.reduce(v)), float(np.fmax.reduce(v))  # NaN if none is finite
        t_start, t_end = header.t_start, header.t_start + (n - 1) * header.sample_interval
        stream.envelope.add_chunk(header, v, t_start, t_end, mn, mx)
        thr, buf, size = self.zoom[stream.topic]
        if t_end >= thr:
            t = header.times(n)
            sel = t >= thr
            buf.append((t[sel], v[sel]))
            size[0] += int(sel.sum())
            while size[0] > ZOOM_CAP and len(buf) > 1:
                size[0] -= buf.popleft()[0].shape[0]
        if self.fd is not None:
            self._pair(role, header.first_sample_index, (header.z_offset, v, finite, mn, mx))

    def _pair(self, role, key, item):
        """Pair a chunk with the other stream's chunk of the same first sample index (the
        cantilever publishes both per step); a chunk waits for its partner, at most PENDING_CAP
        samples wait. ``item`` = (z_offset, samples, all finite, min, max)."""
        mine, theirs = (
            (self.pend_d, self.pend_f) if role == "deflection" else (self.pend_f, self.pend_d)
        )
        other = theirs.pop(key, None)
        if other is None:
            mine[key] = item
            self.pend_samples += item[1].shape[0]
            while self.pend_samples > PENDING_CAP and len(self.pend_d) + len(self.pend_f) > 1:
                side = self.pend_d if len(self.pend_d) >= len(self.pend_f) else self.pend_f
                self.pend_samples -= side.popitem(last=False)[1][1].shape[0]
                self.fd.unpaired_chunks += 1
            return
        self.pend_samples -= other[1].shape[0]
        (zoff, dv, d_ok, d_min, _), (_, fv, f_ok, f_min, f_max) = (
            (item, other) if role == "deflection" else (other, item)
        )
        fd = self.fd
        n = min(dv.shape[0], fv.shape[0])
        fd.pairs += n
        local = None  # positions in the chunk of the pairs that count (None: all n)
        if d_ok and f_ok and math.isfinite(zoff) and dv.shape[0] == fv.shape[0]:
            # addition is monotonic in floating point: min(zoff + d) == zoff + min(d)
            fd.min_gap = min(fd.min_gap, zoff + d_min)
            fd.max_force, fd.min_force = max(fd.max_force, f_max), min(fd.min_force, f_min)
        else:
            gap, force = zoff + dv[:n], fv[:n]
            ok = np.isfinite(gap) & np.isfinite(force)
            local = np.flatnonzero(ok)
            fd.non_finite += n - local.shape[0]
            if local.shape[0] == 0:
                return
            fd.min_gap = min(fd.min_gap, float(gap[ok].min()))
            fd.max_force = max(fd.max_force, float(force[ok].max()))
            fd.min_force = min(fd.min_force, float(force[ok].min()))
        room = (
            MAX_SCATTER_POINTS if self._kept is None else self._kept[0].shape[0]
        ) - self._kept_n
        if room <= 0:
            return
        span, base, m = (
            self.data.deflection.index_span,
            self.data.deflection.min_index,
            MAX_SCATTER_POINTS,
        )
        if span > m:
            # M of the N samples of the index range, evenly spaced: sample k is kept when floor(k M
            # / N) steps between k and k + 1, i.e. k = ceil(j N / M) - 1 for j = 1 .. M
            k0 = key - base
            j = np.arange((k0 * m) // span + 1, ((k0 + n) * m) // span + 1, dtype=np.int64)
            sel = (j * span + m - 1) // m - 1 - k0
            local = sel if local is None else np.intersect1d(sel, local, assume_unique=True)
        elif local is None:
            local = np.arange(n)
        local = local[:room]
        if local.shape[0]:
            if (
                self._kept is None
            ):  # preallocated: a list of small arrays per chunk would cost ~300 B each
                size = min(MAX_SCATTER_POINTS, span)
                self._kept = (np.empty(size), np.empty(size), np.empty(size, dtype=np.int64))
            a, b = self._kept_n, self._kept_n + local.shape[0]
            self._kept[0][a:b] = zoff + dv[local]
            self._kept[1][a:b] = fv[local]
            self._kept[2][a:b] = key + local
            self._kept_n = b

    # series
    def batch(self, role: str, data: bytes) -> None:
        """A lockin/outputs or z_controller/trace batch: its series with their exact times."""
        _, _, _, t, u, v = cdr_batch(role, data)
        if t.shape[0] == 0:
            return
        if role == "outputs":
            a, p = amplitude_phase(u, v)
            pairs = (("amplitude", a), ("phase", p))
        else:
            pairs = (("z_piezo", np.array(u)), ("error", np.array(v)))
        for name, values in pairs:
            s = self.data.series.get(name)
            if s is None or s.batch is None or (self.tracking_only and name != "amplitude"):
                continue
            queue = self.batched[name]
            queue.append((np.array(t), values))
            if len(queue) * t.shape[0] >= SERIES_BATCH:
                self.flush_batched(name)

    def flush_batched(self, role: str) -> None:
        queue = self.batched[role]
        if queue:
            t, v = np.concatenate([q[0] for q in queue]), np.concatenate([q[1] for q in queue])
            queue.clear()
            self._series(role, t, v)

    def scalar(self, role: str, log_time: int, data: bytes) -> None:
        self.pending[role].append((log_time, cdr_float64(data)))
        if len(self.pending[role]) >= SERIES_BATCH:
            self.flush(role)

    def xy(self, data: bytes) -> None:
        stamp = cdr_vector3_stamped(data)[0]
        for role, q in self.stamps.items():
            q.append(stamp)
            if len(q) >= SERIES_BATCH:
                self.flush(role)

    def flush(self, role: str, final: bool = False) -> None:
        pend = self.pending[role]
        if role in self.stamps and max(len(pend), len(self.stamps[role])) > STAMP_LAG_CAP:
            del self.stamps[
                role
            ]  # values and their xy stamps far apart in the file: receive times from here
            self.data.notes.append(
                f"From message {self.data.series[role].count - len(pend)} on, {role} is placed "
                "by its receive time (its lockin/xy stamps are too far away in the file)."
            )
        if role in self.stamps:
            q = self.stamps[role]
            n = min(len(pend), len(q))
            if n == 0 and not final:
                return
            t = np.array([q.popleft() for _ in range(n)])
            if (
                final and len(pend) > n
            ):  # fewer stamps than values left (cannot happen: equal counts)
                t = np.concatenate([t, self.plan.map([lt for lt, _ in pend[n:]])])
                n = len(pend)
            vals = np.array([v for _, v in pend[:n]])
            del pend[:n]
        else:
            if not pend:
                return
            lt = np.array([lt for lt, _ in pend], dtype=np.int64)
            vals = np.array([v for _, v in pend])
            pend.clear()
            t = self.plan.map(lt)
        self._series(role, t, vals)

    def _series(self, role: str, t: np.ndarray, v: np.ndarray) -> None:
        s = self.data.series[role]
        ok = np.isfinite(v)
        if not ok.all():
            if not self.tracking_only:
                s.non_finite += int((~ok).sum())
        if s.envelope is not None and not self.tracking_only:
            s.envelope.add(t, np.where(ok, v, np.nan))
        if role == "amplitude":
            self._amplitude(t, v, ok)
        elif role in ("phase", "z_piezo") and not self.tracking_only:
            if self.ta0 is None and self.plan.tail_lo_est is None:
                return
            lo = self.tail_lo if self.tail_lo is not None else self.plan.tail_lo_est
            self.contact[role].add(v[ok & (t >= lo)])
        elif role == "error" and not self.tracking_only:
            if (
                self.plan.error_lo is None or s.batch is not None
            ):  # batches: the setpoint is known exactly
                return
            sel = ok & (t >= self.plan.error_lo)
            if sel.any():
                self.err_wait.append((t[sel], v[sel]))
                self.err_wait_n += int(sel.sum())
                self._resolve_errors(final=self.err_wait_n > PENDING_CAP)

    def _amplitude(self, t, a, ok):
        plan = self.plan
        if plan.engage is not None:
            before = ok & (t < plan.engage)
            self.before_n += int(before.sum())
            if plan.free_lo is not None:
                self.free.add(a[before & (t >= plan.free_lo)])
            after = t >= plan.engage
        else:
            after = np.ones(t.shape[0], dtype=bool)
        if self.settling:
            seg = np.searchsorted(self.seg_starts, t, side="right") - 1
            for k in np.unique(seg[after & (seg >= 0)]).tolist():
                in_seg = after & (seg == k)
                if self.seg_first[k] is None:
                    self.seg_first[k] = float(t[in_seg][0])
                self.settling[k].add(t[in_seg & ok], a[in_seg & ok])
            last = after & (seg == len(self.settling) - 1)
        else:
            last = after
        if (
            self.ta0 is None and last.any()
        ):  # first sample of the last segment: the final state's window
            self.ta0 = float(t[last][0])
            if plan.tail_last is not None:
                self.tail_lo = plan.tail_last - 0.2 * (plan.tail_last - self.ta0)
        sel = after & ok
        self.after_n += int(sel.sum())
        if self.tail_lo is not None:
            self.tail.add(a[sel & last & (t >= self.tail_lo)])
        if not self.tracking_only and "error" in self.data.series:
            ht, ha = self.amp_hist
            keep = max(0, ht.shape[0] + t.shape[0] - 65536)
            self.amp_hist = (np.concatenate([ht, t])[keep:], np.concatenate([ha, a])[keep:])
            self._resolve_errors()

    def _resolve_errors(self, final: bool = False) -> None:
        if not self.err_wait:
            return
        ht, ha = self.amp_hist
        t = np.concatenate([w[0] for w in self.err_wait])
        v = np.concatenate([w[1] for w in self.err_wait])
        done = (
            np.ones(t.shape[0], dtype=bool)
            if final
            else (t <= ht[-1] if ht.shape[0] else np.zeros(t.shape[0], dtype=bool))
        )
        if ht.shape[0] and done.any():
            est = np.interp(t[done], ht, ha) + v[done]
            for x in est[np.isfinite(est)]:
                self.median.add(x)
        elif done.any():
            done[:] = False
        self.err_wait = [(t[~done], v[~done])] if (~done).any() else []
        self.err_wait_n = int((~done).sum())

    def finish(self) -> None:
        for role in SCALAR_ROLES:
            if role in self.data.series:
                if self.data.series[role].batch is not None:
                    self.flush_batched(role)
                else:
                    self.flush(role, final=True)
        if self.tracking_only:
            return
        if self.data.fm is not None:
            self.data.fm.flush()
        self._resolve_errors(final=True)
        for s in (self.data.deflection, self.data.force):
            if s is not None and s.topic in self.zoom:
                _, buf, _ = self.zoom[s.topic]
                if buf:
                    s.zoom = (
                        np.concatenate([b[0] for b in buf]),
                        np.concatenate([b[1] for b in buf]),
                    )
        if self.fd is not None:
            self.fd.unpaired_chunks += len(self.pend_d) + len(self.pend_f)
            if self._kept is not None:
                self.fd.gap, self.fd.force, self.fd.index = (k[: self._kept_n] for k in self._kept)
            self.data.fd = self.fd if self.fd.pairs else None

    def run(self, path, roles, limits: dict) -> None:
        """Read the chosen topics of ``path``, at most ``limits[topic]`` messages each (what pass 1
        saw: a file that grows meanwhile, e.g. one still being recorded, is reported as
        surveyed)."""
        self._kept, self._kept_n = None, 0
        topics = {self.data.topics[r]: r for r in roles if r in self.data.topics}
        images = (
            {}
            if self.tracking_only
            else {t: it for t, it in self.data.images.items() if it.last_good}
        )
        streams = {"deflection": self.data.deflection, "force": self.data.force}
        counts = dict.fromkeys([*topics, *images], 0)
        for m in read_session(path, SessionScan(Path(path)), set(counts)):
            counts[m.topic] += 1
            it = images.get(m.topic)
            if it is not None:
                if counts[m.topic] == it.last_good:
                    _keep_image(it, m.data)
                continue
            role = topics[m.topic]
            if counts[m.topic] > limits.get(m.topic, 0):
                continue
            try:
                if role in CHUNK_ROLES:
                    self.chunk(role, streams[role], m.data)
                elif role in BATCH_ROLES:
                    self.batch(role, m.data)
                elif role == FM_ROLE:
                    self.data.fm.add_batch(m.data)
                elif role == "xy":
                    self.xy(m.data)
                else:
                    self.scalar(role, m.log_time, m.data)
            except ReportError:
                raise
            except Exception as exc:  # noqa: BLE001 - the file changed between the passes
                raise bad_message(m.topic, m.type_name, counts[m.topic], exc) from None
        self.finish()


def setpoint_tracking(data: SessionData, plan: Plan, c: Collector) -> dict:
    """The setpoint-tracking numbers from the pass-2 accumulators: the settling after engaging and
    after every later setpoint change (each into +-SETTLING_BAND of its own setpoint), and the
    final state over the last 20 % of the last segment (after engaging, or after the last
    change)."""
    out: dict = {}
    amp = data.series.get("amplitude")
    if amp is None or amp.count == 0:
        return out
    setpoint = plan.setpoint
    sd = data.setpoint_data
    if data.setpoint_source == "data":
        out["setpoint_from_error_m"] = sd.value  # amplitude + error at the last output
    elif c.median.seen:
        est = float(np.median(c.median.arrays()[0]))
        out["setpoint_from_error_m"] = est
        if c.median.stride > 1:
            data.notes.append(
                f"The setpoint from the error is the median of every {nth(c.median.stride)} "
                "error sample of the window."
            )
    if plan.engage is not None:
        if c.before_n >= 2 and c.free.n:
            out["free_amplitude_m"] = c.free.mean()
        out["engage_time_s"] = float(plan.engage)
    if setpoint is not None:
        out["setpoint_m"] = float(setpoint)

    def settled(k: int):
        return c.settling[k].result(c.seg_first[k]) if c.seg_first[k] is not None else None

    change_segments = [k for k, seg in enumerate(plan.segments) if seg[2] == "change"]
    if data.setpoints:
        changes = []
        for change in data.setpoints:
            entry = {
                "time_s": change["time_s"],
                "old_m": change["old_m"],
                "new_m": change["new_m"],
                "engaged": change["engaged"],
                "exact_time": change["exact_time"],
            }
            if change["engaged"] and change_segments:
                k = change_segments.pop(0)
                entry["settling_time_s"] = settled(k)
                entry["outputs_after"] = c.seg_first[k] is not None
                entry["during_scan"] = (
                    plan.scan_start is not None and plan.segments[k][0] >= plan.scan_start
                )
            changes.append(entry)
        out["setpoint_changes"] = changes
    if plan.scan_start is not None:
        out["scan_start_s"] = plan.scan_start
    if c.after_n >= 2 and setpoint is not None and c.tail.n:
        out["reached_amplitude_m"] = c.tail.mean()
        out["rms_tracking_error_m"] = c.tail.rms_about(setpoint)
        out["settling_time_s"] = settled(0)
        out["settling_band_m"] = SETTLING_BAND * abs(plan.segments[0][1])
        scanning = plan.scan_start is not None and plan.segments[-1][0] >= plan.scan_start
        # while scanning the amplitude follows the topography: no "settled" state at the end
        out["settled_at_end"] = (
            None if scanning else (c.seg_first[-1] is not None and not c.settling[-1].last_outside)
        )
        out["final_window_s"] = [c.tail_lo, plan.tail_last]
        for role, key in (("phase", "contact_phase_deg"), ("z_piezo", "contact_z_piezo_m")):
            if role in data.series and c.contact[role].n:
                out[key] = c.contact[role].mean()
    return out


def tracking_numbers(data: SessionData) -> dict:
    """Setpoint tracking: free amplitude, setpoint, reached amplitude, settling time, contact
    phase."""
    return dict(data.tracking)


def force_distance(data: SessionData):
    """(gap [m], force [N], sample index) of the pairs kept for the figure (at most
    MAX_SCATTER_POINTS, evenly spaced in the sample index; every pair while there are fewer), or
    None. The extremes over all pairs are in ``data.fd``."""
    if data.fd is None or data.fd.gap.size == 0:
        return None
    return data.fd.gap, data.fd.force, data.fd.index
