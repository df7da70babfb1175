"""A scanned frame on disk: every channel in one Gwyddion ``.gwy`` file plus PNG previews.

:func:`write_frame` (``frame``: an :class:`afm_ros.core.imaging.Frame`) writes

- ``<stem>.gwy``: every channel x direction of :data:`afm_ros.core.imaging.CHANNELS` /
  :data:`~afm_ros.core.imaging.DIRECTIONS`, titled as :func:`frame_channels` names them
  ("Height (trace)", "Phase (retrace)", ...), raw values in SI units (m, deg, J), real size = the
  scan size, offsets = the scan's lower-left corner (``x_left``, ``y_low``: image row 0 is the
  lowest y, which Gwyddion shows at the top, its y axis pointing down the rows), and the
  metadata flattened to strings (``section.name [unit]`` -> text) in every channel;
- ``<stem>_<channel>_<direction>.png``: a matplotlib preview of each channel with a colour bar in
  its unit (SI prefix chosen for display). The height previews are plane-levelled (least-squares
  plane removed) and say so in their title; the other channels are shown raw. The ``.gwy`` file
  always holds the raw data.

Colour range (:func:`display_range`): 2 % of the pixels clipped at each end (the live view's tail
cut), so edge spikes do not squeeze the contrast. The previews use it, and the ``.gwy`` file stores
it per channel as Gwyddion's fixed colour range, so Gwyddion and its thumbnailer show the contrast
too (the range is a display setting; the data are untouched).

Every file is written to a temporary file in the target directory and renamed over the target,
so it appears complete or not at all. A frame with pixels that were never acquired (NaN: an
incomplete frame, or more pixels per line than lock-in outputs per pass) is rejected with a
``ValueError`` naming the channel and the count: a ``.gwy`` file holds no NaN.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Mapping

import numpy as np

from afm_ros.formats.channels import DIRECTIONS, IMAGE_TAIL_CUT, UNITS, tail_cut_limits
from afm_ros.formats.gwy import write_gwy

CHANNEL_TITLES = {
    "height": "Height",
    "amplitude": "Amplitude",
    "phase": "Phase",
    "amplitude_error": "Amplitude error",
    "dissipation": "Dissipation",
    "frequency_shift": "Frequency shift",
    "drive": "Drive",
    "phase_error": "Phase error",
    "frequency_shift_error": "Frequency shift error",
}

# display scaling of the previews: (factor, unit text) for a value range of this magnitude
_PREFIXES = (
    (1e-18, "a"),
    (1e-15, "f"),
    (1e-12, "p"),
    (1e-9, "n"),
    (1e-6, "u"),
    (1e-3, "m"),
    (1.0, ""),
)


def channel_title(channel: str, direction: str) -> str:
    """Gwyddion channel title of ``channel`` in ``direction``: ``"Height (trace)"``."""
    return f"{CHANNEL_TITLES[channel]} ({direction})"


def frame_channels(frame) -> dict[str, tuple[np.ndarray, str]]:
    """Ordered {title: (float64 array [lines, pixels], SI unit)} of every channel x direction
    (channel-major: Height (trace), Height (retrace), Amplitude (trace), ...); row 0 = lowest y."""
    out = {}
    for channel in frame.channels:
        for direction in DIRECTIONS:
            out[channel_title(channel, direction)] = (
                np.asarray(frame.images[direction][channel], dtype=np.float64),
                UNITS[channel],
            )
    return out


def _text(value) -> str:
    if isinstance(value, str):
        return value
    if isinstance(value, (bool, np.bool_)):
        return "true" if value else "false"
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    if isinstance(value, (float, np.floating)):
        return repr(float(value))
    if value is None:
        return "none"
    if isinstance(value, (list, tuple)):
        return json.dumps(
            [v if isinstance(v, (int, float, str, bool)) or v is None else _text(v) for v in value]
        )
    return str(value)


def flatten_metadata(metadata: Mapping | None, units: Mapping | None = None) -> dict[str, str]:
    """Flat {key: text} of a (nested) mapping: ``{"scan": {"line_rate": 1.0}}`` ->
    ``{"scan.line_rate [Hz]": "1.0"}`` when ``units["scan.line_rate"] == "Hz"``. Numbers are
    written as their shortest round-trip text, booleans as true/false, lists as JSON."""
    out: dict[str, str] = {}
    units = units or {}

    def walk(prefix: str, value) -> None:
        if isinstance(value, Mapping):
            for k, v in value.items():
                walk(f"{prefix}.{k}" if prefix else str(k), v)
            return
        unit = units.get(prefix, "")
        key = f"{prefix} [{unit}]" if unit and unit not in ("1", "") else prefix
        out[key] = _text(value)

    for k, v in (metadata or {}).items():
        walk(str(k), v)
    return out


def plane_level(image: np.ndarray) -> np.ndarray:
    """``image`` minus its least-squares plane a + b col + c row (over the finite pixels)."""
    z = np.asarray(image, dtype=np.float64)
    rows, cols = np.indices(z.shape)
    ok = np.isfinite(z)
    if ok.sum() < 3:
        return z - np.nanmean(z) if ok.any() else z.copy()
    a = np.column_stack([np.ones(ok.sum()), cols[ok], rows[ok]])
    coef, *_ = np.linalg.lstsq(a, z[ok], rcond=None)
    return z - (coef[0] + coef[1] * cols + coef[2] * rows)


def display_range(image: np.ndarray) -> tuple[float, float] | None:
    """(low, high) colour range of ``image`` in its unit: :data:`IMAGE_TAIL_CUT` of the finite
    pixels clipped at each end (:func:`tail_cut_limits`); None for an image without two distinct
    values."""
    lo, hi = tail_cut_limits(image)
    if not hi > lo:  # constant after the cut (or no data): fall back to the plain extremes
        lo, hi = tail_cut_limits(image, 0.0)
    return (lo, hi) if hi > lo else None


RANGE_TEXT = (
    f"colour range: {100 * IMAGE_TAIL_CUT:g}-{100 - 100 * IMAGE_TAIL_CUT:g} % of the pixels"
)


def display_scale(values: np.ndarray, unit: str) -> tuple[float, str]:
    """(factor to divide by, unit text) so the values' range reads in 1..1000 of the unit."""
    if unit in ("deg", ""):
        return 1.0, unit or "1"
    finite = values[np.isfinite(values)]
    span = float(np.max(np.abs(finite))) if finite.size else 0.0
    if span == 0.0:
        return 1.0, unit
    for factor, prefix in reversed(_PREFIXES):
        if span >= factor:
            return factor, prefix + unit
    return _PREFIXES[0][0], _PREFIXES[0][1] + unit


def _atomic_write(path: Path, write) -> None:
    """Call ``write(tmp_path)``, then rename the temporary file over ``path``."""
    tmp = path.parent / f".{path.name}.{os.getpid()}.{os.urandom(4).hex()}.tmp"
    try:
        write(tmp)
        with open(tmp, "rb+") as f:
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        try:
            os.unlink(tmp)
        except OSError:
            pass
        raise


def write_text_atomically(path, text: str) -> Path:
    """Write ``text`` to ``path`` via a temporary file and a rename."""
    path = Path(path)
    _atomic_write(path, lambda tmp: tmp.write_text(text))
    return path


def display_image(
    image: np.ndarray, unit: str, levelled: bool = False
) -> tuple[np.ndarray, tuple, str]:
    """What a preview shows of ``image`` (SI ``unit``): (values / display factor, colour range in
    the same scaled unit, unit text such as "nm"). ``levelled``: plane-levelled
    (:func:`plane_level`) and shifted so the colour range starts at 0. The colour range is
    :func:`display_range` (a unit-wide span around a constant image)."""
    shown = plane_level(image) if levelled else np.asarray(image, dtype=np.float64)
    span = display_range(shown)
    if levelled and span is not None:  # heights from the bottom of the colour range
        shown, span = shown - span[0], (0.0, span[1] - span[0])
    factor, unit_text = display_scale(shown if span is None else np.asarray(span), unit)
    if span is None:
        value = float(np.nanmean(shown)) / factor if np.isfinite(shown).any() else 0.0
        return (
            shown / factor,
            (value - 0.5 * (abs(value) or 1.0), value + 0.5 * (abs(value) or 1.0)),
            unit_text,
        )
    return shown / factor, (span[0] / factor, span[1] / factor), unit_text


def _preview(path: Path, image: np.ndarray, unit: str, title: str, plan, levelled: bool) -> None:
    # the object-oriented API without pyplot: no global figure state, so a writer thread (the
    # scanner node writes its frames in one) cannot interfere with another user of matplotlib
    from matplotlib.figure import Figure

    shown, (lo, hi), unit_text = display_image(image, unit, levelled)
    x0, y0 = plan.x_left * 1e6, plan.y_low * 1e6
    x1, y1 = x0 + plan.size_x * 1e6, y0 + plan.size_y * 1e6
    aspect_w = 5.6
    fig = Figure(
        figsize=(aspect_w, max(2.5, min(8.0, aspect_w * plan.size_y / plan.size_x * 0.9 + 0.8)))
    )
    ax = fig.add_subplot()
    # row 0 (lowest y) at the top, as Gwyddion shows it: its y axis points down the rows
    im = ax.imshow(
        shown,
        origin="upper",
        extent=(x0, x1, y1, y0),
        cmap="afmhot",
        interpolation="nearest",
        aspect="equal",
        vmin=lo,
        vmax=hi,
    )
    ax.set_xlabel("x [um]")
    ax.set_ylabel("y [um]")
    ax.set_title(title, fontsize=10)
    bar = fig.colorbar(im, ax=ax, extend="both")
    bar.set_label(f"{unit_text} ({RANGE_TEXT})")
    fig.tight_layout()

    def write(tmp: Path) -> None:
        fig.savefig(tmp, dpi=100, format="png")

    _atomic_write(path, write)


def write_frame(
    frame,
    stem,
    metadata: Mapping | None = None,
    previews: bool = True,
    units: Mapping | None = None,
) -> list[Path]:
    """Write ``<stem>.gwy`` (every channel, raw SI values, with its :func:`display_range` as
    Gwyddion's colour range) and, if ``previews``, one PNG per channel and direction
    (``<stem>_<channel>_<direction>.png``); return the paths written.

    ``metadata``: flat or nested mapping (e.g. ``{"scan": {...}, "feedback": {...},
    "cantilever": {...}, "sample": {...}}``), stored flattened to strings in every channel
    (:func:`flatten_metadata`; ``units`` maps flattened keys to a unit for the key text).
    ValueError for pixels without data (see module doc).
    """

    stem = Path(stem)
    plan = frame.plan
    channels = frame_channels(frame)
    for title, (values, _) in channels.items():
        missing = int(np.count_nonzero(~np.isfinite(values)))
        if missing:
            raise ValueError(
                f"frame channel {title!r} has {missing} of {values.size} pixels without data "
                f"(frame incomplete: {frame.lines_done} of {plan.lines} lines, or more pixels per "
                f"line than lock-in outputs per pass)"
            )
    stem.parent.mkdir(parents=True, exist_ok=True)
    gwy = stem.with_name(stem.name + ".gwy")
    meta = flatten_metadata(metadata, units)
    ranges = {
        title: span
        for title, (values, _) in channels.items()
        if (span := display_range(values)) is not None
    }
    write_gwy(
        gwy,
        channels,
        xreal=plan.size_x,
        yreal=plan.size_y,
        xoff=plan.x_left,
        yoff=plan.y_low,
        metadata=meta,
        display_ranges=ranges,
    )
    written = [gwy]
    if previews:
        for channel in frame.channels:
            for direction in DIRECTIONS:
                path = stem.with_name(f"{stem.name}_{channel}_{direction}.png")
                title = channel_title(channel, direction)
                levelled = channel == "height"
                if levelled:
                    title += ": plane-levelled preview\n(raw data in the .gwy)"
                _preview(
                    path, frame.images[direction][channel], UNITS[channel], title, plan, levelled
                )
                written.append(path)
    return written


def spec_units(sections: Mapping[str, Mapping]) -> dict[str, str]:
    """{``section.name``: unit} for flatten_metadata from {section: {name: ParamSpec}}."""
    out = {}
    for section, specs in sections.items():
        for name, spec in specs.items():
            unit = getattr(spec, "unit", "")
            if unit and unit != "1":
                out[f"{section}.{name}"] = unit
    return out
