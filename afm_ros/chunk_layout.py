"""Layout of a sample chunk in a std_msgs/Float64MultiArray (no ROS import here).

``data[0:PREAMBLE_LENGTH]`` is a preamble (``layout.data_offset == PREAMBLE_LENGTH``), the
samples follow. Sample ``i`` of the chunk has the running sample index ``first_sample_index + i``
and the simulated time ``t_start + i * sample_interval`` [s]; the drive phase at that sample is
``drive_phase + 2 pi drive_frequency i sample_interval`` [rad]; the tip-sample gap is
``z_offset + deflection`` [m].
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

PREAMBLE_FIELDS = ("first_sample_index", "t_start_s", "sample_interval_s", "drive_phase_rad",
                   "drive_frequency_hz", "z_offset_m")
PREAMBLE_LENGTH = len(PREAMBLE_FIELDS)
SAMPLES_LABEL = "samples"


@dataclass
class ChunkHeader:
    first_sample_index: int
    t_start: float  # simulated time of the first sample [s]
    sample_interval: float  # [s]
    drive_phase: float  # drive phase at the first sample [rad]
    drive_frequency: float  # [Hz]
    z_offset: float  # z_base + z_piezo [m]; gap = z_offset + deflection

    def as_array(self) -> np.ndarray:
        return np.array([float(self.first_sample_index), self.t_start, self.sample_interval,
                         self.drive_phase, self.drive_frequency, self.z_offset])

    def times(self, count: int) -> np.ndarray:
        return self.t_start + np.arange(count) * self.sample_interval

    def drive_phases(self, count: int) -> np.ndarray:
        return self.drive_phase + 2.0 * np.pi * self.drive_frequency * np.arange(count) * self.sample_interval


def pack(header: ChunkHeader, samples: np.ndarray) -> np.ndarray:
    """Preamble followed by the samples, as one float64 array."""
    out = np.empty(PREAMBLE_LENGTH + samples.shape[0])
    out[:PREAMBLE_LENGTH] = header.as_array()
    out[PREAMBLE_LENGTH:] = samples
    return out


def unpack(data) -> tuple[ChunkHeader, np.ndarray]:
    """Inverse of :func:`pack` for a message's ``data`` (array.array, list or ndarray)."""
    arr = np.frombuffer(data, dtype=np.float64) if isinstance(data, (bytes, memoryview)) else np.asarray(data, dtype=np.float64)
    if arr.shape[0] < PREAMBLE_LENGTH:
        raise ValueError(f"chunk has {arr.shape[0]} values, fewer than the {PREAMBLE_LENGTH}-value preamble")
    p = arr[:PREAMBLE_LENGTH]
    header = ChunkHeader(int(p[0]), float(p[1]), float(p[2]), float(p[3]), float(p[4]), float(p[5]))
    return header, arr[PREAMBLE_LENGTH:]
