"""Between the passes: the topic of each role, the time axis, the parameters and their changes,
the setpoint history and the averaging windows (:class:`Plan`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from afm_ros.formats.mcap_io import SessionScan, parameter_metadata
from afm_ros.tools.report.session import (
    CHANGES_CAP,
    SETPOINT_ABS_TOL,
    SETPOINT_REL_TOL,
    ReportError,
    Series,
    SessionData,
)
from afm_ros.tools.report.survey import BATCH_ROLES, EXPECTED_TYPES, ROLES, Survey, role_of


def pick_topics(scan: SessionScan, wrong: dict, counts: dict, data: SessionData) -> None:
    """The recorded topic of each role (the most messages of the expected type) into
    ``data.topics``; ReportError if a role's only topics have another type."""
    topics = scan.topics
    for role in ROLES:
        good = [
            t
            for t in topics
            if role_of(t) == role and topics[t] == EXPECTED_TYPES[role] and counts.get(t)
        ]
        bad = wrong.get(role, {})
        if good:
            data.topics[role] = max(good, key=lambda t: counts.get(t, 0))
            data.ignored += [(t, ty, EXPECTED_TYPES[role]) for t, ty in sorted(bad.items())]
        elif bad:
            t = max(bad, key=lambda x: scan.message_counts.get(x, 0))
            raise ReportError(
                f"topic {t} has type {bad[t]}, the report expects {EXPECTED_TYPES[role]} "
                f"for the {role.replace('_', ' ')} (not an afm_ros session?)"
            )


def series_from_batches(data: SessionData, survey: Survey) -> None:
    """Amplitude and phase from lockin/outputs, z piezo and error from z_controller/trace, when
    recorded: complete, in time order, with exact simulated times (preferred over the per-output
    copies)."""
    for batch_role, roles in BATCH_ROLES.items():
        stream = survey.batches.get(data.topics.get(batch_role))
        if stream is None or not stream.outputs:
            continue
        data.batches[batch_role] = stream
        if batch_role == "outputs" and "xy" in data.series:  # its stamps place the copies only
            data.unused.append(data.series.pop("xy").topic)
        for role in roles:
            old = data.series.get(role)
            if old is not None:
                data.unused.append(old.topic)
            data.series[role] = Series(
                stream.topic,
                role,
                count=stream.outputs,
                stamped=True,
                batch=stream,
                t_first=stream.t_first,
                t_last=stream.t_last,
            )
    outputs, trace = data.batches.get("outputs"), data.batches.get("z_trace")
    if outputs is not None and trace is not None:
        prefix = outputs.topic[: -len(ROLES["outputs"])]
        if trace.topic[: -len(ROLES["z_trace"])] == prefix:
            data.setpoint_data = survey.setpoints.get(prefix)


@dataclass
class Plan:
    """The time mapping, engage time, setpoint segments and averaging windows (times in s)."""

    ref: tuple | None  # (sorted log_time ns, simulated s) for the time mapping, None: wall time
    t0: int  # [ns] origin of the wall-time axis
    engage: float | None = None
    engage_log: int | None = None  # receive time of the parameter event that enabled the feedback
    setpoint: float | None = None  # in force at the end
    segments: list = field(
        default_factory=list
    )  # (start [s], setpoint [m], kind): "engage", "change", "scan"
    scan_start: float | None = None  # simulated start of the (last) recorded scan
    free_lo: float | None = None  # free amplitude window [free_lo, engage)
    tail_lo_est: float | None = (
        None  # reached-amplitude window: t >= tail_lo (in the last segment)
    )
    tail_last: float | None = None  # last amplitude time after engaging (ta[-1])
    error_lo: float | None = None  # setpoint-from-error window: error t >= error_lo
    exact_bounds: bool = True

    def map(self, log_time) -> np.ndarray:
        lt = np.asarray(log_time, dtype=np.int64)
        if self.ref is not None:
            return np.interp(lt, self.ref[0], self.ref[1])
        return (lt - self.t0) * 1e-9


def _param_value(v):
    from rclpy.parameter import parameter_value_to_python  # noqa: PLC0415 - ROS only for the messages that need it

    value = parameter_value_to_python(v)
    return list(value) if type(value).__name__ == "array" else value


def parse_float(text):
    """``float(text)``, or None if it is not a number."""
    try:
        return float(text)
    except (TypeError, ValueError):
        return None


def _parsed(raw):
    """A parameter value as recorded in a snapshot (text): bool, float or None."""
    return {"true": True, "false": False}.get(raw, parse_float(raw))


def _text(raw) -> str:
    """A string parameter value as recorded in a snapshot (its YAML quotes removed)."""
    return str(raw).strip("'\"")


def current(
    data: SessionData, node_suffix: str, name: str, at: float | None = None, parse=_parsed
):
    """Value of parameter ``name`` of the node whose name ends with ``node_suffix`` at time ``at``
    (the snapshot's text through ``parse``, then the recorded changes)."""
    value = None
    for node, values in data.initial_parameters.items():
        if node.endswith(node_suffix) and name in values:
            value = parse(values[name])
    for (lt, node, pname, v), t in zip(data.changes, data.change_times):
        if node.endswith(node_suffix) and pname == name and (at is None or t <= at):
            value = v
    return value


def _same_setpoint(a: float, b: float) -> bool:
    return abs(a - b) <= SETPOINT_REL_TOL * max(abs(a), abs(b)) + SETPOINT_ABS_TOL


def _setpoint_history(data: SessionData, plan: Plan) -> float | None:
    """Fill ``data.setpoints`` with every setpoint change ({time_s, old_m, new_m, engaged,
    exact_time}); return the setpoint in force at the start (None if unknown).

    From the data when the lock-in batches and the z trace are recorded: amplitude + error at every
    output, a change at the exact simulated time of the first output computed with the new value
    (the value itself from the matching /parameter_events change, exact, when there is one).
    Otherwise from the /parameter_events changes, placed by their receive time (to within the
    delivery latency). None in FM (the z loop regulates df, not the amplitude)."""
    if data.fm_feedback:
        data.setpoint_data = None
        return None
    events = [
        (lt, t, float(v))
        for (lt, node, name, v), t in zip(data.changes, data.change_times)
        if node.endswith("z_controller")
        and name == "setpoint"
        and isinstance(v, (int, float))
        and not isinstance(v, bool)
    ]
    initial = None
    for node, values in data.initial_parameters.items():
        if node.endswith("z_controller") and "setpoint" in values:
            initial = parse_float(values["setpoint"])
    sd = data.setpoint_data
    history = data.setpoints
    if sd is not None and sd.first is not None and not sd.too_many:
        data.setpoint_source = "data"
        start = sd.first[1]
        exact = [
            v
            for v in ([initial] if initial is not None else []) + [e[2] for e in events]
            if _same_setpoint(v, start)
        ]
        start = current = exact[0] if exact else start
        k = 0
        for t, _, new in sd.changes:
            match = next(
                (j for j in range(k, len(events)) if _same_setpoint(events[j][2], new)), None
            )
            log_time = None
            if match is not None:
                new, log_time, k = events[match][2], events[match][0], match + 1
            history.append(
                {
                    "time_s": t,
                    "old_m": current,
                    "new_m": new,
                    "exact_time": True,
                    "log_time": log_time,
                }
            )
            current = new
        silent = len(events) - sum(1 for c in history if c["log_time"] is not None)
        if silent > 0:
            data.notes.append(
                f"{silent} setpoint parameter change(s) on /parameter_events left the value the "
                "lock-in outputs were controlled to as it was (set to the value in force, or no "
                "output after them)."
            )
    else:
        if sd is not None and sd.too_many:
            data.notes.append(
                f"amplitude + error changes more than {CHANGES_CAP} times: not a setpoint; the "
                "setpoint history is taken from /parameter_events."
            )
        data.setpoint_source = "events" if events else ""
        start = current = initial
        for lt, t, value in events:
            history.append(
                {
                    "time_s": t,
                    "old_m": current,
                    "new_m": value,
                    "exact_time": False,
                    "log_time": lt,
                }
            )
            current = value
    for c in history:
        if plan.engage is None:
            c["engaged"] = True
        elif c["log_time"] is not None and plan.engage_log is not None:
            c["engaged"] = (
                c["log_time"] > plan.engage_log
            )  # receive order: exact, unlike mapped times
        else:
            c["engaged"] = c["time_s"] >= plan.engage
    return start


def make_plan(data: SessionData, events: list) -> Plan:
    # parameters: snapshots (metadata records, else initial ParameterEvents) and later changes
    data.initial_parameters = {n: dict(v) for n, v in parameter_metadata(data.scan).items()}
    from_events: dict[str, dict] = {}
    for log_time, event in events:
        for p in event.new_parameters:
            from_events.setdefault(event.node, {})[p.name] = repr(_param_value(p.value))
        for p in event.changed_parameters:
            data.changes.append((log_time, event.node, p.name, _param_value(p.value)))
    for node, values in from_events.items():
        data.initial_parameters.setdefault(node, values)

    ref = table = None
    clock = data.series.get("clock")
    if clock is not None and clock.count >= 2:
        table, what = clock.times, "/clock"
    else:
        for s in (
            data.deflection,
            data.force,
            data.batches.get("outputs"),
            data.batches.get("z_trace"),
        ):
            if s is not None and s.messages >= 2:
                table, what = s.receive, s.topic + " messages"
                break
    if table is not None:
        lt, t = table.arrays()
        order = np.argsort(lt, kind="stable")
        ref = (lt[order], t[order])
        if table.tol > 0:
            bound = (
                f"within {table.error_bound * 1e6:.3g} µs of"
                if math.isfinite(table.error_bound)
                else "close to"
            )
            data.notes.append(
                f"Times from receive times: the mapping through {table.seen} {what} messages "
                f"is a polyline of {lt.size} points, {bound} "
                "the one through all of them."
            )
    t0 = min((s.min_log for s in data.series.values() if s.min_log is not None), default=0)
    if ref is None and data.deflection is None and not data.batches:
        data.time_axis = "wall time since first message [s]"
    plan = Plan(ref, t0)
    data.change_times = [float(plan.map(lt)) for lt, *_ in data.changes]
    data.fm_feedback = (
        current(data, "z_controller", "feedback_signal", parse=_text) == "frequency_shift"
    )

    xy = data.series.get("xy")
    for role, s in data.series.items():
        if s.batch is not None:
            continue  # exact simulated times, set from the batches
        if role == "xy":
            s.stamped = True
            s.t_first, s.t_last = s.stamp_first, s.stamp_last
        elif role in ("amplitude", "phase") and xy is not None and s.count == xy.count:
            # lock-in outputs are published together with xy (exact simulated time)
            s.stamped = True
            s.t_first, s.t_last = xy.stamp_first, xy.stamp_last
        else:
            s.t_first, s.t_last = (float(v) for v in plan.map([s.first_log, s.last_log]))

    # engagement: the z_controller's `enabled` switched on, else the first error sample
    for (lt, node, name, v), tc in zip(data.changes, data.change_times):
        if node.endswith("z_controller") and name == "enabled" and v is True:
            plan.engage, plan.engage_log = tc, lt
    err = data.series.get("error")
    if (
        plan.engage is None
        and current(data, "z_controller", "enabled") is True
        and err is not None
    ):
        plan.engage = err.t_first
    start = _setpoint_history(data, plan)
    final = data.setpoints[-1]["new_m"] if data.setpoints else start
    plan.setpoint = float(final) if final is not None else None
    if plan.setpoint is not None:
        at_engage = start
        for c in data.setpoints:
            if not c["engaged"]:
                at_engage = c["new_m"]
        plan.segments = [
            (plan.engage if plan.engage is not None else -math.inf, at_engage, "engage")
        ] + [
            (
                c["time_s"] if plan.engage is None else max(c["time_s"], plan.engage),
                c["new_m"],
                "change",
            )
            for c in data.setpoints
            if c["engaged"]
        ]
        scan = (data.geometry or {}).get("start_time_s")
        if (
            isinstance(scan, (int, float))
            and not isinstance(scan, bool)
            and math.isfinite(scan)
            and scan > plan.segments[0][0]
        ):
            # the settling after engaging (or a change) is measured up to the scan: from then on
            # the amplitude follows the topography
            plan.scan_start = float(scan)
            k = sum(1 for seg in plan.segments if seg[0] <= scan)
            plan.segments.insert(k, (float(scan), plan.segments[k - 1][1], "scan"))
    if err is not None:
        plan.error_lo = err.t_last - 0.2 * (err.t_last - err.t_first)

    amp = data.series.get("amplitude")
    if amp is not None and amp.count:
        if amp.batch is not None:
            t = amp.batch.times.arrays()[0]
            plan.exact_bounds = amp.batch.times.stride == 1
        else:
            t = xy.times.arrays()[1] if amp.stamped else plan.map(amp.times.arrays()[0])
            plan.exact_bounds = amp.times.stride == 1
        if plan.engage is not None:
            before = t[t < plan.engage]
            if before.size:
                plan.free_lo = before[-1] - 0.2 * (before[-1] - before[0])
        last_start = (
            plan.segments[-1][0]
            if plan.segments
            else (plan.engage if plan.engage is not None else -math.inf)
        )
        after = t[t >= last_start]
        if after.size:
            plan.tail_last = float(after[-1])
            plan.tail_lo_est = after[-1] - 0.2 * (after[-1] - after[0])
    return plan
