"""Faults are never silent: impossible parameter combinations are refused when they are set,
a blown-up integration is caught in the chunk it happens, reported, and recovered from.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from conftest import EXACT_PHYSICS
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from std_msgs.msg import Float64MultiArray

from afm_ros.formats.chunk_layout import unpack
from afm_ros.nodes.cantilever_node import CantileverNode
from afm_ros.nodes.topics import CONSUMER_QOS, Acknowledger

pytestmark = pytest.mark.ros

BIN = Path(sys.executable).parent
# the sequence: each value alone is in range, the third makes F0 = k A0 / Q = 2 mN (> 1 mN)
SEQUENCE = (("free_amplitude", 1e-6), ("quality_factor", 5.0), ("spring_constant", 1e4))
# in range, but a 1 um indentation into a 1e13 Pa contact is far too stiff for plain rk4 at 220
# steps per period (rk4_event, the default, cuts its steps by the contact stiffness); at z_base 40
# nm plain rk4 at 220 taps the 1e13 Pa sample stably again (at 80 steps per period it does not: the
# recovery would blow up again)
BLOW_UP = (
    ("integrator", "rk4"),
    ("steps_per_period", 220),
    ("tip_youngs_modulus", 1e13),
    ("sample_youngs_modulus", 1e13),
    ("z_base", -1e-6),
)


class Watcher(Node):
    """Collects deflection chunks (acknowledging them) and the cantilever's /diagnostics."""

    def __init__(self, ctx, ns):
        super().__init__("watcher", context=ctx, namespace=ns)
        self.chunks, self.status = [], []
        self.ack = Acknowledger(self)
        self.create_subscription(
            Float64MultiArray, "cantilever/deflection", self._on_chunk, CONSUMER_QOS
        )
        self.create_subscription(DiagnosticArray, "/diagnostics", self._on_diag, 100)

    def _on_chunk(self, msg):
        header, samples = unpack(msg.data)
        self.chunks.append((header, samples.copy()))
        self.ack.send(header.first_sample_index + samples.shape[0])

    def _on_diag(self, msg):
        self.status += [s for s in msg.status if s.name.endswith("cantilever: simulation")]


def spin_until(executor, condition, timeout=30.0):
    import time

    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, "condition not met"
        executor.spin_once(timeout_sec=0.01)


def start(ctx, executor, ns, **params):
    node = CantileverNode(
        context=ctx,
        namespace=ns,
        parameter_overrides=[
            Parameter(k, value=v)
            for k, v in {"real_time_factor": 0.0, **EXACT_PHYSICS, **params}.items()
        ],
    )
    watcher = Watcher(ctx, ns)
    client_node = Node("client", context=ctx, namespace=ns)
    for n in (node, watcher, client_node):
        executor.add_node(n)
    client = AsyncParameterClient(client_node, f"{ns}/cantilever")
    assert client.wait_for_services(timeout_sec=10.0)

    def set_param(name, value):
        future = client.set_parameters([Parameter(name, value=value)])
        spin_until(executor, future.done)
        return future.result().results[0]

    return node, watcher, set_param


def test_impossible_combination_refused_when_set_node_keeps_running(
    ros_context, ros_executor, ros_namespace
):
    node, watcher, set_param = start(ros_context, ros_executor, ros_namespace)
    spin_until(ros_executor, lambda: len(watcher.chunks) >= 3)
    assert set_param(*SEQUENCE[0]).successful and set_param(*SEQUENCE[1]).successful
    refused = set_param(*SEQUENCE[2])
    assert not refused.successful
    # the reason names the parameters a user sets, and the combination: F0 = k A0 / Q
    for word in (
        "free_amplitude",
        "spring_constant",
        "quality_factor",
        "k*A0/Q",
        "0.002 N",
        "0.001 N",
    ):
        assert word in refused.reason, refused.reason
    assert node.get_parameter("spring_constant").value == 10.0
    n = len(watcher.chunks)
    spin_until(
        ros_executor, lambda: len(watcher.chunks) >= n + 10
    )  # still integrating and publishing
    idx = np.concatenate([h.first_sample_index + np.arange(s.shape[0]) for h, s in watcher.chunks])
    assert np.array_equal(idx, np.arange(idx.size))


def test_impossible_combination_as_start_values_is_one_clear_error(tmp_path):
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    args = [a for name, value in SEQUENCE for a in ("-p", f"{name}:={value!r}")]
    result = subprocess.run(
        [str(BIN / "cantilever_node"), "--ros-args", *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 1
    assert "Traceback" not in result.stderr
    line = [x for x in result.stderr.splitlines() if x.startswith("cantilever_node:")]
    assert len(line) == 1 and "k*A0/Q" in line[0] and "free_amplitude" in line[0], result.stderr


def test_too_many_chunks_per_second_refused(ros_context, ros_executor, ros_namespace):
    node, watcher, set_param = start(
        ros_context, ros_executor, ros_namespace, real_time_factor=1.0
    )
    r = set_param("chunk_duration", 1e-5)  # 100 000 chunks per wall second at real time
    assert not r.successful and "chunk_duration" in r.reason and "real_time_factor" in r.reason
    assert set_param("chunk_duration", 1e-3).successful  # 1000 per second: fine


@pytest.mark.slow
def test_blow_up_is_caught_in_its_chunk_reported_and_recovered(
    ros_context, ros_executor, ros_namespace
):
    node, watcher, set_param = start(ros_context, ros_executor, ros_namespace)
    spin_until(ros_executor, lambda: len(watcher.chunks) >= 5)
    for name, value in BLOW_UP:
        assert set_param(name, value).successful  # each value is in range
    spin_until(ros_executor, lambda: node.blowup is not None)
    blown_at = node.blowup["sample_index"]
    # nothing non-finite was ever published, and the stream stops exactly before the failed chunk
    spin_until(
        ros_executor,
        lambda: (
            watcher.chunks[-1][0].first_sample_index + watcher.chunks[-1][1].shape[0] == blown_at
        ),
    )
    assert all(np.isfinite(s).all() for _, s in watcher.chunks)
    # /diagnostics says ERROR, what happened and the parameters in force
    spin_until(
        ros_executor, lambda: any(s.level == DiagnosticStatus.ERROR for s in watcher.status)
    )
    err = next(s for s in watcher.status if s.level == DiagnosticStatus.ERROR)
    assert "blew up" in err.message
    values = {kv.key: kv.value for kv in err.values}
    assert "sample_youngs_modulus=10000000000000.0" in values["blowup_parameters"]
    assert "z_base=-1e-06" in values["blowup_parameters"]
    n = len(watcher.chunks)
    for _ in range(20):
        ros_executor.spin_once(timeout_sec=0.01)
    assert len(watcher.chunks) == n  # stopped: no garbage, no new chunks
    # valid values again: restarts from rest at the same time and index, finite data
    assert set_param("z_base", 40e-9).successful
    spin_until(ros_executor, lambda: len(watcher.chunks) >= n + 20)
    assert node.blowup is None and node.blowups == 1
    header, samples = watcher.chunks[n]
    assert header.first_sample_index == blown_at  # the index continues where the stream stopped
    assert np.isfinite(samples).all() and samples[0] == 0.0  # from rest
    assert all(np.isfinite(s).all() for _, s in watcher.chunks[n:])


@pytest.mark.slow
def test_instrument_with_a_blow_up_reports_it_instead_of_a_summary(tmp_path):
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    args = [a for name, value in BLOW_UP for a in ("-p", f"{name}:={value!r}")]
    # the engaged start on the flat sample of these force constants (the modes' default is the
    # blend, whose materials table sets them, approached from 5 um)
    result = subprocess.run(
        [str(BIN / "afm_instrument"), "--ideal", "--ros-args", "-p", "sample:=flat", *args],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert result.returncode == 1
    assert "Traceback" not in result.stderr
    assert (
        "afm_instrument summary" not in result.stdout
    )  # no settling time or amplitude over garbage
    assert "blew up" in result.stderr and "sample_youngs_modulus=10000000000000.0" in result.stderr


# --- damaged files -----------------------------------------------------------------------------


def _session_with_chunks(path: Path, n: int = 3000) -> dict[str, int]:
    """A real session file (our writer): n deflection-like chunks and n clock messages, small
    MCAP chunks so the file has dozens of them; returns the message count per topic."""
    from rclpy.serialization import serialize_message
    from rosgraph_msgs.msg import Clock

    from afm_ros.formats.chunk_layout import ChunkHeader, cdr_chunk_message
    from afm_ros.formats.mcap_io import SessionWriter

    w = SessionWriter(path, compression="zstd", chunk_size=64 * 1024)
    defl = w.add_channel("/cantilever/deflection", "std_msgs/msg/Float64MultiArray")
    clock = w.add_channel("/clock", "rosgraph_msgs/msg/Clock")
    rng = np.random.default_rng(1)
    for k in range(n):
        samples = rng.normal(size=60) * 1e-8
        msg = cdr_chunk_message(ChunkHeader(60 * k, k * 6e-5, 1e-6, 0.0, 45e3, 4e-8), samples)
        w.write(defl, msg, 1_000_000 * k + 1)
        c = Clock()
        c.clock.nanosec = 60_000 * (k + 1)
        w.write(clock, serialize_message(c), 1_000_000 * k + 2)
    w.close()
    return {"/cantilever/deflection": n, "/clock": n}


def _chunks(path: Path):
    from mcap.reader import make_reader

    with open(path, "rb") as f:
        return sorted(
            make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset
        )


def _flip(path: Path, offset: int, mask: int = 0x10) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= mask
    path.write_bytes(bytes(data))


@pytest.mark.parametrize("where", ["payload", "length"])
def test_damaged_middle_chunk_is_skipped_and_every_intact_chunk_kept(tmp_path, where):
    from afm_ros.formats.mcap_io import SessionScan, read_session, recover, scan_session

    path = tmp_path / "session.mcap"
    counts = _session_with_chunks(path)
    chunks = _chunks(path)
    assert len(chunks) > 20
    bad = chunks[len(chunks) // 2]
    # ground truth from the intact file: the messages of that chunk are those logged in its time
    # range (the synthetic log times are unique and increasing)
    in_bad = sum(
        1
        for m in read_session(path)
        if bad.message_start_time <= m.log_time <= bad.message_end_time
    )
    assert in_bad > 0
    # a flipped bit in the compressed messages (the chunk CRC catches it), or in the chunk's length
    # field (the record boundary is lost: the reader must find the next record)
    _flip(path, bad.chunk_start_offset + (bad.chunk_length // 2 if where == "payload" else 8))
    scan = SessionScan(path)
    got = sum(1 for _ in read_session(path, scan))
    assert not scan.complete and len(scan.damaged) == 1
    assert scan.damaged[0][0] == bad.chunk_start_offset
    # exactly the damaged chunk's messages are missing: every other chunk, before and after, is
    # read
    assert scan.chunks == len(chunks) - 1
    assert got == sum(counts.values()) - in_bad
    if where == "payload":  # the chunk's message index follows it intact and says what was lost
        assert scan.skipped_messages == in_bad
    assert (
        "damaged" in scan.truncated_reason and str(bad.chunk_start_offset) in scan.truncated_reason
    )
    # recover keeps every intact chunk after the damage too
    out = tmp_path / "recovered.mcap"
    result = recover(path, out)
    assert result.messages == got
    rec = scan_session(out)
    assert rec.complete and sum(rec.message_counts.values()) == got


def test_fifo_is_refused_by_every_reader(tmp_path):
    from afm_ros.formats.mcap_io import SessionFileError, read_session

    fifo = tmp_path / "session.mcap"
    os.mkfifo(fifo)
    with pytest.raises(SessionFileError, match="FIFO"):
        next(read_session(fifo))
    for cmd in (
        ["afm_report", str(fifo)],
        ["python", "-m", "afm_ros.formats.mcap_io", "info", str(fifo)],
    ):
        exe = [str(BIN / cmd[0])] + cmd[1:] if cmd[0] != "python" else [sys.executable] + cmd[1:]
        result = subprocess.run(exe, capture_output=True, text=True, timeout=60)
        assert (
            result.returncode != 0 and "FIFO" in result.stderr and "Traceback" not in result.stderr
        )


def test_replay_and_report_warn_about_damage_and_say_what_they_read(
    ros_context, ros_executor, tmp_path, capsys
):
    from afm_ros.nodes.replay_node import ReplayNode
    from afm_ros.tools import report

    path = tmp_path / "session.mcap"
    counts = _session_with_chunks(path)
    bad = _chunks(path)[len(_chunks(path)) // 2]
    _flip(path, bad.chunk_start_offset + bad.chunk_length // 2)
    replay = ReplayNode(
        context=ros_context,
        parameter_overrides=[
            Parameter("file", value=str(path)),
            Parameter("rate", value=1000.0),
            Parameter("start_delay", value=0.0),
            Parameter("topic_prefix", value="/replayed"),
        ],
    )
    ros_executor.add_node(replay)
    spin_until(ros_executor, replay.done.is_set, timeout=60)
    assert replay.error is None
    assert "damaged region" in replay.damage and "messages lost there" in replay.damage
    assert 0 < sum(replay.published.values()) < sum(counts.values())
    # the report reads the intact part and says that the file is damaged
    assert report.main([str(path), "--out", str(tmp_path / "rep")]) == 0
    err = capsys.readouterr().err
    assert "damaged region" in err
    assert "damaged region" in (tmp_path / "rep" / "report.md").read_text()


@pytest.fixture
def small_disk(tmp_path):
    """A 3 MB tmpfs: a disk that fills up during a session (CI runs as root; skipped elsewhere)."""
    mount = tmp_path / "disk"
    mount.mkdir()
    result = subprocess.run(
        ["mount", "-t", "tmpfs", "-o", "size=3m", "tmpfs", str(mount)], capture_output=True
    )
    if result.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {result.stderr.decode().strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", str(mount)], capture_output=True)


@pytest.mark.slow
def test_full_disk_fails_the_job_marks_the_session_incomplete_and_keeps_the_file_readable(
    small_disk,
):
    """A disk that fills during a session (an unbounded --interactive one: a bounded job whose
    session cannot fit is refused before it starts, tested in test_image_job and
    test_executables)."""
    import signal

    from afm_ros.formats.mcap_io import SessionScan, read_session

    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    # ~1 MB per simulated second at the defaults: the 3 MB disk fills up after a few seconds
    proc = subprocess.Popen(
        [
            str(BIN / "afm_instrument"),
            "--interactive",
            "--ideal",
            "--record-raw",
            "--ros-args",
            "-p",
            "real_time_factor:=0.0",
            "-p",
            "recorder:flush_interval:=0.25",
            # the disk is far below the default min_free_space (the recorder would not start)
            "-p",
            "recorder:min_free_space:=0.0",
            # noise-free: noise does not compress, and the byte budget above assumes it does
            "-p",
            "cantilever:temperature:=0.0",
            "-p",
            "cantilever:detector_noise_density:=0.0",
        ],
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        cwd=small_disk,
    )
    import threading
    import time

    err_lines = []
    reader = threading.Thread(target=lambda: err_lines.extend(proc.stderr), daemon=True)
    reader.start()
    deadline = (
        time.monotonic() + 240
    )  # the disk fills after a few simulated seconds, as fast as possible
    while not any(
        "No space left on device" in line for line in list(err_lines)
    ):  # then the loop goes on
        assert time.monotonic() < deadline and proc.poll() is None, "".join(err_lines)[-2000:]
        time.sleep(0.1)
    proc.send_signal(signal.SIGINT)
    out = proc.stdout.read()
    proc.wait(timeout=120)
    reader.join(timeout=30)
    err = "".join(err_lines)
    assert proc.returncode == 1, err
    assert "Traceback" not in err
    assert "No space left on device" in err and "the recording is incomplete" in err
    assert "recording            INCOMPLETE" in out
    # the partial file is readable up to the failure: chunks flushed before it are intact
    path = next(small_disk.glob("afm_runs/*/afm_session_*.mcap"))
    scan = SessionScan(path)
    chunks = [m for m in read_session(path, scan) if m.topic.endswith("cantilever/deflection")]
    assert not scan.complete and scan.truncated_reason
    assert len(chunks) > 100  # more than 0.2 s simulated made it to the disk


def _rss_kb(pid: int) -> int:
    with open(f"/proc/{pid}/status") as f:
        return next(int(line.split()[1]) for line in f if line.startswith("VmRSS:"))


@pytest.mark.slow
def test_long_session_memory_stays_flat(tmp_path):
    """afm_instrument for 60 simulated seconds (as fast as possible, recording): RSS sampled every
    0.5 s of wall time must not grow between the first third of the run and its end (medians of 5 s
    windows), except by the recorder's MCAP chunk index (the file's summary, ~2 KB per chunk; 3 KB
    allowed) and 1.5 MB of allocator noise. The old monitor kept three floats per lock-in output
    (~100 kB per simulated second, 4 MB over the 40 s compared here)."""
    import json
    import time

    from mcap.reader import make_reader

    # a fixed mmap threshold: the recorder's 4 MB chunk buffers go back to the OS when freed
    # instead of raising glibc's heap high-water mark in steps, so RSS measures live memory
    env = {
        **os.environ,
        "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF",
        "MALLOC_MMAP_THRESHOLD_": "262144",
    }
    # --ideal: the engaged start, no imperfections or tip wear (what this bound was calibrated on:
    # the loop and the recorder; the default instrument adds one step of ~3 MB when its worn tip's
    # map is rebuilt)
    proc = subprocess.Popen(
        [
            str(BIN / "afm_instrument"),
            "--duration",
            "60",
            "--json",
            "--ideal",
            "--ros-args",
            "-p",
            "real_time_factor:=0.0",
        ],
        env=env,
        cwd=tmp_path,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )
    samples = []
    while proc.poll() is None:
        try:
            samples.append((time.monotonic(), _rss_kb(proc.pid)))
        except (FileNotFoundError, StopIteration, ProcessLookupError):
            break
        time.sleep(0.5)
    out, _ = proc.communicate(timeout=60)
    assert proc.returncode == 0
    summary = json.loads(out.strip().splitlines()[-1])
    assert summary["simulated_time_s"] >= 60 and summary["lost_samples"] == 0
    assert summary["recording"]["complete"]
    with open(summary["recording"]["file"], "rb") as f:
        chunks = len(make_reader(f).get_summary().chunk_indexes)
    wall = summary["wall_time_s"]
    t_end = samples[-1][0]
    # medians over 5 s windows: the recorder's chunk buffers make RSS swing by +-2-3 MB around a
    # constant level as they are allocated and freed; a leak moves the level
    third = [kb for t, kb in samples if abs(t - (t_end - wall * 2 / 3)) <= 2.5]
    last = [kb for t, kb in samples if t >= t_end - 5.0]
    assert len(third) >= 5 and len(last) >= 5
    growth_kb = float(np.median(last) - np.median(third))
    allowed_kb = 1536 + 3 * chunks * 2 / 3
    assert growth_kb < allowed_kb, (
        f"RSS grew {growth_kb} kB over {wall * 2 / 3:.0f} s ({chunks} MCAP chunks)"
    )


@pytest.mark.parametrize(
    "args,field",
    [
        (["recorder_node", "-p", "chunk_size:=10"], "chunk_size"),
        (["recorder_node", "-p", "flush_interval:=0.01"], "flush_interval"),
        (["replay_node", "-p", "start_delay:=100.0", "-p", "file:=x.mcap"], "start_delay"),
        (["afm_instrument", "-p", "steps_per_period:=10"], "steps_per_period"),
        (["cantilever_node", "--params-file", "/nonexistent/afm.yaml"], "/nonexistent/afm.yaml"),
        (["lockin_node", "--params-file", "MALFORMED"], "params file"),
        (["z_controller_node", "--params-file", "MALFORMED"], "params file"),
        (["recorder_node", "--params-file", "MALFORMED"], "params file"),
        (["afm_instrument", "--params-file", "MALFORMED"], "params file"),
    ],
)
def test_bad_start_values_give_one_line_and_no_traceback(args, field, tmp_path):
    malformed = tmp_path / "bad.yaml"
    malformed.write_text("a: [\n")
    exe, *rest = args
    cmd = [
        str(BIN / exe),
        "--ros-args",
        *[str(malformed) if a == "MALFORMED" else a for a in rest],
    ]
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    result = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=60, cwd=tmp_path)
    assert result.returncode != 0
    assert "Traceback" not in result.stderr, result.stderr
    ours = [
        line
        for line in result.stderr.splitlines()
        if line.startswith(exe.replace("_node", "") + ":") or line.startswith(exe + ":")
    ]
    assert len(ours) == 1 and field in ours[0], result.stderr


def test_an_fm_df_setpoint_of_the_wrong_sign_is_refused_at_the_start_naming_the_field(tmp_path):
    """A positive df is only reached past the df minimum, where the z loop's sign is inverted:
    refused (before, the session started and its approach failed reading 20 Hz as 20 m of
    amplitude)."""
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    result = subprocess.run(
        [
            str(BIN / "afm_instrument"),
            "--fm",
            "--no-record",
            "--ros-args",
            "-p",
            "z_controller:df_setpoint:=20.0",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
    )
    assert result.returncode == 1 and "Traceback" not in result.stderr, result.stderr
    ours = [line for line in result.stderr.splitlines() if line.startswith("afm_instrument:")]
    assert (
        len(ours) == 1
        and "df_setpoint=20.0 Hz is out of range; allowed range [-100000, 0) Hz" in ours[0]
    ), ours
    assert not (tmp_path / "afm_runs").exists()  # a refused start leaves nothing behind
