"""The scanner node checks what a scan needs before it starts, keeps what a stopped scan made, and
says the truth on /diagnostics (issue 16, points 2, 13, 14, 18), over real DDS in one process
(discovery confined, see conftest), through its real services and parameter service.

- scanner/scan_frame is refused (success False, the reason in the answer) when the lock-in's
  output_rate cannot give every pixel an output (it used to run the whole frame and then refuse
  to write it), when the frame buffers would not fit in memory, when the lock-in is unknown, and
  when output_directory cannot be written; a change of the lock-in's output_rate reaches the
  scanner through /parameter_events.
- output_directory: a regular file or a chain of missing folders is refused when the parameter is
  set; a missing last level is created when the scan starts.
- A scan stopped after some lines writes them as a partial frame (cropped to the completed lines,
  with their real y size and offset, marked partial in the metadata and the file name), equal bit
  for bit to the same lines of the same scan done by the wired cores; scanner/stop does so by
  default.
- A failed frame write shows on /diagnostics and is cleared by a later successful one (the count
  of failed frames stays).
"""

from __future__ import annotations

import json
import os
import time

import gwyfile
import numpy as np
import pytest
from conftest import EXACT_PHYSICS
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus
from rclpy.node import Node
from rclpy.parameter import Parameter
from rclpy.parameter_client import AsyncParameterClient
from std_srvs.srv import Trigger

from afm_ros.core.artefacts import INSTRUMENT_ARTEFACTS
from afm_ros.core.imaging import CHANNELS, DIRECTIONS, Frame
from afm_ros.core.samples import resolve_sample
from afm_ros.core.scanner import ScanPlan
from afm_ros.core.tip import INSTRUMENT_TIP
from afm_ros.core.wired import WiredInstrument
from afm_ros.formats.frames import channel_title
from afm_ros.nodes.cantilever_node import CantileverNode
from afm_ros.nodes.lockin_node import LockInNode
from afm_ros.nodes.scanner_node import ScannerNode
from afm_ros.nodes.z_controller_node import ZControllerNode

pytestmark = pytest.mark.ros

CANTILEVER = {**EXACT_PHYSICS, "force_model": "viscoelastic_dmt", "sample": "ps_ldpe_blend"}
SCAN = dict(
    scan_size_x=5e-6,
    scan_size_y=5e-6,
    scan_center_x=5e-6,
    scan_center_y=5e-6,
    pixels_per_line=16,
    lines=8,
    line_rate=10.0,
)
ENGAGE = 0.05  # [s] simulated before the scan starts


def spin_until(executor, condition, timeout=120.0):
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, "condition not met in time"
        executor.spin_once(timeout_sec=0.01)


def call(executor, client, timeout=60.0):
    """Call a std_srvs/Trigger service through DDS; its response."""
    spin_until(executor, client.service_is_ready, timeout)
    future = client.call_async(Trigger.Request())
    spin_until(executor, future.done, timeout)
    return future.result()


def set_param(executor, client: AsyncParameterClient, name, value):
    spin_until(executor, client.services_are_ready, 60)
    future = client.set_parameters([Parameter(name, value=value)])
    spin_until(executor, future.done, 60)
    return future.result().results[0]


@pytest.fixture
def rig(ros_context, ros_executor, ros_namespace, tmp_path):
    """A scanner and a lock-in (no cantilever: nothing is scanned) and a user's clients."""
    lockin = LockInNode(context=ros_context, namespace=ros_namespace)
    scanner = ScannerNode(
        context=ros_context,
        namespace=ros_namespace,
        parameter_overrides=[Parameter("output_directory", value=str(tmp_path / "frames"))],
    )
    user = Node("user", context=ros_context, namespace=ros_namespace)
    for n in (lockin, scanner, user):
        ros_executor.add_node(n)
    clients = {
        "scan_frame": user.create_client(Trigger, "scanner/scan_frame"),
        "stop": user.create_client(Trigger, "scanner/stop"),
        "scanner": AsyncParameterClient(user, "scanner"),
        "lockin": AsyncParameterClient(user, "lockin"),
    }
    spin_until(ros_executor, lambda: scanner.lockin_output_rate == 1000.0, 60)
    return scanner, lockin, clients, ros_executor


def test_pixels_beyond_the_lockin_rate_are_refused_before_the_scan(rig):
    scanner, lockin, c, ex = rig
    assert set_param(ex, c["scanner"], "pixels_per_line", 1000).successful
    answer = call(ex, c["scan_frame"])
    assert not answer.success
    for words in ("pixels_per_line=1000", "output_rate=1000 Hz", "[2, 499]", "line_rate"):
        assert words in answer.message, answer.message
    assert scanner.state == "idle"
    # the lock-in's new rate reaches the scanner through /parameter_events; then the scan may start
    assert set_param(ex, c["lockin"], "output_rate", 2500.0).successful
    spin_until(ex, lambda: scanner.lockin_output_rate == 2500.0, 30)
    answer = call(ex, c["scan_frame"])
    assert answer.success, answer.message
    assert scanner.state == "requested"
    assert call(ex, c["stop"]).success


def test_a_frame_too_big_for_memory_is_refused(rig):
    scanner, _, c, ex = rig
    for name, value in (("pixels_per_line", 4096), ("lines", 4096), ("line_rate", 0.1)):
        assert set_param(ex, c["scanner"], name, value).successful
    answer = call(ex, c["scan_frame"])
    assert not answer.success
    assert "pixels_per_line=4096 x lines=4096" in answer.message and "GiB" in answer.message, (
        answer.message
    )
    assert scanner.state == "idle"


def test_without_a_lockin_the_scan_is_refused(ros_context, ros_executor, ros_namespace, tmp_path):
    scanner = ScannerNode(
        context=ros_context,
        namespace=ros_namespace,
        parameter_overrides=[Parameter("output_directory", value=str(tmp_path))],
    )
    user = Node("user", context=ros_context, namespace=ros_namespace)
    for n in (scanner, user):
        ros_executor.add_node(n)
    answer = call(ros_executor, user.create_client(Trigger, "scanner/scan_frame"))
    assert not answer.success
    assert f"{ros_namespace}/lockin" in answer.message and "not reachable" in answer.message, (
        answer.message
    )


def test_output_directory_is_checked_when_set_and_at_the_scan_start(rig, tmp_path):
    scanner, _, c, ex = rig
    a_file = tmp_path / "a_file"
    a_file.write_text("x")
    before = scanner.get_parameter("output_directory").value
    for value, words in (
        (str(a_file), "is a file"),
        (str(tmp_path / "no" / "such" / "chain"), "does not exist"),
        ("/afm_ros_test_folder_at_the_root", "file-system root"),
    ):
        result = set_param(ex, c["scanner"], "output_directory", value)
        assert (
            not result.successful
            and "output_directory=" in result.reason
            and words in result.reason
        ), result.reason
        assert scanner.get_parameter("output_directory").value == before
    assert not os.path.exists("/afm_ros_test_folder_at_the_root")
    # a folder nobody can write to (root can: then a read-only file system)
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o555)
    if os.access(locked, os.W_OK):
        locked = "/sys" if os.path.isdir("/sys") else None
    if locked is not None:
        assert set_param(
            ex, c["scanner"], "output_directory", str(locked)
        ).successful  # may become writable
        answer = call(ex, c["scan_frame"])
        assert (
            not answer.success
            and "output_directory=" in answer.message
            and "cannot write" in answer.message
        ), answer.message
        assert scanner.state == "idle"
    # a new last level is made when the scan starts
    new = tmp_path / "new_run"
    assert set_param(ex, c["scanner"], "output_directory", str(new)).successful
    assert not new.exists()
    answer = call(ex, c["scan_frame"])
    assert answer.success, answer.message
    assert new.is_dir()


def test_completed_part_of_a_frame_keeps_its_rows_and_geometry():
    """Frame.completed: the completed acquisition lines only, with the y size and offset of those
    rows, for both slow-scan directions (down: the first lines are the highest rows)."""
    for direction in ("up", "down"):
        plan = ScanPlan.from_values({**SCAN, "slow_scan_direction": direction})
        frame = Frame.empty(plan, 2)
        done = 3
        for line in range(done):
            for d in DIRECTIONS:
                for ch in CHANNELS:
                    frame.images[d][ch][plan.row_of_line(line)] = 100 * line + np.arange(
                        plan.pixels
                    )
        frame.lines_done = done
        part = frame.completed()
        assert part.partial and part.info() == {
            "partial": True,
            "lines_done": 3,
            "lines_planned": 8,
        }
        assert part.plan.lines == done
        assert part.plan.size_y == pytest.approx(done * plan.line_pitch, rel=1e-12, abs=0)
        rows = [plan.row_of_line(k) for k in range(done)]
        assert part.plan.y_low == pytest.approx(
            plan.y_low + min(rows) * plan.line_pitch, rel=1e-12, abs=0
        )
        for k in range(done):  # every completed line at its own y in the cropped plan
            assert part.plan.line_y(k) == pytest.approx(plan.line_y(k), rel=1e-12, abs=0)
            np.testing.assert_array_equal(
                part.images["trace"]["height"][part.plan.row_of_line(k)],
                frame.images["trace"]["height"][plan.row_of_line(k)],
            )
        assert all(np.isfinite(part.images[d][ch]).all() for d in DIRECTIONS for ch in CHANNELS)
    assert not frame.partial or frame.lines_done < plan.lines
    with pytest.raises(ValueError, match="no line completed"):
        Frame.empty(plan, 0).completed()


@pytest.fixture(scope="module")
def stopped(tmp_path_factory):
    """The closed loop scans 3.5 of 8 lines and is stopped with stop_scan(); then a second scan is
    stopped through the scanner/stop service; a frame whose write fails, then one that succeeds."""
    import rclpy
    from rclpy.executors import SingleThreadedExecutor

    out = tmp_path_factory.mktemp("frames")
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ns = "/scanner_checks_stop"
    params = {**CANTILEVER, "real_time_factor": 0.0, "run_until": 0.0, "feedback_sync": "lockstep"}
    cantilever = CantileverNode(
        context=ctx,
        namespace=ns,
        parameter_overrides=[Parameter(k, value=v) for k, v in params.items()],
    )
    lockin = LockInNode(context=ctx, namespace=ns)
    controller = ZControllerNode(context=ctx, namespace=ns)
    scanner = ScannerNode(
        context=ctx,
        namespace=ns,
        parameter_overrides=[
            Parameter(k, value=v) for k, v in {**SCAN, "output_directory": str(out)}.items()
        ],
    )
    user = Node("user", context=ctx, namespace=ns)
    diagnostics = []
    user.create_subscription(
        DiagnosticArray,
        "/diagnostics",
        lambda m: diagnostics.extend(s for s in m.status if s.name == f"{ns}/scanner: scan"),
        50,
    )
    nodes = [cantilever, lockin, controller, scanner, user]
    for n in nodes:
        ex.add_node(n)
    result = {}
    try:
        spin_until(ex, lambda: {f"{ns}/lockin", f"{ns}/scanner"} <= set(cantilever.consumers))
        spin_until(ex, lambda: scanner.lockin_output_rate is not None)
        cantilever.set_parameters([Parameter("run_until", value=ENGAGE)])
        spin_until(ex, lambda: cantilever.paused and scanner.lockin_end[1] >= ENGAGE - 1e-9)
        assert scanner.start_scan(single=True).success
        spin_until(ex, lambda: scanner.state == "scanning")
        line_time = 1.0 / SCAN["line_rate"]
        cantilever.set_parameters([Parameter("run_until", value=ENGAGE + 3.5 * line_time)])
        spin_until(ex, lambda: cantilever.paused and scanner.accumulator.frame.lines_done >= 3)
        result["line_end"] = scanner.line_end_after(cantilever.sim_time)
        result["paths"] = scanner.stop_scan(write_partial=True)
        result["partial_frame"] = scanner.partial_frame
        result["lines_done"] = 3
        # the second scan, stopped through the service (partial frames are written by default)
        assert scanner.write_error == ""
        t = cantilever.sim_time
        assert scanner.start_scan(single=True).success
        cantilever.set_parameters([Parameter("run_until", value=t + 2.5 * line_time)])
        spin_until(
            ex, lambda: scanner.state == "scanning" and scanner.accumulator.frame.lines_done >= 1
        )
        spin_until(ex, lambda: cantilever.paused)
        lines = scanner.accumulator.frame.lines_done
        written = len(scanner.frames_written)
        result["service_stop"] = call(ex, user.create_client(Trigger, "scanner/stop"))
        scanner.wait_for_writers()
        result["service_file"], result["service_lines"] = scanner.frames_written[written:], lines
        # a write that fails (the folder became a file), then one that succeeds
        os.rename(out, str(out) + "_moved")
        out.write_text("not a folder")
        frame = Frame.empty(ScanPlan.from_values(SCAN), 7)
        for d in DIRECTIONS:
            for ch in CHANNELS:
                frame.images[d][ch][:] = 1.0
        frame.lines_done = SCAN["lines"]
        scanner.write_frame(frame).join(60)
        spin_until(
            ex,
            lambda: (
                diagnostics
                and diagnostics[-1].message != "ok"
                and "cannot write" in diagnostics[-1].message
            ),
            30,
        )
        result["failed"] = diagnostics[-1]
        out.unlink()
        os.rename(str(out) + "_moved", out)
        scanner.write_frame(frame).join(60)
        spin_until(ex, lambda: diagnostics[-1].message == "ok", 30)
        result["recovered"] = diagnostics[-1]
        yield result
    finally:
        for n in nodes:
            ex.remove_node(n)
            n.destroy_node()
        ex.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown(context=ctx)


@pytest.mark.slow
def test_a_stopped_scan_writes_its_completed_lines_as_a_partial_frame(stopped):
    paths = stopped["paths"]
    assert paths and paths[0].name.endswith("_partial.gwy"), paths
    stem = paths[0].name[: -len(".gwy")]
    assert {p.name for p in paths[1:]} == {
        f"{stem}_{c}_{d}.png" for c in CHANNELS for d in DIRECTIONS
    }
    # the same lines of the same scan (same start: the paused boundary) by the wired cores, with
    # the nodes' default imperfections and tip (a real instrument's)
    wired = WiredInstrument(
        cantilever=CANTILEVER,
        sample=resolve_sample("ps_ldpe_blend"),
        imperfections=INSTRUMENT_ARTEFACTS,
        tip=INSTRUMENT_TIP,
    )
    wired.run_until(ENGAGE)
    full = wired.scan_frame(SCAN)
    plan = full.plan
    assert stopped["line_end"] == pytest.approx(
        plan.line_end_time(0, 3), abs=1e-9
    )  # the 4th line was running
    done = stopped["lines_done"]
    obj = gwyfile.load(str(paths[0]))
    fields = gwyfile.util.get_datafields(obj)
    assert len(fields) == len(CHANNELS) * len(DIRECTIONS)
    for c in CHANNELS:
        for d in DIRECTIONS:
            f = fields[channel_title(c, d)]
            assert f.data.shape == (done, plan.pixels)
            assert f.yreal == pytest.approx(done * plan.line_pitch, rel=1e-12, abs=0)
            assert f.yoff == pytest.approx(plan.y_low, rel=1e-12, abs=0)
            assert f.xoff == pytest.approx(plan.x_left, rel=1e-12, abs=0)
            assert np.isfinite(f.data).all()
            np.testing.assert_array_equal(
                f.data, full.images[d][c][:done].astype(np.float64), err_msg=f"{c} {d}"
            )
    kept = stopped["partial_frame"]  # what an in-process caller summarises
    assert kept.partial and kept.lines_done == done and kept.plan.lines == done
    np.testing.assert_array_equal(
        kept.images["trace"]["phase"], full.images["trace"]["phase"][:done]
    )
    meta = obj["/0/meta"]
    assert (
        meta["frame.partial"] == "true"
        and meta["frame.lines_done"] == "3"
        and meta["frame.lines_planned"] == "8"
    )
    assert meta["scan.lines"] == "8"  # the scan as planned; the data field has the completed part


@pytest.mark.slow
def test_scanner_stop_keeps_the_lines_done_by_default(stopped):
    answer, files = stopped["service_stop"], stopped["service_file"]
    assert answer.success and "partial frame" in answer.message, answer.message
    assert len(files) == 1 and files[0].name.endswith("_partial.gwy")
    field = gwyfile.util.get_datafields(gwyfile.load(str(files[0])))["Height (trace)"]
    assert field.data.shape[0] == stopped["service_lines"] >= 1


@pytest.mark.slow
def test_diagnostics_clear_an_old_write_error_after_a_successful_write(stopped):
    failed, recovered = stopped["failed"], stopped["recovered"]
    values = {kv.key: kv.value for kv in failed.values}
    assert failed.level != DiagnosticStatus.OK and "cannot write frame 7" in failed.message
    assert values["frames_failed"] == "1"
    values = {kv.key: kv.value for kv in recovered.values}
    assert recovered.level == DiagnosticStatus.OK and recovered.message == "ok"
    assert values["frames_failed"] == "1"  # the count stays
    assert json.loads(json.dumps(values))["lockin_output_rate_Hz"] == "1000.0"


# --- the ROS-free rules the node, afm_study scan and afm_instrument share ----------------------
def test_check_scan_hints_are_right_and_the_memory_estimate_follows_the_buffers():
    """The refusal's suggestions pass the same check (a lower line_rate, a higher lock-in rate),
    and the per-pixel estimate of the accumulator and frame is what they really allocate."""
    import re

    from afm_ros.core.imaging import ImageAccumulator
    from afm_ros.core.scanner import (
        ACCUMULATOR_BYTES_PER_PIXEL,
        FRAME_BYTES_PER_PIXEL,
        check_scan,
        default_sample_interval,
        max_pixels,
    )

    values = {**SCAN, "pixels_per_line": 1000, "line_rate": 1.0}
    with pytest.raises(ValueError) as refused:
        check_scan(values, 1000.0)
    text = str(refused.value)
    limit = max_pixels(1.0, 1000.0, default_sample_interval())
    assert f"[2, {limit}]" in text and limit == 499
    rate = float(re.search(r"output_rate to >= (\d+) Hz", text).group(1))
    line_rate = float(re.search(r"line_rate to <= ([0-9.e-]+) Hz", text).group(1))
    assert check_scan(values, rate).max_pixels >= 1000
    assert check_scan({**values, "line_rate": line_rate}, 1000.0).max_pixels >= 1000
    with pytest.raises(ValueError):
        check_scan(values, rate - 1)  # the suggestion is the smallest whole rate that works
    plan = ScanPlan.from_values({**SCAN, "pixels_per_line": 64, "lines": 32, "line_rate": 1.0})
    acc = ImageAccumulator(plan, 10.0, 25.0, 60e-9)
    allocated = (
        acc._lockin_sums.nbytes + acc._z_sums.nbytes + sum(c.nbytes for c in acc._counts.values())
    )
    assert allocated == ACCUMULATOR_BYTES_PER_PIXEL * 64 * 32
    frame_bytes = sum(a.nbytes for chans in acc.frame.images.values() for a in chans.values())
    assert frame_bytes == FRAME_BYTES_PER_PIXEL * 64 * 32
    assert check_scan(plan, 1000.0, memory_limit=10**9).memory_bytes < 10**9
    with pytest.raises(
        ValueError, match=r"pixels_per_line=64 x lines=32 needs about .*allowed at most"
    ):
        check_scan(plan, 1000.0, memory_limit=2048 * 16)


def test_output_directory_rule(tmp_path):
    from afm_ros.formats.folders import check_output_directory

    assert check_output_directory(str(tmp_path)) == tmp_path
    made = check_output_directory(str(tmp_path / "run1"), create=True)
    assert made == tmp_path / "run1" and made.is_dir()
    with pytest.raises(
        ValueError, match=r"output_directory=.*a/b'.*does not exist; only the last level"
    ):
        check_output_directory(str(tmp_path / "a" / "b"), create=True)
    assert not (tmp_path / "a").exists()
    (tmp_path / "f").write_text("")
    with pytest.raises(ValueError, match="is a file, not a folder"):
        check_output_directory(str(tmp_path / "f"), create=True)
    with pytest.raises(ValueError, match="file-system root"):
        check_output_directory("/afm_ros_never_made", create=True)
    with pytest.raises(ValueError, match=r"free on its file system, a frame needs about"):
        check_output_directory(str(tmp_path), need_bytes=2**62)
    with pytest.raises(ValueError, match="--out="):
        check_output_directory(str(tmp_path / "f"), field="--out")
