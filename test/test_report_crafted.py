"""afm_report on crafted imaging sessions (real MCAP files written with the project's
SessionWriter, messages serialised by rclpy): every defect in the images, the scan geometry or the
image topic names gives a report of what is intact, exit status 0, and one line naming the topic
and what was skipped and why (stderr and report.md), never a traceback."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from rclpy.serialization import serialize_message
from sensor_msgs.msg import Image
from std_msgs.msg import String

from afm_ros.core.imaging import CHANNELS, DIRECTIONS
from afm_ros.formats.mcap_io import SessionWriter
from afm_ros.tools import report

LINES, PIXELS = 6, 8
GEOMETRY = {
    "frame_id": "afm_scan",
    "x_offset_m": 1e-6,
    "y_offset_m": 2e-6,
    "size_x_m": 4e-6,
    "size_y_m": 3e-6,
    "pixels": PIXELS,
    "lines": LINES,
    "line_rate_Hz": 2.0,
    "start_time_s": 0.5,
    "row_0": "lowest y",
    "channels": {
        "height": "m",
        "amplitude": "m",
        "phase": "deg",
        "amplitude_error": "m",
        "dissipation": "J",
    },
    "sample": "ps_ldpe_blend",
}


def image_bytes(values: np.ndarray, **fields) -> bytes:
    msg = Image(
        height=values.shape[0],
        width=values.shape[1],
        encoding="32FC1",
        is_bigendian=0,
        step=4 * values.shape[1],
        data=values.astype("<f4").tobytes(),
    )
    for k, v in fields.items():
        setattr(msg, k, v)
    return serialize_message(msg)


def frame(channel: str) -> np.ndarray:
    rng = np.random.default_rng(CHANNELS.index(channel))
    return rng.normal(size=(LINES, PIXELS)) * {"phase": 1.0, "dissipation": 1e-17}.get(
        channel, 1e-9
    )


def write_session(path, extra=(), geometry=GEOMETRY, skip=()):
    """An imaging session: the geometry, one good image per channel and direction (unless in
    ``skip``), then ``extra`` = [(topic, type, bytes)] messages."""
    w = SessionWriter(path)
    t = 1_700_000_000 * 10**9
    channels = {}

    def put(topic, type_name, data):
        nonlocal t
        if topic not in channels:
            channels[topic] = w.add_channel(topic, type_name)
        t += 1_000_000
        w.write(channels[topic], data, t)

    if geometry is not None:
        put(
            "/scanner/geometry",
            "std_msgs/msg/String",
            serialize_message(String(data=json.dumps(geometry))),
        )
    for c in CHANNELS:
        for d in DIRECTIONS:
            if (c, d) not in skip:
                put(f"/scanner/image/{c}/{d}", "sensor_msgs/msg/Image", image_bytes(frame(c)))
    for topic, type_name, data in extra:
        put(topic, type_name, data)
    w.close()
    return path


GOOD = {(c, d) for c in CHANNELS for d in DIRECTIONS}
HEIGHT = "/scanner/image/height/trace"
CASES = {
    # garbage image data: a message that is not a sensor_msgs/Image at all
    "garbage image": dict(
        extra=[(HEIGHT, "sensor_msgs/msg/Image", b"\x00\x01\x00\x00" + bytes(range(7)))],
        why="message 2: ",
    ),
    # dimensions that the data do not hold (80 x 60 pixels announced, 8 x 6 sent)
    "wrong dimensions": dict(
        extra=[
            (
                HEIGHT,
                "sensor_msgs/msg/Image",
                image_bytes(frame("height"), height=60, width=80, step=320),
            )
        ],
        why="80 x 60 pixels",
    ),
    "row step too short": dict(
        extra=[(HEIGHT, "sensor_msgs/msg/Image", image_bytes(frame("height"), step=4))],
        why="row step 4 B",
    ),
    "not 32FC1": dict(
        extra=[(HEIGHT, "sensor_msgs/msg/Image", image_bytes(frame("height"), encoding="mono8"))],
        why="encoding 'mono8'",
    ),
    "zero size": dict(
        extra=[(HEIGHT, "sensor_msgs/msg/Image", image_bytes(np.zeros((0, 0))))],
        why="0 x 0 pixels",
    ),
    # odd topic names and types
    "no direction": dict(
        extra=[("/scanner/image/height", "sensor_msgs/msg/Image", image_bytes(frame("height")))],
        topic="/scanner/image/height",
        why="not scanner/image/<channel>/<direction>",
    ),
    "too deep": dict(
        extra=[
            (
                "/scanner/image/height/trace/x",
                "sensor_msgs/msg/Image",
                image_bytes(frame("height")),
            )
        ],
        topic="/scanner/image/height/trace/x",
        why="not scanner/image/<channel>/<direction>",
    ),
    "empty part": dict(
        extra=[("/scanner/image//trace", "sensor_msgs/msg/Image", image_bytes(frame("height")))],
        topic="/scanner/image//trace",
        why="not scanner/image/<channel>/<direction>",
    ),
    "string on an image topic": dict(
        extra=[
            (
                "/scanner/image/notes/trace",
                "std_msgs/msg/String",
                serialize_message(String(data="hello")),
            )
        ],
        topic="/scanner/image/notes/trace",
        why="type std_msgs/msg/String",
    ),
    # the geometry: missing keys, wrong types, not JSON, not an object
    "geometry missing keys": dict(
        geometry={k: v for k, v in GEOMETRY.items() if k != "size_x_m"},
        topic="/scanner/geometry",
        why="size_x_m missing or not a finite number",
    ),
    "geometry of wrong types": dict(
        geometry={
            **GEOMETRY,
            "x_offset_m": "left",
            "size_y_m": -1.0,
            "pixels": "many",
            "channels": ["m"],
            "sample": 7,
        },
        topic="/scanner/geometry",
        why="x_offset_m, size_y_m missing",
    ),
    "geometry is a list": dict(
        geometry=[1, 2, 3], topic="/scanner/geometry", why="a JSON list, not an object"
    ),
    "geometry not JSON": dict(
        extra=[
            (
                "/scanner/geometry",
                "std_msgs/msg/String",
                serialize_message(String(data="{size: 5 um")),
            )
        ],
        topic="/scanner/geometry",
        why="not a JSON text",
    ),
    "geometry of another type": dict(
        geometry=None,
        extra=[("/scanner/geometry", "sensor_msgs/msg/Image", image_bytes(frame("height")))],
        topic="/scanner/geometry",
        why="type sensor_msgs/msg/Image",
    ),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_crafted_imaging_file_gives_a_report_of_what_is_intact(tmp_path, case, capsys):
    spec = CASES[case]
    session = write_session(
        tmp_path / "crafted.mcap",
        extra=spec.get("extra", ()),
        geometry=spec.get("geometry", GEOMETRY),
    )
    out = tmp_path / "rep"
    assert report.main([str(session), "--out", str(out), "--json"]) == 0
    captured = capsys.readouterr()
    err = captured.err
    numbers = json.loads(captured.out.strip().splitlines()[-1])
    topic = spec.get("topic", HEIGHT)
    notes = [line for line in err.splitlines() if line.startswith("afm_report: note: skipped ")]
    assert len(notes) == 1 and topic in notes[0] and spec["why"] in notes[0], err
    md = (out / "report.md").read_text()
    assert "## Skipped" in md and f"`{topic}" in md and spec["why"] in md
    # every intact image is in the figure and the table; a damaged last image falls back to the one
    # before
    assert set(numbers["images"]) == {f"{c}/{d}" for c, d in GOOD}
    assert (out / "images.png").stat().st_size > 10_000
    assert numbers["images"]["height/trace"]["min"] == pytest.approx(
        float(frame("height").astype("<f4").min()), rel=1e-6, abs=0
    )
    geometry_ok = spec.get("topic") != "/scanner/geometry"
    assert ("over 4 x 3 µm" in md) == geometry_ok


def test_session_with_only_broken_images_still_gives_the_rest(tmp_path, capsys):
    """No image intact: no image figure, a note per topic, the report of the rest; exit status
    0."""
    bad = image_bytes(frame("height"), encoding="bgr8")
    session = write_session(
        tmp_path / "s.mcap",
        skip=GOOD,
        extra=[(f"/scanner/image/{c}/{d}", "sensor_msgs/msg/Image", bad) for c, d in sorted(GOOD)],
    )
    assert report.main([str(session), "--out", str(tmp_path / "rep")]) == 0
    err = capsys.readouterr().err
    assert err.count("afm_report: note: skipped /scanner/image/") == len(GOOD)
    assert "none of its 1 messages is a 32FC1 image" in err
    assert not (tmp_path / "rep" / "images.png").exists()
    assert (tmp_path / "rep" / "report.md").exists()


@pytest.mark.slow
def test_crafted_file_from_the_command_line_no_traceback(tmp_path):
    session = write_session(
        tmp_path / "c.mcap", geometry=[1], extra=CASES["garbage image"]["extra"]
    )
    proc = subprocess.run(
        [sys.executable, "-m", "afm_ros.tools.report", str(session), "--out", str(tmp_path / "r")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    assert (
        len(
            [
                line
                for line in proc.stderr.splitlines()
                if line.startswith("afm_report: note: skipped")
            ]
        )
        == 2
    )
