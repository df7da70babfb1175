"""One API for scripts and agents, over ROS against running nodes or in-process without ROS.

::

    from afm_ros.client import Microscope

    with Microscope.local() as afm:            # or Microscope.connect(namespace="/afm1")
        afm.tune()                             # drive at the resonance, free amplitude, phase zero
        afm.approach()                         # coarse motor + z piezo until the setpoint: engaged
        afm.set_scan(center=(5e-6, 5e-6), size=(2e-6, 2e-6), pixels=64, lines=64, line_rate=2.0)
        frame = afm.scan()                     # xarray.Dataset: height, phase, ... x trace/retrace
        curve = afm.spectroscopy(x=5e-6, y=5e-6)
        afm.withdraw()

Every verb blocks until done (simulated time advances as long as it needs) and has an
``*_async`` form returning a :class:`concurrent.futures.Future` (one instrument: verbs run one
after the other in a worker thread). Units are SI everywhere (m, s, Hz, deg, J, N). Errors are
typed: :class:`Refused` carries the node's own reason (a setpoint out of range, a scan while not
engaged: :class:`NotEngaged`), :class:`WorkflowFailed` an approach that failed and why,
:class:`~afm_ros.client.ros_link.NoAnswer` a timeout naming what did not answer. Nothing waits
forever: every wait has a timeout, and the simulated time must keep advancing.
"""

from __future__ import annotations

import math
import numbers
import os
import warnings
from concurrent.futures import Future, ThreadPoolExecutor

from afm_ros.client.backend import Backend
from afm_ros.client.errors import BadArgument, LongWork
from afm_ros.client.frames import save_frame
from afm_ros.client.local_backend import LocalBackend
from afm_ros.client.results import (
    ApproachResult,
    Feedback,
    ScanSettings,
    Signals,
    StageState,
    Trace,
    Truth,
    TuneResult,
    WithdrawResult,
)
from afm_ros.core.approach import APPROACH_SPECS, approach_time
from afm_ros.core.spectroscopy import SPECTROSCOPY_SPECS

LONG_WALL_S = 60.0  # [s] wall: a verb expected to take longer says so first (LongWork)
ASSUMED_WALL_PER_SIMULATED = 1.0  # [s/s] before the instrument has run: real time


def _number(
    name: str,
    value,
    low: float = -math.inf,
    high: float = math.inf,
    low_open: bool = False,
    unit: str = "",
) -> float:
    """``value`` as a finite float in the range; BadArgument naming ``name`` otherwise."""
    lb, unit_text = "(" if low_open or low == -math.inf else "[", f" {unit}" if unit else ""
    allowed = f"{lb}{low:g}, {high:g}]{unit_text}"
    if isinstance(value, bool) or not isinstance(value, numbers.Real):
        raise BadArgument(f"{name}={value!r} is not a number; allowed {allowed}")
    v = float(value)
    if not math.isfinite(v) or v < low or v > high or (low_open and v == low):
        raise BadArgument(f"{name}={value!r}{unit_text} is out of range; allowed {allowed}")
    return v


def _pair(name: str, value, unit: str = "m") -> tuple[float, float]:
    """``value`` as two finite floats (x, y); BadArgument naming ``name`` otherwise."""
    if isinstance(value, (str, bytes)) or not hasattr(value, "__len__") or len(value) != 2:
        raise BadArgument(
            f"{name}={value!r} must be a pair (x, y) [{unit}], e.g. {name}=(2e-6, 2e-6)"
        )
    return _number(f"{name}[0]", value[0], unit=unit), _number(f"{name}[1]", value[1], unit=unit)


def _integer(name: str, value) -> int:
    """``value`` as an int (its range is the node's to check); BadArgument naming ``name``
    otherwise."""
    if isinstance(value, bool) or not isinstance(value, numbers.Integral):
        raise BadArgument(f"{name}={value!r} is not an integer")
    return int(value)


def _duration_text(seconds: float) -> str:
    for unit, size in (("years", 3.156e7), ("days", 86400.0), ("h", 3600.0), ("min", 60.0)):
        if seconds >= size:
            return f"{seconds / size:.3g} {unit}"
    return f"{seconds:.3g} s"


class Microscope:
    """The instrument as a program sees it; build it with :meth:`connect` or :meth:`local`.

    Every verb checks its arguments before anything is sent (:class:`BadArgument`), says before it
    starts when its work will take more than a minute (:class:`LongWork`, a warning with the
    estimate), and when Ctrl-C interrupts it leaves the instrument where the next verb works: an
    approach, withdraw or spectroscopy stops where it is (the z stage ``stopped``, or engaged again
    after a spectroscopy), a scan stops (its tip parked), a tune restores the drive."""

    def __init__(self, backend: Backend):
        self._backend = backend
        self._pool = ThreadPoolExecutor(max_workers=1, thread_name_prefix="afm-client")

    @classmethod
    def connect(
        cls, namespace: str = "/", timeout: float = 10.0, hold: bool = True
    ) -> "Microscope":
        """The instrument running as ROS nodes in ``namespace`` (cantilever, lockin, z_controller,
        scanner). ``timeout`` [s]: the longest any node may take to be discovered or to answer.
        ``hold``: the client pauses the simulation between verbs (the cantilever's run_until) and
        runs it in lockstep, so a script gives the same results every time; False: it runs
        freely."""
        from afm_ros.client.ros_backend import RosBackend  # noqa: PLC0415 - rclpy only for this backend

        if not isinstance(namespace, str):
            raise BadArgument(f"namespace={namespace!r} must be a string, e.g. '/afm1'")
        return cls(
            RosBackend(
                namespace, _number("timeout", timeout, 0.0, 1e6, low_open=True, unit="s"), hold
            )
        )

    @classmethod
    def local(
        cls,
        sample: str = "ps_ldpe_blend",
        force_model: str = "viscoelastic_dmt",
        ideal: bool = False,
        withdrawn: bool = True,
        cantilever: dict | None = None,
        lockin: dict | None = None,
        z_controller: dict | None = None,
        scanner: dict | None = None,
        approach: dict | None = None,
        tip: dict | None = None,
    ) -> "Microscope":
        """The same blocks wired in this process, no ROS
        (:class:`afm_ros.core.wired.WiredInstrument`).

        Defaults are the nodes' (a real instrument: room-temperature noise, the scanner's
        imperfections, a wearing tip, a 3 um z piezo range), with the tip ``withdrawn`` 5 um above
        ``sample`` (a built-in name, a description file or a .gwy map); ``ideal``: no noise, no
        imperfections, no wear. The dicts override parameters by name (the nodes' tables)."""
        for name, value in (
            ("cantilever", cantilever),
            ("lockin", lockin),
            ("z_controller", z_controller),
            ("scanner", scanner),
            ("approach", approach),
            ("tip", tip),
        ):
            if value is not None and not isinstance(value, dict):
                raise BadArgument(f"{name}={value!r} must be a dict of parameter values by name")
        if not isinstance(sample, (str, os.PathLike)):
            raise BadArgument(f"sample={sample!r} must be a name or a file path")
        return cls(
            LocalBackend(
                os.fspath(sample),
                force_model,
                ideal,
                withdrawn,
                cantilever or {},
                lockin or {},
                z_controller or {},
                scanner or {},
                approach or {},
                tip or {},
            )
        )

    @classmethod
    def in_process(cls, **options) -> "Microscope":
        """The instrument's nodes (cantilever, lock-in, z controller, and as asked the PLL,
        scanner, live view and recorder) run in this process on one executor, the simulation
        stepped with the cantilever's run_until pause (what ``afm_instrument`` runs; rclpy must be
        initialised). ``options`` are :class:`afm_ros.client.nodes_backend.NodesBackend`'s;
        :attr:`session` is that backend (its monitor's statistics, the recording, the frame behind
        a scan)."""
        from afm_ros.client.nodes_backend import NodesBackend  # noqa: PLC0415 - rclpy only for this backend

        return cls(NodesBackend(**options))

    @property
    def session(self):
        """The in-process nodes' backend of :meth:`in_process` (None for the other backends)."""
        return self._backend if hasattr(self._backend, "monitor") else None

    # --- life cycle
    # ---------------------------------------------------------------------------------
    def close(self) -> None:
        self._pool.shutdown(wait=True)
        self._backend.close()

    def __enter__(self) -> "Microscope":
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def _submit(self, fn, *args, **kwargs) -> Future:
        return self._pool.submit(fn, *args, **kwargs)

    def _run(self, verb: str, *args):
        """The backend's ``verb``; on Ctrl-C the backend puts the instrument where the next verb
        works (its ``recover``), then the KeyboardInterrupt goes on."""
        try:
            return getattr(self._backend, verb)(*args)
        except KeyboardInterrupt:
            self._backend.recover(verb)
            raise

    def _announce(self, what: str, simulated_s: float) -> None:
        """A :class:`LongWork` warning if ``simulated_s`` of simulated time will take over a
        minute."""
        per = self._backend.wall_per_simulated_second()
        measured = math.isfinite(per) and per > 0
        wall = simulated_s * (per if measured else ASSUMED_WALL_PER_SIMULATED)
        if wall > LONG_WALL_S:
            basis = (
                f"the {per:.3g} s of wall time per simulated second measured so far"
                if measured
                else "real time (nothing measured yet)"
            )
            warnings.warn(
                LongWork(
                    f"{what} simulates {simulated_s:.4g} s: about {_duration_text(wall)} of wall "
                    "time "
                    f"at {basis}; Ctrl-C stops it and leaves the instrument usable"
                ),
                stacklevel=3,
            )

    # --- settings
    # -------------------------------------------------------------------------------------
    def set_scan(
        self,
        center: tuple[float, float] | None = None,
        top_left: tuple[float, float] | None = None,
        size: tuple[float, float] | None = None,
        pixels: int | None = None,
        lines: int | None = None,
        line_rate: float | None = None,
        slow_scan_direction: str | None = None,
        angle: float | None = None,
    ) -> ScanSettings:
        """The next scan's region and raster: ``center`` or ``top_left`` (x, y) [m] in sample
        coordinates (the image's top-left corner: its first pixel of the highest row), ``size`` (x,
        y) [m], ``angle`` [deg] (the fast axis turned counterclockwise from the sample's x axis,
        about the centre), ``pixels`` per line, ``lines``, ``line_rate`` [lines/s],
        ``slow_scan_direction`` ('up' or 'down'). All or nothing: a refused value
        (:class:`Refused`, the node's reason) changes none. Returns the scan settings."""
        if center is not None and top_left is not None:
            raise BadArgument("give center or top_left, not both")
        values: dict = {}
        if size is not None:
            values["scan_size_x"], values["scan_size_y"] = _pair("size", size)
        if angle is not None:
            values["scan_angle"] = _number("angle", angle, unit="deg")
        if center is not None:
            values["scan_center_x"], values["scan_center_y"] = _pair("center", center)
        if top_left is not None:
            corner = _pair("top_left", top_left)
            current = self.scan_settings()
            sx = values.get("scan_size_x", current.get("scan_size_x"))
            sy = values.get("scan_size_y", current.get("scan_size_y"))
            turn = math.radians(values.get("scan_angle", current.get("scan_angle", 0.0)))
            u, v = (
                0.5 * sx,
                -0.5 * sy,
            )  # the centre from the top-left corner, in the scan's own frame
            values["scan_center_x"] = corner[0] + u * math.cos(turn) - v * math.sin(turn)
            values["scan_center_y"] = corner[1] + u * math.sin(turn) + v * math.cos(turn)
        for name, value in (("pixels", pixels), ("lines", lines)):
            if value is not None:
                values["pixels_per_line" if name == "pixels" else name] = _integer(name, value)
        if line_rate is not None:
            values["line_rate"] = _number("line_rate", line_rate, unit="lines/s")
        if slow_scan_direction is not None:
            if slow_scan_direction not in ("up", "down"):
                raise BadArgument(
                    f"slow_scan_direction={slow_scan_direction!r}; allowed 'up' or 'down'"
                )
            values["slow_scan_direction"] = slow_scan_direction
        self._backend.set_values("scanner", values)
        return self.scan_settings()

    def scan_settings(self) -> ScanSettings:
        """The scan's parameters (the scanner node's names, SI units)."""
        return self._backend.scan_settings()

    def set_feedback(
        self,
        setpoint: float | None = None,
        p_gain: float | None = None,
        i_gain: float | None = None,
    ) -> Feedback:
        """The z loop's ``setpoint`` [m] (amplitude), ``p_gain`` [1] and ``i_gain`` [1/s]; all or
        nothing (:class:`Refused` with the node's reason). Returns the feedback settings."""
        values = {
            k: _number(k, v)
            for k, v in (("setpoint", setpoint), ("p_gain", p_gain), ("i_gain", i_gain))
            if v is not None
        }
        self._backend.set_values("z_controller", values)
        return self.feedback()

    def feedback(self) -> Feedback:
        """setpoint [m], p_gain [1], i_gain [1/s], z_min, z_max [m] of the z loop."""
        return self._backend.feedback()

    def set(self, node: str, **values) -> None:
        """Any parameters of one node by name (the README's tables), all or nothing."""
        if not isinstance(node, str):
            raise BadArgument(
                f"node={node!r} must be a node name (cantilever, lockin, z_controller, scanner)"
            )
        self._backend.set_values(node, values)

    def get(self, node: str, *names: str) -> dict:
        """Parameter values of one node by name."""
        if not isinstance(node, str) or not all(isinstance(n, str) for n in names):
            raise BadArgument(f"get(node, *names) takes names as strings; got {node!r}, {names!r}")
        return self._backend.get_values(node, list(names))

    # --- actions
    # ----------------------------------------------------------------------------------------
    def tune(self) -> TuneResult:
        """Sweep the drive around the resonance with the tip free, fit f0 [Hz] and Q, and set the
        working point (drive frequency, drive for the free amplitude, phase zero). Refused while
        engaged (withdraw first)."""
        return self._run("tune")

    def approach(self) -> ApproachResult:
        """Coarse approach and engage: the motor and z piezo bring the tip down until the amplitude
        falls to the setpoint, then the z loop regulates. Returns the approach's numbers (cycles,
        motor steps, engaged_s [s], engaged_z_m [m]); :class:`WorkflowFailed` with the reason."""
        try:
            v = self.get("z_controller", "z_min", "z_max", *APPROACH_SPECS)
            estimate = approach_time({k: v[k] for k in APPROACH_SPECS}, v["z_min"], v["z_max"])
        except (ValueError, KeyError):
            estimate = 0.0  # a bad value: the approach is refused with the node's reason
        self._announce("approach()", estimate)
        return self._run("approach")

    def engage(self) -> ApproachResult | StageState:
        """Engaged on the surface: approaches if the z stage is not engaged already."""
        state = self.state()["stage"]
        return {"state": state} if state == "engaged" else self.approach()

    def withdraw(self) -> WithdrawResult:
        """Feedback off, z piezo retracted, the motor backs off: the tip is safe to move."""
        return self._run("withdraw")

    def scan(self, progress=None, save=None):
        """Scan one frame with the scan settings from now; returns it as an xarray Dataset
        (:mod:`afm_ros.client.frames`). ``progress(lines_done, lines)`` is called as lines finish;
        ``save``: also write it as a Gwyddion file there (the values the .gwy holds are the
        Dataset's). :class:`NotEngaged` if the tip is not on the surface."""
        if progress is not None and not callable(progress):
            raise BadArgument(
                f"progress={progress!r} must be a function progress(lines_done, lines) or None"
            )
        if save is not None and not isinstance(save, (str, os.PathLike)):
            raise BadArgument(f"save={save!r} must be a file path or None")
        if self.state()["stage"] == "engaged":  # (else refused at once: nothing long to announce)
            settings = self.scan_settings()
            self._announce(
                f"scan() of {settings['lines']} lines at {settings['line_rate']:g} lines/s",
                settings["lines"] / settings["line_rate"],
            )
        frame = self._run("scan", progress)
        if save is not None:
            frame.attrs["file"] = str(save_frame(frame, save)[0])
        return frame

    def move_tip(self, x: float, y: float) -> None:
        """Move the tip to (x, y) [m] (sample coordinates) and hold it there (not while
        scanning)."""
        self._backend.move_tip(_number("x", x, unit="m"), _number("y", y, unit="m"))

    def spectroscopy(self, x: float | None = None, y: float | None = None, **values):
        """Amplitude, phase, mean deflection and mean force vs z at (x, y) [m] (default: where the
        tip is): the tip moves there, the feedback regulates for ``spectroscopy_settle_time`` [s]
        and is then held, z ramps toward the sample and back at ``spectroscopy_rate`` [m/s] (the z
        controller's spectroscopy_* parameters; ``values`` override them for this curve), then the
        loop resumes. Returns an xarray Dataset over time with z [m] beside it."""

        if (x is None) != (y is None):
            raise BadArgument("give both x and y, or neither")
        unknown = [k for k in values if k not in SPECTROSCOPY_SPECS]
        if unknown:
            raise BadArgument(
                f"{unknown[0]!r} is not a spectroscopy parameter; allowed: "
                f"{', '.join(SPECTROSCOPY_SPECS)}"
            )
        v = {**self.get("z_controller", *SPECTROSCOPY_SPECS), **values}
        try:
            rate = _number(
                "spectroscopy_rate",
                v["spectroscopy_rate"],
                0.0,
                math.inf,
                low_open=True,
                unit="m/s",
            )
            legs = 2 * (
                _number("spectroscopy_retract", v["spectroscopy_retract"], unit="m")
                + _number("spectroscopy_distance", v["spectroscopy_distance"], unit="m")
            )
            settle = _number(
                "spectroscopy_settle_time", v["spectroscopy_settle_time"], 0.0, unit="s"
            )
        except BadArgument:
            rate, legs, settle = 1.0, 0.0, 0.0  # the node refuses it with its own reason
        if x is not None:
            x, y = _number("x", x, unit="m"), _number("y", y, unit="m")
        self._announce("spectroscopy()", settle + legs / rate)
        if x is not None:
            self.move_tip(x, y)
        return self._run("spectroscopy", values)

    def wait_until(self, t: float) -> float:
        """Let simulated time pass up to ``t`` [s] (the first chunk boundary at or after it, where
        the instrument pauses); returns the time reached [s]."""
        t = _number("t", t, unit="s")
        self._announce(f"wait_until({t:g})", max(0.0, t - self.state()["t_s"]))
        return self._run("wait_until", t)

    def wait(self, seconds: float) -> None:
        """Let ``seconds`` [s] of simulated time pass with the instrument as it is."""
        seconds = _number("seconds", seconds, 0.0, unit="s")
        self._announce(f"wait({seconds:g})", seconds)
        self._run("advance", seconds)

    def flags(self) -> dict:
        """The problem flags of the last frame, by name (what an instrument could see: feedback, z
        range, drift, tip; docs/imperfections.md); {} if it raised none or no frame was scanned."""
        return self._backend.flags()

    def truth(self) -> Truth:
        """The emulator's ground truth now: the piezo's hysteresis and creep and the sample's drift
        [m] (zero when off), the tip's radius [m] in force and its pick-up events."""
        return self._backend.truth()

    def state(self) -> StageState:
        """Simulated time ``t_s`` [s] and the z stage's ``stage`` (engaged, withdrawn, approaching,
        ...)."""
        return self._backend.state()

    # --- what a controller needs (the Nanonis server: afm_ros.client.nanonis)
    # ----------------------
    def set_tick(self, tick) -> None:
        """``tick()`` is then called from inside every verb and wait, in its thread, between two
        chunks of the simulation (over ROS at least every 20 ms of wall time while it waits): a
        controller executes its short commands there (reads and settings of this Microscope) and
        may raise :class:`Interrupted` to stop the verb, which then recovers as after Ctrl-C (a
        scan keeps its lines, an approach stops with the feedback off). None removes it."""
        if tick is not None and not callable(tick):
            raise BadArgument(f"tick={tick!r} must be a function tick() or None")
        self._backend.set_tick(tick)

    def signals(self) -> Signals:
        """The live values now: tip position, z piezo, motor, amplitude, phase, frequency, drive,
        deflection, the z stage (see :class:`afm_ros.client.results.Signals`)."""
        return self._backend.signals()

    def frame_so_far(self):
        """The frame being scanned, or the last one, as a Dataset on its whole raster (NaN in the
        lines not scanned yet; attribute ``lines_done``); None before the first scan."""
        return self._backend.frame_so_far()

    def move_motor(self, steps: int) -> None:
        """Move the coarse motor ``steps`` steps (positive: away from the sample, negative:
        towards it; the z controller's motor_step each) with the tip withdrawn; returns when
        done."""
        steps = _integer("steps", steps)
        if abs(steps) > 1_000_000:
            raise BadArgument(f"steps={steps} is out of range; allowed [-1000000, 1000000]")
        self._run("move_motor", steps)

    def move_z(self, z: float) -> None:
        """Put the z piezo at ``z`` [m] (within the z controller's [z_min, z_max]) with the
        feedback off (set z_controller enabled False first)."""
        self._backend.move_z(_number("z", z, unit="m"))

    def oscilloscope(self, samples: int = 5000) -> Trace:
        """The last ``samples`` samples of the measured deflection (the raw stream: detector
        noise included) and their timing (see :class:`afm_ros.client.results.Trace`)."""
        samples = _integer("samples", samples)
        if not 1 <= samples <= 100_000:
            raise BadArgument(f"samples={samples} is out of range; allowed [1, 100000]")
        return self._backend.oscilloscope(samples)

    # --- the same verbs, asynchronous
    # -------------------------------------------------------------------
    def tune_async(self) -> Future:
        return self._submit(self.tune)

    def approach_async(self) -> Future:
        return self._submit(self.approach)

    def withdraw_async(self) -> Future:
        return self._submit(self.withdraw)

    def scan_async(self, progress=None, save=None) -> Future:
        return self._submit(self.scan, progress, save)

    def spectroscopy_async(
        self, x: float | None = None, y: float | None = None, **values
    ) -> Future:
        return self._submit(self.spectroscopy, x, y, **values)
