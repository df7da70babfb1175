"""Nanonis files written by afm_ros.formats.nanonis_files, read back with readers this project did
not write: ``nanonispy`` (PyPI) for .sxm and .dat, ``nanonis_xarray`` for .dat, and Gwyddion's own
Nanonis importer (``gwyddion-thumbnailer`` renders the .sxm; skipped without the Debian package).

Every pixel value encodes where it was written (channel, row, column), so each reader's array is
checked against the layout the module documents: per channel the forward then the backward image,
lines in the order scanned (an 'up' scan from the lowest y, a 'down' one from the highest), each
backward line right to left, Nanonis' NaN for pixels never acquired.
"""

import shutil
import subprocess
from datetime import datetime

import numpy as np
import pytest

from afm_ros.formats.nanonis_files import SxmChannel, SxmFrame, write_dat, write_sxm

LINES, PIXELS = 3, 5


@pytest.fixture(scope="module")
def nanonispy():
    """nanonispy 1.1.0 uses numpy's float and int aliases that numpy 1.24 removed: they are put
    back (as the builtins they aliased) while this module runs."""
    import numpy

    with pytest.MonkeyPatch.context() as mp:
        for name, kind in (("float", float), ("int", int)):
            if name not in numpy.__dict__:
                mp.setattr(numpy, name, kind, raising=False)
        import nanonispy.read

        yield nanonispy.read


def _image(channel: int, backward: bool) -> np.ndarray:
    """Row r (0 = lowest y), column c (0 = lowest x): 1000 channel + 10 r + c (+ 0.5 backward)."""
    r, c = np.mgrid[0:LINES, 0:PIXELS]
    return 1000.0 * channel + 10.0 * r + c + (0.5 if backward else 0.0)


def _frame(direction: str, unscanned_rows=()) -> SxmFrame:
    channels = []
    for k, (index, name, unit) in enumerate(((14, "Z", "m"), (5, "Phase", "deg"))):
        fwd, bwd = _image(k, False), _image(k, True)
        for row in unscanned_rows:
            fwd[row] = bwd[row] = np.nan
        channels.append(SxmChannel(index, name, unit, fwd, bwd))
    return SxmFrame(
        pixels=PIXELS,
        lines=LINES,
        size=(2e-6, 1.2e-6),
        center=(5e-6, 4e-6),
        angle=10.0,
        direction=direction,
        line_time=0.25,
        channels=channels,
        acquisition_time=0.75,
        recorded=datetime(2026, 12, 4, 12, 0, 0),
        comment="a test frame",
    )


@pytest.mark.parametrize("direction", ["up", "down"])
def test_nanonispy_reads_every_channel_in_the_order_scanned(tmp_path, nanonispy, direction):
    path = write_sxm(tmp_path / f"frame_{direction}.sxm", _frame(direction))
    scan = nanonispy.Scan(str(path))
    h = scan.header
    assert list(h["scan_pixels"]) == [PIXELS, LINES]
    assert np.allclose(h["scan_range"], [2e-6, 1.2e-6]) and np.allclose(
        h["scan_offset"], [5e-6, 4e-6]
    )
    assert h["scan_dir"] == direction and float(h["scan_angle"]) == -10.0  # clockwise
    assert [row["Name"] for row in _rows(h["data_info"])] == ["Z", "Phase"]
    for k, name in enumerate(("Z", "Phase")):
        fwd, bwd = scan.signals[name]["forward"], scan.signals[name]["backward"]
        order = slice(None) if direction == "up" else slice(None, None, -1)
        assert np.array_equal(fwd, _image(k, False)[order])  # first line scanned first
        assert np.array_equal(bwd, _image(k, True)[order][:, ::-1])  # right to left


def _rows(data_info) -> list[dict]:
    if isinstance(data_info, dict):  # nanonispy: a dict of columns
        keys = list(data_info)
        return [dict(zip(keys, values)) for values in zip(*data_info.values())]
    return data_info


def test_pixels_never_acquired_are_nanonis_nan(tmp_path, nanonispy):
    path = write_sxm(tmp_path / "partial.sxm", _frame("up", unscanned_rows=(2,)))
    raw = path.read_bytes()
    data = raw[raw.index(b"\x1a\x04") + 2 :]
    assert len(data) == 2 * 2 * LINES * PIXELS * 4
    words = np.frombuffer(data, ">u4").reshape(2, 2, LINES, PIXELS)
    assert (words[:, :, 2] == 0x7FFFFFFF).all() and (words[:, :, :2] != 0x7FFFFFFF).all()
    scan = nanonispy.Scan(str(path))
    assert np.isnan(scan.signals["Z"]["forward"][2]).all()


def test_the_header_is_what_gwyddions_importer_requires(tmp_path):
    """Gwyddion (modules/file/nanonis.c): the file starts with :NANONIS_VERSION:, version 2 (an
    older one swaps the pixel counts), SCANIT_TYPE FLOAT MSBFIRST, the data after the first
    \\x1a\\x04 and exactly header + 2 + channels x 2 x pixels x lines x 4 bytes long."""
    path = write_sxm(tmp_path / "f.sxm", _frame("up"))
    raw = path.read_bytes()
    assert raw.startswith(b":NANONIS_VERSION:\n2\n")
    header = raw[: raw.index(b"\x1a")].decode("latin-1")
    assert ":SCANIT_TYPE:\n              FLOAT            MSBFIRST\n" in header
    assert header.endswith("\n\n:SCANIT_END:\n\n\n")
    assert len(raw) == len(header) + 2 + 2 * 2 * PIXELS * LINES * 4


@pytest.mark.skipif(
    shutil.which("gwyddion-thumbnailer") is None,
    reason="gwyddion-thumbnailer not installed (Debian package gwyddion)",
)
def test_gwyddion_opens_the_sxm(tmp_path):
    frame = _frame("up")
    big = []
    r, c = np.mgrid[0:48, 0:64]
    for ch in frame.channels:
        image = np.sin(r / 5.0) + np.cos(c / 7.0) + ch.index
        big.append(SxmChannel(ch.index, ch.name, ch.unit, image, image))
    frame.channels, frame.pixels, frame.lines = big, 64, 48
    path = write_sxm(tmp_path / "big.sxm", frame)
    png = tmp_path / "thumb.png"
    done = subprocess.run(
        [
            "gwyddion-thumbnailer",
            "-c",
            str(tmp_path / "cfg"),
            "gnome2",
            "128",
            str(path),
            str(png),
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr
    assert png.stat().st_size > 1000 and png.read_bytes().startswith(b"\x89PNG")


def test_a_dat_file_reads_back_in_nanonispy_and_nanonis_xarray(tmp_path, nanonispy):
    z = np.linspace(10e-9, -20e-9, 7)
    columns = {"Z (m)": z, "Amplitude (m)": 40e-9 + z, "Phase (deg)": np.arange(7.0)}
    header = {
        "Experiment": "Z spectroscopy",
        "X (m)": 5e-6,
        "Z-Ctrl hold": True,
        "Final Z (m)": np.nan,
    }
    path = write_dat(tmp_path / "Z-Spectroscopy001.dat", header, columns)
    spec = nanonispy.Spec(str(path))
    assert spec.header["Experiment"] == "Z spectroscopy"
    assert float(spec.header["X (m)"]) == 5e-6 and spec.header["Z-Ctrl hold"] == "TRUE"
    for name, values in columns.items():
        assert np.allclose(spec.signals[name], values, rtol=1e-9, atol=0), name
    nx = pytest.importorskip("nanonis_xarray")
    ds = nx.read_dat(path, quantify_vars=False)
    by_name = {v.attrs.get("long_name"): v for v in ds.data_vars.values()}
    assert set(by_name) == {"Amplitude", "Phase"}  # the first column is the sweep axis
    assert by_name["Amplitude"].attrs["units"] == "m"
    amplitude = by_name["Amplitude"]  # indexed by the sweep axis, which it sorts
    z_axis = amplitude[amplitude.dims[0]].values
    assert np.allclose(np.sort(z_axis), np.sort(z), rtol=1e-9)
    assert np.allclose(amplitude.values.ravel(), 40e-9 + z_axis, rtol=1e-9)


def test_a_wrong_file_name_or_shape_is_refused(tmp_path):
    with pytest.raises(ValueError, match=r"\.sxm"):
        write_sxm(tmp_path / "x.gwy", _frame("up"))
    frame = _frame("up")
    frame.lines = 4
    with pytest.raises(ValueError, match="shape"):
        write_sxm(tmp_path / "x.sxm", frame)
    with pytest.raises(ValueError, match="one length"):
        write_dat(tmp_path / "x.dat", {}, {"a (m)": [1, 2], "b (m)": [1]})
