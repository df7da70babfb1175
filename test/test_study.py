"""The study tool: every subcommand on tiny inputs, files and columns, physics sanity, bad
flags."""

import csv
import json
import math
import subprocess
import sys

import numpy as np
import pytest

from afm_ros.core.physics import Cantilever, Drive, steady_amplitude_phase
from afm_ros.tools import study

UNITS = ("_m", "_s", "_N", "_J", "_deg", "_Hz")


def read_csv(path):
    with open(path) as fh:
        rows = list(csv.DictReader(fh))
    return rows


def test_parse_z_bases():
    assert study.parse_z_bases("80e-9,40e-9, 5e-9") == [80e-9, 40e-9, 5e-9]
    # start:stop:step includes stop; the direction comes from start -> stop
    assert np.allclose(
        study.parse_z_bases("80e-9:5e-9:5e-9"), np.arange(80, 4, -5) * 1e-9, rtol=1e-12, atol=0
    )
    assert np.allclose(
        study.parse_z_bases("10e-9:20e-9:5e-9"), [10e-9, 15e-9, 20e-9], rtol=1e-12, atol=0
    )
    for bad, field in (
        ("abc", "z_base"),
        ("1e-9:2e-9", "z_base"),
        ("1e-9:2e-9:0", "step"),
        ("1.0", "z_base"),
    ):
        with pytest.raises(ValueError, match=field):
            study.parse_z_bases(bad)


def test_convergence_subcommand(tmp_path, capsys):
    code = study.main(
        [
            "convergence",
            "--out",
            str(tmp_path),
            "--quick",
            "--periods",
            "40",
            "--window-periods",
            "10",
        ]
    )
    assert code == 0
    rows = read_csv(tmp_path / "convergence.csv")
    assert list(rows[0]) == ["method", "steps_per_period", "dt_s", "l1_error_m"]
    assert {r["method"] for r in rows} == {"euler", "verlet", "rk4"}
    for r in rows:  # dt = 1 / (f spp)
        assert float(r["dt_s"]) == pytest.approx(
            1 / (45e3 * int(r["steps_per_period"])), rel=1e-12, abs=0
        )
    out = capsys.readouterr().out
    orders = json.loads((tmp_path / "convergence_orders.json").read_text())
    assert f"fitted order rk4: {orders['rk4']:.3f}" in out
    # even on the three coarsest steps the orders are recognisable (see test_physics_free for tight
    # ones)
    assert orders["rk4"] == pytest.approx(4, abs=0.3)
    assert orders["euler"] == pytest.approx(1, abs=0.3) and orders["verlet"] == pytest.approx(
        1, abs=0.3
    )
    assert (tmp_path / "convergence.png").stat().st_size > 1000


def test_sweep_subcommand_approach_and_retract(tmp_path):
    code = study.main(
        [
            "sweep",
            "--out",
            str(tmp_path),
            "--z-base",
            "70e-9:10e-9:20e-9",
            "--retract",
            "--steps-per-period",
            "100",
            "--no-progress",
        ]
    )
    assert code == 0
    rows = read_csv(tmp_path / "sweep.csv")
    assert list(rows[0]) == study.SWEEP_COLUMNS
    for col in rows[0]:
        assert col in ("direction", "periods_simulated", "converged") or col.endswith(UNITS), col
    approach = [r for r in rows if r["direction"] == "approach"]
    retract = [r for r in rows if r["direction"] == "retract"]
    assert [float(r["z_base_m"]) for r in approach] == pytest.approx(
        [70e-9, 50e-9, 30e-9, 10e-9], rel=1e-12, abs=0
    )
    assert [float(r["z_base_m"]) for r in retract] == pytest.approx(
        [30e-9, 50e-9, 70e-9], rel=1e-12, abs=0
    )
    amp = [float(r["amplitude_m"]) for r in approach]
    # far away the free amplitude; then the amplitude falls toward the sample (tapping)
    free, _ = steady_amplitude_phase(Cantilever(), Drive.from_free_amplitude(Cantilever(), 60e-9))
    assert amp[0] == pytest.approx(free, rel=1e-3)
    assert all(a > b for a, b in zip(amp, amp[1:]))
    assert all(r["converged"] == "1" for r in rows)
    tapping = approach[-1]
    # the minimum gap is where the tip reaches: z_base - amplitude + mean deflection (to harmonics)
    assert float(tapping["min_gap_m"]) < 0 < float(tapping["max_force_N"])
    assert float(tapping["mean_force_N"]) == pytest.approx(
        10 * float(tapping["mean_deflection_m"]), rel=0.05
    )
    assert (tmp_path / "sweep.png").stat().st_size > 1000


def test_sweep_retract_continues_and_returns_to_the_same_state():
    # approach 40 -> 20 nm, then retract to 40 nm from the 20 nm steady state (one simulation).
    # With the seed parameters the DMT tapping state is unique (no bistability), so the retract
    # must land on the approach's steady state: within the steady-state criterion (windows agree to
    # 1e-14 m / 1e-5 deg; the transient left is smaller still), allowed 1e-12 m / 1e-4 deg.
    rows = study.sweep([40e-9, 20e-9], steps_per_period=100, retract=True, progress=False)
    assert [(r["direction"], r["z_base_m"]) for r in rows] == [
        ("approach", 40e-9),
        ("approach", 20e-9),
        ("retract", 40e-9),
    ]
    assert rows[2]["amplitude_m"] == pytest.approx(rows[0]["amplitude_m"], abs=1e-12)
    assert rows[2]["phase_deg"] == pytest.approx(rows[0]["phase_deg"], abs=1e-4)
    assert rows[1]["amplitude_m"] < rows[0]["amplitude_m"] - 5e-9


def test_trajectory_subcommand(tmp_path):
    code = study.main(
        [
            "trajectory",
            "--out",
            str(tmp_path),
            "--z-base",
            "30e-9",
            "--periods",
            "2",
            "--steps-per-period",
            "100",
        ]
    )
    assert code == 0
    rows = read_csv(tmp_path / "trajectory.csv")
    assert list(rows[0]) == study.TRAJECTORY_COLUMNS
    assert len(rows) == 200
    z = np.array([float(r["deflection_m"]) for r in rows])
    gap = np.array([float(r["tip_position_m"]) for r in rows])
    drive = np.array([float(r["drive_force_N"]) for r in rows])
    t = np.array([float(r["t_s"]) for r in rows])
    assert np.allclose(gap, 30e-9 + z, rtol=0, atol=1e-20)
    assert np.allclose(np.diff(t), 1 / (45e3 * 100), rtol=1e-9, atol=0)
    assert np.max(np.abs(drive)) == pytest.approx(10 * 60e-9 / 25, rel=1e-3)  # F0 = k A0 / Q
    assert (tmp_path / "trajectory.png").stat().st_size > 1000


@pytest.mark.slow
def test_notebook_subcommand(tmp_path):
    code = study.main(["notebook", "--out", str(tmp_path), "--quick"])
    assert code == 0
    for name in (
        "plot1_analytic_steady_state",
        "plot2_euler_28spp",
        "plot3_verlet",
        "plot3_rk4_steady",
        "plot4_comparison",
        "plot5_6_l1_error",
        "plot7_tip_response_drive",
        "plot8_force_distance",
    ):
        assert (tmp_path / f"{name}.png").stat().st_size > 1000, name
    summary = (tmp_path / "summary.md").read_text()
    assert "rk4_frozen" in summary and "near 45 nm" in summary
    # the stated amplitude at 40 nm is the corrected one, far from the notebook's 45 nm
    line = next(ln for ln in summary.splitlines() if ln.startswith("The correct integration"))
    amp_nm = float(line.split("**")[1].split()[0])
    assert 50 < amp_nm < 60


def test_bench_benchmark_tiny(capsys):
    # the speed benchmark (formerly afm_study bench) lives in the repository's benchmarks/, not in
    # the package
    from benchmarks import bench

    code = bench.main(["--steps", "20000", "--solve-ivp-periods", "12", "--no-startup"])
    assert code == 0
    result = json.loads(capsys.readouterr().out)
    for key in (
        "rk4_ns_per_step",
        "real_time_factor",
        "solve_ivp_ns_per_step",
        "speedup_vs_solve_ivp",
    ):
        assert result[key] > 0, key
    if "c_ns_per_step" in result:
        # the C baseline must be the same computation (bit-identical state), else the ratio is moot
        assert result["c_bit_identical_to_numba"] is True
    assert result["solve_ivp"][result["solve_ivp_method"]]["reached_target"]


def test_bench_subcommand_points_to_the_benchmark(capsys):
    # the installed package has no benchmark: afm_study bench says what to run instead and fails
    code = study.main(["bench", "--steps", "20000", "--solve-ivp-periods", "12", "--no-startup"])
    assert code == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert (
        "python -m benchmarks.bench --steps 20000 --solve-ivp-periods 12 --no-startup"
        in captured.err
    )


@pytest.mark.parametrize(
    "flag,value,field",
    [
        ("--quality-factor", "-1", "quality_factor"),
        ("--tip-radius", "nan", "tip_radius"),
        ("--steps-per-period", "10", "steps_per_period"),
        ("--spring-constant", "soft", "spring_constant"),
        ("--sample-poisson-ratio", "0.6", "sample_poisson_ratio"),
        ("--drive-force", "2.0", "drive_force"),
        ("--temperature", "-3", "temperature"),
        ("--detector-noise", "1e-6", "detector_noise_density"),
        ("--noise-seed", "0.5", "noise_seed"),
    ],
)
def test_bad_flag_exit_code_2_names_field(tmp_path, capsys, flag, value, field):
    code = study.main(["sweep", "--out", str(tmp_path / "o"), "--z-base", "40e-9", flag, value])
    assert code == 2
    err = capsys.readouterr().err
    assert field in err and "allowed" in err
    assert not (tmp_path / "o" / "sweep.csv").exists()


def test_bad_value_in_subprocess_no_traceback(tmp_path):
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "afm_ros.tools.study",
            "trajectory",
            "--out",
            str(tmp_path),
            "--z-base",
            "1.0",
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2
    assert "z_base=1.0 m is out of range" in proc.stderr and "Traceback" not in proc.stderr
    proc = subprocess.run(
        [sys.executable, "-m", "afm_ros.tools.study", "sweep", "--method", "rk5"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert (
        proc.returncode == 2 and "method='rk5'" in proc.stderr and "Traceback" not in proc.stderr
    )


def test_drive_force_flag_is_the_same_drive_as_free_amplitude():
    # F0 = k A0 / Q: 10 N/m * 30 nm / 25 = 12 nN drives the same oscillator as --free-amplitude
    # 30e-9
    parser = study.build_parser()
    by_force = study.physics_from_args(parser.parse_args(["sweep", "--drive-force", "1.2e-8"]))[1]
    by_amplitude = study.physics_from_args(
        parser.parse_args(["sweep", "--free-amplitude", "3e-8"])
    )[1]
    assert by_force.force == pytest.approx(by_amplitude.force, rel=1e-12, abs=0)
    assert by_force.frequency == by_amplitude.frequency


def test_thermal_tune_is_an_afm_study_subcommand(tmp_path):
    """`afm_study thermal` runs the thermal tune (its physics is tested in
    test_thermal_tune.py)."""
    from afm_ros.tools import study

    assert study.main(["thermal", "--seconds", "0.2", "--out", str(tmp_path)]) == 0
    for name in ("thermal_tune.csv", "thermal_tune.png", "thermal_tune.json"):
        assert (tmp_path / name).stat().st_size > 0
    assert study.main(["thermal", "--temperature", "-1", "--out", str(tmp_path)]) == 2


def test_contrast_is_an_afm_study_subcommand(tmp_path):
    """`afm_study contrast` runs the phase-contrast study (physics tested in test_contrast.py)."""
    from afm_ros.tools import study

    assert (
        study.main(
            [
                "contrast",
                "--ratios",
                "0.9:0.8:0.1",
                "--steps-per-period",
                "400",
                "--out",
                str(tmp_path),
            ]
        )
        == 0
    )
    assert (tmp_path / "contrast.csv").stat().st_size > 0 and (
        tmp_path / "contrast.png"
    ).stat().st_size > 0


def test_material_flag_sets_the_sample_and_explicit_values_win():
    from afm_ros.core.physics.materials import MATERIALS
    from afm_ros.tools import study

    parser = study.build_parser()
    ns = parser.parse_args(["sweep", "--material", "ldpe", "--sample-youngs-modulus", "1e9"])
    _, _, sample, _ = study.physics_from_args(ns)
    ldpe = MATERIALS["ldpe"]
    assert sample.sample_youngs_modulus == 1e9  # explicit
    assert (
        sample.sample_poisson_ratio == ldpe.poisson_ratio
        and sample.hamaker_constant == ldpe.hamaker_constant
    )
    assert ns.dissipation == {
        "viscosity": ldpe.viscosity,
        "hamaker_retract": ldpe.hamaker_constant_retract,
    }
    ns = parser.parse_args(["sweep"])
    _, _, sample, _ = study.physics_from_args(ns)
    assert sample.sample_youngs_modulus == 70e6  # no material: the seed notebook's sample


def test_noisy_sweep_averages_to_the_deterministic_answer_with_the_predicted_standard_error(
    tmp_path,
):
    """Sweep with thermal (300 K) and detector (100 fm/sqrt(Hz)) noise, free cantilever (z_base 200
    nm).

    Expected standard error of the amplitude over T = 200 periods: the thermal motion's quadrature
    components have variance kB T / k and correlation time tau = 2 Q / w0, so their mean over T has
    variance (kB T / k) 2 tau / T (5.7 pm); the detector adds D^2 / T (1.5 pm), together 5.9 pm.
    The sweep estimates it from 10 blocks of 20 periods (2.5 tau): the estimate scatters by ~24 %
    (9 degrees of freedom) and neighbouring blocks are correlated, which biases it low by up to ~40
    %; hence the accepted band 0.3 .. 2 times the prediction. The mean must lie within 5 predicted
    standard errors of the deterministic amplitude (thermal bias in quadrature: < 0.01 pm).
    """
    c = Cantilever()
    kbt = 1.380649e-23 * 300.0
    tau = 2 * c.quality_factor / c.omega0
    t_avg = 200 / c.resonance_frequency
    predicted = math.sqrt(kbt / c.spring_constant * 2 * tau / t_avg + (1e-13) ** 2 / t_avg)
    exact = study.sweep([200e-9], progress=False)[0]
    code = study.main(
        [
            "sweep",
            "--out",
            str(tmp_path),
            "--z-base",
            "200e-9,40e-9",
            "--temperature",
            "300",
            "--detector-noise",
            "1e-13",
            "--noise-seed",
            "3",
            "--no-progress",
        ]
    )
    assert code == 0
    rows = read_csv(tmp_path / "sweep.csv")
    assert list(rows[0])[-2:] == ["amplitude_sem_m", "phase_sem_deg"]
    free = rows[0]
    assert 0.3 * predicted < float(free["amplitude_sem_m"]) < 2 * predicted
    assert abs(float(free["amplitude_m"]) - exact["amplitude_m"]) < 5 * predicted
    # phase: the same quadrature noise over the amplitude, in degrees
    assert abs(float(free["phase_deg"]) - exact["phase_deg"]) < math.degrees(
        5 * predicted / exact["amplitude_m"]
    )
    assert int(free["periods_simulated"]) == 200 + math.ceil(10 * c.quality_factor / math.pi)
    again = study.sweep(
        [200e-9, 40e-9], temperature=300, detector_density=1e-13, noise_seed=3, progress=False
    )
    assert [r["amplitude_m"] for r in again] == [
        float(r["amplitude_m"]) for r in rows
    ]  # a seed reproduces a run
    other = study.sweep(
        [200e-9], temperature=300, detector_density=1e-13, noise_seed=4, progress=False
    )
    assert other[0]["amplitude_m"] != again[0]["amplitude_m"]


# --- issue 16.17: numeric flags that would fill the memory are refused before any work
# ----------------
@pytest.mark.parametrize(
    "args,hint",
    [
        (
            ["convergence", "--periods", "1000000000"],
            "--periods <= 1562",
        ),  # 12800 steps per period (Euler)
        (["convergence", "--methods", "rk4", "--periods", "1000000000"], "--periods <= 44642"),
        (
            ["convergence", "--periods", "5", "--window-periods", "10"],
            "--window-periods=10 must be at most --periods=5",
        ),
        (
            [
                "sweep",
                "--z-base",
                "40e-9",
                "--temperature",
                "300",
                "--average-periods",
                "1000000000",
            ],
            "--average-periods <= 250000",
        ),
        (
            [
                "sweep",
                "--z-base",
                "40e-9",
                "--steps-per-period",
                "100000",
                "--quality-factor",
                "1e6",
            ],
            "--quality-factor <= 628 at this step count, or fewer --steps-per-period",
        ),
        (["trajectory", "--periods", "1000000000"], "--periods <= 12500"),
        (["trajectory", "--from-rest", "1000000000"], "--from-rest <= 250000"),
        (
            ["trajectory", "--steps-per-period", "100000", "--quality-factor", "1e6"],
            "--quality-factor <= 628",
        ),
        (["notebook", "--quality-factor", "1e6"], "--quality-factor <= 19634"),
    ],
)
def test_flags_that_would_fill_the_memory_are_refused_before_any_work(
    tmp_path, capsys, args, hint
):
    """Each run keeps the samples it records (24 bytes per step); the bounds are fixed (2e7 steps,
    480 MB; the trajectory's CSV 1e6 rows), so the refusal is the same on every machine. Expected
    limits, from the module's bounds and the step counts: convergence 2e7 // 12800 (Euler's finest)
    = 1562 periods, // 448 (RK4's) = 44642; the sweep's average and the trajectory's warm-up 2e7 //
    80 (the default step count) = 250000; the trajectory's CSV 1e6 // 80 = 12500; a steady-state
    window is Q/pi periods: Q <= pi * (2e7 // 1e5) = 628 at 1e5 steps per period, pi * (2e7 //
    3200) = 19634 for the notebook's reference runs. Before, each of these died with a MemoryError
    traceback (or worse, started)."""
    import time

    out = tmp_path / "o"
    t0 = time.monotonic()
    assert study.main([*args, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert (
        err.count("\n") == 1 and err.startswith(f"afm_study {args[0]}: error: ") and hint in err
    ), err
    if "must be at most" not in hint:
        assert "integration steps in memory" in err and "allowed" in err
    assert time.monotonic() - t0 < 20
    assert not out.exists() or not any(out.iterdir())


def test_flags_at_the_bounds_are_accepted():
    """The largest allowed values pass the checks (the checks alone: the runs would take
    minutes)."""
    from afm_ros.core.physics import Cantilever

    study.check_recorded_steps("x", study.MAX_RECORDED_STEPS, "")
    assert (
        study.steady_window_steps(Cantilever(quality_factor=628.0), 100_000)
        <= study.MAX_RECORDED_STEPS
    )
    assert (
        study.steady_window_steps(Cantilever(quality_factor=629.0), 100_000)
        > study.MAX_RECORDED_STEPS
    )
    assert (
        study.steady_window_steps(Cantilever(), 220) == 8 * 220
    )  # Q = 25: ceil(25 / pi) = 8 periods
