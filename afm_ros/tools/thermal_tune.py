"""Thermal tune: calibrate a cantilever from its Brownian motion (no ROS).

The undriven point-mass cantilever ``m z'' + c z' + k z = F_th`` (``m = k / w0^2``,
``c = m w0 / Q``) is driven only by the thermal force of one-sided power spectral density
``S_F = 4 kB T c`` (fluctuation-dissipation, :meth:`Simulation.set_thermal`). Its one-sided
deflection PSD is

    S_z(f) = 4 kB T c / |k - m w^2 + i c w|^2
           = 2 kB T f0^3 / (pi Q k [(f0^2 - f^2)^2 + (f f0 / Q)^2])        [m^2/Hz]

(integral over f >= 0: kB T / k, equipartition). The thermal tune estimates the one-sided PSD of a
deflection record (Welch, Hann window, 50 % overlap) and fits ``A_w + S_z(f; f0, Q, k)`` with ``T``
known and ``A_w`` a white (detector) floor, in a band f0/3 .. 3 f0 around an initial peak estimate.
Each Welch bin scatters with relative standard deviation ``1 / sqrt(K_eff)`` (K_eff: the number of
averaged segments, corrected for their overlap), so the fit is weighted by ``model / sqrt(K_eff)``
(iteratively reweighted with the fitted model, which avoids the downward bias of weighting by the
noisy data). The standard uncertainties come from the fit covariance, with the correlation of
neighbouring Hann bins (4/9 between adjacent bins) included by a sandwich estimate.

The equipartition estimate ``k = kB T / <z^2>`` (Hutter and Bechhoefer 1993, Rev. Sci. Instrum. 64,
1868) is reported beside it, with the fitted white floor's variance ``A_w fs / 2`` removed from
``<z^2>``. A real optical-lever instrument measures the slope of the first flexural mode, not the
deflection of a point mass, and needs the mode-shape correction (0.817 for the deflection, 0.764
for the optical-lever slope; Butt and Jaschke 1995); it does not apply to this point-mass model.

The simulated record is never held whole: it is simulated and reduced to its Welch spectrum and
moments block by block (:class:`WelchAccumulator`), so memory stays ~30 MB for any ``--seconds``
(at most ``MAX_SECONDS``: the bound is CPU time). The defaults are the instrument's: the cantilever
node's temperature (295 K) and detector floor (100 fm/sqrt(Hz)), from
:data:`afm_ros.core.cantilever_params.INSTRUMENT_NOISE_SPECS`.
"""

from __future__ import annotations

import argparse
import json
import math
import signal
import sys
import threading
import time
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from afm_ros.core.cantilever_params import INSTRUMENT_NOISE_SPECS
from afm_ros.core.physics.forces import NoForce
from afm_ros.core.physics.noise import BOLTZMANN, detector_noise
from afm_ros.core.physics.parameters import CANTILEVER_SPECS, Cantilever, Drive
from afm_ros.core.physics.parameters import parse_number as _number
from afm_ros.core.physics.simulation import Simulation
from afm_ros.formats.chunk_layout import ChunkLayoutError, cdr_chunk
from afm_ros.formats.mcap_io import (
    SessionFileError,
    SessionScan,
    check_mcap_file,
    parameter_metadata,
    read_session,
)
from afm_ros.formats.user_files import parse_yaml
from afm_ros.tools.figures import pyplot, write_csv

DEFAULT_SECONDS = 1.0  # [s] of simulated record: ~0.5 s of CPU, f0 to ~0.03 %, Q and k to ~1.5 %
# The tune emulates tuning the instrument, so its defaults are the cantilever node's (room
# temperature and a typical optical-beam-deflection floor), from the one place that defines them.
INSTRUMENT_TEMPERATURE = INSTRUMENT_NOISE_SPECS["temperature"].default  # [K]
INSTRUMENT_DETECTOR_NOISE = INSTRUMENT_NOISE_SPECS[
    "detector_noise_density"
].default  # [m/sqrt(Hz)]
SAMPLES_PER_PERIOD = 20  # output samples per resonance period: fs = 20 f0 (Nyquist 10 f0)
STEPS_PER_PERIOD = 220  # RK4 steps per resonance period (the project default), decimation 11
BINS_PER_LINEWIDTH = 16  # Welch resolution: the peak's full width f0/Q spans 16 bins
SETTLE_TAU = 20  # amplitude decay times tau = 2 Q / w0 discarded before recording (start at rest)
BAND = (1.0 / 3.0, 3.0)  # fit band in units of the initial peak estimate
MIN_SEGMENTS = 16  # Welch averages needed for a meaningful weighted fit
SEGMENTS_PER_BATCH = 64  # Welch segments computed at once (a streamed record's memory: one batch)
BLOCK_SAMPLES = (
    2**18
)  # deflection samples simulated at once (2 MB; ~0.3 s of record at the defaults)
# Memory no longer grows with --seconds (the record is streamed); the bound is the time: 1e4 s of
# record takes ~80 min of CPU (CPU_PER_SECOND, measured on the project's 2-core machine) and gives
# Q and k to ~0.013 %, far below any calibration's other errors; beyond it a typo (1e9) would run
# for years.
MAX_SECONDS = 1e4  # [s]
CPU_PER_SECOND = 0.48  # [s of CPU per s of record] measured: 1 s record 0.47-0.49 s
PROGRESS_SECONDS = 30.0  # [s] records longer than this show a progress bar


def _duration_text(seconds: float) -> str:
    for unit, size in (("h", 3600.0), ("min", 60.0)):
        if seconds >= size:
            return f"{seconds / size:.3g} {unit}"
    return f"{seconds:.3g} s"


# --- model --------------------------------------------------------------------------------------
def sho_thermal_psd(f, f0: float, q: float, k: float, temperature: float):
    """One-sided thermal deflection PSD [m^2/Hz] of the damped harmonic oscillator (see module
    doc)."""
    f = np.asarray(f, dtype=float)
    denom = (f0 * f0 - f * f) ** 2 + (f * f0 / q) ** 2
    return 2.0 * BOLTZMANN * temperature * f0**3 / (math.pi * q * k * denom)


def tune_model(f, f0: float, q: float, k: float, white: float, temperature: float):
    """White floor ``white`` [m^2/Hz] plus :func:`sho_thermal_psd`."""
    return white + sho_thermal_psd(f, f0, q, k, temperature)


# --- spectrum
# -------------------------------------------------------------------------------------
@dataclass
class Spectrum:
    f: np.ndarray  # [Hz]
    psd: np.ndarray  # one-sided [m^2/Hz]
    segments: int  # Welch segments averaged
    effective_averages: (
        float  # segments corrected for the 50 % overlap (1/K_eff: relative variance)
    )
    bin_correlation: np.ndarray  # correlation of bins 0, 1, 2, 3 apart (Hann: 1, 4/9, 1/36, 0)


class WelchAccumulator:
    """Welch PSD (Hann, 50 % overlap, mean detrended, one-sided density, as ``scipy.signal.welch``)
    and the mean and variance of a record fed in pieces of any size.

    Segments are computed in batches of ``SEGMENTS_PER_BATCH`` and each sample enters the moments
    once, in pieces fixed by the record alone, so the result does not depend on how the record was
    fed; memory is one batch (about 2 MB of samples at the defaults), whatever the record's length.
    """

    def __init__(self, sample_rate: float, nperseg: int):
        self.sample_rate = float(sample_rate)
        self.nperseg = int(nperseg)
        self.step = self.nperseg - self.nperseg // 2
        self._pending = np.empty(0)  # samples from the start of the next segment on
        self._psd_sum = None
        self.segments = 0
        self._moments = (
            0,
            0.0,
            0.0,
        )  # samples before _pending: count, mean [m], squared deviations [m^2]

    def add(self, z) -> None:
        z = np.asarray(z, dtype=float)
        self._pending = z if self._pending.size == 0 else np.concatenate([self._pending, z])
        while self._complete_segments() >= SEGMENTS_PER_BATCH:
            self._batch(SEGMENTS_PER_BATCH)

    def _complete_segments(self) -> int:
        n = self._pending.size
        return (n - self.nperseg) // self.step + 1 if n >= self.nperseg else 0

    def _batch(self, count: int) -> None:
        from scipy.signal import welch

        _, psd = welch(
            self._pending[: (count - 1) * self.step + self.nperseg],
            fs=self.sample_rate,
            window="hann",
            nperseg=self.nperseg,
            noverlap=self.nperseg // 2,
        )
        self._psd_sum = psd * count if self._psd_sum is None else self._psd_sum + psd * count
        self.segments += count
        self._moments = _combine(self._moments, self._pending[: count * self.step])
        self._pending = self._pending[count * self.step :]

    @property
    def samples(self) -> int:
        return self._moments[0] + self._pending.size

    @property
    def available_segments(self) -> int:
        """Welch segments complete so far (those :meth:`spectrum` averages)."""
        return self.segments + self._complete_segments()

    @property
    def variance(self) -> float:
        """<(z - <z>)^2> [m^2] of every sample added."""
        n, _, m2 = _combine(self._moments, self._pending)
        return m2 / n if n else float("nan")

    def spectrum(self) -> Spectrum:
        """The Welch spectrum of every complete segment so far, with its averaging statistics;
        ValueError (naming --seconds) below ``MIN_SEGMENTS`` segments."""
        from scipy.signal import get_window

        nperseg, step = self.nperseg, self.step
        segments = self.available_segments
        if segments < MIN_SEGMENTS:
            need = ((MIN_SEGMENTS - 1) * step + nperseg) / self.sample_rate
            raise ValueError(
                f"--seconds={self.samples / self.sample_rate:g} s is too short for the thermal "
                "tune: "
                f"{segments} Welch segments of {nperseg} samples; at least {need:.3g} s needed "
                f"for {MIN_SEGMENTS}"
            )
        if self._complete_segments():
            self._batch(self._complete_segments())
        f = np.fft.rfftfreq(nperseg, 1.0 / self.sample_rate)
        psd = self._psd_sum / segments
        w = get_window("hann", nperseg)
        w2 = np.sum(w * w)
        # variance of the average of overlapping segments (Welch 1967): 1/K * (1 + 2 sum (1 - j/K)
        # c_j^2)
        c = [
            np.sum(w[: nperseg - j * step] * w[j * step :]) / w2
            for j in range(1, nperseg // step + 1)
        ]
        factor = 1.0 + 2.0 * sum(
            (1.0 - j / segments) * cj * cj for j, cj in enumerate(c, 1) if j < segments
        )
        # correlation of periodogram bins m apart (Gaussian data): |sum w^2 exp(-2 pi i m n / N)|^2
        # / (sum w^2)^2
        n = np.arange(nperseg)
        rho = np.array(
            [
                abs(np.sum(w * w * np.exp(-2j * np.pi * m * n / nperseg))) ** 2 / w2**2
                for m in range(4)
            ]
        )
        return Spectrum(f, psd, segments, segments / factor, rho)


def _combine(moments: tuple, z: np.ndarray) -> tuple:
    """(count, mean, sum of squared deviations) of ``moments`` and the samples ``z`` together
    (Chan, Golub and LeVeque's pairwise update)."""
    n_a, mean_a, m2_a = moments
    n_b = z.size
    if n_b == 0:
        return moments
    mean_b = float(np.mean(z))
    m2_b = float(np.sum((z - mean_b) ** 2))
    n = n_a + n_b
    delta = mean_b - mean_a
    return n, mean_a + delta * n_b / n, m2_a + m2_b + delta * delta * n_a * n_b / n


def welch_psd(z, sample_rate: float, nperseg: int) -> Spectrum:
    """One-sided PSD by Welch (Hann, 50 % overlap, mean detrended) with its averaging
    statistics."""
    acc = WelchAccumulator(sample_rate, nperseg)
    acc.add(z)
    return acc.spectrum()


def default_nperseg(cantilever: Cantilever, sample_rate: float) -> int:
    """Segment length giving ``BINS_PER_LINEWIDTH`` bins across the peak's full width f0/Q."""
    linewidth = cantilever.resonance_frequency / cantilever.quality_factor
    return int(round(sample_rate * BINS_PER_LINEWIDTH / linewidth))


# --- simulated record
# -----------------------------------------------------------------------------
@dataclass
class ThermalRecord:
    """A deflection record (thermal motion + detector noise) reduced to what the tune uses."""

    spectrum: Spectrum  # Welch PSD of the whole record
    samples: int  # deflection samples in the record
    variance: float  # <(z - <z>)^2> [m^2]
    sample_rate: float  # [Hz]
    temperature: float  # [K]
    detector_density: float  # [m/sqrt(Hz)]
    cantilever: Cantilever
    z: np.ndarray | None = (
        None  # the samples, kept for a record read from a session (None: simulated)
    )
    requested_seconds: float | None = None  # set when Ctrl-C ended a simulated record early

    @property
    def seconds(self) -> float:
        return self.samples / self.sample_rate

    @classmethod
    def of(
        cls,
        z,
        sample_rate: float,
        temperature: float,
        detector_density: float,
        cantilever: Cantilever,
        nperseg: int | None = None,
    ) -> "ThermalRecord":
        """The record of the samples ``z`` [m] (kept as ``z``)."""
        acc = WelchAccumulator(sample_rate, nperseg or default_nperseg(cantilever, sample_rate))
        acc.add(z)
        return cls(
            acc.spectrum(),
            acc.samples,
            acc.variance,
            sample_rate,
            temperature,
            detector_density,
            cantilever,
            np.asarray(z),
        )


def _check_positive(value, flag: str, unit: str, allow_zero: bool = False) -> float:
    if (
        isinstance(value, bool)
        or not isinstance(value, (int, float))
        or not math.isfinite(value)
        or value < 0
        or (value == 0 and not allow_zero)
    ):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{flag}={value!r} {unit} must be a finite number {bound}")
    return float(value)


def simulate_thermal(
    cantilever: Cantilever,
    temperature: float,
    seconds: float,
    seed: int = 0,
    detector_density: float = 0.0,
    samples_per_period: int = SAMPLES_PER_PERIOD,
    steps_per_period: int = STEPS_PER_PERIOD,
    nperseg: int | None = None,
    interactive: bool = False,
) -> ThermalRecord:
    """Deflection record of the undriven cantilever at ``temperature`` [K], ``seconds`` [s] long.

    RK4 at ``steps_per_period`` steps per resonance period, one output sample every
    ``steps_per_period // samples_per_period`` steps; the first ``SETTLE_TAU`` decay times from
    rest are discarded. Detector noise of density ``detector_density`` [m/sqrt(Hz)] is added to the
    samples from the seed's detector stream (by output sample index). The record is simulated and
    reduced (:class:`WelchAccumulator`) in blocks of ``BLOCK_SAMPLES``, so memory does not grow
    with ``seconds`` (at most ``MAX_SECONDS``); the noise is counter-based, so the samples are
    those of one long run. ``interactive`` (the command line): a progress bar on stderr for records
    of more than ``PROGRESS_SECONDS``, and Ctrl-C ends the record at the next block
    (``requested_seconds`` says so; KeyboardInterrupt if it holds fewer than ``MIN_SEGMENTS`` Welch
    segments).
    """

    temperature = _check_positive(temperature, "--temperature", "K")
    seconds = _check_positive(seconds, "--seconds", "s")
    if seconds > MAX_SECONDS:
        tau = 2.0 * cantilever.quality_factor / cantilever.omega0
        raise ValueError(
            f"--seconds={seconds:g} s is too long: at most {MAX_SECONDS:g} s (about "
            f"{MAX_SECONDS * CPU_PER_SECOND / 60:.0f} min of CPU on an idle core of the project's "
            f"machine, hours on a busy one; the uncertainties of Q and k shrink "
            f"only as 1/sqrt(seconds), to {100 * math.sqrt(tau / MAX_SECONDS):.2g} % there)"
        )
    detector_density = _check_positive(
        detector_density, "--detector-noise", "m/sqrt(Hz)", allow_zero=True
    )
    if steps_per_period % samples_per_period:
        raise ValueError(
            f"steps_per_period={steps_per_period} must be a multiple of "
            f"samples_per_period={samples_per_period}"
        )
    f0 = cantilever.resonance_frequency
    fs = f0 * samples_per_period
    acc = WelchAccumulator(fs, nperseg or default_nperseg(cantilever, fs))
    sim = Simulation(cantilever, Drive(f0, 0.0), NoForce(), 0.0, steps_per_period)
    sim.set_thermal(temperature, seed)
    tau = 2.0 * cantilever.quality_factor / cantilever.omega0
    sim.advance(int(math.ceil(SETTLE_TAU * tau / sim.dt)), record=False)
    decimation = steps_per_period // samples_per_period
    count = int(round(seconds * fs))
    with (
        _ctrl_c_stops(interactive) as stop,
        tqdm(
            total=count,
            unit="S",
            unit_scale=True,
            desc="thermal tune",
            file=sys.stderr,
            disable=not interactive or seconds <= PROGRESS_SECONDS,
        ) as bar,
    ):
        wall0 = time.monotonic()
        for block, first in enumerate(range(0, count, BLOCK_SAMPLES)):
            if stop.is_set():
                break
            n = min(BLOCK_SAMPLES, count - first)
            started = time.monotonic()
            z = sim.advance(n * decimation, decimation).z  # n samples: every decimation-th step
            if detector_density > 0.0:
                z = z + detector_noise(seed, first, n, detector_density, 1.0 / fs)
            acc.add(z)
            bar.update(n)
            if block == 1 and interactive and seconds > PROGRESS_SECONDS:
                # the second block (the first compiled the kernel): this machine's rate, said once
                rate = (time.monotonic() - started) / (n / fs)
                left = (count - first - n) / fs * rate
                bar.write(
                    f"thermal tune: {seconds:g} s of record take about "
                    f"{_duration_text(time.monotonic() - wall0 + left)} here ({rate:.3g} s per "
                    "second of "
                    f"record measured now); Ctrl-C stops and fits what is done",
                    file=sys.stderr,
                )
    interrupted = acc.samples < count
    if interrupted and acc.available_segments < MIN_SEGMENTS:
        raise KeyboardInterrupt  # nothing worth tuning on yet
    return ThermalRecord(
        acc.spectrum(),
        acc.samples,
        acc.variance,
        fs,
        temperature,
        detector_density,
        cantilever,
        requested_seconds=seconds if interrupted else None,
    )


@contextmanager
def _ctrl_c_stops(enabled: bool):
    """An Event that Ctrl-C sets (instead of raising KeyboardInterrupt at any line) while enabled,
    in the main thread; elsewhere, or disabled, an Event nobody sets."""
    stop = threading.Event()
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield stop
        return
    previous = signal.signal(signal.SIGINT, lambda signum, frame: stop.set())
    try:
        yield stop
    finally:
        signal.signal(signal.SIGINT, previous)


# --- recorded session ----------------------------------------------------------------------------
DEFLECTION_SUFFIX = "cantilever/deflection"


def _session_value(params: dict, name: str, path) -> float:

    if name not in params:
        raise ValueError(
            f"{path}: the session's cantilever parameters lack {name!r} "
            f"(recorded by an afm_ros recorder? it stores them as metadata)"
        )
    value = parse_yaml(str(params[name])[:1000], f"{path}: parameter {name}")
    try:
        return float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{path}: parameter {name}={params[name]!r} is not a number") from None


def record_from_session(path, namespace: str | None = None) -> ThermalRecord:
    """The undriven cantilever's deflection record from a recorded session (``.mcap``).

    Uses the ``<namespace>/cantilever/deflection`` chunks (the longest run of consecutive sample
    indices) and the cantilever's recorded parameters: the drive must be off (free_amplitude 0),
    the temperature > 0; the first ``SETTLE_TAU`` decay times after the start are dropped.
    Raises ValueError naming the file and what is wrong.
    """

    try:
        p = check_mcap_file(path)
    except SessionFileError as exc:
        raise ValueError(str(exc)) from None
    scan = SessionScan(p)
    chunks: dict[str, list] = {}
    for m in read_session(p, scan):
        if not m.topic.endswith(DEFLECTION_SUFFIX):
            continue
        try:
            header, samples = cdr_chunk(m.data)
        except ChunkLayoutError:
            continue
        chunks.setdefault(m.topic[: -len(DEFLECTION_SUFFIX)].rstrip("/"), []).append(
            (header, samples)
        )
    if not chunks:
        raise ValueError(f"{p}: no {DEFLECTION_SUFFIX} chunks recorded")
    if namespace is None:
        if len(chunks) > 1:
            raise ValueError(
                f"{p}: deflection of several namespaces ({', '.join(sorted(chunks))}); "
                f"choose one with --namespace"
            )
        namespace = next(iter(chunks))
    namespace = "/" + namespace.strip("/") if namespace.strip("/") else ""
    if namespace not in chunks:
        raise ValueError(
            f"{p}: no deflection under namespace {namespace or '/'!r}; "
            f"recorded: {', '.join(sorted(n or '/' for n in chunks))}"
        )
    params = parameter_metadata(scan).get(f"{namespace}/cantilever")
    if params is None:
        raise ValueError(f"{p}: no recorded parameters of {namespace}/cantilever")
    drive = _session_value(params, "free_amplitude", p)
    if drive != 0.0:
        raise ValueError(
            f"{p}: the drive was on (free_amplitude={drive:g} m); a thermal tune needs the "
            f"undriven cantilever: record with free_amplitude 0"
        )
    temperature = _session_value(params, "temperature", p)
    if temperature <= 0.0:
        raise ValueError(
            f"{p}: temperature={temperature:g} K: no thermal motion to tune on (needs > 0)"
        )
    cantilever = Cantilever(
        _session_value(params, "spring_constant", p),
        _session_value(params, "resonance_frequency", p),
        _session_value(params, "quality_factor", p),
    )
    parts = sorted(chunks[namespace], key=lambda hs: hs[0].first_sample_index)
    interval = parts[0][0].sample_interval
    runs, current, next_index = [], [], None
    for header, samples in parts:
        if header.sample_interval != interval:
            raise ValueError(
                f"{p}: the sample interval changed during the session "
                f"({interval:g} s, then {header.sample_interval:g} s)"
            )
        if next_index is not None and header.first_sample_index != next_index:
            runs.append(current)
            current = []
        current.append((header, samples))
        next_index = header.first_sample_index + samples.shape[0]
    runs.append(current)
    run = max(runs, key=lambda r: sum(s.shape[0] for _, s in r))
    t0 = run[0][0].t_start
    z = np.concatenate([s for _, s in run])
    tau = 2.0 * cantilever.quality_factor / cantilever.omega0
    skip = max(0, int(math.ceil((SETTLE_TAU * tau - t0) / interval)))
    needed = (
        default_nperseg(cantilever, 1.0 / interval) * (MIN_SEGMENTS + 1) // 2
    )  # MIN_SEGMENTS at 50 % overlap
    if z.size - skip < needed:
        raise ValueError(
            f"{p}: {(z.size - skip) * interval:.3g} s of contiguous deflection after settling "
            f"is too short for a thermal tune; record at least "
            f"{(needed * interval + max(0.0, SETTLE_TAU * tau - t0)):.2g} s"
        )
    return ThermalRecord.of(
        z[skip:].copy(),
        1.0 / interval,
        temperature,
        _session_value(params, "detector_noise_density", p),
        cantilever,
    )


# --- fit
# ------------------------------------------------------------------------------------------
@dataclass
class TuneFit:
    f0: float  # [Hz]
    q: float
    k: float  # [N/m]
    white: float  # [m^2/Hz]
    f0_err: float  # standard uncertainties
    q_err: float
    k_err: float
    white_err: float
    band: tuple  # (f_low, f_high) [Hz]
    bins: int
    chi2_per_dof: float
    temperature: float

    def model(self, f):
        return tune_model(f, self.f0, self.q, self.k, self.white, self.temperature)


def initial_estimate(spectrum: Spectrum, temperature: float):
    """(f0, Q, k, white) from the peak bin, its half-power width and the PSD area
    (equipartition)."""
    f, psd = spectrum.f[1:], spectrum.psd[1:]
    smooth = np.convolve(psd, np.ones(5) / 5.0, mode="same")
    i = int(np.argmax(smooth))
    f0 = float(f[i])
    half = smooth[i] / 2.0
    lo, hi = i, i
    while lo > 0 and smooth[lo] > half:
        lo -= 1
    while hi < f.size - 1 and smooth[hi] > half:
        hi += 1
    q = f0 / max(f[hi] - f[lo], f[1] - f[0])
    white = float(np.median(psd[f > min(5 * f0, 0.8 * f[-1])])) if np.any(f > 5 * f0) else 0.0
    area = float(np.sum(psd - white) * (f[1] - f[0]))
    k = BOLTZMANN * temperature / area if area > 0 else 1.0
    return f0, q, k, white


def fit_thermal_tune(
    spectrum: Spectrum, temperature: float, band=BAND, iterations: int = 3
) -> TuneFit:
    """Weighted least-squares fit of ``A_w + S_z(f; f0, Q, k)`` (``T`` known) in the band
    ``band[0] f0 .. band[1] f0`` of the initial peak estimate; standard uncertainties from the
    covariance, including the correlation of neighbouring Welch bins."""
    from scipy.optimize import curve_fit

    temperature = _check_positive(temperature, "--temperature", "K")
    p0 = initial_estimate(spectrum, temperature)
    f0i = p0[0]
    sel = (spectrum.f >= band[0] * f0i) & (spectrum.f <= band[1] * f0i) & (spectrum.f > 0)
    f, psd = spectrum.f[sel], spectrum.psd[sel]
    if f.size < 8:
        raise ValueError(
            f"only {f.size} spectrum bins in the fit band; a longer segment is needed"
        )
    scale = float(np.max(psd))  # normalized parameters: x = (f0/f0i, Q/Qi, k/ki, white/scale)
    ref = np.array([p0[0], p0[1], p0[2], scale])

    def model(fx, a, b, c, d):
        return tune_model(fx, a * ref[0], b * ref[1], c * ref[2], d * ref[3], temperature) / scale

    x = np.array([1.0, 1.0, 1.0, max(p0[3], 0.0) / scale])
    y = psd / scale
    rel = 1.0 / math.sqrt(spectrum.effective_averages)
    sigma = y * rel  # first pass: data weights; then the fitted model's expected scatter
    for _ in range(iterations + 1):
        x, _ = curve_fit(model, f, y, p0=x, sigma=sigma, absolute_sigma=True, maxfev=20000)
        sigma = model(f, *x) * rel
    # sandwich covariance with the banded bin correlation: (J'WJ)^-1 J'W C W J (J'WJ)^-1
    jac = np.empty((f.size, 4))
    for j in range(4):
        h = 1e-6 * max(abs(x[j]), 1e-3)
        xp, xm = x.copy(), x.copy()
        xp[j] += h
        xm[j] -= h
        jac[:, j] = (model(f, *xp) - model(f, *xm)) / (2 * h)
    jw = jac / sigma[:, None] ** 2
    bread = np.linalg.inv(jac.T @ jw)
    cov_y = np.diag(sigma**2)
    for m, r in enumerate(spectrum.bin_correlation[1:], 1):
        off = r * sigma[:-m] * sigma[m:]
        cov_y += np.diag(off, m) + np.diag(off, -m)
    cov = bread @ (jw.T @ cov_y @ jw) @ bread
    err = np.sqrt(np.diag(cov)) * ref
    val = x * ref
    resid = (y - model(f, *x)) / sigma
    return TuneFit(
        float(val[0]),
        float(val[1]),
        float(val[2]),
        float(val[3]),
        float(err[0]),
        float(err[1]),
        float(err[2]),
        float(err[3]),
        (float(f[0]), float(f[-1])),
        int(f.size),
        float(np.sum(resid**2) / (f.size - 4)),
        temperature,
    )


def equipartition_k(
    variance: float, temperature: float, white: float = 0.0, sample_rate: float = 0.0
) -> float:
    """Hutter-Bechhoefer ``k = kB T / <z^2>`` [N/m] from the record's variance [m^2], with the
    white floor's variance ``white * sample_rate / 2`` removed (0: none)."""
    var = float(variance) - white * sample_rate / 2.0
    return BOLTZMANN * temperature / var if var > 0 else float("inf")


# --- the whole tune
# -------------------------------------------------------------------------------
@dataclass
class TuneResult:
    record: ThermalRecord
    spectrum: Spectrum
    fit: TuneFit
    k_equipartition: float  # [N/m]
    k_equipartition_rel_err: float  # sqrt(tau / T_rec), tau = 2 Q / w0 (fitted Q, f0)
    notes: tuple = ()  # lines printed under the first (defaults used, an interruption)

    def summary(self) -> dict:
        c, fit = self.record.cantilever, self.fit
        return {
            "temperature_K": self.record.temperature,
            "seconds_s": self.record.seconds,
            "sample_rate_Hz": self.record.sample_rate,
            "detector_noise_m_per_sqrtHz": self.record.detector_density,
            "welch_segments": self.spectrum.segments,
            "welch_effective_averages": self.spectrum.effective_averages,
            "resolution_Hz": float(self.spectrum.f[1] - self.spectrum.f[0]),
            "fit_band_Hz": list(fit.band),
            "fit_bins": fit.bins,
            "chi2_per_dof": fit.chi2_per_dof,
            "true": {
                "resonance_frequency_Hz": c.resonance_frequency,
                "quality_factor": c.quality_factor,
                "spring_constant_N_per_m": c.spring_constant,
            },
            "fit": {
                "resonance_frequency_Hz": fit.f0,
                "resonance_frequency_err_Hz": fit.f0_err,
                "quality_factor": fit.q,
                "quality_factor_err": fit.q_err,
                "spring_constant_N_per_m": fit.k,
                "spring_constant_err_N_per_m": fit.k_err,
                "white_floor_m2_per_Hz": fit.white,
                "white_floor_err_m2_per_Hz": fit.white_err,
            },
            "equipartition": {
                "spring_constant_N_per_m": self.k_equipartition,
                "spring_constant_err_N_per_m": self.k_equipartition * self.k_equipartition_rel_err,
            },
            "interrupted": self.record.requested_seconds is not None,
            "notes": list(self.notes),
        }

    def text(self) -> str:
        c, fit = self.record.cantilever, self.fit
        rel = self.k_equipartition_rel_err
        return "\n".join(
            [
                f"thermal tune: T = {self.record.temperature:g} K, record {self.record.seconds:g} "
                "s at "
                f"{self.record.sample_rate:g} Hz, detector noise {self.record.detector_density:g} "
                "m/sqrt(Hz), "
                f"{self.spectrum.segments} Welch segments",
                *self.notes,
                f"f0 = {fit.f0:.2f} +- {fit.f0_err:.2f} Hz   (true {c.resonance_frequency:g})",
                f"Q  = {fit.q:.3f} +- {fit.q_err:.3f}   (true {c.quality_factor:g})",
                f"k  = {fit.k:.4f} +- {fit.k_err:.4f} N/m   (true {c.spring_constant:g})",
                f"white floor = {fit.white:.3e} +- {fit.white_err:.1e} m^2/Hz; chi2/dof = "
                f"{fit.chi2_per_dof:.3f}",
                f"equipartition k = kB T / <z^2> = {self.k_equipartition:.4f} +- "
                f"{self.k_equipartition * rel:.4f} N/m (floor removed)",
            ]
        )


def thermal_tune(
    cantilever: Cantilever,
    temperature: float = INSTRUMENT_TEMPERATURE,
    seconds: float = DEFAULT_SECONDS,
    seed: int = 0,
    detector_density: float = INSTRUMENT_DETECTOR_NOISE,
    nperseg: int | None = None,
) -> TuneResult:
    """Simulate (streamed, :func:`simulate_thermal`), fit the spectrum and compute the
    equipartition estimate. The defaults are the instrument's (the cantilever node's temperature
    and detector floor)."""
    record = simulate_thermal(
        cantilever, temperature, seconds, seed, detector_density, nperseg=nperseg
    )
    return tune_record(record)


def tune_record(record: ThermalRecord, notes: tuple = ()) -> TuneResult:
    """Fit and equipartition estimate of a deflection record (simulated or recorded)."""
    fit = fit_thermal_tune(record.spectrum, record.temperature)
    k_eq = equipartition_k(record.variance, record.temperature, fit.white, record.sample_rate)
    if record.requested_seconds is not None:
        notes = (
            f"interrupted (Ctrl-C) after {record.seconds:g} s of the {record.requested_seconds:g} "
            "s "
            f"requested: tuned on the record simulated so far",
            *notes,
        )
    return TuneResult(
        record, record.spectrum, fit, k_eq, equipartition_rel_err(record, fit), tuple(notes)
    )


def equipartition_rel_err(record: ThermalRecord, fit: TuneFit) -> float:
    """Approximate relative standard error of the equipartition k: the thermal mean square's
    sqrt(tau / T_rec) (tau = 2 Q / w0), and with a floor of variance s_d^2 = A_w fs / 2 its own
    scatter 2 s_d^4 / N, the cross term 4 s_x^2 s_d^2 / N and the fitted floor's uncertainty."""
    tau = 2.0 * fit.q / (2.0 * math.pi * fit.f0)
    var_x = BOLTZMANN * record.temperature / fit.k  # thermal mean square (fitted)
    var_d = max(fit.white, 0.0) * record.sample_rate / 2.0
    n = record.samples
    rel2 = (
        tau / record.seconds
        + (2.0 * var_d**2 + 4.0 * var_x * var_d) / (n * var_x**2)
        + (fit.white_err * record.sample_rate / 2.0 / var_x) ** 2
    )
    return math.sqrt(rel2)


# --- output
# ---------------------------------------------------------------------------------------
CSV_COLUMNS = ["f_Hz", "psd_m2_per_Hz", "fit_m2_per_Hz"]


def write_outputs(result: TuneResult, out: Path) -> list[Path]:

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sp, fit = result.spectrum, result.fit
    model = fit.model(sp.f)
    paths = [
        write_csv(
            out / "thermal_tune.csv",
            CSV_COLUMNS,
            (
                {"f_Hz": a, "psd_m2_per_Hz": b, "fit_m2_per_Hz": c}
                for a, b, c in zip(sp.f, sp.psd, model)
            ),
        )
    ]
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 5))
    pos = sp.f > 0
    ax.loglog(sp.f[pos], sp.psd[pos], "-", color="0.6", lw=0.7, label="Welch PSD")
    band = (sp.f >= fit.band[0]) & (sp.f <= fit.band[1])
    ax.loglog(sp.f[pos], model[pos], "b--", lw=0.8, label="model (outside the fit band)")
    ax.loglog(
        sp.f[band],
        model[band],
        "r-",
        lw=1.5,
        label=f"fit: f0 = {fit.f0:.1f} Hz, Q = {fit.q:.2f}, k = {fit.k:.3f} N/m",
    )
    if fit.white > 0:
        ax.axhline(
            fit.white, color="k", ls=":", lw=0.8, label=f"white floor {fit.white:.2e} m²/Hz"
        )
    ax.set_xlabel("frequency [Hz]")
    ax.set_ylabel("deflection PSD [m²/Hz]")
    ax.set_title(f"Thermal tune, T = {result.record.temperature:g} K, {result.record.seconds:g} s")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(out / "thermal_tune.png", dpi=110)
    plt.close(fig)
    paths.append(out / "thermal_tune.png")
    with open(out / "thermal_tune.json", "w") as fh:
        json.dump(result.summary(), fh, indent=1)
    paths.append(out / "thermal_tune.json")
    (out / "thermal_tune.txt").write_text(result.text() + "\n")
    paths.append(out / "thermal_tune.txt")
    return paths


# --- command line
# ---------------------------------------------------------------------------------
HELP = (
    "thermal tune: PSD of the undriven cantilever's Brownian motion, SHO fit (f0, Q, k) and "
    "equipartition k"
)


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="study_out", help="output folder (default ./study_out)")
    p.add_argument(
        "--temperature",
        type=_number,
        default=None,
        metavar="K",
        help=f"temperature [K] of the thermal force, > 0 (default {INSTRUMENT_TEMPERATURE:g}: the "
        f"instrument's, the cantilever node's temperature)",
    )
    p.add_argument(
        "--seconds",
        type=_number,
        default=DEFAULT_SECONDS,
        metavar="S",
        help=f"simulated record length [s], > 0, at most {MAX_SECONDS:g} (default "
        f"{DEFAULT_SECONDS:g}; "
        f"about {CPU_PER_SECOND:g} s of CPU per second of record, memory independent of it)",
    )
    p.add_argument(
        "--seed", type=_number, default=0, help="noise seed, integer in [0, 2^63) (default 0)"
    )
    p.add_argument(
        "--session",
        default=None,
        metavar="FILE.mcap",
        help="tune on a recorded session instead of a simulation: its cantilever/deflection, "
        "recorded with free_amplitude 0 and temperature > 0 (temperature and cantilever from "
        "its recorded parameters; the simulation flags are then ignored)",
    )
    p.add_argument(
        "--namespace", default=None, help="with --session: the namespace whose cantilever to use"
    )
    p.add_argument(
        "--detector-noise",
        dest="detector_noise",
        type=_number,
        default=None,
        metavar="D",
        help=f"white detector noise density [m/sqrt(Hz)] added to the samples, >= 0 (default "
        f"{INSTRUMENT_DETECTOR_NOISE:g}: the instrument's, the cantilever node's "
        f"detector_noise_density; 0 = none)",
    )
    group = p.add_argument_group("cantilever parameters (SI units)")
    for name in ("spring_constant", "resonance_frequency", "quality_factor"):
        spec = CANTILEVER_SPECS[name]
        unit = f" [{spec.unit}]" if spec.unit and spec.unit != "1" else ""
        group.add_argument(
            "--" + name.replace("_", "-"),
            dest=name,
            type=_number,
            default=spec.default,
            metavar="X",
            help=f"{spec.description}{unit}; default {spec.default:g}, range {spec.range_text()}",
        )


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``thermal`` subcommand to ``afm_study``'s subparsers."""
    p = subparsers.add_parser("thermal", help=HELP, description=HELP)
    _add_arguments(p)
    return p


def run(args, prog: str = "afm_study thermal") -> int:
    """Run the thermal tune from parsed flags; 0 on success, 2 (one line on stderr) for a bad
    value, 130 after Ctrl-C (the tune of the record simulated so far is written if it is long
    enough)."""
    defaults = []
    if args.temperature is None:
        args.temperature = INSTRUMENT_TEMPERATURE
        defaults.append(f"--temperature {INSTRUMENT_TEMPERATURE:g} K")
    if args.detector_noise is None:
        args.detector_noise = INSTRUMENT_DETECTOR_NOISE
        defaults.append(f"--detector-noise {INSTRUMENT_DETECTOR_NOISE:g} m/sqrt(Hz)")
    notes = (
        ()
        if args.session or not defaults
        else (
            f"defaults used: {' and '.join(defaults)} (the instrument's: the cantilever node's "
            f"temperature and detector_noise_density)",
        )
    )
    try:
        cantilever = Cantilever(
            args.spring_constant, args.resonance_frequency, args.quality_factor
        )
        seed = args.seed
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2**63:
            raise ValueError(f"--seed={seed!r} must be an integer in [0, 2^63)")
        for flag, value in (
            ("--temperature", args.temperature),
            ("--seconds", args.seconds),
            ("--detector-noise", args.detector_noise),
        ):
            if isinstance(value, str):
                raise ValueError(f"{flag}={value!r} is not a number")
        if args.session:
            result = tune_record(record_from_session(args.session, args.namespace))
        else:
            record = simulate_thermal(
                cantilever,
                args.temperature,
                args.seconds,
                seed,
                args.detector_noise,
                interactive=True,
            )
            result = tune_record(record, notes)
        paths = write_outputs(result, Path(args.out))
    except ValueError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"{prog}: interrupted (Ctrl-C); nothing written", file=sys.stderr)
        return 130
    print(result.text())
    print("wrote " + ", ".join(str(p) for p in paths))
    return 130 if result.record.requested_seconds is not None else 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m afm_ros.tools.thermal_tune", description=HELP)
    _add_arguments(parser)
    return run(parser.parse_args(argv), parser.prog)


if __name__ == "__main__":
    sys.exit(main())
