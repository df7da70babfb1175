"""What a scanned frame shows against what the sample is and what the physics core predicts.

One analysis for every frame, offline (``afm_study scan``) and live (``afm_instrument --image``),
so both say the same thing with the same caveats:

- step / island height: the image's medians on the two most common true height levels
  (:func:`afm_ros.core.image_analysis.level_step`), pixels within the edge-exclusion distance of
  another level or material left out, against the true step; when the two levels are different
  materials also the apparent step the physics core predicts, true + z_base(top material) -
  z_base(bottom material) from :func:`afm_ros.tools.contrast.contrast_study` at the same setpoint
  (a soft material is indented deeper, so it looks lower: a real tapping-mode artefact);
- phase contrast and dissipation between the materials (medians per material) against
  contrast_study's steady states at A/A0 = setpoint / free amplitude;
- the amplitude error on the kept pixels: above :data:`SETTLED_ERROR` the feedback has not settled
  on the features (scan too fast for the gains), the medians are biased by the loop, not by the
  material, and every measured-vs-predicted line says so;
- trace-retrace rms of height and phase.

Edge exclusion (default; an explicit distance overrides): tip radius + speed x (latency + t_fall +
3 tau), with latency = feedback_latency x chunk_duration + 1/output_rate, tau = (1 + p_gain) /
i_gain the loop's time constant (dA/dz = 1) and t_fall = max(0, H - (1 + p_gain) dA) / (i_gain dA)
the free fall after a down-step of height H when the tip loses contact (dA = A0 - setpoint, z then
moves at the speed limit i_gain dA): beyond it the feedback error is below ~5 % of the step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from afm_ros.core.image_analysis import (
    edge_mask,
    level_step,
    material_medians,
    plane_fit,
    trace_retrace_rms,
    truth_under_pixels,
)
from afm_ros.core.imaging import DIRECTIONS
from afm_ros.tools.contrast import CONTRAST_MODELS, DEFAULT_SPP, contrast_study

# more distinct true heights than this: no step to measure (e.g. a rough sample)
DISCRETE_LEVELS = 16
# [m] largest median amplitude error on the kept pixels for the frame to count as settled
SETTLED_ERROR = 0.1e-9
NOT_SETTLED = " [feedback not settled: biased, see the warning]"


@dataclass
class Loop:
    """The z feedback as the frame saw it (SI units)."""

    setpoint: float  # [m]
    p_gain: float  # [m/m]
    i_gain: float  # [1/s]
    free_amplitude: float  # [m]
    latency: float  # [s] feedback_latency x chunk_duration + 1 / lock-in output_rate
    tip_radius: float  # [m]

    def numbers(self) -> dict:
        """Speed limit, time constant and latency of the z feedback (see the module doc)."""
        da = self.free_amplitude - self.setpoint
        return {
            "free_amplitude_m": self.free_amplitude,
            "setpoint_ratio": self.setpoint / self.free_amplitude,
            "amplitude_margin_m": da,
            "z_speed_limit_m_per_s": self.i_gain * da,
            "loop_time_constant_s": (1.0 + self.p_gain) / self.i_gain
            if self.i_gain > 0
            else math.inf,
            "latency_s": self.latency,
        }


def auto_edge_exclusions(loop: Loop, plan, step: float) -> list[tuple[float, str]]:
    """Candidate exclusion distances along x [m], most settled first (module doc): tip radius +
    speed x (latency + t_fall + n tau) for n = 3 (error below ~5 % of the step) and n = 1 (1/e),
    then tip radius + one pixel (no settling allowance); each at least one pixel."""
    numbers = loop.numbers()
    out = []
    if loop.i_gain > 0.0:
        da = numbers["amplitude_margin_m"]
        t_fall = max(0.0, abs(step) - (1.0 + loop.p_gain) * da) / (loop.i_gain * da)
        for n, text in (
            (3, "settled to ~5 %"),
            (1, "settled to ~1/e only: medians biased towards the neighbour"),
        ):
            d = loop.tip_radius + plan.speed * (
                loop.latency + t_fall + n * numbers["loop_time_constant_s"]
            )
            out.append(
                (
                    max(d, plan.pixel_size),
                    f"tip radius + speed x (latency + t_fall + {n} (1 + p_gain) / i_gain), {text}",
                )
            )
    out.append(
        (
            loop.tip_radius + plan.pixel_size,
            "tip radius + 1 pixel: the feedback has not settled on these "
            "features at this speed, medians biased",
        )
    )
    return out


def predictions(
    materials,
    force_model: str,
    ratio: float,
    cantilever,
    drive,
    steps_per_period: int | None = None,
) -> dict:
    """contrast_study's steady state per material at A/A0 = ratio: {name: row} (two or more
    materials), with ``image_dissipation_J``: what the image's first-harmonic dissipation estimate
    reads for that steady state (E_dis + the damping of the higher harmonics, pi k (w / w0) / Q
    sum_{n>=2} n^2 A_n^2)."""

    names = list(dict.fromkeys(materials))
    if force_model not in CONTRAST_MODELS or not 0.0 < ratio < 1.0 or len(names) < 2:
        return {}
    rows, scans = contrast_study(
        names,
        force_model,
        (ratio,),
        cantilever,
        drive,
        steps_per_period=steps_per_period or DEFAULT_SPP,
    )
    c, d = cantilever, drive
    out = {}
    for r in rows:
        point = scans[r["material"]][0]
        if point.analysis is not None:
            a = point.analysis.harmonics
            n = np.arange(1, a.size + 1)
            r = {
                **r,
                "image_dissipation_J": r["dissipated_energy_J"]
                + math.pi
                * c.spring_constant
                * (d.frequency / c.resonance_frequency)
                / c.quality_factor
                * float(np.sum((n[1:] * a[1:]) ** 2)),
            }
        out[r["material"]] = r
    return out


def clean(value):
    """JSON-ready: numpy scalars to Python, NaN/inf to None."""
    if isinstance(value, dict):
        return {str(k): clean(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [clean(v) for v in value]
    if isinstance(value, (np.floating, float)):
        v = float(value)
        return v if math.isfinite(v) else None
    if isinstance(value, np.integer):
        return int(value)
    if isinstance(value, np.ndarray):
        return clean(value.tolist())
    return value


def _height_slope(frame) -> list[float] | None:
    """[dz/dx, dz/dy] of the trace height image's least-squares plane [m/m] (what an operator reads
    off a first image for the slope compensation); None for fewer than 2 lines."""
    height = frame.images["trace"]["height"].astype(float)
    if height.shape[0] < 2 or np.isfinite(height).sum() < 3:
        return None
    _, gx, gy = plane_fit(height)
    return [gx / frame.plan.pixel_size, gy / frame.plan.line_pitch]


def phase_contrasts(phase: dict, present: list, names: list, pred: dict) -> dict:
    """Phase contrast [deg] of each present material against the reference (the sample's first
    material if present), per direction from the per-direction medians ``phase[d][material]``; a
    direction whose kept pixels miss one of the two (a few lines, wide edges, the retrace shifted
    by hysteresis) has none, a pair with none in either direction is left out."""
    contrast: dict = {}
    if len(present) < 2:
        return contrast
    ref = present[0] if names[0] not in present else names[0]
    for other in (m for m in present if m != ref):
        c = {
            d: phase[d][other] - phase[d][ref]
            for d in DIRECTIONS
            if other in phase[d] and ref in phase[d]
        }
        if not c:
            continue
        if other in pred and ref in pred:
            c["predicted"] = float(pred[other]["phase_deg"] - pred[ref]["phase_deg"])
        contrast[f"{other} - {ref}"] = c
    return contrast


def analyse_frame(
    frame,
    sample,
    loop: Loop,
    force_model: str,
    cantilever,
    drive,
    steps_per_period: int | None = None,
    edge_exclusion: float = -1.0,
    predict: bool = True,
    artefacts: np.ndarray | None = None,
) -> dict:
    """The frame's numbers (module doc) as a JSON-ready dict; SI units in the keys, angles in
    degrees.

    ``edge_exclusion`` [m] < 0: automatic. The frame may be partial (fewer lines than planned).
    ``artefacts``: the packed imperfections in force during the frame (``Imperfections.packed``):
    each direction is then compared with the sample under the apex where the scanner truly was
    (hysteresis, creep, drift), its height image less the tilt and vertical drift there (ground
    truth, :func:`afm_ros.core.image_analysis.truth_under_pixels`)."""
    plan = frame.plan
    under = truth_under_pixels(sample, plan, artefacts, frame.index, frame.lines_planned)
    true_h, mat = under["trace"].height, under["trace"].material
    levels, level_index = np.unique(np.round(true_h, 15), return_inverse=True)
    level_index = level_index.reshape(true_h.shape)
    numbers = loop.numbers()
    discrete = 2 <= levels.size <= DISCRETE_LEVELS
    step_guess = float(levels.max() - levels.min()) if levels.size >= 2 else 0.0

    def labels(u):
        index = np.searchsorted(levels, np.round(u.height, 15)).clip(0, max(levels.size - 1, 0))
        return index.astype(np.int64) * 256 + u.material.astype(np.int64)

    if edge_exclusion >= 0.0:
        candidates = [(edge_exclusion, "explicit")]
        distance_y = edge_exclusion
    else:
        candidates = auto_edge_exclusions(loop, plan, step_guess)
        distance_y = loop.tip_radius
    # the first candidate that leaves pixels on each of the two main levels (and on each material)
    top = np.argsort(np.bincount(level_index.ravel()))[-2:] if levels.size >= 2 else np.array([0])
    for distance, rule in candidates:
        keeps = {d: edge_mask(labels(under[d]), plan, distance, distance_y) for d in DIRECTIONS}
        keep = keeps["trace"]
        if all((keep & (level_index == k)).any() for k in top) and all(
            (keep & (mat == k)).any() for k in np.unique(mat)
        ):
            break
    names = list(sample.materials)
    present = [names[k] for k in np.unique(mat[keep])] if keep.any() else []
    ratio = numbers["setpoint_ratio"]
    pred = (
        predictions(present, force_model, ratio, cantilever, drive, steps_per_period)
        if predict and present
        else {}
    )

    step: dict = {"levels_m": levels.tolist() if discrete else None}
    if not discrete:
        step["note"] = (
            f"{levels.size} distinct true heights under the pixels: no two-level step"
            if levels.size > DISCRETE_LEVELS
            else "one true height level: no step"
        )
    else:
        try:
            by_dir = {
                d: level_step(
                    frame.images[d]["height"].astype(float) - under[d].plane,
                    under[d].height,
                    keeps[d],
                )
                for d in DIRECTIONS
            }
        except ValueError as exc:
            step["note"] = f"not measurable: {exc} (edge exclusion {distance:.3g} m)"
        else:
            ls = by_dir["trace"]
            level_mats = []
            for lv in ls.levels:
                counts = np.bincount(
                    mat[keep & (np.abs(true_h - lv) < 1e-15)], minlength=len(names)
                )
                level_mats.append(names[int(np.argmax(counts))])
            step.update(
                {
                    "true_m": ls.true_step,
                    "measured_trace_m": ls.measured_step,
                    "measured_retrace_m": by_dir["retrace"].measured_step,
                    "level_pixels": ls.pixels.tolist(),
                    "level_materials": level_mats,
                    "two_levels_m": ls.levels.tolist(),
                }
            )
            if level_mats[0] == level_mats[1]:
                step["predicted_apparent_m"] = ls.true_step
                step["predicted_rule"] = "one material: apparent = true"
            elif all(m in pred and pred[m]["regime"] != "not_reached" for m in level_mats):
                zb = [float(pred[m]["z_base_m"]) for m in level_mats]
                step["predicted_apparent_m"] = ls.true_step + zb[1] - zb[0]
                step["z_base_m"] = dict(zip(level_mats, zb))
                step["predicted_rule"] = (
                    f"true + z_base({level_mats[1]}) - z_base({level_mats[0]}) "
                    f"(contrast_study at A/A0 = {ratio:.4g})"
                )

    phase, dissipation, amplitude_error = {}, {}, {}
    for d in DIRECTIONS:
        m, k = under[d].material, keeps[d]
        phase[d] = material_medians(frame.images[d]["phase"].astype(float), m, k, names)
        dissipation[d] = material_medians(
            frame.images[d]["dissipation"].astype(float), m, k, names
        )
        amplitude_error[d] = material_medians(
            frame.images[d]["amplitude_error"].astype(float), m, k, names
        )
    worst = max((abs(v) for e in amplitude_error.values() for v in e.values()), default=math.nan)
    # without dissipation, at resonance, sin(phi) = A / A0: dphi/dA = 1 / (A0 cos(phi)) = 1 / (A0
    # sqrt(1 - r^2)) at the setpoint ratio r (1.6 deg/nm at r = 0.8; the core's slope on PS and
    # LDPE is the same)
    sensitivity = math.degrees(
        1.0 / (numbers["free_amplitude_m"] * math.sqrt(max(1.0 - ratio**2, 1e-12)))
    )
    contrast = phase_contrasts(phase, present, names, pred)
    return clean(
        {
            "feedback": numbers,
            "force_model": force_model,
            "lines_scanned": int(plan.lines),
            "edge_exclusion_m": distance,
            "edge_exclusion_y_m": distance_y,
            "edge_exclusion_rule": rule,
            "kept_pixels": int(keep.sum()),
            "pixels": int(keep.size),
            "step": step,
            "phase_deg": phase,
            "phase_contrast_deg": contrast,
            "dissipation_J": dissipation,
            "amplitude_error_m": amplitude_error,
            "settled": bool(worst <= SETTLED_ERROR) if math.isfinite(worst) else False,
            "phase_per_amplitude_deg_per_m": sensitivity,
            "prediction": {
                m: {
                    k: r.get(k)
                    for k in (
                        "z_base_m",
                        "amplitude_m",
                        "phase_deg",
                        "dissipated_energy_J",
                        "image_dissipation_J",
                        "indentation_m",
                        "peak_force_N",
                        "regime",
                    )
                }
                for m, r in pred.items()
            },
            "height_slope": _height_slope(frame),
            "trace_retrace_rms": {
                "height_m": trace_retrace_rms(frame, "height"),
                "phase_deg": trace_retrace_rms(frame, "phase"),
            },
        }
    )


def _nm(x) -> str:
    return "n/a" if x is None else f"{x * 1e9:.3f} nm"


def frame_lines(s: dict) -> list[str]:
    """The printed lines of :func:`analyse_frame`'s dict (the same in every tool)."""
    st = s["step"]
    caveat = "" if s["settled"] else NOT_SETTLED
    lines = [
        f"  edge exclusion       {s['edge_exclusion_m'] * 1e6:.3g} um along x, "
        f"{s['edge_exclusion_y_m'] * 1e6:.3g} um along y ({s['edge_exclusion_rule']}); "
        f"{s['kept_pixels']} of {s['pixels']} pixels kept"
    ]
    if "true_m" in st:
        lines.append(
            f"  step height          true {_nm(st['true_m'])}; measured "
            f"{_nm(st['measured_trace_m'])} (trace), "
            f"{_nm(st['measured_retrace_m'])} (retrace){caveat}"
        )
        if st.get("predicted_apparent_m") is not None:
            lines.append(
                f"  predicted apparent   {_nm(st['predicted_apparent_m'])} = "
                f"{st['predicted_rule']}"
            )
            if st["level_materials"][0] != st["level_materials"][1]:
                lines.append(
                    f"                       ({st['level_materials'][1]} on "
                    f"{st['level_materials'][0]}: "
                    "the softer material is indented deeper and looks lower; a real tapping-mode "
                    "artefact)"
                )
    else:
        lines.append(f"  step height          {st.get('note', 'n/a')}")
    for d in DIRECTIONS:
        ph = s["phase_deg"][d]
        if ph:
            lines.append(
                f"  {'phase, ' + d:<21s}" + ", ".join(f"{m} {v:.3f} deg" for m, v in ph.items())
            )
    for key, c in s["phase_contrast_deg"].items():
        pred = (
            f"; predicted {c['predicted']:.3f} deg (contrast_study)"
            if c.get("predicted") is not None
            else ""
        )
        measured = ", ".join(f"{c[d]:.3f} deg ({d})" for d in DIRECTIONS if d in c)
        lines.append(f"  phase contrast       {key}: {measured}{pred}{caveat}")
    ds = s["dissipation_J"]["trace"]
    if ds:
        lines.append(
            "  dissipation (trace)  "
            + ", ".join(f"{m} {v * 1e18:.2f} aJ" for m, v in ds.items())
            + caveat
        )
        if s["prediction"]:
            pr = s["prediction"]
            lines.append(
                "  core dissipation     "
                + ", ".join(f"{m} {r['dissipated_energy_J'] * 1e18:.2f} aJ" for m, r in pr.items())
                + "; as the image estimates it (+ higher-harmonic damping) "
                + ", ".join(
                    f"{m} {r['image_dissipation_J'] * 1e18:.2f} aJ"
                    for m, r in pr.items()
                    if r.get("image_dissipation_J") is not None
                )
            )
    errors = [(abs(v), v, m, d) for d, e in s["amplitude_error_m"].items() for m, v in e.items()]
    if errors:
        _, worst_value, worst, worst_dir = max(errors)
        text = ", ".join(f"{m} {_nm(v)}" for m, v in s["amplitude_error_m"]["trace"].items())
        lines.append(f"  amplitude error      {text} (trace medians)")
        if not s["settled"]:
            advice = "scan slower or raise the gains"
            tr, rt = s["amplitude_error_m"]["trace"], s["amplitude_error_m"]["retrace"]
            if tr and all(
                m in rt and v * rt[m] < 0 and 0.5 < abs(v / rt[m]) < 2 for m, v in tr.items()
            ):
                # a steady error of one sign uphill and the other downhill: an integral loop
                # lagging on a ramp
                advice = (
                    "trace and retrace errors of opposite sign: the loop lags on a slope, e.g. "
                    "the sample's "
                    "tilt; set the scanner's slope_compensation_x/y to the image's slope, scan "
                    "slower or "
                    "raise i_gain"
                )
            lines.append(
                "  warning              not settled: median amplitude error up to "
                f"{_nm(worst_value)} "
                f"({worst}, {worst_dir}); the phase moves "
                f"~{s['phase_per_amplitude_deg_per_m'] * 1e-9:.2g} deg per nm "
                "of amplitude error and the height by up to as much: medians are biased by the "
                "feedback, "
                f"not material ({advice})"
            )
    if s.get("height_slope"):
        gx, gy = s["height_slope"]
        lines.append(
            f"  height plane         dz/dx {gx:.5f}, dz/dy {gy:.5f} (the image's least-squares "
            "plane: the sample's "
            f"tilt plus drift; level it, or give it to the scanner's slope_compensation_x/y)"
        )
    rms = s["trace_retrace_rms"]
    lines.append(
        f"  trace-retrace rms    height {_nm(rms['height_m'])}, phase "
        f"{'n/a' if rms['phase_deg'] is None else format(rms['phase_deg'], '.3f')} deg"
    )
    return lines
