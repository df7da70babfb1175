"""FM-AFM part of the session report (:mod:`afm_ros.tools.report`): the PLL's batches
``pll/outputs``.

Pass 1 surveys the batches (continuity, time range) and the last ``z_controller/stage`` messages
(approach start, engage time). Between the passes the windows are set, on the simulated time axis:

- ``free``: the second half of the outputs before the approach started (withdrawn, PLL locked);
- ``engaged``: the second half from engaging (``z_controller/stage``; else the ``enabled`` change)
  to the scan start (or to the end), what ``afm_instrument --fm`` calls the hold;
- ``scan``: the recorded frame, ``scanner/geometry`` ``start_time_s`` plus lines / line_rate;
- ``last half`` of the session when none of these is known.

Pass 2 fills a min/max envelope per block for ``fm.png`` and each window's
:class:`afm_ros.core.session_stats.FmWindow` (mean and standard deviation of df [Hz], drive [N],
amplitude [m], phase error [deg]; rows with a non-finite value are counted and left out). The
dissipation per cycle [J] of a window is :func:`afm_ros.core.fm.dissipation_from_drive` of its mean
drive and amplitude with the cantilever's k and Q as set, as the session's summary computes it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from afm_ros.core.fm import dissipation_from_drive
from afm_ros.core.session_stats import FmWindow
from afm_ros.tools.report.accumulators import Envelope
from afm_ros.tools.report.cdr import cdr_fm_batch
from afm_ros.tools.report.collect import SERIES_BATCH, SERIES_RAW_POINTS
from afm_ros.tools.report.plan import current

BLOCKS = FmWindow.NAMES  # df, drive, amplitude, phase_error
# block -> (display scale, unit shown, axis label)
DISPLAY = {
    "df": (1.0, "Hz", "df [Hz]"),
    "drive": (1e12, "pN", "drive [pN]"),
    "amplitude": (1e9, "nm", "amplitude [nm]"),
    "phase_error": (1.0, "deg", "phase error [deg]"),
}
SI_UNITS = {"df": "Hz", "drive": "N", "amplitude": "m", "phase_error": "deg"}


@dataclass
class FmData:
    """What the report knows of the FM loop: the batch stream, set-up, windows and pass-2
    results."""

    stream: object  # session.BatchStream of pll/outputs
    feedback: bool  # the z loop regulates df
    df_setpoint: float | None  # [Hz], in force at the end
    amplitude_setpoint: float | None  # [m]
    spring_constant: float | None  # [N/m]
    quality_factor: float | None  # as set
    approach_started: float | None = None  # [s]
    engaged: float | None = None  # [s]
    engaged_from: str = ""
    scan: tuple | None = None  # (start, end) [s]
    windows: dict = field(default_factory=dict)  # name -> (FmWindow, description)
    envelopes: dict = field(default_factory=dict)  # block -> accumulators.Envelope
    extremes: dict = field(default_factory=dict)  # block -> [min, max]
    centre: dict = field(default_factory=dict)  # window name -> PLL centre frequency in force [Hz]
    non_finite: int = 0  # output rows with a non-finite value (left out of the windows)
    pending: list = field(default_factory=list)
    pending_n: int = 0

    def add_batch(self, raw) -> None:
        """Pass 2: one ``pll/outputs`` message (queued; handled in batches of SERIES_BATCH
        outputs)."""
        b = cdr_fm_batch(raw)
        if b.t.shape[0] == 0:
            return
        self.pending.append((np.array(b.t), *(np.array(getattr(b, name)) for name in BLOCKS)))
        self.pending_n += b.t.shape[0]
        if self.pending_n >= SERIES_BATCH:
            self.flush()

    def flush(self) -> None:
        """Pass 2: the queued outputs into the envelopes, extremes and windows."""
        if not self.pending:
            return
        cols = [np.concatenate(c) for c in zip(*self.pending)]
        self.pending, self.pending_n = [], 0
        t, values = cols[0], dict(zip(BLOCKS, cols[1:]))
        ok = np.logical_and.reduce([np.isfinite(v) for v in values.values()])
        self.non_finite += int((~ok).sum())
        for name, v in values.items():
            finite = np.isfinite(v)
            self.envelopes[name].add(t, np.where(finite, v, np.nan))
            if finite.any():
                lo, hi = self.extremes[name]
                self.extremes[name] = [
                    min(lo, float(v[finite].min())),
                    max(hi, float(v[finite].max())),
                ]
        rows = [values[name][ok] for name in BLOCKS]
        for w, _ in self.windows.values():
            w.add(t[ok], *rows)


def _number(value):
    return (
        float(value)
        if isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
        else None
    )


def prepare(data, stream, stage: dict) -> FmData | None:
    """Between the passes: set-up from the parameters, times and windows (module docstring)."""
    if stream is None or not stream.outputs:
        return None
    fm = FmData(
        stream,
        data.fm_feedback,
        _number(current(data, "z_controller", "df_setpoint")),
        _number(current(data, "pll", "amplitude_setpoint")),
        _number(current(data, "cantilever", "spring_constant")),
        _number(current(data, "cantilever", "quality_factor")),
    )
    t_first, t_last = stream.t_first, stream.t_last
    fm.approach_started = stage.get("approach_started_s")
    if "engaged_s" in stage and (
        fm.approach_started is None or stage["engaged_s"] >= fm.approach_started
    ):
        fm.engaged, fm.engaged_from = (
            stage["engaged_s"],
            "z_controller/stage",
        )  # (not from an earlier approach)
    elif data.plan.engage_log is not None:
        fm.engaged, fm.engaged_from = data.plan.engage, "the z controller's `enabled` change"
    g = data.geometry or {}
    start = _number(g.get("start_time_s"))
    if start is not None:
        lines, rate = _number(g.get("lines")), _number(g.get("line_rate_Hz"))
        end = start + lines / rate if lines and rate and g.get("continuous") is False else t_last
        fm.scan = (start, end)
    if fm.approach_started is not None and fm.approach_started > t_first:
        lo = t_first + 0.5 * (fm.approach_started - t_first)
        fm.windows["free"] = (
            FmWindow(lo, fm.approach_started),
            "free: withdrawn, second half before the approach",
        )
    if fm.engaged is not None:
        before_scan = fm.scan is not None and fm.scan[0] > fm.engaged
        end = fm.scan[0] if before_scan else math.nextafter(t_last, math.inf)
        fm.windows["engaged"] = (
            FmWindow(fm.engaged + 0.5 * (end - fm.engaged), end),
            "engaged: second half " + ("before the scan" if before_scan else "to the end"),
        )
    if fm.scan is not None:
        fm.windows["scan"] = (
            FmWindow(fm.scan[0], min(fm.scan[1], math.nextafter(t_last, math.inf))),
            "scan: the recorded frame",
        )
    if not fm.windows:
        fm.windows["last_half"] = (
            FmWindow(t_first + 0.5 * (t_last - t_first), math.nextafter(t_last, math.inf)),
            "last half of the session",
        )
    for name, (w, _) in fm.windows.items():
        fm.centre[name] = _number(current(data, "pll", "center_frequency", at=w.t0))
    fm.envelopes = {
        b: Envelope(stream.t_min, stream.t_max, raw_cap=SERIES_RAW_POINTS) for b in BLOCKS
    }
    fm.extremes = {b: [math.inf, -math.inf] for b in BLOCKS}
    return fm


def window_numbers(fm: FmData, name: str) -> dict:
    """Mean and std (SI units) of each block over window ``name``, its dissipation per cycle [J]
    and, for the free window, the oscillator frequency [Hz] and Q = k A / F."""

    w, what = fm.windows[name]
    out = {"what": what, "window_s": [w.t0, w.t1], "outputs": w.n}
    if not w.n:
        return out
    for b in BLOCKS:
        out[b] = {"mean": w.mean(b), "std": w.std(b)}
    k, q = fm.spring_constant, fm.quality_factor
    if k and q:
        out["dissipation_J"] = float(
            dissipation_from_drive(w.mean("drive"), w.mean("amplitude"), k, q)
        )
    if name == "free":
        if fm.centre.get(name) is not None:
            out["oscillator_Hz"] = fm.centre[name] + w.mean("df")
        if k and w.mean("drive") > 0:
            out["quality_factor_measured"] = k * w.mean("amplitude") / w.mean("drive")
    return out


def numbers(fm: FmData) -> dict:
    """The FM numbers of ``afm_report --json`` (SI units)."""
    s = fm.stream
    return {
        "topic": s.topic,
        "outputs": s.outputs,
        "batches": s.messages,
        "lost_input_samples": s.lost,
        "gaps": s.gaps,
        "t_first_s": s.t_first,
        "t_last_s": s.t_last,
        "non_finite_outputs": fm.non_finite,
        "z_on_frequency_shift": fm.feedback,
        "df_setpoint_Hz": fm.df_setpoint,
        "amplitude_setpoint_m": fm.amplitude_setpoint,
        "spring_constant_N_per_m": fm.spring_constant,
        "quality_factor_set": fm.quality_factor,
        "approach_started_s": fm.approach_started,
        "engaged_s": fm.engaged,
        "scan_s": list(fm.scan) if fm.scan else None,
        "extremes": {f"{b}_{SI_UNITS[b]}": v for b, v in fm.extremes.items() if v[0] <= v[1]},
        "windows": {name: window_numbers(fm, name) for name in fm.windows},
    }


def markers(fm: FmData) -> dict:
    """The engage and scan times for the other figures (the tracking numbers of an FM session)."""
    out = {}
    if fm.engaged is not None:
        out["engage_time_s"] = fm.engaged
    if fm.scan is not None:
        out["scan_start_s"] = fm.scan[0]
    return out


def _pm(entry: dict, block: str) -> str:
    scale = DISPLAY[block][0]
    return f"{entry[block]['mean'] * scale:.5g} ± {entry[block]['std'] * scale:.3g}"


def markdown_lines(fm: FmData) -> list[str]:
    """The FM section of report.md."""
    s = fm.stream
    lines = [
        "",
        "## FM-AFM (PLL and amplitude controller)",
        "",
        f"PLL outputs (`{s.topic}`): {s.outputs} outputs in {s.messages} batches, simulated "
        f"{s.t_first:.6g} s "
        f"to {s.t_last:.6g} s; "
        + (
            "complete: every input sample has its outputs"
            if s.lost == 0
            else f"{s.lost} input samples without outputs in {s.gaps} gaps"
        )
        + (f", {s.repeats} repeated batches" if s.repeats else "")
        + ".",
    ]
    setup = []
    if fm.feedback:
        setup.append(
            "the z loop regulates the frequency shift"
            + (
                f" to df = {fm.df_setpoint:g} Hz (`df_setpoint` at the end)"
                if fm.df_setpoint is not None
                else ""
            )
        )
    if fm.amplitude_setpoint is not None:
        setup.append(f"amplitude setpoint {fm.amplitude_setpoint * 1e9:g} nm")
    if fm.spring_constant and fm.quality_factor:
        setup.append(
            f"cantilever k = {fm.spring_constant:g} N/m, Q = {fm.quality_factor:g} as set (the "
            "dissipation's reference: E = π A F − π k A² / Q)"
        )
    events = []
    if fm.approach_started is not None:
        events.append(f"approach started at {fm.approach_started:.6g} s")
    if fm.engaged is not None:
        events.append(f"engaged at {fm.engaged:.6g} s ({fm.engaged_from})")
    if fm.scan is not None:
        events.append(f"scan from {fm.scan[0]:.6g} s to {fm.scan[1]:.6g} s (`scanner/geometry`)")
    if setup:
        lines += ["", "Set-up: " + "; ".join(setup) + "."]
    if events:
        lines += ["", "Times (simulated): " + "; ".join(events) + "."]
    lines += [
        "",
        "`fm.png`: df, drive, amplitude and phase error of every PLL output (min/max envelope "
        "when long). "
        "Mean ± standard deviation over each window:",
        "",
        "| window | simulated time [s] | outputs | df [Hz] | drive [pN] | amplitude [nm] | phase "
        "error [deg] "
        "| dissipation per cycle [aJ] |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for name in fm.windows:
        e = window_numbers(fm, name)
        span = f"{e['window_s'][0]:.6g} – {e['window_s'][1]:.6g}"
        if not e["outputs"]:
            lines.append(f"| {e['what']} | {span} | 0 | — | — | — | — | — |")
            continue
        diss = f"{e['dissipation_J'] * 1e18:.4g}" if "dissipation_J" in e else "—"
        lines.append(
            f"| {e['what']} | {span} | {e['outputs']} | {_pm(e, 'df')} | {_pm(e, 'drive')} | "
            f"{_pm(e, 'amplitude')} | {_pm(e, 'phase_error')} | {diss} |"
        )
    free = window_numbers(fm, "free") if "free" in fm.windows else {}
    extra = []
    if "oscillator_Hz" in free:
        extra.append(
            f"free oscillator frequency {free['oscillator_Hz']:.4f} Hz (PLL centre "
            f"{fm.centre['free']:g} Hz + df)"
        )
    if "quality_factor_measured" in free:
        extra.append(f"Q = k A / F = {free['quality_factor_measured']:.5g} (free)")
    engaged = window_numbers(fm, "engaged") if "engaged" in fm.windows else {}
    if engaged.get("outputs") and fm.feedback and fm.df_setpoint is not None:
        extra.append(f"engaged df − setpoint = {engaged['df']['mean'] - fm.df_setpoint:+.3g} Hz")
    if engaged.get("outputs") and free.get("outputs") and free["drive"]["mean"] > 0:
        extra.append(
            f"engaged drive {engaged['drive']['mean'] / free['drive']['mean']:.3g} x free"
        )
    if extra:
        text = "; ".join(extra)
        lines += ["", text[0].upper() + text[1:] + "."]
    ext = [
        f"{b.replace('_', ' ')} {v[0] * DISPLAY[b][0]:.4g} to {v[1] * DISPLAY[b][0]:.4g} "
        f"{DISPLAY[b][1]}"
        for b, v in fm.extremes.items()
        if v[0] <= v[1]
    ]
    if ext:
        lines += ["", "Over the whole session: " + ", ".join(ext) + "."]
    if fm.non_finite:
        lines += [
            "",
            f"{fm.non_finite} outputs with a non-finite value (drawn as gaps, left out of the "
            "windows).",
        ]
    return lines


def write_figure(data, out: Path) -> Path | None:
    """``fm.png``: df (with the z loop's setpoint), drive, amplitude (with its setpoint) and phase
    error against simulated time, the windows shaded, approach / engage / scan marked."""
    fm = data.fm
    if fm is None:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(
        len(BLOCKS), 1, figsize=(9, 2.4 * len(BLOCKS)), sharex=True, squeeze=False
    )
    shades = {"free": "C0", "engaged": "C2", "scan": "C4", "last_half": "C7"}
    for ax, b in zip(axes[:, 0], BLOCKS):
        scale, _, label = DISPLAY[b]
        fm.envelopes[b].draw(ax, scale)
        ax.set_ylabel(label)
        if b == "df" and fm.feedback and fm.df_setpoint is not None and fm.engaged is not None:
            ax.hlines(
                fm.df_setpoint,
                fm.engaged,
                fm.stream.t_max,
                color="k",
                ls="--",
                lw=0.8,
                label="df setpoint",
            )
            ax.legend(loc="best", fontsize=8)
        if b == "amplitude" and fm.amplitude_setpoint is not None:
            ax.axhline(fm.amplitude_setpoint * scale, color="k", ls="--", lw=0.8, label="setpoint")
            ax.legend(loc="best", fontsize=8)
        for name, (w, _) in fm.windows.items():
            ax.axvspan(w.t0, w.t1, color=shades.get(name, "C7"), alpha=0.08, lw=0)
        for t, color in (
            (fm.approach_started, "C1"),
            (fm.engaged, "C2"),
            (fm.scan[0] if fm.scan else None, "C4"),
        ):
            if t is not None:
                ax.axvline(t, color=color, ls=":", lw=0.8)
    axes[0, 0].set_title(
        f"from {fm.stream.topic} (every PLL output, exact simulated time); shaded: "
        + ", ".join(fm.windows),
        fontsize=9,
    )
    axes[-1, 0].set_xlabel(data.time_axis)
    fig.tight_layout()
    path = out / "fm.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
