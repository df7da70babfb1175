"""Lab-notebook report of a recorded session: PNG figures + Markdown summary.

``python -m afm_ros.report SESSION.mcap [--out DIR]`` (also ``afm_report``) writes into DIR
(default: ``<SESSION>_report`` next to the file):

- ``deflection_force.png``: deflection and tip-sample force vs simulated time (whole session as
  a min/max envelope, and the last few drive periods in full);
- ``lockin_z.png``: lock-in amplitude (with the setpoint), phase and z piezo vs simulated time;
- ``force_distance.png``: tip-sample force vs gap, reconstructed sample by sample: gap =
  z_offset (chunk preamble) + deflection, force from the tip_sample_force chunk with the same
  sample index;
- ``report.md``: file status, topics, every node's parameters at start and every change, and the
  setpoint-tracking numbers (free amplitude, setpoint, reached amplitude, settling time, phase
  and z piezo in contact).

Works on truncated files (reads the intact part, says so) and on files with only some topics
(figures and numbers whose inputs are missing are skipped with a note). Times: samples carry
their exact simulated time; the unstamped Float64 topics (amplitude, phase, z piezo, error) are
placed on the simulated time axis through their receive time and the receive times of the
recorded /clock messages (or deflection chunks), i.e. to within the delivery latency.
"""
from __future__ import annotations

import argparse
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .chunk_layout import unpack
from .mcap_io import SessionFileError, SessionScan, decode, parameter_metadata, read_session

SETTLING_BAND = 0.02  # |amplitude - setpoint| <= 2 % of the setpoint counts as settled
MAX_SCATTER_POINTS = 200_000
ZOOM_PERIODS = 5


@dataclass
class ChunkStream:
    """Samples of one chunk topic with their running indices and simulated times."""

    index: np.ndarray
    t: np.ndarray  # [s] simulated
    values: np.ndarray
    z_offset: np.ndarray  # [m] per sample (from the chunk preamble)
    drive_frequency: float = float("nan")  # [Hz] of the last chunk
    receive: tuple = ()  # (log_time ns of each chunk, simulated end time of each chunk [s])

    @staticmethod
    def from_messages(messages) -> "ChunkStream | None":
        idx, t, vals, off, rx_log, rx_t = [], [], [], [], [], []
        freq = float("nan")
        for m in messages:
            header, samples = unpack(decode(m).data)
            n = samples.shape[0]
            idx.append(header.first_sample_index + np.arange(n, dtype=np.int64))
            t.append(header.times(n))
            vals.append(np.array(samples))
            off.append(np.full(n, header.z_offset))
            rx_log.append(m.log_time)
            rx_t.append(header.t_start + n * header.sample_interval)
            freq = header.drive_frequency
        if not idx:
            return None
        return ChunkStream(np.concatenate(idx), np.concatenate(t), np.concatenate(vals), np.concatenate(off),
                           freq, (np.array(rx_log, dtype=np.int64), np.array(rx_t)))


@dataclass
class Series:
    log_time: np.ndarray  # [ns] wall receive time
    values: np.ndarray
    t: np.ndarray | None = None  # [s] simulated (mapped or stamped)


@dataclass
class SessionData:
    path: Path
    scan: SessionScan
    topics: dict = field(default_factory=dict)  # role -> recorded topic
    deflection: ChunkStream | None = None
    force: ChunkStream | None = None
    series: dict = field(default_factory=dict)  # role -> Series
    initial_parameters: dict = field(default_factory=dict)  # node -> {name: value}
    changes: list = field(default_factory=list)  # (log_time ns, node, name, value)
    change_times: list = field(default_factory=list)  # time of each change on the report's axis [s]
    time_axis: str = "simulated time [s]"


ROLES = {
    "deflection": "cantilever/deflection",
    "force": "cantilever/tip_sample_force",
    "amplitude": "lockin/amplitude",
    "phase": "lockin/phase",
    "xy": "lockin/xy",
    "z_piezo": "z_controller/z_piezo",
    "error": "z_controller/error",
    "clock": "clock",  # /clock, or /<ns>/clock of an instrument in a namespace
}


def _pick_topics(topics: dict[str, int]) -> dict[str, str]:
    """role -> topic (if several namespaces recorded one role, the one with most messages)."""
    out = {}
    for role, suffix in ROLES.items():
        cands = [t for t in topics if (t == suffix if suffix.startswith("/") else t.endswith("/" + suffix))]
        if cands:
            out[role] = max(cands, key=lambda t: topics[t])
    return out


def _param_value(v):
    from rclpy.parameter import parameter_value_to_python
    value = parameter_value_to_python(v)
    return list(value) if type(value).__name__ == "array" else value


def load_session(path) -> SessionData:
    """Read every intact message of ``path`` and sort it by role (see :data:`ROLES`)."""
    scan = SessionScan(Path(path))
    by_topic: dict[str, list] = {}
    for m in read_session(path, scan):
        by_topic.setdefault(m.topic, []).append(m)
    data = SessionData(Path(path), scan)
    data.topics = _pick_topics({t: len(v) for t, v in by_topic.items()})
    if "deflection" in data.topics:
        data.deflection = ChunkStream.from_messages(by_topic[data.topics["deflection"]])
    if "force" in data.topics:
        data.force = ChunkStream.from_messages(by_topic[data.topics["force"]])
    for role in ("amplitude", "phase", "z_piezo", "error"):
        if role in data.topics:
            msgs = by_topic[data.topics[role]]
            data.series[role] = Series(np.array([m.log_time for m in msgs], dtype=np.int64),
                                       np.array([decode(m).data for m in msgs]))
    if "xy" in data.topics:
        msgs = by_topic[data.topics["xy"]]
        dec = [decode(m) for m in msgs]
        data.series["xy"] = Series(np.array([m.log_time for m in msgs], dtype=np.int64),
                                   np.array([[d.vector.x, d.vector.y] for d in dec]),
                                   np.array([d.header.stamp.sec + 1e-9 * d.header.stamp.nanosec for d in dec]))
    if "clock" in data.topics:
        msgs = by_topic[data.topics["clock"]]
        clocks = [decode(m).clock for m in msgs]
        data.series["clock"] = Series(np.array([m.log_time for m in msgs], dtype=np.int64),
                                      np.array([c.sec + 1e-9 * c.nanosec for c in clocks]))
    # parameters: snapshots (metadata records, else initial ParameterEvents) and later changes
    data.initial_parameters = {n: dict(v) for n, v in parameter_metadata(scan).items()}
    from_events: dict[str, dict] = {}
    for m in by_topic.get("/parameter_events", []):
        event = decode(m)
        for p in event.new_parameters:
            from_events.setdefault(event.node, {})[p.name] = repr(_param_value(p.value))
        for p in event.changed_parameters:
            data.changes.append((m.log_time, event.node, p.name, _param_value(p.value)))
    for node, values in from_events.items():
        data.initial_parameters.setdefault(node, values)
    _map_times(data)
    return data


def _map_times(data: SessionData) -> None:
    """Give every unstamped series a simulated time from its receive time."""
    ref = None
    if "clock" in data.series and data.series["clock"].log_time.size >= 2:
        ref = (data.series["clock"].log_time, data.series["clock"].values)
    elif data.deflection is not None and data.deflection.receive[0].size >= 2:
        ref = data.deflection.receive
    elif data.force is not None and data.force.receive[0].size >= 2:
        ref = data.force.receive
    all_logs = [s.log_time for s in data.series.values() if s.log_time.size]
    t0 = min((int(x.min()) for x in all_logs), default=0)
    for role, s in data.series.items():
        if s.t is not None:
            continue
        if ref is not None:
            order = np.argsort(ref[0], kind="stable")
            s.t = np.interp(s.log_time, ref[0][order], ref[1][order])
        else:
            s.t = (s.log_time - t0) * 1e-9
    if ref is None and data.deflection is None:
        data.time_axis = "wall time since first message [s]"
    # lock-in outputs are produced together with xy (stamped with the exact simulated time)
    xy = data.series.get("xy")
    for role in ("amplitude", "phase"):
        s = data.series.get(role)
        if xy is not None and s is not None and s.values.size == xy.values.shape[0]:
            s.t = xy.t
    data.change_times = [(float(np.interp(lt, ref[0][np.argsort(ref[0])], ref[1][np.argsort(ref[0])]))
                          if ref is not None else (lt - t0) * 1e-9) for lt, *_ in data.changes]


# --- numbers -------------------------------------------------------------------------------


def _parse_float(text):
    try:
        return float(text)
    except (TypeError, ValueError):
        return None


def _current(data: SessionData, node_suffix: str, name: str, at: float | None = None):
    """Value of parameter ``name`` of the node whose name ends with ``node_suffix`` at time ``at``."""
    value = None
    for node, values in data.initial_parameters.items():
        if node.endswith(node_suffix) and name in values:
            raw = values[name]
            value = {"true": True, "false": False}.get(raw, _parse_float(raw))
    for (lt, node, pname, v), t in zip(data.changes, data.change_times):
        if node.endswith(node_suffix) and pname == name and (at is None or t <= at):
            value = v
    return value


def tracking_numbers(data: SessionData) -> dict:
    """Setpoint tracking: free amplitude, setpoint, reached amplitude, settling time, contact phase."""
    out: dict = {}
    amp = data.series.get("amplitude")
    if amp is None or amp.values.size == 0:
        return out
    t, a = amp.t, amp.values
    # engagement: the z_controller's `enabled` switched on, else the first error sample
    engage = None
    for (lt, node, name, v), tc in zip(data.changes, data.change_times):
        if node.endswith("z_controller") and name == "enabled" and v is True:
            engage = tc
    if engage is None and _current(data, "z_controller", "enabled") is True and "error" in data.series:
        engage = float(data.series["error"].t[0]) if data.series["error"].t.size else None
    setpoint = _current(data, "z_controller", "setpoint")
    err = data.series.get("error")
    if err is not None and err.values.size:  # error = setpoint - amplitude
        tail = err.t >= err.t[-1] - 0.2 * (err.t[-1] - err.t[0])
        est = float(np.median(np.interp(err.t[tail], t, a) + err.values[tail]))
        out["setpoint_from_error_m"] = est
        if setpoint is None:
            setpoint = est
    if engage is not None:
        before = t < engage
        if before.sum() >= 2:
            w = t[before] >= t[before][-1] - 0.2 * (t[before][-1] - t[before][0])
            out["free_amplitude_m"] = float(np.mean(a[before][w]))
        out["engage_time_s"] = float(engage)
    if setpoint is not None:
        out["setpoint_m"] = float(setpoint)
    after = t >= (engage if engage is not None else t[0])
    if after.sum() >= 2 and setpoint is not None:
        ta, aa = t[after], a[after]
        tail = ta >= ta[-1] - 0.2 * (ta[-1] - ta[0])
        out["reached_amplitude_m"] = float(np.mean(aa[tail]))
        out["rms_tracking_error_m"] = float(np.sqrt(np.mean((aa[tail] - setpoint) ** 2)))
        band = SETTLING_BAND * abs(setpoint)
        outside = np.nonzero(np.abs(aa - setpoint) > band)[0]
        if outside.size == 0:
            out["settling_time_s"] = 0.0
        elif outside[-1] < aa.size - 1:
            out["settling_time_s"] = float(ta[outside[-1] + 1] - ta[0])
        else:
            out["settling_time_s"] = None  # still outside the band at the end of the record
        out["settling_band_m"] = band
        for role, key in (("phase", "contact_phase_deg"), ("z_piezo", "contact_z_piezo_m")):
            s = data.series.get(role)
            if s is not None and s.values.size:
                sel = s.t >= ta[-1] - 0.2 * (ta[-1] - ta[0])
                if sel.any():
                    out[key] = float(np.mean(s.values[sel]))
    return out


def force_distance(data: SessionData):
    """(gap [m], force [N]) for every sample index present in both chunk streams."""
    d, f = data.deflection, data.force
    if d is None or f is None:
        return None
    common, i_d, i_f = np.intersect1d(d.index, f.index, assume_unique=True, return_indices=True)
    if common.size == 0:
        return None
    return d.z_offset[i_d] + d.values[i_d], f.values[i_f], common


# --- figures -------------------------------------------------------------------------------


def _envelope(t, y, bins=2000):
    """Min/max per bin so a long trace stays readable."""
    if t.size <= 2 * bins:
        return t, y, y
    edges = np.linspace(0, t.size, bins + 1).astype(int)
    tb = t[edges[:-1]]
    lo = np.minimum.reduceat(y, edges[:-1])
    hi = np.maximum.reduceat(y, edges[:-1])
    return tb, lo, hi


def _plot_trace(ax_full, ax_zoom, stream: ChunkStream, scale, label, color):
    tb, lo, hi = _envelope(stream.t, stream.values)
    ax_full.fill_between(tb, lo * scale, hi * scale, color=color, alpha=0.6, lw=0)
    ax_full.set_ylabel(label)
    if math.isfinite(stream.drive_frequency) and stream.drive_frequency > 0:
        span = ZOOM_PERIODS / stream.drive_frequency
    else:
        span = (stream.t[-1] - stream.t[0]) * 0.01
    sel = stream.t >= stream.t[-1] - span
    ax_zoom.plot((stream.t[sel] - stream.t[-1]) * 1e6, stream.values[sel] * scale, color=color, lw=0.8)
    ax_zoom.set_ylabel(label)


def write_figures(data: SessionData, out: Path) -> list[Path]:
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figures = []
    streams = [(s, sc, lab, col) for s, sc, lab, col in (
        (data.deflection, 1e9, "deflection [nm]", "C0"), (data.force, 1e9, "tip-sample force [nN]", "C3"))
        if s is not None]
    if streams:
        fig, axes = plt.subplots(len(streams), 2, figsize=(11, 3.2 * len(streams)), squeeze=False)
        for row, (s, sc, lab, col) in enumerate(streams):
            _plot_trace(axes[row, 0], axes[row, 1], s, sc, lab, col)
        axes[0, 0].set_title("whole session (min/max envelope)")
        axes[0, 1].set_title(f"last {ZOOM_PERIODS} drive periods")
        axes[-1, 0].set_xlabel("simulated time [s]")
        axes[-1, 1].set_xlabel(f"simulated time - {streams[0][0].t[-1]:.6g} s [µs]")
        fig.tight_layout()
        figures.append(out / "deflection_force.png")
        fig.savefig(figures[-1], dpi=110)
        plt.close(fig)

    rows = [(r, sc, lab) for r, sc, lab in (("amplitude", 1e9, "amplitude [nm]"), ("phase", 1.0, "phase [deg]"),
                                             ("z_piezo", 1e9, "z piezo [nm]")) if r in data.series]
    if rows:
        numbers = tracking_numbers(data)
        fig, axes = plt.subplots(len(rows), 1, figsize=(9, 2.6 * len(rows)), sharex=True, squeeze=False)
        for ax, (role, sc, lab) in zip(axes[:, 0], rows):
            s = data.series[role]
            ax.plot(s.t, s.values * sc, lw=0.9)
            ax.set_ylabel(lab)
            if role == "amplitude" and "setpoint_m" in numbers:
                ax.axhline(numbers["setpoint_m"] * sc, color="k", ls="--", lw=0.8, label="setpoint")
                band = numbers.get("settling_band_m")
                if band:
                    ax.axhspan((numbers["setpoint_m"] - band) * sc, (numbers["setpoint_m"] + band) * sc,
                               color="k", alpha=0.08, lw=0)
                ax.legend(loc="best")
            if "engage_time_s" in numbers:
                ax.axvline(numbers["engage_time_s"], color="C2", ls=":", lw=0.8)
        axes[-1, 0].set_xlabel(data.time_axis)
        fig.tight_layout()
        figures.append(out / "lockin_z.png")
        fig.savefig(figures[-1], dpi=110)
        plt.close(fig)

    fd = force_distance(data)
    if fd is not None:
        gap, force, _ = fd
        step = max(1, gap.size // MAX_SCATTER_POINTS)
        fig, ax = plt.subplots(figsize=(6.5, 4.5))
        ax.plot(gap[::step] * 1e9, force[::step] * 1e9, ".", ms=1.0, alpha=0.4)
        ax.axvline(0.0, color="k", lw=0.6)
        ax.set_xlabel("gap = z_offset + deflection [nm]")
        ax.set_ylabel("tip-sample force [nN]")
        ax.set_title("force-distance, reconstructed from the recorded chunks")
        fig.tight_layout()
        figures.append(out / "force_distance.png")
        fig.savefig(figures[-1], dpi=110)
        plt.close(fig)
    return figures


# --- markdown ------------------------------------------------------------------------------


def lost_samples(index: np.ndarray) -> tuple[int, int]:
    """(samples missing, gaps) in a recorded running sample index (sorted by arrival)."""
    if index.size < 2:
        return 0, 0
    step = np.diff(index)
    gaps = step > 1
    return int(np.sum(step[gaps] - 1)), int(np.count_nonzero(gaps))


def stream_completeness(index: np.ndarray) -> str:
    """One sentence: complete, or how many samples were lost in how many gaps (and repeats)."""
    lost, gaps = lost_samples(index)
    repeats = int(np.count_nonzero(np.diff(index) < 1)) if index.size > 1 else 0
    text = ("complete: no sample lost (no gap in the sample index)" if lost == 0
            else f"{lost} samples lost in {gaps} gaps of the sample index")
    return text + (f", {repeats} repeated or out-of-order samples" if repeats else "")


def _fmt(value, unit="", scale=1.0):
    if value is None:
        return "—"
    if isinstance(value, float):
        return f"{value * scale:.4g}{(' ' + unit) if unit else ''}"
    return f"{value}{(' ' + unit) if unit else ''}"


def write_markdown(data: SessionData, figures: list[Path], out: Path) -> Path:
    scan = data.scan
    lines = [f"# AFM session report: `{data.path.name}`", ""]
    if scan.complete:
        lines.append(f"File complete ({scan.file_size} bytes, profile `{scan.header.profile if scan.header else '?'}`).")
    else:
        lines.append(f"**File incomplete**: {scan.truncated_reason}. This report covers the intact part "
                     f"({scan.bytes_read} of {scan.file_size} bytes).")
    lines += ["", "## Topics", "", "| topic | type | messages |", "|---|---|---|"]
    for topic, type_name in sorted(scan.topics.items()):
        lines.append(f"| `{topic}` | `{type_name}` | {scan.message_counts.get(topic, 0)} |")
    missing = [role for role in ("deflection", "force", "amplitude", "phase", "z_piezo") if role not in data.topics]
    if missing:
        lines += ["", f"Not recorded (figures/numbers skipped): {', '.join(missing)}."]

    if data.deflection is not None:
        d = data.deflection
        lines += ["", f"Deflection: {d.index.size} samples, simulated {d.t[0]:.6g} s to {d.t[-1]:.6g} s; "
                  + stream_completeness(d.index) + "."]
        if data.force is not None:
            lines += ["", f"Tip-sample force: {data.force.index.size} samples; "
                      + stream_completeness(data.force.index) + "."]

    numbers = tracking_numbers(data)
    lines += ["", "## Setpoint tracking", ""]
    if numbers:
        lines += ["| quantity | value |", "|---|---|",
                  f"| free amplitude | {_fmt(numbers.get('free_amplitude_m'), 'nm', 1e9)} |",
                  f"| setpoint | {_fmt(numbers.get('setpoint_m'), 'nm', 1e9)} |",
                  f"| engaged at | {_fmt(numbers.get('engage_time_s'), 's')} |",
                  f"| reached amplitude (last 20 %) | {_fmt(numbers.get('reached_amplitude_m'), 'nm', 1e9)} |",
                  f"| rms tracking error (last 20 %) | {_fmt(numbers.get('rms_tracking_error_m'), 'nm', 1e9)} |",
                  f"| settling time (into ±{SETTLING_BAND * 100:g} % of the setpoint) | "
                  f"{_fmt(numbers.get('settling_time_s'), 's') if 'settling_time_s' in numbers else '—'}"
                  f"{' (not settled)' if 'settling_time_s' in numbers and numbers['settling_time_s'] is None else ''} |",
                  f"| phase in contact | {_fmt(numbers.get('contact_phase_deg'), 'deg')} |",
                  f"| z piezo in contact | {_fmt(numbers.get('contact_z_piezo_m'), 'nm', 1e9)} |"]
    else:
        lines.append("No lock-in amplitude recorded.")

    fd = force_distance(data)
    if fd is not None:
        gap, force, _ = fd
        lines += ["", "## Force-distance", "",
                  f"{gap.size} matched samples; minimum gap {gap.min() * 1e9:.4g} nm, maximum (repulsive) force "
                  f"{force.max() * 1e9:.4g} nN, minimum (adhesive) force {force.min() * 1e9:.4g} nN."]

    lines += ["", "## Parameters at start", ""]
    if data.initial_parameters:
        for node in sorted(data.initial_parameters):
            lines += [f"### `{node}`", "", "| parameter | value |", "|---|---|"]
            for name, value in sorted(data.initial_parameters[node].items()):
                lines.append(f"| `{name}` | `{value}` |")
            lines.append("")
    else:
        lines.append("No parameter snapshot recorded.")
    lines += ["## Parameter changes", ""]
    if data.changes:
        lines += [f"| {data.time_axis} | node | parameter | new value |", "|---|---|---|---|"]
        for (lt, node, name, value), t in zip(data.changes, data.change_times):
            lines.append(f"| {t:.6g} | `{node}` | `{name}` | `{value!r}` |")
    else:
        lines.append("None.")
    if figures:
        lines += ["", "## Figures", ""] + [f"![{f.stem}]({f.name})" for f in figures]
    path = out / "report.md"
    path.write_text("\n".join(lines) + "\n")
    return path


@dataclass
class Report:
    markdown: Path
    figures: list
    numbers: dict
    data: SessionData


def make_report(session, out_dir=None) -> Report:
    """Read ``session`` and write figures and ``report.md`` into ``out_dir``."""
    session = Path(session)
    out = Path(out_dir) if out_dir else session.with_name(session.stem + "_report")
    data = load_session(session)
    out.mkdir(parents=True, exist_ok=True)
    figures = write_figures(data, out)
    md = write_markdown(data, figures, out)
    numbers = tracking_numbers(data)
    for role, stream in (("deflection", data.deflection), ("force", data.force)):
        if stream is not None:
            numbers[f"{role}_samples"] = int(stream.index.size)
            numbers[f"{role}_lost_samples"], numbers[f"{role}_gaps"] = lost_samples(stream.index)
    return Report(md, figures, numbers, data)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="afm_report", description="Figures and a Markdown summary of a "
                                     "recorded AFM session (.mcap; truncated files are read up to the damage).")
    parser.add_argument("session", help="the .mcap file")
    parser.add_argument("--out", help="output directory (default: <session>_report next to the file)")
    args = parser.parse_args(argv)
    try:
        report = make_report(args.session, args.out)
    except (SessionFileError, OSError) as exc:
        print(f"afm_report: error: {exc}", file=sys.stderr)
        return 1
    if not report.data.scan.complete:
        print(f"afm_report: warning: {report.data.path} is incomplete ({report.data.scan.truncated_reason}); "
              "reported the intact part", file=sys.stderr)
    print(f"wrote {report.markdown} and {len(report.figures)} figures")
    return 0


if __name__ == "__main__":
    sys.exit(main())
