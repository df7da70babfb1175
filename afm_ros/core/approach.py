"""Coarse approach, engage and withdraw (no ROS): the auto-approach state machine of a real AFM.

The sample starts ``approach_start_distance`` [m] below the tip's rest position (the piezo
retracted at z_max). A coarse motor moves the head in steps of ``motor_step`` [m]
(``motor_step_time`` [s] each); the z piezo covers [z_min, z_max] (the z controller's limits).
As real auto-approach does (Nanonis ``AutoApproach``, aespm "Approach" then "Engage"), each cycle:

0. **arm**: the free oscillation must first be above the setpoint (it rings up in a few Q / (pi
   f0)); a tip that is already on the surface fails here, with the reason;
1. **extend**: the piezo moves from z_max towards z_min at ``approach_speed`` [m/s] while the
   amplitude is watched at every lock-in output;
2. the amplitude falls to the setpoint: **engaged** at that z (the z loop takes over from there,
   bumpless); or the piezo reaches z_min without it:
3. **retract** to z_max at ``retract_speed`` [m/s], then **step** the motor towards the sample by
   ``approach_cycle_fraction`` of the piezo range (whole steps; the simulated STM of STM-Bench
   keeps a cycle under 80 % of the fine range, so the surface is never jumped over), and repeat;
4. **failed** when the motor's travel (``motor_travel`` [m]) is used up.

No crash: the amplitude falls from A0 to the setpoint over about A0 - setpoint of gap on a hard
sample, and the piezo moves on for the loop's detection delay (one lock-in output interval plus
the feedback latency) at ``approach_speed``: 2 um/s x ~5 ms = 10 nm, less than the 12 nm between
the setpoint and the free amplitude, so the tip never presses harder than imaging at the setpoint
does (tested: the approach's peak force is within 1.5 times the engaged steady state's).

Decisions are taken at lock-in outputs (simulated time), so the approach is deterministic and
independent of how the run is split into chunks. The motor's position is part of the base height
(``motor`` [m], 0 = the position at which the sample surface is at the gap z_base with the piezo at
0, as without approach).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from afm_ros.core.controller import Z_CONTROLLER_SPECS
from afm_ros.core.physics.parameters import ParamSpec, validate_values
from afm_ros.core.refusals import BAD_VALUE, BUSY, ENGAGED, NOT_ENGAGED, Refusal
from afm_ros.core.spectroscopy import SPECTROSCOPY_SPECS, SpectroscopyRamp

APPROACH_SPECS: dict[str, ParamSpec] = {
    s.name: s
    for s in (
        ParamSpec(
            "approach_start_distance",
            5e-6,
            "m",
            "gap between the tip's rest position (piezo retracted) and the sample when the "
            "approach starts; "
            "at most motor_travel plus the z range",
            0.0,
            0.1,
        ),
        ParamSpec(
            "motor_step", 50e-9, "m", "coarse motor step (stick-slip or stepper)", 1e-9, 1e-6
        ),
        ParamSpec("motor_step_time", 1e-3, "s", "time per motor step", 1e-5, 1.0),
        ParamSpec(
            "motor_travel",
            5e-3,
            "m",
            "largest distance the motor can move towards the sample",
            1e-6,
            0.1,
        ),
        ParamSpec(
            "approach_speed",
            2e-6,
            "m/s",
            "z piezo extension speed while watching the amplitude",
            1e-8,
            1e-3,
        ),
        ParamSpec(
            "retract_speed",
            20e-6,
            "m/s",
            "z piezo retraction speed between cycles and on withdraw",
            1e-8,
            1e-2,
        ),
        ParamSpec(
            "approach_cycle_fraction",
            0.8,
            "1",
            "motor travel per cycle as a fraction of the z piezo range",
            0.1,
            0.95,
        ),
        ParamSpec(
            "withdraw_distance",
            1e-6,
            "m",
            "the motor backs off this far on withdraw (piezo retracted too)",
            0.0,
            1e-3,
        ),
        ParamSpec(
            "start_withdrawn",
            False,
            "",
            "start far from the sample: withdrawn at approach_start_distance with the feedback "
            "off, as a real "
            "session starts (tune, then approach); false: engaged at z_base from the first chunk "
            "(the ideal start)",
            kind=bool,
        ),
        ParamSpec(
            "motor_move_steps",
            0,
            "steps",
            "coarse motor steps that the service z_controller/move_motor makes (Nanonis "
            "Motor.StartMove): positive away from the sample (Z+), negative towards it (Z-); "
            "only while the tip is not engaged",
            -1000000,
            1000000,
            kind=int,
        ),
        ParamSpec(
            "z_position",
            0.0,
            "m",
            "z piezo position that the service z_controller/move_z moves to while the feedback "
            "is off (Nanonis ZCtrl.ZPosSet); within [z_min, z_max]",
            -1e-4,
            1e-4,
        ),
    )
}

# a real session's z stage (afm_instrument's workflow, afm_study scan --approach): a 3 um z piezo
# range (retracted at 0), the tip withdrawn far from the sample at the start
INSTRUMENT_Z = {"z_min": -3e-6, "z_max": 0.0, "start_withdrawn": True}

ARM_TIMEOUT_S = 0.5  # [s] simulated: the free oscillation must rise above the setpoint within this
RING_UP_TIME_CONSTANTS = 5  # an oscillation moved away from the surface is free after 5 Q/(pi f0)
Z_NODE_SPECS: dict[str, ParamSpec] = {}  # the z controller node's parameters (filled below)
STATES = ("idle", "extending", "retracting", "stepping", "engaged", "failed", "withdrawn")


Z_NODE_SPECS.update({**Z_CONTROLLER_SPECS, **APPROACH_SPECS, **SPECTROSCOPY_SPECS})


def validate(values: dict) -> dict:
    return validate_values(APPROACH_SPECS, values, "an approach")


def approach_time(values: dict, z_min: float, z_max: float) -> float:
    """[s] simulated an approach from approach_start_distance takes until it engages, about (each
    cycle extends the piezo at approach_speed, retracts it at retract_speed and steps the motor
    by approach_cycle_fraction of the range), for a surface at the start distance: what a caller
    says before a long one."""
    v = validate(values)
    z_range = max(z_max - z_min, 1e-12)
    step = v["approach_cycle_fraction"] * z_range
    # the first extension covers the piezo's range; each next cycle the motor brings step more
    cycles = 1 + math.ceil(max(0.0, v["approach_start_distance"] - z_range) / step)
    per_cycle = (
        z_range / v["approach_speed"]
        + z_range / v["retract_speed"]
        + math.ceil(step / v["motor_step"]) * v["motor_step_time"]
    )
    return cycles * per_cycle


def blind_time(
    chunk_duration: float, feedback_latency: int, quality_factor: float, resonance_frequency: float
) -> float:
    """[s] simulated after a jump of the z command during which the loop's outputs still tell of
    the position before it: the command reaches the cantilever ``feedback_latency`` chunks later,
    the lock-in output of a chunk reads it a chunk after that, and the oscillation needs a few time
    constants Q / (pi f0) to ring to its new amplitude."""
    return (feedback_latency + 2) * chunk_duration + RING_UP_TIME_CONSTANTS * quality_factor / (
        math.pi * resonance_frequency
    )


SIGNALS = {
    False: ("amplitude", "m"),
    True: ("frequency shift", "Hz"),
}  # the loop's signal: tapping, FM


@dataclass
class ApproachLog:
    """What happened: per cycle (start time [s], motor [m], deepest z reached [m])."""

    cycles: list = field(default_factory=list)
    steps: int = 0
    engaged_at: float = math.nan  # simulated time [s]
    engaged_z: float = math.nan  # z piezo at engage [m]
    started_at: float = math.nan


class AutoApproach:
    """The approach state machine; :meth:`update` takes each lock-in amplitude [m] and its time [s]
    and returns the z piezo command [m]; :attr:`motor` [m] is the motor's position."""

    def __init__(
        self,
        values: dict,
        z_min: float,
        z_max: float,
        setpoint: float,
        z_base: float,
        t: float,
        motor: float | None = None,
        blind_until: float = -math.inf,
        fm: bool = False,
    ):
        """``blind_until`` [s]: outputs before it are not judged (they come from chunks integrated
        before the approach moved the z command); ``fm``: the signal is the frequency shift
        [Hz]."""
        self.values = v = validate(values)
        self.blind_until = float(blind_until)
        self.signal, self.unit = SIGNALS[fm]
        if not z_min < z_max:
            raise ValueError(f"z_min={z_min!r} m must be below z_max={z_max!r} m")
        self.z_min, self.z_max, self.setpoint = float(z_min), float(z_max), float(setpoint)
        # the gap at rest (piezo at z_max) is z_base + motor + z_max
        self.motor = (
            v["approach_start_distance"] - z_base - z_max if motor is None else float(motor)
        )
        self.motor_start = self.motor
        self.state = "extending"
        self.z = self.z_max
        self._phase_t = float(t)
        self._phase_z = self.z_max
        self._steps_left = 0
        self.armed = False  # the amplitude was above the setpoint once (the oscillation is there)
        self.reason = ""  # why it failed
        self.log = ApproachLog(started_at=float(t))
        self.log.cycles.append((float(t), self.motor, self.z))
        travel_needed = v["approach_start_distance"] - (z_max - z_min)
        if travel_needed > v["motor_travel"]:
            raise ValueError(
                f"approach_start_distance={v['approach_start_distance']:g} m is beyond the "
                "motor's "
                f"reach: motor_travel={v['motor_travel']:g} m plus the z range {z_max - z_min:g} "
                "m; "
                f"allowed up to {v['motor_travel'] + z_max - z_min:g} m"
            )

    @property
    def active(self) -> bool:
        return self.state in ("extending", "retracting", "stepping")

    @property
    def range(self) -> float:
        return self.z_max - self.z_min

    def update(self, amplitude: float, t: float) -> float:
        v = self.values
        if t < self.blind_until:  # an output of the position before the approach moved it
            return self.z
        if self.state == "extending" and not self.armed:
            # the oscillation must first be there (free, above the setpoint); it rings up in a few
            # Q/(pi f0)
            if math.isfinite(amplitude) and amplitude > self.setpoint:
                self.armed = True
                self._phase_t = t
            elif t - self.log.started_at > ARM_TIMEOUT_S:
                self.state = "failed"
                self.reason = (
                    f"the {self.signal} stayed at or below the setpoint {self.setpoint:g} "
                    f"{self.unit} for "
                    f"{ARM_TIMEOUT_S:g} s before moving: is the tip already on the surface "
                    "(withdraw "
                    "first) or the drive off?"
                )
            return self.z
        if self.state == "extending":
            self.z = max(self.z_min, self._phase_z - v["approach_speed"] * (t - self._phase_t))
            self.log.cycles[-1] = (self.log.cycles[-1][0], self.motor, self.z)
            if math.isfinite(amplitude) and amplitude <= self.setpoint:
                self.state = "engaged"
                self.log.engaged_at, self.log.engaged_z = float(t), self.z
            elif self.z <= self.z_min:
                self.state, self._phase_t, self._phase_z = "retracting", t, self.z
        elif self.state == "retracting":
            self.z = min(self.z_max, self._phase_z + v["retract_speed"] * (t - self._phase_t))
            if self.z >= self.z_max:
                travelled = self.motor_start - self.motor
                if travelled >= v["motor_travel"] - 1e-15:
                    self.state = "failed"
                    self.reason = (
                        "no surface within the motor's travel "
                        f"motor_travel={v['motor_travel']:g} m"
                    )
                    return self.z
                steps = max(1, int(v["approach_cycle_fraction"] * self.range / v["motor_step"]))
                steps = min(
                    steps, int(round((v["motor_travel"] - travelled) / v["motor_step"])) or 1
                )
                self._steps_left = steps
                self.state, self._phase_t = "stepping", t
        elif self.state == "stepping":
            due = int((t - self._phase_t) / v["motor_step_time"])
            while self._steps_left > 0 and due > 0:
                self.motor -= v["motor_step"]
                self._steps_left -= 1
                self.log.steps += 1
                due -= 1
                self._phase_t += v["motor_step_time"]
            if self._steps_left == 0:
                self.state, self._phase_t, self._phase_z = "extending", t, self.z_max
                self.log.cycles.append((float(t), self.motor, self.z))
        return self.z


class ZStage:
    """One z axis as the cantilever sees it: the z controller, the approach and the coarse motor.

    :meth:`update` takes each lock-in amplitude [m] and its simulated time [s] and returns the z
    piezo position [m] (the topography); :attr:`command` = piezo + motor is what moves the base
    (gap = z_base + command + deflection). Without an approach the motor stays at 0 and the stage
    is the z controller alone (the ideal start: engaged at z_base). The wired instrument and the z
    controller node both run this, so their z is the same.
    """

    def __init__(self, controller, z_base: float):
        self.controller = controller
        self.z_base = float(z_base)
        self.motor = 0.0
        self.auto: AutoApproach | None = None
        # engaged (the loop regulates), approaching, withdrawing, withdrawn, failed, spectroscopy
        self.state = "engaged"
        self.reason = ""
        self._withdraw: dict | None = None
        self._move: dict | None = None  # a motor move (Motor.StartMove)
        self.ramp: SpectroscopyRamp | None = None  # the z spectroscopy running or last run
        self.settling: dict | None = (
            None  # a spectroscopy's settling under feedback before it holds
        )
        self._held_params: dict | None = None  # the controller's settings before a spectroscopy
        self.t_last: float | None = None  # simulated time of the last lock-in output [s]

    @property
    def command(self) -> float:
        return self.z + self.motor

    @property
    def z(self) -> float:
        if self.state == "approaching":
            return self.auto.z
        if self.state == "spectroscopy" and self.settling is None:
            return self.ramp.z_at(self.ramp.t0 if self.t_last is None else self.t_last)
        return self.controller.z

    @property
    def engaged(self) -> bool:
        return self.state == "engaged"

    def start_approach(self, values: dict, t: float, blind: float = 0.0) -> AutoApproach:
        """Start an approach from ``approach_start_distance`` at time t [s] (ValueError naming the
        field for bad values; nothing changes then). ``blind`` [s] (:func:`blind_time`): if the
        start moves the z command (from engaged, or a motor elsewhere), the outputs of the next
        ``blind`` seconds still come from the old position and are not taken as the approach's."""
        c = self.controller.params
        auto = AutoApproach(
            values,
            c["z_min"],
            c["z_max"],
            self.controller.setpoint,
            self.z_base,
            t,
            fm=self.controller.fm,
        )
        if auto.z + auto.motor != self.command:
            auto.blind_until = t + blind
        self.auto, self.settling = auto, None
        self.controller.configure(enabled=False, disabled_action="hold", max_slew_rate=0.0)
        self.controller.z = self.controller.integrator = auto.z
        self.motor = auto.motor
        self.state, self.reason = "approaching", ""
        return auto

    def place_withdrawn(self, values: dict) -> None:
        """Before the first chunk: the head far from the sample (gap approach_start_distance at
        rest, piezo retracted, feedback off): where a real session starts."""
        v = validate(values)
        c = self.controller
        c.configure(enabled=False, disabled_action="hold", max_slew_rate=0.0)
        c.z = c.integrator = c.params["z_max"]
        self.motor = v["approach_start_distance"] - self.z_base - c.params["z_max"]
        self.state, self.reason = "withdrawn", ""

    def start_withdraw(self, values: dict | None, t: float) -> None:
        """Feedback off; the piezo retracts to z_max at retract_speed, then the motor backs off by
        withdraw_distance, one step per motor_step_time."""
        v = validate(
            values if values is not None else (self.auto.values if self.auto is not None else {})
        )
        if self.state == "spectroscopy":  # abandoned: the piezo retracts from where the ramp is
            self.controller.z = self.controller.integrator = self.z
        self.settling = None
        self.controller.configure(
            enabled=False, disabled_action="withdraw", max_slew_rate=v["retract_speed"]
        )
        steps = int(round(v["withdraw_distance"] / v["motor_step"]))
        self._withdraw = {"values": v, "steps": steps, "t_motor": None}
        self.state, self.reason = "withdrawing", ""

    def start_spectroscopy(self, values: dict, t: float, meta: dict) -> SpectroscopyRamp:
        """A z spectroscopy (:mod:`afm_ros.core.spectroscopy`) requested at time t [s]: the
        feedback first regulates for ``spectroscopy_settle_time`` (after a move the loop needs it
        to reach the setpoint at the new point), then holds where it is and the ramp starts (at
        once without settling). ``meta`` completes the curve's set-up (x, y, spring_constant, ...).
        ValueError with the reason when the stage is not engaged or a value is bad (nothing changes
        then); the ramp is returned (its path is placed when the hold begins)."""
        if self.state != "engaged":
            raise Refusal(
                NOT_ENGAGED,
                f"spectroscopy refused: the z stage is {self.state}"
                + (f" ({self.reason})" if self.reason else "")
                + "; it needs the tip engaged (approach first)",
            )
        c = self.controller
        ramp = SpectroscopyRamp(
            values,
            c.z,
            t,
            c.params["z_min"],
            c.params["z_max"],
            self.z_base + self.motor,
            {**meta, "setpoint": c.params["setpoint"]},
        )
        settle = ramp.values["spectroscopy_settle_time"]
        self.ramp, self.state, self.reason = ramp, "spectroscopy", ""
        if settle > 0.0:
            self.settling = {"until": t + settle}
        else:
            self._hold(ramp)
        return ramp

    def _hold(self, ramp: SpectroscopyRamp) -> None:
        c = self.controller
        self._held_params = {
            k: c.params[k] for k in ("enabled", "disabled_action", "max_slew_rate")
        }
        c.configure(enabled=False, disabled_action="hold", max_slew_rate=0.0)

    def start_motor_move(self, steps: int, values: dict) -> None:
        """Move the coarse motor ``steps`` steps (positive: away from the sample) at
        motor_step_time each, the piezo held where it is; refused while the tip is engaged or the
        stage is busy. The stage goes back to its state when the steps are done (stop() ends it
        early)."""
        v = validate(values)
        if self.state in ("engaged", "approaching", "withdrawing", "spectroscopy", "moving"):
            raise Refusal(
                ENGAGED if self.state == "engaged" else BUSY,
                f"motor move refused: the z stage is {self.state}; the motor moves only with the "
                "tip withdrawn (withdraw first)",
            )
        if steps == 0:
            return
        c = self.controller
        c.configure(enabled=False, disabled_action="hold", max_slew_rate=0.0)
        direction = 1.0 if steps > 0 else -1.0
        self._move = {
            "steps": abs(int(steps)),
            "step": direction * v["motor_step"],
            "step_time": v["motor_step_time"],
            "t_motor": None,
            "was": self.state,
        }
        self.state, self.reason = "moving", ""

    def move_z(self, z: float) -> None:
        """Put the z piezo at ``z`` [m] now (Nanonis ZCtrl.ZPosSet): only with the feedback off
        and the stage at rest; ValueError naming the range otherwise."""
        c = self.controller
        if self.state in ("approaching", "withdrawing", "spectroscopy", "moving"):
            raise Refusal(BUSY, f"z move refused: the z stage is {self.state}")
        if c.params["enabled"]:
            raise Refusal(BAD_VALUE, "z move refused: the z feedback is on (switch it off first)")
        low, high = c.params["z_min"], c.params["z_max"]
        if not low <= z <= high:
            raise ValueError(f"z_position={z:g} m is outside the z range [{low:g}, {high:g}] m")
        c.configure(disabled_action="hold", max_slew_rate=0.0)
        c.z = c.integrator = float(z)

    def stop(self, why: str) -> str:
        """Stop what the stage is doing now (an interrupted verb, Motor.StopMove): an approach or
        withdraw leaves the piezo and motor where they are with the feedback off (state
        ``stopped``, ``reason`` = ``why``); a spectroscopy resumes the feedback from where the ramp
        is (state engaged; its curve is abandoned). Returns the state it stopped ('' if nothing
        ran)."""
        was = self.state
        c = self.controller
        if was in ("approaching", "withdrawing", "moving"):
            z = self.z
            c.configure(enabled=False, disabled_action="hold", max_slew_rate=0.0)
            c.z = c.integrator = z
            self.state, self.reason = "stopped", why
            self._withdraw = self._move = None
            return was
        if was == "spectroscopy":
            z = self.z
            if self.settling is None:
                c.z = c.integrator = z
                c.configure(**self._held_params)
            self.settling = None
            self.ramp.done, self.ramp.t_end = True, math.nan
            self.state, self.reason = "engaged", why
            return was
        return ""

    def update(self, amplitude: float, t: float, phase: float = math.nan) -> float:
        """Take one lock-in output (amplitude [m], time [s], phase [deg]: recorded by a
        spectroscopy) and return the z piezo position [m]."""
        self.t_last = t
        if self.settling is not None:  # a spectroscopy's settling: the loop regulates, then holds
            z = self.controller.update(amplitude, t)
            if t >= self.settling["until"]:
                self.settling = None
                ramp = self.ramp
                try:
                    ramp.place(self.controller.z, t)
                except (
                    ValueError
                ) as exc:  # the loop settled where the ramp does not fit the z range
                    self.state, self.reason = "engaged", f"spectroscopy abandoned: {exc}"
                    ramp.done, ramp.t_end, ramp.failed = True, math.nan, str(exc)
                    return z
                self._hold(ramp)
            return z
        if self.state == "spectroscopy":
            c = self.controller
            z = self.ramp.update(amplitude, phase, t)
            if self.ramp.done:  # back at the held point: the loop takes over, bumpless
                c.z = c.integrator = self.ramp.z_held
                c.configure(**self._held_params)
                c.t_last = t
                self.state = "engaged"
            c.error = c.setpoint - amplitude
            return z
        if self.state == "approaching":
            z = self.auto.update(amplitude, t)
            self.motor = self.auto.motor
            if self.auto.state == "engaged":  # the loop takes over from here, bumpless
                self.controller.z = self.controller.integrator = z
                self.controller.configure(enabled=True)
                self.controller.t_last = t
                self.state = "engaged"
            elif self.auto.state == "failed":
                self.state, self.reason = "failed", self.auto.reason
                self.controller.z = self.controller.integrator = z
            self.controller.error = self.controller.setpoint - amplitude
            return z
        z = self.controller.update(amplitude, t)
        if self.state == "moving":
            m = self._move
            if m["t_motor"] is None:
                m["t_motor"] = t
            due = min(m["steps"], int((t - m["t_motor"]) / m["step_time"]))
            while due > 0:
                self.motor += m["step"]
                m["steps"] -= 1
                m["t_motor"] += m["step_time"]
                due -= 1
            if m["steps"] == 0:
                self.state, self._move = m["was"], None
            return z
        if self.state == "withdrawing":
            w = self._withdraw
            if z >= self.controller.params["z_max"]:
                if w["t_motor"] is None:
                    w["t_motor"] = t
                v = w["values"]
                due = min(w["steps"], int((t - w["t_motor"]) / v["motor_step_time"]))
                while due > 0:
                    self.motor += v["motor_step"]
                    w["steps"] -= 1
                    w["t_motor"] += v["motor_step_time"]
                    due -= 1
                if w["steps"] == 0:
                    self.controller.configure(max_slew_rate=0.0)
                    self.state = "withdrawn"
        return z
