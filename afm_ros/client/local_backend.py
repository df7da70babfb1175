"""The client's in-process instrument: :class:`afm_ros.core.wired.WiredInstrument`, the same cores
the nodes run, with the nodes' parameters and refusals (no ROS)."""

from __future__ import annotations

from math import nan

from afm_ros.client.errors import Refused, WorkflowFailed, refusal
from afm_ros.client.frames import curve_dataset, frame_dataset, trace_of
from afm_ros.core import artefacts
from afm_ros.core.angles import wrap_deg
from afm_ros.core.approach import APPROACH_SPECS, INSTRUMENT_Z
from afm_ros.core.approach import validate as approach_validate
from afm_ros.core.controller import Z_CONTROLLER_SPECS
from afm_ros.core.flags import feedback_setpoint, frame_flags
from afm_ros.core.refusals import ENGAGED, NOT_ENGAGED, Refusal, code_of
from afm_ros.core.samples import resolve_sample
from afm_ros.core.scanner import (
    SCANNER_NODE_SPECS,
    ScanPlan,
    check_scan,
    check_scanner_values,
    scan_position,
)
from afm_ros.core.spectroscopy import SPECTROSCOPY_SPECS
from afm_ros.core.spectroscopy import validate as spectroscopy_validate
from afm_ros.core.tip import INSTRUMENT_TIP, TIP_SPECS
from afm_ros.core.tip import validate as tip_validate
from afm_ros.core.tune import TUNE_SPECS, sweep_wired
from afm_ros.core.wired import WiredInstrument

IDEAL_CANTILEVER = {"temperature": 0.0, "detector_noise_density": 0.0}
WORKFLOW_TIMEOUT_S = 600.0  # [s] simulated: an approach or withdraw that takes longer has failed
LIVE_CANTILEVER = ("drive_frequency", "free_amplitude", *TIP_SPECS)  # settable after the start


class LocalBackend:
    """A wired instrument with the nodes' defaults (see
    :meth:`afm_ros.client.Microscope.local`)."""

    def __init__(
        self,
        sample: str,
        force_model: str,
        ideal: bool,
        withdrawn: bool,
        cantilever: dict,
        lockin: dict,
        z_controller: dict,
        scanner: dict,
        approach: dict,
        tip: dict,
    ):

        try:
            sample_map = resolve_sample(sample)
        except (ValueError, OSError) as exc:
            raise Refused("cantilever", f"sample: {exc}") from None
        if sample_map is None:
            raise Refused(
                "cantilever", f"sample={sample!r} is flat: the client images a sample map"
            )
        self.scanner = {name: spec.default for name, spec in SCANNER_NODE_SPECS.items()}
        if ideal:
            self.scanner.update(artefacts.IDEAL_ARTEFACTS)
        self._checked("scanner", scanner, self.scanner)
        zc = {
            **({k: INSTRUMENT_Z[k] for k in ("z_min", "z_max")} if withdrawn else {}),
            **z_controller,
        }
        approach_values = {"start_withdrawn": withdrawn, **approach}
        imperfections = {name: self.scanner[name] for name in artefacts.ARTEFACT_SPECS}
        try:
            self.w = WiredInstrument(
                cantilever={
                    **(IDEAL_CANTILEVER if ideal else {}),
                    "force_model": force_model,
                    **cantilever,
                },
                lockin=dict(lockin),
                z_controller={k: v for k, v in zc.items() if k in Z_CONTROLLER_SPECS},
                sample=sample_map,
                imperfections=imperfections,
                approach_values={
                    **approach_values,
                    **{k: v for k, v in zc.items() if k in APPROACH_SPECS},
                },
                tip={**({} if ideal else INSTRUMENT_TIP), **tip},
            )
        except ValueError as exc:
            raise Refused("instrument", str(exc)) from None
        self.sample_name = sample
        self.spectroscopy_values = spectroscopy_validate(
            {k: v for k, v in zc.items() if k in SPECTROSCOPY_SPECS}
        )
        self.tune_values: dict = {}
        self.last_frame = None
        self.last_flags: dict = {}

    def close(self) -> None:
        pass

    def recover(self, verb: str) -> None:
        """After an interrupted verb: nothing to do, the wired instrument's verbs stop where they
        are (ZStage.stop, stop_scan) and the tune restores the drive itself."""

    def wall_per_simulated_second(self) -> float:
        return self.w.seconds_per_simulated_second()

    # --- parameters
    # -----------------------------------------------------------------------------------
    @staticmethod
    def _checked(node: str, changes: dict, into: dict) -> None:
        """Validate scanner ``changes`` by the node's specs and checks, then apply them to
        ``into``."""
        specs = SCANNER_NODE_SPECS
        merged = dict(into)
        for name, value in changes.items():
            if name not in specs:
                raise Refused(node, f"{name!r} is not a {node} parameter")
            try:
                merged[name] = specs[name].validate(value)
            except ValueError as exc:
                raise refusal(node, exc) from None
        try:
            check_scanner_values(merged)
        except ValueError as exc:
            raise refusal(node, exc) from None
        into.update(merged)

    def set_values(self, node: str, values: dict) -> None:
        w = self.w
        if not values:
            return
        if node == "scanner":
            self._checked("scanner", values, self.scanner)
            if any(name in artefacts.ARTEFACT_SPECS for name in values):
                w.imperfect.configure(
                    t=w.t, **{name: self.scanner[name] for name in artefacts.ARTEFACT_SPECS}
                )
                w.sim.set_artefacts(
                    w.imperfect.packed(w.images.plan if w.images is not None else None)
                )
            return
        try:
            if node == "z_controller":
                unknown = (
                    set(values)
                    - set(Z_CONTROLLER_SPECS)
                    - set(APPROACH_SPECS)
                    - set(SPECTROSCOPY_SPECS)
                )
                if unknown:
                    raise ValueError(f"{sorted(unknown)[0]!r} is not a z_controller parameter")
                approach = {
                    k: APPROACH_SPECS[k].validate(v)
                    for k, v in values.items()
                    if k in APPROACH_SPECS
                }
                spectroscopy = spectroscopy_validate(
                    {
                        **self.spectroscopy_values,
                        **{k: v for k, v in values.items() if k in SPECTROSCOPY_SPECS},
                    }
                )
                w.controller.configure(
                    **{k: v for k, v in values.items() if k in Z_CONTROLLER_SPECS}
                )
                w.approach_values.update(approach)
                self.spectroscopy_values = spectroscopy
            elif node == "lockin":
                tune = {k: v for k, v in values.items() if k in TUNE_SPECS}
                w.lock_in.configure(**{k: v for k, v in values.items() if k not in TUNE_SPECS})
                self.tune_values.update(tune)
            elif node == "cantilever":
                other = set(values) - set(LIVE_CANTILEVER)
                if other:
                    raise ValueError(
                        f"{sorted(other)[0]}: in-process, only {', '.join(LIVE_CANTILEVER)} "
                        "change "
                        f"after the start; give the others to Microscope.local(cantilever={{...}})"
                    )
                if set(values) & set(TIP_SPECS):
                    w.wear.values = tip_validate(
                        {**w.wear.values, **{k: v for k, v in values.items() if k in TIP_SPECS}}
                    )
                if "drive_frequency" in values or "free_amplitude" in values:
                    w.set_drive(
                        values.get("drive_frequency", w.values["drive_frequency"]),
                        values.get("free_amplitude", w.values["free_amplitude"]),
                    )
            else:
                raise ValueError(f"no node {node!r} (cantilever, lockin, z_controller, scanner)")
        except ValueError as exc:
            raise refusal(node, exc) from None

    def get_values(self, node: str, names: list[str]) -> dict:
        w = self.w
        source = {
            "scanner": self.scanner,
            "z_controller": {
                **w.controller.params,
                **approach_validate(w.approach_values),
                **self.spectroscopy_values,
            },
            "lockin": {**w.lock_in.params, **self.tune_values},
            "cantilever": w.values,
        }.get(node)
        if source is None:
            raise Refused(node, "no such node (cantilever, lockin, z_controller, scanner)")
        missing = [n for n in names if n not in source]
        if missing:
            raise Refused(node, f"{missing[0]!r} is not a {node} parameter")
        return {n: source[n] for n in names}

    def scan_settings(self) -> dict:
        return {k: self.scanner[k] for k in ScanPlan.from_values(self.scanner).values()}

    def feedback(self) -> dict:
        p = self.w.controller.params
        return {k: p[k] for k in ("setpoint", "p_gain", "i_gain", "z_min", "z_max")}

    # --- actions
    # --------------------------------------------------------------------------------------
    def state(self) -> dict:
        return {"t_s": self.w.t, "stage": self.w.stage.state}

    def advance(self, seconds: float) -> None:
        self.w.run_until(self.w.t + seconds)

    def wait_until(self, t: float) -> float:
        self.w.run_until(t)
        return self.w.t

    def tune(self) -> dict:

        w = self.w
        if w.stage.state in ("engaged", "approaching", "withdrawing"):
            raise Refused(
                "lockin/tune",
                f"tune refused: the z stage is {w.stage.state}; the tune needs the "
                "cantilever free: withdraw first (service z_controller/withdraw)",
                ENGAGED,
            )
        t0 = w.t
        try:
            r = sweep_wired(w, self.tune_values)
        except ValueError as exc:
            raise Refused("lockin/tune", f"tune refused: {exc}") from None
        offset = float(wrap_deg(w.lock_in.params["phase_offset"] + r.phase_offset_deg))
        w.set_drive(r.drive_frequency, w.values["free_amplitude"] * r.drive_scale)
        w.lock_in.configure(phase_offset=offset)
        return {**r.message(), "start_s": t0, "end_s": w.t}

    def approach(self) -> dict:
        w = self.w
        try:
            log = w.approach(timeout=WORKFLOW_TIMEOUT_S)
        except RuntimeError as exc:
            raise WorkflowFailed(str(exc)) from None
        return {
            "state": "engaged",
            "started_s": log.started_at,
            "engaged_s": log.engaged_at,
            "duration_s": log.engaged_at - log.started_at,
            "engaged_z_m": log.engaged_z,
            "motor_steps": log.steps,
            "cycles": len(log.cycles),
            "motor_m": w.motor,
        }

    def withdraw(self) -> dict:
        w = self.w
        t0 = w.t
        w.withdraw(timeout=WORKFLOW_TIMEOUT_S)
        if w.stage.state != "withdrawn":
            raise WorkflowFailed(f"withdraw ended {w.stage.state} at t={w.t:.6g} s")
        return {"state": "withdrawn", "started_s": t0, "withdrawn_s": w.t, "motor_m": w.motor}

    def scan(self, progress):
        w = self.w
        values = dict(self.scanner, continuous=False)
        try:
            if not w.engaged:
                raise Refusal(
                    NOT_ENGAGED,
                    f"not engaged: the z stage is {w.stage.state}; approach first (service "
                    "z_controller/approach)",
                )
            check_scan(values, w.lock_in.params["output_rate"], w.setup.sample_interval)
        except ValueError as exc:
            raise refusal(
                "scanner/scan_frame", Refusal(code_of(exc), f"scan refused: {exc}")
            ) from None
        done = [0]

        def report(images) -> None:
            lines = images.plan.lines if images.done else images.frame.lines_done
            if progress is not None and lines != done[0]:
                done[0] = lines
                progress(lines, images.plan.lines)

        frame = w.scan_frame(values, progress=report)
        zc = w.controller.params
        flags = frame_flags(
            frame,
            feedback_setpoint(frame, zc),
            (zc["z_min"], zc["z_max"]),
            previous=self.last_frame,
        )
        self.last_frame = frame
        self.last_flags = {f.name: f.message for f in flags}
        return frame_dataset(
            frame.images,
            frame.plan,
            {
                "source": "local",
                "sample": self.sample_name,
                "flags": self.last_flags,
                **{f"feedback_{k}": v for k, v in self.feedback().items()},
            },
        )

    def move_tip(self, x: float, y: float) -> None:
        for name, value in (("tip_x", x), ("tip_y", y)):
            try:
                SCANNER_NODE_SPECS[name].validate(value)
            except ValueError as exc:
                raise Refused("scanner", str(exc)) from None
        self.scanner.update(tip_x=x, tip_y=y)
        self.w.park(x, y)

    def spectroscopy(self, values: dict):
        w = self.w
        try:
            curve = w.spectroscopy({**self.spectroscopy_values, **values})
        except ValueError as exc:
            raise refusal("z_controller/spectroscopy", exc) from None
        return curve_dataset(curve, {"source": "local"})

    def flags(self) -> dict:
        return dict(self.last_flags)

    # --- a controller's needs (Microscope.set_tick, signals, ...)
    # ---------------------------------
    def set_tick(self, tick) -> None:
        self.w.on_step = tick

    def signals(self) -> dict:
        w = self.w
        last = w.last
        amplitude = float(last.amplitude[-1]) if last is not None and last.amplitude.size else nan
        phase = float(last.phase_deg[-1]) if last is not None and last.phase_deg.size else nan
        scanning = w.images is not None and not w.images.done
        if scanning:
            x, y = scan_position(w.images.plan.packed(), w.t)
        else:
            x, y = w.parked_at
        raw = w.raw[-1][2] if w.raw else None
        setup = w.setup
        return {
            "t_s": w.t,
            "x_m": float(x),
            "y_m": float(y),
            "z_m": float(w.stage.z),
            "motor_m": float(w.motor),
            "amplitude_m": amplitude,
            "phase_deg": phase,
            "amplitude_error_m": float(w.controller.params["setpoint"]) - amplitude,
            "frequency_Hz": float(setup.drive.frequency),
            "frequency_shift_Hz": nan,
            "drive_N": float(setup.drive.force),
            "deflection_m": float(raw[-1]) if raw is not None and raw.size else nan,
            "stage": w.stage.state,
            "feedback": bool(w.stage.engaged and w.controller.params["enabled"]),
            "scanning": bool(scanning),
        }

    def frame_so_far(self):
        w = self.w
        if w.images is not None:
            frame = w.frame_so_far
        elif w.stopped_frame is not None:
            frame = w.stopped_frame
        else:
            frame = self.last_frame
        if frame is None:
            return None
        return frame_dataset(
            frame.images,
            frame.plan,
            {"source": "local", "lines_done": frame.lines_done, "sample": self.sample_name},
        )

    def move_motor(self, steps: int) -> None:
        try:
            self.w.move_motor(steps, timeout=WORKFLOW_TIMEOUT_S)
        except ValueError as exc:
            raise refusal("z_controller/move_motor", exc) from None

    def move_z(self, z: float) -> None:
        try:
            self.w.move_z(z)
        except ValueError as exc:
            raise refusal("z_controller/move_z", exc) from None

    def oscilloscope(self, samples: int) -> dict:
        return trace_of(list(self.w.raw), samples)

    def truth(self) -> dict:
        w = self.w
        t = w.t
        row = artefacts.truth(w.sim.artefacts, w.sim.plan, t)
        return {
            "t_s": t,
            **{f"{k}_m": float(v[0]) for k, v in row.items()},
            "tip_radius_m": float(w.wear.built_radius),
            "second_apex_m": [float(v) for v in (w.wear.second_apex or (0.0, 0.0, 0.0))],
        }
