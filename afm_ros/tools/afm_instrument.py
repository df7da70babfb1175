"""``afm_instrument``: the whole virtual tapping-mode AFM in one process, or the job against
running nodes.

Runs the ``cantilever``, ``lockin``, ``z_controller`` and ``recorder`` nodes on one executor (or,
with ``--attach``, drives nodes that already run as separate processes) and performs the main job,
stepping the simulation with the cantilever's ``run_until`` pause so every phase starts at a
defined simulated time:

1. the cantilever waits at t = 0 in lockstep with the z controller (``feedback_sync`` lockstep);
   the z controller is disabled and withdraws (z_piezo = z_max, tip far from the sample);
2. run ``--free-time`` and measure the free amplitude and phase from the lock-in (second half);
3. enable the feedback at the setpoint (the z_controller's ``setpoint`` [m], or
   ``--setpoint-ratio`` times the measured free amplitude);
4. run ``--duration`` simulated seconds and print a summary (free amplitude and phase, setpoint,
   reached amplitude, phase in contact, z piezo, settling time, lost samples, recording).

With the same parameters the job gives the same session sample for sample (z piezo stream,
lock-in outputs, summary numbers except wall time and real-time factor), whatever the load, the
executor, the real-time factor and the process layout. ``--interactive`` engages and then keeps
running until Ctrl-C (for ``ros2 param set``). All times are *simulated* seconds; the cantilever's
``real_time_factor`` sets how fast they pass. ``--ros-args`` (``-p``, ``--params-file``, ``-r``)
apply to every node in the process (a ``-p`` is offered to every node; only the node that
declares the name uses it).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import warnings
from dataclasses import asdict
from pathlib import Path

import rclpy
from rclpy.executors import ExternalShutdownException
from rclpy.logging import LoggingSeverity, set_logger_level
from rclpy.utilities import remove_ros_args

from afm_ros.client import LongWork, Microscope
from afm_ros.client.nanonis import serve, supported
from afm_ros.core.approach import INSTRUMENT_Z
from afm_ros.core.artefacts import (
    ARTEFACT_NODE_SPECS,
    ARTEFACT_SPECS,
    IDEAL_ARTEFACTS,
    Imperfections,
)
from afm_ros.core.scanner import ScanPlan
from afm_ros.core.tip import IDEAL_TIP, TIP_NODE_SPECS, TIP_SPECS, TipWear
from afm_ros.formats.mcap_io import default_output_path
from afm_ros.nodes import node_main, topics
from afm_ros.tools import bimodal_session
from afm_ros.tools.fm_session import (
    FM_CANTILEVER,
    FM_RAW_EXCLUDE,
    FM_SCAN,
    FM_Z,
    run_fm_job,
    summary_text,
)
from afm_ros.tools.instrument_job import InstrumentJob
from afm_ros.tools.instrument_summary import recording_line
from afm_ros.tools.run_setup import RUNS_DIR, RosArgs, make_run_folder

ROLES = ("cantilever", "lockin", "z_controller")
# [s] at most for the tune (~1 s), an approach from 5 um (~4 s), the withdraw
WORKFLOW_SIMULATED_S = 8.0
# the default sample: topography (islands) and phase contrast (PS vs LDPE)
IMAGE_SAMPLE = "ps_ldpe_blend"
# the default frame (each can be set with -p scanner:<name>:=...): 64 x 64 pixels over 5 um at 2
# lines/s, 32 s simulated, about a minute on 2 cores with recording
IMAGE_SCAN = {"pixels_per_line": 64, "lines": 64, "line_rate": 2.0}
# the job records the loop's batches (lockin/outputs, z_controller/trace and z_command hold every
# lock-in output, z and error), the images and the state topics, but not the raw 900 kS/s streams
# nor the per-output scalar copies of the batches (unless --record-raw): a session a person can
# leave on
RAW_EXCLUDE = ",".join(
    (
        topics.DEFLECTION,
        topics.FORCE,
        "lockin/amplitude",
        "lockin/phase",
        "lockin/xy",
        "z_controller/z_piezo",
        "z_controller/error",
    )
)
IMAGE_FORCE_MODEL = "viscoelastic_dmt"  # PS and LDPE differ in dissipation, hence in phase
INTERRUPTED_STATUS = 130  # the shell's convention for a job ended by Ctrl-C (128 + SIGINT)


def parse_args(argv):
    parser = argparse.ArgumentParser(
        prog="afm_instrument",
        description=__doc__.split("\n\n")[0],
        epilog="ROS arguments follow --ros-args, e.g. --ros-args --params-file config/afm.yaml. "
        "--bimodal: a bimodal AM-FM or AM-AM frame, offline (afm_instrument --bimodal --help)",
    )
    parser.add_argument(
        "--duration",
        type=float,
        default=0.5,
        help="simulated seconds from engaging to the end of the hold (default 0.5)",
    )
    parser.add_argument(
        "--free-time",
        type=float,
        default=0.03,
        help="simulated seconds withdrawn before measuring the free amplitude (default 0.03)",
    )
    parser.add_argument(
        "--setpoint-ratio",
        type=float,
        default=None,
        help="setpoint as a fraction of the measured free amplitude (default: the "
        "z_controller's setpoint parameter [m])",
    )
    parser.add_argument(
        "--band",
        type=float,
        default=0.01,
        help="settling band as a fraction of the setpoint (default 0.01)",
    )
    parser.add_argument(
        "--executor",
        choices=["single", "multi", "events"],
        default="events",
        help="executor for all nodes (default events: fastest and fair, see docs/cantilever.md)",
    )
    parser.add_argument(
        "--no-record",
        action="store_true",
        help="do not record the session (default: afm_session_<date-time>.mcap in the run "
        "folder, see docs/recording.md; -p recorder:output:=FILE chooses the file)",
    )
    parser.add_argument(
        "--out",
        metavar="DIR",
        default=None,
        help="folder for this run's session and frames (default: a new "
        "afm_runs/<date>_<time>[_<namespace>] in the working directory)",
    )
    parser.add_argument(
        "--verbose",
        action="store_true",
        help="also show the nodes' INFO log lines (default: warnings and errors only; the job "
        "prints its own progress)",
    )
    parser.add_argument(
        "--attach",
        action="store_true",
        help="create no nodes: run the job against cantilever, lockin and z_controller nodes "
        "already running (e.g. as ros2 run processes) in this process's namespace",
    )
    parser.add_argument(
        "--interactive",
        action="store_true",
        help="after engaging, keep running until Ctrl-C (tune it from another terminal with "
        "afm_ctl, or ros2 param set with ROS 2), then print the summary",
    )
    parser.add_argument(
        "--ideal",
        action="store_true",
        help="an ideal instrument: no drift, creep, hysteresis, tilt, tip wear or pick-up (the "
        "nodes' "
        "defaults are a real instrument's), and --image without the operating workflow: the tip "
        "starts engaged at z_base (no tune, approach or withdraw)",
    )
    parser.add_argument(
        "--image",
        action="store_true",
        help="the imaging job: engage for --duration, then scan one frame with the scanner's "
        "parameters (-p scanner:...) over the cantilever's sample (default ps_ldpe_blend), "
        "write .gwy + PNG previews, record the session and print the frame's numbers; "
        "Ctrl-C finishes the current line and keeps the lines done as a partial frame",
    )
    parser.add_argument(
        "--record-raw",
        action="store_true",
        help="also record the raw 900 kS/s cantilever/deflection and cantilever/tip_sample_force "
        "streams and the per-output scalar topics (about 14 MB per simulated second with the "
        "default noise; default: the loop's batches, images, parameters and diagnostics only)",
    )
    parser.add_argument(
        "--live-view",
        action="store_true",
        help="also serve the instrument to Foxglove over WebSocket (the live_view node, "
        "ws://127.0.0.1:8765 by default, -p live_view:port:=...; docs/live_view.md); "
        "the scanner node runs too, so scans can be started from Foxglove",
    )
    parser.add_argument(
        "--fm",
        action="store_true",
        help="the frequency-modulation (non-contact) session: the pll node self-excites a Q 1e4 "
        "cantilever at a constant amplitude, the z loop regulates on the frequency shift; lock "
        "free, centre the PLL, approach on df, hold --duration, scan a frame of the cut PS/LDPE "
        "blend, print df, drive, dissipation and their contrast by material (docs/fm.md); with "
        "--interactive: after the hold, run until Ctrl-C (scan with afm_ctl)",
    )
    parser.add_argument(
        "--nanonis",
        action="store_true",
        help="serve the instrument over the Nanonis TCP programming interface (127.0.0.1:6501 by "
        "default, --nanonis-port, --nanonis-address) instead of running a job: lab scripts "
        "written for a Nanonis-controlled AFM tune, approach, scan and take spectra; frames saved "
        "as .sxm, spectra as .dat in the run folder, until Ctrl-C (docs/nanonis.md); with --fm "
        "the FM instrument",
    )
    parser.add_argument(
        "--nanonis-port", type=int, default=6501, help="with --nanonis: TCP port (default 6501)"
    )
    parser.add_argument(
        "--nanonis-address",
        default="127.0.0.1",
        help="with --nanonis: address to listen on (default 127.0.0.1: the protocol has no "
        "authentication)",
    )
    parser.add_argument(
        "--json", action="store_true", help="also print the summary as one JSON line"
    )
    args = parser.parse_args(argv)
    if args.fm and (args.attach or args.image):
        parser.error("--fm is a job of its own: not with --attach or --image")
    if args.nanonis and (args.attach or args.image or args.interactive or args.ideal):
        parser.error(
            "--nanonis serves the instrument to a Nanonis client: not with --attach, --image, "
            "--interactive or --ideal"
        )
    if not 0 <= args.nanonis_port <= 65535:
        parser.error(f"--nanonis-port={args.nanonis_port}: allowed 0-65535 (0: any free port)")
    for name in ("duration", "free_time"):
        if not (getattr(args, name) > 0 and math.isfinite(getattr(args, name))):
            parser.error(f"--{name.replace('_', '-')}={getattr(args, name)} s must be > 0")
    if args.setpoint_ratio is not None and not (0 < args.setpoint_ratio < 1):
        parser.error(f"--setpoint-ratio={args.setpoint_ratio} must be in (0, 1)")
    if not (0 < args.band < 1):
        parser.error(f"--band={args.band} must be in (0, 1)")
    return args


def _node_log_level(names, namespace: str, level) -> None:
    """Set the loggers of the instrument's nodes (created later) to ``level``."""
    prefix = namespace.strip("/").replace("/", ".")
    for name in names:
        set_logger_level(f"{prefix}.{name}" if prefix else name, level)


def _overrides(options, ros: RosArgs, run_folder: Path | None) -> tuple[dict, list[str]]:
    """Parameter values the job gives its nodes by role (never one the user set; under a namespace
    the user's -p node:name values, which rcl applies only in the root namespace), and the lines
    that say so."""
    given = {role: ros.node_rules(role) for role in (*ROLES, "scanner", "recorder", "live_view")}
    cantilever, recorder, scanner = given["cantilever"], given["recorder"], given["scanner"]
    notes = []
    if options.fm:
        for role, defaults in (
            ("cantilever", FM_CANTILEVER),
            ("scanner", FM_SCAN),
            ("z_controller", {**INSTRUMENT_Z, **FM_Z}),
        ):
            given[role].update({k: v for k, v in defaults.items() if not ros.given(role, k)})
        if not options.ideal:  # the user compensated the tilt they measured (docs/fm.md)
            for axis in ("x", "y"):
                if not ros.given("scanner", f"slope_compensation_{axis}"):
                    scanner[f"slope_compensation_{axis}"] = scanner.get(
                        f"tilt_{axis}",
                        ros.value(
                            "scanner", f"tilt_{axis}", ARTEFACT_NODE_SPECS[f"tilt_{axis}"].default
                        ),
                    )
        c = {k: cantilever.get(k, ros.value("cantilever", k, v)) for k, v in FM_CANTILEVER.items()}
        f = {k: scanner.get(k, ros.value("scanner", k, v)) for k, v in FM_SCAN.items()}
        c, f = ({k: f"{v:g}" if isinstance(v, float) else v for k, v in d.items()} for d in (c, f))
        notes.append(
            f"FM-AFM: excitation {c['excitation']} (the pll node), Q {c['quality_factor']}, "
            "chunks of "
            f"{c['chunk_duration']} s, sample {c['sample']}, force_model {c['force_model']} "
            "(non-contact "
            f"dissipation: adhesion hysteresis); z loop on df; {f['pixels_per_line']} x "
            f"{f['lines']} "
            f"pixels at {f['line_rate']} lines/s (-p <node>:<name>:=... change them)"
        )
    if (
        not options.fm and not options.attach
    ):  # every tapping mode: the blend, its frame, a real session
        scanner.update({k: v for k, v in IMAGE_SCAN.items() if not ros.given("scanner", k)})
        switched = []
        if not ros.given("cantilever", "sample"):
            cantilever["sample"] = IMAGE_SAMPLE
            switched.append(f"sample {IMAGE_SAMPLE}")
        if not ros.given("cantilever", "force_model"):
            cantilever["force_model"] = IMAGE_FORCE_MODEL
            switched.append(
                f"force_model {IMAGE_FORCE_MODEL} (not the parameter's default dmt: the PS/LDPE "
                "phase "
                "contrast comes from dissipation)"
            )
        if (
            not options.ideal
        ):  # a real session: far from the sample with a z piezo of a few um, tune, approach
            given["z_controller"].update(
                {k: v for k, v in INSTRUMENT_Z.items() if not ros.given("z_controller", k)}
            )
        plan = {k: scanner.get(k, ros.value("scanner", k, v)) for k, v in IMAGE_SCAN.items()}
        rate = plan["line_rate"]
        rate = (
            f"{rate:g}" if isinstance(rate, (int, float)) else rate
        )  # (a bad value: the scanner says why)
        notes.append(
            "imaging: "
            + ", ".join(
                switched
                + [f"{plan['pixels_per_line']} x {plan['lines']} pixels at {rate} lines/s"]
            )
            + " (-p cantilever:<name>:=... and -p scanner:<name>:=... change them)"
        )
    # the nodes' defaults are a real instrument's scanner, sample mount and tip; --ideal: none of
    # it
    for role, ideal in (("scanner", IDEAL_ARTEFACTS), ("cantilever", IDEAL_TIP)):
        if options.ideal:
            given[role].update({k: v for k, v in ideal.items() if not ros.given(role, k)})
    if not options.attach:
        notes.append(
            imperfections_line(
                {
                    **{
                        k: ros.value("scanner", k, spec.default)
                        for k, spec in ARTEFACT_NODE_SPECS.items()
                    },
                    **scanner,
                },
                {
                    **{
                        k: ros.value("cantilever", k, spec.default)
                        for k, spec in TIP_NODE_SPECS.items()
                    },
                    **cantilever,
                },
            )
        )
    if run_folder is not None:
        # '' (the parameters' own default, e.g. from a dumped config) means: the run folder
        if not ros.value("recorder", "output"):
            recorder["output"] = str(
                default_output_path(directory=run_folder, namespace=ros.namespace or "/")
            )
        if not ros.value("scanner", "output_directory"):
            scanner["output_directory"] = str(run_folder)
    if (
        not options.record_raw
        and not ros.value("recorder", "exclude")
        and not ros.value("recorder", "topics")
    ):
        recorder["exclude"] = RAW_EXCLUDE
        if options.fm:
            recorder["exclude"] = ",".join((RAW_EXCLUDE, *FM_RAW_EXCLUDE))
    return given, notes


def imperfections_line(scanner: dict, cantilever: dict) -> str:
    """The start line that says which imperfections the session has (values the user gave
    included)."""

    def num(values, name, scale=1.0):
        value = values.get(name)
        return (
            f"{value * scale:.3g}"
            if isinstance(value, (int, float)) and not isinstance(value, bool)
            else repr(value)
        )

    try:
        ideal = (
            not Imperfections({k: v for k, v in scanner.items() if k in ARTEFACT_SPECS}).enabled
            and not TipWear(1e-8, {k: v for k, v in cantilever.items() if k in TIP_SPECS}).enabled
        )
    except (ValueError, TypeError):
        ideal = False  # a bad value: the node says why
    if ideal:
        return "imperfections: none (an ideal scanner, sample mount and tip)"
    loop = (
        "closed-loop scanner (no hysteresis, no creep)"
        if scanner.get("closed_loop") is True
        else "hysteresis "
        f"{num(scanner, 'hysteresis_small', 100)}-{num(scanner, 'hysteresis_large', 100)} % "
        "of the "
        f"scan, creep {num(scanner, 'creep_per_decade', 100)} %/decade"
    )
    return (
        f"imperfections: drift {num(scanner, 'drift_lateral_rate', 6e10)} nm/min lateral, "
        f"{num(scanner, 'drift_vertical_rate', 6e10)} nm/min vertical, tilt "
        f"{num(scanner, 'tilt_x')} x "
        f"{num(scanner, 'tilt_y')} y, {loop}; tip wear {num(cantilever, 'tip_wear_coefficient')} "
        "m/N, pick-ups "
        f"{num(cantilever, 'tip_pickup_rate')} /s (docs/imperfections.md; --ideal: none)"
    )


def main(args=None):
    argv = sys.argv if args is None else args
    if "--bimodal" in argv[1:]:  # a session of its own, offline: no node, no ROS argument
        return bimodal_session.main(argv[1:])
    try:
        plain = remove_ros_args(argv)
    except (
        Exception
    ) as exc:  # rclpy's RCLInvalidROSArgsError, e.g. a params file that cannot be read
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        print(f"afm_instrument: invalid --ros-args: {first}", file=sys.stderr)
        return 2
    options = parse_args(plain[1:])
    ros = RosArgs.parse(argv)
    failed = node_main.exit_on_startup_error("afm_instrument", argv)
    if failed is not None:
        return failed
    afm = instrument = job = None
    status = 0
    refused = False  # by the checks before the job: the run folder made for it goes again
    run_folder = None
    try:
        record = not (options.no_record or options.attach)
        scanner = (
            not options.attach
        )  # every mode has one: afm_ctl scan frame from a second terminal
        if (record or scanner) and not options.attach:
            try:
                run_folder = make_run_folder(options.out, ros.namespace)
            except OSError as exc:
                raise ValueError(f"--out: cannot create the run folder: {exc}") from None
        overrides, notes = _overrides(options, ros, run_folder)
        # the operating workflow (tune, approach, withdraw) runs from a withdrawn start: not
        # --ideal, not attached, and not when the user started the z stage engaged (-p
        # z_controller:start_withdrawn:=false)
        workflow = (
            not options.ideal
            and not options.attach
            and overrides.get("z_controller", {}).get(
                "start_withdrawn", ros.value("z_controller", "start_withdrawn", False)
            )
            is True
        )
        if not workflow and not options.ideal and not options.attach and not options.fm:
            notes.append(
                "workflow: none (the z stage starts engaged at z_base: start_withdrawn is false)"
            )
        if (
            not options.verbose and ros.log_level is None
        ):  # the job says what matters; node INFO lines with --verbose
            _node_log_level(
                (
                    *ROLES,
                    "pll",
                    "scanner",
                    "recorder",
                    "live_view",
                    "afm_instrument_monitor",
                    "afm_instrument_fm_monitor",
                ),
                ros.namespace,
                LoggingSeverity.WARN,
            )
        afm = Microscope.in_process(
            executor=options.executor,
            record=record,
            attach=options.attach,
            namespace=None,
            scanner=scanner,
            overrides=overrides,
            live_view=options.live_view,
            pll=options.fm,
        )
        instrument = afm.session
        job = InstrumentJob(afm)
        # the job says itself how long it takes (say_long_job): not the client's LongWork warnings
        warnings.simplefilter("ignore", LongWork)
        job.run_folder = str(run_folder) if run_folder is not None else ""
        if run_folder is not None:
            print(f"run folder: {run_folder}", flush=True)
        for note in notes:
            print(note, flush=True)
        if "live_view" in instrument.nodes:
            live = instrument.nodes["live_view"]
            print(
                f"live view: ws://{live.get_parameter('address').value}:{live.port} (Foxglove, "
                "subprotocol "
                f"foxglove.sdk.v1; no authentication)",
                flush=True,
            )
        if "recorder" in instrument.nodes:
            print(recording_line(instrument.nodes["recorder"], options.record_raw), flush=True)
        try:  # what the job needs, checked before it starts
            frame_time, frame = 0.0, None
            if options.image or options.fm:
                instrument.check_scan()
                plan = ScanPlan.from_values(instrument.nodes["scanner"].values)
                frame_time, frame = plan.frame_time, (plan.pixels, plan.lines)
            if not options.interactive and not options.nanonis:  # a bounded job: it must fit
                workflow_s = WORKFLOW_SIMULATED_S if workflow or options.fm else 0.0
                job.check_recording(
                    options.free_time + options.duration + frame_time + workflow_s,
                    options.record_raw,
                    frame,
                )
                say_long_job(
                    options.free_time + options.duration + frame_time + workflow_s,
                    ros.value("cantilever", "real_time_factor", 1.0),
                )
        except ValueError:
            refused = True
            raise
        if options.nanonis:
            return serve_nanonis(afm, run_folder, options)
        if options.fm:
            fm_summary = run_fm_job(job, options.duration, interactive=options.interactive)
            print(summary_text(fm_summary), flush=True)
            if options.json:
                print(json.dumps(fm_summary, default=float), flush=True)
            if fm_summary["interrupted"]:
                status = INTERRUPTED_STATUS
            elif fm_summary["recording"] and not fm_summary["recording"]["complete"]:
                print("afm_instrument: the recording is incomplete", file=sys.stderr)
                status = 1
            return status
        if options.image:
            summary = job.run_image_job(
                options.duration,
                options.free_time,
                options.setpoint_ratio,
                options.band,
                workflow=workflow,
            )
        else:
            summary = job.run_job(
                options.duration,
                options.free_time,
                options.setpoint_ratio,
                options.band,
                interactive=options.interactive,
                workflow=workflow,
                withdraw=True,
            )
        print(summary.text(), flush=True)
        if options.json:
            print(json.dumps(asdict(summary)), flush=True)
        if summary.interrupted:
            status = INTERRUPTED_STATUS
        elif summary.recording and not summary.recording["complete"]:
            print("afm_instrument: the recording is incomplete", file=sys.stderr)
            status = 1
    except (KeyboardInterrupt, ExternalShutdownException):
        status = INTERRUPTED_STATUS
        state = job.job if job is not None else None
        if state is not None:
            # --interactive ends with Ctrl-C once running; before (the tune, the approach) it was
            # interrupted
            ended = options.interactive and state.phase == "running"
            status = 0 if ended else INTERRUPTED_STATUS
            summary = job.summary(interrupted="" if ended else job.interruption())
            print(summary.text(), flush=True)
            if options.json:
                print(json.dumps(asdict(summary)), flush=True)
        elif not (options.fm and options.interactive and instrument is not None):
            print("afm_instrument: interrupted while starting", file=sys.stderr)
        else:
            status = 0  # --fm --interactive ends with Ctrl-C
    except (
        ValueError,
        TimeoutError,
        RuntimeError,
        OSError,
    ) as exc:  # RecordingError is a RuntimeError
        print(f"afm_instrument: {exc}", file=sys.stderr)
        status = 1
        refused = (
            refused or instrument is None
        )  # a bad start value: the run folder made for it goes again
    finally:

        def teardown():
            if afm is not None:
                afm.close()
            rclpy.try_shutdown()

        node_main.teardown_within(teardown, "afm_instrument", status)
        if refused and run_folder is not None and options.out is None:
            _remove_unused_run_folder(run_folder)
    return status


def serve_nanonis(afm: Microscope, run_folder: Path, options) -> int:
    """The instrument behind a Nanonis server until Ctrl-C (then the frame being scanned is saved
    as far as it got); the exit status."""
    instrument = afm.session
    instrument.wait_ready()
    instrument.start_far()
    instrument.finishing = True  # Ctrl-C ends the server, which stops its own work first
    served = serve(
        afm,
        run_folder,
        mode="fm" if options.fm else "am",
        address=options.nanonis_address,
        port=options.nanonis_port,
        log=nanonis_log,
    )
    print(
        f"Nanonis server on {options.nanonis_address}:{served.port} ({len(supported())} "
        f"commands, {'FM' if options.fm else 'AM'}; no authentication): point a Nanonis script "
        "at it; Ctrl-C stops",
        flush=True,
    )
    try:
        while node_main.running(instrument.context) and not served.session.controller.failure:
            time.sleep(0.2)
    finally:
        try:
            served.close()
        except KeyboardInterrupt:
            print("afm_instrument: Ctrl-C again: stopped without waiting", file=sys.stderr)
    failure = served.session.controller.failure
    print(
        f"nanonis: {len(served.session.files)} file(s) in {run_folder}"
        + (f"; the instrument stopped: {failure}" if failure else ""),
        flush=True,
    )
    return 1 if failure else 0


def nanonis_log(level: str, text: str) -> None:
    """The server's lines worth printing: files saved, warnings and errors."""
    if level != "info" or text.startswith(("frame saved", "spectroscopy saved")):
        print(text if level == "info" else f"nanonis [{level}]: {text}", flush=True)


def say_long_job(simulated_s: float, real_time_factor) -> None:
    """A bounded job of more than a minute says how long it takes, before it starts."""
    try:
        rate = float(real_time_factor)
    except (TypeError, ValueError):
        return  # a bad value: the cantilever says why
    if rate > 0 and simulated_s / rate > 60.0:
        print(
            f"job: {simulated_s:.4g} s simulated: about {simulated_s / rate / 3600:.3g} h at the "
            "cantilever's "
            f"real_time_factor {rate:g} (Ctrl-C ends it with the summary of what was done)",
            flush=True,
        )
    elif rate == 0 and simulated_s > 60.0:
        print(
            f"job: {simulated_s:.4g} s simulated as fast as this machine goes (about 0.5-2 s of "
            "wall time per "
            f"simulated second on 2 cores; Ctrl-C ends it with the summary of what was done)",
            flush=True,
        )


def _remove_unused_run_folder(folder: Path) -> None:
    """A run refused before its job started leaves nothing: its new folder holds only the session
    file the recorder opened (no data yet)."""
    files = list(folder.iterdir())
    if all(f.name.startswith("afm_session_") and f.suffix == ".mcap" for f in files):
        for f in files:
            f.unlink()
        folder.rmdir()
        if folder.parent.name == RUNS_DIR and not any(folder.parent.iterdir()):
            folder.parent.rmdir()


if __name__ == "__main__":
    sys.exit(main())
