"""What the client's verbs return, field by field (SI units in the names): TypedDicts, so a script
author's editor shows the fields, and the values stay plain dicts (JSON-ready, as the nodes send
them)."""

from __future__ import annotations

from typing import TypedDict


class TuneResult(TypedDict, total=False):
    """:meth:`Microscope.tune`: the fit of the drive sweep and the working point it set."""

    f0_Hz: float  # fitted resonance [Hz]
    f0_error_Hz: float  # its standard error [Hz]
    Q: float
    Q_error: float
    f_peak_Hz: float  # where the fitted amplitude peaks [Hz]
    peak_amplitude_m: float
    drive_frequency_Hz: float  # the working point set: drive at the peak [Hz]
    drive_scale: float  # the drive force scaled by this for the requested free amplitude
    phase_offset_deg: float  # the lock-in's phase zero set [deg]
    fit_residual_rms: float  # [m]
    points: int  # drive frequencies of the sweep
    static_amplitude_m: float
    phase0_deg: float
    frequency_Hz: list  # the sweep: frequencies [Hz], amplitudes [m], phases [deg]
    amplitude_m: list
    phase_deg: list
    settings: dict  # the tune's parameters in force
    start_s: float  # simulated time of the sweep's start and end [s]
    end_s: float


class ApproachResult(TypedDict):
    """:meth:`Microscope.approach`: where and when it engaged."""

    state: str  # 'engaged'
    started_s: float  # [s] simulated
    engaged_s: float
    duration_s: float
    engaged_z_m: float  # z piezo at the engage [m]
    motor_steps: int
    cycles: int
    motor_m: float  # the coarse motor's position [m]


class WithdrawResult(TypedDict):
    """:meth:`Microscope.withdraw`."""

    state: str  # 'withdrawn'
    started_s: float  # [s] simulated
    withdrawn_s: float
    motor_m: float  # [m]


class StageState(TypedDict):
    """:meth:`Microscope.state`."""

    t_s: float  # simulated time [s]
    stage: str  # engaged, withdrawn, approaching, withdrawing, stopped, spectroscopy, failed


class Feedback(TypedDict):
    """:meth:`Microscope.feedback`: the z loop."""

    setpoint: float  # amplitude setpoint [m]
    p_gain: float  # [m/m]
    i_gain: float  # [1/s]
    z_min: float  # z piezo range [m]
    z_max: float


class ScanSettings(TypedDict, total=False):
    """:meth:`Microscope.scan_settings`: the scanner's parameters of the next frame."""

    scan_size_x: float  # [m]
    scan_size_y: float
    scan_center_x: float  # [m], sample coordinates
    scan_center_y: float
    pixels_per_line: int
    lines: int
    line_rate: float  # [lines/s]
    slow_scan_direction: str  # 'up' or 'down'
    scan_angle: float  # [deg]


class Truth(TypedDict, total=False):
    """:meth:`Microscope.truth`: the emulator's ground truth now (zero where an imperfection is
    off)."""

    t_s: float
    hysteresis_x_m: float  # true minus commanded tip position [m]
    hysteresis_y_m: float
    creep_x_m: float
    creep_y_m: float
    drift_x_m: float  # the sample's drift since t = 0 [m]
    drift_y_m: float
    drift_z_m: float
    tip_radius_m: float  # the worn apex in force [m]
    second_apex_m: list  # a picked-up second apex (x, y, height) [m]; zeros without


class Signals(TypedDict, total=False):
    """:meth:`Microscope.signals`: the instrument's live values now (NaN where this mode has none:
    the frequency shift in tapping mode)."""

    t_s: float  # simulated time [s]
    x_m: float  # commanded tip position, sample coordinates [m]
    y_m: float
    z_m: float  # z piezo [m] (higher: retracted)
    motor_m: float  # coarse motor [m]
    amplitude_m: float  # oscillation amplitude, last lock-in output [m]
    phase_deg: float  # its phase [deg]
    amplitude_error_m: float  # setpoint - amplitude [m]
    frequency_Hz: float  # drive (AM) or PLL oscillator (FM) frequency [Hz]
    frequency_shift_Hz: float  # FM: f - centre frequency [Hz]
    drive_N: float  # drive force amplitude [N]
    deflection_m: float  # the last measured deflection sample [m]
    stage: str  # the z stage: engaged, withdrawn, approaching, ...
    feedback: bool  # the z loop regulates
    scanning: bool


class Trace(TypedDict):
    """:meth:`Microscope.oscilloscope`: the last samples of the measured deflection."""

    t0_s: float  # simulated time of the first sample [s]
    dt_s: float  # sample interval [s]
    deflection_m: list  # [m]
