"""FM-AFM over real DDS (in-process, discovery confined; see conftest): cantilever (excitation
'pll'), lock-in, PLL, z controller on the frequency shift and scanner nodes in lockstep scan a
frame of the PS/LDPE blend.

- The ROS frame equals the frame of the same cores wired directly (WiredInstrument(fm=...)) bit for
  bit, in every FM channel (height, df, drive, dissipation, amplitude, phase error, df error): the
  excitation the PLL computes from chunk k drives chunk k + feedback_latency in both.
- The loop holds what FM-AFM holds: the amplitude at its setpoint, the df at the z loop's setpoint;
  the two polymers show in the drive (dissipation) and the height.
- The published images decode to the frame; the .gwy file, read back with gwyfile (not written by
  this project), holds the FM channels with their SI units.
"""

from __future__ import annotations

import time

import numpy as np
import pytest
from conftest import EXACT_PHYSICS
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rclpy.parameter import Parameter
from sensor_msgs.msg import Image

from afm_ros.core.artefacts import INSTRUMENT_ARTEFACTS
from afm_ros.core.imaging import DIRECTIONS, FM_CHANNELS, UNITS
from afm_ros.core.samples import resolve_sample
from afm_ros.core.tip import INSTRUMENT_TIP
from afm_ros.core.wired import WiredInstrument
from afm_ros.formats.frames import channel_title
from afm_ros.nodes.cantilever_node import CantileverNode
from afm_ros.nodes.lockin_node import LockInNode
from afm_ros.nodes.pll_node import PllNode
from afm_ros.nodes.scanner_node import ScannerNode, image_topic
from afm_ros.nodes.topics import LATCHED_QOS
from afm_ros.nodes.z_controller_node import ZControllerNode

pytestmark = [pytest.mark.ros, pytest.mark.slow]

# a vacuum cantilever (Q 1e4) self-excited at 5 nm (the PLL's amplitude setpoint), 8 nm above the
# blend, with the nodes' real tip (wear) and scanner (drift, tilt, creep, hysteresis), given to the
# wired one too
CANTILEVER = {
    **EXACT_PHYSICS,
    **INSTRUMENT_TIP,
    "force_model": "viscoelastic_dmt",
    "sample": "ps_ldpe_blend",
    "excitation": "pll",
    "quality_factor": 1e4,
    "chunk_duration": 2e-3,
    "z_base": 8e-9,
}
Z_LOOP = {"feedback_signal": "frequency_shift", "df_setpoint": -20.0}
# FM scans slowly: the z loop on df is held below the PLL's bandwidth (docs/fm.md); 1 um at 1
# line/s
SCAN = dict(
    scan_size_x=1e-6,
    scan_size_y=1e-6,
    scan_center_x=5e-6,
    scan_center_y=5e-6,
    pixels_per_line=8,
    lines=4,
    line_rate=1.0,
)
ENGAGE = 0.5  # [s]: the PLL locks and the z loop settles on df_setpoint (~0.4 s) before the scan


def spin_until(executor, condition, timeout=180.0):
    end = time.monotonic() + timeout
    while not condition():
        assert time.monotonic() < end, "condition not met in time"
        executor.spin_once(timeout_sec=0.01)


@pytest.fixture(scope="module")
def fm_scanned(tmp_path_factory):
    import rclpy

    out = tmp_path_factory.mktemp("fm_frames")
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    ex = SingleThreadedExecutor(context=ctx)
    ns = "/fm_scan_test"
    params = {**CANTILEVER, "real_time_factor": 0.0, "run_until": 0.0, "feedback_sync": "lockstep"}
    cantilever = CantileverNode(
        context=ctx,
        namespace=ns,
        parameter_overrides=[Parameter(k, value=v) for k, v in params.items()],
    )
    lockin = LockInNode(context=ctx, namespace=ns)
    pll = PllNode(context=ctx, namespace=ns)
    controller = ZControllerNode(
        context=ctx,
        namespace=ns,
        parameter_overrides=[Parameter(k, value=v) for k, v in Z_LOOP.items()],
    )
    scanner = ScannerNode(
        context=ctx,
        namespace=ns,
        parameter_overrides=[
            Parameter(k, value=v)
            for k, v in {**SCAN, **INSTRUMENT_ARTEFACTS, "output_directory": str(out)}.items()
        ],
    )
    viewer = Node("viewer", context=ctx, namespace=ns)
    images = {}
    for c in FM_CHANNELS:
        for d in DIRECTIONS:
            viewer.create_subscription(
                Image,
                image_topic(c, d),
                lambda m, key=(c, d): images.__setitem__(key, m),
                LATCHED_QOS,
            )
    nodes = [cantilever, lockin, pll, controller, scanner, viewer]
    for n in nodes:
        ex.add_node(n)
    try:
        spin_until(ex, lambda: {f"{ns}/lockin", f"{ns}/scanner"} <= set(cantilever.consumers))
        spin_until(ex, lambda: scanner.lockin_output_rate is not None)
        spin_until(
            ex, lambda: cantilever.imperfections_received
        )  # latched; before the first chunk
        cantilever.set_parameters([Parameter("run_until", value=ENGAGE)])
        spin_until(ex, lambda: cantilever.paused and scanner.lockin_end[1] >= ENGAGE - 1e-9)
        response = scanner.start_scan(single=True)
        assert response.success, response.message
        spin_until(ex, lambda: scanner.state == "scanning")
        cantilever.set_parameters(
            [Parameter("run_until", value=ENGAGE + SCAN["lines"] / SCAN["line_rate"] + 0.01)]
        )
        spin_until(ex, lambda: scanner.frames_done >= 1)
        scanner.wait_for_writers()
        end = ENGAGE + SCAN["lines"] / SCAN["line_rate"]
        spin_until(
            ex,
            lambda: (
                len(images) == len(FM_CHANNELS) * len(DIRECTIONS)
                and all(
                    m.header.stamp.sec + 1e-9 * m.header.stamp.nanosec >= end - 1e-6
                    for m in images.values()
                )
            ),
            30,
        )  # the images of the last line
        yield {
            "frame": scanner.accumulator.frames_done[0],
            "images": images,
            "files": list(scanner.frames_written),
            "pll": dict(pll.loop.params),
        }
    finally:
        for n in nodes:
            ex.remove_node(n)
            n.destroy_node()
        ex.shutdown(timeout_sec=1.0)
        rclpy.try_shutdown(context=ctx)


@pytest.fixture(scope="module")
def offline():
    wired = WiredInstrument(
        cantilever=CANTILEVER,
        sample=resolve_sample("ps_ldpe_blend"),
        fm={},
        z_controller=Z_LOOP,
        imperfections=INSTRUMENT_ARTEFACTS,
    )
    wired.run_until(ENGAGE)
    return wired.scan_frame(SCAN)


def test_ros_fm_frame_equals_the_wired_cores_bit_for_bit(fm_scanned, offline):
    frame = fm_scanned["frame"]
    assert frame.plan == offline.plan
    assert tuple(frame.channels) == tuple(FM_CHANNELS) == tuple(offline.channels)
    for d in DIRECTIONS:
        for c in FM_CHANNELS:
            assert np.isfinite(frame.images[d][c]).all(), (d, c)
            np.testing.assert_array_equal(
                frame.images[d][c], offline.images[d][c], err_msg=f"{d} {c}"
            )


def test_the_fm_loop_holds_amplitude_and_frequency_shift(offline, fm_scanned):
    """FM imaging of a conservative-in-non-contact sample (viscoelastic DMT, tip ~1 nm above the
    polystyrene: no contact, so no loss):
    - the amplitude at the PLL's setpoint (the amplitude controller) within 0.2 %;
    - df at the z loop's setpoint up to the ramp error of a PI loop: the scanner's tilt makes the
      surface a ramp of rate tilt_x v_x under the tip (v_x = 2 size line_rate, trace and retrace),
      which an integrating loop follows with a constant error v / K_I [Hz], of opposite sign on
      trace and retrace: their medians are 2 v / K_I apart (within 15 %: the P term and the line
      turns) and centred on the setpoint (within 1.5 Hz);
    - the drive is the free drive k A / Q times f / f0 (no dissipation) within 1e-3, and the
      dissipation channel below 1e-3 of the free loss pi k A^2 / Q."""
    params = fm_scanned["pll"]
    a = params["amplitude_setpoint"]
    k, q, f0 = 10.0, CANTILEVER["quality_factor"], params["center_frequency"]
    medians = {}
    # each line starts where the last one turned (left for trace, right for retrace; images are in
    # x order): the z loop's error flips sign there and the tip dips briefly; judge the line's far
    # half
    far = {"trace": np.s_[1:, 4:], "retrace": np.s_[1:, :4]}  # row 0: the scan's start transient
    for d in DIRECTIONS:
        img = offline.images[d]
        assert np.median(img["amplitude"]) == pytest.approx(a, rel=2e-3, abs=0)
        medians[d] = float(np.median(img["frequency_shift"][far[d]]))
        drive = np.median(img["drive"][far[d]])
        assert drive == pytest.approx(k * a / q * (1 + medians[d] / f0), rel=1e-3, abs=0)
        assert abs(np.median(img["dissipation"][far[d]])) < 1e-3 * np.pi * k * a * a / q
    ramp = INSTRUMENT_ARTEFACTS["tilt_x"] * 2 * SCAN["scan_size_x"] * SCAN["line_rate"]  # [m/s]
    expected_error = ramp / 1e-9  # K_I: the z controller's default df_i_gain [m/(Hz s)]
    assert abs(medians["trace"] - medians["retrace"]) == pytest.approx(
        2 * expected_error, rel=0.15
    )
    assert abs(0.5 * (medians["trace"] + medians["retrace"]) - Z_LOOP["df_setpoint"]) < 1.5


def test_published_fm_images_and_gwy_file_hold_the_frame(fm_scanned):
    import gwyfile

    frame = fm_scanned["frame"]
    for (c, d), msg in fm_scanned["images"].items():
        decoded = np.frombuffer(bytes(msg.data), dtype="<f4").reshape(msg.height, msg.width)
        np.testing.assert_array_equal(decoded, frame.images[d][c])
    [path] = fm_scanned["files"]
    channels = gwyfile.util.get_datafields(gwyfile.load(str(path)))
    expected = {channel_title(c, d): (c, d) for c in FM_CHANNELS for d in DIRECTIONS}
    assert set(channels) == set(expected)
    for title, (c, d) in expected.items():
        field = channels[title]
        np.testing.assert_array_equal(np.asarray(field.data, dtype=np.float32), frame.images[d][c])
        assert field.si_unit_z.unitstr == UNITS[c], title
