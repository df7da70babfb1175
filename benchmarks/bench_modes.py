"""Cost per step of the N-mode RK4 (core/physics/modes.py) against the point mass's plain RK4, in
one run (prints JSON).

``python -m benchmarks.bench_modes [--steps 2000000] [--repeats 5]``

Same problem for every kernel: the seed lever (10 N/m, 45 kHz, Q 25) as mode 1 tapping the seed's
DMT sample at z_base 40 nm (A0 60 nm), fixed step (800 per mode-1 period, so that mode 3 is
resolved too); the point mass's plain ``rk4`` (the baseline: ``Simulation(method="rk4")``), then
the N-mode kernel with 1, 2 and 3 modes (mode 1 driven; the step the same), and 2 modes without the
energies (the bimodal session's call), and two modes with ``rk4_event`` beside the point mass's
``rk4_event`` (contacts located on the deflection, pieces near the surface; a checkout without the
two-mode event kernel leaves that row out). Timed alternately, best of ``--repeats``; ns per step
and the ratio to one mode and to the point mass. Issue 32's goal: two modes within 1.3x of one
mode.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

from afm_ros.core.physics.forces import DMTForce
from afm_ros.core.physics.modes import ModeDrive, MultiModeSimulation, rectangular_modes
from afm_ros.core.physics.parameters import Cantilever, DMTSample, Drive
from afm_ros.core.physics.simulation import Simulation

LEVER = Cantilever()
SPP = 800  # steps per mode-1 period: 128 per mode-2 and 46 per mode-3 period


def _point_mass():
    drive = Drive.from_free_amplitude(LEVER, 60e-9)
    return Simulation(LEVER, drive, DMTForce(DMTSample()), 40e-9, SPP, method="rk4")


def _modes(n: int, integrator: str = "rk4"):
    modes = rectangular_modes(LEVER, n)
    drive = ModeDrive(0, LEVER.resonance_frequency, LEVER.spring_constant * 60e-9 / 25.0)
    dt = 1.0 / (LEVER.resonance_frequency * SPP)
    sim = MultiModeSimulation(modes, [drive], DMTForce(DMTSample()), 40e-9, dt)
    if integrator != "rk4":
        sim.set_integrator(integrator)
    return sim


def _point_mass_event():
    drive = Drive.from_free_amplitude(LEVER, 60e-9)
    return Simulation(LEVER, drive, DMTForce(DMTSample()), 40e-9, SPP, method="rk4_event")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_modes", description=__doc__.split("\n\n")[0]
    )
    parser.add_argument("--steps", type=int, default=2_000_000, help="steps per timing")
    parser.add_argument("--repeats", type=int, default=5, help="timings per kernel (best kept)")
    a = parser.parse_args(argv)
    if a.steps < 1000 or a.repeats < 1:
        parser.error("--steps >= 1000 and --repeats >= 1")
    kernels = {
        "point_mass_rk4": lambda: _point_mass(),
        "modes_1": lambda: _modes(1),
        "modes_2": lambda: _modes(2),
        "modes_3": lambda: _modes(3),
        "modes_2_no_energies": lambda: _modes(2),
        "point_mass_rk4_event": lambda: _point_mass_event(),
    }
    if hasattr(MultiModeSimulation, "set_integrator"):
        kernels["modes_2_event"] = lambda: _modes(2, "rk4_event")
    sims = {k: make() for k, make in kernels.items()}
    runs = {
        "point_mass_rk4": lambda s, n: s.advance(n, record=False),
        "modes_1": lambda s, n: s.advance(n, every=n),
        "modes_2": lambda s, n: s.advance(n, every=n),
        "modes_3": lambda s, n: s.advance(n, every=n),
        # the bimodal session's call: no energies (two modes: the kernel of scalars)
        "modes_2_no_energies": lambda s, n: s.advance(n, every=n, energies=False),
        "point_mass_rk4_event": lambda s, n: s.advance(n, record=False),
        "modes_2_event": lambda s, n: s.advance(n, every=n),
    }
    for k, s in sims.items():  # compile (or load) and reach the tapping steady state's region
        runs[k](s, 200_000)
    best = {k: float("inf") for k in sims}
    for _ in range(a.repeats):
        for k, s in sims.items():
            t0 = time.perf_counter()
            runs[k](s, a.steps)
            best[k] = min(best[k], (time.perf_counter() - t0) / a.steps)
    ns = {k: v * 1e9 for k, v in best.items()}
    out = {
        "steps": a.steps,
        "repeats": a.repeats,
        "cpu_count": os.cpu_count(),
        "ns_per_step": ns,
        "ratio_to_modes_1": {k: v / ns["modes_1"] for k, v in ns.items()},
        "ratio_to_point_mass_rk4": {k: v / ns["point_mass_rk4"] for k, v in ns.items()},
    }
    print(json.dumps(out, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
