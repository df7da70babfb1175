"""A z spectroscopy curve in a std_msgs/Float64MultiArray (topic ``z_controller/spectroscopy``; no ROS import).

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

import numpy as np

from afm_ros.core.spectroscopy import CHUNK_COLUMNS, OUTPUT_COLUMNS, SpectroscopyCurve

META_LABELS = ("x_m", "y_m", "t_start_s", "t_end_s", "rate_m_per_s", "retract_m", "distance_m", "z_held_m",
               "z_offset_m", "spring_constant_N_per_m", "quality_factor", "resonance_frequency_Hz", "setpoint_m",
               "chunk_duration_s", "feedback_latency_chunks", "missing_chunks")
N_META = len(SpectroscopyCurve.META)
assert len(META_LABELS) == N_META


def pack_curve(curve: SpectroscopyCurve) -> np.ndarray:
    """The message's ``data`` (float64)."""
    n, m = curve.t.shape[0], curve.chunk_t_start.shape[0]
    parts = [np.array([N_META, n, m], dtype=np.float64),
             np.array([float(getattr(curve, k)) for k in SpectroscopyCurve.META])]
    parts += [np.asarray(getattr(curve, k), dtype=np.float64) for k in SpectroscopyCurve.OUTPUTS]
    parts += [np.asarray(getattr(curve, k), dtype=np.float64) for k in SpectroscopyCurve.CHUNKS]
    return np.concatenate(parts)


def dims(curve: SpectroscopyCurve) -> list[tuple[str, int, int]]:
    """(label, size, stride) of ``layout.dim``: the set-up, the outputs and the chunks."""
    n, m = curve.t.shape[0], curve.chunk_t_start.shape[0]
    return [("meta:" + ",".join(META_LABELS), N_META, N_META),
            ("outputs:" + ",".join(OUTPUT_COLUMNS), n, n * len(OUTPUT_COLUMNS)),
            ("chunks:" + ",".join(CHUNK_COLUMNS), m, m * len(CHUNK_COLUMNS))]


def unpack_curve(msg) -> SpectroscopyCurve:
    """The curve of a message (anything with ``.data``) or of its ``data`` array; ValueError if the
    layout does not add up."""
    data = getattr(msg, "data", msg)
    arr = np.frombuffer(data, dtype=np.float64) if isinstance(data, (bytes, memoryview)) \
        else np.asarray(data, dtype=np.float64)
    if arr.shape[0] < 3:
        raise ValueError(f"spectroscopy curve has {arr.shape[0]} values, fewer than its 3 counts")
    n_meta, n, m = (int(v) for v in arr[:3])
    want = 3 + n_meta + n * len(OUTPUT_COLUMNS) + m * len(CHUNK_COLUMNS)
    if n_meta != N_META or n < 0 or m < 0 or arr.shape[0] != want:
        raise ValueError(f"spectroscopy curve has {arr.shape[0]} values for counts ({n_meta}, {n}, {m}); "
                         f"expected {N_META} set-up values and {want} values in all")
    d = dict(zip(SpectroscopyCurve.META, arr[3:3 + n_meta].tolist()))
    pos = 3 + n_meta
    for name in SpectroscopyCurve.OUTPUTS:
        d[name], pos = arr[pos:pos + n].copy(), pos + n
    for name in SpectroscopyCurve.CHUNKS:
        d[name], pos = arr[pos:pos + m].copy(), pos + m
    return SpectroscopyCurve.from_dict(d)
