"""Recording and reading robustness (issue 16): a damaged first chunk, a file cut by one byte, the
replay's exit status, a recorder joining a running instrument, default file names of namespaced
recorders, and the disk budget (max_size, min_free_space).

Real parts only: sessions recorded by the real cantilever / lock-in nodes over DDS into real MCAP
files, read back by this project's readers and by mcap / rosbags; subprocesses (replay_node,
recorder_node, cantilever_node, lockin_node) in its own ROS domain (conftest.DOMAIN_IDS;
LOCALHOST), or with discovery OFF where they need no peer."""

from __future__ import annotations

import datetime as dt
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import rclpy
from conftest import domain_id
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from mcap.reader import make_reader
from mcap.records import Channel, Message
from mcap.stream_reader import breakup_chunk
from rclpy.executors import SingleThreadedExecutor
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from rosgraph_msgs.msg import Clock

from afm_ros.formats import mcap_io
from afm_ros.formats.chunk_layout import cdr_chunk_index
from afm_ros.formats.mcap_io import (
    RecordingError,
    SessionScan,
    read_session,
    recover,
    scan_session,
)
from afm_ros.nodes.cantilever_node import CantileverNode
from afm_ros.nodes.lockin_node import LockInNode
from afm_ros.nodes.recorder_node import RecorderNode

pytestmark = pytest.mark.ros

BIN = Path(sys.executable).parent
DOMAIN_ID = domain_id(__name__)
OUTPUT_RATE = 90e3  # [S/s] 180 samples per 2 ms chunk: light on 2 shared cores
SAMPLES_PER_CHUNK = 180
DEFAULT_SAMPLES_PER_CHUNK = 1800  # at the cantilever's default 900 kS/s
# the chunk publishers' transient-local history (afm_ros.nodes.topics.HISTORY_QOS)
HISTORY_CHUNKS = 200


def spin_until(executor, condition, timeout=60.0, what="condition"):
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, f"{what} not met within {timeout} s"
        executor.spin_once(timeout_sec=0.01)


def chunk_indices(path: Path, suffix: str) -> list[tuple[int, int]]:
    """(first sample index, samples) of every recorded chunk of the topic ending in ``suffix``."""
    return [cdr_chunk_index(m.data) for m in read_session(path) if m.topic.endswith(suffix)]


def gaps(chunks: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """(expected, found) first indices wherever a chunk does not start where the previous one
    ended."""
    return [(a[0] + a[1], b[0]) for a, b in zip(chunks, chunks[1:]) if b[0] != a[0] + a[1]]


class DiagnosticsSink(rclpy.node.Node):
    """Keeps the last /diagnostics status of every name."""

    def __init__(self, ctx, ns):
        super().__init__("diag_sink", context=ctx, namespace=ns)
        self.last: dict[str, DiagnosticStatus] = {}
        self.create_subscription(DiagnosticArray, "/diagnostics", self._on, 100)

    def _on(self, msg):
        for s in msg.status:
            self.last[s.name] = s


def values(status: DiagnosticStatus) -> dict[str, str]:
    return {kv.key: kv.value for kv in status.values}


# --- a real session, then damage -----------------------------------------------------------------


@pytest.fixture(scope="module")
def session(tmp_path_factory):
    """~1 s of cantilever + lock-in recorded with 64 KiB chunks (dozens of MCAP chunks): every
    topic definition is in the first chunk of the data section (and repeated in the summary)."""
    path = tmp_path_factory.mktemp("robust") / "session.mcap"
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    try:
        cantilever = CantileverNode(
            context=ctx,
            namespace="/s",
            parameter_overrides=[Parameter("output_sample_rate", value=OUTPUT_RATE)],
        )
        recorder = RecorderNode(
            context=ctx,
            namespace="/s",
            parameter_overrides=[
                Parameter("output", value=str(path)),
                Parameter("chunk_size", value=64 * 1024),
                Parameter("compression", value="zstd"),
            ],
        )
        for n in (cantilever, LockInNode(context=ctx, namespace="/s"), recorder):
            ex.add_node(n)
        spin_until(
            ex,
            lambda: (
                recorder.streams.get("/s/cantilever/deflection") is not None
                and recorder.streams["/s/cantilever/deflection"].chunks >= 600
            ),
            what="600 recorded chunks",
        )
        ex.remove_node(cantilever)
        cantilever.destroy_node()
        recorder.drain(ex)
    finally:
        for n in list(ex.get_nodes()):
            ex.remove_node(n)
            n.destroy_node()
        ex.shutdown()
        rclpy.try_shutdown(context=ctx)
    return path


def _chunk_indexes(path: Path):
    with open(path, "rb") as f:
        return sorted(
            make_reader(f).get_summary().chunk_indexes, key=lambda c: c.chunk_start_offset
        )


def _records_of_chunk(path: Path, index) -> list:
    with open(path, "rb") as f:
        f.seek(index.chunk_start_offset)
        raw = f.read(index.chunk_length)
    return breakup_chunk(mcap_io._parse(raw[0], raw[9:]), validate_crc=True)


def _flip(path: Path, offset: int) -> None:
    data = bytearray(path.read_bytes())
    data[offset] ^= 0x10
    path.write_bytes(bytes(data))


@pytest.mark.slow
def test_damaged_first_chunk_loses_only_its_own_messages(session, tmp_path, capsys):
    """Issue 16.12: the topic definitions are read from the summary, so one flipped bit in the
    first chunk loses that chunk's messages, nothing else; every reader says which chunk and how
    many."""
    from afm_ros.tools import report

    chunks = _chunk_indexes(session)
    assert len(chunks) > 10
    first = _records_of_chunk(session, chunks[0])
    defl = "/s/cantilever/deflection"
    # the premise: the data section defines the topics only inside the first chunk
    assert any(isinstance(r, Channel) and r.topic == defl for r in first)
    in_first = sum(isinstance(r, Message) for r in first)
    with open(session, "rb") as f:  # counted by the mcap library's reader
        total = sum(1 for _ in make_reader(f).iter_messages())
    assert 0 < in_first < total

    bad = tmp_path / "bad.mcap"
    bad.write_bytes(session.read_bytes())
    _flip(bad, chunks[0].chunk_start_offset + chunks[0].chunk_length // 2)
    scan = SessionScan(bad)
    got = list(read_session(bad, scan))
    assert len(got) == total - in_first, "only the damaged chunk's messages may be missing"
    assert not scan.complete and len(scan.damaged) == 1
    assert scan.damaged[0].chunk == (1, len(chunks)) and scan.damaged[0].messages == in_first
    assert f"chunk 1 of {len(chunks)}" in scan.truncated_reason
    # the deflection stream after the lost chunk is contiguous to the end
    idx = [cdr_chunk_index(m.data) for m in got if m.topic == defl]
    assert len(idx) > 100 and not gaps(idx)

    # info names the chunk and what it held, and does not claim completeness
    assert mcap_io.main(["info", str(bad)]) == 0
    out = capsys.readouterr().out
    assert (
        "complete: no" in out
        and f"chunk 1 of {len(chunks)}" in out
        and f"{in_first} messages lost" in out
    )
    assert f"{total - in_first} read of {total}" in out

    # recover keeps every other message
    result = recover(bad, tmp_path / "recovered.mcap")
    assert (
        result.messages == total - in_first and scan_session(tmp_path / "recovered.mcap").complete
    )

    # the report reads the rest: traces drawn, the damage named
    assert report.main([str(bad), "--out", str(tmp_path / "rep")]) == 0
    assert (tmp_path / "rep" / "deflection_force.png").is_file()
    assert f"chunk 1 of {len(chunks)}" in (tmp_path / "rep" / "report.md").read_text()


@pytest.mark.slow
def test_a_file_missing_its_last_byte_is_not_complete(session, tmp_path, capsys):
    """Issue 16.18: the closing magic is part of a complete file."""
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(session.read_bytes()[:-1])
    scan = scan_session(cut)
    assert not scan.complete and "truncated" in scan.truncated_reason
    assert (
        scan.all_read and scan.message_counts == scan_session(session).message_counts
    )  # every record intact
    assert mcap_io.main(["info", str(cut)]) == 0
    assert "complete: no - the file is truncated" in capsys.readouterr().out


def _replay(path: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    return subprocess.run(
        [
            str(BIN / "replay_node"),
            "--ros-args",
            "-p",
            f"file:={path}",
            "-p",
            "rate:=1000.0",
            "-p",
            "start_delay:=0.0",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )


@pytest.mark.slow
def test_replay_exit_status_says_whether_everything_was_replayed(session, tmp_path):
    """Issue 16.18: 0 = every message replayed, 2 = damaged file, intact part replayed (and what
    was lost is named), 1 = nothing readable (one line naming the file)."""
    ok = _replay(session)
    assert ok.returncode == 0, ok.stderr
    assert "Traceback" not in ok.stderr

    chunks = _chunk_indexes(session)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(session.read_bytes())
    _flip(bad, chunks[0].chunk_start_offset + chunks[0].chunk_length // 2)
    damaged = _replay(bad)
    assert damaged.returncode == 2, damaged.stderr
    last = [line for line in damaged.stderr.splitlines() if "finished" in line][-1]
    assert (
        f"chunk 1 of {len(chunks)}" in last
        and "messages replayed" in last
        and "Traceback" not in damaged.stderr
    )

    every = tmp_path / "all_damaged.mcap"
    every.write_bytes(session.read_bytes())
    for c in chunks:
        _flip(every, c.chunk_start_offset + c.chunk_length // 2)
    nothing = _replay(every)
    assert nothing.returncode == 1, nothing.stderr
    errors = [
        line
        for line in nothing.stderr.splitlines()
        if "[ERROR]" in line or line.startswith("replay: error")
    ]
    assert len(errors) == 1 and str(every) in errors[0] and "Traceback" not in nothing.stderr


# --- a recorder joining a running instrument ----------------------------------------------------


@pytest.fixture
def localhost_context():
    """A context that sees subprocesses on this machine in DOMAIN_ID (set before rclpy.init)."""
    saved = {k: os.environ.get(k) for k in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROS_DOMAIN_ID")}
    os.environ.update({"ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": DOMAIN_ID})
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        yield ctx
    finally:
        rclpy.try_shutdown(context=ctx)
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@pytest.mark.slow
def test_recorder_joining_a_running_instrument_starts_clean(localhost_context, tmp_path):
    """Issue 16.11: cantilever and lock-in run as processes, as fast as they can; recorders join
    eight times. Each file's deflection stream is contiguous from its first chunk and begins with
    the publisher's history (200 chunks before the live part), and the recorder reports 0 lost. The
    old recorder let the cantilever run on while the history was still on its way, which pushed
    chunks out of the history before they arrived: holes among the first chunks (about every
    second join). The force stream is published only while subscribed, so a later recorder's force
    history ends where the previous subscriber left: later joins record the deflection only."""
    ns = f"/join{os.getpid()}"
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "LOCALHOST", "ROS_DOMAIN_ID": DOMAIN_ID}
    ros = ["--ros-args", "-r", f"__ns:={ns}"]
    # the default 900 kS/s: a history of 200 chunks of 1800 samples is 2.9 MB on its way to the
    # recorder
    procs = [
        subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        for cmd in (
            [str(BIN / "cantilever_node"), *ros, "-p", "real_time_factor:=0.0"],
            [str(BIN / "lockin_node"), *ros],
        )
    ]
    ctx = localhost_context
    ex = SingleThreadedExecutor(context=ctx)
    sink = DiagnosticsSink(ctx, ns)
    clock = []
    sink.create_subscription(
        Clock, f"{ns}/clock", lambda m: clock.append(m.clock.sec + 1e-9 * m.clock.nanosec), 10
    )
    ex.add_node(sink)
    try:
        # running, with a full history (> 200 chunks = 0.4 s simulated) behind it
        spin_until(
            ex,
            lambda: clock and clock[-1] > 1.0,
            timeout=120,
            what="the instrument running 1 s simulated",
        )
        for k in range(8):
            path = tmp_path / f"late{k}.mcap"
            overrides = [Parameter("output", value=str(path))]
            if k:
                overrides.append(Parameter("exclude", value="cantilever/tip_sample_force"))
            rec = RecorderNode(context=ctx, namespace=ns, parameter_overrides=overrides)
            ex.add_node(rec)
            defl = f"{ns}/cantilever/deflection"
            spin_until(
                ex,
                lambda: defl in rec.streams and rec.streams[defl].chunks >= 3 * HISTORY_CHUNKS,
                timeout=120,
                what=f"join {k}: 600 recorded chunks",
            )
            name = f"{ns}/recorder: recording"
            spin_until(
                ex,
                lambda: (
                    name in sink.last
                    and values(sink.last[name])["file"] == str(path)
                    and int(values(sink.last[name])["messages"]) > 0
                ),
                timeout=30,
                what="the recorder's diagnostics",
            )
            diag = values(sink.last[name])
            ex.remove_node(rec)
            rec.destroy_node()
            # the next recorder has the same name: start it once the cantilever has let this one go
            spin_until(
                ex,
                lambda: (
                    f"{ns}/recorder"
                    not in next(
                        (
                            values(st)["consumers"].split(",")
                            for st in sink.last.values()
                            if "consumers" in values(st)
                        ),
                        [f"{ns}/recorder"],
                    )
                ),
                timeout=30,
                what="the cantilever letting the recorder go",
            )
            assert diag["lost_samples"] == "0", [
                f"{k}={v}" for k, v in diag.items() if "missing" in k
            ]
            chunks = chunk_indices(path, "cantilever/deflection")
            assert not gaps(chunks), (
                f"join {k}: holes after the first recorded chunk: {gaps(chunks)[:5]}"
            )
            force = chunk_indices(path, "cantilever/tip_sample_force")
            if k == 0:
                assert force and not gaps(force), gaps(force)[:5]
                # the history came first: the force publisher started only when the recorder
                # subscribed, well after the deflection history's first chunk (up to 200 chunks;
                # how much of it lies before the force's start depends on which subscription
                # discovery matched first: 176 seen on a busy machine, so half the history is the
                # bound)
                assert (
                    force[0][0] - chunks[0][0]
                ) / DEFAULT_SAMPLES_PER_CHUNK >= 0.5 * HISTORY_CHUNKS
    finally:
        for p in procs:
            p.send_signal(2)
        for p in procs:
            try:
                p.wait(15)
            except subprocess.TimeoutExpired:
                p.kill()
        ex.shutdown()


def test_a_recorder_of_neither_stream_is_not_waited_for(
    ros_context, ros_executor, ros_namespace, tmp_path
):
    """A recorder of other topics (here the clock only) must not become a consumer the cantilever
    waits for (the old one signed up and never acknowledged: the loop stalled after 32 chunks)."""
    cantilever = CantileverNode(
        context=ros_context,
        namespace=ros_namespace,
        parameter_overrides=[
            Parameter("output_sample_rate", value=OUTPUT_RATE),
            Parameter("real_time_factor", value=0.0),
        ],
    )
    rec = RecorderNode(
        context=ros_context,
        namespace=ros_namespace,
        parameter_overrides=[
            Parameter("output", value=str(tmp_path / "clock.mcap")),
            Parameter("topics", value="clock"),
        ],
    )
    ros_executor.add_node(cantilever)
    ros_executor.add_node(rec)
    name = f"{ros_namespace}/recorder"
    seen = []

    def done():
        seen.append(name in cantilever.consumers)
        return cantilever.samples_published > 400 * SAMPLES_PER_CHUNK

    spin_until(ros_executor, done, timeout=60, what="400 chunks published")
    assert not any(seen) and not cantilever.consumers_dropped


# --- file names
# -----------------------------------------------------------------------------------


def test_default_names_carry_the_namespace_and_never_collide(ros_context, tmp_path, monkeypatch):
    """Issue 16.16: recorders of /afm1 and /afm2 started in the same second write different files,
    and a name already taken gets _2 (never overwritten, never an error)."""
    monkeypatch.chdir(tmp_path)
    now = dt.datetime.now()
    # a file of this name exists for the next two minutes (however slowly the recorders start): the
    # /afm1 recorder must take _2
    for s in range(120):
        mcap_io.default_output_path(now + dt.timedelta(seconds=s), namespace="/afm1").write_bytes(
            b"precious"
        )
    recs = [
        RecorderNode(context=ros_context, namespace=ns) for ns in ("/afm1", "/afm2", "/lab/afm3")
    ]
    try:
        names = [Path(r.output_path).name for r in recs]
        assert names[0].startswith("afm_session_afm1_") and names[0].endswith("_2.mcap"), names
        assert names[1].startswith("afm_session_afm2_") and names[2].startswith(
            "afm_session_lab_afm3_"
        )
        assert all(Path(r.output_path).parent == tmp_path for r in recs)
    finally:
        for r in recs:
            r.destroy_node()
    assert all(scan_session(r.output_path).complete for r in recs)
    taken = [p for p in tmp_path.glob("afm_session_afm1_*.mcap") if not p.name.endswith("_2.mcap")]
    assert len(taken) == 120 and all(p.read_bytes() == b"precious" for p in taken)


def test_output_of_a_namespaced_recorder_from_the_command_line(tmp_path):
    """rcl matches `-p node:param` against the node's full name, so `-p recorder:output:=F` does
    not reach /afm1/recorder; the documented forms do: a params file keyed `/**/recorder` (or
    `/afm1/recorder`), or `-p output:=F` for a recorder_node process."""
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    params = tmp_path / "rec.yaml"
    params.write_text(
        f"/**/recorder:\n  ros__parameters:\n    output: {tmp_path / 'by_file.mcap'}\n"
    )
    for args, out in (
        (["--params-file", str(params)], tmp_path / "by_file.mcap"),
        (["-p", f"output:={tmp_path / 'by_p.mcap'}"], tmp_path / "by_p.mcap"),
    ):
        proc = subprocess.Popen(
            [str(BIN / "recorder_node"), "--ros-args", "-r", "__ns:=/afm1", *args],
            env=env,
            cwd=tmp_path,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        try:
            line = proc.stdout.readline()
        finally:
            proc.send_signal(2)
            rest = proc.communicate(timeout=30)[0]
        assert proc.returncode == 0, line + rest
        assert f"recording to {out}" in line and scan_session(out).complete


# --- disk budget
# ----------------------------------------------------------------------------------


@pytest.mark.slow
def test_max_size_closes_a_complete_file_and_the_loop_goes_on(
    ros_context, ros_executor, ros_namespace, tmp_path
):
    """Issue 16.4: at max_size the recorder closes the file complete (within the budget, readable
    by mcap and rosbags), says why on /diagnostics and in one log line, leaves the flow control,
    and the cantilever and lock-in go on."""
    ns = ros_namespace
    path = tmp_path / "budget.mcap"
    # [B] ~1.9 s simulated at 90 kS/s deflection + force (the rate needs 1 s wall of samples first)
    max_size = 3.0e6
    cantilever = CantileverNode(
        context=ros_context,
        namespace=ns,
        parameter_overrides=[Parameter("output_sample_rate", value=OUTPUT_RATE)],
    )
    lockin = LockInNode(context=ros_context, namespace=ns)
    rec = RecorderNode(
        context=ros_context,
        namespace=ns,
        parameter_overrides=[
            Parameter("output", value=str(path)),
            Parameter("max_size", value=max_size),
            Parameter("flush_interval", value=0.1),
        ],
    )
    sink = DiagnosticsSink(ros_context, ns)
    for n in (cantilever, lockin, rec, sink):
        ros_executor.add_node(n)
    defl = f"{ns}/cantilever/deflection"
    spin_until(
        ros_executor,
        lambda: rec.write_rate()[1] is not None,
        timeout=60,
        what="a measured write rate",
    )
    per_wall, per_sim = rec.write_rate()
    assert per_wall > 0 and per_sim > 0
    spin_until(ros_executor, lambda: rec.budget_reached, timeout=120, what="max_size reached")
    stopped_at = rec.streams[defl].next_index
    # the loop goes on without the recorder: the lock-in keeps taking chunks (2 s simulated more)
    spin_until(
        ros_executor,
        lambda: lockin.acknowledged_index > stopped_at + 1000 * SAMPLES_PER_CHUNK,
        timeout=120,
        what="the lock-in going on after the stop",
    )
    assert f"{ns}/recorder" not in cantilever.consumers
    name = f"{ns}/recorder: recording"
    spin_until(
        ros_executor,
        lambda: name in sink.last and "max_size" in sink.last[name].message,
        timeout=30,
        what="diagnostics naming max_size",
    )
    status = sink.last[name]
    assert status.level == DiagnosticStatus.WARN and "complete up to there" in status.message
    assert "raise max_size" in rec.stopped_reason and str(path) in rec.stopped_reason
    # a new limit after the stop is refused with the reason (the file is closed)
    client = AsyncParameterClient(sink, f"{ns}/recorder")
    assert client.wait_for_services(10.0)
    future = client.set_parameters([Parameter("max_size", value=1e9)])
    spin_until(ros_executor, future.done, timeout=10)
    assert (
        not future.result().results[0].successful
        and "stopped" in future.result().results[0].reason
    )

    size = path.stat().st_size
    assert rec.bytes_written == size and int(values(status)["bytes_written"]) == size
    assert 0.9 * max_size <= size <= max_size, (
        size
    )  # stops within 1 % (+ the last chunk's compression bound)
    scan = scan_session(path)
    assert scan.complete
    chunks = chunk_indices(path, "cantilever/deflection")
    assert chunks and not gaps(chunks) and chunks[-1][0] + chunks[-1][1] == stopped_at
    # the rate measured by the recorder vs the file: bytes per simulated second of the recording
    span = (chunks[-1][0] + chunks[-1][1] - chunks[0][0]) / OUTPUT_RATE
    assert 0.75 < per_sim / (size / span) < 1.33, (
        per_sim,
        size / span,
    )  # the start (schemas, snapshots) is out of the 1 s window
    with open(path, "rb") as f:
        summary = make_reader(f).get_summary()
    assert summary.statistics.message_count == scan.messages_read
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    with AnyReader([path], default_typestore=get_typestore(Stores.EMPTY)) as reader:
        n = sum(
            1
            for conn, _, raw in reader.messages()
            if reader.deserialize(raw, conn.msgtype) is not None
        )
    assert n == scan.messages_read


def test_min_free_space_above_the_free_space_refuses_to_start(ros_context, tmp_path):
    free = mcap_io.free_space(tmp_path)
    path = tmp_path / "never.mcap"
    with pytest.raises(RecordingError, match="min_free_space"):
        RecorderNode(
            context=ros_context,
            parameter_overrides=[
                Parameter("output", value=str(path)),
                Parameter("min_free_space", value=float(free) * 2),
            ],
        )
    assert not path.exists()
    env = {**os.environ, "ROS_AUTOMATIC_DISCOVERY_RANGE": "OFF"}
    result = subprocess.run(
        [
            str(BIN / "recorder_node"),
            "--ros-args",
            "-p",
            f"output:={path}",
            "-p",
            f"min_free_space:={float(free) * 2:.6g}",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 1 and "Traceback" not in result.stderr
    ours = [line for line in result.stderr.splitlines() if line.startswith("recorder:")]
    assert len(ours) == 1 and "min_free_space" in ours[0] and "B free" in ours[0], result.stderr
    assert not path.exists()


@pytest.mark.slow
def test_min_free_space_raised_live_stops_a_running_recording(
    ros_context, ros_executor, ros_namespace, tmp_path
):
    """The budget is live: min_free_space set to 4 MB below the free space of the disk stops the
    recording (file complete) after at most that much more (less if others write on the disk). The
    4 MB count from the size the file would have if closed when the limit is set (its open chunk
    and summary included: the file's size on disk then lags by up to one compressed chunk)."""
    ns = ros_namespace
    path = tmp_path / "free.mcap"
    cantilever = CantileverNode(
        context=ros_context,
        namespace=ns,
        parameter_overrides=[Parameter("output_sample_rate", value=OUTPUT_RATE)],
    )
    rec = RecorderNode(
        context=ros_context,
        namespace=ns,
        parameter_overrides=[
            Parameter("output", value=str(path)),
            Parameter("flush_interval", value=0.1),
        ],
    )
    sink = DiagnosticsSink(ros_context, ns)
    for n in (cantilever, rec, sink):
        ros_executor.add_node(n)
    defl = f"{ns}/cantilever/deflection"
    spin_until(
        ros_executor,
        lambda: defl in rec.streams and rec.streams[defl].chunks > 50,
        what="recording",
    )
    client = AsyncParameterClient(sink, f"{ns}/recorder")
    assert client.wait_for_services(10.0)
    before = rec.writer.size_bound(0)
    limit = mcap_io.free_space(tmp_path) - 4e6
    future = client.set_parameters([Parameter("min_free_space", value=float(limit))])
    spin_until(ros_executor, future.done, timeout=10)
    assert future.result().results[0].successful, future.result().results[0].reason
    spin_until(
        ros_executor, lambda: rec.budget_reached, timeout=120, what="min_free_space reached"
    )
    assert "min_free_space" in rec.stopped_reason and "free disk space" in rec.stopped_reason
    assert scan_session(path).complete and path.stat().st_size - before < 4e6
    assert not gaps(chunk_indices(path, "cantilever/deflection"))
