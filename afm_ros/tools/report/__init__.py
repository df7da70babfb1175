"""Lab-notebook report of a recorded session: PNG figures + Markdown summary, in bounded memory.

``python -m afm_ros.tools.report SESSION.mcap [--out DIR]`` (also ``afm_report``) writes into DIR
(default: ``<SESSION>_report`` next to the file):

- ``deflection_force.png``: deflection and tip-sample force vs simulated time (whole session as
  a min/max envelope, and the last few drive periods in full);
- ``lockin_z.png``: lock-in amplitude (with the setpoint in force, a step at every change, and the
  settling band), phase, z piezo and error vs simulated time (every sample while a series is short,
  a min/max envelope beyond). From the loop's batches (``lockin/outputs``: t, X, Y of every output,
  amplitude = hypot(X, Y), phase = atan2(-Y, X); ``z_controller/trace``: t, z, error) when they are
  recorded (complete, in time order, exact simulated times), else from the per-output copies
  (``lockin/amplitude`` ...), placed by their receive times;
- ``force_distance.png``: tip-sample force vs gap, reconstructed sample by sample: gap =
  z_offset (chunk preamble) + deflection, force from the tip_sample_force chunk with the same
  sample index (at most :data:`MAX_SCATTER_POINTS` exact pairs, evenly spaced in the sample index);
- ``images.png`` (imaging sessions): the last well-formed ``scanner/image/<channel>/<direction>``
  of each topic in display units, heights plane-levelled, colour range 2-98 % of the pixels (FM
  frames: the FM channels, df, drive, dissipation, ...);
- ``fm.png`` (FM-AFM sessions, ``pll/outputs`` recorded): df, drive, amplitude and phase error of
  every PLL output vs simulated time, and an FM section in report.md: mean and std per window
  (free, engaged before the scan, the scan) and the dissipation per cycle from the drive
  (:mod:`afm_ros.tools.report.fm`). With the z loop on df (``feedback_signal`` 'frequency_shift')
  there is no amplitude setpoint: the setpoint tracking is left out and the error is plotted in Hz;
- ``report.md``: file status, ERROR statuses recorded on /diagnostics (a blow-up with the
  parameters in force) at the top, topics, stream completeness, the setpoint-tracking numbers (free
  amplitude, settling after engaging, every setpoint change with its own settling time, the state
  at the end), the force-distance extremes (over all pairs), the images, what was skipped and why,
  every node's parameters at start and every change.

Setpoint history: the setpoint in force at every lock-in output is amplitude + error (the z trace's
error = setpoint - amplitude at the same output times): a change is placed at the exact simulated
time of the first output computed with it (its value from the matching /parameter_events change).
Without the batches the changes come from /parameter_events, placed by their receive time. The
settling after engaging ends at the first change (or the scan start); a change's settling is into
+-SETTLING_BAND of its own setpoint; the final state is the last 20 % of the last segment.

Memory does not grow with the session (peak RSS < :data:`PEAK_RSS_BOUND_MB` for one instrument's
recording of any length): the file is streamed twice and never held.

- Pass 1 (nothing but the chunk preambles, the batches and the small messages is parsed): topics,
  their types and counts, the /clock table (receive time -> simulated time), the sample-index
  continuity and time range of every chunk and batch stream, the setpoint at every output (paired
  batches, O(1) state), parameters and their changes, ERROR statuses, the header of every image
  message, first/last receive times of every series and a table of the sample times of each series.
- Between the passes: topic per role, the time mapping, engage time, setpoint segments and the
  averaging windows of the tracking numbers (e.g. the last 20 % of the last segment).
- Pass 2: the chunks one at a time and the series in batches feed fixed-size accumulators:
  min/max envelopes with :data:`ENVELOPE_BINS` bins over the time range known from pass 1, the
  last :data:`ZOOM_PERIODS` drive periods, running sums over the windows, an O(1) settling tracker
  per segment, the force-distance extremes over all pairs and an evenly spaced subset of them; the
  chosen image of each topic is decoded alone (at most :data:`DISPLAY_MAX_PIXELS` per side kept).

Tables hold at most :data:`TABLE_CAP` rows. Until then everything is exact (the numbers equal those
of the former in-memory report bit for bit). Beyond, the time map becomes a polyline within a
stated tolerance of the full one (:class:`TimeMapTable`), the series' sample-time tables keep every
k-th time (the start of the free-amplitude window may move by < k samples; the other windows'
bounds stay exact), and the setpoint-from-error median is taken over every k-th value.

Works on truncated and damaged files (reads the intact part, says so) and on files with only some
topics (figures and numbers whose inputs are missing are skipped with a note). A file from another
tool (a role's topic with another message type, a message that does not deserialise, a chunk or
batch not in the afm_ros layout) stops with :class:`ReportError`, one line naming the topic and the
problem. Images, the scan geometry and /diagnostics are never fatal: a malformed one is skipped
with a one-line reason (report.md and stderr) and the rest is reported.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from afm_ros.formats.mcap_io import SessionFileError
from afm_ros.tools.report import fm
from afm_ros.tools.report.accumulators import TABLE_CAP, TimeMapTable
from afm_ros.tools.report.cdr import IMAGE_ENCODING
from afm_ros.tools.report.collect import (
    MAX_SCATTER_POINTS,
    SETTLING_BAND,
    Collector,
    force_distance,
    setpoint_tracking,
    tracking_numbers,
)
from afm_ros.tools.report.figures import (
    write_bimodal_figure,
    write_figures,
    write_image_figure,
    write_spectroscopy_figure,
    write_tune_figure,
)
from afm_ros.tools.report.markdown import diagnostic_errors, write_markdown
from afm_ros.tools.report.plan import make_plan, pick_topics, series_from_batches
from afm_ros.tools.report.session import ReportError, SessionData, nth, shown_images
from afm_ros.tools.report.survey import (
    BATCH_ROLES,
    FM_ROLE,
    SCALAR_ROLES,
    check_bimodal,
    check_geometry,
    check_spectroscopy,
    check_tune,
    spectroscopy_numbers,
    survey_session,
)

__all__ = [
    "MAX_SCATTER_POINTS",
    "PEAK_RSS_BOUND_MB",
    "SETTLING_BAND",
    "TABLE_CAP",
    "Report",
    "ReportError",
    "SessionData",
    "TimeMapTable",
    "force_distance",
    "last_images",
    "load_session",
    "main",
    "make_report",
    "spectroscopy_numbers",
    "tracking_numbers",
]


# stated bound (see docs/recording.md, "Report"), checked by test_report_memory
PEAK_RSS_BOUND_MB = 300


def load_session(path) -> SessionData:
    """Read ``path`` twice (survey, then samples) into bounded summaries (see the module doc)."""
    path = Path(path)
    survey = survey_session(path)
    data = SessionData(path, survey.scan)
    pick_topics(survey.scan, survey.wrong, survey.counts, data)
    data.deflection = survey.chunks.get(data.topics.get("deflection"))
    data.force = survey.chunks.get(data.topics.get("force"))
    data.series = {
        role: survey.series[data.topics[role]]
        for role in ("amplitude", "phase", "xy", "z_piezo", "error", "clock")
        if role in data.topics and data.topics[role] in survey.series
    }
    series_from_batches(data, survey)
    data.diagnostics, data.images, data.skipped = (
        survey.diagnostics,
        survey.images,
        dict(survey.skipped),
    )
    check_geometry(survey, data)
    check_tune(survey, data)
    check_spectroscopy(survey, data)
    check_bimodal(survey, data)
    plan = data.plan = make_plan(data, survey.events)
    if FM_ROLE in data.topics:
        data.fm = fm.prepare(data, survey.batches.get(data.topics[FM_ROLE]), survey.stage)
    collector = Collector(data, plan)
    roles = [
        "deflection",
        "force",
        *(r for r in BATCH_ROLES if r in data.batches),
        *(r for r in ("xy", *SCALAR_ROLES) if r in data.series and data.series[r].batch is None),
        *([FM_ROLE] if data.fm is not None else []),
    ]
    collector.run(path, roles, survey.counts)
    data.passes = 2
    if (
        plan.setpoint is None
        and not data.fm_feedback
        and collector.median.seen
        and "amplitude" in data.series
    ):
        # no setpoint parameter recorded: the setpoint is rebuilt from the error, and the tracking
        # numbers that compare with it need the amplitude once more
        plan.setpoint = float(np.median(collector.median.arrays()[0]))
        plan.segments = [
            (plan.engage if plan.engage is not None else -math.inf, plan.setpoint, "engage")
        ]
        again = Collector(data, plan, tracking_only=True)
        again.run(
            path,
            ["outputs"] if data.series["amplitude"].batch is not None else ["xy", "amplitude"],
            survey.counts,
        )
        data.passes = 3
        collector.tail, collector.after_n, collector.settling, collector.ta0 = (
            again.tail,
            again.after_n,
            again.settling,
            again.ta0,
        )
        collector.seg_first, collector.tail_lo = again.seg_first, again.tail_lo
    if (
        data.fm_feedback
    ):  # no amplitude setpoint: the FM section reports the loop; engage and scan for the figures
        data.tracking = fm.markers(data.fm) if data.fm is not None else {}
    else:
        data.tracking = setpoint_tracking(data, plan, collector)
    if not plan.exact_bounds and "free_amplitude_m" in data.tracking:
        amp = data.series["amplitude"]
        stride = (amp.batch.times if amp.batch is not None else amp.times).stride
        data.notes.append(
            f"The free-amplitude window starts within {stride} amplitude samples of its "
            f"definition (the amplitude's sample times are kept for every {nth(stride)} sample)."
        )
    for it in data.images.values():
        if not it.last_good:
            data.skipped[it.topic] = (
                f"none of its {it.count} messages is a {IMAGE_ENCODING} image ({it.problem})"
            )
        elif it.problem:
            data.skipped[it.topic + f" (message {it.count})"] = (
                f"{it.problem}; the image of message {it.last_good} is shown"
            )
    return data


def last_images(path) -> tuple[dict, dict | None]:
    """The last recorded frame of an imaging session: {(channel, direction): float32 array} (the
    last well-formed ``scanner/image/<channel>/<direction>`` message of each topic; at full size up
    to DISPLAY_MAX_PIXELS per side) and the checked ``scanner/geometry`` or None."""
    data = load_session(path)
    return {(it.channel, it.direction): it.array for it in shown_images(data)}, data.geometry


@dataclass
class Report:
    """What :func:`make_report` wrote: report.md, the figures, the numbers (SI units) and the
    data."""

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
    if data.fm is not None:
        figures.append(fm.write_figure(data, out))
    image_figure = write_image_figure(data, out)
    if image_figure is not None:
        figures.append(image_figure)
    tune_figure = write_tune_figure(data, out)
    if tune_figure is not None:
        figures.append(tune_figure)
    spectroscopy_figure = write_spectroscopy_figure(data, out)
    if spectroscopy_figure is not None:
        figures.append(spectroscopy_figure)
    bimodal_figure = write_bimodal_figure(data, out)
    if bimodal_figure is not None:
        figures.append(bimodal_figure)
    md = write_markdown(data, figures, out)
    numbers = tracking_numbers(data)
    for role, stream in (("deflection", data.deflection), ("force", data.force)):
        if stream is not None:
            numbers[f"{role}_samples"] = stream.samples
            numbers[f"{role}_lost_samples"], numbers[f"{role}_gaps"] = stream.lost, stream.gaps
            numbers[f"{role}_non_finite"] = stream.non_finite
    for role, s in data.series.items():
        if role in SCALAR_ROLES:
            numbers[f"{role}_non_finite"] = s.non_finite
    if data.fd is not None:
        numbers.update(
            force_distance_pairs=data.fd.pairs, force_distance_kept=int(data.fd.gap.size)
        )
        if data.fd.pairs > data.fd.non_finite:
            numbers.update(
                min_gap_m=data.fd.min_gap,
                max_force_n=data.fd.max_force,
                min_force_n=data.fd.min_force,
            )
    for role, b in data.batches.items():
        numbers[f"{role}_outputs"] = b.outputs
        if role == "outputs":
            numbers["outputs_lost_input_samples"] = b.lost
    numbers["series_source"] = "batches" if data.batches else ("copies" if data.series else None)
    numbers["setpoint_history_from"] = data.setpoint_source or None
    numbers["errors"] = diagnostic_errors(data)
    numbers["images"] = {f"{it.channel}/{it.direction}": it.stats for it in shown_images(data)}
    numbers["skipped"] = dict(data.skipped)
    if data.tune is not None:
        numbers["tune"] = {k: v for k, v in data.tune.items() if not isinstance(v, np.ndarray)}
    if data.spectroscopy is not None:
        numbers["spectroscopy"] = spectroscopy_numbers(data.spectroscopy)
    if data.bimodal is not None:
        numbers["bimodal"] = data.bimodal
    if data.fm is not None:
        numbers["fm"] = fm.numbers(data.fm)
    return Report(md, figures, numbers, data)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="afm_report",
        description="Figures and a Markdown summary of a "
        "recorded AFM session (.mcap; truncated files are read up to the damage).",
    )
    parser.add_argument("session", help="the .mcap file")
    parser.add_argument(
        "--out", help="output directory (default: <session>_report next to the file)"
    )
    parser.add_argument(
        "--json", action="store_true", help="also print the report's numbers as one JSON line"
    )
    args = parser.parse_args(argv)
    try:
        report = make_report(args.session, args.out)
    except (ReportError, SessionFileError) as exc:
        print(
            f"afm_report: error: {args.session}: {exc}"
            if isinstance(exc, ReportError)
            else f"afm_report: error: {exc}",
            file=sys.stderr,
        )
        return 1
    except OSError as exc:
        print(f"afm_report: error: {exc}", file=sys.stderr)
        return 1
    if not report.data.scan.complete:
        print(
            f"afm_report: warning: {report.data.path} is incomplete "
            f"({report.data.scan.truncated_reason}); "
            "reported the intact part",
            file=sys.stderr,
        )
    for e in report.numbers["errors"]:
        print(
            f"afm_report: warning: the session reported an ERROR: {e['name']}: {e['message']}",
            file=sys.stderr,
        )
    for topic, why in sorted(report.data.skipped.items()):
        print(f"afm_report: note: skipped {topic}: {why}", file=sys.stderr)
    print(f"wrote {report.markdown} and {len(report.figures)} figures")
    if args.json:
        print(json.dumps(report.numbers))
    return 0
