"""Live view over the Foxglove WebSocket protocol: parameters and pure helpers (no ROS import).

The ``live_view`` node (:mod:`afm_ros.nodes.live_view_node`) serves the instrument's topics as
Foxglove channels. What a screen cannot show is decimated here:

- ``cantilever/deflection`` and ``cantilever/tip_sample_force`` (900 kS/s in 500 chunks/s): only
  the chunks whose chunk number ``first_sample_index // samples_per_chunk`` is a multiple of
  ``deflection_decimation`` are forwarded, unchanged (each a contiguous 2 ms trace of 1800 samples,
  the preamble included). The default 25 gives 20 chunks/s, the refresh rate of a plot. The rule
  depends only on the sample index, so which chunks a viewer sees does not depend on timing.
- the images ``scanner/image/<channel>/<direction>`` (sensor_msgs/Image 32FC1, SI units) go out as
  ``foxglove.RawImage`` mono8, scaled to the image's own range with the extreme 2 % of pixels at
  each end cut off (:data:`IMAGE_TAIL_CUT`, as Gwyddion's automatic colour range does), so that a
  few spikes at island edges do not squeeze the rest into one grey; pixels not yet scanned (NaN)
  are 0. Foxglove shows them without a value range to set.

- ``lockin/amplitude``, ``lockin/phase``, ``z_controller/z_piezo`` and ``z_controller/error`` (one
  std_msgs/Float64 per lock-in output, 1 kHz) and, in FM-AFM, ``pll/frequency_shift`` [Hz],
  ``pll/phase_error`` [deg] and ``pll/drive`` [N] are served in full but built from the batch
  topics ``lockin/outputs``, ``z_controller/trace`` and ``pll/outputs`` (:data:`DERIVED`, one
  message per input chunk, always published), with the values the lock-in, the z controller and the
  PLL publish on them, bit for bit: those nodes publish their per-output copies only while
  subscribed (~10 us each), so a viewer costs them nothing.

Everything else is forwarded as received: the ROS 2 message bytes (CDR) with the ``ros2msg``
definition the recorder writes, which Foxglove decodes natively.
"""

from __future__ import annotations

import base64
import math
import struct

import numpy as np

from afm_ros.core.angles import phase_deg
from afm_ros.core.physics.parameters import ParamSpec
from afm_ros.formats import chunk_layout
from afm_ros.formats.channels import IMAGE_TAIL_CUT, tail_cut_limits  # noqa: F401 - re-exported

LIVE_VIEW_SPECS: dict[str, ParamSpec] = {
    s.name: s
    for s in (
        ParamSpec(
            "address",
            "127.0.0.1",
            "",
            "address the Foxglove WebSocket server binds to; the protocol has no "
            "authentication: 0.0.0.0 lets anyone on the network read the instrument and change "
            "its parameters",
            kind=str,
            live=False,
        ),
        ParamSpec(
            "port",
            8765,
            "",
            "TCP port of the Foxglove WebSocket server (0 = any free port, logged at start)",
            0,
            65535,
            kind=int,
            live=False,
        ),
        ParamSpec(
            "deflection_decimation",
            25,
            "chunks",
            "forward one deflection (and force) chunk in N: the chunks whose "
            "number (first sample index / samples per chunk) is a multiple of N; 25 = 20 chunks/s "
            "at the "
            "defaults",
            1,
            100000,
            kind=int,
        ),
        ParamSpec(
            "message_backlog",
            256,
            "messages",
            "messages queued per viewer before the oldest view frame is "
            "dropped (a slow or stalled viewer loses view frames, the instrument never waits)",
            16,
            100000,
            kind=int,
            live=False,
        ),
        ParamSpec(
            "discovery_period",
            1.0,
            "s",
            "wall-clock period of looking for new topics and nodes",
            0.05,
            60.0,
            live=False,
        ),
        ParamSpec(
            "parameter_timeout",
            3.0,
            "s",
            "wall-clock time a parameter write or service call from a viewer may "
            "take before it is reported as failed",
            0.1,
            60.0,
        ),
    )
}

DEFLECTION_TOPICS = (
    "cantilever/deflection",
    "cantilever/tip_sample_force",
)  # relative to the namespace
PARAMETER_NODES = (
    "cantilever", "lockin", "z_controller", "pll", "scanner", "recorder", "bimodal",
)  # fmt: skip
# advertised from the start (a missing node's answers "not available")
SERVICES = ("scanner/start", "scanner/scan_frame", "scanner/stop")
# advertised while their node offers them (found at each discovery, withdrawn when gone)
OPTIONAL_SERVICES = ("bimodal/scan_frame", "bimodal/stop")
# image topics sent as foxglove.RawImage mono8 (sensor_msgs/Image 32FC1 or 64FC1)
IMAGE_PREFIXES = ("scanner/image/", "bimodal/image/")
IMAGE_DTYPES = {"32FC1": "f4", "64FC1": "f8"}
# per-output topics served from the batch topics the loop always publishes, so the lock-in, the z
# controller and the PLL never publish per-output copies for a viewer: topic -> (source topic,
# field)
DERIVED = {
    "lockin/amplitude": ("lockin/outputs", "amplitude"),
    "lockin/phase": ("lockin/outputs", "phase"),
    "z_controller/z_piezo": ("z_controller/trace", "z"),
    "z_controller/error": ("z_controller/trace", "error"),
    "pll/frequency_shift": ("pll/outputs", "df"),
    "pll/phase_error": ("pll/outputs", "phase_error"),
    "pll/drive": ("pll/outputs", "drive"),
}
FM_FIELDS = ("df", "phase_error", "drive")  # blocks of a pll/outputs batch served as they are
# Foxglove name of a ROS parameter: <node fqn>.<name>, as foxglove_bridge names it
PARAMETER_SEPARATOR = "."

# foxglove.RawImage as JSON (Foxglove decodes its well-known schemas in JSON encoding too)
RAW_IMAGE_SCHEMA = {
    "title": "foxglove.RawImage",
    "type": "object",
    "properties": {
        "timestamp": {
            "type": "object",
            "properties": {"sec": {"type": "integer"}, "nsec": {"type": "integer"}},
        },
        "frame_id": {"type": "string"},
        "width": {"type": "integer"},
        "height": {"type": "integer"},
        "encoding": {"type": "string"},
        "step": {"type": "integer"},
        "data": {"type": "string", "contentEncoding": "base64"},
    },
}


def parameter_name(node_fqn: str, name: str) -> str:
    """Foxglove name of parameter ``name`` of node ``node_fqn`` (``/cantilever.z_base``)."""
    return f"{node_fqn}{PARAMETER_SEPARATOR}{name}"


def split_parameter_name(full: str) -> tuple[str, str]:
    """(node fqn, parameter name) of a Foxglove parameter name; ValueError if it has no node
    part."""
    node, sep, name = full.partition(PARAMETER_SEPARATOR)
    if not sep or not node.startswith("/") or not name:
        raise ValueError(f"parameter {full!r} is not of the form /<node>.<name>")
    return node, name


def multiarray_data(cdr: bytes) -> np.ndarray:
    """``data`` of a std_msgs/Float64MultiArray in CDR (little endian, as rmw writes it), as a
    read-only view of the bytes (no copy, no deserialisation). ValueError if malformed."""
    try:
        pos = 4  # encapsulation header; CDR alignment counts from here
        (ndim,) = struct.unpack_from("<I", cdr, pos)
        pos += 4
        for _ in range(ndim):
            (length,) = struct.unpack_from("<I", cdr, pos)
            pos += 4 + length
            pos += (-(pos - 4)) % 4
            pos += 8  # size, stride
        pos += 4  # data_offset
        (n,) = struct.unpack_from("<I", cdr, pos)
        pos += 4
        pos += (-(pos - 4)) % 8
        return np.frombuffer(cdr, dtype="<f8", count=n, offset=pos)
    except (struct.error, ValueError) as exc:
        raise ValueError(f"not a Float64MultiArray: {exc}") from None


def chunk_first_index(cdr: bytes) -> tuple[int, int]:
    """(first_sample_index, samples in the chunk) of a deflection chunk in CDR, read without
    deserialising the samples. ValueError if the bytes are not a chunk (too short, no preamble)."""
    data = multiarray_data(cdr)
    samples = data.shape[0] - 6
    if samples <= 0 or not np.isfinite(data[0]):
        raise ValueError("not a deflection chunk: no samples after the preamble")
    return int(data[0]), samples


def float64_cdr(value: float) -> bytes:
    """std_msgs/Float64 ``value`` in CDR (little endian), the bytes rmw publishes."""
    return _CDR_HEADER + struct.pack("<d", value)


_CDR_HEADER = b"\x00\x01\x00\x00"


def derived_values(field: str, data: np.ndarray) -> tuple[list[float], list[float], float]:
    """(simulated times [s], values, batch end time [s]) of ``field`` from a batch's data:
    ``amplitude`` / ``phase`` from a ``lockin/outputs`` batch, ``z`` / ``error`` from a
    ``z_controller/trace``, ``df`` [Hz] / ``phase_error`` [deg] / ``drive`` [N] from a
    ``pll/outputs`` batch; computed exactly as the lock-in, the z controller and the PLL compute
    the values they publish on the per-output topics (bit for bit)."""
    if field in FM_FIELDS:
        fm = chunk_layout.unpack_fm_outputs(data)
        return fm.t.tolist(), getattr(fm, field).tolist(), fm.input_end_time
    if field in ("amplitude", "phase"):
        b = chunk_layout.unpack_outputs(data)
        xs, ys = b.x.tolist(), b.y.tolist()
        if field == "amplitude":
            values = [math.hypot(x, y) for x, y in zip(xs, ys)]
        else:
            values = [phase_deg(x, y) for x, y in zip(xs, ys)]
        return b.t.tolist(), values, b.input_end_time
    tr = chunk_layout.unpack_z_trace(data)
    return tr.t.tolist(), (tr.z if field == "z" else tr.error).tolist(), tr.input_end_time


def forward_chunk(first_index: int, samples: int, decimation: int) -> bool:
    """True for the chunks a viewer gets: chunk number ``first_index // samples`` a multiple of
    ``decimation``."""
    return (first_index // samples) % decimation == 0


def mono8(image: np.ndarray) -> tuple[np.ndarray, float, float]:
    """``image`` (float, NaN = no data) scaled to uint8 between its :func:`tail_cut_limits` (0 and
    255); NaN -> 0, pixels beyond the limits are clipped to 0 or 255. Returns (pixels, low, high);
    a constant image is all 128, an image without data all 0."""
    finite = np.isfinite(image)
    values = image[finite]
    if values.size == 0:
        return np.zeros(image.shape, np.uint8), float("nan"), float("nan")
    low, high = tail_cut_limits(values)
    out = np.zeros(image.shape, np.uint8)
    if high > low:
        out[finite] = np.clip(np.rint((values - low) * (255.0 / (high - low))), 0, 255).astype(
            np.uint8
        )
    else:
        out[finite] = 128
    return out, low, high


def raw_image_json(image: np.ndarray, stamp_sec: int, stamp_nsec: int, frame_id: str) -> dict:
    """foxglove.RawImage (JSON encoding, mono8) of a float image, row 0 first."""
    pixels, _, _ = mono8(image)
    height, width = pixels.shape
    return {
        "timestamp": {"sec": int(stamp_sec), "nsec": int(stamp_nsec)},
        "frame_id": frame_id,
        "width": int(width),
        "height": int(height),
        "encoding": "mono8",
        "step": int(width),
        "data": base64.b64encode(np.ascontiguousarray(pixels).tobytes()).decode("ascii"),
    }
