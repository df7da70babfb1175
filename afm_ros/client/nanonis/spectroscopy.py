"""ZSpectr.*: Z spectroscopy at the tip's position, as the instrument's own
(:meth:`afm_ros.client.Microscope.spectroscopy`): settle under feedback, hold, ramp z towards the
sample and back.

The Nanonis settings map onto the ramp: the sweep starts ``Z offset`` [m] above the held z and runs
``Z sweep distance`` [m] towards the sample (the z controller's spectroscopy_retract and
spectroscopy_distance), at the rate that gives each of the ``points`` its settling plus integration
time (spectroscopy_rate = distance / (points x (settling + integration))); the initial settling is
spectroscopy_settle_time. The data are the ramp's lock-in outputs averaged in ``points`` equal z
bins per direction (forward: towards the sample; backward: back), as the controller averages each
point over its integration time; a point shorter than the lock-in's output interval has no output
of its own and takes the linear interpolation of its neighbours'.
"""

from __future__ import annotations

import math
from datetime import datetime

import numpy as np

from afm_ros.client.nanonis.commands import Unsupported, command, finite, flag
from afm_ros.client.nanonis.signals import SIGNALS
from afm_ros.formats.nanonis_files import write_dat

# signal index -> the curve's variable, per mode (in FM the ramp records the frequency shift in
# the curve's amplitude column and the PLL's phase + 90 deg in its phase column)
CURVE_CHANNELS = {
    "am": {4: "amplitude", 5: "phase", 8: "chunk_deflection"},
    "fm": {6: "amplitude", 8: "chunk_deflection"},
}
FIXED = ("Z offset (m)", "Z sweep distance (m)")
PARAMETERS = ("Initial settling (s)", "Settling time (s)", "Integration time (s)")


def ramp_values(z: dict) -> dict:
    """The z controller's spectroscopy parameters from the ZSpectr settings (ValueError naming
    the setting that makes the rate impossible)."""
    per_point = z["settling"] + z["integration"]
    if per_point <= 0:
        raise ValueError(
            "settling + integration time = 0 s per point: the sweep would take no time "
            "(ZSpectr.TimingSet)"
        )
    return {
        "spectroscopy_retract": z["offset"],
        "spectroscopy_distance": z["distance"],
        "spectroscopy_rate": z["distance"] / (z["points"] * per_point),
        "spectroscopy_settle_time": z["initial_settling"],
    }


def bin_curve(curve, settings: dict, mode: str) -> tuple[list[str], np.ndarray]:
    """(names, data rows) of a curve Dataset: "Z (m)" and each recorded channel, forward then (if
    asked) backward, averaged over ``points`` equal z bins from the sweep's start to its end."""
    points = settings["points"]
    z_start = float(curve.attrs["z_held"]) + float(curve.attrs["retract"])
    legs = [("approach", "")] + ([("retract", " [bwd]")] if settings["backward"] else [])
    z_out = np.asarray(curve["z_piezo"].values, dtype=np.float64)
    branch = np.asarray(curve["branch"].values)
    z_end = z_start - settings["distance"]
    grid = z_start + (np.arange(points) + 0.5) / points * (z_end - z_start)
    edges = z_start + np.arange(points + 1) / points * (z_end - z_start)
    names, rows = ["Z (m)"], [grid]
    channels = CURVE_CHANNELS[mode]
    for suffix_leg, suffix in legs:
        for index in settings["channels"]:
            var = channels[index]
            chunked = var.startswith("chunk_")
            # a chunk's z: the piezo the cantilever applied to it (its gap minus base and motor)
            z = curve["chunk_z_gap"].values - float(curve.attrs["z_offset"]) if chunked else z_out
            legs_of = curve["chunk_branch"].values if chunked else branch
            values = np.asarray(curve[var].values, dtype=np.float64)
            keep = legs_of == suffix_leg
            rows.append(_bin(z[keep], values[keep], edges, grid))
            name, unit = SIGNALS[index].name.rsplit(" (", 1)
            names.append(f"{name}{suffix} ({unit}")
    return names, np.vstack(rows)


def _bin(z: np.ndarray, values: np.ndarray, edges: np.ndarray, centres: np.ndarray) -> np.ndarray:
    """Mean of ``values`` in each z bin between consecutive ``edges`` (descending); a bin that got
    no output (points shorter than the lock-in's output interval) takes the linear interpolation
    of the outputs at its centre (beyond the first or last output: that output's value)."""
    lo, hi = np.minimum(edges[:-1], edges[1:]), np.maximum(edges[:-1], edges[1:])
    out = np.full(lo.size, np.nan)
    for i in range(lo.size):
        inside = (z >= lo[i]) & (z < hi[i]) if i < lo.size - 1 else (z >= lo[i]) & (z <= hi[i])
        if inside.any():
            out[i] = float(np.mean(values[inside]))
    empty = np.isnan(out)
    finite = np.isfinite(values)
    if empty.any() and finite.sum() >= 2:
        order = np.argsort(z[finite])
        zs, vs = z[finite][order], values[finite][order]
        out[empty] = np.interp(centres[empty], zs, vs)
    return out


def _params(z: dict) -> list[float]:
    return [z["offset"], z["distance"], z["initial_settling"], z["settling"], z["integration"]]


@command("ZSpectr.Open")
def spectr_open(s):
    """Nothing to open (accepted for scripts that call it)."""
    pass


@command(
    "ZSpectr.Start",
    args=[("get_data", "I"), ("base_name", "str")],
    returns=[("channels", "strarr"), ("data", "f2d"), ("parameters", "f[]")],
)
def spectr_start(s, get_data: int, base_name: str):
    """Run one Z spectroscopy at the tip's position and answer when it is done: the channels'
    names, their data (rows: Z then each channel forward, then backward) and the settings; saved
    as .dat if autosave is on (base_name: the file's base name, '' no change)."""
    flag("get_data", get_data)
    z = s.zspectr
    if base_name:
        if any(c in base_name for c in '/\\:*?"<>|\0'):
            raise ValueError(f"base_name={base_name!r}: a file name, no path characters")
        z["base_name"] = base_name
    values = ramp_values(z)
    job = s.controller.submit("spectroscopy", lambda afm: afm.spectroscopy(**values))
    job.done.wait()
    s.job_error(job)
    if job.stopped or job.result is None:
        return ([], np.zeros((0, 0)), _params(z))
    names, data = bin_curve(job.result, z, s.mode)
    if z["autosave"]:
        path = s.next_path(z["base_name"], ".dat")
        header = _dat_header(job.result, z, values)
        write_dat(path, header, dict(zip(names, data)))
        s.files.append(str(path))
        s.log("info", f"spectroscopy saved: {path}")
    if not get_data:
        return ([], np.zeros((0, 0)), _params(z))
    return (names, data, _params(z))


def _dat_header(curve, z: dict, values: dict) -> dict:
    a = curve.attrs
    return {
        "Experiment": "Z spectroscopy",
        "Date": datetime.now().strftime("%d.%m.%Y %H:%M:%S"),
        "User": "",
        "X (m)": float(a.get("x", math.nan)),
        "Y (m)": float(a.get("y", math.nan)),
        "Z (m)": float(a.get("z_held", math.nan)),
        "Z offset (m)": z["offset"],
        "Settling time (s)": z["settling"],
        "Integration time (s)": z["integration"],
        "Z-Ctrl hold": True,
        "Final Z (m)": math.nan,
        "Z Spectroscopy>Sweep Start (m)": z["offset"],
        "Z Spectroscopy>Sweep End (m)": z["offset"] - z["distance"],
        "Z Spectroscopy>Num Pixel": z["points"],
        "Z Spectroscopy>Ramp rate (m/s)": values["spectroscopy_rate"],
        "Z Spectroscopy>Start time (s)": float(a.get("t_start", math.nan)),
        "Comment01": "afm_ros: lock-in outputs averaged per z bin",
    }


@command("ZSpectr.Stop")
def spectr_stop(s):
    """Stops the spectroscopy running (the feedback resumes; no data)."""
    s.controller.stop("spectroscopy")


@command("ZSpectr.StatusGet", returns=[("running", "I")])
def spectr_status(s):
    """1 while a Z spectroscopy runs."""
    return (1 if s.controller.running("spectroscopy") else 0,)


@command(
    "ZSpectr.PropsSet",
    args=[
        ("backward", "H"),
        ("points", "i"),
        ("sweeps", "H"),
        ("autosave", "H"),
        ("show_save_dialog", "H"),
        ("save_all", "H"),
    ],
)
def spectr_props_set(s, backward, points, sweeps, autosave, show_save_dialog, save_all):
    """Backward sweep (0 no change, 1 on, 2 off), points per sweep (0 no change), sweeps (1),
    autosave (0 no change, 1 on, 2 off)."""
    for name, v in (("backward", backward), ("autosave", autosave), ("save_all", save_all)):
        flag(name, v, (0, 1, 2))
    flag("show_save_dialog", show_save_dialog, (0, 1, 2))
    if points and not 2 <= points <= 100_000:
        raise ValueError(f"points={points}: allowed [2, 100000] (0: no change)")
    if sweeps not in (0, 1):
        raise Unsupported(f"sweeps={sweeps}: one sweep per start here (run Start again)")
    z = s.zspectr
    if backward:
        z["backward"] = backward == 1
    if points:
        z["points"] = points
    if autosave:
        z["autosave"] = autosave == 1
    if save_all:
        z["save_all"] = save_all == 1


@command(
    "ZSpectr.PropsGet",
    returns=[
        ("backward", "H"),
        ("points", "i"),
        ("parameters", "strarr"),
        ("fixed_parameters", "strarr"),
        ("sweeps", "H"),
        ("save_all", "H"),
    ],
)
def spectr_props_get(s):
    """As nanonis_spm reads it (the document adds autosave and the save dialog after the sweeps;
    where the two disagree the server follows nanonis_spm)."""
    z = s.zspectr
    return (int(z["backward"]), z["points"], list(PARAMETERS), list(FIXED), 1, int(z["save_all"]))


@command("ZSpectr.ChsSet", args=[("channels", "i[]")])
def spectr_channels_set(s, channels):
    """The channels recorded: 4 Amplitude and 5 Phase (AM) or 6 Frequency Shift (FM), 8 Deflection
    (per chunk)."""
    chosen = [int(c) for c in channels]
    allowed = CURVE_CHANNELS[s.mode]
    bad = [c for c in chosen if c not in allowed]
    if bad or not chosen or len(set(chosen)) != len(chosen):
        names = ", ".join(f"{i} {SIGNALS[i].name}" for i in allowed)
        raise ValueError(f"channels {chosen}: each once, from {names}")
    s.zspectr["channels"] = chosen


@command("ZSpectr.ChsGet", returns=[("channels", "i[]"), ("names", "strarr")])
def spectr_channels_get(s):
    chosen = s.zspectr["channels"]
    return (list(chosen), [SIGNALS[i].name for i in chosen])


@command("ZSpectr.RangeSet", args=[("z_offset", "f"), ("z_sweep_distance", "f")])
def spectr_range_set(s, z_offset: float, z_sweep_distance: float):
    """The sweep starts z_offset [m] above the held z and runs z_sweep_distance [m] towards the
    sample."""
    offset = finite("z_offset", z_offset, "m")
    distance = finite("z_sweep_distance", z_sweep_distance, "m")
    if not 0 <= offset <= 10e-6:
        raise ValueError(f"z_offset={offset:g} m: allowed [0, 1e-05] m")
    if not 0 < distance <= 10e-6:
        raise ValueError(f"z_sweep_distance={distance:g} m: allowed (0, 1e-05] m")
    s.zspectr.update(offset=offset, distance=distance)


@command("ZSpectr.RangeGet", returns=[("z_offset", "f"), ("z_sweep_distance", "f")])
def spectr_range_get(s):
    return (s.zspectr["offset"], s.zspectr["distance"])


_TIMING = (
    ("z_avg_time", "f"),
    ("initial_settling", "f"),
    ("max_slew_rate", "f"),
    ("settling", "f"),
    ("integration", "f"),
    ("end_settling", "f"),
    ("z_control_time", "f"),
)


@command("ZSpectr.TimingSet", args=_TIMING)
def spectr_timing_set(s, **times):
    """The times [s] (and the z slew rate): initial settling is the feedback's settling before the
    hold; settling + integration per point set the ramp's rate."""
    for name, v in times.items():
        if not (math.isfinite(v) and 0 <= v <= 100):
            raise ValueError(f"{name}={v:g}: allowed [0, 100]")
    s.zspectr.update(times)


@command("ZSpectr.TimingGet", returns=_TIMING)
def spectr_timing_get(s):
    return tuple(s.zspectr[name] for name, _ in _TIMING)


# --- bias spectroscopy: no tunnelling junction here; its settings are kept (tools such as
# afspm set them at start-up), its status reads not running, starting it is refused
@command(
    "BiasSpectr.PropsSet",
    args=[
        ("save_all", "H"),
        ("sweeps", "i"),
        ("backward", "H"),
        ("points", "i"),
        ("z_offset", "f"),
        ("autosave", "H"),
        ("show_save_dialog", "H"),
    ],
)
def bias_props_set(s, **values):
    """Kept, without effect: afm_ros has no bias spectroscopy (BiasSpectr.Start says so); accepted
    so that tools which configure every module at start-up (afspm) start."""
    s.bias_spectroscopy = dict(values)


@command("BiasSpectr.StatusGet", returns=[("running", "I")])
def bias_status(s):
    """0: a bias spectroscopy never runs here."""
    return (0,)
