"""afm_study scan: the files it writes (read back by readers this project did not write: gwyfile
directly, Gwyddion's thumbnailer), the summary, a written image as a sample again, bad flags.

A small frame (16 px x 8 lines at 8 lines/s over 2.5 um of the PS/LDPE blend: 1 s simulated)
scanned once by the command line in a subprocess and once in-process with the same flags: the
scan is deterministic (noise off by default), so the file must hold the in-process frame's
values bit for bit.
"""

import argparse
import json
import shutil
import subprocess
import sys

import gwyfile
import numpy as np
import pytest

from afm_ros.core.imaging import CHANNELS, DIRECTIONS, UNITS
from afm_ros.core.samples import from_file
from afm_ros.formats.frames import channel_title, frame_channels
from afm_ros.tools import scan, study

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
ARGS = [
    "--sample",
    "ps_ldpe_blend",
    "--scan-size-x",
    "2.5e-6",
    "--scan-size-y",
    "2.5e-6",
    "--scan-center-x",
    "6e-6",
    "--scan-center-y",
    "3e-6",
    "--pixels-per-line",
    "16",
    "--lines",
    "8",
    "--line-rate",
    "8",
    "--engage-time",
    "0.05",
    "--quiet",
]


@pytest.fixture(scope="module")
def cli(tmp_path_factory):
    out = tmp_path_factory.mktemp("scan")
    proc = subprocess.run(
        [sys.executable, "-m", "afm_ros.tools.study", "scan", *ARGS, "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    return out, proc


@pytest.fixture(scope="module")
def frame():
    parser = argparse.ArgumentParser()
    scan._add_arguments(parser)
    config = scan.config_from_args(parser.parse_args(ARGS))
    return scan.run_scan(config).frame


@pytest.mark.slow
def test_cli_writes_gwy_previews_and_summary(cli):
    out, proc = cli
    text = proc.stdout
    for words in (
        "afm_study scan summary",
        "step height",
        "true 10.000 nm",
        "predicted apparent",
        "phase contrast",
        "ldpe - polystyrene",
        "trace-retrace rms",
        "real-time factor",
        "edge exclusion",
    ):
        assert words in text, words
    assert (out / "scan.gwy").is_file()
    for channel in CHANNELS:
        for direction in DIRECTIONS:
            data = (out / f"scan_{channel}_{direction}.png").read_bytes()
            assert data.startswith(PNG_SIGNATURE) and len(data) > 1000
    summary = json.loads((out / "scan_summary.json").read_text())
    assert summary["scan"]["pixels_per_line"] == 16 and summary["scan"]["lines"] == 8
    assert summary["scan"]["speed_m_per_s"] == pytest.approx(2 * 2.5e-6 * 8, rel=1e-12, abs=0)
    assert summary["step"]["true_m"] == pytest.approx(10e-9, rel=0, abs=1e-15)
    assert summary["step"]["level_materials"] == ["polystyrene", "ldpe"]
    assert summary["edge_exclusion_m"] > 0 and summary["kept_pixels"] > 0
    assert summary["timing"]["simulated_scan_s"] == pytest.approx(1.0, rel=1e-12)
    assert summary["timing"]["real_time_factor"] > 0
    assert (
        summary["prediction"]["ldpe"]["phase_deg"]
        > summary["prediction"]["polystyrene"]["phase_deg"]
    )
    assert summary["peak_rss_bytes"] > 10 * 2**20
    assert not [
        p for p in out.iterdir() if p.name.endswith(".tmp")
    ]  # atomic writes left no temporary


@pytest.mark.slow
def test_gwy_read_back_with_gwyfile(cli, frame):
    """gwyfile itself: 10 channels with titles, pixel counts, real size = scan size, offsets =
    the scan's lower-left corner, SI units, values equal to the frame's, metadata as strings."""
    out, _ = cli
    obj = gwyfile.load(str(out / "scan.gwy"))
    plan = frame.plan
    expected = frame_channels(frame)
    assert list(expected) == [channel_title(c, d) for c in CHANNELS for d in DIRECTIONS]
    for n, (title, (values, unit)) in enumerate(expected.items()):
        field = obj[f"/{n}/data"]
        assert obj[f"/{n}/data/title"] == title
        assert (field["xres"], field["yres"]) == (16, 8)
        assert field["xreal"] == plan.size_x and field["yreal"] == plan.size_y
        assert field["xoff"] == pytest.approx(4.75e-6, rel=1e-12, abs=0)
        assert field["yoff"] == pytest.approx(1.75e-6, rel=1e-12, abs=0)
        assert field["xoff"] == plan.x_left and field["yoff"] == plan.y_low
        assert field["si_unit_xy"]["unitstr"] == "m"
        assert field["si_unit_z"]["unitstr"] == unit
        data = np.asarray(field["data"], dtype=float).reshape(8, 16)
        assert np.array_equal(data, values), title
    assert obj["/0/data/title"] == "Height (trace)" and UNITS["phase"] == "deg"
    meta = obj["/0/meta"]
    assert meta["scan.line_rate [Hz]"] == "8.0"
    assert meta["scan.pixels_per_line"] == "16"
    assert meta["feedback.setpoint [m]"] == "4.8e-08"
    assert meta["feedback.i_gain [1/s]"] == "100.0"
    assert meta["cantilever.force_model"] == "viscoelastic_dmt"
    assert meta["cantilever.temperature [K]"] == "0.0"
    assert meta["sample.generator"] == "blend" and meta["sample.islands"] == "ldpe"
    assert meta["sample.spec"] == "ps_ldpe_blend"
    assert all(isinstance(v, str) for v in meta.values())


@pytest.mark.slow
@pytest.mark.skipif(
    shutil.which("gwyddion-thumbnailer") is None,
    reason="gwyddion-thumbnailer not installed (Debian package gwyddion)",
)
def test_gwyddion_renders_the_scan(cli, tmp_path):
    out, _ = cli
    for n in (0, 4, 9):  # Height (trace), Phase (trace), Dissipation (retrace)
        png = tmp_path / f"thumb{n}.png"
        run = subprocess.run(
            [
                "gwyddion-thumbnailer",
                "-c",
                str(n),
                "gnome2",
                "128",
                str(out / "scan.gwy"),
                str(png),
            ],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert run.returncode == 0, run.stderr
        data = png.read_bytes()
        assert data.startswith(PNG_SIGNATURE) and len(data) > 60


@pytest.mark.slow
def test_written_gwy_is_a_sample_again(cli, frame, tmp_path, capsys):
    """from_file takes the first channel (Height (trace), unit m) at the file's real size: the
    height map is the frame's, bit for bit; and the tool images it (--sample FILE.gwy)."""
    out, _ = cli
    sample = from_file(str(out / "scan.gwy"))
    assert np.array_equal(sample.height, frame.images["trace"]["height"].astype(float))
    assert (sample.size_x, sample.size_y) == (frame.plan.size_x, frame.plan.size_y)
    assert sample.materials == ("silicon",)
    with pytest.raises(ValueError, match="Phase"):
        from_file(str(out / "scan.gwy"), channel="Phase (trace)")  # deg, not a height
    rc = scan.main(
        [
            "--sample",
            str(out / "scan.gwy"),
            "--scan-size-x",
            "2e-6",
            "--scan-size-y",
            "2e-6",
            "--scan-center-x",
            "1.25e-6",
            "--scan-center-y",
            "1.25e-6",
            "--pixels-per-line",
            "8",
            "--lines",
            "2",
            "--line-rate",
            "10",
            "--engage-time",
            "0.02",
            "--force-model",
            "dmt",
            "--quiet",
            "--no-previews",
            "--out",
            str(tmp_path / "again"),
        ]
    )
    assert rc == 0
    assert "silicon" in capsys.readouterr().out
    assert (tmp_path / "again" / "scan.gwy").is_file()
    assert not list((tmp_path / "again").glob("*.png"))


@pytest.mark.parametrize(
    "flags, field",
    [
        (["--scan-size-x", "2"], "scan_size_x"),
        (["--lines", "0"], "lines"),
        (["--line-rate", "abc"], "line_rate"),
        (["--slow-scan-direction", "left"], "slow_scan_direction"),
        (["--setpoint", "7e-8"], "setpoint"),
        (["--i-gain", "-1"], "i_gain"),
        (["--force-model", "none"], "force_model"),
        (["--sample", "nosuch"], "sample"),
        (["--pixels-per-line", "600"], "pixels_per_line"),
        (["--temperature", "-1"], "temperature"),
        (["--engage-time", "-0.1"], "engage_time"),
        (["--approach", "0.5"], "approach"),
        (["--imperfection", "tilt_x=0.5"], "imperfection"),
        (["--imperfection", "creep_per_decade=0.2"], "imperfection"),
        (
            ["--imperfection", "scanner_field=1e-6"],
            "scan_size_x",
        ),  # the 5 um scan does not fit in a 1 um field
    ],
)
def test_bad_flags_exit_2_with_one_line_naming_the_field(flags, field, tmp_path, capsys):
    out = tmp_path / "never"
    assert study.main(["scan", *flags, "--out", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err
    flag = "--" + field.replace("_", "-")
    assert err.startswith(f"afm_study scan: error: {flag}: ") and field in err
    assert "allowed" in err
    assert not out.exists()


def test_pixels_per_line_limit_follows_the_lockin_output_rate():
    """A pixel lasts 1 / (2 line_rate pixels); it needs one lock-in output, which comes every
    1/output_rate, up to one input sample (1/900 kHz) late: 1 Hz, 1 kHz -> 499 pixels."""
    from afm_ros.core.scanner import max_pixels

    interval = 1.0 / 900e3
    assert max_pixels(1.0, 1000.0, interval) == 499
    assert max_pixels(4.0, 1000.0, interval) == 124
    assert max_pixels(100.0, 125e3, interval) == 548


def test_edge_mask_with_equal_distances_is_the_one_distance_mask():
    """edge_mask with a y distance equal to the x distance is the one-distance mask; a wider x
    distance alone (the feedback lags along the fast axis only) keeps more than both."""
    from afm_ros.core.image_analysis import edge_mask, sample_under_pixels
    from afm_ros.core.samples import resolve_sample
    from afm_ros.core.scanner import ScanPlan

    plan = ScanPlan.from_values(
        dict(scan_size_x=5e-6, scan_size_y=4e-6, pixels_per_line=64, lines=40)
    )
    _, mat = sample_under_pixels(resolve_sample("ps_ldpe_blend"), plan)
    for d in (0.0, 0.05e-6, 0.2e-6, 0.5e-6):
        assert np.array_equal(edge_mask(mat, plan, d, d), edge_mask(mat, plan, d))
    wide_x = edge_mask(mat, plan, 0.5e-6, 0.0)
    assert wide_x.sum() > edge_mask(mat, plan, 0.5e-6).sum()


LONG = [
    a if a != "8" or ARGS[i - 1] != "--lines" else "128"
    for i, a in enumerate(ARGS)
    if a != "--quiet"
]


@pytest.mark.slow
def test_ctrl_c_keeps_the_completed_lines_and_exits_130(tmp_path):
    """SIGINT once lines have been reported: the scan finishes the current line, writes the
    completed lines as scan_partial.gwy (+ previews, readable by gwyfile; the lines equal those of
    a full run: the scan is deterministic), prints the summary marked interrupted and exits 130.
    It used to print a 25-line traceback and keep nothing."""
    import signal

    assert "--lines" in LONG and LONG[LONG.index("--lines") + 1] == "128"
    out = tmp_path / "out"
    proc = subprocess.Popen(
        [sys.executable, "-m", "afm_ros.tools.study", "scan", *LONG, "--out", str(out)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    err = []
    for (
        line
    ) in proc.stderr:  # progress lines: "afm_study scan: line 13/128 (0.6 s)" at every tenth
        err.append(line)
        if "line 13/128" in line:
            proc.send_signal(signal.SIGINT)
            break
    rest_err = proc.stderr.read()
    stdout = proc.stdout.read()
    assert proc.wait(timeout=300) == 130, "".join(err) + rest_err
    assert "Traceback" not in rest_err and "interrupted: finishing line" in rest_err, rest_err
    assert "afm_study scan summary (interrupted)" in stdout and "Ctrl-C after" in stdout, stdout
    assert not (out / "scan.gwy").exists()
    assert {p.name for p in out.glob("scan_partial_*.png")} == {
        f"scan_partial_{c}_{d}.png" for c in CHANNELS for d in DIRECTIONS
    }
    summary = json.loads((out / "scan_summary.json").read_text())
    done = summary["interrupted"]["lines_done"]
    assert (
        summary["interrupted"]["partial"] is True
        and summary["interrupted"]["lines_planned"] == 128
    )
    assert 13 <= done < 128 and summary["scan"]["lines"] == done
    obj = gwyfile.load(str(out / "scan_partial.gwy"))
    assert obj["/0/meta"]["frame.partial"] == "true" and obj["/0/meta"]["frame.lines_done"] == str(
        done
    )
    assert obj["/0/meta"]["scan.lines"] == "128"
    parser = argparse.ArgumentParser()
    scan._add_arguments(parser)
    full = scan.run_scan(scan.config_from_args(parser.parse_args(LONG + ["--quiet"]))).frame
    pitch = full.plan.line_pitch
    for n, (title, (values, unit)) in enumerate(frame_channels(full).items()):
        field = obj[f"/{n}/data"]
        assert obj[f"/{n}/data/title"] == title
        assert (field["xres"], field["yres"]) == (16, done)
        assert field["yreal"] == pytest.approx(done * pitch, rel=1e-12, abs=0)
        assert field["yoff"] == pytest.approx(full.plan.y_low, rel=1e-12, abs=0)
        data = np.asarray(field["data"], dtype=float).reshape(done, 16)
        assert np.array_equal(data, values[:done]), title


@pytest.mark.slow
def test_approach_and_a_real_instrument_from_the_command_line(tmp_path):
    """--approach 5e-6: the workflow's approach (3 um z range, 50 nm motor steps, 80 % of the range
    per cycle) finds no surface in the first extension, steps 2.4 um (48 steps) and engages in the
    second; --imperfections: the instrument's drift, hysteresis, tilt and tip wear, listed in the
    summary; the height image's plane is the tilt the loop followed (1 % for the loop's lag at the
    line ends)."""
    out = tmp_path / "o"
    proc = subprocess.run(
        [
            sys.executable,
            "-m",
            "afm_ros.tools.study",
            "scan",
            "--pixels-per-line",
            "32",
            "--lines",
            "8",
            "--line-rate",
            "2",
            "--approach",
            "5e-6",
            "--imperfections",
            "--quiet",
            "--out",
            str(out),
        ],
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert proc.returncode == 0, proc.stderr
    summary = json.loads((out / "scan_summary.json").read_text())
    approach = summary["approach"]
    assert approach["cycles"] == 2 and approach["motor_steps"] == 48
    assert -3e-6 < approach["engaged_z_m"] < -2.4e-6
    assert (
        summary["imperfections"]["tilt_x"] == 0.008
        and summary["imperfections"]["tip_wear_coefficient"] == 5e-9
    )
    assert summary["tip_radius_m"]["end"] > summary["tip_radius_m"]["start"]
    gx, gy = summary["height_slope"]
    assert gx == pytest.approx(0.008, rel=0.05) and gy == pytest.approx(-0.005, rel=0.05)
    assert (
        "approach             from 5 um" in proc.stdout
        and "imperfections        drift_lateral_rate" in proc.stdout
    )


@pytest.mark.slow
def test_the_analysis_compares_each_pixel_with_the_sample_where_the_scanner_truly_was():
    """With a wide hysteresis loop (10 % of the scan: pixels land up to 250 nm, 3 pixels, off their
    commanded place, in opposite directions on trace and retrace), the material a pixel's phase
    says (nearer the PS or the LDPE median) is the material truth_under_pixels puts there for 93 %
    or more of the pixels (the rest: the loop's transients at island edges), and for at most 88 %
    at the commanded positions."""
    from afm_ros.core.image_analysis import sample_under_pixels, truth_under_pixels

    parser = argparse.ArgumentParser()
    scan._add_arguments(parser)
    config = scan.config_from_args(
        parser.parse_args(
            [
                "--pixels-per-line",
                "64",
                "--lines",
                "8",
                "--line-rate",
                "1",
                "--quiet",
                "--imperfection",
                "hysteresis_small=0.1",
            ]
        )
    )
    result = scan.run_scan(config)
    frame = result.frame
    under = truth_under_pixels(config.sample, frame.plan, result.artefacts, frame.index)
    _, commanded = sample_under_pixels(config.sample, frame.plan)
    for direction in ("trace", "retrace"):
        phase = frame.images[direction]["phase"].astype(float)
        material = under[direction].material
        ps, ldpe = np.median(phase[material == 0]), np.median(phase[material == 1])
        said = (np.abs(phase - ldpe) < np.abs(phase - ps)).astype(int)
        assert (said == material).mean() >= 0.93, direction
        assert (said == commanded).mean() <= 0.88, direction
