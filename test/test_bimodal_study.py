"""``afm_study bimodal`` (tools/bimodal_study.py): the sweep's table and figure, its physics in
the written numbers, and bad values refused in one line before any work."""

import csv
import math
import signal
import subprocess
import sys

import pytest

from afm_ros.tools.study import main


@pytest.mark.slow
def test_the_sweep_writes_the_table_and_figure_with_the_physics_in_them(tmp_path, capsys):
    out = tmp_path / "bimodal"
    code = main(
        ["bimodal", "--materials", "ldpe", "--z-base", "40e-9,21e-9,16e-9", "--out", str(out)]
    )
    assert code == 0
    rows = list(csv.DictReader(open(out / "bimodal.csv")))
    assert [float(r["z_base_m"]) for r in rows] == [40e-9, 21e-9, 16e-9]
    far, mid, near = ({k: float(v) for k, v in r.items() if k != "material"} for r in rows)
    # 40 nm: A1 (25 nm) never reaches the Hertz sample: mode 2 keeps its free frequency
    assert far["df2_Hz"] == 0.0 and math.isnan(far["recovered_modulus_Pa"])
    assert far["a1_m"] == pytest.approx(25e-9, rel=1e-3)
    # deeper z_base: mode 1's amplitude drops, the contact stiffens mode 2 more
    assert near["a1_m"] < mid["a1_m"] < far["a1_m"]
    assert near["df2_Hz"] > mid["df2_Hz"] > 0.0
    for r in (mid, near):
        # the averaging's own error (docs/bimodal.md 3.2) and the method's bias (test_bimodal)
        assert r["df2_Hz"] == pytest.approx(r["df2_first_order_orbit_Hz"], rel=0.07)
        assert r["recovered_modulus_Pa"] == pytest.approx(r["true_modulus_Pa"], rel=0.15)
    assert (out / "bimodal.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    text = capsys.readouterr().out
    assert "no repulsive contact" in text and "3 point(s)" in text


@pytest.mark.parametrize(
    "args, message",
    [
        (["--z-base", "21e-9,2"], "z_base: 2.0 is out of range; allowed range [5e-10, 1e-06]"),
        (["--materials", "cheese"], "cheese"),
        (["--q-exponent", "0.7"], "q_exponent: 0.7 is not one of 0, 0.5, 1"),
        (["--mode2-amplitude", "x"], "mode2_amplitude: 'x' is not a number"),
        (
            ["--spring-constant", "0"],
            "spring_constant=0.0 N/m is out of range; allowed range [0.001, 10000] N/m",
        ),
    ],
)
def test_bad_values_are_refused_in_one_line_before_any_work(tmp_path, capsys, args, message):
    out = tmp_path / "never"
    assert main(["bimodal", *args, "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not out.exists()


@pytest.mark.slow
def test_ctrl_c_writes_the_points_done_and_says_so(tmp_path):
    out = tmp_path / "cut"
    proc = subprocess.Popen(
        [sys.executable, "-m", "afm_ros.tools.study", "bimodal", "--materials", "ldpe",
         "--z-base", ",".join(["21e-9"] * 50), "--out", str(out)],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    for line in proc.stdout:  # the first point's line: one is done
        if "ldpe" in line and "z_base" in line:
            break
    proc.send_signal(signal.SIGINT)
    rest, err = proc.communicate(timeout=60)
    assert proc.returncode == 130
    rows = list(csv.DictReader(open(out / "bimodal.csv")))
    assert 1 <= len(rows) < 50
    assert f"interrupted after {len(rows)} point(s); writing those" in err
    assert "Traceback" not in err
