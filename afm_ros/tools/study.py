"""afm_study: the seed notebook's tapping-mode study as a command-line tool.

``python -m afm_ros.tools.study SUBCOMMAND [options]`` (also installed as ``afm_study``) writes PNG
figures and CSV tables (header row, SI units in the column names) into ``--out DIR``:

- ``notebook``    every figure of the seed notebook, corrected, plus ``summary.md``
- ``convergence`` L1 error vs time step for Euler, notebook Verlet and RK4 (fitted orders)
- ``sweep``       steady-state observables vs z_base (approach, optional retract)
- ``trajectory``  tip position, drive and tip-sample force vs time at one z_base
- ``fm-curve``    FM: df, drive and dissipation vs distance of the self-excited steady state
                  (shooting)
- ``bench``       moved: says to run ``python -m benchmarks.bench`` from the repository
                  (not installed)
- ``scan``        image a sample with the wired instrument (.gwy, PNGs, summary), see
                  :mod:`afm_ros.tools.scan`

The reusable pieces (:func:`convergence_study`, :func:`fit_order`, :func:`sweep`,
:func:`trajectory`) are plain functions so tests can call them on tiny inputs.
"""

from __future__ import annotations

import argparse
import importlib
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
from tqdm import tqdm

from afm_ros.core.cantilever_params import MATERIAL_FIELDS, material_values
from afm_ros.core.physics import (
    CANTILEVER_SPECS,
    DMT_SPECS,
    Cantilever,
    DMTSample,
    Drive,
    NoForce,
    Simulation,
    analyze,
    free_solution,
    make_force_model,
    steady_amplitude_phase,
    steady_state,
)
from afm_ros.core.physics.analysis import SteadyStateResult
from afm_ros.core.physics.forces import FORCE_MODELS
from afm_ros.core.physics.integrators import METHODS
from afm_ros.core.physics.materials import MATERIALS
from afm_ros.core.physics.noise import detector_noise
from afm_ros.core.physics.parameters import DISSIPATION_SPECS, DRIVE_FORCE_SPEC, NOISE_SPECS
from afm_ros.core.physics.parameters import parse_number as _number
from afm_ros.core.physics.self_excited import FM_CURVE_COLUMNS, fm_curve
from afm_ros.core.physics.shooting import periodic_orbit
from afm_ros.core.physics.simulation import Samples
from afm_ros.tools import (
    bimodal_study,
    contrast,
    dataset,
    drive_tune,
    force_reconstruction,
    scan,
    thermal_tune,
)
from afm_ros.tools.figures import pyplot, write_csv

# --- parameters from flags ----------------------------------------------------------------
# Every cantilever and sample spec gets a flag --name-with-dashes; z_base is per subcommand.
PARAM_SPECS = {
    name: spec
    for name, spec in {**CANTILEVER_SPECS, **DMT_SPECS, **DISSIPATION_SPECS}.items()
    if name not in ("z_base", "integrator")
}  # the integrator is --method


def _int_at_least(minimum: int):
    """argparse type: an integer >= minimum (argparse reports a bad value and exits with status
    2)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer >= {minimum}") from None
        if value < minimum:
            raise argparse.ArgumentTypeError(f"{value} is not an integer >= {minimum}")
        return value

    return parse


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


def add_param_flags(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group("cantilever and sample parameters (SI units)")
    for name, spec in PARAM_SPECS.items():
        unit = f" [{spec.unit}]" if spec.unit and spec.unit != "1" else ""
        if name == "drive_frequency":  # follows --resonance-frequency unless given
            group.add_argument(
                _flag(name),
                dest=name,
                type=_number,
                default=None,
                metavar="X",
                help=f"{spec.description}{unit}; default: the resonance frequency, "
                f"range {spec.range_text()}",
            )
            continue
        if name in MATERIAL_FIELDS:  # None: the --material's value, else the spec default
            group.add_argument(
                _flag(name),
                dest=name,
                type=_number,
                default=None,
                metavar="X",
                help=f"{spec.description}{unit}; default: the --material's value, else "
                f"{spec.default:g}; range {spec.range_text()}",
            )
            continue
        group.add_argument(
            _flag(name),
            dest=name,
            type=_number,
            default=spec.default,
            metavar="X",
            help=f"{spec.description}{unit}; default {spec.default:g}, range {spec.range_text()}",
        )
    group.add_argument(
        "--material",
        default="",
        metavar="NAME",
        help="named sample material (docs/materials.md): "
        + ", ".join(MATERIALS)
        + "; explicit --sample-* / --hamaker-* values win",
    )
    group.add_argument(
        "--drive-force",
        dest="drive_force",
        type=_number,
        default=None,
        metavar="X",
        help=f"{DRIVE_FORCE_SPEC.description} [N]; overrides --free-amplitude; "
        f"range {DRIVE_FORCE_SPEC.range_text()}",
    )


def physics_from_args(ns: argparse.Namespace):
    """Validated (Cantilever, Drive, DMTSample, steps_per_period) from parsed flags.

    Raises ValueError naming the field and allowed range for a bad value.
    """
    raw = {name: getattr(ns, name) for name in PARAM_SPECS}
    chosen = (
        material_values(getattr(ns, "material", "") or "")
        if getattr(ns, "material", "") in ("", *MATERIALS)
        else None
    )
    if chosen is None:
        raise ValueError(f"material={ns.material!r} is not known; allowed: {', '.join(MATERIALS)}")
    for name in MATERIAL_FIELDS:
        if raw[name] is None:
            raw[name] = chosen.get(name, PARAM_SPECS[name].default)
    if raw["drive_frequency"] is None:
        raw["drive_frequency"] = raw["resonance_frequency"]
    values = {name: PARAM_SPECS[name].validate(value) for name, value in raw.items()}
    cantilever = Cantilever(
        values["spring_constant"], values["resonance_frequency"], values["quality_factor"]
    )
    if getattr(ns, "drive_force", None) is not None:
        drive = Drive(values["drive_frequency"], DRIVE_FORCE_SPEC.validate(ns.drive_force))
    else:
        drive = Drive.from_free_amplitude(
            cantilever, values["free_amplitude"], values["drive_frequency"]
        )
    sample = DMTSample(**{name: values[name] for name in DMT_SPECS})
    ns.dissipation = {
        "viscosity": values["sample_viscosity"],
        "hamaker_retract": values["hamaker_constant_retract"],
    }
    return cantilever, drive, sample, values["steps_per_period"]


def parse_z_bases(text: str) -> list[float]:
    """``a,b,c`` or ``start:stop:step`` [m] (inclusive of stop) -> validated z_base values [m]."""
    spec = CANTILEVER_SPECS["z_base"]
    text = text.strip()
    if ":" in text:
        parts = text.split(":")
        if len(parts) != 3:
            raise ValueError(f"z_base range {text!r} must be start:stop:step in metres")
        start, stop, step = (
            spec.validate(_number(p)) if i < 2 else _number(p) for i, p in enumerate(parts)
        )
        if isinstance(step, str) or not math.isfinite(step) or step == 0:
            raise ValueError(f"z_base step={step!r} must be a non-zero number of metres")
        step = abs(step) if stop >= start else -abs(step)
        count = int(math.floor((stop - start) / step + 1e-9)) + 1
        if count > 100000:
            raise ValueError(f"z_base range {text!r} has {count} points; at most 100000 allowed")
        return [start + i * step for i in range(count)]
    values = [spec.validate(_number(p)) for p in text.split(",") if p.strip()]
    if not values:
        raise ValueError("z_base list is empty")
    return values


# --- memory bounds of the command line --------------------------------------------------------- A
# run keeps z, v and the force of every step it records (24 bytes per step; the noisy average and
# the trajectory's CSV rows more). The bounds are fixed, the same on every machine (a command that
# works on one works on all), and fit the free memory of a small laptop: 2e7 steps = 480 MB, e.g.
# 90 000 drive periods at the default 220 steps. trajectory.csv has one row per step and the figure
# one point per step: 1e6 steps (4500 periods at 220 steps, ~80 MB of CSV) is more than a plot
# shows.
MAX_RECORDED_STEPS = 20_000_000
MAX_TRAJECTORY_STEPS = 1_000_000


def check_recorded_steps(
    what: str, steps: int, hint: str, limit: int = MAX_RECORDED_STEPS
) -> None:
    """ValueError (one line: what would be kept, the limit, and ``hint``: the flag and its largest
    value) if ``steps`` recorded integration steps exceed ``limit``."""
    if steps > limit:
        raise ValueError(
            f"{what} would keep {steps:.3g} integration steps in memory ({steps * 24 / 2**30:.3g} "
            f"GiB); at most {limit:.3g} allowed: {hint}"
        )


def steady_window_steps(cantilever: Cantilever, steps_per_period: int) -> int:
    """Steps recorded per window by :func:`afm_ros.core.physics.steady_state` (its default window:
    max(5, ceil(Q / pi)) periods)."""
    return max(5, int(math.ceil(cantilever.quality_factor / math.pi))) * int(steps_per_period)


def _check_steady_state(cantilever: Cantilever, steps_per_period: int, source: str = "") -> None:
    periods = steady_window_steps(cantilever, steps_per_period) // steps_per_period
    q_max = math.floor(math.pi * (MAX_RECORDED_STEPS // steps_per_period))
    check_recorded_steps(
        f"a steady-state window of Q/pi = {periods} periods (--quality-factor="
        f"{cantilever.quality_factor:g}) at {steps_per_period} steps per period{source}",
        periods * steps_per_period,
        f"--quality-factor <= {q_max}"
        + ("" if source else " at this step count, or fewer --steps-per-period"),
    )


# --- reusable study logic ------------------------------------------------------------------
DEFAULT_CONVERGENCE_SPP = {
    # Euler is unstable below ~160 steps per period for Q = 25 (its growth factor per step exceeds
    # the damping), so its study starts higher. All values are integers (the drive is tabulated).
    "euler": (800, 1600, 3200, 6400, 12800),
    "verlet": (28, 56, 112, 224, 448, 896),
    "rk4": (28, 56, 112, 224, 448),
}


def l1_error(
    cantilever: Cantilever,
    drive: Drive,
    method: str,
    steps_per_period: int,
    periods: int = 100,
    window_periods: int = 20,
    z0: float = 0.0,
    v0: float = 0.0,
) -> float:
    """The notebook's L1 error dt * sum |z - z_exact| [m s] over the last ``window_periods`` of a
    free run."""
    sim = Simulation(
        cantilever,
        drive,
        NoForce(),
        0.0,
        steps_per_period,
        method,
        z0=z0,
        v0=v0,
        check_resolution=False,
    )
    sim.advance_periods(periods - window_periods)
    samples = sim.advance_periods(window_periods)
    z_exact, _ = free_solution(cantilever, drive, samples.t, z0, v0)
    return float(samples.dt * np.sum(np.abs(samples.z - z_exact)))


def convergence_study(
    cantilever: Cantilever | None = None,
    drive: Drive | None = None,
    spps: dict | None = None,
    periods: int = 100,
    window_periods: int = 20,
) -> list[dict]:
    """Rows {method, steps_per_period, dt_s, l1_error_m} for each method and step count."""
    cantilever = cantilever or Cantilever()
    drive = drive or Drive.from_free_amplitude(cantilever, 60e-9)
    rows = []
    for method, values in (spps or DEFAULT_CONVERGENCE_SPP).items():
        for spp in values:
            rows.append(
                {
                    "method": method,
                    "steps_per_period": int(spp),
                    "dt_s": 1.0 / (drive.frequency * spp),
                    "l1_error_m": l1_error(
                        cantilever, drive, method, spp, periods, window_periods
                    ),
                }
            )
    return rows


def fit_order(rows: list[dict], method: str) -> float:
    """Least-squares slope of log(L1 error) vs log(dt) for ``method`` (finite errors only)."""
    pts = [
        (r["dt_s"], r["l1_error_m"])
        for r in rows
        if r["method"] == method and math.isfinite(r["l1_error_m"]) and r["l1_error_m"] > 0
    ]
    if len(pts) < 2:
        return float("nan")
    dt, err = np.log(np.array(pts)).T
    return float(np.polyfit(dt, err, 1)[0])


SWEEP_COLUMNS = [
    "direction",
    "z_base_m",
    "amplitude_m",
    "phase_deg",
    "mean_deflection_m",
    "mean_force_N",
    "max_force_N",
    "min_force_N",
    "min_gap_m",
    "indentation_m",
    "drive_work_J",
    "damping_loss_J",
    "dissipated_energy_J",
    "virial_J",
    "harmonic2_m",
    "harmonic3_m",
    "periods_simulated",
    "converged",
    "amplitude_sem_m",
    "phase_sem_deg",
]
# ``--steady shooting`` rows carry the shooting's convergence after these (a waiting sweep writes
# SWEEP_COLUMNS only, as before): the method, Newton iterations (Jacobians), transient windows of
# ceil(Q / pi) periods run before the orbit was taken, Newton's correction of the state [m], the
# largest Floquet multiplier's modulus and whether all are inside the unit circle
SHOOTING_COLUMNS = [
    "steady_method",
    "newton_iterations",
    "transient_windows",
    "correction_m",
    "spectral_radius",
    "stable",
]
STEADY_METHODS = (
    "wait",
    "shooting",
)  # sweep's steady=: wait out the transient, or shoot (core/physics/shooting.py)


def sweep_columns(steady: str = "wait") -> list[str]:
    """The columns of sweep.csv for ``steady`` (``wait``: SWEEP_COLUMNS; ``shooting``: +
    SHOOTING_COLUMNS)."""
    return SWEEP_COLUMNS + (SHOOTING_COLUMNS if steady == "shooting" else [])


DETECTOR_NOISE_SPEC = NOISE_SPECS["detector_noise_density"]
NOISE_BLOCKS = 10  # sub-windows of a noisy average: their scatter gives the standard errors


def _sweep_row(direction: str, z_base: float, result, sem=(0.0, 0.0)) -> dict:
    a = result.analysis
    return {
        "direction": direction,
        "z_base_m": z_base,
        "amplitude_m": a.amplitude,
        "phase_deg": a.phase_deg,
        "mean_deflection_m": a.mean_deflection,
        "mean_force_N": a.mean_force,
        "max_force_N": a.max_force,
        "min_force_N": a.min_force,
        "min_gap_m": a.min_gap,
        "indentation_m": a.indentation,
        "drive_work_J": a.drive_work,
        "damping_loss_J": a.damping_loss,
        "dissipated_energy_J": a.tip_sample_dissipation,
        "virial_J": a.virial,
        "harmonic2_m": float(a.harmonics[1]),
        "harmonic3_m": float(a.harmonics[2]),
        "periods_simulated": result.periods_simulated,
        "converged": result.converged,
        "amplitude_sem_m": sem[0],
        "phase_sem_deg": sem[1],
    }


def _shooting_row(direction: str, z_base: float, orbit) -> dict:
    """A sweep row of a :class:`~afm_ros.core.physics.shooting.PeriodicOrbit`: its one-period
    analysis, ``periods_simulated`` all the periods it integrated, ``converged`` its own flag, and
    SHOOTING_COLUMNS."""
    row = _sweep_row(
        direction,
        z_base,
        SteadyStateResult(orbit.analysis, orbit.samples, orbit.periods, orbit.converged),
    )
    row.update(
        {
            "steady_method": "shooting",
            "newton_iterations": orbit.iterations,
            "transient_windows": orbit.restarts,
            "correction_m": orbit.correction,
            "spectral_radius": orbit.spectral_radius,
            "stable": orbit.stable,
        }
    )
    return row


def shooting_summary(rows: list[dict]) -> str:
    """One line on a shooting sweep's convergence: points converged and stable, the worst Newton
    correction, periods in all and at most per point, Newton iterations and transient windows."""
    worst = max(rows, key=lambda r: r["correction_m"])
    periods = [r["periods_simulated"] for r in rows]
    return (
        f"shooting: {sum(bool(r['converged']) for r in rows)}/{len(rows)} points converged, "
        f"{sum(bool(r['stable']) for r in rows)} stable; worst correction "
        f"{worst['correction_m']:.2g} m "
        f"(z_base {worst['z_base_m']:.4g} m, {worst['direction']}); {sum(periods)} periods in all "
        f"(at most {max(periods)} per point), {sum(r['newton_iterations'] for r in rows)} Newton "
        "iterations, "
        f"{sum(r['transient_windows'] for r in rows)} transient windows"
    )


def noisy_average(
    sim: Simulation,
    average_periods: int,
    detector_density: float = 0.0,
    settle_periods: int | None = None,
):
    """Settle, then analyse ``average_periods`` drive periods of a noisy run.

    Settling: ``settle_periods`` (default 10 amplitude decay times, 10 Q / pi periods) are run
    unrecorded. Detector noise of ``detector_density`` [m/sqrt(Hz)] (one sample per step, the
    seed's detector stream indexed by the absolute step) is added to the measured deflection only.
    Returns (SteadyStateResult with converged=False, (amplitude_sem [m], phase_sem [deg])): the
    standard errors come from the scatter of ``NOISE_BLOCKS`` equal sub-windows.
    """

    if settle_periods is None:
        settle_periods = int(math.ceil(10.0 * sim.cantilever.quality_factor / math.pi))
    sim.advance_periods(settle_periods) if settle_periods else None
    first = sim.noise_index
    samples = sim.advance_periods(average_periods)
    measured = samples.z + detector_noise(
        sim.noise_seed, first, samples.z.size, detector_density, sim.dt
    )
    result = analyze(samples, sim, measured_z=measured)
    spp = sim.steps_per_period
    blocks = max(1, min(NOISE_BLOCKS, average_periods))
    bounds = np.linspace(0, average_periods, blocks + 1).astype(int) * spp
    amps, phases = [], []
    for lo, hi in zip(bounds[:-1], bounds[1:]):
        part = Samples(
            samples.first_step + lo,
            1,
            samples.dt,
            samples.segment_start,
            samples.drive_phase0,
            samples.drive_frequency,
            samples.z_offset,
            samples.z[lo:hi],
            samples.v[lo:hi],
            samples.force[lo:hi],
        )
        block = analyze(part, sim, measured_z=measured[lo:hi])
        amps.append(block.amplitude)
        phases.append(block.phase_deg)
    sem = (
        (0.0, 0.0)
        if blocks < 2
        else (
            float(np.std(amps, ddof=1) / math.sqrt(blocks)),
            float(np.std(phases, ddof=1) / math.sqrt(blocks)),
        )
    )
    return SteadyStateResult(result, samples, settle_periods + average_periods, False), sem


def sweep(
    z_bases,
    cantilever: Cantilever | None = None,
    drive: Drive | None = None,
    force_model=None,
    steps_per_period: int = CANTILEVER_SPECS["steps_per_period"].default,
    method: str = CANTILEVER_SPECS["integrator"].default,
    retract: bool = False,
    progress: bool | None = None,
    amplitude_tol: float = 1e-14,
    phase_tol_deg: float = 1e-5,
    max_periods: int = 20000,
    temperature: float = 0.0,
    detector_density: float = 0.0,
    noise_seed: int = 0,
    average_periods: int = 200,
    event_beta: float | None = None,
    steady: str = "wait",
    shooting_tol: float | None = None,
) -> list[dict]:
    """Steady state at each z_base [m] in order (approach), then optionally back (retract).

    One simulation carries its state from point to point (``reconfigure(z_offset=...)``), so a
    retract continues from the approach's last steady state and hysteresis shows if the physics has
    it. Deterministic (temperature 0 [K] and detector_density 0 [m/sqrt(Hz)]): steady state =
    amplitude and phase change between successive windows below ``amplitude_tol`` [m] and
    ``phase_tol_deg`` [deg]. Noisy: a fixed settling time, then an average over ``average_periods``
    periods with standard errors (:func:`noisy_average`); ``converged`` is then False because no
    convergence test applies. ``event_beta``: rk4_event's near-surface fraction (None: the
    default).

    ``steady``: ``"wait"`` (the above) or ``"shooting"``: each point is the periodic orbit
    :func:`afm_ros.core.physics.shooting.periodic_orbit` finds from the previous point's state (the
    orbit the waiting method would reach from there, so branches are followed as by waiting), with
    Newton's correction below ``shooting_tol`` [m] (None: its default, 1e-14 m, as
    ``amplitude_tol``); its rows add SHOOTING_COLUMNS and ``converged`` is the orbit's.
    Deterministic sweeps only (a thermal force or detector noise has no periodic steady state).
    """

    z_bases = [float(z) for z in z_bases]
    cantilever = cantilever or Cantilever()
    drive = drive or Drive.from_free_amplitude(cantilever, 60e-9)
    force_model = force_model if force_model is not None else make_force_model("dmt")
    plan = [("approach", z) for z in z_bases]
    if retract:
        plan += [("retract", z) for z in reversed(z_bases[:-1])]
    sim = Simulation(cantilever, drive, force_model, plan[0][1], steps_per_period, method)
    if (
        event_beta is not None
    ):  # rk4_event's near-surface cut (afm_ros.core.physics.events), for studies
        sim.event_beta = float(event_beta)
    if steady not in STEADY_METHODS:
        raise ValueError(f"steady={steady!r} is not known; allowed: {', '.join(STEADY_METHODS)}")
    noisy = temperature > 0.0 or detector_density > 0.0
    if noisy and steady == "shooting":
        raise ValueError(
            f"steady='shooting' needs a deterministic sweep (temperature={temperature:g} K, "
            f"detector_density={detector_density:g} m/sqrt(Hz)): a noisy run has no periodic "
            "steady "
            "state; use steady='wait' (it averages), or temperature 0 and detector_density 0"
        )
    orbit_options = {} if shooting_tol is None else {"tol": shooting_tol}
    sim.set_thermal(temperature, noise_seed)
    if noisy:
        DETECTOR_NOISE_SPEC.validate(detector_density)
        if (
            isinstance(average_periods, bool)
            or int(average_periods) != average_periods
            or average_periods < 1
        ):
            raise ValueError(f"average_periods={average_periods!r} must be an integer >= 1")
    rows = []
    bar = tqdm(
        plan,
        desc="sweep",
        unit="z_base",
        disable=(len(plan) < 8) if progress is None else not progress,
        file=sys.stderr,
    )
    for direction, z_base in bar:
        sim.reconfigure(z_offset=z_base)
        if noisy:
            result, sem = noisy_average(sim, int(average_periods), detector_density)
            rows.append(_sweep_row(direction, z_base, result, sem))
            continue
        if steady == "shooting":
            rows.append(_shooting_row(direction, z_base, periodic_orbit(sim, **orbit_options)))
            continue
        result = steady_state(
            sim, amplitude_tol=amplitude_tol, phase_tol_deg=phase_tol_deg, max_periods=max_periods
        )
        rows.append(_sweep_row(direction, z_base, result))
    return rows


TRAJECTORY_COLUMNS = [
    "t_s",
    "deflection_m",
    "tip_position_m",
    "drive_force_N",
    "tip_sample_force_N",
]


def trajectory(
    z_base: float,
    cantilever: Cantilever | None = None,
    drive: Drive | None = None,
    force_model=None,
    steps_per_period: int = CANTILEVER_SPECS["steps_per_period"].default,
    method: str = CANTILEVER_SPECS["integrator"].default,
    periods: int = 5,
    from_rest_periods: int | None = None,
):
    """Time series over ``periods`` drive periods: steady state first, or ``from_rest_periods``
    from rest.

    Returns (columns dict of arrays, PeriodAnalysis of the recorded periods).
    """
    cantilever = cantilever or Cantilever()
    drive = drive or Drive.from_free_amplitude(cantilever, 60e-9)
    force_model = force_model if force_model is not None else make_force_model("dmt")
    sim = Simulation(cantilever, drive, force_model, z_base, steps_per_period, method)
    if from_rest_periods is None:
        steady_state(sim)
    else:
        sim.advance_periods(from_rest_periods)
    s = sim.advance_periods(periods)
    cols = {
        "t_s": s.t,
        "deflection_m": s.z,
        "tip_position_m": s.gap,
        "drive_force_N": drive.force * np.cos(s.drive_phase),
        "tip_sample_force_N": s.force,
    }
    return cols, analyze(s, sim)


# --- output helpers -----------------------------------------------------------------------
def _columns_to_rows(cols: dict):
    names = list(cols)
    return [dict(zip(names, vals)) for vals in zip(*(cols[n] for n in names))]


# --- subcommands ----------------------------------------------------------------------------
def cmd_convergence(ns, out: Path) -> int:
    cantilever, drive, _, _ = physics_from_args(ns)
    spps = {m: DEFAULT_CONVERGENCE_SPP[m] for m in ns.methods}
    if ns.quick:
        spps = {m: v[:3] for m, v in spps.items()}
    if ns.window_periods > ns.periods:
        raise ValueError(
            f"--window-periods={ns.window_periods} must be at most --periods={ns.periods}"
        )
    finest = max(max(v) for v in spps.values())
    check_recorded_steps(
        f"--periods={ns.periods} at up to {finest} steps per period",
        ns.periods * finest,
        f"--periods <= {MAX_RECORDED_STEPS // finest}",
    )
    rows = convergence_study(cantilever, drive, spps, ns.periods, ns.window_periods)
    write_csv(out / "convergence.csv", ["method", "steps_per_period", "dt_s", "l1_error_m"], rows)
    orders = {m: fit_order(rows, m) for m in spps}
    plot_convergence(rows, orders, out / "convergence.png")
    for m, p in orders.items():
        print(f"fitted order {m}: {p:.3f}")
    with open(out / "convergence_orders.json", "w") as fh:
        json.dump(orders, fh, indent=1)
    return 0


def plot_convergence(rows, orders, path: Path, title="L1 error vs time step (free oscillator)"):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 5))
    for m in orders:
        pts = [(r["dt_s"], r["l1_error_m"]) for r in rows if r["method"] == m]
        dt, err = np.array(pts).T
        ax.loglog(dt, err, "o-", label=f"{m} (fitted order {orders[m]:.2f})")
    ax.set_xlabel("time step dt [s]")
    ax.set_ylabel("L1 error over the last 20 periods [m s]")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def cmd_sweep(ns, out: Path) -> int:
    cantilever, drive, sample, spp = physics_from_args(ns)
    z_bases = parse_z_bases(ns.z_base)
    ns.temperature = NOISE_SPECS["temperature"].validate(ns.temperature)
    ns.detector_noise = DETECTOR_NOISE_SPEC.validate(ns.detector_noise)
    ns.noise_seed = NOISE_SPECS["noise_seed"].validate(ns.noise_seed)
    model = make_force_model(ns.force_model, sample, **ns.dissipation)
    noisy = ns.temperature > 0 or ns.detector_noise > 0
    if ns.steady == "shooting" and noisy:
        raise ValueError(
            f"--steady shooting needs a deterministic sweep: --temperature={ns.temperature:g} and "
            f"--detector-noise={ns.detector_noise:g} must both be 0 (a noisy run has no periodic "
            "steady state); a noisy sweep averages with --steady wait"
        )
    if ns.steady == "shooting":
        # one period recorded per map evaluation (at most 1e5 steps), the transient windows
        # unrecorded
        pass
    elif noisy:  # noisy_average: settling, then the average, recorded
        settle = int(math.ceil(10.0 * cantilever.quality_factor / math.pi))
        check_recorded_steps(
            f"--average-periods={ns.average_periods} at {spp} steps per period",
            ns.average_periods * spp,
            f"--average-periods <= {MAX_RECORDED_STEPS // spp}",
        )
        check_recorded_steps(
            f"settling 10 Q/pi = {settle} periods "
            f"(--quality-factor={cantilever.quality_factor:g}) "
            f"at {spp} steps per period",
            settle * spp,
            f"--quality-factor <= {math.floor(math.pi * (MAX_RECORDED_STEPS // spp) / 10)}",
        )
    else:
        _check_steady_state(cantilever, spp)
    rows = sweep(
        z_bases,
        cantilever,
        drive,
        model,
        spp,
        ns.method,
        ns.retract,
        progress=None if not ns.no_progress else False,
        temperature=ns.temperature,
        detector_density=ns.detector_noise,
        noise_seed=ns.noise_seed,
        average_periods=ns.average_periods,
        steady=ns.steady,
    )
    write_csv(out / "sweep.csv", sweep_columns(ns.steady), rows)
    plot_sweep(rows, out / "sweep.png")
    not_converged = [] if noisy else [r["z_base_m"] for r in rows if not r["converged"]]
    if ns.steady == "shooting":
        print(shooting_summary(rows))
        if not_converged:
            print(
                "warning: no periodic orbit within the transient windows at z_base "
                f"{not_converged}",
                file=sys.stderr,
            )
        unstable = [r["z_base_m"] for r in rows if r["converged"] and not r["stable"]]
        if unstable:
            print(f"warning: unstable orbit at z_base {unstable}", file=sys.stderr)
    elif not_converged:
        print(
            f"warning: no steady state within max periods at z_base {not_converged}",
            file=sys.stderr,
        )
    print(f"wrote {out / 'sweep.csv'} and {out / 'sweep.png'} ({len(rows)} points)")
    return 0


def plot_sweep(rows, path: Path):
    plt = pyplot()
    fig, axes = plt.subplots(2, 3, figsize=(13, 7), sharex=True)
    panels = [
        ("amplitude_m", 1e9, "amplitude [nm]"),
        ("phase_deg", 1, "phase lag [deg]"),
        ("mean_force_N", 1e9, "mean tip-sample force [nN]"),
        ("max_force_N", 1e9, "peak force [nN]"),
        ("min_gap_m", 1e9, "minimum gap [nm]"),
        ("dissipated_energy_J", 1e18, "E_ts per period [aJ]"),
    ]
    for ax, (col, scale, label) in zip(axes.flat, panels):
        for direction, style in (("approach", "o-"), ("retract", "s--")):
            pts = [(r["z_base_m"], r[col]) for r in rows if r["direction"] == direction]
            if pts:
                x, y = np.array(pts).T
                ax.plot(x * 1e9, y * scale, style, ms=3, label=direction)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("z_base [nm]")
    axes[0, 0].legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def cmd_trajectory(ns, out: Path) -> int:
    cantilever, drive, sample, spp = physics_from_args(ns)
    z_base = CANTILEVER_SPECS["z_base"].validate(_number(ns.z_base))
    model = make_force_model(ns.force_model, sample, **ns.dissipation)
    check_recorded_steps(
        f"--periods={ns.periods} at {spp} steps per period (one CSV row per step)",
        ns.periods * spp,
        f"--periods <= {MAX_TRAJECTORY_STEPS // spp}",
        MAX_TRAJECTORY_STEPS,
    )
    if ns.from_rest is None:
        _check_steady_state(cantilever, spp)
    else:
        check_recorded_steps(
            f"--from-rest={ns.from_rest} at {spp} steps per period",
            ns.from_rest * spp,
            f"--from-rest <= {MAX_RECORDED_STEPS // spp}",
        )
    cols, analysis = trajectory(
        z_base,
        cantilever,
        drive,
        model,
        spp,
        ns.method,
        ns.periods,
        None if ns.from_rest is None else ns.from_rest,
    )
    write_csv(out / "trajectory.csv", TRAJECTORY_COLUMNS, _columns_to_rows(cols))
    plot_trajectory(
        cols,
        out / "trajectory.png",
        f"z_base = {z_base * 1e9:g} nm, amplitude "
        f"{analysis.amplitude * 1e9:.3f} nm, phase {analysis.phase_deg:.3f} deg",
    )
    print(
        f"amplitude {analysis.amplitude:.6e} m, phase {analysis.phase_deg:.4f} deg; wrote "
        f"{out / 'trajectory.csv'}"
    )
    return 0


def plot_trajectory(cols, path: Path, title: str):
    plt = pyplot()
    fig, (ax1, ax3) = plt.subplots(2, 1, figsize=(9, 6), sharex=True)
    t_ms = cols["t_s"] * 1e3
    ax1.plot(t_ms, cols["tip_position_m"] * 1e9, "g-")
    ax1.set_ylabel("tip position (gap) [nm]", color="g")
    ax2 = ax1.twinx()
    ax2.plot(t_ms, cols["drive_force_N"] * 1e9, "b-")
    ax2.set_ylabel("drive force [nN]", color="b")
    ax1.set_title(title)
    ax3.plot(t_ms, cols["tip_sample_force_N"] * 1e9, "r-")
    ax3.set_ylabel("tip-sample force [nN]")
    ax3.set_xlabel("time [ms]")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


BENCH_MOVED = (
    "the speed benchmark is not part of the installed package (it compiles C baselines kept "
    "beside "
    "it in the repository's benchmarks/ folder); from the root of a checkout of the repository "
    "run: "
)


def cmd_bench(ns, out: Path) -> int:
    """The benchmark lives outside the package (benchmarks/bench.py), which never imports it: say
    what to run instead, with the flags given here, and fail (exit 2)."""
    command = (
        f"python -m benchmarks.bench --steps {ns.steps} --solve-ivp-periods {ns.solve_ivp_periods}"
    )
    print(
        f"afm_study bench: {BENCH_MOVED}{command}{' --no-startup' if ns.no_startup else ''}",
        file=sys.stderr,
    )
    return 2


def cmd_notebook(ns, out: Path) -> int:
    cantilever, drive, sample, _ = physics_from_args(ns)
    _check_steady_state(cantilever, 800 if ns.quick else 3200, " (the notebook's reference runs)")
    written = make_notebook(out, cantilever, drive, sample, quick=ns.quick)
    for path in written:
        print(f"wrote {path}")
    return 0


# --- the notebook ------------------------------------------------------------------------------
NOTEBOOK_SPP = 28  # the notebook's coarse step (dt = period / 28) for the free-oscillator figures
NOTEBOOK_DMT_SPP = 280  # the notebook's step count for the DMT run


def _free_run(cantilever, drive, method, spp, periods=100):
    sim = Simulation(cantilever, drive, NoForce(), 0.0, spp, method, check_resolution=False)
    return sim.advance_periods(periods)


def _line_plot(path, title, curves, xlabel="time [ms]", ylabel="z [nm]", ylim=None, xlim=None):
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(8, 4.5))
    for x, y, style, label in curves:
        ax.plot(x, y, style, label=label)
    ax.set_title(title)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    if ylim:
        ax.set_ylim(*ylim)
    if xlim:
        ax.set_xlim(*xlim)
    if any(c[3] for c in curves):
        ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def dmt_comparison(cantilever, drive, sample, z_base=40e-9, reference_spp=3200):
    """Frozen-force RK4 (notebook) vs corrected RK4 at ``z_base`` [m]: steady-state analyses.

    Returns a list of (label, method, steps_per_period, PeriodAnalysis, from_rest_analysis) where
    from_rest_analysis covers periods 95..100 of a run from rest, as the notebook's plot does.
    """
    out = []
    for label, method, spp in (
        ("notebook RK4, force frozen over the step", "rk4_frozen", NOTEBOOK_DMT_SPP),
        ("corrected RK4, force at every stage", "rk4", NOTEBOOK_DMT_SPP),
        ("corrected RK4, default step", "rk4", CANTILEVER_SPECS["steps_per_period"].default),
        ("notebook RK4, force frozen, fine step", "rk4_frozen", reference_spp),
        ("corrected RK4, converged reference", "rk4", reference_spp),
    ):
        model = make_force_model("dmt", sample)
        sim = Simulation(cantilever, drive, model, z_base, spp, method)
        steady = steady_state(sim, amplitude_tol=1e-15, phase_tol_deg=1e-6).analysis
        sim = Simulation(cantilever, drive, model, z_base, spp, method)
        sim.advance_periods(95)
        rest = analyze(sim.advance_periods(5), sim)
        out.append((label, method, spp, steady, rest))
    return out


def _summary_md(comparison, orders, z_base, cantilever, drive, where_45nm="") -> str:
    _where_45nm = where_45nm
    a_free, _ = steady_amplitude_phase(cantilever, drive)
    ref = comparison[-1][3]
    frozen, fixed = comparison[0][3], comparison[1][3]
    lines = [
        "# Seed notebook study, corrected",
        "",
        f"Cantilever k = {cantilever.spring_constant:g} N/m, f0 = "
        f"{cantilever.resonance_frequency:g} Hz, "
        f"Q = {cantilever.quality_factor:g}, drive F0 = {drive.force:.4g} N at "
        f"{drive.frequency:g} Hz "
        f"(free amplitude {a_free * 1e9:.3f} nm), DMT sample, z_base = {z_base * 1e9:g} nm.",
        "",
        "Step sizes: the notebook's time steps are not integer fractions of the drive period "
        "(its L1 study",
        "uses dt = 8e-7, 2e-7, 5e-8, 1e-8, 1e-9 s, i.e. 27.8 ... 22222 steps per period). The "
        "integrators",
        "here tabulate the drive per step, so they use an integer number of steps per period "
        "(spp): 28 for",
        "the coarse free-oscillator figures, 280 for the DMT run (as the notebook), and the spp "
        "values in",
        "`convergence.csv` for the error study.",
        "",
        "## Frozen-force RK4 (notebook) vs corrected RK4 at z_base = %g nm" % (z_base * 1e9),
        "",
        "Steady state (successive 8-period windows agree to 1e-15 m and 1e-6 deg). Energy "
        "balance error",
        "= (drive work - damping loss - tip-sample dissipation) / drive work, per period.",
        "",
        "| run | spp | amplitude [nm] | phase [deg] | min gap [nm] | peak force [nN] | E_ts per "
        "period [aJ] "
        "| energy balance error | amplitude, periods 95-100 from rest [nm] |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for label, method, spp, a, rest in comparison:
        balance = (a.drive_work - a.damping_loss - a.tip_sample_dissipation) / a.drive_work
        lines.append(
            f"| {label} (`{method}`) | {spp} | {a.amplitude * 1e9:.4f} | {a.phase_deg:.4f} | "
            f"{a.min_gap * 1e9:.4f} | {a.max_force * 1e9:.4f} | "
            f"{a.tip_sample_dissipation * 1e18:.4f} | "
            f"{balance:.2e} | {rest.amplitude * 1e9:.4f} |"
        )
    lines += [
        "",
        "Differences, frozen minus corrected at the same spp (%d):" % NOTEBOOK_DMT_SPP,
        "",
        f"- amplitude {(frozen.amplitude - fixed.amplitude) * 1e9:+.4f} nm, "
        f"phase {frozen.phase_deg - fixed.phase_deg:+.4f} deg, "
        f"min gap {(frozen.min_gap - fixed.min_gap) * 1e9:+.4f} nm, "
        f"peak force {(frozen.max_force - fixed.max_force) * 1e9:+.4f} nN;",
        f"- the frozen force turns the conservative DMT force into a spurious energy sink/source: "
        f"E_ts = {frozen.tip_sample_dissipation * 1e18:+.4f} aJ per period (corrected: "
        f"{fixed.tip_sample_dissipation * 1e18:+.2e} aJ; DMT is conservative so it must be ~0).",
        "- the corrected RK4 also shows a small non-zero E_ts at coarse steps: its own numerical",
        "  energy error where the step crosses the force kink at a0 (a trapezoidal loop integral "
        "of",
        "  F dz along the samples gives the same number, so it is not a quadrature artefact). It "
        "is",
        "  irregular in z_base, below 1e-3 of the drive work at the default step and goes to ~0 "
        "as",
        "  spp grows; the frozen-force scheme is only first order in dt and its energy balance "
        "stays",
        "  off even at 3200 spp (last column).",
        "",
        "## The amplitude at z_base = %g nm" % (z_base * 1e9),
        "",
        f"The correct integration gives a steady amplitude of **{ref.amplitude * 1e9:.3f} nm** "
        f"(phase lag {ref.phase_deg:.3f} deg, peak repulsive force {ref.max_force * 1e9:.3f} nN), "
        f"i.e. a reduction of {(a_free - ref.amplitude) * 1e9:.2f} nm from the free "
        f'{a_free * 1e9:.2f} nm. The notebook\'s sentence "near 45 nm" is wrong: 45 nm is not '
        "what "
        f"either RK4 variant gives here (see the table). {_where_45nm}",
        "",
        "## Convergence orders (free oscillator, L1 error over the last 20 of 100 periods)",
        "",
    ]
    lines += [f"- {m}: fitted order {p:.3f}" for m, p in orders.items()]
    lines += [
        "",
        "Euler is first order; RK4 fourth order; the notebook's Verlet is *first* order, not "
        "second,",
        "because its damping term uses the velocity (z_n - z_{n-2}) / 2dt, which lags by one "
        "step.",
        "",
    ]
    return "\n".join(lines)


def _where_amplitude(target, cantilever, drive, sample, quick=False) -> str:
    """Sentence giving the z_base at which the steady amplitude equals ``target`` [m] (1 nm
    grid)."""
    z_bases = np.arange(40e-9, 4.5e-9, -(5e-9 if quick else 1e-9))
    rows = sweep(z_bases, cantilever, drive, make_force_model("dmt", sample), progress=False)
    amps = np.array([r["amplitude_m"] for r in rows])
    for i in range(len(rows) - 1):
        if (amps[i] - target) * (amps[i + 1] - target) <= 0:
            z = z_bases[i] + (target - amps[i]) * (z_bases[i + 1] - z_bases[i]) / (
                amps[i + 1] - amps[i]
            )
            return (
                f"A steady amplitude of {target * 1e9:g} nm occurs only much closer to the "
                "sample, at "
                f"z_base = {z * 1e9:.1f} nm (linear interpolation of a sweep; see `afm_study "
                "sweep`)."
            )
    return f"No z_base between 5 and 40 nm gives a steady amplitude of {target * 1e9:g} nm."


def make_notebook(
    out: Path,
    cantilever: Cantilever | None = None,
    drive: Drive | None = None,
    sample: DMTSample | None = None,
    quick: bool = False,
    z_base: float = 40e-9,
) -> list[Path]:
    """Write every figure of the seed notebook (corrected) and summary.md into ``out``."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    cantilever = cantilever or Cantilever()
    drive = drive or Drive.from_free_amplitude(cantilever, 60e-9)
    sample = sample or DMTSample()
    period = 1.0 / drive.frequency
    written = []
    ms = 1e3
    nm = 1e9
    periods = 100
    last10 = slice(-10 * NOTEBOOK_SPP, None)

    # Plot 1: analytic steady state (last 10 of 100 periods)
    t = np.arange(periods * NOTEBOOK_SPP) * period / NOTEBOOK_SPP
    amp, phi = steady_amplitude_phase(cantilever, drive)
    z_an = amp * np.cos(drive.omega * t + drive.phase - phi)
    written.append(
        _line_plot(
            out / "plot1_analytic_steady_state.png",
            "Plot 1: analytic steady state",
            [(t[last10] * ms, z_an[last10] * nm, "b--", "")],
        )
    )
    # Plot 2: Euler at 28 steps per period blows up
    euler = _free_run(cantilever, drive, "euler", NOTEBOOK_SPP, periods)
    written.append(
        _line_plot(
            out / "plot2_euler_28spp.png",
            f"Plot 2: Euler, {NOTEBOOK_SPP} steps per period (unstable: grows without bound)",
            [(euler.t * ms, euler.z * nm, "-", "")],
        )
    )
    # Plot 3: Verlet and RK4 at the same coarse step
    verlet = _free_run(cantilever, drive, "verlet", NOTEBOOK_SPP, periods)
    written.append(
        _line_plot(
            out / "plot3_verlet.png",
            f"Plot 3: notebook Verlet, {NOTEBOOK_SPP} spp",
            [(verlet.t * ms, verlet.z * nm, "g-", "")],
            ylim=(-65, 65),
        )
    )
    written.append(
        _line_plot(
            out / "plot3_verlet_steady.png",
            "Plot 3: notebook Verlet, last 10 periods",
            [(verlet.t[last10] * ms, verlet.z[last10] * nm, "g-", "")],
            ylim=(-65, 65),
        )
    )
    rk4 = _free_run(cantilever, drive, "rk4", NOTEBOOK_SPP, periods)
    written.append(
        _line_plot(
            out / "plot3_rk4_steady.png",
            f"Plot 3: RK4, {NOTEBOOK_SPP} spp, last 10 periods",
            [(rk4.t[last10] * ms, rk4.z[last10] * nm, "r-", "")],
            ylim=(-65, 65),
        )
    )
    # Plot 4: comparison (Euler left out, as in the notebook: it diverges at this step)
    written.append(
        _line_plot(
            out / "plot4_comparison.png",
            "Plot 4: schemes vs analytic solution",
            [
                (t[last10] * ms, z_an[last10] * nm, "b--", "analytic"),
                (verlet.t[last10] * ms, verlet.z[last10] * nm, "g-", "notebook Verlet"),
                (rk4.t[last10] * ms, rk4.z[last10] * nm, "r-", "RK4"),
            ],
            xlim=(2.0, 2.06),
        )
    )
    # Plots 5-6: L1 error vs time step with fitted orders
    spps = (
        {m: v[:3] for m, v in DEFAULT_CONVERGENCE_SPP.items()}
        if quick
        else DEFAULT_CONVERGENCE_SPP
    )
    rows = convergence_study(cantilever, drive, spps)
    write_csv(out / "convergence.csv", ["method", "steps_per_period", "dt_s", "l1_error_m"], rows)
    written.append(out / "convergence.csv")
    orders = {m: fit_order(rows, m) for m in spps}
    plot_convergence(
        rows, orders, out / "plot5_6_l1_error.png", "Plots 5-6: L1 error vs time step"
    )
    written.append(out / "plot5_6_l1_error.png")
    # Plot 7: tip response with drive (DMT, z_base 40 nm, RK4 at 280 spp, periods 95-100 from rest)
    cols, _ = trajectory(
        z_base,
        cantilever,
        drive,
        make_force_model("dmt", sample),
        NOTEBOOK_DMT_SPP,
        "rk4",
        periods=periods,
        from_rest_periods=0,
    )
    write_csv(out / "trajectory_40nm.csv", TRAJECTORY_COLUMNS, _columns_to_rows(cols))
    written.append(out / "trajectory_40nm.csv")
    tail = slice(-5 * NOTEBOOK_DMT_SPP, None)
    plot_trajectory(
        {k: v[tail] for k, v in cols.items()},
        out / "plot7_tip_response_drive.png",
        f"Plot 7: tip response and drive, z_base = {z_base * nm:g} nm (corrected RK4)",
    )
    written.append(out / "plot7_tip_response_drive.png")
    # Plot 8: force-distance curve along the trajectory, with the model curve
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(7, 4.5))
    ax.plot(
        cols["tip_position_m"] * nm,
        cols["tip_sample_force_N"] * nm,
        "b.",
        ms=2,
        label="along trajectory",
    )
    gaps = np.linspace(-20e-9, 30e-9, 2001)
    ax.plot(
        gaps * nm,
        make_force_model("dmt", sample).force(gaps) * nm,
        "k-",
        lw=0.8,
        label="DMT model",
    )
    ax.set_xlim(-20, 30)
    ax.set_ylim(
        min(-1.0, cols["tip_sample_force_N"].min() * nm * 1.2),
        max(1.0, cols["tip_sample_force_N"].max() * nm * 1.2),
    )
    ax.set_xlabel("tip position (gap) [nm]")
    ax.set_ylabel("tip-sample force [nN]")
    ax.set_title("Plot 8: force-distance curve")
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "plot8_force_distance.png", dpi=110)
    plt.close(fig)
    written.append(out / "plot8_force_distance.png")
    # Summary: frozen-force RK4 beside the corrected one
    comparison = dmt_comparison(cantilever, drive, sample, z_base, 800 if quick else 3200)
    (out / "summary.md").write_text(
        _summary_md(
            comparison,
            orders,
            z_base,
            cantilever,
            drive,
            _where_amplitude(45e-9, cantilever, drive, sample, quick),
        )
    )
    written.append(out / "summary.md")
    return written


def cmd_fm_curve(ns, out: Path) -> int:
    """FM curves: the self-excited steady state (amplitude --amplitude, phase --phase) at each
    z_base by shooting (afm_ros.core.physics.self_excited): df, drive and dissipation vs distance,
    with Giessibl's first-order df beside it; fm_curve.csv (readable by ``afm_study reconstruct``)
    and fm_curve.png."""

    cantilever, drive, sample, spp = physics_from_args(ns)
    amplitude = CANTILEVER_SPECS["free_amplitude"].validate(_number(ns.amplitude))
    phase = _number(ns.phase)
    if isinstance(phase, bool) or not isinstance(phase, (int, float)) or not 0.0 < phase < 180.0:
        raise ValueError(f"phase={ns.phase!r} deg must be in (0, 180)")
    if ns.method == "verlet":
        raise ValueError(
            "method='verlet' (the notebook's scheme) cannot change its drive frequency within a "
            "period map; use rk4, rk4_event or euler"
        )
    text = ns.z_base or f"{amplitude + 5e-9!r}:{max(amplitude - 1e-9, 1e-10)!r}:1e-10"
    z_bases = parse_z_bases(text)
    model = make_force_model(ns.force_model, sample, **ns.dissipation)
    sim = Simulation(cantilever, drive, model, z_bases[0], spp, ns.method)
    t0 = time.perf_counter()
    rows, free = fm_curve(z_bases, sim, amplitude, float(phase), retract=ns.retract)
    wall = time.perf_counter() - t0
    write_csv(out / "fm_curve.csv", FM_CURVE_COLUMNS, rows)
    plot_fm_curve(rows, free, out / "fm_curve.png")
    bad = [r["z_base_m"] for r in rows if not r["converged"]]
    if bad:
        print(f"warning: no self-excited orbit found at z_base {bad}", file=sys.stderr)
    lowest = min(rows, key=lambda r: r["df_Hz"])
    print(
        f"free: f = {free.frequency:.6f} Hz, drive {free.force:.6g} N at A = {amplitude:g} m; "
        f"{len(rows)} points, {len(rows) - len(bad)} converged, {sum(r['periods'] for r in rows)} "
        "periods, "
        f"{sum(r['newton_iterations'] for r in rows)} Newton iterations, {wall:.2f} s; lowest df "
        f"{lowest['df_Hz']:.4g} Hz at distance {lowest['distance_m']:.4g} m"
    )
    print(f"wrote {out / 'fm_curve.csv'} and {out / 'fm_curve.png'} ({len(rows)} points)")
    return 0


def plot_fm_curve(rows, free, path: Path):
    """df (simulated and first-order theory), drive and dissipation against the closest
    distance."""
    plt = pyplot()
    fig, axes = plt.subplots(3, 1, figsize=(7, 8.5), sharex=True)
    for direction, style in (("approach", "-"), ("retract", "--")):
        sel = [r for r in rows if r["direction"] == direction]
        if not sel:
            continue
        d = np.array([r["distance_m"] for r in sel]) * 1e9
        axes[0].plot(
            d,
            [r["df_Hz"] for r in sel],
            "b" + style,
            label=f"df, self-excited orbit ({direction})",
        )
        axes[0].plot(
            d,
            [r["df_theory_Hz"] for r in sel],
            "k:",
            label="first-order theory (Giessibl)" if direction == "approach" else None,
        )
        axes[1].plot(
            d, [r["drive_N"] * 1e12 for r in sel], "r" + style, label=f"drive ({direction})"
        )
        axes[2].plot(
            d,
            [r["dissipation_from_drive_J"] * 1e18 for r in sel],
            "g" + style,
            label=f"from the drive ({direction})",
        )
        axes[2].plot(
            d,
            [r["tip_sample_dissipation_J"] * 1e18 for r in sel],
            "m:",
            label="work of the tip-sample force" if direction == "approach" else None,
        )
    axes[1].axhline(free.force * 1e12, color="0.5", lw=0.8, label="free drive")
    axes[0].set_ylabel("frequency shift [Hz]")
    axes[1].set_ylabel("drive [pN]")
    axes[2].set_ylabel("dissipation per cycle [aJ]")
    axes[2].set_xlabel("closest tip-sample distance [nm]")
    for ax in axes:
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8)
    axes[0].set_title(
        f"FM curves: A = {rows[0]['amplitude_m'] * 1e9:.3g} nm, f_free = {free.frequency:.3f} Hz"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# --- command line ---------------------------------------------------------------------------
def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="afm_study", description=__doc__.split("\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    def add(name, help_text, params=True):
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.add_argument("--out", default="study_out", help="output folder (default ./study_out)")
        if params:
            add_param_flags(p)
        return p

    p = add("notebook", "regenerate every figure of the seed notebook (corrected) plus summary.md")
    p.add_argument("--quick", action="store_true", help="coarser reference runs (for tests)")

    p = add("convergence", "L1 error vs time step for each integrator, fitted orders")
    p.add_argument(
        "--methods",
        type=lambda s: [m.strip() for m in s.split(",") if m.strip()],
        default=list(DEFAULT_CONVERGENCE_SPP),
        help="comma list from euler,verlet,rk4",
    )
    p.add_argument(
        "--periods", type=_int_at_least(1), default=100, help="drive periods per run (default 100)"
    )
    p.add_argument(
        "--window-periods",
        type=_int_at_least(1),
        default=20,
        help="periods at the end in the L1 error",
    )
    p.add_argument(
        "--quick", action="store_true", help="only the three coarsest step counts per method"
    )

    for name, text in (
        ("sweep", "steady-state observables vs z_base (approach, optional --retract)"),
        ("trajectory", "tip position, drive and tip-sample force vs time at one z_base"),
    ):
        p = add(name, text)
        p.add_argument(
            "--method",
            default=CANTILEVER_SPECS["integrator"].default,
            help=f"integrator: {', '.join(METHODS)}; default "
            f"{CANTILEVER_SPECS['integrator'].default}",
        )
        p.add_argument(
            "--force-model",
            default="dmt",
            choices=FORCE_MODELS,
            help="tip-sample force model (default dmt; viscoelastic_dmt uses --sample-viscosity, "
            "hysteresis_dmt --hamaker-constant-retract)",
        )
    sweep_p = sub.choices["sweep"]
    sweep_p.add_argument(
        "--z-base",
        default="80e-9:5e-9:5e-9",
        help="z_base values [m]: comma list or start:stop:step (default 80e-9:5e-9:5e-9)",
    )
    sweep_p.add_argument("--retract", action="store_true", help="after the approach, retract back")
    sweep_p.add_argument("--no-progress", action="store_true", help="no progress bar")
    sweep_p.add_argument(
        "--steady",
        default="wait",
        choices=STEADY_METHODS,
        help="how each point's steady state is found: wait (default: the transient waited out, "
        "windows of Q/pi periods until two agree) or shooting (Newton on the one-period map "
        "from the previous point's orbit, the orbit waiting would reach; for high Q; adds "
        "the convergence columns " + ", ".join(SHOOTING_COLUMNS) + "; deterministic only)",
    )
    noise = sweep_p.add_argument_group("noise (default off: deterministic, as the seed notebook)")
    for name, flag in (
        ("temperature", "--temperature"),
        ("detector_noise_density", "--detector-noise"),
        ("noise_seed", "--noise-seed"),
    ):
        spec = NOISE_SPECS[name]
        unit = f" [{spec.unit}]" if spec.unit != "1" else ""
        noise.add_argument(
            flag,
            dest=flag[2:].replace("-", "_"),
            type=_number,
            default=spec.default,
            metavar="X",
            help=f"{spec.description}{unit}; default {spec.default:g}, range {spec.range_text()}",
        )
    noise.add_argument(
        "--average-periods",
        dest="average_periods",
        type=_int_at_least(1),
        default=200,
        help="with noise: drive periods averaged per z_base after 10 Q/pi settling periods "
        "(default 200)",
    )
    traj_p = sub.choices["trajectory"]
    traj_p.add_argument("--z-base", default="40e-9", help="z_base [m] (default 40e-9)")
    traj_p.add_argument(
        "--periods", type=_int_at_least(1), default=5, help="periods to record (default 5)"
    )
    traj_p.add_argument(
        "--from-rest",
        type=_int_at_least(0),
        default=None,
        metavar="P",
        help="record after P periods from rest instead of after the steady state",
    )

    p = add(
        "fm-curve",
        "FM curves: df, drive and dissipation vs distance of the self-excited steady state "
        "(shooting), with Giessibl's first-order df (fm_curve.csv, fm_curve.png)",
    )
    p.add_argument(
        "--amplitude",
        default="5e-9",
        help="oscillation amplitude A [m] the amplitude controller holds (default 5e-9)",
    )
    p.add_argument(
        "--phase", default="90", help="phase lag the PLL holds [deg] (default 90: the resonance)"
    )
    p.add_argument(
        "--z-base",
        default=None,
        help="z_base values [m]: comma list or start:stop:step (default "
        "A + 5 nm down to A - 1 nm in 0.1 nm steps)",
    )
    p.add_argument("--retract", action="store_true", help="after the approach, retract back")
    p.add_argument(
        "--method",
        default=CANTILEVER_SPECS["integrator"].default,
        help="integrator: rk4_event, rk4 or euler (default "
        f"{CANTILEVER_SPECS['integrator'].default}, as "
        "everywhere: plain rk4 steps over the contact's kink, 1.5 %% off in df at 80 steps per "
        "period)",
    )
    p.add_argument(
        "--force-model",
        default="dmt",
        choices=FORCE_MODELS,
        help="tip-sample force model (default dmt)",
    )

    p = add(
        "bench",
        "moved: the speed benchmark is python -m benchmarks.bench, run from the repository root "
        "(not installed); this only says so and exits with status 2",
        params=False,
    )
    p.add_argument(
        "--steps", type=_int_at_least(1), default=10_000_000, help="RK4 steps timed (default 1e7)"
    )
    p.add_argument(
        "--solve-ivp-periods",
        type=_int_at_least(1),
        default=40,
        help="periods integrated by solve_ivp",
    )
    p.add_argument(
        "--no-startup", action="store_true", help="skip the warm-startup subprocess timing"
    )
    thermal_tune.add_parser(sub)
    drive_tune.add_parser(sub)
    contrast.add_parser(sub)
    scan.add_parser(sub)
    dataset.add_parser(sub)
    force_reconstruction.add_parser(sub)
    bimodal_study.add_parser(sub)
    return parser


def _external(module_name: str):
    """A subcommand implemented in its own module (``add_parser`` / ``run(args) -> int``)."""

    def run(ns, out):
        return importlib.import_module(f"afm_ros.tools.{module_name}").run(ns)

    return run


EXTERNAL = {
    "thermal": "thermal_tune",
    "tune": "drive_tune",
    "contrast": "contrast",
    "scan": "scan",
    "dataset": "dataset",
    "reconstruct": "force_reconstruction",
    "bimodal": "bimodal_study",
}


COMMANDS = {
    "notebook": cmd_notebook,
    "convergence": cmd_convergence,
    "sweep": cmd_sweep,
    "fm-curve": cmd_fm_curve,
    "trajectory": cmd_trajectory,
    "bench": cmd_bench,
    **{name: _external(module) for name, module in EXTERNAL.items()},
}


def main(argv=None) -> int:
    """Entry point of ``afm_study``; returns the exit code (2 for a bad value, with a clear
    message)."""
    parser = build_parser()
    ns = parser.parse_args(argv)
    if getattr(ns, "method", "rk4") not in METHODS:
        parser.error(f"method={ns.method!r} is not known; allowed: {', '.join(METHODS)}")
    for name in getattr(ns, "methods", []) or []:
        if name not in DEFAULT_CONVERGENCE_SPP:
            parser.error(
                f"methods: {name!r} is not known; allowed: {', '.join(DEFAULT_CONVERGENCE_SPP)}"
            )
    if ns.command in EXTERNAL:
        return COMMANDS[ns.command](ns, None)
    out = Path(ns.out)
    try:
        if ns.command != "bench":
            physics_from_args(ns) if hasattr(ns, "spring_constant") else None
            out.mkdir(parents=True, exist_ok=True)
        return COMMANDS[ns.command](ns, out)
    except ValueError as exc:
        print(f"{parser.prog} {ns.command}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
