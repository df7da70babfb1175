"""Problem flags an instrument can raise from what it measures (no ROS, no ground truth).

Automation frameworks name these problems (afspm: FEEDBACK_NON_OPTIMAL, THERMAL_DRIFT,
TIP_SHAPE_CHANGED); here each is computed from a finished frame (and the one before it), put in
the frame's metadata and on ``/diagnostics``. The emulator's ground truth (``truth/scanner``) says
whether a flag was right, so detection software can be scored against it.

- ``feedback_not_optimal``: lines whose median absolute amplitude error (setpoint - amplitude,
  trace and retrace) exceeds ``error_fraction`` of the setpoint: the loop does not follow the
  surface over most of the line (gains, speed or setpoint); the short transients at edges, which
  any loop shows, do not count. Reported with the lines and the worst median.
- ``z_range_saturated``: pixels where the z piezo sat at a limit of its range (within
  ``LIMIT_TOLERANCE_M``): the surface left the range (a tall feature, a tilt, drift); the image is
  clipped there.
- ``drift_detected``: the frame is shifted against the previous frame of the same area by more than
  ``drift_pixels`` (sub-pixel image registration of the height images,
  :func:`afm_ros.core.image_analysis.image_shift`); reported as a shift [m] and a rate [m/s].
  Frames of fewer than 8 lines or pixels are too small to register: no drift check.
- ``tip_change_suspected``: on the lines with features (height steps above ``FEATURE_FRACTION`` of
  the frame's upper quartile: a flat line images the same with any tip), the trace/retrace mismatch
  relative to the line's height steps (the rms height difference over the rms pixel-to-pixel step:
  the scanner's hysteresis, which shifts trace against retrace, mismatches a line by about the
  shift times its steps and does not count) jumps above ``tip_jump`` times the median of the lines
  before it (at least ``tip_persist`` of them) and stays there for ``tip_persist`` lines (a tip
  that picked something up or broke images differently from then on).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from afm_ros.core.image_analysis import MIN_SHIFT_SIZE, image_shift

LIMIT_TOLERANCE_M = 1e-12
# a line whose height steps are below this fraction of the frame's upper quartile is flat
FEATURE_FRACTION = 0.2


@dataclass(frozen=True)
class FlagSettings:
    error_fraction: float = (
        0.05  # rms amplitude error / setpoint above which a line is not followed
    )
    drift_pixels: float = 0.5  # frame-to-frame shift [pixels] above which drift is flagged
    tip_jump: float = 3.0  # trace/retrace mismatch jump (x the median) that suggests a tip change
    tip_persist: int = 3  # ... lasting at least this many lines


@dataclass
class Flag:
    name: str
    message: str
    values: dict = field(default_factory=dict)


def feedback_setpoint(frame, z_controller: dict) -> float:
    """The setpoint the frame's error channel is measured against: the amplitude setpoint [m] of a
    tapping frame, the df setpoint [Hz] of an FM frame (its error channel is
    ``frequency_shift_error``)."""
    return (
        z_controller["df_setpoint"]
        if "frequency_shift_error" in frame.channels
        else z_controller["setpoint"]
    )


def frame_flags(
    frame,
    setpoint: float,
    z_limits: tuple[float, float],
    previous=None,
    settings: FlagSettings = FlagSettings(),
) -> list[Flag]:
    """The problems a finished frame shows (see the module doc); ``previous``: the frame before it
    (the same area for a drift check; ignored if its plan differs). ``setpoint``: the z loop's, in
    the error channel's unit (:func:`feedback_setpoint`: m in tapping, Hz in FM)."""
    flags = []
    tr, re = frame.images["trace"], frame.images["retrace"]
    done = max(1, frame.lines_done or frame.plan.lines)
    fm = "frequency_shift_error" in frame.channels
    channel = "frequency_shift_error" if fm else "amplitude_error"
    err = np.concatenate([tr[channel][:done], re[channel][:done]], axis=1).astype(float)
    with np.errstate(invalid="ignore"):
        typical = np.nanmedian(np.abs(err), axis=1)
    bad = np.flatnonzero(typical > settings.error_fraction * abs(setpoint))
    if bad.size:
        worst = f"{np.nanmax(typical):.3g} Hz" if fm else f"{np.nanmax(typical) * 1e9:.3g} nm"
        flags.append(
            Flag(
                "feedback_not_optimal",
                f"{bad.size} of {done} lines with a median {'df' if fm else 'amplitude'} error "
                "above "
                f"{settings.error_fraction:.0%} of the setpoint (worst {worst}, line "
                f"{int(np.nanargmax(typical))})",
                {
                    "lines": bad.tolist(),
                    ("worst_median_hz" if fm else "worst_median_m"): float(np.nanmax(typical)),
                },
            )
        )
    z_lo, z_hi = z_limits
    height = np.concatenate([tr["height"][:done], re["height"][:done]], axis=1).astype(float)
    at_limit = (height <= z_lo + LIMIT_TOLERANCE_M) | (height >= z_hi - LIMIT_TOLERANCE_M)
    # the z channel is float32 in the frame: compare with its resolution at the limit's magnitude
    tol = np.float32(max(abs(z_lo), abs(z_hi))) * np.finfo(np.float32).eps * 4
    at_limit |= (np.abs(height - z_lo) <= tol) | (np.abs(height - z_hi) <= tol)
    n = int(np.count_nonzero(at_limit))
    if n:
        flags.append(
            Flag(
                "z_range_saturated",
                f"{n} of {height.size} pixels at a z limit ({z_lo * 1e9:.4g} or {z_hi * 1e9:.4g} "
                "nm): "
                "the surface left the z piezo's range and the image is clipped there",
                {"pixels": n, "fraction": n / height.size},
            )
        )
    if (
        previous is not None
        and previous.plan.values() == frame.plan.values()
        and not frame.partial
        and min(frame.plan.lines, frame.plan.pixels) >= MIN_SHIFT_SIZE
    ):  # a smaller frame: no drift check
        a = previous.images["trace"]["height"].astype(float)
        b = tr["height"].astype(float)
        if np.isfinite(a).all() and np.isfinite(b).all():
            rows, cols = image_shift(a, b)
            p = frame.plan
            dt = (
                p.frame_time * (frame.index - previous.index)
                if frame.index > previous.index
                else p.frame_time
            )
            dx, dy = cols * p.pixel_size, rows * p.line_pitch
            if math.hypot(rows, cols) > settings.drift_pixels:
                flags.append(
                    Flag(
                        "drift_detected",
                        f"frame shifted by ({dx * 1e9:.3g}, {dy * 1e9:.3g}) nm against the "
                        "previous one: "
                        f"{math.hypot(dx, dy) / dt * 60e9:.3g} nm/min",
                        {
                            "shift_x_m": dx,
                            "shift_y_m": dy,
                            "rate_m_per_s": math.hypot(dx, dy) / dt,
                        },
                    )
                )
    trace_h = tr["height"][:done].astype(float)
    raw = np.sqrt(np.nanmean((trace_h - re["height"][:done]) ** 2, axis=1))
    # relative to the line's features: the scanner's hysteresis shifts trace against retrace, which
    # mismatches a line by about the shift times its height steps; a tip change shows beyond that,
    # and only where there are features (a flat line images the same with any tip)
    steps = (
        np.sqrt(np.nanmean(np.diff(trace_h, axis=1) ** 2, axis=1))
        if trace_h.shape[1] > 1
        else raw * 0
    )
    featured = (
        np.flatnonzero(steps > FEATURE_FRACTION * np.nanpercentile(steps, 75))
        if done
        else np.array([], int)
    )
    relative = raw[featured] / steps[featured]
    if np.isfinite(relative).all():
        k = settings.tip_persist
        for i in range(k, relative.size - k + 1):
            base = float(np.median(relative[:i]))
            if base > 0 and (relative[i : i + k] > settings.tip_jump * base).all():
                line = int(featured[i])
                flags.append(
                    Flag(
                        "tip_change_suspected",
                        f"from line {line} on the trace/retrace mismatch (relative to the line's "
                        "height "
                        f"steps) is over {settings.tip_jump:g} times the median of the lines "
                        "before",
                        {"line": line, "median_relative_mismatch": base},
                    )
                )
                break
    return flags


def flags_metadata(flags: list[Flag]) -> dict:
    """The flags as frame metadata (``flags.<name>`` -> message; ``flags.none`` when there is
    none)."""
    if not flags:
        return {"flags.none": "no problem detected"}
    return {f"flags.{f.name}": f.message for f in flags}
