"""PLL.* and PLLFreqSwp.*: the oscillation controller. In FM it is the pll node (phase-locked
loop and amplitude controller); in AM, as a Nanonis AFM runs tapping on the same controller, it is
the fixed excitation: the drive's frequency and force, no loops (docs/nanonis.md)."""

from __future__ import annotations

import numpy as np

from afm_ros.client.nanonis.commands import Unsupported, command, finite, flag

MODULATOR = 1  # one oscillation controller


def _mod(modulator: int) -> None:
    if modulator != MODULATOR:
        raise ValueError(f"modulator={modulator}: this instrument has one, modulator 1")


def _fm_only(s, what: str) -> None:
    if s.mode != "fm":
        raise Unsupported(
            f"{what} is a loop of the FM instrument; in AM the excitation is fixed (the drive's "
            "frequency and force: PLL.CenterFreqSet, PLL.ExcitationSet; afm_instrument --fm "
            "--nanonis runs FM)"
        )


@command("PLL.CenterFreqSet", args=[("modulator", "i"), ("frequency", "d")])
def center_set(s, modulator: int, frequency: float):
    """FM: the PLL's centre frequency [Hz] (df = f - centre); AM: the drive frequency [Hz]."""
    _mod(modulator)
    f = finite("frequency", frequency, "Hz")
    if s.mode == "fm":
        s.controller.call(lambda afm: afm.set("pll", center_frequency=f))
    else:
        s.controller.call(lambda afm: afm.set("cantilever", drive_frequency=f))


@command("PLL.CenterFreqGet", args=[("modulator", "i")], returns=[("frequency", "d")])
def center_get(s, modulator: int):
    _mod(modulator)
    node, name = (
        ("pll", "center_frequency") if s.mode == "fm" else ("cantilever", "drive_frequency")
    )
    return (s.controller.call(lambda afm: afm.get(node, name))[name],)


@command("PLL.FreqShiftGet", args=[("modulator", "i")], returns=[("frequency_shift", "f")])
def shift_get(s, modulator: int):
    """FM: the PLL's frequency shift now [Hz]; AM: 0 (the drive stays at the centre)."""
    _mod(modulator)
    if s.mode != "fm":
        return (0.0,)
    return (s.controller.call(lambda afm: afm.signals())["frequency_shift_Hz"],)


def _drive_to_amplitude(afm, force: float) -> float:
    v = afm.get("cantilever", "spring_constant", "quality_factor")
    return force * v["quality_factor"] / v["spring_constant"]


@command("PLL.ExcitationSet", args=[("modulator", "i"), ("excitation", "f")])
def excitation_set(s, modulator: int, excitation: float):
    """The drive force [N] (this emulator's excitation is a force, not a shaker voltage): AM the
    fixed drive (free amplitude = F Q / k); FM only with the amplitude controller off."""
    _mod(modulator)
    force = finite("excitation", excitation, "N")
    if force < 0:
        raise ValueError(f"excitation={force:g} N: allowed >= 0")
    if s.mode == "fm":

        def apply(afm):
            if afm.get("pll", "amplitude_enabled")["amplitude_enabled"]:
                raise ValueError("the amplitude controller is on: switch it off first")
            afm.set("pll", drive_initial=force)

        s.controller.call(apply)
    else:
        s.controller.call(
            lambda afm: afm.set("cantilever", free_amplitude=_drive_to_amplitude(afm, force))
        )


@command("PLL.ExcitationGet", args=[("modulator", "i")], returns=[("excitation", "f")])
def excitation_get(s, modulator: int):
    """The drive force now [N]."""
    _mod(modulator)
    return (s.controller.call(lambda afm: afm.signals())["drive_N"],)


@command("PLL.OutOnOffSet", args=[("modulator", "i"), ("on", "I")])
def output_set(s, modulator: int, on: int):
    """AM: the drive on (1, at the free amplitude it had) or off (0)."""
    _mod(modulator)
    flag("on", on)
    _am_only(s, "switching the excitation output")

    def apply(afm):
        now = afm.get("cantilever", "free_amplitude")["free_amplitude"]
        if on and now == 0.0:
            afm.set("cantilever", free_amplitude=s.saved_drive or 0.0)
        elif not on and now > 0.0:
            s.saved_drive = now
            afm.set("cantilever", free_amplitude=0.0)

    s.controller.call(apply)


def _am_only(s, what: str) -> None:
    if s.mode == "fm":
        raise Unsupported(f"{what} is not modelled in FM (the amplitude controller drives)")


@command("PLL.OutOnOffGet", args=[("modulator", "i")], returns=[("on", "I")])
def output_get(s, modulator: int):
    _mod(modulator)
    return (1 if s.controller.call(lambda afm: afm.signals())["drive_N"] > 0 else 0,)


@command("PLL.AmpCtrlSetpntSet", args=[("modulator", "i"), ("setpoint", "f")])
def amplitude_setpoint_set(s, modulator: int, setpoint: float):
    """FM: the oscillation amplitude the amplitude controller holds [m]."""
    _mod(modulator)
    _fm_only(s, "the amplitude controller")
    value = finite("setpoint", setpoint, "m")
    s.controller.call(lambda afm: afm.set("pll", amplitude_setpoint=value))


@command("PLL.AmpCtrlSetpntGet", args=[("modulator", "i")], returns=[("setpoint", "f")])
def amplitude_setpoint_get(s, modulator: int):
    _mod(modulator)
    _fm_only(s, "the amplitude controller")
    return (
        s.controller.call(lambda afm: afm.get("pll", "amplitude_setpoint"))["amplitude_setpoint"],
    )


def _loop_on(s, modulator: int, name: str, on: int, what: str) -> None:
    _mod(modulator)
    flag("on", on)
    if s.mode != "fm":
        if on:
            _fm_only(s, what)
        return
    s.controller.call(lambda afm: afm.set("pll", **{name: bool(on)}))


def _loop_get(s, modulator: int, name: str) -> tuple:
    _mod(modulator)
    if s.mode != "fm":
        return (0,)
    return (1 if s.controller.call(lambda afm: afm.get("pll", name))[name] else 0,)


@command("PLL.AmpCtrlOnOffSet", args=[("modulator", "i"), ("on", "I")])
def amplitude_on_set(s, modulator: int, on: int):
    """FM: the amplitude controller on (1) or off (0: the drive holds); AM: off only."""
    _loop_on(s, modulator, "amplitude_enabled", on, "the amplitude controller")


@command("PLL.AmpCtrlOnOffGet", args=[("modulator", "i")], returns=[("on", "I")])
def amplitude_on_get(s, modulator: int):
    return _loop_get(s, modulator, "amplitude_enabled")


@command("PLL.PhasCtrlOnOffSet", args=[("modulator", "i"), ("on", "I")])
def phase_on_set(s, modulator: int, on: int):
    """FM: the phase-locked loop on (1) or off (0: the frequency holds); AM: off only."""
    _loop_on(s, modulator, "pll_enabled", on, "the phase controller")


@command("PLL.PhasCtrlOnOffGet", args=[("modulator", "i")], returns=[("on", "I")])
def phase_on_get(s, modulator: int):
    return _loop_get(s, modulator, "pll_enabled")


def _gains_set(s, modulator, p, tc, names, what) -> None:
    _mod(modulator)
    _fm_only(s, what)
    p, tc = finite("p_gain", p), finite("time_constant", tc, "s")
    if tc <= 0:
        raise ValueError(f"time_constant={tc:g} s: must be > 0 (I = P / time constant)")
    s.controller.call(lambda afm: afm.set("pll", **{names[0]: p, names[1]: p / tc}))


def _gains_get(s, modulator, names, what) -> tuple:
    _mod(modulator)
    _fm_only(s, what)
    v = s.controller.call(lambda afm: afm.get("pll", *names))
    p, i = v[names[0]], v[names[1]]
    return (p, p / i if i > 0 else 0.0, i)


AMPLITUDE_GAINS = ("amplitude_p_gain", "amplitude_i_gain")
PHASE_GAINS = ("pll_p_gain", "pll_i_gain")


@command("PLL.AmpCtrlGainSet", args=[("modulator", "i"), ("p_gain", "f"), ("time_constant", "f")])
def amplitude_gain_set(s, modulator: int, p_gain: float, time_constant: float):
    """FM: P [N/m] and the time constant [s] (I = P / time constant) of the amplitude
    controller."""
    _gains_set(s, modulator, p_gain, time_constant, AMPLITUDE_GAINS, "the amplitude controller")


@command(
    "PLL.AmpCtrlGainGet",
    args=[("modulator", "i")],
    returns=[("p_gain", "f"), ("time_constant", "f"), ("i_gain", "f")],
)
def amplitude_gain_get(s, modulator: int):
    return _gains_get(s, modulator, AMPLITUDE_GAINS, "the amplitude controller")


@command("PLL.PhasCtrlGainSet", args=[("modulator", "i"), ("p_gain", "f"), ("time_constant", "f")])
def phase_gain_set(s, modulator: int, p_gain: float, time_constant: float):
    """FM: P [Hz/deg] and the time constant [s] (I = P / time constant) of the phase loop."""
    _gains_set(s, modulator, p_gain, time_constant, PHASE_GAINS, "the phase controller")


@command(
    "PLL.PhasCtrlGainGet",
    args=[("modulator", "i")],
    returns=[("p_gain", "f"), ("time_constant", "f")],
)
def phase_gain_get(s, modulator: int):
    """P [Hz/deg] and the time constant [s] (I = P / time constant), as nanonis_spm reads it (the
    document adds the I gain; the server follows nanonis_spm)."""
    return _gains_get(s, modulator, PHASE_GAINS, "the phase controller")[:2]


# --- the frequency sweep (the tune)
# ---------------------------------------------------------------------
@command("PLLFreqSwp.Open", args=[("modulator", "i")])
def sweep_open(s, modulator: int):
    """Nothing to open (accepted for scripts that call it)."""
    _mod(modulator)


@command(
    "PLLFreqSwp.ParamsSet",
    args=[("modulator", "i"), ("points", "i"), ("period", "f"), ("settling", "f")],
)
def sweep_params_set(s, modulator: int, points: int, period: float, settling: float):
    """Points of the sweep, the averaging time per point [s] (period) and the settling before it
    [s] (0: the lock-in's defaults, 3 output intervals and 8 decay times)."""
    _mod(modulator)
    dwell, settle = finite("period", period, "s"), finite("settling", settling, "s")
    s.controller.call(
        lambda afm: afm.set("lockin", tune_points=points, tune_dwell=dwell, tune_settle=settle)
    )


@command(
    "PLLFreqSwp.ParamsGet",
    args=[("modulator", "i")],
    returns=[("points", "i"), ("period", "f"), ("settling", "f")],
)
def sweep_params_get(s, modulator: int):
    _mod(modulator)
    v = s.controller.call(
        lambda afm: afm.get("lockin", "tune_points", "tune_dwell", "tune_settle")
    )
    return (v["tune_points"], v["tune_dwell"], v["tune_settle"])


@command(
    "PLLFreqSwp.Start",
    args=[("modulator", "i"), ("get_data", "I"), ("sweep_up", "I")],
    returns=[
        ("channels", "strarr"),
        ("data", "f2d"),
        ("resonance_frequency", "d"),
        ("q_factor", "d"),
        ("phase", "f"),
        ("amplitude_to_excitation", "f"),
        ("fit_length", "i"),
        ("points", "i"),
    ],
)
def sweep_start(s, modulator: int, get_data: int, sweep_up: int):
    """The tune: sweep the drive around the resonance with the tip free, fit f0 and Q, and set
    the working point (drive at the peak, the free amplitude, phase zero); answers when done with
    the sweep (frequency [Hz], amplitude [m], phase [deg]), f0 [Hz], Q, the phase at f0 [deg] and
    the peak amplitude per drive force [m/N]."""
    _mod(modulator)
    flag("get_data", get_data)
    flag("sweep_up", sweep_up)
    if s.mode == "fm":
        raise Unsupported(
            "the sweep drives the cantilever at fixed frequencies, but in FM the PLL self-excites "
            "it: lock with PLL.PhasCtrlOnOffSet and read PLL.CenterFreqGet + PLL.FreqShiftGet"
        )
    if not sweep_up:
        raise Unsupported("the sweep runs upwards in frequency here (sweep_up 1)")
    job = s.controller.submit("tune", lambda afm: afm.tune())
    job.done.wait()
    s.job_error(job)
    if job.stopped or job.result is None:
        return ([], np.zeros((0, 0)), 0.0, 0.0, 0.0, 0.0, 0, 0)
    r = job.result
    data = np.array([r["frequency_Hz"], r["amplitude_m"], r["phase_deg"]], dtype=np.float64)
    force = s.controller.call(lambda afm: afm.signals())["drive_N"]
    ratio = r["peak_amplitude_m"] / force if force > 0 else 0.0
    names = ["Frequency (Hz)", "Amplitude (m)", "Phase (deg)"]
    if not get_data:
        names, data = [], np.zeros((0, 0))
    return (names, data, r["f0_Hz"], r["Q"], r["phase0_deg"], ratio, r["points"], r["points"])
