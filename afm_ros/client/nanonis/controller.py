"""The instrument as a Nanonis controller runs it: one thread owns the
:class:`~afm_ros.client.Microscope`, keeps the simulation going in real time, runs one long action
at a time (a scan, an approach, a sweep), and executes the short commands of every connection
between two chunks.

Nothing here knows the protocol. :meth:`Controller.call` runs a function on the instrument
thread and returns its result (the connection's thread waits for it); :meth:`Controller.submit`
starts a long action (a :class:`Job`) and returns at once, as ``Scan.Action`` does on a real
controller; :meth:`Controller.stop` stops it where it is (the client's Ctrl-C recovery: a scan
keeps its lines, an approach stops with the feedback off).

How the short commands get in while a long action runs: the Microscope calls the controller's
tick from inside every verb, between chunks (:meth:`afm_ros.client.Microscope.set_tick`); the tick
executes the commands waiting, paces the simulation to real time where the backend does not pace
itself (the in-process wired instrument), and stops the action when asked.

``idle``: 'run' (default) lets simulated time pass while no action runs, as a controller's
feedback, drift and noise never stop; 'hold' advances it only inside actions, so a script's
results depend on the script alone (the frames of a sequence equal those of the same verbs in
process, bit for bit).
"""

from __future__ import annotations

import math
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any, Callable

from afm_ros.client.errors import Interrupted, Refused
from afm_ros.client.microscope import Microscope
from afm_ros.core.refusals import BUSY

IDLE_STEP_S = 0.1  # [s] simulated: while idle, time advances in steps of this (ticks within)
CALL_TIMEOUT_S = 60.0  # [s] wall: a short command waits at most this long for the instrument
LAG_RESET_S = 0.5  # [s] wall: pacing that falls this far behind starts again from now


class _Preempt(Interrupted):
    """Ends an idle wait early: an action was submitted (or the controller closes)."""


@dataclass
class Job:
    """A long action: ``kind`` (scan, approach, withdraw, tune, spectroscopy, motor, move), the
    function that runs it on the Microscope, and what it gave (``result``, or ``error`` and
    ``stopped``); ``done`` is set when it ended. Simulated start and end times [s]."""

    kind: str
    run: Callable[[Microscope], Any]
    done: threading.Event = field(default_factory=threading.Event)
    result: Any = None
    error: BaseException | None = None
    stop_requested: bool = False
    stopped: bool = False
    start_s: float = math.nan
    end_s: float = math.nan


@dataclass
class _Call:
    fn: Callable[[Microscope], Any]
    taken: threading.Event = field(default_factory=threading.Event)
    done: threading.Event = field(default_factory=threading.Event)
    result: Any = None
    error: BaseException | None = None


class Controller:
    """See the module doc. ``pace``: pace the simulation to ``real_time_factor`` simulated
    seconds per wall second (for the in-process wired instrument; nodes pace themselves);
    ``log(level, text)``."""

    def __init__(
        self,
        afm: Microscope,
        idle: str = "run",
        pace: bool = False,
        real_time_factor: float = 1.0,
        idle_step: float = IDLE_STEP_S,
        log: Callable[[str, str], None] | None = None,
        on_job_end: Callable[[Job], None] | None = None,
    ):
        if idle not in ("run", "hold"):
            raise ValueError(f"idle={idle!r}: 'run' or 'hold'")
        if not (real_time_factor > 0 and math.isfinite(real_time_factor)):
            raise ValueError(f"real_time_factor={real_time_factor!r}: a number > 0")
        self.afm = afm
        self.idle = idle
        self.pace = pace
        self.rate = float(real_time_factor)
        self.idle_step = idle_step
        self.log = log or (lambda level, text: None)
        self.on_job_end = on_job_end
        self.job: Job | None = None  # the action running now
        self.last: dict[str, Job] = {}  # the last action of each kind that ended
        self._pending: Job | None = None
        self._calls: deque[_Call] = deque()
        self._wake = threading.Condition()
        self._closing = threading.Event()
        self._in_tick = False
        self._pace_ref: tuple[float, float] | None = None  # (wall, simulated) [s]
        self.failure: str = ""  # why the instrument thread stopped, if it did
        self._thread = threading.Thread(target=self._loop, name="nanonis-instrument", daemon=True)
        afm.set_tick(self._tick)

    # --- what the connections call
    # ----------------------------------------------------------------------
    def start(self) -> "Controller":
        self._thread.start()
        return self

    def call(self, fn: Callable[[Microscope], Any], timeout: float = CALL_TIMEOUT_S):
        """``fn(afm)`` on the instrument thread, between two chunks; its result, or its exception
        raised here. TimeoutError if the instrument does not take it within ``timeout`` [s] (once
        taken, it runs to its end: its own work takes the time it takes)."""
        if threading.current_thread() is self._thread:
            return fn(self.afm)
        if self.failure:
            raise RuntimeError(f"the instrument stopped: {self.failure}")
        item = _Call(fn)
        with self._wake:
            self._calls.append(item)
            self._wake.notify_all()
        if not item.taken.wait(timeout):
            with self._wake:
                if item in self._calls:
                    self._calls.remove(item)
                    raise TimeoutError(
                        f"the instrument did not take the command within {timeout:g} s"
                    )
        while not item.done.wait(1.0):
            if self.failure:
                raise RuntimeError(f"the instrument stopped: {self.failure}")
        if item.error is not None:
            raise item.error
        return item.result

    def submit(self, kind: str, run: Callable[[Microscope], Any]) -> Job:
        """Start the action ``run(afm)`` (refused with code busy while another runs); returns its
        Job at once."""

        def take(afm) -> Job:
            busy = self.job or self._pending
            if busy is not None:
                raise Refused(
                    kind,
                    f"refused: {busy.kind} is running; stop it first or wait for its end",
                    BUSY,
                )
            self._pending = Job(kind, run)
            return self._pending

        return self.call(take)

    def running(self, kind: str | None = None) -> Job | None:
        """The action running or about to (of ``kind``, if given), else None."""
        job = self.job or self._pending
        return job if job is not None and kind in (None, job.kind) else None

    def stop(self, kind: str | None = None, timeout: float = CALL_TIMEOUT_S) -> Job | None:
        """Stop the action of ``kind`` (any, if None) where it is and wait until it ended; the
        Job stopped, or None if none ran."""
        job = self.running(kind)
        if job is None:
            return None
        job.stop_requested = True
        with self._wake:
            self._wake.notify_all()
        job.done.wait(timeout)
        return job

    def close(self, timeout: float = 30.0) -> None:
        """Stop the action running (its results kept), then the instrument thread."""
        self._closing.set()
        job = self.job or self._pending
        if job is not None:
            job.stop_requested = True
        with self._wake:
            self._wake.notify_all()
        if self._thread.is_alive():
            self._thread.join(timeout)
        self.afm.set_tick(None)

    # --- the instrument thread
    # --------------------------------------------------------------------------
    def _loop(self) -> None:
        try:
            while not self._closing.is_set():
                self._serve_calls()
                with self._wake:
                    job, self._pending = self._pending, None
                if job is not None:
                    self._run(job)
                elif self.idle == "run":
                    self._idle_step()
                else:
                    self._pace_ref = None
                    with self._wake:
                        if not self._calls and self._pending is None:
                            self._wake.wait(0.05)
        except BaseException as exc:  # the instrument itself failed: every waiter learns why
            self.failure = f"{type(exc).__name__}: {exc}"
            self.log("error", f"the instrument thread stopped: {self.failure}")
        finally:
            with self._wake:
                calls, self._calls = list(self._calls), deque()
            for item in calls:
                item.error = RuntimeError(f"the instrument stopped: {self.failure or 'closed'}")
                item.taken.set()
                item.done.set()

    def _idle_step(self) -> None:
        try:
            self.afm.wait(self.idle_step)
        except _Preempt:
            pass
        except Interrupted:
            pass

    def _run(self, job: Job) -> None:
        self.job = job
        job.start_s = self._now()
        try:
            job.result = job.run(self.afm)
        except Interrupted as exc:
            job.stopped, job.error = True, exc
        except Exception as exc:  # a refusal or a failed action: the connection reports it
            job.error = exc
        finally:
            job.end_s = self._now()
            self.job = None
            self.last[job.kind] = job
            if self.on_job_end is not None:
                try:
                    self.on_job_end(job)
                except Exception as exc:  # saving its file failed: say so, keep the instrument
                    self.log("error", f"after the {job.kind}: {exc}")
            job.done.set()

    def _now(self) -> float:
        try:
            return float(self.afm.state()["t_s"])
        except Exception:
            return math.nan

    def _serve_calls(self) -> None:
        while True:
            with self._wake:
                if not self._calls:
                    return
                item = self._calls.popleft()
                item.taken.set()
            try:
                item.result = item.fn(self.afm)
            except BaseException as exc:  # handed to the caller's thread
                item.error = exc
            item.done.set()

    def _tick(self) -> None:
        """Called by the Microscope between chunks inside every verb (the instrument thread)."""
        if self._in_tick:  # a command served here advanced time itself: no recursion
            return
        self._in_tick = True
        try:
            self._serve_calls()
            if self.pace:
                self._pace()
        finally:
            self._in_tick = False
        job = self.job
        if job is not None and job.stop_requested:
            raise Interrupted(f"{job.kind} stopped on request")
        if job is None and (self._pending is not None or self._closing.is_set()):
            raise _Preempt("an action starts")

    def _pace(self) -> None:
        """Hold the simulation to real time: wait (serving commands) until the wall clock catches
        up with the simulated time."""
        t = self._now()
        now = time.monotonic()
        if self._pace_ref is None or not math.isfinite(t):
            self._pace_ref = (now, t)
            return
        wall0, t0 = self._pace_ref
        due = wall0 + (t - t0) / self.rate
        if now - due > LAG_RESET_S:  # behind (a slow machine): no burst to catch up
            self._pace_ref = (now, t)
            return
        while due > now:
            with self._wake:
                if not self._calls and not self._closing.is_set():
                    self._wake.wait(due - now)
            self._serve_calls()
            job = self.job
            if (job is not None and job.stop_requested) or self._closing.is_set():
                return
            if job is None and self._pending is not None:
                return
            now = time.monotonic()
