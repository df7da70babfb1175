"""afm_ros.formats.gwy: files written by write_gwy, read by readers this project did not write
(the gwyfile package directly, Gwyddion's own thumbnailer and converter), and bad-file errors."""

import os
import shutil
import subprocess

import gwyfile
import numpy as np
import pytest

from afm_ros.formats.gwy import read_gwy, write_gwy

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def random_channels(rows=48, cols=64, seed=1):
    rng = np.random.default_rng(seed)
    return {
        "Height": (rng.normal(scale=5e-9, size=(rows, cols)), "m"),
        "Phase": (rng.uniform(0, 180, size=(rows, cols)), "deg"),
        "Amplitude": (rng.normal(scale=1e-3, size=(rows, cols)), "V"),
        "E": (rng.normal(scale=1e-18, size=(rows, cols)), "J"),
    }


GEOMETRY = dict(xreal=6.4e-6, yreal=4.8e-6, xoff=1.5e-6, yoff=-2.25e-6)
METADATA = {
    "Sample": "PS/LDPE blend",
    "Tip radius [m]": 2e-08,
    "Lines": 48,
    "Date": "2026-12-01 17:41:05",
}


@pytest.fixture
def written(tmp_path):
    path = tmp_path / "scan.gwy"
    channels = random_channels()
    write_gwy(path, channels, metadata=METADATA, **GEOMETRY)
    return path, channels


def expected_meta_text(value):
    return (
        value
        if isinstance(value, str)
        else repr(value)
        if isinstance(value, float)
        else str(value)
    )


def check_container(obj, channels):
    """The Gwyddion container layout of docs/gwyddion.md, from gwyfile's own parse."""
    titles = dict(gwyfile.util.find_datafields(obj))
    assert [titles[n] for n in sorted(titles)] == list(channels)
    for n, (title, (values, unit)) in enumerate(channels.items()):
        field = obj[f"/{n}/data"]
        assert (field["xres"], field["yres"]) == (values.shape[1], values.shape[0])
        for key, value in GEOMETRY.items():
            assert field[key] == value, key
        assert field["si_unit_xy"]["unitstr"] == "m"
        assert field["si_unit_z"]["unitstr"] == unit
        assert field.data.dtype == np.float64
        np.testing.assert_array_equal(field.data, values)  # exact float64 round trip, row 0 first
        meta = obj[f"/{n}/meta"]
        assert dict(meta) == {k: expected_meta_text(v) for k, v in METADATA.items()}


def test_gwyfile_reads_what_write_gwy_wrote(written):
    path, channels = written
    check_container(gwyfile.load(str(path)), channels)


def test_read_gwy_round_trip(written):
    path, channels = written
    image = read_gwy(path)
    assert list(image.channels) == list(channels)
    for title, (values, unit) in channels.items():
        got, got_unit = image.channels[title]
        assert got_unit == unit
        np.testing.assert_array_equal(got, values)
        got[0, 0] = 1.0  # a writable array of its own
    assert (image.xreal, image.yreal, image.xoff, image.yoff) == tuple(GEOMETRY.values())
    assert image.xy_unit == "m"
    assert image.metadata == {k: expected_meta_text(v) for k, v in METADATA.items()}
    # a float stored in the metadata reads back to the same number
    assert float(image.metadata["Tip radius [m]"]) == METADATA["Tip radius [m]"]


def test_the_write_is_atomic_and_leaves_no_temporary_file(tmp_path):
    path = tmp_path / "scan.gwy"
    write_gwy(path, random_channels(seed=2), 1e-6, 1e-6)
    before = path.read_bytes()
    with pytest.raises(ValueError, match="Phase"):  # a bad channel: the old file stays untouched
        write_gwy(
            path,
            {"Height": (np.zeros((4, 4)), "m"), "Phase": (np.full((4, 4), np.nan), "deg")},
            1e-6,
            1e-6,
        )
    assert path.read_bytes() == before
    write_gwy(path, random_channels(seed=3), 1e-6, 1e-6)
    assert sorted(os.listdir(tmp_path)) == ["scan.gwy"]
    assert path.read_bytes() != before


@pytest.mark.skipif(
    shutil.which("gwyddion-thumbnailer") is None,
    reason="gwyddion-thumbnailer not installed (Debian package gwyddion)",
)
def test_gwyddion_thumbnailer_renders_every_channel(written, tmp_path):
    path, channels = written
    bad = tmp_path / "bad.gwy"
    bad.write_bytes(b"GWYP not really")
    for n in range(len(channels)):
        png = tmp_path / f"thumb{n}.png"
        run = subprocess.run(
            ["gwyddion-thumbnailer", "-c", str(n), "gnome2", "128", str(path), str(png)],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert run.returncode == 0, run.stderr
        data = png.read_bytes()
        assert data.startswith(PNG_SIGNATURE) and len(data) > 100
        width, height = int.from_bytes(data[16:20], "big"), int.from_bytes(data[20:24], "big")
        assert (width, height) == (64, 48)  # the channel's aspect, within the 128 px box
    # the same call on a broken file fails: the exit status above means something
    run = subprocess.run(
        ["gwyddion-thumbnailer", "gnome2", "128", str(bad), str(tmp_path / "bad.png")],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode != 0


@pytest.mark.skipif(
    shutil.which("gwyddion") is None, reason="gwyddion not installed (Debian package gwyddion)"
)
def test_gwyddion_itself_reads_titles_units_and_metadata(written, tmp_path):
    """Gwyddion loads the file with its own deserialiser and writes it again (--convert-to-gwy);
    titles, units, geometry, values and the metadata survive."""
    path, channels = written
    out = tmp_path / "converted.gwy"
    run = subprocess.run(
        ["gwyddion", "--no-splash", "--convert-to-gwy=" + str(out), str(path)],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "DISPLAY": ""},
    )
    assert run.returncode == 0, run.stderr
    check_container(gwyfile.load(str(out)), channels)


# --- errors ----------------------------------------------------------------------------------
def test_missing_file_is_an_oserror_naming_it(tmp_path):
    path = tmp_path / "nowhere.gwy"
    with pytest.raises(OSError, match="nowhere.gwy"):
        read_gwy(path)


def test_a_directory_is_an_oserror_naming_it(tmp_path):
    with pytest.raises(OSError, match=str(tmp_path)):
        read_gwy(tmp_path)


@pytest.mark.parametrize(
    "content, why",
    [
        (b"", "GWYP"),
        (b"\x89PNG\r\n\x1a\nnot a gwy file", "GWYP"),
        (b"GWYO\0\0\0\0", "1.x"),
        (b"GWYP", "truncated"),
        (b"GWYPGwyContainer\0\xff\0\0\0abc", "truncated"),
    ],
)
def test_not_a_gwy_file_is_a_valueerror_naming_it(tmp_path, content, why):
    path = tmp_path / "bad.gwy"
    path.write_bytes(content)
    with pytest.raises(ValueError, match=why) as err:
        read_gwy(path)
    assert str(path) in str(err.value)


def test_truncated_file_is_a_valueerror_naming_it(written):
    path, _ = written
    path.write_bytes(path.read_bytes()[:-100])
    with pytest.raises(ValueError, match="truncated") as err:
        read_gwy(path)
    assert str(path) in str(err.value)


def test_a_container_without_channels_is_a_valueerror(tmp_path):
    path = tmp_path / "empty.gwy"
    gwyfile.objects.GwyContainer({"/filename": "x"}).tofile(str(path))
    with pytest.raises(ValueError, match="no data channel") as err:
        read_gwy(path)
    assert str(path) in str(err.value)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        (dict(xreal=0.0), "xreal"),
        (dict(yreal=-1e-6), "yreal"),
        (dict(xoff=float("inf")), "xoff"),
        (dict(metadata={"": 1}), "metadata key"),
        (dict(metadata={"a": [1]}), "metadata"),
        (dict(channels={}), "channels"),
        (dict(channels={"H": np.zeros((2, 2))}), "'H'"),
        (dict(channels={"H": (np.zeros(4), "m")}), "2D"),
        (dict(channels={"H": (np.zeros((2, 2)), 1)}), "unit"),
        (dict(channels={"H": (np.zeros((2, 2)), "m"), "P": (np.zeros((3, 2)), "deg")}), "'P'"),
    ],
)
def test_write_rejects_bad_arguments_by_name(tmp_path, kwargs, field):
    args = dict(channels={"H": (np.zeros((2, 2)), "m")}, xreal=1e-6, yreal=1e-6)
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        write_gwy(tmp_path / "x.gwy", **args)
    assert not os.listdir(tmp_path)


def test_write_into_a_missing_directory_is_an_oserror_naming_the_file(tmp_path):
    path = tmp_path / "no" / "such" / "dir" / "x.gwy"
    with pytest.raises(OSError, match="x.gwy"):
        write_gwy(path, {"H": (np.zeros((2, 2)), "m")}, 1e-6, 1e-6)


# --- the display range of a frame (afm_ros.formats.frames.write_frame) ---------------------------
def island_frame(pixels=64, film=40e-9, island=1e-9, spike=30e-9):
    """A frame whose height is a film with a 1 nm high central island (radius pixels/4) and, as a
    scan over a soft island gives them, a few parachuting spikes of +-30 nm on the island's edge
    (0.6 % of the pixels); the other channels are copies scaled to their units. Returns (frame,
    island mask)."""
    from afm_ros.core.imaging import CHANNELS, DIRECTIONS, Frame
    from afm_ros.core.scanner import ScanPlan

    plan = ScanPlan(
        size_x=5e-6,
        size_y=5e-6,
        center_x=5e-6,
        center_y=5e-6,
        pixels=pixels,
        lines=pixels,
        line_rate=1.0,
    )
    rows, cols = np.indices((pixels, pixels)) - (pixels - 1) / 2
    r = np.hypot(rows, cols)
    inside = r < pixels / 4
    height = np.where(inside, film + island, film)
    edge = np.flatnonzero(np.abs(r - pixels / 4).ravel() < 0.5)
    spikes = edge[:: max(1, edge.size // 24)][:24]
    height.ravel()[spikes[::2]] += spike
    height.ravel()[spikes[1::2]] -= spike
    scale = {
        "height": 1.0,
        "amplitude": 1.0,
        "phase": 1e9,
        "amplitude_error": 0.1,
        "dissipation": 1e-8,
    }
    frame = Frame(
        plan,
        0,
        {d: {c: (height * scale[c]).astype(np.float32) for c in CHANNELS} for d in DIRECTIONS},
        lines_done=pixels,
    )
    return frame, inside


@pytest.mark.skipif(
    shutil.which("gwyddion-thumbnailer") is None,
    reason="gwyddion-thumbnailer not installed (Debian package gwyddion)",
)
def test_frame_thumbnail_shows_the_island_despite_edge_spikes(tmp_path):
    """Gwyddion's thumbnail of a written frame: the 1 nm island against the film must be a clear
    grey step although +-30 nm edge spikes span 60 times that (with the full data range as the
    colour range the island is 1/60 of the grey scale, ~4 of 255 levels); the file's data stay
    raw."""
    from PIL import Image

    from afm_ros.formats.frames import write_frame

    frame, inside = island_frame()
    gwy = write_frame(frame, tmp_path / "frame", previews=False)[0]
    obj = gwyfile.load(str(gwy))
    np.testing.assert_array_equal(
        obj["/0/data"].data, frame.images["trace"]["height"].astype(np.float64)
    )
    png = tmp_path / "thumb.png"
    run = subprocess.run(
        ["gwyddion-thumbnailer", "-c", "0", "gnome2", "128", str(gwy), str(png)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert run.returncode == 0, run.stderr
    grey = np.asarray(Image.open(png).convert("L"), dtype=float)
    assert grey.shape == inside.shape
    # medians (the spikes are 0.6 % of the pixels): at least half the grey scale between island and
    # film
    assert abs(np.median(grey[inside]) - np.median(grey[~inside])) > 128
    # Gwyddion's fixed colour range: the film and the island level, the spikes clipped
    assert obj["/0/base/range-type"] == 1
    assert obj["/0/base/min"] == pytest.approx(40e-9, abs=1e-15)
    assert obj["/0/base/max"] == pytest.approx(41e-9, abs=1e-15)


def test_pixels_without_a_value_are_masked_as_gwyddion_marks_bad_data(tmp_path):
    """invalid="mask": a NaN pixel holds the mean of the others and is 1 in ``/n/mask`` (read by
    gwyfile directly and by read_gwy); the default refuses it naming the channel; Gwyddion's
    thumbnailer opens the masked file."""
    data = np.arange(12.0).reshape(3, 4)
    data[1, 2] = np.nan
    channels = {"E": (data, "Pa"), "Height": (np.ones((3, 4)), "m")}
    with pytest.raises(ValueError, match="'E' has non-finite values"):
        write_gwy(tmp_path / "refused.gwy", channels, 4e-6, 3e-6)
    assert not (tmp_path / "refused.gwy").exists()
    path = tmp_path / "masked.gwy"
    write_gwy(path, channels, 4e-6, 3e-6, invalid="mask")
    obj = gwyfile.load(str(path))
    stored = np.asarray(obj["/0/data"]["data"]).reshape(3, 4)
    mask = np.asarray(obj["/0/mask"]["data"]).reshape(3, 4)
    good = np.isfinite(data)
    assert stored[1, 2] == pytest.approx(data[good].mean())
    assert np.array_equal(stored[good], data[good])
    assert np.array_equal(mask, (~good).astype(float))
    assert "/1/mask" not in obj  # a channel with every value has no mask
    image = read_gwy(path)
    assert np.array_equal(image.masks["E"], ~good) and "Height" not in image.masks
    if shutil.which("gwyddion-thumbnailer"):
        png = tmp_path / "masked.png"
        subprocess.run(
            ["gwyddion-thumbnailer", "gnome2", "128", str(path), str(png)], check=True, timeout=60
        )
        assert png.read_bytes().startswith(PNG_SIGNATURE)
