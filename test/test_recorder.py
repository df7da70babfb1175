"""The recorder over real DDS into real MCAP files, read back with readers this project did not
write.

- in-process: the real cantilever node + recorder in a private context (discovery OFF, see
  conftest.py); the file is decoded by mcap_ros2 and by rosbags with an *empty* type store
  (so our schema text alone must define every type), and compared with what was published;
- subprocesses (LOCALHOST discovery, this file's own ROS domain, conftest.DOMAIN_IDS): SIGKILL and
  SIGTERM of a recording, and a recorder whose file size limit runs out (the kernel's EFBIG, as a
  full disk gives ENOSPC);
- bad output paths.
"""

from __future__ import annotations

import os
import resource
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import yaml
from conftest import domain_id
from mcap.reader import make_reader
from mcap_ros2.decoder import DecoderFactory
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient

from afm_ros.formats import mcap_io
from afm_ros.formats.chunk_layout import unpack
from afm_ros.formats.mcap_io import RecordingError, read_session, recover, scan_session
from afm_ros.nodes.cantilever_node import CantileverNode
from afm_ros.nodes.recorder_node import RecorderNode

pytestmark = pytest.mark.ros

VENV_BIN = Path(sys.executable).parent
DOMAIN_ID = domain_id(__name__)
OUTPUT_RATE = 90e3  # [S/s] decimated output keeps the in-process test light on 2 cores


def spin_for(executor, seconds):
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        executor.spin_once(timeout_sec=0.01)


def spin_until(executor, condition, timeout=20.0):
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, f"condition not met within {timeout} s"
        executor.spin_once(timeout_sec=0.01)


def chunk_stream(messages):
    """(sample indices, samples) concatenated from chunk messages (rclpy-decoded)."""
    idx, vals = [], []
    for m in messages:
        header, samples = unpack(mcap_io.decode(m).data)
        idx.append(header.first_sample_index + np.arange(samples.shape[0]))
        vals.append(samples)
    return np.concatenate(idx), np.concatenate(vals)


@pytest.mark.slow
def test_round_trip_with_foreign_readers(ros_context, ros_executor, ros_namespace, tmp_path):
    ns = ros_namespace
    path = tmp_path / "session.mcap"
    cantilever = CantileverNode(
        context=ros_context,
        namespace=ns,
        parameter_overrides=[Parameter("output_sample_rate", value=OUTPUT_RATE)],
    )
    ros_executor.add_node(cantilever)
    # default topic selection (everything) apart from the output path
    recorder = RecorderNode(
        context=ros_context,
        namespace=ns,
        parameter_overrides=[Parameter("output", value=str(path))],
    )
    ros_executor.add_node(recorder)
    defl, force = f"{ns}/cantilever/deflection", f"{ns}/cantilever/tip_sample_force"
    spin_until(ros_executor, lambda: recorder.received.get(defl, 0) > 0)
    # the publisher's view of the topic, an independent source for QoS depth and type hash
    pub_info = {i.node_name: i for i in recorder.get_publishers_info_by_topic(defl)}["cantilever"]
    spin_for(ros_executor, 0.7)

    # a live parameter change (what `ros2 param set` does) must land in the record
    client = AsyncParameterClient(recorder, f"{ns}/cantilever")
    assert client.wait_for_services(5.0)
    future = client.set_parameters([Parameter("z_base", value=35e-9)])
    spin_until(ros_executor, future.done)
    assert future.result().results[0].successful
    spin_for(ros_executor, 0.7)

    # stop the source first (its last booked chunk is still published), let the recorder write
    # everything, then close (what SIGINT does)
    ros_executor.remove_node(cantilever)
    cantilever_params = {
        name: p.value for name, p in cantilever.get_parameters_by_prefix("").items()
    }
    cantilever.destroy_node()
    published = cantilever.samples_published
    spin_until(ros_executor, lambda: recorder.streams[defl].next_index == published)
    recorder.drain(ros_executor)
    received = dict(recorder.received)
    ros_executor.remove_node(recorder)
    recorder.destroy_node()

    # --- the file as the mcap library's seeking reader sees it: complete with summary -----------
    with open(path, "rb") as f:
        reader = make_reader(f, decoder_factories=[DecoderFactory()])
        header = reader.get_header()
        summary = reader.get_summary()
        assert header.profile == "ros2"
        assert "afm_ros" in header.library
        counts = {
            summary.channels[cid].topic: n
            for cid, n in summary.statistics.channel_message_counts.items()
        }
        for topic in (
            defl,
            force,
            defl.replace("cantilever/deflection", "clock"),
            "/parameter_events",
        ):
            assert topic in counts, f"{topic} not recorded (default = all topics)"
        # every message the recorder counted is in the file (+ the recorder's own parameter
        # snapshots)
        for topic, n in received.items():
            assert counts.get(topic, 0) >= n
        for schema in summary.schemas.values():
            assert schema.encoding == "ros2msg"
            assert schema.name.count("/") == 2 and schema.name.split("/")[1] == "msg"
        for channel in summary.channels.values():
            assert channel.message_encoding == "cdr"
            profiles = yaml.safe_load(channel.metadata["offered_qos_profiles"])
            assert isinstance(profiles, list) and profiles, channel.topic
            assert {
                "history",
                "depth",
                "reliability",
                "durability",
                "deadline",
                "lifespan",
                "liveliness",
                "liveliness_lease_duration",
                "avoid_ros_namespace_conventions",
            } <= set(profiles[0])
        chunk_channel = next(c for c in summary.channels.values() if c.topic == defl)
        profile = yaml.safe_load(chunk_channel.metadata["offered_qos_profiles"])[0]
        assert (
            profile["reliability"] == "reliable" and profile["depth"] == pub_info.qos_profile.depth
        )
        assert chunk_channel.metadata["topic_type_hash"] == str(pub_info.topic_type_hash)
        schema = summary.schemas[chunk_channel.schema_id]
        text = schema.data.decode()
        # top-level definition first, then each dependency once behind the rosbag2 delimiter
        msg_file = (
            Path(os.environ.get("VIRTUAL_ENV", VENV_BIN.parent))
            / "share/std_msgs/msg/Float64MultiArray.msg"
        )
        assert text.startswith(msg_file.read_text())
        for dep in ("std_msgs/MultiArrayLayout", "std_msgs/MultiArrayDimension"):
            assert text.count("\n" + "=" * 80 + "\nMSG: " + dep + "\n") == 1

        # every message decodes with mcap_ros2's decoder (built from our schema text)
        n_decoded = 0
        mcap_ros2_chunks = []
        for _, channel, _, decoded in reader.iter_decoded_messages():
            n_decoded += 1
            if channel.topic == defl:
                mcap_ros2_chunks.append(np.asarray(decoded.data))
        assert n_decoded == summary.statistics.message_count

    # --- rosbags with an EMPTY type store: types come only from the schemas in the file ------
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    n_rosbags = 0
    rosbags_chunks = []
    with AnyReader([path], default_typestore=get_typestore(Stores.EMPTY)) as areader:
        for conn, _, raw in areader.messages():
            msg = areader.deserialize(raw, conn.msgtype)
            n_rosbags += 1
            if conn.topic == defl:
                rosbags_chunks.append(np.asarray(msg.data))
    assert n_rosbags == n_decoded

    # --- the deflection stream: no gap, nothing lost, identical through every reader ---------
    messages = [m for m in read_session(path) if m.topic == defl]
    idx, samples = chunk_stream(messages)
    assert idx[0] == 0 and np.array_equal(idx, np.arange(idx.shape[0])), (
        "gap or duplicate in sample indices"
    )
    assert idx.shape[0] == published, "recorded samples differ from what the cantilever published"
    for a, b, c in zip(
        mcap_ros2_chunks, rosbags_chunks, (np.asarray(mcap_io.decode(m).data) for m in messages)
    ):
        assert np.array_equal(a, c) and np.array_equal(b, c)
    # log_time = receive time >= publish_time = source timestamp (same wall clock, same host)
    assert all(m.publish_time <= m.log_time for m in messages)
    assert any(m.publish_time < m.log_time for m in messages), (
        "publish_time is not the source timestamp"
    )

    # --- parameters: full initial set of the cantilever, and the later change ----------------
    scan = scan_session(path)
    snap = mcap_io.parameter_metadata(scan)[f"{ns}/cantilever"]
    assert set(snap) == set(cantilever_params)
    events = [mcap_io.decode(m) for m in read_session(path) if m.topic == "/parameter_events"]
    initial = next(e for e in events if e.node == f"{ns}/cantilever" and e.new_parameters)
    values = {p.name: p.value for p in initial.new_parameters}
    assert set(values) == set(cantilever_params)
    assert values["output_sample_rate"].double_value == OUTPUT_RATE
    changes = [p for e in events if e.node == f"{ns}/cantilever" for p in e.changed_parameters]
    assert any(p.name == "z_base" and p.value.double_value == 35e-9 for p in changes)


def _env():
    env = dict(
        os.environ,
        ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST",
        ROS_DOMAIN_ID=DOMAIN_ID,
        PYTHONUNBUFFERED="1",
    )
    return env


# Another run of this file at the same time (same domain id) must not leak into this one: every
# subprocess runs in a namespace unique to this pytest process, and recorders take relative names.
RUN_NS = f"/run{os.getpid()}"


def _start(args, **kw):
    assert args[1] == "--ros-args"
    return subprocess.Popen(
        [str(VENV_BIN / args[0]), "--ros-args", "-r", f"__ns:={RUN_NS}", *args[2:]],
        env=_env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
        **kw,
    )


def _wait_for_growth(path: Path, size: int, timeout=30.0):
    end = time.monotonic() + timeout
    while not (path.exists() and path.stat().st_size > size):
        assert time.monotonic() < end, f"{path} did not grow beyond {size} bytes"
        time.sleep(0.1)


FLUSH_INTERVAL = 0.5  # [s]


@pytest.mark.slow
def test_sigkill_loses_at_most_one_flush_interval_and_sigterm_closes_cleanly(tmp_path):
    killed, termed = tmp_path / "killed.mcap", tmp_path / "termed.mcap"
    topics = "cantilever/deflection,cantilever/tip_sample_force"
    cantilever = _start(
        [
            "cantilever_node",
            "--ros-args",
            "-p",
            f"output_sample_rate:={OUTPUT_RATE}",
            "-p",
            "publish_clock:=false",
        ]
    )
    rec_args = ["-p", f"topics:={topics}", "-p", f"flush_interval:={FLUSH_INTERVAL}"]
    rec_kill = _start(["recorder_node", "--ros-args", "-p", f"output:={killed}", *rec_args])
    rec_term = _start(["recorder_node", "--ros-args", "-p", f"output:={termed}", *rec_args])
    try:
        _wait_for_growth(killed, 50_000)  # zstd shrinks a settled oscillation a lot: a low bar
        _wait_for_growth(termed, 50_000)
        time.sleep(1.3)  # not a multiple of the flush interval: the kill lands mid-interval
        t_kill = time.time_ns()
        rec_kill.send_signal(signal.SIGKILL)
        rec_term.send_signal(signal.SIGTERM)
        assert rec_kill.wait(10) == -signal.SIGKILL
        assert rec_term.wait(10) == 0, rec_term.stdout.read()
    finally:
        cantilever.send_signal(signal.SIGINT)
        try:
            cantilever.wait(10)
        except subprocess.TimeoutExpired:
            cantilever.kill()
        for p in (rec_kill, rec_term):
            if p.poll() is None:
                p.kill()

    # SIGTERM: complete file with summary and index
    with open(termed, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary is not None and summary.statistics.message_count > 0
    assert scan_session(termed).complete

    # SIGKILL: no footer, nothing claims completeness; the tolerant reader and recover agree
    scan = scan_session(killed)
    assert not scan.complete and scan.truncated_reason
    with open(killed, "rb") as f:
        with pytest.raises(Exception):
            make_reader(f).get_summary() or (_ for _ in ()).throw(ValueError("no summary"))
    out = tmp_path / "recovered.mcap"
    assert (
        mcap_io.main(["recover", str(killed), str(tmp_path / "cli.mcap")]) == 0
    )  # the command line
    assert scan_session(tmp_path / "cli.mcap").complete
    result = recover(killed, out)
    assert result.messages == sum(scan.message_counts.values()) > 0
    assert scan_session(out).complete
    messages = [m for m in read_session(out) if m.topic == f"{RUN_NS}/cantilever/deflection"]
    idx, _ = chunk_stream(messages)
    assert np.array_equal(idx, idx[0] + np.arange(idx.shape[0])), "recovered stream has a gap"
    # Loss bound: chunks are closed every FLUSH_INTERVAL of wall time, so the newest recovered
    # message is at most one interval (plus timer jitter of a loaded 2-core machine, 0.3 s)
    # older than the kill.
    lost_s = (t_kill - max(m.log_time for m in messages)) * 1e-9
    assert 0.0 <= lost_s <= FLUSH_INTERVAL + 0.3, f"lost {lost_s:.3f} s of data"
    # the SIGTERM'd recorder saw the same stream up to at least the kill: it also has no gap
    idx_t, _ = chunk_stream(
        [m for m in read_session(termed) if m.topic == f"{RUN_NS}/cantilever/deflection"]
    )
    assert np.array_equal(idx_t, idx_t[0] + np.arange(idx_t.shape[0]))
    assert idx_t[-1] >= idx[-1]


@pytest.mark.slow
def test_write_failure_stops_with_clear_error_and_no_complete_claim(tmp_path):
    """A file size limit (RLIMIT_FSIZE -> EFBIG) fails writes like a full disk (ENOSPC) does."""
    path = tmp_path / "limited.mcap"
    limit = 300_000  # [B] reached within ~1 s of 2 chunk streams at 90 kS/s

    def limit_size():
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # get EFBIG from write() instead of a signal
        resource.setrlimit(resource.RLIMIT_FSIZE, (limit, limit))

    cantilever = _start(
        ["cantilever_node", "--ros-args", "-p", f"output_sample_rate:={OUTPUT_RATE}"]
    )
    rec = _start(
        [
            "recorder_node",
            "--ros-args",
            "-p",
            f"output:={path}",
            "-p",
            "compression:=none",
            "-p",
            "topics:=cantilever/*",
        ],
        preexec_fn=limit_size,
    )
    try:
        code = rec.wait(30)  # exits by itself: no hang
        out = rec.stdout.read()
    finally:
        cantilever.send_signal(signal.SIGINT)
        try:
            cantilever.wait(10)
        except subprocess.TimeoutExpired:
            cantilever.kill()
        if rec.poll() is None:
            rec.kill()
    assert code == 1, out
    assert str(path) in out and "File too large" in out, out
    assert path.stat().st_size <= limit
    scan = scan_session(path)
    assert not scan.complete, "a failed recording must not look complete"
    assert recover(path, tmp_path / "rescued.mcap").messages == sum(scan.message_counts.values())


def test_bad_output_paths(ros_context, tmp_path):
    missing_dir = tmp_path / "no_such_dir" / "s.mcap"
    with pytest.raises(RecordingError, match=str(missing_dir.parent)):
        RecorderNode(
            context=ros_context, parameter_overrides=[Parameter("output", value=str(missing_dir))]
        )
    assert not missing_dir.exists()

    a_file = tmp_path / "plain_file"
    a_file.write_text("not a directory")
    with pytest.raises(RecordingError, match="not a directory"):
        RecorderNode(
            context=ros_context,
            parameter_overrides=[Parameter("output", value=str(a_file / "s.mcap"))],
        )

    existing = tmp_path / "existing.mcap"
    existing.write_bytes(b"precious")
    recorder = RecorderNode(
        context=ros_context, parameter_overrides=[Parameter("output", value=str(existing))]
    )
    recorder.destroy_node()
    assert existing.read_bytes() == b"precious", "an existing file must never be overwritten"
    assert (
        recorder.output_path == str(tmp_path / "existing_2.mcap")
        and scan_session(recorder.output_path).complete
    )

    with pytest.raises(Exception, match="compression"):
        RecorderNode(
            context=ros_context,
            parameter_overrides=[
                Parameter("output", value=str(tmp_path / "x.mcap")),
                Parameter("compression", value="gzip"),
            ],
        )
    assert not (tmp_path / "x.mcap").exists()

    # the executable reports the path and exits non-zero instead of hanging
    proc = subprocess.run(
        [str(VENV_BIN / "recorder_node"), "--ros-args", "-p", f"output:={missing_dir}"],
        env=_env(),
        capture_output=True,
        text=True,
        timeout=30,
    )
    assert proc.returncode == 1 and str(missing_dir.parent) in proc.stderr


def test_default_output_is_timestamped_in_cwd(ros_context, tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    recorder = RecorderNode(context=ros_context)
    try:
        assert Path(recorder.output_path).parent == tmp_path
        assert Path(recorder.output_path).name.startswith("afm_session_")
    finally:
        recorder.destroy_node()
    assert scan_session(recorder.output_path).complete


def test_records_under_the_events_executor(ros_context, ros_namespace, tmp_path):
    """afm_instrument spins everything on rclpy's EventsExecutor: the recorder must work there
    too."""
    from rclpy.experimental import EventsExecutor

    ex = EventsExecutor(context=ros_context)
    path = tmp_path / "events.mcap"
    cantilever = CantileverNode(
        context=ros_context,
        namespace=ros_namespace,
        parameter_overrides=[Parameter("output_sample_rate", value=OUTPUT_RATE)],
    )
    recorder = RecorderNode(
        context=ros_context,
        namespace=ros_namespace,
        parameter_overrides=[
            Parameter("output", value=str(path)),
            Parameter("topics", value="cantilever/deflection"),
        ],
    )
    try:
        ex.add_node(cantilever)
        ex.add_node(recorder)
        spin_for(ex, 1.0)
        ex.remove_node(cantilever)
        cantilever.destroy_node()
        published = cantilever.samples_published
        topic = f"{ros_namespace}/cantilever/deflection"
        spin_until(
            ex,
            lambda: topic in recorder.streams and recorder.streams[topic].next_index == published,
        )
        ex.remove_node(recorder)
        recorder.destroy_node()
    finally:
        ex.shutdown()
    idx, _ = chunk_stream(
        [m for m in read_session(path) if m.topic.endswith("cantilever/deflection")]
    )
    assert scan_session(path).complete
    assert np.array_equal(idx, np.arange(idx.size)) and idx.size == published


@pytest.mark.parametrize(
    "type_name",
    [
        "geometry_msgs/msg/Vector3Stamped",
        "rcl_interfaces/msg/ParameterEvent",
        "diagnostic_msgs/msg/DiagnosticArray",
        "rosgraph_msgs/msg/Clock",
    ],
)
def test_schema_text_follows_rosbag2_and_defines_every_type(type_name):
    """No DDS: the schema text of the types the instrument publishes, checked against rosbag2's
    rule (root text, then each dependency depth first behind '=' * 80 + 'MSG: pkg/Type') and
    against the field definitions rosbags ships for ROS 2 Jazzy (an independent source)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    text = mcap_io.message_definition(type_name)
    pkg, _, name = type_name.split("/")
    share = Path(os.environ.get("VIRTUAL_ENV", VENV_BIN.parent)) / "share"
    blocks = text.split("\n" + "=" * 80 + "\n")
    assert blocks[0] == (share / pkg / "msg" / f"{name}.msg").read_text()
    deps = []
    for block in blocks[1:]:
        head, _, body = block.partition("\n")
        assert head.startswith("MSG: ") and head.count("/") == 1  # rosbag2 writes 'pkg/Type'
        dep_pkg, dep_name = head[5:].split("/")
        assert body == (share / dep_pkg / "msg" / f"{dep_name}.msg").read_text()
        deps.append(head[5:])
    assert len(deps) == len(set(deps)), "a dependency appears twice"
    if type_name == "geometry_msgs/msg/Vector3Stamped":
        # root's dependencies in byte order, each followed by its own (Header -> Time)
        assert deps == ["geometry_msgs/Vector3", "std_msgs/Header", "builtin_interfaces/Time"]
    parsed = get_types_from_msg(text, type_name)
    reference = get_typestore(Stores.ROS2_JAZZY).fielddefs
    for t, definition in parsed.items():
        assert definition[1] == reference[t][1], t

    # every dependency of the reference definition is in the text
    def closure(t, seen):
        for _, (kind, spec) in reference[t][1]:
            sub = (
                spec
                if isinstance(spec, str)
                else (spec[0][1] if isinstance(spec[0], tuple) else spec[0])
            )
            if isinstance(sub, str) and "/" in sub and sub not in seen:
                seen.add(sub)
                closure(sub, seen)
        return seen

    assert closure(type_name, set()) <= set(parsed)
