"""Benchmark of ``afm_report`` on synthetic sessions of growing length: wall time and peak memory.

``python -m benchmarks.bench_report [--seconds 10 60 600] [--rate 90e3] [--series-rate 1000]
[--keep DIR]`` prints one JSON document. For every length it writes a synthetic session
(:func:`write_synthetic_session`) into a temporary directory (removed afterwards unless ``--keep``)
and runs, each in a fresh process:

- ``baseline``: :func:`afm_ros.formats.mcap_io.read_session` over the whole file, no message
  decoded (the floor any reader of the file pays: decompression and record parsing);
- ``report``: ``afm_report SESSION --out DIR --json`` (two passes over the file); ``numbers_exact``
  says whether its counts and tracking numbers are those the session was built with.

``--series copies`` (default) writes the lock-in and z controller outputs as the per-output Float64
copies (``lockin/amplitude`` ...), ``batches`` as the loop's batches (``lockin/outputs``,
``z_controller/trace``: what ``afm_instrument --image`` records), ``both`` as both (the report then
reads the batches).

Reported per run: wall time [s] and peak resident set size [MB] of each process (the kernel's
``ru_maxrss``, see :func:`run_measured`), file size, messages and samples. The synthetic session
has the instrument's message pattern (2 ms chunks of deflection and tip-sample force with a /clock
message each, lock-in amplitude, phase and xy, z piezo and error at ``series_rate``, an engage via
``/parameter_events``) at a reduced sample rate by default (``--rate 900e3`` for the instrument's
rate; the number of messages, which sets most of the report's cost, does not depend on it).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from rcl_interfaces.msg import Parameter, ParameterEvent, ParameterType, ParameterValue

from afm_ros.core.physics.forces import DMTForce
from afm_ros.formats.chunk_layout import PREAMBLE_LENGTH
from afm_ros.formats.mcap_io import SessionWriter, serialize_exact

WALL_START_NS = 1_700_000_000 * 10**9  # log_time of simulated t = 0 (real-time pacing)
NS = "/syn"


def _chunk_prefix(n: int) -> bytes:
    """CDR of a std_msgs/Float64MultiArray with one dimension 'samples' up to its float data."""
    label = b"samples\x00"
    head = (
        b"\x00\x01\x00\x00"
        + struct.pack("<II", 1, len(label))
        + label
        + struct.pack("<IIII", n, n, PREAMBLE_LENGTH, PREAMBLE_LENGTH + n)
    )
    return head + b"\x00" * ((-(len(head) - 4)) % 8)


def _float64(value: float) -> bytes:
    return b"\x00\x01\x00\x00" + struct.pack("<d", value)


def _stamp(t: float) -> tuple[int, int]:
    sec = int(math.floor(t))
    return sec, int(round((t - sec) * 1e9))


def _clock(sec: int, nanosec: int) -> bytes:
    return b"\x00\x01\x00\x00" + struct.pack("<iI", sec, nanosec)


def _vector3_stamped(sec: int, nanosec: int, x: float, y: float) -> bytes:
    # stamp, frame_id '' (length 1: the terminating NUL), padding to 8, vector x y z
    return (
        b"\x00\x01\x00\x00"
        + struct.pack("<iII", sec, nanosec, 1)
        + b"\x00" * 4
        + struct.pack("<ddd", x, y, 0.0)
    )


def _parameter_event(node: str, new: dict | None = None, changed: dict | None = None) -> bytes:

    def msg(name, value):
        if isinstance(value, bool):
            v = ParameterValue(type=ParameterType.PARAMETER_BOOL, bool_value=value)
        else:
            v = ParameterValue(type=ParameterType.PARAMETER_DOUBLE, double_value=float(value))
        return Parameter(name=name, value=v)

    return serialize_exact(
        ParameterEvent(
            node=node,
            new_parameters=[msg(k, v) for k, v in (new or {}).items()],
            changed_parameters=[msg(k, v) for k, v in (changed or {}).items()],
        )
    )


def _batch(preamble: tuple, t: list, u: list, v: list) -> bytes:
    """CDR of a std_msgs/Float64MultiArray in the batch layout: ``preamble``, then t, u, v
    blocks."""
    label = b"outputs\x00"
    n, p = len(t), len(preamble)
    head = (
        b"\x00\x01\x00\x00"
        + struct.pack("<II", 1, len(label))
        + label
        + struct.pack("<IIII", n, 3 * n, p, p + 3 * n)
    )
    head += b"\x00" * ((-(len(head) - 4)) % 8)
    return head + np.array([*preamble, *t, *u, *v], dtype="<f8").tobytes()


def write_synthetic_session(
    path,
    seconds: float,
    sample_rate: float = 20e3,
    chunk_s: float = 0.002,
    series_rate: float = 100.0,
    samples_per_period: int = 20,
    compression: str = "zstd",
    non_finite_chunks=(),
    non_finite_amplitudes=(),
    record_setpoint: bool = True,
    series: str = "copies",
) -> dict:
    """Write a session of ``seconds`` simulated seconds into ``path`` and return what it holds.

    Deflection: ``A_d sin(2 pi i / P - pi/2)`` (P = ``samples_per_period``, every chunk holds whole
    periods, so every chunk has the same samples); z_offset constant; force: the DMT model (default
    sample) at gap = z_offset + deflection. /clock once per chunk (its end time), receive time =
    WALL_START_NS + simulated time (real-time pacing). At ``series_rate``: lock-in amplitude (free
    amplitude before engaging, then an exponential approach to the setpoint), phase, xy (stamped
    with the exact simulated time), z piezo and, after engaging, error = setpoint - amplitude. The
    z_controller's ``enabled`` switches on at ``engage_time_s`` (a /parameter_events change).
    ``non_finite_chunks``: chunk numbers whose deflection sample 1 is NaN;
    ``non_finite_amplitudes``: series sample numbers whose amplitude is NaN. ``record_setpoint``
    False: the z_controller's parameters lack ``setpoint`` (the report must rebuild it from the
    error). ``series``: "copies" (one Float64 message per output and quantity), "batches" (per
    chunk one lockin/outputs batch with the chunk's outputs t, X, Y and one z_controller/trace with
    t, z, error = setpoint - amplitude, as the z controller computes it also before engaging) or
    "both".

    Returns the expected report numbers (``expected``) and the construction constants.
    """

    n = int(round(sample_rate * chunk_s))
    if n % samples_per_period:
        raise ValueError(
            f"a chunk of {n} samples does not hold whole periods of {samples_per_period}"
        )
    chunks = int(round(seconds / chunk_s))
    series_dt = 1.0 / series_rate
    dt = 1.0 / sample_rate
    amp_d, z_offset = 20e-9, 10e-9
    i = np.arange(n)
    deflection = amp_d * np.sin(2.0 * np.pi * i / samples_per_period - np.pi / 2.0)
    force = DMTForce().force(z_offset + deflection)
    free_amp, setpoint, tau = 60e-9, 48e-9, 0.02
    phase_free, phase_contact, z_free, z_contact = 90.0, 45.0, 0.0, -15e-9
    engage = (
        round(0.1 * seconds / series_dt) + 0.5
    ) * series_dt  # half way between two series samples

    if series not in ("copies", "batches", "both"):
        raise ValueError(f"series={series!r} must be copies, batches or both")
    copies, batches = series in ("copies", "both"), series in ("batches", "both")
    w = SessionWriter(path, compression=compression)
    ch = {
        name: w.add_channel(f"{NS}/{name}" if name != "/parameter_events" else name, typ)
        for name, typ in (
            ("cantilever/deflection", "std_msgs/msg/Float64MultiArray"),
            ("cantilever/tip_sample_force", "std_msgs/msg/Float64MultiArray"),
            ("clock", "rosgraph_msgs/msg/Clock"),
            *(
                (
                    ("lockin/amplitude", "std_msgs/msg/Float64"),
                    ("lockin/phase", "std_msgs/msg/Float64"),
                    ("lockin/xy", "geometry_msgs/msg/Vector3Stamped"),
                    ("z_controller/z_piezo", "std_msgs/msg/Float64"),
                    ("z_controller/error", "std_msgs/msg/Float64"),
                )
                if copies
                else ()
            ),
            *(
                (
                    ("lockin/outputs", "std_msgs/msg/Float64MultiArray"),
                    ("z_controller/trace", "std_msgs/msg/Float64MultiArray"),
                )
                if batches
                else ()
            ),
            ("/parameter_events", "rcl_interfaces/msg/ParameterEvent"),
        )
    }
    z_params = {"setpoint": setpoint, "enabled": False} if record_setpoint else {"enabled": False}
    w.write(
        ch["/parameter_events"],
        _parameter_event(f"{NS}/z_controller", new=z_params),
        WALL_START_NS,
    )
    w.write(
        ch["/parameter_events"],
        _parameter_event(f"{NS}/cantilever", new={"output_sample_rate": sample_rate}),
        WALL_START_NS,
    )
    prefix = _chunk_prefix(n)
    d_bytes, f_bytes = deflection.tobytes(), force.tobytes()
    bad_d = deflection.copy()
    bad_d[1] = np.nan
    bad_d_bytes = bad_d.tobytes()
    non_finite_chunks, non_finite_amplitudes = set(non_finite_chunks), set(non_finite_amplitudes)
    pre = np.empty(PREAMBLE_LENGTH)
    freq = sample_rate / samples_per_period
    engaged = False

    def _engage() -> bool:
        w.write(
            ch["/parameter_events"],
            _parameter_event(f"{NS}/z_controller", changed={"enabled": True}),
            WALL_START_NS + int(round(engage * 1e9)),
        )
        return True

    series_times, amplitudes = [], []
    for k in range(chunks):
        t_start = k * chunk_s
        pre[:] = (k * n, t_start, dt, 0.0, freq, z_offset)
        sec, nsec = _stamp((k + 1) * chunk_s)
        t_end = sec + 1e-9 * nsec  # what a reader makes of the stamp
        chunk_log = WALL_START_NS + sec * 10**9 + nsec
        # in receive-time order: the series samples up to the chunk's end (the engage event at its
        # time among them), then the chunk's batches, the chunk and its /clock
        batch = ([], [], [], [], [])  # t, X, Y, z, error of the chunk's outputs
        while (len(series_times) + 1) * series_dt <= (k + 1) * chunk_s * (1 + 1e-12):
            sec_s, nsec_s = _stamp((len(series_times) + 1) * series_dt)
            t_s = sec_s + 1e-9 * nsec_s
            log = WALL_START_NS + sec_s * 10**9 + nsec_s
            contact = t_s > engage
            if contact and not engaged:
                engaged = _engage()
            a = (
                setpoint + (free_amp - setpoint) * math.exp(-(t_s - engage) / tau)
                if contact
                else free_amp
            )
            a_written = float("nan") if len(series_times) in non_finite_amplitudes else a
            series_times.append(t_s)
            amplitudes.append(a_written)
            ph = phase_contact if contact else phase_free
            x, y = a_written * math.cos(math.radians(ph)), -a_written * math.sin(math.radians(ph))
            if copies:
                w.write(ch["lockin/amplitude"], _float64(a_written), log)
                w.write(ch["lockin/phase"], _float64(ph), log)
                w.write(
                    ch["lockin/xy"],
                    _vector3_stamped(
                        sec_s,
                        nsec_s,
                        a * math.cos(math.radians(ph)),
                        -a * math.sin(math.radians(ph)),
                    ),
                    log,
                )
                w.write(
                    ch["z_controller/z_piezo"], _float64(z_contact if contact else z_free), log
                )
                if contact:
                    w.write(ch["z_controller/error"], _float64(setpoint - a), log)
            for column, value in zip(
                batch, (t_s, x, y, z_contact if contact else z_free, setpoint - a_written)
            ):
                column.append(value)
        if not engaged and t_end >= engage:
            engaged = _engage()
        if batches:
            w.write(
                ch["lockin/outputs"], _batch((k * n, (k + 1) * n, t_end), *batch[:3]), chunk_log
            )
            w.write(
                ch["z_controller/trace"],
                _batch(((k + 1) * n, t_end), batch[0], *batch[3:]),
                chunk_log,
            )
        head = prefix + pre.tobytes()
        w.write(
            ch["cantilever/deflection"],
            head + (bad_d_bytes if k in non_finite_chunks else d_bytes),
            chunk_log,
        )
        w.write(ch["cantilever/tip_sample_force"], head + f_bytes, chunk_log)
        w.write(ch["clock"], _clock(sec, nsec), chunk_log)
    w.close()

    # expected numbers from the same sample times and today's definitions
    t, a = np.array(series_times), np.array(amplitudes)
    ok = np.isfinite(a)
    after = (t > engage) & ok
    ta, aa = t[t > engage], a[t > engage]
    band = 0.02 * setpoint
    settled = np.abs(aa - setpoint) <= band
    outside = np.flatnonzero(~settled & np.isfinite(aa))
    settling = 0.0 if outside.size == 0 else float(ta[outside[-1] + 1] - ta[0])
    tail = after & (t >= ta[-1] - 0.2 * (ta[-1] - ta[0]))
    gap = z_offset + deflection
    expected = {
        "deflection_samples": chunks * n,
        "force_samples": chunks * n,
        "deflection_lost_samples": 0,
        "deflection_gaps": 0,
        "force_lost_samples": 0,
        "force_gaps": 0,
        "deflection_non_finite": len(non_finite_chunks),
        "amplitude_non_finite": len(non_finite_amplitudes),
        "free_amplitude_m": free_amp,
        "setpoint_m": setpoint,
        "setpoint_from_error_m": setpoint,
        "engage_time_s": engage,
        "reached_amplitude_m": float(np.mean(a[tail])),
        "settling_time_s": settling,
        "contact_phase_deg": phase_contact,
        "contact_z_piezo_m": z_contact,
        "min_gap_m": float(gap.min()),
        "max_force_n": float(force.max()),
        "min_force_n": float(force.min()),
        "force_distance_pairs": chunks * n,
    }
    if batches:
        expected["outputs_outputs"] = expected["z_trace_outputs"] = len(series_times)
    return {
        "path": str(path),
        "seconds": chunks * chunk_s,
        "sample_rate": sample_rate,
        "chunk_samples": n,
        "chunks": chunks,
        "series_samples": len(series_times),
        "z_offset_m": z_offset,
        "deflection_amplitude_m": amp_d,
        "samples_per_period": samples_per_period,
        "bytes": os.path.getsize(path),
        "messages": w.message_count,
        "expected": expected,
    }


# --- benchmark -------------------------------------------------------------------------------

_BASELINE = (
    "import sys; from afm_ros.formats.mcap_io import read_session\n"
    "n = sum(1 for _ in read_session(sys.argv[1]))\nprint(n)\n"
)

# A child's ru_maxrss starts at its parent's resident size (Linux keeps the high-water mark of the
# memory image it had before exec, and subprocess spawns with vfork), so measuring from a large
# process (pytest, this benchmark) would report the parent. The command therefore runs under a
# small intermediate (python -S, ~10 MB) whose only child it is: an upper bound that is off by at
# most the intermediate's size, and the kernel's exact high-water mark (no sampling).
_PROBE = (
    "import resource, subprocess, sys\n"
    "rc = subprocess.call(sys.argv[2:])\n"
    "open(sys.argv[1], 'w').write(str(resource.getrusage(resource.RUSAGE_CHILDREN).ru_maxrss))\n"
    "sys.exit(rc)\n"
)


def run_measured(cmd: list[str], timeout: float = 3600.0) -> dict:
    """Run ``cmd``: exit status, stdout, stderr, wall time [s] and peak RSS [MB] of that
    process."""
    with tempfile.TemporaryDirectory(prefix="afm_rss_") as tmp:
        rss = Path(tmp) / "maxrss_kb"
        start = time.perf_counter()
        proc = subprocess.run(
            [sys.executable, "-S", "-c", _PROBE, str(rss), *[str(c) for c in cmd]],
            capture_output=True,
            text=True,
            timeout=timeout,
            stdin=subprocess.DEVNULL,
        )
        wall = time.perf_counter() - start
        return {
            "status": proc.returncode,
            "stdout": proc.stdout,
            "stderr": proc.stderr,
            "wall_s": wall,
            "peak_rss_mb": int(rss.read_text()) / 1024,
        }


def _run_child(cmd: list[str]) -> tuple[dict, str]:
    r = run_measured(cmd)
    if r["status"] != 0:
        raise RuntimeError(
            f"{' '.join(map(str, cmd))} failed ({r['status']}): {r['stderr'].strip()[-500:]}"
        )
    return {"wall_s": round(r["wall_s"], 2), "peak_rss_mb": round(r["peak_rss_mb"], 1)}, r[
        "stdout"
    ]


def _numbers_exact(numbers: dict, expected: dict) -> bool:
    """Counts equal, averages within 1e-12 relative, engage time within 1 us (receive-time
    mapping)."""
    for key, want in expected.items():
        got = numbers.get(key)
        if got is None:
            return False
        tol = 1e-6 if key == "engage_time_s" else 1e-12 * abs(want)
        if abs(got - want) > tol:
            return False
    return True


def _period(n: int) -> int:
    """Samples per drive period: the largest divisor of the chunk length from 20 down to 3."""
    return next((p for p in range(20, 2, -1) if n % p == 0), n)


def report_command(session, out_dir) -> list[str]:
    return [
        sys.executable,
        "-m",
        "afm_ros.tools.report",
        str(session),
        "--out",
        str(out_dir),
        "--json",
    ]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_report", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument(
        "--seconds",
        type=float,
        nargs="+",
        default=[10.0, 60.0, 600.0],
        help="simulated lengths of the synthetic sessions [s]",
    )
    parser.add_argument(
        "--rate", type=float, default=90e3, help="sample rate [S/s] (instrument: 900e3)"
    )
    parser.add_argument(
        "--series-rate", type=float, default=1000.0, help="lock-in/z rate [Hz] (instrument: 1000)"
    )
    parser.add_argument(
        "--series",
        choices=("copies", "batches", "both"),
        default="copies",
        help="how the lock-in and z outputs are recorded (see the module doc)",
    )
    parser.add_argument(
        "--keep", help="write the sessions and reports here instead of a removed temp dir"
    )
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory(prefix="afm_bench_report_") as tmp:
        base = Path(args.keep) if args.keep else Path(tmp)
        base.mkdir(parents=True, exist_ok=True)
        runs = []
        for seconds in args.seconds:
            path = base / f"synthetic_{seconds:g}s.mcap"
            if path.exists():
                path.unlink()
            start = time.perf_counter()
            info = write_synthetic_session(
                path,
                seconds,
                sample_rate=args.rate,
                series_rate=args.series_rate,
                samples_per_period=_period(int(round(args.rate * 0.002))),
                series=args.series,
            )
            write_s = time.perf_counter() - start
            baseline, _ = _run_child([sys.executable, "-c", _BASELINE, str(path)])
            out = base / f"report_{seconds:g}s"
            rep, stdout = _run_child(report_command(path, out))
            numbers = json.loads(stdout.strip().splitlines()[-1])
            runs.append(
                {
                    "simulated_s": info["seconds"],
                    "sample_rate": args.rate,
                    "series_rate": args.series_rate,
                    "series": args.series,
                    "series_source": numbers.get("series_source"),
                    "samples_per_stream": info["expected"]["deflection_samples"],
                    "messages": info["messages"],
                    "file_mb": round(info["bytes"] / 1e6, 1),
                    "write_s": round(write_s, 1),
                    "baseline_read_session": baseline,
                    "report": rep,
                    "numbers_exact": _numbers_exact(numbers, info["expected"]),
                    "streams_complete": (out / "report.md")
                    .read_text()
                    .count("complete: no sample lost"),
                }
            )
            if not args.keep:
                path.unlink()
        print(
            json.dumps(
                {
                    "benchmark": "afm_report on synthetic sessions",
                    "python": sys.version.split()[0],
                    "cpus": os.cpu_count(),
                    "load_average_1min": round(os.getloadavg()[0], 2),
                    "runs": runs,
                },
                indent=1,
            )
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
