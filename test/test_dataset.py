"""``afm_study dataset`` (issue 21): a spec, frames of the offline instrument with their ground
truth, a Zarr store xarray opens, on local processes or a real Dask cluster.

Checked: a bad spec is refused naming the field before any work; the dataset is the same bit for
bit with one worker, two worker processes and a local Dask cluster of two workers; a run killed
(SIGKILL) mid-way continues where it stopped and ends with the same dataset; each frame's ground
truth is its own sample's (regenerated from the frame's drawn parameters) under the pixel centres.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from afm_ros.core.dataset import frame_config, load_spec, validate
from afm_ros.formats import dataset_store
from afm_ros.tools.dataset import make_dataset

BIN = Path(sys.executable).parent
SPEC = """\
frames: 4
seed: 7
pixels: 16
lines: 8
scan_size: 1.0e-6
line_rate: {uniform: [6.0, 10.0]}
force_model: {choice: [viscoelastic_dmt, hysteresis_dmt]}
engage_time: 0.03
sample:
  generator: blend
  size: [2.0e-6, 2.0e-6]
  pixels: 128
  island_fraction: {uniform: [0.2, 0.4]}
instrument:
  setpoint_ratio: {uniform: [0.7, 0.85]}
  tip_radius: {log_uniform: [10.0e-9, 30.0e-9]}
"""


def _equal(a_path, b_path):
    import xarray as xr

    a, b = xr.open_zarr(str(a_path)), xr.open_zarr(str(b_path))
    assert set(a.data_vars) == set(b.data_vars)
    for name in a.data_vars:
        x, y = a[name].values, b[name].values
        assert np.array_equal(x, y, equal_nan=x.dtype.kind == "f"), name
    assert a.attrs == b.attrs


@pytest.fixture(scope="module")
def spec_file(tmp_path_factory):
    path = tmp_path_factory.mktemp("spec") / "tiny.yaml"
    path.write_text(SPEC)
    return path


@pytest.fixture(scope="module")
def reference(spec_file, tmp_path_factory):
    """The dataset made in this process, one frame after the other."""
    out = tmp_path_factory.mktemp("ref") / "ref.zarr"
    lines = []
    summary = make_dataset(load_spec(spec_file), out, workers=1, say=lines.append)
    assert summary["done"] == 4 and not summary["interrupted"]
    assert any("4/4 done" in line for line in lines)  # the progress line: frames, rate, time left
    return out


@pytest.mark.parametrize(
    "change,field",
    [
        ({"frames": 0}, "frames=0 is out of range"),
        ({"pixels": {"uniform": [8, 16]}}, "pixels must be fixed"),
        ({"line_rate": {"uniform": [6.0, 1000.0]}}, "line_rate"),
        (
            {"line_rate": {"uniform": [10.0, 6.0]}},
            "line_rate: uniform needs [low, high] with low <= high",
        ),
        ({"force_model": "none"}, "force_model='none' is not allowed"),
        (
            {"sample": {"generator": "blend", "island_fraction": {"uniform": [0.2, 1.5]}}},
            "sample.island_fraction",
        ),
        ({"sample": {"generator": "blob"}}, "sample.generator='blob' is not known"),
        (
            {"instrument": {"setpoint_ratio": {"uniform": [0.5, 1.2]}}},
            "instrument.setpoint_ratio=1.2",
        ),
        ({"instrument": {"tip_radius": -1e-9}}, "instrument.tip_radius"),
        (
            {"instrument": {"imperfections": {"drift_x": 1.0}}},
            "instrument.imperfections.drift_x: not known",
        ),
        ({"colour": "red"}, "unknown key(s) 'colour'"),
        (
            {"pixels": 512, "line_rate": 50.0, "lockin_output_rate": 1000.0},
            "pixels=512 at line_rate=50 Hz",
        ),
        (
            {
                "sample": {
                    "generator": "from_file",
                    "path": "/nonexistent/map.npy",
                    "size": [1e-6, 1e-6],
                }
            },
            "sample.path: cannot read sample file /nonexistent/map.npy",
        ),
    ],
)
def test_bad_spec_is_refused_naming_the_field_before_any_work(tmp_path, change, field):
    import yaml

    spec = {**yaml.safe_load(SPEC), **change}
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump(spec))
    with pytest.raises(ValueError) as err:
        load_spec(path)
    assert field in str(err.value) and str(path) in str(err.value), str(err.value)
    out = tmp_path / "never.zarr"
    code = subprocess.run(
        [str(BIN / "afm_study"), "dataset", str(path), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert code.returncode == 2 and field in code.stderr and "Traceback" not in code.stderr
    assert not out.exists()  # refused before any work


@pytest.mark.slow
def test_the_same_dataset_with_two_worker_processes(spec_file, reference, tmp_path):
    out = tmp_path / "two.zarr"
    make_dataset(load_spec(spec_file), out, workers=2, say=lambda s: None)
    _equal(reference, out)


@pytest.mark.slow
def test_the_same_dataset_on_a_local_dask_cluster_of_two_workers(spec_file, reference, tmp_path):
    from distributed import LocalCluster

    out = tmp_path / "dask.zarr"
    with LocalCluster(
        n_workers=2, threads_per_worker=1, processes=True, dashboard_address=None
    ) as cluster:
        make_dataset(
            load_spec(spec_file), out, scheduler=cluster.scheduler_address, say=lambda s: None
        )
    _equal(reference, out)


@pytest.mark.slow
def test_a_killed_run_continues_where_it_stopped(spec_file, reference, tmp_path):
    """SIGKILL once frame 0 and at least one more are in the store (no chance to clean up); running
    the same command again makes only the missing frames and ends with the reference, bit for
    bit."""
    out = tmp_path / "killed.zarr"
    cmd = [str(BIN / "afm_study"), "dataset", str(spec_file), "--out", str(out), "--workers", "1"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 240
        while True:
            assert proc.poll() is None, "the run ended before it could be killed"
            assert time.monotonic() < deadline, "no frame written in time"
            if (
                dataset_store.spec_of(out) is not None
                and dataset_store.done_frames(out).sum() >= 2
            ):
                break
            time.sleep(0.05)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.wait(timeout=60)
    done = dataset_store.done_frames(out)
    assert 2 <= done.sum() < 4, done
    again = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert again.returncode == 0, again.stderr
    assert (
        f"{int(done.sum()) + 1}/4 done" in again.stdout
    )  # it started from the frames already there
    _equal(reference, out)


@pytest.mark.slow
def test_max_frames_stops_with_that_many_frames_in_the_store(spec_file, reference, tmp_path):
    out = tmp_path / "part.zarr"
    spec = load_spec(spec_file)
    assert make_dataset(spec, out, workers=1, max_frames=2, say=lambda s: None)["done"] == 2
    assert (
        make_dataset(spec, out, workers=1, max_frames=2, say=lambda s: None)["done"] == 2
    )  # nothing to add
    assert make_dataset(spec, out, workers=1, say=lambda s: None)["done"] == 4
    _equal(reference, out)


def test_a_store_of_another_spec_is_not_continued(spec_file, reference):
    import yaml

    other = validate({**yaml.safe_load(SPEC), "seed": 8})
    with pytest.raises(ValueError, match="holds a dataset of another spec"):
        make_dataset(other, reference, workers=1)


def test_each_frames_truth_is_its_own_sample(spec_file, reference):
    """Without imperfections the apex is where it was commanded: the true height and material are
    the frame's sample (regenerated from its drawn parameters) at the pixel centres, the dilated
    height the sample dilated by the frame's tip radius; the frames differ (their draws)."""
    from afm_ros.core.image_analysis import sample_under_pixels
    from afm_ros.core.samples import dilate
    from afm_ros.core.scanner import ScanPlan

    spec = load_spec(spec_file)
    ds = dataset_store.open_dataset(reference)
    assert ds.sizes["frame"] == 4 and bool(ds["done"].all())
    fractions = []
    for i in range(4):
        fc = frame_config(spec, i)
        plan = ScanPlan.from_values(fc.scan.plan_values)
        height, material = sample_under_pixels(fc.scan.sample, plan)
        apex, _ = sample_under_pixels(dilate(fc.scan.sample, fc.values["tip_radius_m"]), plan)
        for d in range(2):
            np.testing.assert_array_equal(
                ds["true_height"][i, d].values, height.astype(np.float32)
            )
            np.testing.assert_array_equal(ds["material"][i, d].values, material.astype(np.uint8))
            np.testing.assert_array_equal(
                ds["dilated_height"][i, d].values, apex.astype(np.float32)
            )
        assert float(ds["tip_radius_m"][i]) == fc.values["tip_radius_m"]
        # no imperfections: the apex was at the commanded pixel centres
        for d in range(2):
            np.testing.assert_allclose(
                ds["apex_x_m"][i, d].values,
                np.broadcast_to(ds["x_m"][i].values, (8, 16)),
                rtol=0,
                atol=1e-15,
            )
            np.testing.assert_allclose(
                ds["apex_y_m"][i, d].values.T,
                np.broadcast_to(ds["y_m"][i].values, (16, 8)),
                rtol=0,
                atol=1e-15,
            )
        fractions.append(float(ds["sample_island_fraction"][i]))
        # the measured height follows the truth: the islands (10 nm) stand out of the matrix
        measured = ds["measured"][i, 0, 0].values
        assert np.isfinite(measured).all()
        if (material == 1).any() and (material == 0).any():
            assert np.median(measured[material == 1]) != np.median(measured[material == 0])
    assert len(set(fractions)) == 4 and all(0.2 <= f <= 0.4 for f in fractions)


def test_with_imperfections_the_truth_is_where_the_apex_really_was(tmp_path):
    """The real instrument's imperfections (hysteresis, creep, drift, tilt): the apex left the
    commanded pixel centres (by up to the hysteresis loop's width), differently in trace and
    retrace, and the true height and material are the sample's at the apex's true position."""
    import yaml

    spec = validate({**yaml.safe_load(SPEC), "frames": 1, "instrument": {"imperfections": True}})
    out = tmp_path / "imperfect.zarr"
    make_dataset(spec, out, workers=1, say=lambda s: None)
    ds = dataset_store.open_dataset(out)
    sample = frame_config(spec, 0).scan.sample
    shift = np.hypot(
        ds["apex_x_m"][0].values - ds["x_m"][0].values[None, None, :],
        ds["apex_y_m"][0].values - ds["y_m"][0].values[None, :, None],
    )
    assert (
        shift.max() > 5e-9
    )  # the imperfections moved the apex (the loop is a few % of the 1 um scan)
    assert not np.array_equal(ds["apex_x_m"][0, 0].values, ds["apex_x_m"][0, 1].values)
    assert float(np.abs(ds["sample_plane"][0]).max()) > 0.0  # the tilt
    for d in range(2):
        xs, ys = ds["apex_x_m"][0, d].values, ds["apex_y_m"][0, d].values
        cols = (
            np.floor(np.mod(xs, sample.size_x) / sample.pixel_x).astype(int)
            % sample.height.shape[1]
        )
        rows = (
            np.floor(np.mod(ys, sample.size_y) / sample.pixel_y).astype(int)
            % sample.height.shape[0]
        )
        np.testing.assert_array_equal(
            ds["true_height"][0, d].values, sample.height[rows, cols].astype(np.float32)
        )
        np.testing.assert_array_equal(
            ds["material"][0, d].values, sample.material_index[rows, cols]
        )


def _refused(spec_path, out, field: str) -> None:
    code = subprocess.run(
        [str(BIN / "afm_study"), "dataset", str(spec_path), "--out", str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    lines = code.stderr.strip().splitlines()
    assert code.returncode == 2 and len(lines) == 1 and field in lines[0], code.stderr


@pytest.mark.slow
def test_an_output_folder_that_cannot_be_written_is_refused_naming_out(spec_file, tmp_path):
    _refused(spec_file, "/proc/never.zarr", "--out='/proc/never.zarr': cannot write in /proc")
    (tmp_path / "a_file").write_text("")
    _refused(spec_file, tmp_path / "a_file", "is a file, not a folder")


@pytest.mark.slow
def test_a_hostile_spec_is_refused_in_one_line(tmp_path):
    """Nine levels of nine aliases (a billion laughs), 5000 nested lists, a binary file, a huge
    file."""
    laughs = "a: &a [lol, lol, lol, lol, lol, lol, lol, lol, lol]\n"
    for prev, name in zip("abcdefgh", "bcdefghi"):
        laughs += f"{name}: &{name} [" + ", ".join([f"*{prev}"] * 9) + "]\n"
    cases = {
        "bomb.yaml": (laughs, "expands to more than 100000 values"),
        "deep.yaml": ("[" * 5000 + "]" * 5000, "nested deeper than 64 levels"),
        "binary.yaml": (b"\x89PNG\r\n\x1a\n\x00\xff", "not a text file"),
        "huge.yaml": ("#" * (2 << 20), "allowed at most 1048576 bytes"),
    }
    for name, (content, field) in cases.items():
        path = tmp_path / name
        (path.write_bytes if isinstance(content, bytes) else path.write_text)(content)
        _refused(path, tmp_path / "never.zarr", field)
        assert not (tmp_path / "never.zarr").exists()


@pytest.mark.slow
def test_ten_million_frames_say_what_they_cost_before_the_work_and_the_store_is_made_at_once(
    tmp_path,
):
    """The store of 1e7 frames is metadata only (it took over a minute, silently, when every chunk
    was planned); the plan line gives frame 0's time, the CPU the rest takes and the bytes, before
    the work."""
    import yaml

    spec = {**yaml.safe_load(SPEC), "frames": 10_000_000}
    path = tmp_path / "big.yaml"
    path.write_text(yaml.safe_dump(spec))
    out = tmp_path / "big.zarr"
    lines = []
    summary = make_dataset(load_spec(path), out, workers=1, max_frames=2, say=lines.append)
    assert summary["done"] == 2 and not summary["interrupted"]
    plan = lines[0]
    assert (
        plan.startswith("dataset: 10000000 frames of 16 x 8 pixels; frame 0 took ")
        and "days of CPU" in plan
    )
    assert "GB stored" in plan and "this run stops at 2 frames (--max-frames)" in plan
    store = dataset_store.open_dataset(
        out, only_done=False
    )  # opens at once (no dask task per frame)
    assert store.sizes["frame"] == 10_000_000
    assert dataset_store.open_dataset(out).sizes["frame"] == 2
    assert np.flatnonzero(dataset_store.done_frames(out)).tolist() == [0, 1]
