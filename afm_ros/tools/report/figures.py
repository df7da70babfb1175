"""The report's figures (PNG): the deflection and force traces, the lock-in and z traces, the
force-distance pairs, the last frame's images, the drive tune and the z spectroscopy."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from afm_ros.core.tune import TuneResult
from afm_ros.formats.frames import RANGE_TEXT, display_image
from afm_ros.tools.bimodal_figure import plot_bimodal
from afm_ros.tools.report.accumulators import Envelope
from afm_ros.tools.report.collect import SETTLING_BAND, ZOOM_PERIODS, force_distance
from afm_ros.tools.report.session import (
    ChunkStream,
    SessionData,
    image_unit,
    number_text,
    shown_images,
)
from afm_ros.tools.spectroscopy_figure import plot_spectroscopy
from afm_ros.tools.tune_figure import plot_tune


def _plot_trace(ax_full, ax_zoom, stream: ChunkStream, scale, label, color):
    env = stream.envelope
    if env.is_raw:
        t, v = env.points()
        ax_full.plot(t, v * scale, color=color, lw=0.8)
    else:
        tb, lo, hi = env.bands()
        ax_full.fill_between(tb, lo * scale, hi * scale, color=color, alpha=0.6, lw=0)
    ax_full.set_ylabel(label)
    t, v = stream.zoom
    ax_zoom.plot((t - stream.t_last) * 1e6, v * scale, color=color, lw=0.8)
    ax_zoom.set_ylabel(label)


def _plot_setpoint(ax, data: SessionData, env: Envelope, scale: float) -> None:
    """The setpoint in force over time (a step at every change) with the settling band."""
    numbers = data.tracking
    t_lo, t_hi = env.t_lo, env.t_lo + env.bins * env.width
    start = (
        numbers["setpoint_changes"][0]["old_m"]
        if numbers.get("setpoint_changes")
        else numbers["setpoint_m"]
    )
    if start is None:
        start = numbers["setpoint_m"]
    edges, values = [t_lo], [start]
    for c in numbers.get("setpoint_changes", []):
        edges.append(min(max(c["time_s"], t_lo), t_hi))
        values.append(c["new_m"])
    edges.append(t_hi)
    values = np.array(values + [values[-1]], dtype=float)
    ax.step(edges, values * scale, where="post", color="k", ls="--", lw=0.8, label="setpoint")
    ax.fill_between(
        edges,
        values * (1 - SETTLING_BAND) * scale,
        values * (1 + SETTLING_BAND) * scale,
        step="post",
        color="k",
        alpha=0.08,
        lw=0,
        label=f"±{SETTLING_BAND * 100:g} %",
    )
    for c in numbers.get("setpoint_changes", []):
        ax.axvline(c["time_s"], color="C1", ls=":", lw=0.8)
    ax.legend(loc="best", fontsize=8)


def write_figures(data: SessionData, out: Path) -> list[Path]:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    figures = []
    streams = [
        (s, sc, lab, col)
        for s, sc, lab, col in (
            (data.deflection, 1e9, "deflection [nm]", "C0"),
            (data.force, 1e9, "tip-sample force [nN]", "C3"),
        )
        if s is not None and s.samples and s.envelope is not None
    ]
    if streams:
        fig, axes = plt.subplots(len(streams), 2, figsize=(11, 3.2 * len(streams)), squeeze=False)
        for row, (s, sc, lab, col) in enumerate(streams):
            _plot_trace(axes[row, 0], axes[row, 1], s, sc, lab, col)
        axes[0, 0].set_title("whole session (min/max envelope)")
        axes[0, 1].set_title(f"last {ZOOM_PERIODS} drive periods")
        axes[-1, 0].set_xlabel("simulated time [s]")
        axes[-1, 1].set_xlabel(f"simulated time - {streams[0][0].t_last:.6g} s [µs]")
        fig.tight_layout()
        figures.append(out / "deflection_force.png")
        fig.savefig(figures[-1], dpi=110)
        plt.close(fig)

    error = (
        (1.0, "df error = df setpoint - df [Hz]")
        if data.fm_feedback
        else (1e9, "error = setpoint - amplitude [nm]")
    )
    rows = [
        (r, sc, lab)
        for r, sc, lab in (
            ("amplitude", 1e9, "amplitude [nm]"),
            ("phase", 1.0, "phase [deg]"),
            ("z_piezo", 1e9, "z piezo [nm]"),
            ("error", *error),
        )
        if r in data.series and data.series[r].envelope is not None
    ]
    if rows:
        numbers = data.tracking
        fig, axes = plt.subplots(
            len(rows), 1, figsize=(9, 2.4 * len(rows)), sharex=True, squeeze=False
        )
        for ax, (role, sc, lab) in zip(axes[:, 0], rows):
            env = data.series[role].envelope
            env.draw(ax, sc)
            ax.set_ylabel(lab, fontsize=8 if role == "error" else None)
            if role == "amplitude" and "setpoint_m" in numbers:
                _plot_setpoint(ax, data, env, sc)
            if "engage_time_s" in numbers:
                ax.axvline(numbers["engage_time_s"], color="C2", ls=":", lw=0.8)
            if "scan_start_s" in numbers:
                ax.axvline(numbers["scan_start_s"], color="C4", ls=":", lw=0.8)
        axes[0, 0].set_title(
            f"from {data.series[rows[0][0]].topic}"
            + (
                " (every lock-in output, exact simulated time)"
                if data.series[rows[0][0]].batch is not None
                else ""
            ),
            fontsize=9,
        )
        axes[-1, 0].set_xlabel(data.time_axis)
        fig.tight_layout()
        figures.append(out / "lockin_z.png")
        fig.savefig(figures[-1], dpi=110)
        plt.close(fig)

    fd = force_distance(data)
    if fd is not None:
        gap, force, _ = fd
        fig, ax = plt.subplots(figsize=(6.5, 4.5))
        ax.plot(gap * 1e9, force * 1e9, ".", ms=1.0, alpha=0.4)
        ax.axvline(0.0, color="k", lw=0.6)
        ax.set_xlabel("gap = z_offset + deflection [nm]")
        ax.set_ylabel("tip-sample force [nN]")
        ax.set_title("force-distance, reconstructed from the recorded chunks")
        fig.tight_layout()
        figures.append(out / "force_distance.png")
        fig.savefig(figures[-1], dpi=110)
        plt.close(fig)
    return figures


def write_image_figure(data: SessionData, out: Path) -> Path | None:
    """``images.png``: the last recorded frame, one panel per channel (columns) and direction
    (rows), in display units (nm, deg, aJ, ...), colour range
    :func:`afm_ros.formats.frames.display_range`, heights plane-levelled, axes in µm when the scan
    geometry is known."""
    shown = shown_images(data)
    if not shown:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import ScalarFormatter

    channels = list(dict.fromkeys(it.channel for it in shown))
    directions = list(
        dict.fromkeys(it.direction for it in sorted(shown, key=lambda it: it.direction != "trace"))
    )
    fig, axes = plt.subplots(
        len(directions),
        len(channels),
        figsize=(3.3 * len(channels), 3.1 * len(directions)),
        squeeze=False,
    )
    for ax in axes.ravel():
        ax.axis("off")
    g = data.geometry
    for it in shown:
        ax = axes[directions.index(it.direction)][channels.index(it.channel)]
        ax.axis("on")
        levelled = it.channel == "height"
        values, (lo, hi), unit_text = display_image(
            it.array, image_unit(data, it.channel), levelled
        )
        extent = None
        if g:
            x0, y0 = g["x_offset_m"] * 1e6, g["y_offset_m"] * 1e6
            extent = (
                x0,
                x0 + g["size_x_m"] * 1e6,
                y0 + g["size_y_m"] * 1e6,
                y0,
            )  # row 0 (lowest y) on top
            ax.set_xlabel("x [µm]", fontsize=8)
            ax.set_ylabel("y [µm]", fontsize=8)
        else:
            ax.set_xlabel("pixel", fontsize=8)
            ax.set_ylabel("line", fontsize=8)
        im = ax.imshow(
            values, cmap="afmhot", extent=extent, interpolation="nearest", vmin=lo, vmax=hi
        )
        ax.tick_params(labelsize=7)
        bar = fig.colorbar(im, ax=ax, fraction=0.046, pad=0.04, extend="both")
        formatter = ScalarFormatter(useOffset=False)
        formatter.set_scientific(False)
        bar.formatter = formatter
        bar.update_ticks()
        bar.ax.tick_params(labelsize=7)
        bar.set_label(f"{it.channel.replace('_', ' ')} [{unit_text}]", fontsize=8)
        ax.set_title(
            f"{it.channel.replace('_', ' ')} ({it.direction})"
            + (", plane-levelled" if levelled else ""),
            fontsize=9,
        )
    if g:
        size = (
            f"{number_text(g, 'size_x_m', 1e6, '.3g')} x "
            f"{number_text(g, 'size_y_m', 1e6, '.3g')} µm, "
        )
    else:
        size = "scan geometry unknown, "
    fig.suptitle(f"last recorded frame: {size}{RANGE_TEXT} (spikes clipped)", fontsize=10)
    fig.tight_layout()
    path = out / "images.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return path


def write_tune_figure(data: SessionData, out: Path) -> Path | None:
    """``tune.png``: the recorded drive sweep with its fit and working point
    (tools/tune_figure.py)."""
    t = data.tune
    if t is None:
        return None

    fit = TuneResult(
        t["frequency_Hz"],
        t["amplitude_m"],
        t["phase_deg"],
        t["f0_Hz"],
        t["Q"],
        static_amplitude=t["static_amplitude_m"],
        phase0_deg=t["phase0_deg"],
        drive_frequency=t["drive_frequency_Hz"],
    )
    return plot_tune(
        fit,
        out / "tune.png",
        "Drive tune (lockin/tune_result), before the phase offset was applied",
    )


def write_spectroscopy_figure(data: SessionData, out: Path) -> Path | None:
    """``spectroscopy.png``: the last recorded z spectroscopy curve
    (tools/spectroscopy_figure.py)."""
    if data.spectroscopy is None:
        return None

    c = data.spectroscopy
    return plot_spectroscopy(
        c,
        out / "spectroscopy.png",
        f"Z spectroscopy at ({c.x * 1e6:.3g}, {c.y * 1e6:.3g}) um, {c.rate * 1e9:.4g} nm/s "
        "(z_controller/spectroscopy)",
    )


def write_bimodal_figure(data: SessionData, out: Path) -> Path | None:
    """``bimodal.png``: the bimodal node's last recorded frame (tools/bimodal_figure.py); mode 2's
    phase where no frequency shift was measured (AM-AM)."""
    if data.bimodal_frame is None:
        return None
    images, corner, size = data.bimodal_frame
    fm = bool(np.isfinite(images["frequency_shift_2"]).any())
    return plot_bimodal(images, corner, size, fm, out / "bimodal.png")
