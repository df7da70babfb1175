"""ZCtrl.*, AutoApproach.*, Motor.*, FolMe.*, Piezo.*: the z controller, the coarse approach and
motor, the tip's position, the piezo's ranges, tilt and drift compensation (docs/nanonis.md)."""

from __future__ import annotations

import math

from afm_ros.client.nanonis.commands import Unsupported, command, finite, flag, timeout_s

CONTROLLERS = ("Amplitude (m)", "Frequency Shift (Hz)")  # AM, FM


def _fm(s) -> bool:
    return s.mode == "fm"


def _wait(s, job, timeout_ms: int) -> None:
    """Wait for ``job`` (timeout [ms], -1 none); raise what ended it badly."""
    if not job.done.wait(timeout_s(timeout_ms)):
        raise TimeoutError(f"{job.kind} still running after {timeout_ms} ms (it goes on)")
    s.job_error(job)


# --- the z controller
# -----------------------------------------------------------------------------------
@command("ZCtrl.OnOffSet", args=[("on", "I")])
def on_off_set(s, on: int):
    """Feedback on (1; the tip must be engaged: AutoApproach first) or off (0: z holds)."""
    flag("on", on)

    def apply(afm):
        stage = afm.state()["stage"]
        if on and stage != "engaged":
            raise ValueError(
                f"the z stage is {stage}: the feedback switches on once the tip is engaged "
                "(AutoApproach.OnOffSet 1)"
            )
        afm.set("z_controller", enabled=bool(on), disabled_action="hold")

    s.controller.call(apply)


@command("ZCtrl.OnOffGet", returns=[("on", "I")])
def on_off_get(s):
    """1 while the z loop regulates (engaged, feedback on)."""
    return (1 if s.controller.call(lambda afm: afm.signals()["feedback"]) else 0,)


@command("ZCtrl.SetpntSet", args=[("setpoint", "f")])
def setpoint_set(s, setpoint: float):
    """AM: the amplitude setpoint [m]; FM: the frequency shift setpoint [Hz] (negative)."""
    name = "df_setpoint" if _fm(s) else "setpoint"
    value = finite("setpoint", setpoint)
    s.controller.call(lambda afm: afm.set("z_controller", **{name: value}))


@command("ZCtrl.SetpntGet", returns=[("setpoint", "f")])
def setpoint_get(s):
    name = "df_setpoint" if _fm(s) else "setpoint"
    return (s.controller.call(lambda afm: afm.get("z_controller", name))[name],)


def _gain_names(s) -> tuple[str, str]:
    return ("df_p_gain", "df_i_gain") if _fm(s) else ("p_gain", "i_gain")


@command("ZCtrl.GainSet", args=[("p_gain", "f"), ("time_constant", "f"), ("i_gain", "f")])
def gain_set(s, p_gain: float, time_constant: float, i_gain: float):
    """P [m/m; FM m/Hz] and I [1/s; FM m/(Hz s)] of the z loop (I = P / time constant [s] when I
    is 0 and the time constant is given)."""
    p = finite("p_gain", p_gain)
    i = finite("i_gain", i_gain)
    tc = finite("time_constant", time_constant, "s")
    if i == 0.0 and tc > 0.0:
        i = p / tc
    names = _gain_names(s)
    s.controller.call(lambda afm: afm.set("z_controller", **{names[0]: p, names[1]: i}))


@command("ZCtrl.GainGet", returns=[("p_gain", "f"), ("time_constant", "f"), ("i_gain", "f")])
def gain_get(s):
    names = _gain_names(s)
    v = s.controller.call(lambda afm: afm.get("z_controller", *names))
    p, i = v[names[0]], v[names[1]]
    return (p, p / i if i > 0 else 0.0, i)


@command("ZCtrl.ZPosSet", args=[("z", "f")])
def z_set(s, z: float):
    """The z piezo [m] with the feedback off (within [z_min, z_max])."""
    value = finite("z", z, "m")
    s.controller.call(lambda afm: afm.move_z(value))


@command("ZCtrl.ZPosGet", returns=[("z", "f")])
def z_get(s):
    """The z piezo now [m] (higher: retracted)."""
    return (s.controller.call(lambda afm: afm.signals()["z_m"]),)


@command("ZCtrl.LimitsGet", returns=[("z_high", "f"), ("z_low", "f")])
def limits_get(s):
    """The z piezo's range: z_max (retracted) then z_min [m]."""
    v = s.controller.call(lambda afm: afm.feedback())
    return (v["z_max"], v["z_min"])


@command("ZCtrl.StatusGet", returns=[("status", "H")])
def status_get(s):
    """1 off, 2 on, 3 hold (a spectroscopy holds it), 6 withdrawing."""
    v = s.controller.call(lambda afm: afm.signals())
    stage = v["stage"]
    if stage == "withdrawing":
        return (6,)
    if stage == "spectroscopy":
        return (3,)
    return (2 if v["feedback"] or stage == "approaching" else 1,)


@command("ZCtrl.CtrlListGet", returns=[("controllers", "strarr"), ("active", "i")])
def controllers_get(s):
    """The controllers: Amplitude (m) and Frequency Shift (Hz); the active one is the mode's."""
    return (list(CONTROLLERS), 1 if _fm(s) else 0)


@command("ZCtrl.ActiveCtrlSet", args=[("index", "i")])
def controller_set(s, index: int):
    """The active controller: only the mode's own (0 amplitude in AM, 1 frequency shift in FM)."""
    flag("index", index, (0, 1))
    active = 1 if _fm(s) else 0
    if index != active:
        raise Unsupported(
            f"this instrument runs in {'FM' if active else 'AM'} mode: the {CONTROLLERS[index]} "
            "controller needs "
            + (
                "the lock-in's amplitude (afm_instrument --nanonis)"
                if active
                else "the PLL (afm_instrument --fm --nanonis)"
            )  # fmt: skip
        )


@command("ZCtrl.Withdraw", args=[("wait", "I"), ("timeout", "i")])
def withdraw(s, wait: int, timeout: int):
    """Feedback off, the piezo retracts to z_max, the motor backs off withdraw_distance; wait
    (1) until done within timeout [ms] (-1 none)."""
    flag("wait", wait)
    job = s.controller.submit("withdraw", lambda afm: afm.withdraw())
    if wait:
        _wait(s, job, timeout)


@command("ZCtrl.Home")
def home(s):
    """Feedback off and the z piezo at its home, z_max (retracted)."""

    def apply(afm):
        afm.set("z_controller", enabled=False, disabled_action="hold")
        afm.move_z(afm.feedback()["z_max"])

    s.controller.call(apply)


# --- the coarse approach and motor
# ----------------------------------------------------------------------
@command("AutoApproach.Open")
def approach_open(s):
    """Nothing to open (accepted for scripts that call it)."""
    pass


@command("AutoApproach.OnOffSet", args=[("on", "H")])
def approach_on_off(s, on: int):
    """Start (1) the coarse approach: motor and z piezo until the setpoint, then engaged with the
    feedback on; stop it (0) where it is."""
    flag("on", on)
    if on:
        s.controller.submit("approach", lambda afm: afm.approach())
    else:
        s.controller.stop("approach")


@command("AutoApproach.OnOffGet", returns=[("running", "H")])
def approach_get(s):
    """1 while the coarse approach runs."""
    return (1 if s.controller.running("approach") else 0,)


Z_PLUS, Z_MINUS = 4, 5


@command(
    "Motor.StartMove",
    args=[("direction", "I"), ("steps", "H"), ("group", "I"), ("wait", "I")],
)
def motor_move(s, direction: int, steps: int, group: int, wait: int):
    """Z+ (4, away from the sample) or Z- (5, towards it) by ``steps`` of motor_step with the tip
    withdrawn; X and Y have no coarse motor here."""
    flag("wait", wait)
    if direction in (0, 1, 2, 3):
        raise Unsupported("X and Y have no coarse motor in this emulator (only Z: 4 Z+, 5 Z-)")
    flag("direction", direction, (Z_PLUS, Z_MINUS))
    count = steps if direction == Z_PLUS else -steps
    job = s.controller.submit("motor", lambda afm: afm.move_motor(count))
    if wait:
        _wait(s, job, -1)


@command("Motor.StopMove")
def motor_stop(s):
    """Stops a motor move where it is (the z stage then reads stopped)."""
    s.controller.stop("motor")


@command(
    "Motor.PosGet",
    args=[("group", "I"), ("timeout", "I")],
    returns=[("x", "d"), ("y", "d"), ("z", "d")],
    optional_from=0,
)
def motor_position(s, group: int = 0, timeout: int = 0):
    """The coarse motor [m]: z only (x and y 0)."""
    return (0.0, 0.0, s.controller.call(lambda afm: afm.signals()["motor_m"]))


# --- the tip's position
# ---------------------------------------------------------------------------------
@command("FolMe.XYPosSet", args=[("x", "d"), ("y", "d"), ("wait", "I")])
def xy_set(s, x: float, y: float, wait: int):
    """Move the tip to (x, y) [m]; with wait (1) also let the move's time pass (distance /
    FolMe speed) before answering."""
    flag("wait", wait)
    x, y = finite("x", x, "m"), finite("y", y, "m")
    if s.controller.running("scan"):
        raise ValueError("refused: a scan is running (stop it first)")

    def move(afm):
        v = afm.signals()
        distance = math.hypot(x - v["x_m"], y - v["y_m"])
        afm.move_tip(x, y)
        return distance

    distance = s.controller.call(move)
    if wait and distance > 0:
        speed = _folme_speed(s)
        job = s.controller.submit("move", lambda afm: afm.wait(distance / speed))
        _wait(s, job, -1)


def _folme_speed(s) -> float:
    if s.folme["custom"]:
        return s.folme["speed"]
    v = s.controller.call(lambda afm: afm.scan_settings())
    return 2.0 * v["scan_size_x"] * v["line_rate"]


@command("FolMe.XYPosGet", args=[("wait_newest", "I")], returns=[("x", "d"), ("y", "d")])
def xy_get(s, wait_newest: int):
    """The tip's commanded position now [m] (while scanning: on the scan's path)."""
    v = s.controller.call(lambda afm: afm.signals())
    return (v["x_m"], v["y_m"])


@command("FolMe.SpeedSet", args=[("speed", "f"), ("custom", "I")])
def folme_speed_set(s, speed: float, custom: int):
    """The tip's speed between points [m/s] (custom 1), or the scan's (0)."""
    flag("custom", custom)
    v = finite("speed", speed, "m/s")
    if not 0 < v <= 1e-3:
        raise ValueError(f"speed={v:g} m/s: allowed (0, 0.001] m/s")
    s.folme = {"speed": v, "custom": custom}


@command("FolMe.SpeedGet", returns=[("speed", "f"), ("custom", "I")])
def folme_speed_get(s):
    return (_folme_speed(s), s.folme["custom"])


# --- the piezo
# ------------------------------------------------------------------------------------------
@command("Piezo.RangeGet", returns=[("x", "f"), ("y", "f"), ("z", "f")])
def piezo_range(s):
    """The scanner's field in x and y and the z piezo's range (z_max - z_min) [m]."""

    def ranges(afm):
        field = afm.get("scanner", "scanner_field")["scanner_field"]
        f = afm.feedback()
        return (field, field, f["z_max"] - f["z_min"])

    return s.controller.call(ranges)


@command("Piezo.TiltSet", args=[("tilt_x", "f"), ("tilt_y", "f")])
def tilt_set(s, tilt_x: float, tilt_y: float):
    """The scanner's slope compensation as angles [deg]: z follows the plane tan(angle)."""
    sx = math.tan(math.radians(finite("tilt_x", tilt_x, "deg")))
    sy = math.tan(math.radians(finite("tilt_y", tilt_y, "deg")))
    s.controller.call(
        lambda afm: afm.set("scanner", slope_compensation_x=sx, slope_compensation_y=sy)
    )


@command("Piezo.TiltGet", returns=[("tilt_x", "f"), ("tilt_y", "f")])
def tilt_get(s):
    v = s.controller.call(
        lambda afm: afm.get("scanner", "slope_compensation_x", "slope_compensation_y")
    )
    return (
        math.degrees(math.atan(v["slope_compensation_x"])),
        math.degrees(math.atan(v["slope_compensation_y"])),
    )


_COMP = ("drift_compensation_x", "drift_compensation_y", "drift_compensation_z")


@command(
    "Piezo.DriftCompSet",
    args=[("on", "I"), ("vx", "f"), ("vy", "f"), ("vz", "f"), ("saturation_limit", "f")],
    optional_from=4,
)
def drift_set(s, on: int, vx: float, vy: float, vz: float, saturation_limit: float = -1.0):
    """Drift compensation (0 no change, 1 on, 2 off) at (vx, vy, vz) [m/s]: the scanner moves the
    tip so, from now on; it saturates at saturation_limit [%] of the scanner's field (-1 or
    absent: no change). It acts on the emulator's real drift (docs/imperfections.md)."""
    flag("on", on, (0, 1, 2))
    velocities = [finite(n, v, "m/s") for n, v in (("vx", vx), ("vy", vy), ("vz", vz))]
    values = dict(zip(_COMP, velocities))
    if on:
        values["drift_compensation"] = on == 1
    if saturation_limit != -1.0:
        limit = finite("saturation_limit", saturation_limit, "%")
        if not 0 <= limit <= 100:
            raise ValueError(f"saturation_limit={limit:g} %: allowed [0, 100] (-1: no change)")
        values["drift_compensation_limit"] = limit / 100.0

    def apply(afm):
        afm.set("scanner", **values)
        s.drift_since = afm.state()["t_s"]

    s.controller.call(apply)


@command(
    "Piezo.DriftCompGet",
    returns=[
        ("on", "I"),
        ("vx", "f"),
        ("vy", "f"),
        ("vz", "f"),
        ("x_saturated", "I"),
        ("y_saturated", "I"),
        ("z_saturated", "I"),
        ("saturation_limit", "f"),
    ],
)
def drift_get(s):
    """The compensation's state; an axis reads saturated when its velocity times the time since
    the last DriftCompSet reached the limit."""

    def read(afm):
        v = afm.get("scanner", "drift_compensation", *_COMP, "drift_compensation_limit",
                    "scanner_field")  # fmt: skip
        return v, afm.state()["t_s"]

    v, t = s.controller.call(read)
    limit = v["drift_compensation_limit"] * v["scanner_field"]
    elapsed = t - s.drift_since
    saturated = [
        1 if v["drift_compensation"] and abs(v[name] * elapsed) >= limit else 0 for name in _COMP
    ]
    return (
        1 if v["drift_compensation"] else 0,
        *(v[name] for name in _COMP),
        *saturated,
        100.0 * v["drift_compensation_limit"],
    )
