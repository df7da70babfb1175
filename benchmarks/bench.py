"""Speed benchmark of the RK4 + DMT kernel, with baselines in the same run (prints one JSON
object).

``python -m benchmarks.bench [--steps N] [--solve-ivp-periods P] [--no-startup]`` from the
repository root (this was ``afm_study bench``; the installed package has neither this module nor
its C baselines).

Problem: the seed cantilever (k = 10 N/m, f0 = 45 kHz, Q = 25, A0 = 60 nm) over the DMT sample at
z_base = 40 nm, RK4 with 200 steps per drive period, started from rest.

- numba kernel: >= 1e7 steps, no per-step recording -> ``rk4_ns_per_step``, ``real_time_factor``
  (simulated seconds per wall second).
- C baseline: the identical RK4 + DMT step (``bench_baseline.c``: same drive table, same
  arithmetic, checked bit-identical to the numba kernel) compiled with ``gcc -O2``.
- scipy ``solve_ivp`` (RK45 and DOP853) on the same ODE: rtol is tightened until its error
  against a reference (RK4 at 6400 steps per period) is no larger than RK4-200's error over the
  same interval; its time is reported per *equivalent* RK4 step (wall time / number of RK4-200
  steps covering the same simulated time).
- warm startup: a fresh ``python -c`` that imports the package and runs a tiny simulation,
  run twice so the numba cache is warm; the second wall time is reported.
- ``rk4_event``: the event-located RK4 kernel (``events.advance_event``, flat sample, no recording)
  against the same algorithm in C (``bench_event_baseline.c``: the same operations in the same
  order, compiled with ``gcc -O2 -fno-fast-math -ffp-contract=off``), for dmt, viscoelastic_dmt (20
  Pa s) and hysteresis_dmt (H_retract = 1.5 H) far from the surface (z_base 2 um), tapping (50 nm)
  and tapping hard (20 nm), at the steps per period and near-surface fraction ``Simulation`` uses
  for the method; ns per output step, timed alternately (best of 3), and whether the end state and
  the split / sub-step counts are bit-identical.
"""

from __future__ import annotations

import argparse
import copy
import ctypes
import json
import math
import os
import platform
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from afm_ros.core.physics import CANTILEVER_SPECS, Cantilever, Drive, Simulation, seed_simulation
from afm_ros.core.physics.forces import make_force_model
from afm_ros.core.physics.parameters import DMTSample
from afm_ros.core.physics.reference import hard_tapping_models

Z_BASE = 40e-9
SPP = 200


def _time_numba_once(sim, steps: int) -> float:
    t0 = time.perf_counter()
    sim.advance(steps, record=False)
    return (time.perf_counter() - t0) / steps


def _compile(tmp: Path, source: str, flags: list[str]):
    """``source`` (beside this file) compiled into a shared library in ``tmp``: (ctypes.CDLL, None)
    or (None, why not)."""
    gcc = shutil.which("gcc") or shutil.which("cc")
    if gcc is None:
        return None, "no C compiler (gcc/cc) found"
    lib = tmp / Path(source).with_suffix(".so").name
    proc = subprocess.run(
        [
            gcc,
            *flags,
            "-shared",
            "-fPIC",
            "-o",
            str(lib),
            str(Path(__file__).with_name(source)),
            "-lm",
        ],
        capture_output=True,
        text=True,
    )
    if proc.returncode != 0:
        return None, f"gcc failed: {proc.stderr.strip()[:300]}"
    return ctypes.CDLL(str(lib)), None


def _build_c(tmp: Path):
    dll, note = _compile(tmp, "bench_baseline.c", ["-O2"])
    if dll is None:
        return None, note
    ptr = ctypes.POINTER(ctypes.c_double)
    fn = dll.rk4_dmt
    fn.argtypes = [
        ptr,
        ctypes.c_long,
        ctypes.c_long,
        ctypes.c_double,
        ctypes.c_double,
        ctypes.c_double,
        ctypes.c_double,
        ptr,
        ctypes.c_long,
        ptr,
        ctypes.c_double,
    ]
    fn.restype = None
    return fn, None


EVENT_C_FLAGS = ["-O2", "-fno-fast-math", "-ffp-contract=off"]
# (name, z_base [m]) of the rk4_event comparison: the tip far from the surface, tapping, tapping
# hard
EVENT_REGIMES = (("far", 2e-6), ("tapping", 50e-9), ("hard_tapping", 20e-9))


def build_event_c(tmp: Path):
    """``advance_event`` of ``bench_event_baseline.c`` via ctypes, or (None, why not)."""
    dll, note = _compile(tmp, "bench_event_baseline.c", EVENT_C_FLAGS)
    if dll is None:
        return None, note
    ptr = ctypes.POINTER(ctypes.c_double)
    fn = dll.advance_event
    fn.argtypes = [
        ptr,
        ctypes.c_long,
        ctypes.c_long,
        ctypes.c_double,
        ctypes.c_double,
        ctypes.c_double,
        ctypes.c_double,
        ptr,
        ctypes.c_long,
        ctypes.c_long,
        ptr,
        ctypes.c_double,
        ctypes.c_long,
        ctypes.c_double,
        ptr,
        ptr,
    ]
    fn.restype = None
    return fn, None


def event_c_call(fn, sim, steps: int, out_w=None):
    """``steps`` rk4_event steps in C from the state of ``sim`` (a Simulation with method rk4_event
    over a flat sample; not changed); returns (y [z, v], stats [split steps, extra sub-steps])."""
    ptr = ctypes.POINTER(ctypes.c_double)
    c = sim.cantilever
    table, fp = sim._table, sim._fp
    y = np.array(sim.y[:2], dtype=np.float64)
    stats = np.zeros(2)
    fn(
        y.ctypes.data_as(ptr),
        int(sim.n),
        int(steps),
        float(sim.dt),
        1.0 / float(c.mass),
        float(c.spring_constant),
        float(c.damping),
        table.ctypes.data_as(ptr),
        table.shape[0],
        int(sim.force_model.model_id),
        fp.ctypes.data_as(ptr),
        float(sim.z_offset),
        int(sim.steps_per_period),
        float(sim.event_beta),
        stats.ctypes.data_as(ptr),
        None if out_w is None else out_w.ctypes.data_as(ptr),
    )
    return y, stats


def _event_times(steps: int) -> dict:
    """ns per output step of numba's ``advance_event`` and of the same algorithm in C, per force
    model and regime, from the same state (the lever's steady motion: 150 periods from rest first),
    timed alternately, best of 3; ratio numba / C and whether both end in the same state bit for
    bit."""

    cantilever = Cantilever()
    drive = Drive.from_free_amplitude(cantilever, 60e-9)
    starts = {}
    for regime, z_base in EVENT_REGIMES:
        for name, model in hard_tapping_models().items():
            sim = Simulation(cantilever, drive, model, z_base, method="rk4_event")
            sim.advance(
                150 * sim.steps_per_period, record=False
            )  # also compiles / loads the kernel
            starts[(regime, name)] = sim
    first = next(iter(starts.values()))
    out = {
        "method": "rk4_event",
        "steps": steps,
        "steps_per_period": first.steps_per_period,
        "near_surface_fraction": first.event_beta,
        "z_base_m": {regime: z for regime, z in EVENT_REGIMES},
    }
    with tempfile.TemporaryDirectory() as tmp:
        fn, note = build_event_c(Path(tmp))
        if fn is None:
            out["c_note"] = f"C baseline of rk4_event skipped: {note}"
            return out
        out["c_flags"] = " ".join(EVENT_C_FLAGS)
        numba_times = {key: [] for key in starts}
        c_times = {key: [] for key in starts}
        identical = {key: True for key in starts}
        substeps = {}
        for _ in range(3):
            for key, start in starts.items():
                sim = copy.deepcopy(start)
                t0 = time.perf_counter()
                sim.advance(steps, record=False)
                numba_times[key].append((time.perf_counter() - t0) / steps)
                t0 = time.perf_counter()
                y, stats = event_c_call(fn, start, steps)
                c_times[key].append((time.perf_counter() - t0) / steps)
                added = sim.event_stats - start.event_stats  # (the warm-up's counts are in both)
                identical[key] &= bool(
                    y[0] == sim.y[0] and y[1] == sim.y[1] and np.array_equal(stats, added)
                )
                substeps[key] = 1.0 + float(added[1]) / steps
    cases = {}
    for regime, name in starts:
        ns_numba = min(numba_times[(regime, name)]) * 1e9
        ns_c = min(c_times[(regime, name)]) * 1e9
        cases.setdefault(regime, {})[name] = {
            "numba_ns_per_step": ns_numba,
            "c_ns_per_step": ns_c,
            "ratio_vs_c": ns_numba / ns_c,
            "bit_identical": identical[(regime, name)],
            "substeps_per_step": substeps[(regime, name)],
        }
    out["cases"] = cases
    ratios = [case["ratio_vs_c"] for models in cases.values() for case in models.values()]
    out["worst_ratio_vs_c"] = max(ratios)
    out["all_bit_identical"] = all(
        case["bit_identical"] for models in cases.values() for case in models.values()
    )
    out["goals"] = {"within_1.1x_of_c": out["worst_ratio_vs_c"] <= 1.1}
    return out


def _c_call(fn, y, n0, steps, sim):
    ptr = ctypes.POINTER(ctypes.c_double)
    c = sim.cantilever
    table, fp = sim._table, sim._fp
    fn(
        y.ctypes.data_as(ptr),
        n0,
        steps,
        sim.dt,
        1.0 / c.mass,
        c.spring_constant,
        c.damping,
        table.ctypes.data_as(ptr),
        table.shape[0],
        fp.ctypes.data_as(ptr),
        sim.z_offset,
    )


def _c_matches(fn) -> bool:
    """Same number of steps from rest in C and numba must give the identical state (bit for
    bit)."""
    sim = seed_simulation(Z_BASE, SPP, method="rk4")
    check_steps = 100 * SPP + 7
    y = np.zeros(2)
    _c_call(fn, y, 0, check_steps, sim)
    sim.advance(check_steps, record=False)
    return bool(y[0] == sim.y[0] and y[1] == sim.y[1])


def _time_c_once(fn, sim, steps: int) -> float:
    y = np.zeros(2)
    t0 = time.perf_counter()
    _c_call(fn, y, 0, steps, sim)
    return (time.perf_counter() - t0) / steps


def _rhs_factory():
    sim = seed_simulation(Z_BASE, SPP, method="rk4")
    c, d = sim.cantilever, sim.drive
    k, damp, inv_m, f0, w, ph = (
        c.spring_constant,
        c.damping,
        1.0 / c.mass,
        d.force,
        d.omega,
        d.phase,
    )
    a0, hr6, hertz, fad = (float(x) for x in sim._fp[:4])
    z_base = Z_BASE
    cos, sqrt = math.cos, math.sqrt

    def rhs(t, y):
        z, v = y
        gap = z_base + z
        if gap > a0:
            f = -hr6 / (gap * gap)
        else:
            delta = a0 - gap
            f = -fad + hertz * delta * sqrt(delta)
        return (v, (-k * z - damp * v + f0 * cos(w * t + ph) + f) * inv_m)

    return rhs


def _reference(periods: int, spp_ref: int = 6400):
    """z [m] at every 10th RK4-200 step time, from RK4 at ``spp_ref`` steps per period."""
    sim = seed_simulation(Z_BASE, spp_ref, method="rk4")
    ratio = spp_ref // SPP
    s = sim.advance(periods * spp_ref + 1, decimation=10 * ratio)
    return s.t, s.z


def _solve_ivp_to_accuracy(periods: int, t_ref, z_ref, target: float):
    from scipy.integrate import solve_ivp

    rhs = _rhs_factory()
    t_end = float(t_ref[-1])
    results = {}
    for method in ("RK45", "DOP853"):
        chosen = None
        # loosest tolerance first, tightened by sqrt(10) until the error target is met;
        # atol scales with the motion's size (z ~ 6e-8 m, v ~ 2e-2 m/s) so rtol is the only knob
        for rtol in 10.0 ** -np.arange(3.0, 13.01, 0.5):
            atol = [rtol * 6e-8, rtol * 2e-2]
            t0 = time.perf_counter()
            sol = solve_ivp(
                rhs, (0.0, t_end), [0.0, 0.0], method=method, rtol=rtol, atol=atol, t_eval=t_ref
            )
            wall = time.perf_counter() - t0
            err = float(np.max(np.abs(sol.y[0] - z_ref)))
            chosen = {
                "rtol": float(rtol),
                "atol": [float(a) for a in atol],
                "error_m": err,
                "wall_s": wall,
                "nfev": int(sol.nfev),
            }
            if err <= target:
                break
        # best of two timings at the chosen tolerance (load on the machine only ever adds time)
        t0 = time.perf_counter()
        solve_ivp(
            rhs,
            (0.0, t_end),
            [0.0, 0.0],
            method=method,
            rtol=chosen["rtol"],
            atol=chosen["atol"],
            t_eval=t_ref,
        )
        chosen["wall_s"] = min(chosen["wall_s"], time.perf_counter() - t0)
        results[method] = chosen
    return results


def _startup_time() -> tuple[float, float]:
    code = (
        "from afm_ros.core.physics import seed_simulation, steady_state;"
        "s = seed_simulation(40e-9, 200); s.advance(2000); print('ok')"
    )
    times = []
    for _ in range(2):
        t0 = time.perf_counter()
        subprocess.run([sys.executable, "-c", code], check=True, capture_output=True)
        times.append(time.perf_counter() - t0)
    return times[0], times[1]


def _model_times(steps: int, fn) -> dict:
    """ns per RK4 step for every force model and with the thermal force on, all timed alternately
    (best of 3) beside the C baseline of plain DMT; goals of issue 9 as ratios."""

    cantilever = Cantilever()
    drive = Drive.from_free_amplitude(cantilever, 60e-9)
    sample = DMTSample()
    cases = {
        "dmt": make_force_model("dmt", sample),
        "viscoelastic_dmt": make_force_model("viscoelastic_dmt", sample, viscosity=200.0),
        "hysteresis_dmt": make_force_model("hysteresis_dmt", sample, hamaker_retract=5 * 6.4e-20),
        "dmt + thermal 300 K": make_force_model("dmt", sample),
    }
    sims = {}
    for name, model in cases.items():
        sim = Simulation(cantilever, drive, model, Z_BASE, SPP, "rk4")
        if "thermal" in name:
            sim.set_thermal(300.0, 1)
        sim.advance(10 * SPP, record=False)
        sims[name] = sim
    times = {name: [] for name in sims}
    c_times = []
    for _ in range(3):
        for name, sim in sims.items():
            times[name].append(_time_numba_once(sim, steps))
        if fn is not None:
            c_times.append(_time_c_once(fn, seed_simulation(Z_BASE, SPP, method="rk4"), steps))
    ns = {name: min(t) * 1e9 for name, t in times.items()}
    out = {"ns_per_step": ns, "steps": steps}
    if c_times:
        out["c_dmt_ns_per_step"] = min(c_times) * 1e9
        out["dmt_vs_c"] = ns["dmt"] / out["c_dmt_ns_per_step"]
    out["vs_dmt"] = {name: ns[name] / ns["dmt"] for name in ns if name != "dmt"}
    out["goals"] = {
        "dmt_within_1.3x_of_c": out.get("dmt_vs_c", math.nan) <= 1.3,
        "models_within_1.5x_of_dmt": all(
            out["vs_dmt"][m] <= 1.5 for m in ("viscoelastic_dmt", "hysteresis_dmt")
        ),
        "thermal_adds_at_most_30_percent": out["vs_dmt"]["dmt + thermal 300 K"] <= 1.3,
    }
    return out


def run_bench(steps: int = 10_000_000, solve_ivp_periods: int = 40, startup: bool = True) -> dict:
    """Run all measurements; return a JSON-ready dict (times in ns per step, s, ratios)."""
    steps = int(steps)
    out: dict = {
        "problem": f"seed cantilever + DMT, z_base {Z_BASE:g} m, RK4 {SPP} steps/period",
        "steps": steps,
        "machine": f"{platform.machine()} {os.cpu_count()} cpu, "
        f"python {platform.python_version()}",
    }
    sim = seed_simulation(Z_BASE, SPP, method="rk4")
    sim.advance(10 * SPP, record=False)  # compile / load from the cache outside the timing
    with tempfile.TemporaryDirectory() as tmp:
        fn, note = _build_c(Path(tmp))
        # numba and C timed alternately, best of 3 each: other load on the machine hits both alike
        numba_times, c_times = [], []
        for _ in range(3):
            numba_times.append(_time_numba_once(sim, steps))
            if fn is not None:
                c_times.append(_time_c_once(fn, sim, steps))
        ns_numba = min(numba_times)
        if fn is None:
            out["c_note"] = f"C baseline skipped: {note}"
        else:
            ns_c = min(c_times)
            out["c_ns_per_step"] = ns_c * 1e9
            out["ratio_vs_c"] = ns_numba / ns_c
            out["c_bit_identical_to_numba"] = _c_matches(fn)
    out["rk4_ns_per_step"] = ns_numba * 1e9
    out["models"] = _model_times(max(steps // 5, 200_000), fn)
    out["rk4_event"] = _event_times(max(steps // 20, 1000))
    out["real_time_factor"] = sim.dt / ns_numba
    default_spp = CANTILEVER_SPECS["steps_per_period"].default
    out["default_steps_per_period"] = default_spp
    out["real_time_factor_at_default_spp"] = 1.0 / (sim.drive.frequency * default_spp * ns_numba)
    # accuracy-matched solve_ivp over fewer periods
    t_ref, z_ref = _reference(solve_ivp_periods)
    sim200 = seed_simulation(Z_BASE, SPP, method="rk4")
    s = sim200.advance(solve_ivp_periods * SPP + 1, decimation=10)
    rk4_err = float(np.max(np.abs(s.z - z_ref)))
    out["accuracy_check"] = {
        "periods": solve_ivp_periods,
        "reference": "RK4 at 6400 steps per period",
        "rk4_200_max_error_m": rk4_err,
    }
    ivp = _solve_ivp_to_accuracy(solve_ivp_periods, t_ref, z_ref, rk4_err)
    equivalent_steps = solve_ivp_periods * SPP
    for method, r in ivp.items():
        r["ns_per_equivalent_step"] = r["wall_s"] / equivalent_steps * 1e9
        r["reached_target"] = r["error_m"] <= rk4_err
    best = min(
        ivp,
        key=lambda m: ivp[m]["ns_per_equivalent_step"] if ivp[m]["reached_target"] else math.inf,
    )
    out["solve_ivp"] = ivp
    out["solve_ivp_method"] = best
    out["solve_ivp_ns_per_step"] = ivp[best]["ns_per_equivalent_step"]
    out["speedup_vs_solve_ivp"] = out["solve_ivp_ns_per_step"] / out["rk4_ns_per_step"]
    if startup:
        cold, warm = _startup_time()
        out["startup_first_s"] = cold
        out["startup_warm_s"] = warm
    out["goals"] = {
        "within_1.3x_of_c": out.get("ratio_vs_c", math.nan) <= 1.3,
        "speedup_vs_solve_ivp_ge_300": out["speedup_vs_solve_ivp"] >= 300,
        "real_time_factor_ge_4": out["real_time_factor"] >= 4,
        "warm_startup_lt_2s": out.get("startup_warm_s", math.nan) < 2.0,
    }
    return out


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


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench", description="speed benchmark; prints one JSON object"
    )
    parser.add_argument(
        "--steps", type=_int_at_least(1), default=10_000_000, help="RK4 steps timed (default 1e7)"
    )
    parser.add_argument(
        "--solve-ivp-periods",
        type=_int_at_least(1),
        default=40,
        help="periods integrated by solve_ivp",
    )
    parser.add_argument(
        "--no-startup", action="store_true", help="skip the warm-startup subprocess timing"
    )
    ns = parser.parse_args(argv)
    result = run_bench(
        steps=ns.steps, solve_ivp_periods=ns.solve_ivp_periods, startup=not ns.no_startup
    )
    print(json.dumps(result, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
