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

The equipartition estimate ``k = kB T / <z^2>`` (Hutter and Bechhoefer 1993, Rev. Sci. Instrum.
64, 1868) is reported beside it, with the fitted white floor's variance ``A_w fs / 2`` removed from
``<z^2>``. A real optical-lever instrument measures the slope of the first flexural mode, not the
deflection of a point mass, and needs the mode-shape correction (0.817 for the deflection,
0.764 for the optical-lever slope; Butt and Jaschke 1995); it does not apply to this point-mass model.
"""
from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from afm_ros.core.physics.noise import BOLTZMANN
from afm_ros.core.physics.parameters import CANTILEVER_SPECS, Cantilever
from afm_ros.core.physics.parameters import parse_number as _number

DEFAULT_SECONDS = 1.0  # [s] of simulated record: ~0.5 s of CPU, f0 to ~0.03 %, Q and k to ~1.5 %
SAMPLES_PER_PERIOD = 20  # output samples per resonance period: fs = 20 f0 (Nyquist 10 f0)
STEPS_PER_PERIOD = 220  # RK4 steps per resonance period (the project default), decimation 11
BINS_PER_LINEWIDTH = 16  # Welch resolution: the peak's full width f0/Q spans 16 bins
SETTLE_TAU = 20  # amplitude decay times tau = 2 Q / w0 discarded before recording (start at rest)
BAND = (1.0 / 3.0, 3.0)  # fit band in units of the initial peak estimate
MIN_SEGMENTS = 16  # Welch averages needed for a meaningful weighted fit


# --- model --------------------------------------------------------------------------------------
def sho_thermal_psd(f, f0: float, q: float, k: float, temperature: float):
    """One-sided thermal deflection PSD [m^2/Hz] of the damped harmonic oscillator (see module doc)."""
    f = np.asarray(f, dtype=float)
    denom = (f0 * f0 - f * f) ** 2 + (f * f0 / q) ** 2
    return 2.0 * BOLTZMANN * temperature * f0 ** 3 / (math.pi * q * k * denom)


def tune_model(f, f0: float, q: float, k: float, white: float, temperature: float):
    """White floor ``white`` [m^2/Hz] plus :func:`sho_thermal_psd`."""
    return white + sho_thermal_psd(f, f0, q, k, temperature)


# --- simulated record -----------------------------------------------------------------------------
@dataclass
class ThermalRecord:
    z: np.ndarray  # measured deflection samples [m] (thermal motion + detector noise)
    sample_rate: float  # [Hz]
    temperature: float  # [K]
    detector_density: float  # [m/sqrt(Hz)]
    cantilever: Cantilever

    @property
    def seconds(self) -> float:
        return self.z.size / self.sample_rate


def _check_positive(value, flag: str, unit: str, allow_zero: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) \
            or value < 0 or (value == 0 and not allow_zero):
        bound = ">= 0" if allow_zero else "> 0"
        raise ValueError(f"{flag}={value!r} {unit} must be a finite number {bound}")
    return float(value)


def simulate_thermal(cantilever: Cantilever, temperature: float, seconds: float, seed: int = 0,
                     detector_density: float = 0.0, samples_per_period: int = SAMPLES_PER_PERIOD,
                     steps_per_period: int = STEPS_PER_PERIOD) -> ThermalRecord:
    """Deflection record of the undriven cantilever at ``temperature`` [K], ``seconds`` [s] long.

    RK4 at ``steps_per_period`` steps per resonance period, one output sample every
    ``steps_per_period // samples_per_period`` steps; the first ``SETTLE_TAU`` decay times from
    rest are discarded. Detector noise of density ``detector_density`` [m/sqrt(Hz)] is added to the
    samples from the seed's detector stream (by output sample index).
    """
    from afm_ros.core.physics.forces import NoForce
    from afm_ros.core.physics.noise import detector_noise
    from afm_ros.core.physics.parameters import Drive
    from afm_ros.core.physics.simulation import Simulation

    temperature = _check_positive(temperature, "--temperature", "K")
    seconds = _check_positive(seconds, "--seconds", "s")
    detector_density = _check_positive(detector_density, "--detector-noise", "m/sqrt(Hz)", allow_zero=True)
    if steps_per_period % samples_per_period:
        raise ValueError(f"steps_per_period={steps_per_period} must be a multiple of "
                         f"samples_per_period={samples_per_period}")
    f0 = cantilever.resonance_frequency
    sim = Simulation(cantilever, Drive(f0, 0.0), NoForce(), 0.0, steps_per_period)
    sim.set_thermal(temperature, seed)
    tau = 2.0 * cantilever.quality_factor / cantilever.omega0
    sim.advance(int(math.ceil(SETTLE_TAU * tau / sim.dt)), record=False)
    decimation = steps_per_period // samples_per_period
    count = int(round(seconds * f0 * samples_per_period))
    z = sim.advance(count * decimation, decimation).z
    z = z[:count]
    fs = f0 * samples_per_period
    if detector_density > 0.0:
        z = z + detector_noise(seed, 0, z.size, detector_density, 1.0 / fs)
    return ThermalRecord(z, fs, temperature, detector_density, cantilever)


# --- recorded session ----------------------------------------------------------------------------
DEFLECTION_SUFFIX = "cantilever/deflection"


def _session_value(params: dict, name: str, path) -> float:
    import yaml

    if name not in params:
        raise ValueError(f"{path}: the session's cantilever parameters lack {name!r} "
                         f"(recorded by an afm_ros recorder? it stores them as metadata)")
    value = yaml.safe_load(params[name])
    if isinstance(value, str):
        value = float(value)
    return float(value)


def record_from_session(path, namespace: str | None = None) -> ThermalRecord:
    """The undriven cantilever's deflection record from a recorded session (``.mcap``).

    Uses the ``<namespace>/cantilever/deflection`` chunks (the longest run of consecutive sample
    indices) and the cantilever's recorded parameters: the drive must be off (free_amplitude 0),
    the temperature > 0; the first ``SETTLE_TAU`` decay times after the start are dropped.
    Raises ValueError naming the file and what is wrong.
    """
    from afm_ros.formats.chunk_layout import ChunkLayoutError, cdr_chunk
    from afm_ros.formats.mcap_io import SessionFileError, SessionScan, check_mcap_file, parameter_metadata, read_session

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
        chunks.setdefault(m.topic[:-len(DEFLECTION_SUFFIX)].rstrip("/"), []).append((header, samples))
    if not chunks:
        raise ValueError(f"{p}: no {DEFLECTION_SUFFIX} chunks recorded")
    if namespace is None:
        if len(chunks) > 1:
            raise ValueError(f"{p}: deflection of several namespaces ({', '.join(sorted(chunks))}); "
                             f"choose one with --namespace")
        namespace = next(iter(chunks))
    namespace = "/" + namespace.strip("/") if namespace.strip("/") else ""
    if namespace not in chunks:
        raise ValueError(f"{p}: no deflection under namespace {namespace or '/'!r}; "
                         f"recorded: {', '.join(sorted(n or '/' for n in chunks))}")
    params = parameter_metadata(scan).get(f"{namespace}/cantilever")
    if params is None:
        raise ValueError(f"{p}: no recorded parameters of {namespace}/cantilever")
    drive = _session_value(params, "free_amplitude", p)
    if drive != 0.0:
        raise ValueError(f"{p}: the drive was on (free_amplitude={drive:g} m); a thermal tune needs the "
                         f"undriven cantilever: record with free_amplitude 0")
    temperature = _session_value(params, "temperature", p)
    if temperature <= 0.0:
        raise ValueError(f"{p}: temperature={temperature:g} K: no thermal motion to tune on (needs > 0)")
    cantilever = Cantilever(_session_value(params, "spring_constant", p),
                            _session_value(params, "resonance_frequency", p),
                            _session_value(params, "quality_factor", p))
    parts = sorted(chunks[namespace], key=lambda hs: hs[0].first_sample_index)
    interval = parts[0][0].sample_interval
    runs, current, next_index = [], [], None
    for header, samples in parts:
        if header.sample_interval != interval:
            raise ValueError(f"{p}: the sample interval changed during the session "
                             f"({interval:g} s, then {header.sample_interval:g} s)")
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
    needed = default_nperseg(cantilever, 1.0 / interval) * (MIN_SEGMENTS + 1) // 2  # MIN_SEGMENTS at 50 % overlap
    if z.size - skip < needed:
        raise ValueError(f"{p}: {(z.size - skip) * interval:.3g} s of contiguous deflection after settling "
                         f"is too short for a thermal tune; record at least "
                         f"{(needed * interval + max(0.0, SETTLE_TAU * tau - t0)):.2g} s")
    return ThermalRecord(z[skip:].copy(), 1.0 / interval, temperature,
                         _session_value(params, "detector_noise_density", p), cantilever)


# --- spectrum -------------------------------------------------------------------------------------
@dataclass
class Spectrum:
    f: np.ndarray  # [Hz]
    psd: np.ndarray  # one-sided [m^2/Hz]
    segments: int  # Welch segments averaged
    effective_averages: float  # segments corrected for the 50 % overlap (1/K_eff: relative variance)
    bin_correlation: np.ndarray  # correlation of bins 0, 1, 2, 3 apart (Hann: 1, 4/9, 1/36, 0)


def welch_psd(z, sample_rate: float, nperseg: int) -> Spectrum:
    """One-sided PSD by Welch (Hann, 50 % overlap, mean detrended) with its averaging statistics."""
    from scipy.signal import get_window, welch

    z = np.asarray(z, dtype=float)
    nperseg = int(nperseg)
    step = nperseg - nperseg // 2
    segments = (z.size - nperseg) // step + 1 if z.size >= nperseg else 0
    if segments < MIN_SEGMENTS:
        need = ((MIN_SEGMENTS - 1) * step + nperseg) / sample_rate
        raise ValueError(f"--seconds={z.size / sample_rate:g} s is too short for the thermal tune: "
                         f"{segments} Welch segments of {nperseg} samples; at least {need:.3g} s needed "
                         f"for {MIN_SEGMENTS}")
    f, psd = welch(z, fs=sample_rate, window="hann", nperseg=nperseg, noverlap=nperseg // 2)
    w = get_window("hann", nperseg)
    w2 = np.sum(w * w)
    # variance of the average of overlapping segments (Welch 1967): 1/K * (1 + 2 sum (1 - j/K) c_j^2)
    c = [np.sum(w[: nperseg - j * step] * w[j * step:]) / w2 for j in range(1, nperseg // step + 1)]
    factor = 1.0 + 2.0 * sum((1.0 - j / segments) * cj * cj for j, cj in enumerate(c, 1) if j < segments)
    # correlation of periodogram bins m apart (Gaussian data): |sum w^2 exp(-2 pi i m n / N)|^2 / (sum w^2)^2
    n = np.arange(nperseg)
    rho = np.array([abs(np.sum(w * w * np.exp(-2j * np.pi * m * n / nperseg))) ** 2 / w2 ** 2 for m in range(4)])
    return Spectrum(f, psd, segments, segments / factor, rho)


def default_nperseg(cantilever: Cantilever, sample_rate: float) -> int:
    """Segment length giving ``BINS_PER_LINEWIDTH`` bins across the peak's full width f0/Q."""
    linewidth = cantilever.resonance_frequency / cantilever.quality_factor
    return int(round(sample_rate * BINS_PER_LINEWIDTH / linewidth))


# --- fit ------------------------------------------------------------------------------------------
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
    """(f0, Q, k, white) from the peak bin, its half-power width and the PSD area (equipartition)."""
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


def fit_thermal_tune(spectrum: Spectrum, temperature: float, band=BAND, iterations: int = 3) -> TuneFit:
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
        raise ValueError(f"only {f.size} spectrum bins in the fit band; a longer segment is needed")
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
    cov_y = np.diag(sigma ** 2)
    for m, r in enumerate(spectrum.bin_correlation[1:], 1):
        off = r * sigma[:-m] * sigma[m:]
        cov_y += np.diag(off, m) + np.diag(off, -m)
    cov = bread @ (jw.T @ cov_y @ jw) @ bread
    err = np.sqrt(np.diag(cov)) * ref
    val = x * ref
    resid = (y - model(f, *x)) / sigma
    return TuneFit(float(val[0]), float(val[1]), float(val[2]), float(val[3]),
                   float(err[0]), float(err[1]), float(err[2]), float(err[3]),
                   (float(f[0]), float(f[-1])), int(f.size), float(np.sum(resid ** 2) / (f.size - 4)),
                   temperature)


def equipartition_k(z, temperature: float, white: float = 0.0, sample_rate: float = 0.0) -> float:
    """Hutter-Bechhoefer ``k = kB T / <z^2>`` [N/m], with the white floor's variance
    ``white * sample_rate / 2`` removed from the mean square (0: none)."""
    z = np.asarray(z, dtype=float)
    var = float(np.mean((z - z.mean()) ** 2)) - white * sample_rate / 2.0
    return BOLTZMANN * temperature / var if var > 0 else float("inf")


# --- the whole tune -------------------------------------------------------------------------------
@dataclass
class TuneResult:
    record: ThermalRecord
    spectrum: Spectrum
    fit: TuneFit
    k_equipartition: float  # [N/m]
    k_equipartition_rel_err: float  # sqrt(tau / T_rec), tau = 2 Q / w0 (fitted Q, f0)

    def summary(self) -> dict:
        c, fit = self.record.cantilever, self.fit
        return {
            "temperature_K": self.record.temperature, "seconds_s": self.record.seconds,
            "sample_rate_Hz": self.record.sample_rate, "detector_noise_m_per_sqrtHz": self.record.detector_density,
            "welch_segments": self.spectrum.segments, "welch_effective_averages": self.spectrum.effective_averages,
            "resolution_Hz": float(self.spectrum.f[1] - self.spectrum.f[0]),
            "fit_band_Hz": list(fit.band), "fit_bins": fit.bins, "chi2_per_dof": fit.chi2_per_dof,
            "true": {"resonance_frequency_Hz": c.resonance_frequency, "quality_factor": c.quality_factor,
                     "spring_constant_N_per_m": c.spring_constant},
            "fit": {"resonance_frequency_Hz": fit.f0, "resonance_frequency_err_Hz": fit.f0_err,
                    "quality_factor": fit.q, "quality_factor_err": fit.q_err,
                    "spring_constant_N_per_m": fit.k, "spring_constant_err_N_per_m": fit.k_err,
                    "white_floor_m2_per_Hz": fit.white, "white_floor_err_m2_per_Hz": fit.white_err},
            "equipartition": {"spring_constant_N_per_m": self.k_equipartition,
                              "spring_constant_err_N_per_m": self.k_equipartition * self.k_equipartition_rel_err},
        }

    def text(self) -> str:
        c, fit = self.record.cantilever, self.fit
        rel = self.k_equipartition_rel_err
        return "\n".join([
            f"thermal tune: T = {self.record.temperature:g} K, record {self.record.seconds:g} s at "
            f"{self.record.sample_rate:g} Hz, detector noise {self.record.detector_density:g} m/sqrt(Hz), "
            f"{self.spectrum.segments} Welch segments",
            f"f0 = {fit.f0:.2f} +- {fit.f0_err:.2f} Hz   (true {c.resonance_frequency:g})",
            f"Q  = {fit.q:.3f} +- {fit.q_err:.3f}   (true {c.quality_factor:g})",
            f"k  = {fit.k:.4f} +- {fit.k_err:.4f} N/m   (true {c.spring_constant:g})",
            f"white floor = {fit.white:.3e} +- {fit.white_err:.1e} m^2/Hz; chi2/dof = {fit.chi2_per_dof:.3f}",
            f"equipartition k = kB T / <z^2> = {self.k_equipartition:.4f} +- "
            f"{self.k_equipartition * rel:.4f} N/m (floor removed)",
        ])


def thermal_tune(cantilever: Cantilever, temperature: float = 300.0, seconds: float = DEFAULT_SECONDS,
                 seed: int = 0, detector_density: float = 0.0, nperseg: int | None = None) -> TuneResult:
    """Simulate, estimate the PSD, fit it and compute the equipartition estimate."""
    return tune_record(simulate_thermal(cantilever, temperature, seconds, seed, detector_density), nperseg)


def tune_record(record: ThermalRecord, nperseg: int | None = None) -> TuneResult:
    """PSD, fit and equipartition estimate of a deflection record (simulated or recorded)."""
    cantilever, temperature = record.cantilever, record.temperature
    spectrum = welch_psd(record.z, record.sample_rate,
                         nperseg or default_nperseg(cantilever, record.sample_rate))
    fit = fit_thermal_tune(spectrum, temperature)
    k_eq = equipartition_k(record.z, temperature, fit.white, record.sample_rate)
    return TuneResult(record, spectrum, fit, k_eq, equipartition_rel_err(record, fit))


def equipartition_rel_err(record: ThermalRecord, fit: TuneFit) -> float:
    """Approximate relative standard error of the equipartition k: the thermal mean square's
    sqrt(tau / T_rec) (tau = 2 Q / w0), and with a floor of variance s_d^2 = A_w fs / 2 its own
    scatter 2 s_d^4 / N, the cross term 4 s_x^2 s_d^2 / N and the fitted floor's uncertainty."""
    tau = 2.0 * fit.q / (2.0 * math.pi * fit.f0)
    var_x = BOLTZMANN * record.temperature / fit.k  # thermal mean square (fitted)
    var_d = max(fit.white, 0.0) * record.sample_rate / 2.0
    n = record.z.size
    rel2 = (tau / record.seconds + (2.0 * var_d ** 2 + 4.0 * var_x * var_d) / (n * var_x ** 2)
            + (fit.white_err * record.sample_rate / 2.0 / var_x) ** 2)
    return math.sqrt(rel2)


# --- output ---------------------------------------------------------------------------------------
CSV_COLUMNS = ["f_Hz", "psd_m2_per_Hz", "fit_m2_per_Hz"]


def write_outputs(result: TuneResult, out: Path) -> list[Path]:
    from afm_ros.tools.study import _plt, write_csv

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    sp, fit = result.spectrum, result.fit
    model = fit.model(sp.f)
    paths = [write_csv(out / "thermal_tune.csv", CSV_COLUMNS,
                       ({"f_Hz": a, "psd_m2_per_Hz": b, "fit_m2_per_Hz": c} for a, b, c in zip(sp.f, sp.psd, model)))]
    plt = _plt()
    fig, ax = plt.subplots(figsize=(8, 5))
    pos = sp.f > 0
    ax.loglog(sp.f[pos], sp.psd[pos], "-", color="0.6", lw=0.7, label="Welch PSD")
    band = (sp.f >= fit.band[0]) & (sp.f <= fit.band[1])
    ax.loglog(sp.f[pos], model[pos], "b--", lw=0.8, label="model (outside the fit band)")
    ax.loglog(sp.f[band], model[band], "r-", lw=1.5,
              label=f"fit: f0 = {fit.f0:.1f} Hz, Q = {fit.q:.2f}, k = {fit.k:.3f} N/m")
    if fit.white > 0:
        ax.axhline(fit.white, color="k", ls=":", lw=0.8, label=f"white floor {fit.white:.2e} m²/Hz")
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


# --- command line ---------------------------------------------------------------------------------
HELP = "thermal tune: PSD of the undriven cantilever's Brownian motion, SHO fit (f0, Q, k) and equipartition k"


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--out", default="study_out", help="output folder (default ./study_out)")
    p.add_argument("--temperature", type=_number, default=300.0, metavar="K",
                   help="temperature [K] of the thermal force, > 0 (default 300)")
    p.add_argument("--seconds", type=_number, default=DEFAULT_SECONDS, metavar="S",
                   help=f"simulated record length [s], > 0 (default {DEFAULT_SECONDS:g})")
    p.add_argument("--seed", type=_number, default=0, help="noise seed, integer in [0, 2^63) (default 0)")
    p.add_argument("--session", default=None, metavar="FILE.mcap",
                   help="tune on a recorded session instead of a simulation: its cantilever/deflection, "
                        "recorded with free_amplitude 0 and temperature > 0 (temperature and cantilever from "
                        "its recorded parameters; the simulation flags are then ignored)")
    p.add_argument("--namespace", default=None, help="with --session: the namespace whose cantilever to use")
    p.add_argument("--detector-noise", dest="detector_noise", type=_number, default=0.0, metavar="D",
                   help="white detector noise density [m/sqrt(Hz)] added to the samples, >= 0 (default 0)")
    group = p.add_argument_group("cantilever parameters (SI units)")
    for name in ("spring_constant", "resonance_frequency", "quality_factor"):
        spec = CANTILEVER_SPECS[name]
        unit = f" [{spec.unit}]" if spec.unit and spec.unit != "1" else ""
        group.add_argument("--" + name.replace("_", "-"), dest=name, type=_number, default=spec.default,
                           metavar="X", help=f"{spec.description}{unit}; default {spec.default:g}, "
                                             f"range {spec.range_text()}")


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``thermal`` subcommand to ``afm_study``'s subparsers."""
    p = subparsers.add_parser("thermal", help=HELP, description=HELP)
    _add_arguments(p)
    return p


def run(args, prog: str = "afm_study thermal") -> int:
    """Run the thermal tune from parsed flags; 0 on success, 2 (one line on stderr) for a bad value."""
    try:
        cantilever = Cantilever(args.spring_constant, args.resonance_frequency, args.quality_factor)
        seed = args.seed
        if isinstance(seed, bool) or not isinstance(seed, int) or not 0 <= seed < 2 ** 63:
            raise ValueError(f"--seed={seed!r} must be an integer in [0, 2^63)")
        for flag, value in (("--temperature", args.temperature), ("--seconds", args.seconds),
                            ("--detector-noise", args.detector_noise)):
            if isinstance(value, str):
                raise ValueError(f"{flag}={value!r} is not a number")
        if args.session:
            result = tune_record(record_from_session(args.session, args.namespace))
        else:
            result = thermal_tune(cantilever, args.temperature, args.seconds, seed, args.detector_noise)
        paths = write_outputs(result, Path(args.out))
    except ValueError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    print(result.text())
    print("wrote " + ", ".join(str(p) for p in paths))
    return 0


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(prog="python -m afm_ros.tools.thermal_tune", description=HELP)
    _add_arguments(parser)
    return run(parser.parse_args(argv), parser.prog)


if __name__ == "__main__":
    sys.exit(main())
