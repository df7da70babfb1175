"""``report.md``: file status, ERROR statuses, topics, streams, setpoint tracking, force-distance,
images, what was skipped and the parameters."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from afm_ros.formats.frames import RANGE_TEXT, display_scale
from afm_ros.tools.report.collect import DISPLAY_MAX_PIXELS, SETTLING_BAND
from afm_ros.tools.report.fm import markdown_lines
from afm_ros.tools.report.plan import parse_float
from afm_ros.tools.report.session import (
    ChunkStream,
    SessionData,
    image_unit,
    nth,
    number_text,
    shown_images,
)
from afm_ros.tools.report.survey import spectroscopy_numbers


def lost_samples(index: np.ndarray) -> tuple[int, int]:
    """(samples missing, gaps) in a running sample index (sorted by arrival)."""
    if index.size < 2:
        return 0, 0
    step = np.diff(index)
    gaps = step > 1
    return int(np.sum(step[gaps] - 1)), int(np.count_nonzero(gaps))


def stream_completeness(stream: ChunkStream) -> str:
    """One sentence: complete, or how many samples were lost in how many gaps (and repeats)."""
    text = (
        "complete: no sample lost (no gap in the sample index)"
        if stream.lost == 0
        else f"{stream.lost} samples lost in {stream.gaps} gaps of the sample index"
    )
    text += f", {stream.repeats} repeated or out-of-order chunks" if stream.repeats else ""
    if stream.non_finite:
        text += (
            f"; {stream.non_finite} non-finite samples (left out of the envelope and the "
            "force-distance numbers)"
        )
    return text


def _fmt(value, unit="", scale=1.0):
    if value is None:
        return "—"
    if isinstance(value, float):
        return f"{value * scale:.4g}{(' ' + unit) if unit else ''}"
    return f"{value}{(' ' + unit) if unit else ''}"


def _sim_time_of(data: SessionData, values: dict, log_time: int) -> tuple[float, bool]:
    """(time on the report's axis, exact) of a diagnostic status: its ``simulated_time_s`` value if
    it has one, else its receive time mapped onto the axis."""
    t = parse_float(values.get("simulated_time_s"))
    if t is not None and math.isfinite(t) and data.time_axis.startswith("simulated"):
        return t, True
    return float(data.plan.map(log_time)), False


def diagnostic_errors(data: SessionData) -> list[dict]:
    """Every distinct ERROR status recorded on /diagnostics: name, message, first time, count,
    values."""
    out = []
    if data.diagnostics is None:
        return out
    for (name, message), e in data.diagnostics.entries.items():
        t, exact = _sim_time_of(data, e["values"], e["first_log"])
        out.append(
            {
                "name": name,
                "message": message,
                "time_s": t,
                "time_from_status": exact,
                "count": e["count"],
                "values": e["values"],
            }
        )
    return out


def _setpoint_lines(data: SessionData) -> list[str]:
    numbers = data.tracking
    changes = numbers.get("setpoint_changes", [])
    if not changes:
        return []
    exact = all(c["exact_time"] for c in changes)
    lines = [
        "",
        "### Setpoint changes",
        "",
        (
            "Times: the first lock-in output computed with the new setpoint (amplitude + error of "
            "every output; "
            "exact simulated time)."
            if exact
            else "Times: the receive time of the parameter change on /parameter_events, placed on "
            "the time axis "
            "through the recorded clock (good to the delivery latency, a few ms)."
        ),
        "",
        f"| {data.time_axis} | setpoint old → new | settling (into ±{SETTLING_BAND * 100:g} % of "
        "the new "
        "setpoint) |",
        "|---|---|---|",
    ]
    for c in changes:
        if not c["engaged"]:
            settle = "before engaging (no feedback)"
        elif not c.get("outputs_after"):
            settle = "no lock-in output after it"
        elif c.get("settling_time_s") is None:
            settle = "**not settled** (outside the band at the next change or at the end)"
        else:
            settle = f"{c['settling_time_s']:.4g} s"
        if c.get("during_scan"):
            settle += " (while scanning)"
        old = "—" if c["old_m"] is None else f"{c['old_m'] * 1e9:.6g}"
        lines.append(f"| {c['time_s']:.6g} | {old} → {c['new_m'] * 1e9:.6g} nm | {settle} |")
    return lines


def write_markdown(
    data: SessionData, figures: list[Path], out: Path, images=None, geometry=None
) -> Path:
    scan = data.scan
    lines = [f"# AFM session report: `{data.path.name}`", ""]
    if scan.complete:
        lines.append(
            f"File complete ({scan.file_size} bytes, profile "
            f"`{scan.header.profile if scan.header else '?'}`)."
        )
    else:
        lines.append(
            f"**File incomplete**: {scan.truncated_reason}. This report covers the intact part "
            f"({scan.bytes_read} of {scan.file_size} bytes)."
        )
    errors = diagnostic_errors(data)
    if errors:
        lines += ["", "## ERRORS reported during the session", ""]
        for e in errors:
            when = (
                f"t = {e['time_s']:.6g} s"
                if e["time_from_status"]
                else f"received at {e['time_s']:.6g} s ({data.time_axis})"
            )
            lines.append(
                f"- **{e['name']}**: {e['message']} ({when}; {e['count']} status "
                f"message{'s' if e['count'] != 1 else ''})"
            )
            if "blowup_parameters" in e["values"]:
                lines.append(f"  - parameters in force: {e['values']['blowup_parameters']}")
        if data.diagnostics.dropped:
            lines.append(
                f"- and {data.diagnostics.dropped} more ERROR statuses with other messages (not "
                "listed)"
            )
        lines.append("")
        lines.append(
            "The numbers below cover what was recorded; after such an error they describe a "
            "stopped "
            "or restarted instrument."
        )
    if data.diagnostics is not None and data.diagnostics.unreadable:
        lines += [
            "",
            f"{data.diagnostics.unreadable} /diagnostics messages did not deserialise (skipped).",
        ]
    lines += ["", "## Topics", "", "| topic | type | messages |", "|---|---|---|"]
    for topic, type_name in sorted(scan.topics.items()):
        lines.append(f"| `{topic}` | `{type_name}` | {scan.message_counts.get(topic, 0)} |")
    missing = [role for role in ("deflection", "force") if role not in data.topics] + [
        role for role in ("amplitude", "phase", "z_piezo", "error") if role not in data.series
    ]
    if missing:
        lines += ["", f"Not recorded (figures/numbers skipped): {', '.join(missing)}."]
    if data.tune is not None:
        t = data.tune
        lines += [
            "",
            "## Drive tune",
            "",
            f"{t['frequency_Hz'].size} drive frequencies from {t['frequency_Hz'][0]:.2f} to "
            f"{t['frequency_Hz'][-1]:.2f} Hz (`tune.png`): f0 = {t['f0_Hz']:.3f} +- "
            f"{t['f0_error_Hz']:.2g} Hz, "
            f"Q = {t['Q']:.4f} +- {t['Q_error']:.2g} (driven-oscillator fit). Working point: "
            f"{t['drive_frequency_Hz']:.3f} Hz, drive scaled by {t['drive_scale']:.5f}, lock-in "
            "phase offset "
            f"changed by {t['phase_offset_deg']:.3f} deg.",
        ]
    if data.bimodal is not None:
        lines += _bimodal_lines(data.bimodal, data.bimodal_frame is not None)
    if data.spectroscopy is not None:
        g = spectroscopy_numbers(data.spectroscopy)
        lines += [
            "",
            "## Z spectroscopy",
            "",
            f"At ({g['x_m'] * 1e6:.4g}, {g['y_m'] * 1e6:.4g}) um from t = {g['t_start_s']:.4f} s "
            "to "
            f"{g['t_end_s']:.4f} s (`spectroscopy.png`), feedback held: z up "
            f"{g['retract_m'] * 1e9:.3g} nm, down "
            f"{g['distance_m'] * 1e9:.3g} nm and back at {g['rate_m_per_s'] * 1e9:.4g} nm/s, "
            f"{g['outputs']} lock-in "
            f"outputs and {g['chunks']} chunks ({g['missing_chunks']} without samples). Approach "
            "from gap "
            f"{(g['z_gap_held_m'] + g['retract_m']) * 1e9:.2f} to {g['z_gap_lowest_m'] * 1e9:.2f} "
            "nm: amplitude "
            f"{g['amplitude_top_m'] * 1e9:.3f} -> {g['amplitude_bottom_m'] * 1e9:.3f} nm, phase "
            f"{g['phase_top_deg']:.2f} -> {g['phase_bottom_deg']:.2f} deg; mean tip-sample force "
            f"{g['min_mean_force_N'] * 1e9:.3f} to {g['max_mean_force_N'] * 1e9:.3f} nN. At this "
            "rate the curve "
            f"lags the commanded z by {g['lag_z_m'][0] * 1e9:.3g} to {g['lag_z_m'][1] * 1e9:.3g} "
            "nm "
            "(feedback latency and the amplitude's Q/(pi f0); docs/spectroscopy.md).",
        ]
    for topic, type_name, expected in data.ignored:
        lines += ["", f"Ignored `{topic}`: type `{type_name}`, not `{expected}`."]
    if data.unused:
        lines += [
            "",
            f"Also recorded, not read: {', '.join(f'`{t}`' for t in data.unused)} (the per-output "
            "copies of "
            "the batches the report reads: same values, the batches complete and in time order).",
        ]

    for name, s in (("Deflection", data.deflection), ("Tip-sample force", data.force)):
        if s is not None:
            span = (
                f", simulated {s.t_first:.6g} s to {s.t_last:.6g} s"
                if name == "Deflection" and s.samples
                else ""
            )
            lines += ["", f"{name}: {s.samples} samples{span}; {stream_completeness(s)}."]
    for role, b in data.batches.items():
        what = "Lock-in outputs" if role == "outputs" else "z controller outputs"
        text = (
            f"{what} (`{b.topic}`): {b.outputs} outputs in {b.messages} batches, simulated "
            f"{b.t_first:.6g} s to "
            f"{b.t_last:.6g} s"
        )
        if role == "outputs":
            text += (
                "; complete: every input sample has its outputs"
                if b.lost == 0
                else f"; {b.lost} input samples without outputs in {b.gaps} gaps"
            )
        if b.repeats:
            text += f", {b.repeats} repeated batches"
        lines += ["", text + "."]
    sd = data.setpoint_data
    if sd is not None and (sd.unpaired or sd.mismatched):
        lines += [
            "",
            f"Setpoint from the data: {sd.unpaired} batch(es) without a partner on the other "
            "topic (e.g. "
            f"the last lock-in batch, recorded before its answer), {sd.mismatched} pairs with "
            "other output "
            "times (not used).",
        ]

    if data.fm is not None:
        lines += markdown_lines(data.fm)
    numbers = (
        {} if data.fm_feedback else data.tracking
    )  # FM: the z loop regulates df (the FM section)
    if not data.fm_feedback:
        lines += ["", "## Setpoint tracking", ""]
    if numbers:
        settle = numbers.get("settling_time_s")
        changes = numbers.get("setpoint_changes", [])
        engaged_changes = any(c["engaged"] for c in changes)
        final = numbers.get("final_window_s") or [None, None]
        scan = numbers.get("scan_start_s")
        first_end = [f"before the scan started at {scan:.6g} s"] if scan is not None else []
        if engaged_changes:
            first_end.insert(0, "before the first change")
        if numbers.get("settled_at_end", False) is None:
            window = "last 20 % of the scan" + (
                " since the last change"
                if engaged_changes and any(c.get("during_scan") for c in changes)
                else ""
            )
        else:
            window = "last 20 %" + (" since the last change" if engaged_changes else "")
        settle_text = (
            "—"
            if "settling_time_s" not in numbers
            else "not settled"
            if settle is None
            else _fmt(settle, "s")
        )
        lines += [
            "| quantity | value |",
            "|---|---|",
            f"| free amplitude | {_fmt(numbers.get('free_amplitude_m'), 'nm', 1e9)} |",
            f"| setpoint{' at the end' if changes else ''} | "
            f"{_fmt(numbers.get('setpoint_m'), 'nm', 1e9)} |",
            f"| engaged at | {_fmt(numbers.get('engage_time_s'), 's')} |",
            f"| settling time after engaging (into ±{SETTLING_BAND * 100:g} % of the setpoint "
            "then in force"
            f"{', ' + ' and '.join(first_end) if first_end else ''}) | {settle_text} |",
            f"| reached amplitude ({window}) | "
            f"{_fmt(numbers.get('reached_amplitude_m'), 'nm', 1e9)} |",
            "| rms tracking error (same window) | "
            f"{_fmt(numbers.get('rms_tracking_error_m'), 'nm', 1e9)} |",
            f"| phase in contact (same window) | {_fmt(numbers.get('contact_phase_deg'), 'deg')} "
            "|",
            "| z piezo in contact (same window) | "
            f"{_fmt(numbers.get('contact_z_piezo_m'), 'nm', 1e9)} |",
        ]
        if "setpoint_from_error_m" in numbers:
            how = (
                "amplitude + error of every output"
                if data.setpoint_source == "data"
                else "median of amplitude + error over the last 20 %"
            )
            lines.append(
                f"| setpoint from the data ({how}) | "
                f"{_fmt(numbers['setpoint_from_error_m'], 'nm', 1e9)} |"
            )
        lines += _setpoint_lines(data)
        if "settled_at_end" in numbers:
            span = (
                f" ({window}: {final[0]:.6g} s to {final[1]:.6g} s)" if None not in final else ""
            )
            state = {
                None: f"scanning (the amplitude follows the topography; rms error "
                f"{_fmt(numbers.get('rms_tracking_error_m'), 'nm', 1e9)}).",
                True: "settled (inside the band at the end).",
                False: "**not settled** (outside the band at the end).",
            }[numbers["settled_at_end"]]
            lines += [
                "",
                f"State at the end{span}: setpoint {_fmt(numbers.get('setpoint_m'), 'nm', 1e9)}, "
                "amplitude "
                f"{_fmt(numbers.get('reached_amplitude_m'), 'nm', 1e9)}, {state}",
            ]
    elif not data.fm_feedback:
        lines.append("No lock-in amplitude recorded.")
    skipped = [
        f"{s.non_finite} non-finite {role.replace('_', ' ')} samples"
        for role, s in data.series.items()
        if s.non_finite
    ]
    if skipped:
        lines += ["", f"Skipped (never averaged): {', '.join(skipped)}."]
    for note in data.notes:
        lines += ["", note]

    fd = data.fd
    if fd is not None:
        kept = fd.gap.size
        lines += ["", "## Force-distance", ""]
        if fd.pairs - fd.non_finite > 0:
            lines.append(
                f"{fd.pairs} matched samples; minimum gap {fd.min_gap * 1e9:.4g} nm, maximum "
                "(repulsive) "
                f"force {fd.max_force * 1e9:.4g} nN, minimum (adhesive) force "
                f"{fd.min_force * 1e9:.4g} nN "
                f"(over all of them)."
            )
        else:
            lines.append(f"{fd.pairs} matched samples, none finite.")
        if fd.non_finite:
            lines.append(f"{fd.non_finite} non-finite pairs left out.")
        if kept < fd.pairs - fd.non_finite:
            lines.append(f"The figure shows {kept} of them, evenly spaced in the sample index.")
    lines += _image_lines(data)
    if data.skipped:
        lines += ["", "## Skipped", ""] + [
            f"- `{topic}`: {why}" for topic, why in sorted(data.skipped.items())
        ]
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


def _bimodal_lines(table: dict, figure: bool) -> list[str]:
    """The bimodal node's last per-material table: the recovered modulus against the truth (and
    the figure of its last frame, if drawn)."""

    def num(value, scale: float, fmt: str) -> str:
        return "n/a" if value is None else format(value * scale, fmt)

    lines = [
        "",
        "## Bimodal AM-FM: modulus per material against the truth",
        "",
        f"Frame {table['frame']}, {table['lines_done']} lines (`bimodal/materials`, medians over "
        "each material's pixels away from edges; docs/bimodal.md 7)"
        + ("; `bimodal.png`: height, mode 2's contrast, E* recovered, true." if figure else "."),
        "",
        "| material | pixels | E* recovered [GPa] | E* true [GPa] | bias | df2 [Hz] | "
        "indentation [nm] | height [nm] | tan(delta) mode 2 | true |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in table["materials"]:
        lines.append(
            f"| {r['material']} | {r['pixels']} | {num(r['modulus'], 1e-9, '.4f')} | "
            f"{num(r['true_modulus'], 1e-9, '.4f')} | {num(r['bias'], 100.0, '+.1f')} % | "
            f"{num(r['frequency_shift_2'], 1.0, '.1f')} | {num(r['indentation'], 1e9, '.2f')} | "
            f"{num(r['height'], 1e9, '.2f')} | {num(r['loss_tangent_2'], 1.0, '.4f')} | "
            f"{num(r['true_loss_tangent_2'], 1.0, '.4f')} |"
        )
    return lines


def _image_lines(data: SessionData) -> list[str]:
    shown = shown_images(data)
    if not shown:
        return []

    g = data.geometry
    lines = ["", "## Images (the last recorded frame)", ""]
    if g:
        sample = g.get("sample") if isinstance(g.get("sample"), str) else "?"
        lines += [
            f"{number_text(g, 'pixels', fmt='g')} x {number_text(g, 'lines', fmt='g')} pixels "
            "over "
            f"{number_text(g, 'size_x_m', 1e6, '.3g')} x {number_text(g, 'size_y_m', 1e6, '.3g')} "
            "µm at "
            f"{number_text(g, 'line_rate_Hz', fmt='g')} lines/s from x = "
            f"{number_text(g, 'x_offset_m', 1e6)} µm, "
            f"y = {number_text(g, 'y_offset_m', 1e6)} µm (row 0 = lowest y, shown at the top as "
            "in Gwyddion), sample "
            f"`{sample}`; scan started at t = {number_text(g, 'start_time_s', fmt='.6g')} s.",
            "",
        ]
    lines += [
        "`images.png`: heights plane-levelled (least-squares plane removed) and shown from the "
        "bottom of "
        f"their colour range; {RANGE_TEXT}, each channel on its own. The table gives the raw "
        "values.",
        "",
        "| channel | direction | lines acquired | min | median | max |",
        "|---|---|---|---|---|---|",
    ]
    for it in shown:
        st = it.stats
        if "min" in st:
            factor, unit_text = display_scale(
                np.array([st["min"], st["max"]]), image_unit(data, it.channel)
            )
            values = " | ".join(
                f"{st[k] / factor:.4g} {unit_text}" for k in ("min", "median", "max")
            )
        else:
            values = "- | - | -"
        lines.append(
            f"| {it.channel} | {it.direction} | {st['lines_acquired']} of {st['rows']} | {values} "
            "|"
        )
    reduced = [it for it in shown if it.stats.get("display_step", 1) > 1]
    if reduced:
        it = reduced[0]
        lines += [
            "",
            f"Images larger than {DISPLAY_MAX_PIXELS} pixels per side are drawn with every "
            f"{nth(it.stats['display_step'])} row and column ({it.stats['rows']} x "
            f"{it.stats['columns']}); "
            "the table is over every pixel.",
        ]
    return lines
