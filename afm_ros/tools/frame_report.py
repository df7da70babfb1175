"""What a scanned frame shows against what the sample is and what the physics core predicts.

Used by ``afm_instrument --image`` (and usable on any :class:`afm_ros.core.imaging.Frame`):

- height: the step between the two most common true height levels under the pixels, from the
  image's medians on each level (pixels within ``edge_pixels`` pixels along x, where the feedback
  settles after an edge, and one line along y of a height or material edge left out), for trace
  and retrace, against the true step and against the *apparent* step the physics
  core predicts when the two levels are different materials (a soft material is indented more,
  so the feedback holds the setpoint amplitude with the base lower: true step + z_base(top
  material) - z_base(bottom material) at the setpoint, from :func:`afm_ros.tools.contrast.contrast_study`);
- phase: the median phase on each material and their difference, against the difference the
  physics core predicts at the same amplitude setpoint ratio;
- trace - retrace: rms difference of the height images.
"""
from __future__ import annotations

import math

import numpy as np

from afm_ros.core.image_analysis import edge_mask, level_step, material_medians, sample_under_pixels, trace_retrace_rms
from afm_ros.core.imaging import DIRECTIONS


def predictions(materials, force_model: str, ratio: float, cantilever, drive, steps_per_period: int) -> dict:
    """{material: {"phase_deg", "z_base_m", "dissipated_energy_J"}} at amplitude ratio A/A0 = ratio."""
    from afm_ros.tools.contrast import CONTRAST_MODELS, contrast_study

    names = list(dict.fromkeys(materials))
    if force_model not in CONTRAST_MODELS or len(names) < 2:
        return {}
    rows, _ = contrast_study(names, force_model, ratios=(ratio,), cantilever=cantilever, drive=drive,
                             steps_per_period=steps_per_period)
    return {r["material"]: {"phase_deg": float(r["phase_deg"]), "z_base_m": float(r["z_base_m"]),
                            "dissipated_energy_J": float(r["dissipated_energy_J"])} for r in rows}


def frame_report(frame, sample, setpoint_ratio: float, force_model: str, cantilever, drive,
                 steps_per_period: int, edge_pixels: float = 2.0, predict: bool = True) -> dict:
    """Numbers of a frame (see module doc); SI units, angles in degrees."""
    plan = frame.plan
    true_height, material = sample_under_pixels(sample, plan)
    levels = np.unique(np.round(true_height, 15), return_inverse=True)[1].reshape(true_height.shape)
    labels = levels * 256 + material.astype(np.int64)
    keep = edge_mask(labels, plan, edge_pixels * plan.pixel_size, plan.line_pitch)
    names = list(sample.materials)
    present = [names[i] for i in np.unique(material)]
    pred = predictions(present, force_model, setpoint_ratio, cantilever, drive, steps_per_period) if predict else {}
    out = {"edge_pixels_excluded": edge_pixels, "pixels_kept": int(keep.sum()), "materials": present,
           "setpoint_ratio": setpoint_ratio, "force_model": force_model, "predicted": pred, "directions": {}}
    for d in DIRECTIONS:
        images = frame.images[d]
        entry = {}
        try:
            step = level_step(images["height"].astype(float), true_height, keep)
            entry["true_step_m"] = step.true_step
            entry["measured_step_m"] = step.measured_step
            level_materials = []
            for level in step.levels:
                on = (np.abs(true_height - level) < 1e-15) & keep
                counts = np.bincount(material[on], minlength=len(names))
                level_materials.append(names[int(np.argmax(counts))])
            entry["level_materials"] = level_materials
            if pred and level_materials[0] != level_materials[1] and all(m in pred for m in level_materials):
                entry["predicted_apparent_step_m"] = (step.true_step + pred[level_materials[1]]["z_base_m"]
                                                      - pred[level_materials[0]]["z_base_m"])
        except ValueError as exc:
            entry["step_error"] = str(exc)
        phases = material_medians(images["phase"].astype(float), material, keep, names)
        entry["phase_deg"] = phases
        if len(phases) >= 2:
            a, b = list(phases)[:2]
            entry["phase_contrast_deg"] = {"materials": [b, a], "measured": phases[b] - phases[a]}
            if a in pred and b in pred:
                entry["phase_contrast_deg"]["predicted"] = pred[b]["phase_deg"] - pred[a]["phase_deg"]
        entry["dissipation_J"] = material_medians(images["dissipation"].astype(float), material, keep, names)
        out["directions"][d] = entry
    out["trace_retrace_rms_m"] = trace_retrace_rms(frame)
    return out


def report_text(report: dict) -> str:
    nm = 1e9
    lines = []
    for d, e in report["directions"].items():
        if "measured_step_m" in e:
            text = (f"  {d:8s} step {e['measured_step_m'] * nm:7.3f} nm (true {e['true_step_m'] * nm:.3f} nm "
                    f"{e['level_materials'][1]} on {e['level_materials'][0]}")
            if "predicted_apparent_step_m" in e:
                text += f"; apparent step the physics predicts {e['predicted_apparent_step_m'] * nm:.3f} nm"
            lines.append(text + ")")
        elif "step_error" in e:
            lines.append(f"  {d:8s} step: {e['step_error']}")
        pc = e.get("phase_contrast_deg")
        if pc:
            text = f"  {d:8s} phase {pc['materials'][0]} - {pc['materials'][1]}: {pc['measured']:+.3f} deg"
            if "predicted" in pc:
                text += f" (physics core at A/A0 = {report['setpoint_ratio']:.3f}: {pc['predicted']:+.3f} deg)"
            lines.append(text)
    rms = report.get("trace_retrace_rms_m", math.nan)
    lines.append(f"  trace - retrace height rms {rms * nm:.3f} nm")
    return "\n".join(lines)
