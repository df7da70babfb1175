"""Signals.*, OsciHR.*, Util.*: the live signals, the raw deflection, the session folder and the
version (docs/nanonis.md)."""

from __future__ import annotations

import math

import afm_ros.client.nanonis.signals as table
from afm_ros.client.nanonis.commands import Unsupported, command, flag, supported
from afm_ros.client.nanonis.session import HOST_RELEASE, RT_RELEASE, VERSION

DEFLECTION = 8  # the only signal the high-resolution oscilloscope records (the raw stream)


@command("Signals.NamesGet", returns=[("names", "strarr")])
def names_get(s):
    """The signals' names with their units, index = position (Z at 14)."""
    return (list(table.NAMES),)


@command("Signals.ValGet", args=[("index", "i"), ("wait_newest", "I")], returns=[("value", "f")])
def value_get(s, index: int, wait_newest: int):
    """The signal's value now, in its unit (NaN where this mode has none)."""
    table.signal(index)
    return (table.value(index, s.controller.call(lambda afm: afm.signals())),)


@command(
    "Signals.ValsGet",
    args=[("indexes", "i[]"), ("wait_newest", "I")],
    returns=[("values", "f[]")],
)
def values_get(s, indexes, wait_newest: int):
    """Several signals' values now (NaN where this mode has none)."""
    chosen = [int(i) for i in indexes]
    for i in chosen:
        table.signal(i)
    now = s.controller.call(lambda afm: afm.signals())
    return ([table.value(i, now) for i in chosen],)


@command("Signals.RangeGet", args=[("index", "i")], returns=[("max", "f"), ("min", "f")])
def range_get(s, index: int):
    """The signal's range (max, min) in its unit; Z's is the z controller's [z_min, z_max]."""
    sig = table.signal(index)
    if sig.index == table.Z_INDEX:
        v = s.controller.call(lambda afm: afm.feedback())
        return (v["z_max"], v["z_min"])
    return (sig.high, sig.low)


@command("OsciHR.ChSet", args=[("osci", "i"), ("signal", "i")])
def osci_channel_set(s, osci: int, signal: int):
    """The raw deflection (signal 8) is what this oscilloscope records."""
    flag("osci", osci, (0, 1))
    if signal != DEFLECTION:
        raise Unsupported(
            f"signal {signal}: the high-resolution oscilloscope records the raw deflection "
            f"({DEFLECTION}, {table.SIGNALS[DEFLECTION].name}) only"
        )
    s.osci["channel"] = signal


@command("OsciHR.ChGet", args=[("osci", "i")], returns=[("signal", "i")])
def osci_channel_get(s, osci: int):
    flag("osci", osci, (0, 1))
    return (s.osci["channel"],)


@command("OsciHR.SamplesSet", args=[("samples", "i")])
def osci_samples_set(s, samples: int):
    """Samples OsciDataGet returns, [1, 100000]."""
    if not 1 <= samples <= 100_000:
        raise ValueError(f"samples={samples}: allowed [1, 100000]")
    s.osci["samples"] = samples


@command("OsciHR.SamplesGet", returns=[("samples", "i")])
def osci_samples_get(s):
    return (s.osci["samples"],)


@command("OsciHR.Run")
def osci_run(s):
    """The oscilloscope always runs (accepted for scripts that call it)."""
    pass


@command(
    "OsciHR.OsciDataGet",
    args=[("osci", "i"), ("data_to_get", "H"), ("timeout", "d")],
    returns=[("t0", "str"), ("dt", "d"), ("data", "f[]"), ("timed_out", "I")],
)
def osci_data(s, osci: int, data_to_get: int, timeout: float):
    """The last samples of the measured deflection [m] (the raw 900 kS/s stream, detector noise
    included), the time of the first (simulated seconds, as text) and the sample interval [s];
    data_to_get 1 (next): first let the samples' time pass (fresh data), 0: what is there."""
    flag("osci", osci, (0, 1))
    flag("data_to_get", data_to_get, (0, 1))
    n = s.osci["samples"]
    if data_to_get == 1:
        dt = s.controller.call(lambda afm: afm.oscilloscope(1))["dt_s"]
        span = n * (dt if math.isfinite(dt) else 1.0 / 900e3)
        job = s.controller.submit("oscilloscope", lambda afm: afm.wait(span))
        if not job.done.wait(max(timeout, 0.0) + 60.0):
            return ("", 0.0, [], 1)
        s.job_error(job)
    trace = s.controller.call(lambda afm: afm.oscilloscope(n))
    return (f"{trace['t0_s']:.9f}", trace["dt_s"], trace["deflection_m"], 0)


@command("Util.SessionPathGet", returns=[("path", "str")])
def session_path(s):
    """The session folder, where the .sxm and .dat files go."""
    return (str(s.folder),)


@command(
    "Util.VersionGet",
    returns=[("product", "str"), ("version", "str"), ("host_release", "I"), ("rt_release", "I")],
)
def version(s):
    """The product line names the emulator and how many commands it answers."""
    return (
        "Nanonis SPM Control Software (afm_ros emulator)",
        f"{VERSION}: {len(supported())} commands, {s.mode.upper()} mode (docs/nanonis.md)",
        HOST_RELEASE,
        RT_RELEASE,
    )
