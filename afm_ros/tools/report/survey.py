"""Pass 1: one read of the file for the chunk preambles, batches and small messages (no sample
array), and the checks of the last geometry, tune and spectroscopy messages."""

from __future__ import annotations

import json
import math
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from afm_ros.core.spectroscopy import expected_lag
from afm_ros.formats.chunk_layout import (
    ChunkLayoutError,
    cdr_byte_order,
    cdr_chunk,
    cdr_clock_seconds,
    cdr_float64_array,
)
from afm_ros.formats.mcap_io import SessionScan, read_session
from afm_ros.formats.spectroscopy_layout import unpack_curve
from afm_ros.tools.report.accumulators import StrideTable, TimeMapTable
from afm_ros.tools.report.cdr import (
    LAYOUT_NAMES,
    amplitude_phase,
    cdr_batch,
    cdr_float64,
    cdr_fm_batch,
    cdr_image,
    cdr_vector3_stamped,
    decode_image,
)
from afm_ros.tools.report.session import (
    BatchStream,
    ChunkStream,
    DiagnosticErrors,
    ImageTopic,
    ReportError,
    Series,
    SessionData,
    SetpointFromData,
    bad_message,
)

ROLES = {
    "deflection": "cantilever/deflection",
    "force": "cantilever/tip_sample_force",
    "amplitude": "lockin/amplitude",
    "phase": "lockin/phase",
    "xy": "lockin/xy",
    "z_piezo": "z_controller/z_piezo",
    "error": "z_controller/error",
    "outputs": "lockin/outputs",  # the batches: every lock-in output (t, X, Y) of one input chunk
    # every z controller output (t, z piezo, error) of one lock-in batch
    "z_trace": "z_controller/trace",
    # FM-AFM: every PLL output (t, df, drive, phase error, amplitude) of one batch
    "fm_outputs": "pll/outputs",
    "clock": "clock",  # /clock, or /<ns>/clock of an instrument in a namespace
    "parameter_events": "/parameter_events",
}
EXPECTED_TYPES = {
    "deflection": "std_msgs/msg/Float64MultiArray",
    "force": "std_msgs/msg/Float64MultiArray",
    "amplitude": "std_msgs/msg/Float64",
    "phase": "std_msgs/msg/Float64",
    "z_piezo": "std_msgs/msg/Float64",
    "error": "std_msgs/msg/Float64",
    "xy": "geometry_msgs/msg/Vector3Stamped",
    "outputs": "std_msgs/msg/Float64MultiArray",
    "z_trace": "std_msgs/msg/Float64MultiArray",
    "fm_outputs": "std_msgs/msg/Float64MultiArray",
    "clock": "rosgraph_msgs/msg/Clock",
    "parameter_events": "rcl_interfaces/msg/ParameterEvent",
}
CHUNK_ROLES = ("deflection", "force")
SCALAR_ROLES = ("amplitude", "phase", "z_piezo", "error")
BATCH_ROLES = {
    "outputs": ("amplitude", "phase"),
    "z_trace": ("z_piezo", "error"),
}  # batch -> series it holds
FM_ROLE = "fm_outputs"  # pll/outputs: read by fm.py
IMAGE_TOPIC = "/scanner/image/"
IMAGE_TYPE = "sensor_msgs/msg/Image"
GEOMETRY_TOPIC = "/scanner/geometry"
TUNE_TOPIC = "/lockin/tune_result"
SPECTROSCOPY_TOPIC = "/z_controller/spectroscopy"
STAGE_TOPIC = "/z_controller/stage"
BIMODAL_TOPIC = "/bimodal/materials"  # the bimodal node's per-material table (JSON)
BIMODAL_IMAGE_TOPIC = "/bimodal/image/"  # its channels (sensor_msgs/Image 64FC1)
BIMODAL_PROGRESS_TOPIC = "/bimodal/progress"  # its frame: corner, side, mode 2's control
BIMODAL_FIELDS = ("material", "pixels", "modulus", "true_modulus", "bias", "frequency_shift_2",
                  "indentation", "height", "loss_tangent_2", "true_loss_tangent_2")  # fmt: skip
EXTRA_ROLES = (
    "image",
    "geometry",
    "tune",
    "spectroscopy",
    "diagnostics",
    "stage",
    "bimodal",
    "bimodal_image",
    "bimodal_progress",
)  # read when present and well-formed, skipped with a note if not


def role_of(topic: str) -> str | None:
    """The role (a key of ROLES) of a topic, by its name, or None."""
    for role, suffix in ROLES.items():
        if topic == suffix if suffix.startswith("/") else topic.endswith("/" + suffix):
            return role
    return None


def _extra_role(topic: str, type_name: str) -> str | None:
    if IMAGE_TOPIC in topic:
        return "image"
    if topic.endswith(GEOMETRY_TOPIC):
        return "geometry"
    if topic.endswith(TUNE_TOPIC):
        return "tune"
    if topic.endswith(SPECTROSCOPY_TOPIC):
        return "spectroscopy"
    if topic.endswith(STAGE_TOPIC):
        return "stage"
    if topic.endswith(BIMODAL_TOPIC):
        return "bimodal"
    if BIMODAL_IMAGE_TOPIC in topic:
        return "bimodal_image"
    if topic.endswith(BIMODAL_PROGRESS_TOPIC):
        return "bimodal_progress"
    if topic == "/diagnostics" or topic.endswith("/diagnostics"):
        return "diagnostics"
    return None


def stage_times(raw, stage: dict) -> None:
    """Keep the approach start and engage time [s] of a ``z_controller/stage`` message
    (std_msgs/String, JSON) in ``stage``; a message that is not such JSON is ignored (never
    fatal)."""
    try:
        order = cdr_byte_order(raw)
        n = struct.unpack_from(order + "I", raw, 4)[0]
        g = (
            json.loads(bytes(raw[8 : 8 + n - 1]).decode("utf-8"))
            if 0 < n and 8 + n <= len(raw)
            else None
        )
    except (ValueError, struct.error):
        return
    if not isinstance(g, dict):
        return
    for key in ("approach_started_s", "engaged_s"):
        v = g.get(key)
        if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v):
            stage[key] = float(v)


def _survey_extra(survey: "Survey", role: str, m, k: int) -> None:
    """Images, scan geometry and diagnostics: never fatal; what cannot be read is skipped with a
    reason."""
    if m.topic in survey.skipped:
        return
    if role == "image":
        it = survey.images.get(m.topic)
        if it is None:
            it = _image_topic(m.topic, m.type_name, survey)
            if it is None:
                return
            survey.images[m.topic] = it
        it.count = k
        try:
            height, width, *_ = cdr_image(m.data)
        except ValueError as exc:
            it.problem = f"message {k}: {exc}"
            return
        it.last_good, it.shape, it.problem = k, (height, width), ""
    elif role == "bimodal_image":  # the last one of each channel (a frame is a few kB)
        if m.type_name != IMAGE_TYPE:
            survey.skipped[m.topic] = f"type {m.type_name or '(no schema)'}, not {IMAGE_TYPE}"
            return
        survey.bimodal_images[m.topic.split(BIMODAL_IMAGE_TOPIC, 1)[1]] = (
            m.topic,
            k,
            bytes(m.data),
        )
    elif role in ("geometry", "tune", "bimodal", "bimodal_progress"):
        if m.type_name != "std_msgs/msg/String":
            survey.skipped[m.topic] = (
                f"type {m.type_name or '(no schema)'}, not std_msgs/msg/String"
            )
            return
        setattr(survey, role, (m.topic, k, bytes(m.data)))
    elif role == "stage":  # only its times are read (the FM windows); anything else is ignored
        if m.type_name == "std_msgs/msg/String":
            stage_times(m.data, survey.stage)
    elif role == "spectroscopy":
        if m.type_name != "std_msgs/msg/Float64MultiArray":
            survey.skipped[m.topic] = (
                f"type {m.type_name or '(no schema)'}, not std_msgs/msg/Float64MultiArray"
            )
            return
        survey.spectroscopy = (m.topic, k, bytes(m.data))
    else:
        if m.type_name != "diagnostic_msgs/msg/DiagnosticArray":
            survey.skipped[m.topic] = (
                f"type {m.type_name or '(no schema)'}, not diagnostic_msgs/msg/DiagnosticArray"
            )
            return
        from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus  # noqa: PLC0415 - ROS only for the messages that need it
        from rclpy.serialization import deserialize_message  # noqa: PLC0415 - ROS only for the messages that need it

        try:
            msg = deserialize_message(m.data, DiagnosticArray)
        except Exception:  # noqa: BLE001 - a damaged status message: counted, never fatal
            survey.diagnostics.unreadable += 1
            return
        for status in msg.status:
            if status.level == DiagnosticStatus.ERROR:
                survey.diagnostics.add(
                    m.log_time,
                    status.name,
                    status.message,
                    {kv.key: kv.value for kv in status.values},
                )


@dataclass
class Survey:
    """What pass 1 found."""

    scan: SessionScan
    chunks: dict = field(default_factory=dict)  # topic -> ChunkStream
    series: dict = field(default_factory=dict)  # topic -> Series
    batches: dict = field(default_factory=dict)  # topic -> BatchStream
    wrong: dict = field(default_factory=dict)  # role -> {topic: type}
    events: list = field(default_factory=list)  # (log_time, ParameterEvent)
    counts: dict = field(default_factory=dict)  # topic -> messages of a role's topic
    setpoints: dict = field(default_factory=dict)  # namespace prefix -> SetpointFromData
    diagnostics: DiagnosticErrors = field(default_factory=DiagnosticErrors)
    images: dict = field(default_factory=dict)  # topic -> ImageTopic
    geometry: tuple | None = (
        None  # (topic, message number, CDR bytes) of the last scanner/geometry
    )
    tune: tuple | None = None  # the same for the last lockin/tune_result
    bimodal: tuple | None = None  # the same for the last bimodal/materials
    bimodal_progress: tuple | None = None  # the same for the last bimodal/progress
    bimodal_images: dict = field(default_factory=dict)  # channel -> the same, its last image
    spectroscopy: tuple | None = None  # the same for the last z_controller/spectroscopy
    stage: dict = field(
        default_factory=dict
    )  # the last approach start and engage time [s] on z_controller/stage
    skipped: dict = field(default_factory=dict)  # topic -> why it is left out (one line)


def _image_topic(topic: str, type_name: str, survey: Survey) -> ImageTopic | None:
    """The ImageTopic of a scanner/image/<channel>/<direction> topic, or None (and why, in
    ``skipped``)."""
    parts = topic.split(IMAGE_TOPIC, 1)[1].split("/")
    if len(parts) != 2 or not all(parts):
        survey.skipped[topic] = "not scanner/image/<channel>/<direction>"
        return None
    if type_name != IMAGE_TYPE:
        survey.skipped[topic] = f"type {type_name or '(no schema)'}, not {IMAGE_TYPE}"
        return None
    return ImageTopic(topic, parts[0], parts[1])


def survey_session(path) -> Survey:
    """Read the file once: chunk preambles, batches and small messages (no sample array)."""
    survey = Survey(SessionScan(Path(path)))
    roles: dict[int, tuple[str | None, bool]] = {}  # channel id -> (role, type as expected)
    counts = survey.counts
    for m in read_session(path, survey.scan):
        info = roles.get(m.channel_id)
        if info is None:
            role = role_of(m.topic)
            ok = role is not None and m.type_name == EXPECTED_TYPES[role]
            if role is not None and not ok:
                survey.wrong.setdefault(role, {})[m.topic] = m.type_name or "(no schema)"
            if role is None:
                role = _extra_role(m.topic, m.type_name)
                ok = role is not None
            info = roles[m.channel_id] = (role, ok)
        role, ok = info
        if not ok:
            continue
        k = counts[m.topic] = counts.get(m.topic, 0) + 1
        if role in EXTRA_ROLES:
            _survey_extra(survey, role, m, k)
            continue
        try:
            if role in CHUNK_ROLES:
                header, samples = cdr_chunk(m.data)
                s = survey.chunks.get(m.topic)
                if s is None:
                    s = survey.chunks[m.topic] = ChunkStream(m.topic, receive=TimeMapTable())
                s.survey(header, samples.shape[0], m.log_time)
            elif role in BATCH_ROLES:
                first, end, end_time, t, u, v = cdr_batch(role, m.data)
                s = survey.batches.get(m.topic)
                if s is None:
                    s = survey.batches[m.topic] = BatchStream(
                        m.topic,
                        role,
                        receive=TimeMapTable(),
                        times=StrideTable((np.float64,)) if role == "outputs" else None,
                    )
                s.survey(first, end, end_time, t, m.log_time)
                prefix = m.topic[
                    : -len(ROLES[role])
                ]  # the instrument's namespace: pair its own topics
                pairing = survey.setpoints.get(prefix)
                if pairing is None:
                    pairing = survey.setpoints[prefix] = SetpointFromData()
                pairing.add(
                    role,
                    end,
                    t.tolist(),
                    amplitude_phase(u, v)[0].tolist() if role == "outputs" else v.tolist(),
                )
            elif role == FM_ROLE:
                b = cdr_fm_batch(m.data)
                s = survey.batches.get(m.topic)
                if s is None:
                    s = survey.batches[m.topic] = BatchStream(
                        m.topic, role, receive=TimeMapTable()
                    )
                s.survey(b.input_first_index, b.input_end_index, b.input_end_time, b.t, m.log_time)
            elif role == "parameter_events":
                from rcl_interfaces.msg import ParameterEvent  # noqa: PLC0415 - ROS only for the messages that need it
                from rclpy.serialization import deserialize_message  # noqa: PLC0415 - ROS only for the messages that need it

                survey.events.append((m.log_time, deserialize_message(m.data, ParameterEvent)))
            else:
                s = survey.series.get(m.topic)
                if s is None:
                    # sample times are needed for the time map (clock) and the amplitude's windows
                    times = {
                        "clock": TimeMapTable,
                        "xy": lambda: StrideTable((np.int64, np.float64)),
                        "amplitude": lambda: StrideTable((np.int64,)),
                    }.get(role, lambda: None)()
                    s = survey.series[m.topic] = Series(m.topic, role, times=times)
                if role == "xy":
                    stamp = cdr_vector3_stamped(m.data)[0]
                    s.survey(m.log_time, stamp)
                    if s.count == 1:
                        s.stamp_first = stamp
                    s.stamp_last = stamp
                    s.stamp_min, s.stamp_max = min(s.stamp_min, stamp), max(s.stamp_max, stamp)
                elif role == "clock":
                    s.survey(m.log_time, cdr_clock_seconds(m.data))
                else:
                    cdr_float64(m.data)
                    s.survey(m.log_time)
        except ReportError:
            raise
        except Exception as exc:  # noqa: BLE001 - any parser error: the file is not what the role needs
            if isinstance(exc, ChunkLayoutError):
                raise ReportError(
                    f"topic {m.topic}: message {k} is not a {LAYOUT_NAMES[role]} in the afm_ros "
                    f"layout ({exc})"
                ) from None
            raise bad_message(m.topic, m.type_name, k, exc) from None
    for pairing in survey.setpoints.values():
        pairing.finish()
    return survey


def _json_object(found: tuple, data: SessionData) -> dict | None:
    """The JSON object of a recorded std_msgs/String (topic, message number, CDR bytes); None and a
    note in ``data.skipped`` if it is not one."""
    topic, k, raw = found
    try:
        order = cdr_byte_order(raw)
        n = struct.unpack_from(order + "I", raw, 4)[0]
        if n == 0 or 8 + n > len(raw):
            raise ValueError("the string runs past the end of the message")
        g = json.loads(raw[8 : 8 + n - 1].decode("utf-8"))
    except (ValueError, struct.error) as exc:
        data.skipped[topic] = f"message {k} is not a JSON text ({str(exc)[:120]})"
        return None
    if not isinstance(g, dict):
        data.skipped[topic] = f"message {k} is a JSON {type(g).__name__}, not an object"
        return None
    return g


def check_tune(survey: Survey, data: SessionData) -> None:
    """The last lockin/tune_result: its sweep (equal-length finite lists) and fit, else a note."""
    if survey.tune is None:
        return
    topic, k, _ = survey.tune
    g = _json_object(survey.tune, data)
    if g is None:
        return
    try:
        arrays = {
            key: np.asarray(g[key], dtype=float)
            for key in ("frequency_Hz", "amplitude_m", "phase_deg")
        }
        numbers = {
            key: float(g[key])
            for key in (
                "f0_Hz",
                "f0_error_Hz",
                "Q",
                "Q_error",
                "drive_frequency_Hz",
                "drive_scale",
                "phase_offset_deg",
                "static_amplitude_m",
                "phase0_deg",
            )
        }
    except (KeyError, TypeError, ValueError) as exc:
        data.skipped[topic] = f"message {k}: a field is missing or not a number ({str(exc)[:80]})"
        return
    sizes = {a.shape for a in arrays.values()}
    if (
        len(sizes) != 1
        or next(iter(sizes))[0] < 2
        or any(a.ndim != 1 for a in arrays.values())
        or not all(math.isfinite(v) for key, v in numbers.items() if not key.endswith("_error"))
    ):
        data.skipped[topic] = (
            f"message {k}: the sweep's lists differ in length or the fit is not finite"
        )
        return
    data.tune = {**numbers, **arrays}


def check_bimodal(survey: Survey, data: SessionData) -> None:
    """The last bimodal/materials table (frame, lines done, a row per material with the fields of
    :data:`BIMODAL_FIELDS`, numbers or null), else a note."""
    if survey.bimodal is None:
        return
    topic, k, _ = survey.bimodal
    g = _json_object(survey.bimodal, data)
    if g is None:
        return
    rows = g.get("materials")
    ok = isinstance(rows, list) and all(
        isinstance(r, dict)
        and isinstance(r.get("material"), str)
        and all(
            r.get(f) is None or (isinstance(r.get(f), (int, float)) and not isinstance(r[f], bool))
            for f in BIMODAL_FIELDS[1:]
        )
        and all(f in r for f in BIMODAL_FIELDS)
        for r in rows
    )
    if not ok or not isinstance(g.get("frame"), int) or not isinstance(g.get("lines_done"), int):
        data.skipped[topic] = f"message {k}: not a per-material table (frame, lines, materials)"
        return
    data.bimodal = {"frame": g["frame"], "lines_done": g["lines_done"], "materials": rows}
    check_bimodal_images(survey, data)


def check_bimodal_images(survey: Survey, data: SessionData) -> None:
    """The frame's last images (64FC1) with its corner and side from the last bimodal/progress,
    for ``bimodal.png``; a channel that does not decode is skipped with a note."""
    progress = _json_object(survey.bimodal_progress, data) if survey.bimodal_progress else None
    if not progress or not isinstance(progress.get("origin_m"), list):
        return
    images = {}
    for channel, (topic, k, raw) in survey.bimodal_images.items():
        try:
            images[channel] = decode_image(raw, "64FC1")
        except ValueError as exc:
            data.skipped[topic] = f"message {k}: {exc}"
    needed = ("height", "frequency_shift_2", "phase_2", "modulus", "true_modulus")
    if all(c in images for c in needed) and len({images[c].shape for c in needed}) == 1:
        corner = tuple(float(v) for v in progress["origin_m"])
        data.bimodal_frame = (images, corner, float(progress["size_m"]))


def check_spectroscopy(survey: Survey, data: SessionData) -> None:
    """The last z_controller/spectroscopy curve (formats/spectroscopy_layout.py), else a note."""
    if survey.spectroscopy is None:
        return

    topic, k, raw = survey.spectroscopy
    try:
        curve = unpack_curve(cdr_float64_array(raw)[1])
    except (ValueError, struct.error, KeyError) as exc:
        data.skipped[topic] = f"message {k} is not a spectroscopy curve ({str(exc)[:120]})"
        return
    if curve.t.size < 2 or not (curve.branch("approach").any() and curve.branch("retract").any()):
        data.skipped[topic] = f"message {k}: the curve has no approach or no retract leg"
        return
    data.spectroscopy = curve


def spectroscopy_numbers(curve) -> dict:
    """The report's numbers of a curve: its set-up, the amplitude and phase at the legs' ends, the
    mean force's extremes and the lag the ramp rate implies (core/spectroscopy.expected_lag)."""

    lo, hi = expected_lag(
        curve.chunk_duration,
        curve.feedback_latency,
        curve.quality_factor,
        curve.resonance_frequency,
    )
    a, r = curve.branch("approach"), curve.branch("retract")
    force = curve.chunk_force[np.isfinite(curve.chunk_force)]
    return {
        "x_m": curve.x,
        "y_m": curve.y,
        "t_start_s": curve.t_start,
        "t_end_s": curve.t_end,
        "rate_m_per_s": curve.rate,
        "retract_m": curve.retract,
        "distance_m": curve.distance,
        "z_gap_held_m": curve.z_offset + curve.z_held,
        "z_gap_lowest_m": float(curve.z_gap[a].min()),
        "outputs": int(curve.t.size),
        "chunks": int(curve.chunk_t_start.size),
        "missing_chunks": curve.missing_chunks,
        "amplitude_top_m": float(curve.amplitude[a][0]),
        "amplitude_bottom_m": float(curve.amplitude[a][-1]),
        "phase_top_deg": float(curve.phase[a][0]),
        "phase_bottom_deg": float(curve.phase[a][-1]),
        "amplitude_retract_top_m": float(curve.amplitude[r][-1]),
        "max_mean_force_N": float(force.max()) if force.size else math.nan,
        "min_mean_force_N": float(force.min()) if force.size else math.nan,
        "lag_z_m": [curve.rate * lo, curve.rate * hi],
    }


def check_geometry(survey: Survey, data: SessionData) -> None:
    """The last scanner/geometry, if it is a JSON object whose extent fields are numbers (else a
    note)."""
    if survey.geometry is None:
        return
    topic, k, _ = survey.geometry
    g = _json_object(survey.geometry, data)
    if g is None:
        return
    bad = [
        key
        for key in ("x_offset_m", "y_offset_m", "size_x_m", "size_y_m")
        if isinstance(g.get(key), bool)
        or not isinstance(g.get(key), (int, float))
        or not math.isfinite(g[key])
        or (key.startswith("size") and g[key] <= 0)
    ]
    if bad:
        data.skipped[topic] = (
            f"message {k}: {', '.join(bad)} missing or not a finite number (sizes > 0); "
            "images drawn in pixels"
        )
        return
    if not isinstance(g.get("channels"), dict):
        g["channels"] = {}
    data.geometry = g
