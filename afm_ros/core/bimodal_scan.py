"""Bimodal imaging, offline (no ROS): the two-mode cantilever scanned over a sample map, mode 1 in
amplitude modulation for the topography, mode 2 in frequency modulation (AM-FM) or driven open loop
at its free frequency (AM-AM) for the nanomechanics (docs/bimodal.md 7).

The blocks are the instrument's own cores, wired per chunk of ``chunk_time``:
:class:`~afm_ros.core.physics.modes.MultiModeSimulation` (the modes, the force model of the
material under the tip, z_base = z piezo - local height); one :class:`~afm_ros.core.lockin.LockIn`
per drive on the summed deflection (reference: that drive, as the instrument's lock-in follows its
drive); the :class:`~afm_ros.core.controller.ZController` on mode 1's amplitude (the z piezo within
+-1 um); in AM-FM the :class:`~afm_ros.core.fm.OscillationController` (PLL + amplitude controller)
on mode 2, whose excitation drives mode 2 from the next chunk on (the z command likewise: one chunk
of latency, the ROS loop's lockstep); in AM-AM mode 2 keeps its free frequency and free drive. The
tip moves along x at a constant speed over the trace (recorded) and back at ``retrace_speedup``
times that speed (not recorded), sampled at each chunk's middle.

Per pixel the lock-in and loop outputs inside the pixel's time are averaged; the maps follow per
pixel from those means with :mod:`afm_ros.core.bimodal` (Hertz contact, small A2): the virial of
mode 1 from A1 and phi1 (mode 1 driven at its free resonance), E* and the indentation from the
virial and the mean contact stiffness (AM-FM: from df2; AM-AM: from mode 2's amplitude and phase,
docs/bimodal.md 4) and A2, the loss tangent from mode 1 and from mode 2 (its drive, or its phase).
The truth beside them: each pixel's material (its E*, the Kelvin-Voigt loss tangent) and height,
from the tip-dilated map. SI units; phases in degrees in the channels.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from afm_ros.core import bimodal
from afm_ros.core.angles import phase_deg
from afm_ros.core.bimodal_loop import ENGAGE, RETRACE, TRACE, CompiledLoop
from afm_ros.core.controller import ZController
from afm_ros.core.fm import OscillationController, design_gains
from afm_ros.core.lockin import LOCKIN_SPECS, LockIn
from afm_ros.core.physics.forces import DMTForce, ViscoelasticDMTForce
from afm_ros.core.physics.materials import sample_for
from afm_ros.core.physics.modes import (
    Q_SCALING_EXPONENTS,
    Mode,
    ModeDrive,
    MultiModeSimulation,
    rectangular_modes,
)
from afm_ros.core.physics.parameters import Cantilever, ParamSpec, validate_values
from afm_ros.core.samples import resolve_sample
from afm_ros.core.samples.surface import Sample, dilate
from afm_ros.formats.chunk_layout import ChunkHeader
from afm_ros.formats.gwy import write_gwy

BIMODAL_SPECS: dict[str, ParamSpec] = {
    s.name: s
    for s in (
        ParamSpec("spring_constant", 2.0, "N/m", "mode 1's stiffness k1", 0.01, 1e3),
        ParamSpec("resonance_frequency", 70e3, "Hz", "mode 1's free resonance f1", 1e3, 2e6),
        ParamSpec("quality_factor", 150.0, "1", "mode 1's quality factor Q1", 1.0, 1e5),
        ParamSpec(
            "q_exponent", 1.0, "1", "Q_n = Q_1 (w_n / w_1)^p (1: uniform viscous damping)",
            kind=float, choices=Q_SCALING_EXPONENTS,
        ),
        ParamSpec(
            "mode2_frequency", 0.0, "Hz", "mode 2's free resonance f2, measured (a thermal or "
            "drive tune); 0: the rectangular beam's 6.27 f1", 0.0, 2e7,
        ),
        ParamSpec(
            "mode2_spring_constant", 0.0, "N/m", "mode 2's stiffness k2 at the tip, calibrated; "
            "0: the rectangular beam's 39.3 k1", 0.0, 1e5,
        ),
        ParamSpec(
            "mode2_quality_factor", 0.0, "1", "mode 2's quality factor Q2, measured; 0: Q1 (f2 / "
            "f1)^q_exponent", 0.0, 1e6,
        ),
        ParamSpec("free_amplitude", 25e-9, "m", "mode 1's free amplitude A01", 1e-9, 200e-9),
        ParamSpec(
            "setpoint_ratio", 0.8, "1", "mode 1's amplitude setpoint A1 / A01", 0.1, 0.99
        ),
        ParamSpec(
            "mode2_amplitude", 0.05e-9, "m", "mode 2's amplitude A2 (AM-FM: held by the amplitude "
            "loop; AM-AM: its free amplitude)",
            1e-12, 5e-9,
        ),
        ParamSpec(
            "mode2_control", "fm", "", "fm: AM-FM (mode 2 phase-locked at 90 deg, its amplitude "
            "held: df2 and the drive are the contrast); am: AM-AM (mode 2 driven at its free "
            "frequency with the free drive for A2: its amplitude and phase are the contrast)",
            kind=str, choices=("fm", "am"),
        ),
        ParamSpec(
            "force_model", "dmt", "", "tip-sample force (viscoelastic_dmt: the material's "
            "Kelvin-Voigt viscosity)", kind=str, choices=("dmt", "viscoelastic_dmt"),
        ),
        ParamSpec(
            "adhesion", False, "", "keep the materials' Hamaker constants (DMT); false: Hertz "
            "contact, the maps' own assumption", kind=bool,
        ),
        ParamSpec("steps_per_period", 50, "1", "RK4 steps per mode-2 period", 20, 1000, kind=int),
        ParamSpec("integrator", "rk4", "", "rk4: fixed steps; rk4_event: steps located on the "
                  "force law's switches of the summed deflection (contact onset, the "
                  "viscoelastic clip), pieces near the surface", kind=str,
                  choices=("rk4", "rk4_event")),
        ParamSpec("sample_every", 5, "1", "RK4 steps per deflection sample", 1, 50, kind=int),
        ParamSpec("chunk_time", 25e-6, "s", "simulated time per chunk (one loop update)",
                  10e-6, 10e-3),
        ParamSpec("output_rate", 40e3, "Hz", "both lock-ins' output rate", 1e3, 1e6),
        ParamSpec("time_constant_mode1", 20e-6, "s", "mode 1's lock-in time constant",
                  1e-6, 1e-2),
        ParamSpec("time_constant_mode2", 0.0, "s", "mode 2's lock-in time constant; 0: 10 us "
                  "with fm (short: the PLL's dead time), 100 us with am (no loop: rejects mode "
                  "1's 6th harmonic, which mode 2 answers 18.7 kHz from f2)", 0.0, 1e-2),
        ParamSpec("filter_order", 4, "1", "both lock-ins' low-pass order", 1, 8, kind=int),
        ParamSpec("p_gain", 0.2, "m/m", "z loop proportional gain (on mode 1's amplitude)",
                  0.0, 100.0),
        ParamSpec("i_gain", 1500.0, "1/s", "z loop integral gain", 0.0, 1e7),
        ParamSpec("pll_bandwidth", 1000.0, "Hz", "mode 2's PLL and amplitude loop crossover",
                  1.0, 1e4),
        ParamSpec("frequency_range", 20e3, "Hz", "mode 2's PLL lock range", 1.0, 1e6),
        ParamSpec("size", 3e-6, "m", "scan size (square)", 1e-8, 1e-3),
        ParamSpec("center_x", -1.0, "m", "scan centre x; negative: the map's centre",
                  -1.0, 1e-3),
        ParamSpec("center_y", -1.0, "m", "scan centre y; negative: the map's centre",
                  -1.0, 1e-3),
        ParamSpec("pixels", 24, "1", "pixels per line and lines (square)", 4, 512, kind=int),
        ParamSpec("pixel_time", 2e-3, "s", "trace time per pixel", 1e-4, 1.0),
        ParamSpec("retrace_speedup", 4.0, "1", "retrace speed / trace speed", 1.0, 100.0),
        ParamSpec("engage_time", 20e-3, "s", "feedback on at the first pixel before the "
                  "frame", 1e-3, 10.0),
        ParamSpec("temperature", 0.0, "K", "thermal force on each mode (0: none)", 0.0, 1000.0),
        ParamSpec("noise_seed", 0, "1", "seed of the thermal forces", 0, 2**62, kind=int),
        ParamSpec("edge_exclusion", 2, "1", "pixels this close to another material are left "
                  "out of the per-material statistics", 0, 64, kind=int),
    )
}  # fmt: skip

# the bimodal node's own (afm_ros.nodes.bimodal_node); the offline session takes them as flags
BIMODAL_NODE_SPECS: dict[str, ParamSpec] = {
    s.name: s
    for s in (
        ParamSpec(
            "sample", "ps_ldpe_blend", "", "sample map: a built-in (ps_ldpe_blend, tgz_grating, "
            "terraces; docs/samples.md) or a sample description file (.yaml/.json)", kind=str,
        ),
        ParamSpec(
            "output_directory", "", "", "folder for each frame's bimodal_<frame>.gwy ('' = no "
            "file); checked when set and at each frame's start, when a missing last level is "
            "created (never a chain of folders)", kind=str,
        ),
    )
}  # fmt: skip

SEGMENT_CHUNKS = 256  # chunks per compiled call (Ctrl-C is seen between calls)
AUTO_TIME_CONSTANT_2 = {"fm": 10e-6, "am": 100e-6}  # [s] time_constant_mode2 0
MIN_SAMPLES_PER_PERIOD = 4  # deflection samples per mode-2 period
CHANNELS = {  # name -> unit, in the order the files list them
    "height": "m",
    "amplitude_1": "m",
    "phase_1": "deg",
    "amplitude_2": "m",
    "phase_2": "deg",
    "frequency_shift_2": "Hz",
    "drive_2": "N",
    "modulus": "Pa",
    "indentation": "m",
    "loss_tangent_1": "",
    "loss_tangent_2": "",
    "true_modulus": "Pa",
    "true_loss_tangent_2": "",
    "true_height": "m",
}


@dataclass(frozen=True)
class MaterialRow:
    """Per material, medians over its pixels away from edges: E* recovered and true [Pa], its
    bias (recovered / true - 1), df2 [Hz], indentation [m], topography [m], loss tangents (mode
    1, mode 2, the contact's own at f2), mode 2's amplitude [m] and phase [deg]."""

    material: str
    pixels: int
    true_modulus: float
    modulus: float
    bias: float
    frequency_shift_2: float
    indentation: float
    height: float
    true_height: float
    loss_tangent_1: float
    loss_tangent_2: float
    true_loss_tangent_2: float
    amplitude_2: float
    phase_2: float


@dataclass
class BimodalFrame:
    """A bimodal frame: ``channels`` name -> 2D array [rows = lines, cols = pixels] in the units
    of :data:`CHANNELS`, ``material`` index per pixel and ``materials`` names, the per-material
    table, the scan's extent [m], the modes and the simulated time [s]."""

    channels: dict
    material: np.ndarray
    materials: tuple
    rows: list
    size: float
    origin: tuple
    modes: list
    simulated_time: float
    lines_done: int
    values: dict = field(default_factory=dict)


def check_values(values: dict | None) -> dict:
    """``values`` (:data:`BIMODAL_SPECS`; missing: defaults) validated, each against its range
    and the ones that depend on each other together; ValueError names the field and what is
    allowed."""
    v = validate_values(BIMODAL_SPECS, dict(values or {}), "a bimodal session")
    if v["steps_per_period"] < MIN_SAMPLES_PER_PERIOD * v["sample_every"]:
        raise ValueError(
            f"sample_every={v['sample_every']} with steps_per_period={v['steps_per_period']}: "
            f"allowed up to steps_per_period / {MIN_SAMPLES_PER_PERIOD} (at least "
            f"{MIN_SAMPLES_PER_PERIOD} deflection samples per mode-2 period, or the lock-ins "
            "see an alias of mode 2)"
        )
    if 0.0 < v["mode2_frequency"] <= v["resonance_frequency"]:
        raise ValueError(
            f"mode2_frequency={v['mode2_frequency']!r} Hz: allowed 0 (the beam's) or above mode "
            f"1's resonance_frequency={v['resonance_frequency']!r} Hz"
        )
    low = LOCKIN_SPECS["time_constant"].low
    for name in ("time_constant_mode1", "time_constant_mode2"):
        if 0.0 < v[name] < low:
            raise ValueError(f"{name}={v[name]!r} s is out of range; allowed 0 or >= {low:g} s")
    return v


def second_mode(beam: list[Mode], values: dict) -> list[Mode]:
    """The beam's two modes with mode 2's frequency, stiffness and Q replaced by the values given
    (``mode2_*`` not 0); with measured f2 and no Q2, Q2 = Q1 (f2 / f1)^q_exponent."""
    m1, m2 = beam
    f2 = values["mode2_frequency"] or m2.resonance_frequency
    q2 = (
        values["mode2_quality_factor"]
        or m1.quality_factor * (f2 / m1.resonance_frequency) ** values["q_exponent"]
    )
    k2 = values["mode2_spring_constant"] or m2.spring_constant
    if (f2, k2, q2) == (m2.resonance_frequency, m2.spring_constant, m2.quality_factor):
        return [m1, m2]  # the beam's own, bit for bit
    return [m1, Mode(f2, k2, q2)]


def check_with_sample(values: dict) -> dict:
    """The session's values (missing: defaults) and ``sample`` (a built-in map or a description
    file; the node's default if missing) checked together: what the node and the client take;
    ValueError naming the field."""
    session = check_values({k: v for k, v in values.items() if k in BIMODAL_SPECS})
    sample = values.get("sample", BIMODAL_NODE_SPECS["sample"].default)
    if resolve_sample(sample) is None:
        raise ValueError(f"sample={sample!r}: a sample map is needed (not 'flat')")
    return {**session, "sample": sample}


def scan_of(values: dict, compiled: bool = True) -> "BimodalScan":
    """The scan of values :func:`check_with_sample` accepted (the session's and ``sample``)."""
    return BimodalScan(
        resolve_sample(values["sample"]), {k: values[k] for k in BIMODAL_SPECS}, compiled
    )


def rows_json(rows: list) -> list[dict]:
    """The per-material table as JSON-able dicts (:class:`MaterialRow` fields; NaN as None): what
    the bimodal node publishes and a client frame keeps."""
    return [
        {k: (None if isinstance(v, float) and not math.isfinite(v) else v)
         for k, v in asdict(r).items()}
        for r in rows
    ]  # fmt: skip


def pixel_centres(origin: tuple, size: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """x and y [m] of the pixel centres of an n x n frame of ``size`` [m] from ``origin`` (row 0 =
    the first line)."""
    centres = (np.arange(n) + 0.5) / n * size
    return origin[0] + centres, origin[1] + centres


def write_gwy_frame(path, frame: BimodalFrame) -> Path:
    """``frame`` as a Gwyddion file: every channel of :data:`CHANNELS` (an interrupted frame: its
    lines done), pixels without a value masked, the session's values as metadata."""
    x0, y0 = frame.origin
    done = frame.lines_done
    chans = {name: (frame.channels[name][:done], unit) for name, unit in CHANNELS.items()}
    meta = {k: v if isinstance(v, (int, float)) else str(v) for k, v in frame.values.items()}
    meta["lines_done"] = done
    height = frame.size * done / frame.channels["height"].shape[0]
    write_gwy(path, chans, frame.size, height, x0, y0, metadata=meta, invalid="mask")
    return Path(path)


def _force(name: str, values: dict):
    overrides = {} if values["adhesion"] else {"hamaker_constant": 0.0}
    sample, viscosity, _ = sample_for(name, **overrides)
    if values["force_model"] == "viscoelastic_dmt":
        return ViscoelasticDMTForce(sample, viscosity), viscosity
    return DMTForce(sample), 0.0


class BimodalScan:
    """One bimodal frame (AM-FM or AM-AM) over ``sample`` (a :class:`Sample`) with ``values``
    (:data:`BIMODAL_SPECS`; missing: defaults). :meth:`run` scans; each call of
    :meth:`line` scans one more line."""

    def __init__(self, sample: Sample, values: dict | None = None, compiled: bool = True):
        """``compiled``: chunks run in :mod:`afm_ros.core.bimodal_loop` (the same frame bit for
        bit, 2.8x faster at the defaults); false: one :meth:`chunk` call (Python) each."""
        v = check_values(values)
        self.sample = sample
        cx = 0.5 * sample.size_x if v["center_x"] < 0 else v["center_x"]
        cy = 0.5 * sample.size_y if v["center_y"] < 0 else v["center_y"]
        self.values = v
        lever = Cantilever(
            spring_constant=v["spring_constant"],
            resonance_frequency=v["resonance_frequency"],
            quality_factor=v["quality_factor"],
        )
        self.modes = m1, m2 = second_mode(rectangular_modes(lever, 2, v["q_exponent"]), v)
        self.dt = 1.0 / (m2.resonance_frequency * v["steps_per_period"])
        every = v["sample_every"]
        self.chunk_steps = every * max(1, round(v["chunk_time"] / (self.dt * every)))
        self.a01, self.a2 = v["free_amplitude"], v["mode2_amplitude"]
        self.free_drive_1 = m1.spring_constant * self.a01 / m1.quality_factor
        self.free_drive_2 = m2.spring_constant * self.a2 / m2.quality_factor
        self.forces = {}
        self.truth = {}
        radii = set()
        for name in sample.materials:
            force, viscosity = _force(name, v)
            e_star = force.sample.effective_modulus
            tan2 = bimodal.kelvin_voigt_loss_tangent(m2.resonance_frequency, viscosity, e_star)
            self.forces[name], self.truth[name] = force, (e_star, tan2)
            radii.add(force.sample.tip_radius)
        (self.tip_radius,) = radii  # one tip: every material's sample takes the DMT default
        self.map = dilate(sample, self.tip_radius)
        self.materials = sample.materials
        self.size, self.n = v["size"], v["pixels"]
        self.origin = (cx - 0.5 * self.size, cy - 0.5 * self.size)
        drives = [
            ModeDrive(0, m1.resonance_frequency, self.free_drive_1),
            ModeDrive(1, m2.resonance_frequency, self.free_drive_2),
        ]
        h0, mat0 = self.map.surface(*self._xy(0.0, 0))
        self.z_piezo = h0 + 1.2 * self.a01  # out of contact: the z loop engages from here
        self.sim = MultiModeSimulation(
            self.modes, drives, self.forces[mat0], self.z_piezo - h0, self.dt
        )
        self.sim.set_thermal(v["temperature"], v["noise_seed"])
        self.sim.set_integrator(v["integrator"])
        # start on the free steady state (driven at resonance: z = A sin(w t))
        self.sim.v[:] = [self.a01 * m1.omega, self.a2 * m2.omega]
        lockin = dict(output_rate=v["output_rate"], filter_order=v["filter_order"])
        self.time_constant_2 = v["time_constant_mode2"] or AUTO_TIME_CONSTANT_2[v["mode2_control"]]
        self.lockins = [
            LockIn(time_constant=v["time_constant_mode1"], **lockin),
            LockIn(time_constant=self.time_constant_2, **lockin),
        ]
        self.z = ZController(
            self.z_piezo,
            setpoint=v["setpoint_ratio"] * self.a01,
            p_gain=v["p_gain"],
            i_gain=v["i_gain"],
            z_min=-1e-6,
            z_max=1e-6,
        )
        self.pll = OscillationController(
            center_frequency=m2.resonance_frequency,
            amplitude_setpoint=self.a2,
            drive_initial=self.free_drive_2,
            drive_max=1e3 * self.free_drive_2,
            frequency_range=v["frequency_range"],
            pll_enabled=v["mode2_control"] == "fm",
            amplitude_enabled=v["mode2_control"] == "fm",
            **design_gains(v["pll_bandwidth"], m2.spring_constant, m2.resonance_frequency),
        )
        self.index = 0  # deflection samples so far
        self._loop = CompiledLoop(self) if compiled else None
        self._truth = None
        self.sums = np.zeros((7, self.n, self.n))  # CHANNELS' first seven, summed per pixel
        self.counts = np.zeros((self.n, self.n))
        self.lines_done = 0

    def _xy(self, fraction: float, line: int) -> tuple[float, float]:
        """Tip position [m] at ``fraction`` (0-1) along the trace of ``line``."""
        x0, y0 = self.origin
        return x0 + fraction * self.size, y0 + (line + 0.5) / self.n * self.size

    def chunk(self, x: float, y: float, pixel: tuple | None) -> None:
        """Integrate one chunk with the tip at (x, y) [m]; feed the loops; add the outputs to
        ``pixel`` (row, col) unless None."""
        sim, steps, every = self.sim, self.chunk_steps, self.values["sample_every"]
        h, mat = self.map.surface(x, y)
        sim.set_contact(self.forces[mat], self.z_piezo - h)
        t1 = (sim.steps + every) * self.dt  # time of the chunk's first sample
        z = sim.advance(steps, every, energies=False)  # the maps use no energies
        defl = z.sum(axis=1)
        interval = every * self.dt
        outs = []
        for j, lockin in enumerate(self.lockins):
            f = sim.drive_frequency(j)
            header = ChunkHeader(self.index, t1, interval, sim.drive_phase(j, t1), f, 0.0)
            outs.append(lockin.process(header, defl))
        self.index += defl.shape[0]
        o1, o2 = outs
        # one or two outputs per chunk: Python floats (numpy's per-call cost is the larger part)
        x1, y1, x2, y2 = o1.x.tolist(), o1.y.tolist(), o2.x.tolist(), o2.y.tolist()
        a1 = [math.hypot(a, b) for a, b in zip(x1, y1)]
        for t, a in zip(o1.t.tolist(), a1):
            self.z_piezo = self.z.update(a, t)
        for t, a, b in zip(o2.t.tolist(), x2, y2):
            self.pll.update(t, a, b)
        sim.set_drive(1, self.pll.frequency, self.pll.drive)
        if pixel is None or not a1 or not x2:
            return
        i, j = pixel
        n1, n2 = len(a1), len(x2)
        row = (
            self.z_piezo,
            sum(a1) / n1,
            sum(phase_deg(a, b) for a, b in zip(x1, y1)) / n1,
            sum(math.hypot(a, b) for a, b in zip(x2, y2)) / n2,
            sum(phase_deg(a, b) for a, b in zip(x2, y2)) / n2,
            self.pll.df,
            self.pll.drive,
        )
        self.sums[:, i, j] += row
        self.counts[i, j] += 1

    def _chunks(self) -> tuple[int, int, int]:
        """Chunks of the engage, of a line's trace and of its retrace."""
        v, chunk = self.values, self.chunk_steps * self.dt
        trace = max(1, round(self.n * v["pixel_time"] / chunk))
        return round(v["engage_time"] / chunk), trace, max(1, round(trace / v["retrace_speedup"]))

    @property
    def planned_time(self) -> float:
        """Simulated time [s] of the whole frame: the engage and every line's trace and
        retrace."""
        engage, trace, back = self._chunks()
        return (engage + self.n * (trace + back)) * self.chunk_steps * self.dt

    def engage(self) -> None:
        """The z loop on at the first pixel for ``engage_time``."""
        count = self._chunks()[0]
        if self._loop is not None:
            self._segments(ENGAGE, 0, count)
            return
        x, y = self._xy(0.0, 0)
        for _ in range(count):
            self.chunk(x, y, None)

    def line(self) -> None:
        """Trace (recorded) and retrace of the next line."""
        i = self.lines_done
        _, trace, back = self._chunks()
        if self._loop is not None:
            self._segments(TRACE, i, trace)
            self._segments(RETRACE, i, back)
            self.lines_done += 1
            return
        for c in range(trace):
            frac = (c + 0.5) / trace
            self.chunk(*self._xy(frac, i), (i, min(self.n - 1, int(frac * self.n))))
        nxt = min(i + 1, self.n - 1)  # the retrace also moves to the next line
        for c in range(back):
            frac = 1.0 - (c + 0.5) / back
            x, y = self._xy(frac, i)
            _, y_next = self._xy(frac, nxt)
            self.chunk(x, y + (c + 0.5) / back * (y_next - y), None)
        self.lines_done += 1

    @property
    def compiled(self) -> bool:
        """Chunks run compiled (:mod:`afm_ros.core.bimodal_loop`) or one Python call each; may
        be switched between lines (the same frame either way)."""
        return self._loop is not None

    @compiled.setter
    def compiled(self, on: bool) -> None:
        self._loop = CompiledLoop(self) if on else None

    def warm_up(self) -> None:
        """Load (or compile, ~2 s the first time) the compiled loop now rather than at the first
        line: one chunk of a scratch copy of this session."""
        if self._loop is not None:
            BimodalScan(self.sample, self.values).segment(ENGAGE, 0, 0, 1, 1)

    def _segments(self, kind: int, line: int, count: int) -> None:
        for c0 in range(0, count, SEGMENT_CHUNKS):
            self.segment(kind, line, c0, min(count, c0 + SEGMENT_CHUNKS), count)

    def segment(self, kind: int, line: int, c0: int, c1: int, count: int) -> None:
        """Chunks ``c0`` to ``c1`` - 1 of the ``count`` of a run (bimodal_loop ENGAGE, TRACE or
        RETRACE of ``line``) in one compiled call: what :meth:`chunk` does for each, bit for
        bit."""
        self._loop.run(kind, line, c0, c1, count)

    def run(self, progress=None) -> BimodalFrame:
        """Engage and scan every line (``progress(lines_done, n)`` after each); Ctrl-C keeps the
        lines done (the frame says how many; the line under way is dropped)."""
        try:
            if self.sim.steps == 0:
                self.engage()
            while self.lines_done < self.n:
                self.line()
                if progress is not None:
                    progress(self.lines_done, self.n)
        except KeyboardInterrupt:
            self.sums[:, self.lines_done :] = 0.0
            self.counts[self.lines_done :] = 0.0
        return self.frame()

    def frame(self) -> BimodalFrame:
        """The channels, maps and per-material table of the lines scanned so far."""
        n = self.n
        with np.errstate(invalid="ignore", divide="ignore"):
            mean = self.sums / self.counts
        mean[:, self.counts == 0] = math.nan
        ch = dict(zip(list(CHANNELS)[:7], mean))
        material, true_h = self._truth_maps()
        if self.values["mode2_control"] == "am":  # no PLL: no frequency shift was measured
            ch["frequency_shift_2"] = np.full((n, n), math.nan)
        self._maps(ch, material)
        ch["true_height"] = true_h
        rows = self._table(ch, material)
        chans = {name: ch[name] for name in CHANNELS}
        return BimodalFrame(
            chans, material, self.materials, rows, self.size, self.origin, self.modes,
            self.sim.t, self.lines_done, dict(self.values),
        )  # fmt: skip

    def _truth_maps(self) -> tuple[np.ndarray, np.ndarray]:
        """Each pixel's material index and true height [m] at its centre (made once)."""
        if self._truth is None:
            n = self.n
            material = np.zeros((n, n), dtype=np.int64)
            true_h = np.zeros((n, n))
            for i in range(n):
                for j in range(n):
                    h, mat = self.map.surface(*self._xy((j + 0.5) / n, i))
                    material[i, j], true_h[i, j] = self.materials.index(mat), h
            self._truth = material, true_h
        material, true_h = self._truth
        return material.copy(), true_h.copy()

    def _maps(self, ch: dict, material: np.ndarray) -> None:
        m1, m2 = self.modes
        f2, k2 = m2.resonance_frequency, m2.spring_constant
        shape = material.shape
        for name in ("modulus", "indentation", "loss_tangent_1", "loss_tangent_2"):
            ch[name] = np.full(shape, math.nan)
        ch["true_modulus"] = np.zeros(shape)
        ch["true_loss_tangent_2"] = np.zeros(shape)
        for (i, j), k in np.ndenumerate(material):
            e_true, tan_true = self.truth[self.materials[k]]
            ch["true_modulus"][i, j], ch["true_loss_tangent_2"][i, j] = e_true, tan_true
            a1, phi1 = ch["amplitude_1"][i, j], math.radians(ch["phase_1"][i, j])
            df2, drive2 = ch["frequency_shift_2"][i, j], ch["drive_2"][i, j]
            if not math.isfinite(a1):
                continue
            ch["loss_tangent_1"][i, j] = bimodal.loss_tangent_mode1(self.a01, a1, phi1)
            virial = bimodal.virial_at_resonance(
                m1.spring_constant, m1.quality_factor, self.a01, a1, phi1
            )
            a2 = ch["amplitude_2"][i, j]
            try:
                if self.values["mode2_control"] == "am":  # <k_ts> from the phase (section 4)
                    q2, phi2 = m2.quality_factor, math.radians(ch["phase_2"][i, j])
                    k_bar = bimodal.mean_stiffness_am_am(q2, k2, a2, self.a2, phi2)
                    df2 = f2 * k_bar / (2.0 * k2)  # the shift a PLL would read: 3.2
                    tan2 = bimodal.loss_tangent_am_am(q2, k2, a2, self.a2, phi2)
                else:
                    tan2 = bimodal.loss_tangent_mode2(
                        f2, m2.quality_factor, df2, drive2 / self.free_drive_2
                    )
                est = bimodal.hertz_from_observables(a1, virial, df2, f2, k2, self.tip_radius, a2)
            except ValueError:  # not a repulsive contact here: no Hertz estimate
                continue
            ch["modulus"][i, j], ch["indentation"][i, j] = est.effective_modulus, est.indentation
            ch["loss_tangent_2"][i, j] = tan2

    def _table(self, ch: dict, material: np.ndarray) -> list[MaterialRow]:
        keep = interior(material, self.values["edge_exclusion"])
        keep &= np.isfinite(ch["height"])
        rows = []
        for k, name in enumerate(self.materials):
            sel = keep & (material == k)
            if not sel.any():
                continue

            def med(key, sel=sel):
                vals = ch[key][sel]
                vals = vals[np.isfinite(vals)]
                return float(np.median(vals)) if vals.size else math.nan

            e_true, tan_true = self.truth[name]
            e = med("modulus")
            rows.append(
                MaterialRow(
                    name, int(sel.sum()), e_true, e, e / e_true - 1.0, med("frequency_shift_2"),
                    med("indentation"), med("height"), med("true_height"),
                    med("loss_tangent_1"), med("loss_tangent_2"), tan_true,
                    med("amplitude_2"), med("phase_2"),
                )
            )  # fmt: skip
        return rows


def interior(material: np.ndarray, margin: int) -> np.ndarray:
    """Pixels with no other material within ``margin`` pixels (a square neighbourhood; the
    frame's border counts as no other material)."""
    rows, cols = material.shape
    keep = np.ones(material.shape, dtype=bool)
    for di in range(-margin, margin + 1):
        for dj in range(-margin, margin + 1):
            shifted = np.full(material.shape, -1)
            i0, i1 = max(0, di), min(rows, rows + di)
            j0, j1 = max(0, dj), min(cols, cols + dj)
            shifted[i0 - di : i1 - di, j0 - dj : j1 - dj] = material[i0:i1, j0:j1]
            keep &= (shifted == -1) | (shifted == material)
    return keep
