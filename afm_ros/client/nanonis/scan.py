"""Scan.*: the frame, the buffer, the speed, starting and stopping a scan, its data
(docs/nanonis.md has the mapping, units and limits of each)."""

from __future__ import annotations

import math

from afm_ros.client.nanonis.commands import Unsupported, command, finite, flag, timeout_s
from afm_ros.client.nanonis.signals import SIGNALS, image_channels, signal

START, STOP, PAUSE, RESUME, FREEZE, UNFREEZE, GO_TO_CENTER = range(7)
PIXEL_PACKET = 16  # the controller's lines travel in packets of 16 pixels


@command("Scan.Action", args=[("action", "H"), ("direction", "I")])
def scan_action(s, action: int, direction: int):
    """Start (direction 1 up, 0 down), stop (the lines done are kept and saved, marked stopped)
    or go to the frame's centre; pause and freeze are not modelled."""
    flag("direction", direction)
    if action == START:
        s.controller.call(
            lambda afm: afm.set_scan(slow_scan_direction="up" if direction else "down")
        )
        s.controller.submit("scan", s.run_scan)
    elif action == STOP:
        job = s.controller.stop("scan")
        if job is not None:
            s.job_error(job)
    elif action == GO_TO_CENTER:
        if s.controller.running("scan"):
            raise ValueError("go to centre refused: a scan is running (stop it first)")

        def centre(afm):
            v = afm.scan_settings()
            afm.move_tip(v["scan_center_x"], v["scan_center_y"])

        s.controller.call(centre)
    elif action in (PAUSE, RESUME, FREEZE, UNFREEZE):
        raise Unsupported(
            "pause, resume, freeze and unfreeze are not modelled (the emulated scanner cannot "
            "hold mid-line); stop the scan (1) and start it again (0)"
        )
    else:
        raise ValueError(f"action={action}: 0 start, 1 stop, 2-5 pause/resume/freeze, 6 centre")


@command("Scan.StatusGet", returns=[("scan_running", "I")])
def scan_status(s):
    """1 while a scan runs."""
    return (1 if s.controller.running("scan") else 0,)


@command(
    "Scan.FrameSet",
    args=[("center_x", "f"), ("center_y", "f"), ("width", "f"), ("height", "f"), ("angle", "f")],
)
def frame_set(s, center_x, center_y, width, height, angle):
    """The frame's centre and size [m] and angle [deg, clockwise as Nanonis counts it]."""
    values = [finite(n, v) for n, v in (("center_x", center_x), ("center_y", center_y))]
    size = (finite("width", width, "m"), finite("height", height, "m"))
    turn = -finite("angle", angle, "deg")  # the scanner counts counterclockwise
    s.controller.call(lambda afm: afm.set_scan(center=tuple(values), size=size, angle=turn))


@command(
    "Scan.FrameGet",
    returns=[
        ("center_x", "f"),
        ("center_y", "f"),
        ("width", "f"),
        ("height", "f"),
        ("angle", "f"),
    ],
)
def frame_get(s):
    v = s.controller.call(lambda afm: afm.scan_settings())
    return (
        v["scan_center_x"],
        v["scan_center_y"],
        v["scan_size_x"],
        v["scan_size_y"],
        -v.get("scan_angle", 0.0),
    )


@command("Scan.BufferSet", args=[("channels", "i[]"), ("pixels", "i"), ("lines", "i")])
def buffer_set(s, channels, pixels: int, lines: int):
    """The channels recorded (signal indices of image channels: Signals.NamesGet) and the raster:
    pixels coerced to the closest multiple of 16 (at least 16), as the controller sends lines in
    packets of 16 pixels; lines 0 keeps the frame's aspect ratio."""
    chosen = [int(c) for c in channels]
    if not chosen:
        raise ValueError("channels: at least one")
    available = {SIGNALS[i].index for i in range(len(SIGNALS)) if SIGNALS[i].channel}
    for c in chosen:
        sig = signal(c)
        if c not in available:
            names = ", ".join(f"{i} {SIGNALS[i].name}" for i in sorted(available))
            raise ValueError(f"channel {c} ({sig.name}) is not an image channel; allowed: {names}")
        if sig.channel not in _mode_channels(s):
            raise Unsupported(f"{sig.name} is recorded only in {_other(s)} mode")
    if len(set(chosen)) != len(chosen):
        raise ValueError(f"channels {chosen}: each at most once")

    coerced = max(PIXEL_PACKET, PIXEL_PACKET * round(pixels / PIXEL_PACKET))

    def apply(afm):
        if lines <= 0:
            v = afm.scan_settings()
            n = max(1, round(coerced * v["scan_size_y"] / v["scan_size_x"]))
        else:
            n = lines
        afm.set_scan(pixels=coerced, lines=n)

    if s.controller.running("scan"):
        raise ValueError("buffer refused: a scan is running (stop it first)")
    s.controller.call(apply)
    s.buffer = chosen


@command("Scan.BufferGet", returns=[("channels", "i[]"), ("pixels", "i"), ("lines", "i")])
def buffer_get(s):
    v = s.controller.call(lambda afm: afm.scan_settings())
    return (list(s.buffer), v["pixels_per_line"], v["lines"])


@command(
    "Scan.PropsSet",
    args=[
        ("continuous", "I"),
        ("bouncy", "I"),
        ("autosave", "I"),
        ("series_name", "str"),
        ("comment", "str"),
        ("modules", "strarr"),
        ("autopaste", "I"),
    ],
    optional_from=5,
)
def props_set(s, continuous, bouncy, autosave, series_name, comment, modules=(), autopaste=0):
    """Continuous scanning (0 no change, 1 on, 2 off), autosave (0 no change, 1 all, 2 next, 3
    off), the file series' name and the comment; bouncy scanning is not modelled."""
    flag("continuous", continuous, (0, 1, 2))
    flag("bouncy", bouncy, (0, 1, 2))
    flag("autosave", autosave, (0, 1, 2, 3))
    if bouncy == 1:
        raise Unsupported("bouncy scanning is not modelled (each frame starts at its first line)")
    if series_name and any(c in series_name for c in '/\\:*?"<>|\0'):
        raise ValueError(f"series_name={series_name!r}: a file name, no path characters")
    if continuous:
        s.continuous = continuous == 1
    if autosave:
        s.autosave = {1: "all", 2: "next", 3: "off"}[autosave]
    if series_name:
        s.series = series_name
    s.comment = comment


@command(
    "Scan.PropsGet",
    returns=[
        ("continuous", "I"),
        ("bouncy", "I"),
        ("autosave", "I"),
        ("series_name", "str"),
        ("comment", "str"),
        ("modules", "strarr"),
        ("params_per_module", "i[]"),
        ("parameters", "str2d"),
        ("autopaste", "I"),
    ],
)
def props_get(s):
    autosave = {"all": 0, "next": 1, "off": 2}[s.autosave]
    return (int(s.continuous), 0, autosave, s.series, s.comment, [], [], [], 0)


@command(
    "Scan.SpeedSet",
    args=[
        ("forward_speed", "f"),
        ("backward_speed", "f"),
        ("forward_time_per_line", "f"),
        ("backward_time_per_line", "f"),
        ("keep_constant", "H"),
        ("speed_ratio", "f"),
    ],
)
def speed_set(s, forward_speed, backward_speed, forward_time_per_line, backward_time_per_line,
              keep_constant, speed_ratio):  # fmt: skip
    """The line rate from the forward speed [m/s] (keep_constant 1) or the forward time per line
    [s] (2; 0: whichever is given); trace and retrace take the same time (speed ratio 1)."""
    flag("keep_constant", keep_constant, (0, 1, 2))
    if speed_ratio not in (0.0, 1.0) and math.isfinite(speed_ratio):
        raise Unsupported(
            f"speed_ratio={speed_ratio:g}: trace and retrace take the same time here (ratio 1)"
        )
    if not math.isfinite(speed_ratio):
        raise ValueError(f"speed_ratio={speed_ratio}: a finite number (1)")

    def apply(afm):
        size = afm.scan_settings()["scan_size_x"]
        use_time = keep_constant == 2 or (keep_constant == 0 and forward_time_per_line > 0)
        if use_time:
            t = finite("forward_time_per_line", forward_time_per_line, "s")
            if t <= 0:
                raise ValueError(f"forward_time_per_line={t:g} s: must be > 0")
            rate = 0.5 / t
        else:
            v = finite("forward_speed", forward_speed, "m/s")
            if v <= 0:
                raise ValueError(f"forward_speed={v:g} m/s: must be > 0")
            rate = v / (2.0 * size)
        afm.set_scan(line_rate=rate)

    s.controller.call(apply)


@command(
    "Scan.SpeedGet",
    returns=[
        ("forward_speed", "f"),
        ("backward_speed", "f"),
        ("forward_time_per_line", "f"),
        ("backward_time_per_line", "f"),
        ("keep_constant", "H"),
        ("speed_ratio", "f"),
    ],
)
def speed_get(s):
    v = s.controller.call(lambda afm: afm.scan_settings())
    t = 0.5 / v["line_rate"]
    speed = v["scan_size_x"] / t
    return (speed, speed, t, t, 1, 1.0)


@command(
    "Scan.WaitEndOfScan",
    args=[("timeout", "i")],
    returns=[("timed_out", "I"), ("file_path", "str")],
)
def wait_end_of_scan(s, timeout: int):
    """Until the frame being scanned ends (timeout [ms], -1 none); the path of the file it was
    saved to ('' if autosave is off)."""
    ended = s.wait_frame(timeout_s(timeout))
    return (0 if ended else 1, s.last_sxm if ended else "")


@command(
    "Scan.FrameDataGrab",
    args=[("channel", "I"), ("forward", "I")],
    returns=[("channel_name", "str"), ("data", "f2d"), ("scan_up", "I")],
)
def frame_data_grab(s, channel: int, forward: int):
    """The channel's image of the frame being scanned (or the last): lines x pixels in the order
    scanned (as in the .sxm file; NaN where not scanned yet)."""
    flag("data_direction", forward)
    name, data, direction = s.grab(channel, bool(forward))
    return (name, data, 1 if direction == "up" else 0)


def _mode_channels(s) -> tuple:
    return image_channels(s.mode)


def _other(s) -> str:
    return "AM" if s.mode == "fm" else "FM"
