"""A z spectroscopy curve in a std_msgs/Float64MultiArray (topic ``z_controller/spectroscopy``; no
ROS import).

``data = [n_meta, n_outputs, n_chunks]`` followed by the ``n_meta`` set-up values
(:attr:`SpectroscopyCurve.META` order: x_m, y_m, t_start_s, t_end_s, rate_m_per_s, retract_m,
distance_m, z_held_m, z_offset_m, spring_constant_N_per_m, quality_factor, resonance_frequency_Hz,
setpoint_m, chunk_duration_s, feedback_latency_chunks, missing_chunks), then the per-output columns
one block each (``OUTPUT_COLUMNS``: t_s, z_piezo_m, z_gap_m, amplitude_m, phase_deg, direction),
then the per-chunk columns (``CHUNK_COLUMNS``: t_start_s, t_end_s, z_gap_m, deflection_m, force_N,
direction). ``direction`` indexes ``DIRECTIONS`` (lift, approach, retract, return).
``layout.data_offset = 3 + n_meta`` (where the columns start) and ``layout.dim`` names the three
parts with their column labels (:func:`dims`), for a reader without this module.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

DIRECTIONS = ("lift", "approach", "retract", "return")  # the legs, in order (column value = index)
OUTPUT_COLUMNS = ("t_s", "z_piezo_m", "z_gap_m", "amplitude_m", "phase_deg", "direction")
CHUNK_COLUMNS = ("t_start_s", "t_end_s", "z_gap_m", "deflection_m", "force_N", "direction")


@dataclass
class SpectroscopyCurve:
    """One finished curve: per lock-in output and per deflection chunk (SI units), and its
    set-up."""

    # set-up
    x: float  # tip position on the sample [m]
    y: float
    t_start: float  # simulated time of the ramp's start [s]
    t_end: float  # the output at which the feedback resumed [s]
    rate: float  # [m/s]
    retract: float  # [m]
    distance: float  # [m]
    z_held: float  # the z piezo position held (engaged) [m]
    z_offset: float  # z_base + motor [m]: z_gap = z_offset + z_piezo
    spring_constant: float  # [N/m]
    quality_factor: float
    resonance_frequency: float  # [Hz]
    setpoint: float  # [m]
    chunk_duration: float  # [s]
    feedback_latency: int  # [chunks]
    missing_chunks: int  # chunks whose samples never arrived (their means are NaN)
    # per lock-in output
    t: np.ndarray  # [s]
    z_piezo: np.ndarray  # commanded z piezo [m]
    z_gap: np.ndarray  # z_offset + z_piezo [m]
    amplitude: np.ndarray  # [m]
    phase: np.ndarray  # [deg]
    direction: np.ndarray  # index into DIRECTIONS
    # per deflection chunk
    chunk_t_start: np.ndarray  # [s]
    chunk_t_end: np.ndarray  # [s]
    chunk_z_gap: np.ndarray  # z_base + motor + z piezo the cantilever applied to the chunk [m]
    chunk_deflection: np.ndarray  # mean measured deflection [m]
    chunk_force: np.ndarray  # mean tip-sample force [N] (repulsive > 0)
    chunk_direction: np.ndarray  # index into DIRECTIONS

    META = (
        "x",
        "y",
        "t_start",
        "t_end",
        "rate",
        "retract",
        "distance",
        "z_held",
        "z_offset",
        "spring_constant",
        "quality_factor",
        "resonance_frequency",
        "setpoint",
        "chunk_duration",
        "feedback_latency",
        "missing_chunks",
    )
    OUTPUTS = ("t", "z_piezo", "z_gap", "amplitude", "phase", "direction")
    CHUNKS = (
        "chunk_t_start",
        "chunk_t_end",
        "chunk_z_gap",
        "chunk_deflection",
        "chunk_force",
        "chunk_direction",
    )

    def branch(self, name: str) -> np.ndarray:
        """Mask of the outputs on one leg (``approach``, ``retract``, ``lift``, ``return``)."""
        return self.direction == DIRECTIONS.index(name)

    def chunk_branch(self, name: str) -> np.ndarray:
        return self.chunk_direction == DIRECTIONS.index(name)

    def to_dict(self) -> dict:
        """Plain floats and lists (JSON-able), keys as the field names."""
        out = {}
        for f in fields(self):
            v = getattr(self, f.name)
            out[f.name] = v.tolist() if isinstance(v, np.ndarray) else v
        return out

    @classmethod
    def from_dict(cls, d: dict) -> "SpectroscopyCurve":
        """Inverse of :meth:`to_dict` (lists become float64 arrays, direction columns int)."""
        kw = {}
        for f in fields(cls):
            v = d[f.name]
            if f.name in cls.OUTPUTS or f.name in cls.CHUNKS:
                v = np.asarray(v, dtype=np.int64 if f.name.endswith("direction") else np.float64)
            elif f.name in ("feedback_latency", "missing_chunks"):
                v = int(v)
            else:
                v = float(v)
            kw[f.name] = v
        return cls(**kw)

    def equal(self, other: "SpectroscopyCurve") -> bool:
        """Bit for bit the same (NaN equals NaN)."""
        for f in fields(self):
            a, b = getattr(self, f.name), getattr(other, f.name)
            if isinstance(a, np.ndarray):
                if a.shape != b.shape or not np.array_equal(a, b, equal_nan=a.dtype.kind == "f"):
                    return False
            elif not (a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b))):
                return False
        return True


META_LABELS = (
    "x_m",
    "y_m",
    "t_start_s",
    "t_end_s",
    "rate_m_per_s",
    "retract_m",
    "distance_m",
    "z_held_m",
    "z_offset_m",
    "spring_constant_N_per_m",
    "quality_factor",
    "resonance_frequency_Hz",
    "setpoint_m",
    "chunk_duration_s",
    "feedback_latency_chunks",
    "missing_chunks",
)
N_META = len(SpectroscopyCurve.META)
assert len(META_LABELS) == N_META


def pack_curve(curve: SpectroscopyCurve) -> np.ndarray:
    """The message's ``data`` (float64)."""
    n, m = curve.t.shape[0], curve.chunk_t_start.shape[0]
    parts = [
        np.array([N_META, n, m], dtype=np.float64),
        np.array([float(getattr(curve, k)) for k in SpectroscopyCurve.META]),
    ]
    parts += [np.asarray(getattr(curve, k), dtype=np.float64) for k in SpectroscopyCurve.OUTPUTS]
    parts += [np.asarray(getattr(curve, k), dtype=np.float64) for k in SpectroscopyCurve.CHUNKS]
    return np.concatenate(parts)


def dims(curve: SpectroscopyCurve) -> list[tuple[str, int, int]]:
    """(label, size, stride) of ``layout.dim``: the set-up, the outputs and the chunks."""
    n, m = curve.t.shape[0], curve.chunk_t_start.shape[0]
    return [
        ("meta:" + ",".join(META_LABELS), N_META, N_META),
        ("outputs:" + ",".join(OUTPUT_COLUMNS), n, n * len(OUTPUT_COLUMNS)),
        ("chunks:" + ",".join(CHUNK_COLUMNS), m, m * len(CHUNK_COLUMNS)),
    ]


def unpack_curve(msg) -> SpectroscopyCurve:
    """The curve of a message (anything with ``.data``) or of its ``data`` array; ValueError if the
    layout does not add up."""
    data = getattr(msg, "data", msg)
    arr = (
        np.frombuffer(data, dtype=np.float64)
        if isinstance(data, (bytes, memoryview))
        else np.asarray(data, dtype=np.float64)
    )
    if arr.shape[0] < 3:
        raise ValueError(f"spectroscopy curve has {arr.shape[0]} values, fewer than its 3 counts")
    n_meta, n, m = (int(v) for v in arr[:3])
    want = 3 + n_meta + n * len(OUTPUT_COLUMNS) + m * len(CHUNK_COLUMNS)
    if n_meta != N_META or n < 0 or m < 0 or arr.shape[0] != want:
        raise ValueError(
            f"spectroscopy curve has {arr.shape[0]} values for counts ({n_meta}, {n}, {m}); "
            f"expected {N_META} set-up values and {want} values in all"
        )
    d = dict(zip(SpectroscopyCurve.META, arr[3 : 3 + n_meta].tolist()))
    pos = 3 + n_meta
    for name in SpectroscopyCurve.OUTPUTS:
        d[name], pos = arr[pos : pos + n].copy(), pos + n
    for name in SpectroscopyCurve.CHUNKS:
        d[name], pos = arr[pos : pos + m].copy(), pos + m
    return SpectroscopyCurve.from_dict(d)
