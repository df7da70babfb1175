"""``afm_instrument --fm``: a frequency-modulation (non-contact) AFM session over ROS.

The nodes of the tapping instrument plus the ``pll`` node (afm_ros.nodes.pll_node): the cantilever
is driven at the PLL's frequency and the amplitude controller's force (``excitation`` 'pll'), the z
controller regulates on the frequency shift (``feedback_signal`` 'frequency_shift'). The session
(simulated seconds; docs/fm.md):

1. start withdrawn ``approach_start_distance`` (FM default 100 nm) above the sample; the PLL locks
   and the amplitude controller rings the cantilever up to its amplitude setpoint
   (``FREE_LOCK_S``);
2. measure the free resonance (the PLL's frequency) and drive, and centre the PLL on that resonance
   (``center_frequency``), so df is the shift from the free resonance; Q = k A / F_free follows;
3. approach at ``approach_speed`` (FM default 50 nm/s) until df reaches ``df_setpoint``, engage;
4. hold ``--duration`` and report df, amplitude and drive (last half);
5. scan one frame (defaults :data:`FM_SCAN`: across an LDPE island of the cut PS/LDPE blend) and
   report df, drive and dissipation by material (the map's ground truth under the apex) and the
   contrast; .gwy + PNG as in tapping;
6. withdraw.

With ``--interactive`` steps 5-6 are the user's: after the hold it runs until Ctrl-C (scan, tune
and withdraw with ``afm_ctl``; a status line with df, amplitude and drive every 5 s) and then
prints the summary with the statistics of the last simulated second before Ctrl-C and the frames
written.

Defaults the job sets unless given with -p: :data:`FM_CANTILEVER`, :data:`FM_Z`, :data:`FM_SCAN`,
and the scanner's slope compensation equal to the sample's tilt (a user who compensated the tilt
they measured: an integrating z loop on df otherwise follows the tilt's ramp with an error of v /
K_I).
"""

from __future__ import annotations

import math
import time
from collections import deque

import numpy as np

from afm_ros.core.fm import dissipation_from_drive
from afm_ros.core.image_analysis import fm_material_contrast
from afm_ros.core.session_stats import FmWindow
from afm_ros.formats import chunk_layout
from afm_ros.nodes import topics
from afm_ros.nodes.guard import GuardedNode
from afm_ros.tools.instrument_summary import ScanProgress

# [s] simulated withdrawn: the PLL locks (~0.1 s at 20 Hz) and the amplitude rings up
FREE_LOCK_S = 0.3
# a vacuum cantilever, PLL-excited, 2 ms chunks (the cantilever's default; the PLL keeps 43 deg of
# phase margin at its 4.6 ms loop delay, 57 deg at 1 ms chunks, where the ROS loop is not real time
# on 2 cores)
FM_CANTILEVER = {
    "excitation": "pll",
    "quality_factor": 1e4,
    "chunk_duration": 2e-3,
    "sample": "ps_ldpe_microtomed",
    "force_model": "hysteresis_dmt",
}
FM_Z = {
    "feedback_signal": "frequency_shift",
    "approach_start_distance": 100e-9,
    "approach_speed": 50e-9,
}
# 1.5 um across an LDPE island at 1 line/s: ~3 um/s, what the z loop on df follows (docs/fm.md)
FM_SCAN = {
    "pixels_per_line": 32,
    "lines": 16,
    "line_rate": 1.0,
    "scan_size_x": 1.5e-6,
    "scan_size_y": 1.5e-6,
    "scan_center_x": 5.3e-6,
    "scan_center_y": 6.56e-6,
}
FM_RAW_EXCLUDE = (
    "pll/frequency_shift",
    "pll/phase_error",
    "pll/drive",
)  # per-output copies of pll/outputs


class FmMonitor(GuardedNode):
    """Listens to ``pll/outputs`` and fills the FM windows the session asks for (no history
    kept)."""

    def __init__(self, **kwargs):
        super().__init__("afm_instrument_fm_monitor", **kwargs)
        self.windows: list[FmWindow] = []
        self.end_time = -math.inf  # simulated end [s] of the input chunk the newest batch answered
        self.latest = None
        # [s] simulated: > 0 keeps the batches of that last span (interactive)
        self.recent_span = 0.0
        self.recent: deque = deque()
        topics.subscribe_values(self, topics.PLL_OUTPUTS, self._on_batch, topics.HISTORY_QOS)

    def _on_batch(self, msg: topics.ArrayMessage) -> None:
        out = chunk_layout.unpack_fm_outputs(msg.data)
        for w in self.windows:
            w.add(out.t, out.df, out.drive, out.amplitude, out.phase_error)
        self.end_time = max(self.end_time, out.input_end_time)
        self.latest = out
        if self.recent_span > 0 and out.t.shape[0]:
            self.recent.append(out)
            while self.recent and self.recent[0].t[-1] < out.t[-1] - self.recent_span:
                self.recent.popleft()

    def recent_window(self) -> FmWindow:
        """Statistics of the last ``recent_span`` simulated seconds of outputs."""
        if not self.recent:
            return FmWindow(math.nan, math.nan)
        t1 = float(self.recent[-1].t[-1])
        w = FmWindow(t1 - self.recent_span, math.nextafter(t1, math.inf))
        for out in self.recent:
            w.add(out.t, out.df, out.drive, out.amplitude, out.phase_error)
        return w

    def status_line(self, instrument) -> str:
        """One line of the FM loop's state for --interactive."""
        out = self.latest
        if out is None or not out.t.shape[0]:
            return "t=? (no PLL output yet)"
        return (
            f"t={out.t[-1]:.3f} s  df={out.df[-1]:.3f} Hz (setpoint "
            f"{float(instrument.get('z_controller', 'df_setpoint')):g})  "
            f"amplitude={out.amplitude[-1] * 1e9:.4f} nm  "
            f"drive={out.drive[-1] * 1e12:.4g} pN  z_piezo={instrument.monitor.z * 1e9:.3f} nm"
            + instrument.status_tail()
        )

    def window(self, t0: float, t1: float) -> FmWindow:
        w = FmWindow(t0, t1)
        self.windows.append(w)
        return w


def _measure(afm, fm: FmMonitor, seconds: float) -> FmWindow:
    """Run ``seconds`` simulated and return the FM statistics of their second half."""
    instrument = afm.session
    t0 = instrument.t_paused
    w = fm.window(t0 + seconds / 2, t0 + seconds)
    afm.wait_until(t0 + seconds)
    instrument.spin_until(
        lambda: fm.end_time >= instrument.t_paused - 1e-9, "waiting for the PLL's outputs"
    )
    fm.windows.remove(w)
    return w


# [s] simulated: --interactive's summary covers the last second before Ctrl-C
INTERACTIVE_SPAN_S = 1.0


def run_fm_job(job, duration: float, progress: bool = True, interactive: bool = False) -> dict:
    """The FM session (module docstring) as a :class:`afm_ros.tools.instrument_job.InstrumentJob`
    whose instrument runs the pll and scanner nodes in this process; returns the summary's numbers
    (SI units). ``interactive``: after the hold, run until Ctrl-C instead of scanning and
    withdrawing."""
    afm, instrument = job.afm, job.b

    if instrument.attached or not {"pll", "scanner"} <= set(instrument.nodes):
        raise RuntimeError(
            "the FM session runs the pll and scanner nodes in this process (no --attach)"
        )
    kw = {"context": instrument.context}
    if instrument.namespace:
        kw["namespace"] = instrument.namespace
    fm = FmMonitor(**kw)
    instrument.executor.add_node(fm)
    instrument.extra_nodes.append(fm)
    wall0 = time.monotonic()
    out: dict = {"mode": "fm"}
    instrument.wait_ready()
    instrument.start_far()
    cantilever = instrument.cantilever
    c = cantilever.engine.setup.cantilever
    k, q_set = c.spring_constant, c.quality_factor
    a_set = float(instrument.get("pll", "amplitude_setpoint"))
    # 1-2: lock free, centre the PLL on the free resonance
    free = _measure(afm, fm, FREE_LOCK_S)
    if free.n == 0:
        raise RuntimeError("no PLL output while locking the free cantilever")
    centre = float(instrument.get("pll", "center_frequency"))
    f_free = centre + free.mean("df")
    if abs(free.mean("amplitude") - a_set) > 0.02 * a_set:
        raise RuntimeError(
            f"the free oscillation did not reach the amplitude setpoint {a_set:g} m in "
            f"{FREE_LOCK_S} s "
            f"(amplitude {free.mean('amplitude'):.4g} m, drive {free.mean('drive'):.4g} N): "
            "the drive_max or the amplitude gains may be too small"
        )
    instrument.set("pll", center_frequency=f_free)
    out["free"] = {
        "resonance_Hz": f_free,
        "pll_centre_before_Hz": centre,
        "drive_N": free.mean("drive"),
        "amplitude_m": free.mean("amplitude"),
        "phase_error_deg": free.mean("phase_error"),
        "quality_factor_measured": k * free.mean("amplitude") / free.mean("drive"),
        "quality_factor_set": q_set,
    }
    # 3: approach on df
    out["approach"] = afm.approach()
    out["df_setpoint_Hz"] = float(instrument.get("z_controller", "df_setpoint"))
    # 4: hold
    hold = _measure(afm, fm, duration)
    out["hold"] = {
        name: {"mean": hold.mean(name), "std": hold.std(name)} for name in FmWindow.NAMES
    }
    out["hold"]["dissipation_J"] = float(
        dissipation_from_drive(hold.mean("drive"), hold.mean("amplitude"), k, q_set)
    )
    out["hold"]["window_s"] = [hold.t0, hold.t1]
    scanner = instrument.nodes["scanner"]
    if interactive:
        fm.recent_span = INTERACTIVE_SPAN_S
        job.run_until_interrupted(status=lambda: fm.status_line(instrument))
        last = fm.recent_window()
        out["last_second"] = {
            name: {"mean": last.mean(name), "std": last.std(name)} for name in FmWindow.NAMES
        }
        out["last_second"]["dissipation_J"] = float(
            dissipation_from_drive(last.mean("drive"), last.mean("amplitude"), k, q_set)
        )
        out["last_second"]["window_s"] = [last.t0, last.t1]
        scanner.wait_for_writers(30.0)  # a frame that just finished is still being written
        out["image"] = {
            "files": [str(p) for p in scanner.frames_written],
            "flags": {f.name: f.message for f in scanner.flags},
        }
        out["interrupted"] = ""  # Ctrl-C is how an interactive session ends
        out["simulated_s"] = fm.end_time
        out["wall_s"] = time.monotonic() - wall0
        out["real_time_factor"] = out["simulated_s"] / out["wall_s"]
        out["recording"] = instrument.recording_status(spin=False)
        return out
    # 5: scan
    afm.scan(progress=ScanProgress(instrument) if progress else None)
    scan = instrument.last_scan
    plan, artefacts, interrupted, wall_scan = (
        scan.plan,
        scan.artefacts,
        scan.interrupted,
        scan.wall_s,
    )
    frame = (
        scanner.accumulator.frames_done[0] if scanner.frames_done >= 1 else scanner.partial_frame
    )
    image = {
        "pixels": plan.pixels,
        "lines": plan.lines,
        "line_rate_Hz": plan.line_rate,
        "size_m": plan.size_x,
        "scan_start_s": plan.start_time,
        "frame_time_s": plan.frame_time,
        "scan_wall_s": wall_scan,
        "files": [str(p) for p in scanner.frames_written],
        "flags": {f.name: f.message for f in scanner.flags},
    }
    sample = cantilever.engine.samples.get(cantilever.engine.values["sample"])
    if frame is not None and sample is not None:
        image["sample"] = cantilever.engine.values["sample"]
        image["materials"] = list(sample.materials)
        image["by_material"] = fm_material_contrast(frame, sample, artefacts)
    if frame is not None:
        image["frame"] = {
            ch: {
                "median": float(np.nanmedian(frame.images["trace"][ch])),
                "p5": float(np.nanpercentile(frame.images["trace"][ch], 5)),
                "p95": float(np.nanpercentile(frame.images["trace"][ch], 95)),
            }
            for ch in ("frequency_shift", "drive", "dissipation", "amplitude")
        }
    out["image"] = image
    if not interrupted:
        out["withdraw"] = afm.withdraw()
    out["interrupted"] = interrupted
    out["simulated_s"] = instrument.t_paused
    out["wall_s"] = time.monotonic() - wall0
    out["real_time_factor"] = out["simulated_s"] / out["wall_s"]
    out["recording"] = instrument.recording_status(spin=not interrupted)
    return out


def summary_text(s: dict) -> str:
    """The FM session's summary, one fact per line, SI units with readable prefixes."""
    free, hold, ap, img = s["free"], s["hold"], s["approach"], s["image"]
    lines = [
        "FM-AFM session (PLL + amplitude controller, z loop on the frequency shift):",
        f"  free (withdrawn): resonance {free['resonance_Hz']:.4f} Hz (PLL centred there; it was "
        f"{free['pll_centre_before_Hz']:g} Hz), amplitude {free['amplitude_m'] * 1e9:.4f} nm with "
        "drive "
        f"{free['drive_N']:.4g} N: Q = k A / F = {free['quality_factor_measured']:.5g} "
        f"(set {free['quality_factor_set']:.5g})",
        f"  approach: from {ap['start_distance_m'] * 1e9:.4g} nm, engaged at "
        f"t={ap['engaged_s']:.3f} s "
        f"(df reached {s['df_setpoint_Hz']:g} Hz), z piezo {ap['engaged_z_m'] * 1e9:.4g} nm, "
        f"{ap['motor_steps']} motor steps",
        f"  hold ({hold['window_s'][0]:.3f}-{hold['window_s'][1]:.3f} s): df "
        f"{hold['df']['mean']:.3f} "
        f"+- {hold['df']['std']:.3f} Hz (setpoint {s['df_setpoint_Hz']:g}), amplitude "
        f"{hold['amplitude']['mean'] * 1e9:.4f} +- {hold['amplitude']['std'] * 1e12:.2f} pm, "
        "drive "
        f"{hold['drive']['mean']:.4g} N ({hold['drive']['mean'] / free['drive_N']:.3g} x free): "
        f"dissipation {hold['dissipation_J']:.3g} J per cycle",
    ]
    if "last_second" in s:
        last = s["last_second"]
        lines.append(
            f"  last second before Ctrl-C ({last['window_s'][0]:.3f}-{last['window_s'][1]:.3f} "
            "s): df "
            f"{last['df']['mean']:.3f} +- {last['df']['std']:.3f} Hz, amplitude "
            f"{last['amplitude']['mean'] * 1e9:.4f} +- {last['amplitude']['std'] * 1e12:.2f} pm, "
            "drive "
            f"{last['drive']['mean']:.4g} N: dissipation {last['dissipation_J']:.3g} J per cycle"
        )
    if "pixels" in img:
        lines.append(
            f"  frame: {img['pixels']} x {img['lines']} pixels over {img['size_m'] * 1e6:.3g} um "
            "at "
            f"{img['line_rate_Hz']:g} lines/s, {img['scan_wall_s']:.1f} s wall for "
            f"{img['frame_time_s']:.3g} s "
            f"simulated"
        )
    if "frame" in img:
        for ch, unit, scale in (
            ("frequency_shift", "Hz", 1.0),
            ("drive", "pN", 1e12),
            ("dissipation", "aJ", 1e18),
        ):
            v = img["frame"][ch]
            lines.append(
                f"    {ch}: median {v['median'] * scale:.4g} {unit} (5-95 %: "
                f"{v['p5'] * scale:.4g} .. "
                f"{v['p95'] * scale:.4g})"
            )
    if "by_material" in img:
        names = img["materials"]
        lines.append(
            f"  by material (trace, pixels >= 60 nm from an edge, the map's ground truth), "
            f"{names[1]} - {names[0]}:"
        )
        for ch, unit, scale in (
            ("height", "nm", 1e9),
            ("frequency_shift", "Hz", 1.0),
            ("drive", "pN", 1e12),
            ("dissipation", "aJ", 1e18),
        ):
            entry = img["by_material"].get(ch, {}).get("trace")
            if not entry or "contrast" not in entry:
                continue
            med = entry["medians"]
            rel = entry["contrast"] / abs(med[names[0]]) * 100 if med.get(names[0]) else math.nan
            lines.append(
                f"    {ch}: {names[0]} {med[names[0]] * scale:.4g}, {names[1]} "
                f"{med[names[1]] * scale:.4g} "
                f"{unit}: contrast {entry['contrast'] * scale:+.3g} {unit} ({rel:+.2g} %)"
            )
    for name, message in img.get("flags", {}).items():
        lines.append(f"  flag {name}: {message}")
    for f in img["files"]:
        lines.append(f"  wrote {f}")
    if s.get("withdraw"):
        lines.append(f"  withdrawn at t={s['withdraw']['withdrawn_s']:.3f} s")
    if s["interrupted"]:
        lines.append(f"  interrupted {s['interrupted']}")
    rec = s.get("recording")
    if rec:
        lines.append(
            f"  session: {rec['file']} ({rec['bytes'] / 1e6:.3g} MB, "
            + ("complete" if rec["complete"] else f"INCOMPLETE: {rec['error'] or rec['stopped']}")
            + ")"
        )
    lines.append(
        f"  {s['simulated_s']:.3f} s simulated in {s['wall_s']:.1f} s wall "
        f"({s['real_time_factor']:.2f} x real time)"
    )
    return "\n".join(lines)
