"""An autonomous-experiment agent on the virtual AFM: survey, find islands, zoom, measure.

    .venv/bin/python examples/survey_agent.py              # in-process (no ROS), about a minute
    .venv/bin/python examples/survey_agent.py --ros /afm1  # against nodes run with -r __ns:=/afm1

The agent tunes and approaches, surveys 8 x 8 um of the PS/LDPE blend, levels the survey's height
image and gives its slope to the scanner's slope compensation (as an operator does after a first
image), finds the LDPE islands in the phase image (scikit-image: Otsu threshold, labelling, region
properties), zooms into the largest island that lies whole inside the survey, measures the phase
contrast between island and matrix in the zoom (away from the edges), takes a spectroscopy curve
on the island and one on the matrix, withdraws and prints a summary (also returned as a dict by
:func:`run`, which test/test_survey_agent.py checks against the physics core).
"""

from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from afm_ros.client import Microscope

SURVEY = dict(center=(5e-6, 5e-6), size=(8e-6, 8e-6), pixels=64, lines=64, line_rate=2.0)
SLOPE_SCAN = dict(
    pixels=32, lines=16, line_rate=4.0
)  # a quick first image of the survey's area, for its slope
ZOOM_PIXELS = 48
MIN_SOLIDITY = 0.9  # a single round island, not two touching ones
MIN_ISLAND_PIXELS = (
    12  # smaller regions of the survey's phase mask are noise or edges, not islands
)


def segment(phase: np.ndarray, min_pixels: int = MIN_ISLAND_PIXELS):
    """Label image of the high-phase regions (LDPE lags more than PS) and their region
    properties."""
    from skimage.filters import threshold_otsu
    from skimage.measure import label, regionprops

    lo, hi = np.percentile(
        phase, [1, 99]
    )  # a few transient pixels (the scan's first) must not move the threshold
    labels = label(phase > threshold_otsu(np.clip(phase, lo, hi)))
    small = [r.label for r in regionprops(labels) if r.area < min_pixels]
    labels[np.isin(labels, small)] = 0
    labels = label(labels > 0)
    return labels, regionprops(labels, intensity_image=phase)


def level(height: np.ndarray, frame) -> tuple[float, float]:
    """Slopes dz/dx, dz/dy [m/m] of the height image's least-squares plane."""
    rows, cols = np.indices(height.shape)
    a = np.column_stack([np.ones(height.size), cols.ravel(), rows.ravel()])
    _, gx, gy = np.linalg.lstsq(a, height.ravel(), rcond=None)[0]
    return float(gx / float(frame.x[1] - frame.x[0])), float(gy / float(frame.y[1] - frame.y[0]))


def inner(mask: np.ndarray, pixels: int) -> np.ndarray:
    """The mask shrunk by ``pixels`` (the loop's transient at the edges stays out of the
    medians)."""
    from skimage.morphology import disk, erosion

    return erosion(mask, disk(pixels)).astype(bool) if pixels > 0 else mask


def spectroscopy_summary(curve) -> dict:
    """Where the approach leg's amplitude falls to the setpoint (gap z [m]) and the largest mean
    force [N]."""
    approach = curve.branch.values == "approach"
    z, a = curve.z_gap.values[approach], curve.amplitude.values[approach]
    setpoint = float(curve.attrs["setpoint"])
    below = np.flatnonzero(a <= setpoint)
    z_set = float(z[below[0]]) if below.size else float("nan")
    return {
        "z_at_setpoint_m": z_set,
        "max_mean_force_N": float(np.nanmax(curve.chunk_force.values)),
    }


def run(afm, survey: dict = SURVEY, zoom_pixels: int = ZOOM_PIXELS, say=print) -> dict:
    """The agent's experiment on a connected :class:`afm_ros.client.Microscope`; its numbers."""
    out: dict = {}
    if afm.state()["stage"] != "engaged":
        tune = afm.tune()
        say(f"tuned: f0 {tune['f0_Hz']:.2f} Hz, Q {tune['Q']:.3f}")
        approach = afm.approach()
        say(f"engaged after {approach['cycles']} cycles, {approach['motor_steps']} motor steps")
    afm.set_scan(**{**survey, **SLOPE_SCAN})
    first = afm.scan()
    gx, gy = level(first.height.sel(direction="trace").values, first)
    afm.set("scanner", slope_compensation_x=gx, slope_compensation_y=gy)
    out["slope"] = [gx, gy]
    say(
        f"first image: sample slope dz/dx {gx:.5f}, dz/dy {gy:.5f}, given to the scanner's slope "
        "compensation"
    )
    afm.set_scan(**survey)
    say(
        f"survey: {survey['size'][0] * 1e6:g} x {survey['size'][1] * 1e6:g} um, "
        f"{survey['pixels']} x "
        f"{survey['lines']} pixels at {survey['line_rate']:g} lines/s"
    )
    frame = afm.scan()
    labels, regions = segment(frame.phase.sel(direction="trace").values)
    rows, cols = labels.shape
    whole = [
        r
        for r in regions
        if r.bbox[0] > 0
        and r.bbox[1] > 0
        and r.bbox[2] < rows
        and r.bbox[3] < cols
        and r.solidity >= MIN_SOLIDITY
    ]
    if not whole:
        raise RuntimeError(
            f"no round island lies whole inside the survey ({len(regions)} regions)"
        )
    island = max(whole, key=lambda r: r.area)
    pixel = float(frame.x[1] - frame.x[0])
    cy, cx = island.centroid
    x0, y0 = float(frame.x[0]) + cx * pixel, float(frame.y[0]) + cy * pixel
    diameter = 2.0 * np.sqrt(island.area / np.pi) * pixel
    out.update(
        islands=len(regions),
        island_center_m=[x0, y0],
        island_diameter_m=diameter,
        survey_start_s=float(frame.attrs["start_time_s"]),
    )
    say(
        f"found {len(regions)} islands; zooming into the largest round one inside the survey: "
        f"{diameter * 1e9:.0f} nm across at ({x0 * 1e6:.2f}, {y0 * 1e6:.2f}) um"
    )
    size = 2.5 * diameter
    afm.set_scan(
        center=(x0, y0),
        size=(size, size),
        pixels=zoom_pixels,
        lines=zoom_pixels,
        line_rate=survey["line_rate"],
    )
    zoom = afm.scan()
    phase = zoom.phase.sel(direction="trace").values
    zlabels, _ = segment(phase, max(4, zoom_pixels // 12))
    edge = max(1, zoom_pixels // 16)
    on, off = inner(zlabels > 0, edge), inner(zlabels == 0, edge)
    contrast = float(np.median(phase[on]) - np.median(phase[off]))
    out.update(
        zoom_size_m=size,
        phase_island_deg=float(np.median(phase[on])),
        phase_matrix_deg=float(np.median(phase[off])),
        phase_contrast_deg=contrast,
        flags=afm.flags(),
    )
    say(
        f"zoom {size * 1e6:.2f} um: phase contrast island - matrix {contrast:.3f} deg "
        f"({int(on.sum())} and {int(off.sum())} pixels away from the edges); flags: "
        f"{out['flags'] or 'none'}"
    )
    # the matrix point: the zoom's pixel farthest from any island and from the zoom's edge (an
    # island the zoom does not show may lie just outside it, and the scanner's creep moves the tip
    # by ~100 nm)
    from scipy.ndimage import distance_transform_edt

    free = zlabels == 0
    free[0, :] = free[-1, :] = free[:, 0] = free[:, -1] = False
    far = np.unravel_index(int(np.argmax(distance_transform_edt(free))), zlabels.shape)
    matrix = (float(zoom.x[far[1]]), float(zoom.y[far[0]]))
    for name, (x, y) in (("island", (x0, y0)), ("matrix", matrix)):
        curve = afm.spectroscopy(x, y)
        out[f"spectroscopy_{name}"] = {**spectroscopy_summary(curve), "point_m": [x, y]}
        s = out[f"spectroscopy_{name}"]
        say(
            f"spectroscopy on the {name} at ({x * 1e6:.2f}, {y * 1e6:.2f}) um: the amplitude "
            "reaches the setpoint at "
            f"z {s['z_at_setpoint_m'] * 1e9:.2f} nm, largest mean force "
            f"{s['max_mean_force_N'] * 1e9:.2f} nN"
        )
    afm.withdraw()
    say("withdrawn")
    return out


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--ros",
        metavar="NAMESPACE",
        help="drive the nodes running in NAMESPACE (default: an in-process instrument, no ROS)",
    )
    parser.add_argument(
        "--json", action="store_true", help="also print the numbers as one JSON line"
    )
    args = parser.parse_args(argv)

    afm = Microscope.connect(args.ros, timeout=30.0) if args.ros else Microscope.local()
    with afm:
        result = run(afm)
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
