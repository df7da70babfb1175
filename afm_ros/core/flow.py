"""Flow control of the sample stream (no ROS import): the two gates in front of every chunk.

The cantilever integrates chunk ``k`` (samples ``[S_k, S_k+1)``) only when both are open:

- :class:`FeedbackGate` (determinism): the z piezo position for chunk ``k`` is the z controller's
  answer to chunk ``k - L`` (``L = feedback_latency`` chunks), i.e. its command computed from every
  lock-in output of the samples before ``S_{k-L+1}``. In lockstep the gate waits for that answer,
  so the closed loop is the same sample for sample whatever the load, the executor or the
  process layout: only *when* a chunk is computed depends on the machine, never *what*.
- :class:`ConsumerWindow` (no loss): every consumer that acknowledges what it has handled
  (lock-in, recorder, monitors) may be at most ``flow_window`` chunks behind; a slow consumer
  slows the instrument down (its real-time factor drops) instead of losing samples.
"""

from __future__ import annotations

from collections import deque

from afm_ros.formats.chunk_layout import ACK_LEAVING, ACK_READY, ZCommand

FEEDBACK_SYNC_MODES = ("auto", "lockstep", "free")


class ChunkStarts:
    """Start indices of the recent chunks, ending with the start of the chunk about to be
    integrated."""

    def __init__(self, first_index: int = 0, keep: int = 64):
        self._starts: deque[int] = deque([int(first_index)], maxlen=max(2, keep))

    def resize(self, keep: int) -> None:
        if keep != self._starts.maxlen:
            self._starts = deque(self._starts, maxlen=max(2, keep))

    @property
    def next_index(self) -> int:
        """Start index of the next chunk (= end index of the last published one)."""
        return self._starts[-1]

    def published(self, end_index: int) -> None:
        """A chunk ending before ``end_index`` was published."""
        self._starts.append(int(end_index))

    def unpublish(self) -> None:
        """Take back the last booked chunk (it was never published, e.g. the integration blew
        up)."""
        if len(self._starts) > 1:
            self._starts.pop()

    def back(self, chunks: int) -> int:
        """Start index of the chunk ``chunks - 1`` chunks before the next one (``back(1)`` =
        next_index); the oldest kept start if fewer chunks were published."""
        n = len(self._starts)
        return self._starts[max(0, n - chunks)]


class FeedbackGate:
    """Picks the z [m] of the next chunk from the z controller's commands (see module docstring);
    the same gate picks the FM excitation (frequency, force) from the PLL's commands (``value`` of
    a command).

    mode ``lockstep``: always wait for the answer; ``auto``: lockstep once a synchronised command
    (``answered_end_index >= 0``) arrived from a controller that is still present, free before;
    ``free``: use the latest command as soon as it arrives (the result then depends on timing).
    """

    def __init__(self, mode: str = "auto", latency: int = 1, z_initial: float = 0.0):
        if mode not in FEEDBACK_SYNC_MODES:
            raise ValueError(
                f"feedback_sync={mode!r} is not allowed; allowed: {', '.join(FEEDBACK_SYNC_MODES)}"
            )
        self.mode = mode
        self.latency = int(latency)
        # the value of the last chunk: z [m] for the z command, (frequency [Hz], force [N]) for the
        # excitation
        self.z = float(z_initial) if isinstance(z_initial, (int, float)) else z_initial
        self._commands: deque[tuple[int, float]] = (
            deque()
        )  # synchronised (answered index, z), ascending
        self._synced_seen = False
        self.ignored_unsynchronised = 0
        self.stale_commands = 0  # synchronised commands older than the newest held one

    @property
    def locked(self) -> bool:
        return self.mode == "lockstep" or (self.mode == "auto" and self._synced_seen)

    @property
    def newest_answer(self) -> int | None:
        return self._commands[-1][0] if self._commands else None

    @property
    def newest_value(self) -> float | None:
        """The z [m] of the newest command held (None before one)."""
        return self._commands[-1][1] if self._commands else None

    def receive(self, cmd: ZCommand) -> None:
        if cmd.answered_end_index < 0:
            if self.locked:
                self.ignored_unsynchronised += 1
            else:
                self.z = cmd.value
            return
        self._synced_seen = True
        if self._commands and cmd.answered_end_index <= self._commands[-1][0]:
            if cmd.answered_end_index == self._commands[-1][0]:
                self._commands[-1] = (
                    cmd.answered_end_index,
                    cmd.value,
                )  # a re-sent answer: newest wins
            else:
                self.stale_commands += 1  # e.g. a restarted controller replaying its history
            return
        self._commands.append((cmd.answered_end_index, cmd.value))
        if not self.locked or len(self._commands) > 4096:  # bound memory when nobody consumes them
            while len(self._commands) > 1:
                self._commands.popleft()

    def controller_gone(self) -> None:
        """The command publisher left the graph: fall back to free mode (auto) with the last z."""
        if self.mode == "auto":
            self._synced_seen = False
        while len(self._commands) > 1:
            self._commands.popleft()

    def required_index(self, starts: ChunkStarts) -> int:
        """Answered index the next chunk needs: the end of the chunk ``latency`` chunks back."""
        return starts.back(self.latency)

    def ready(self, starts: ChunkStarts) -> bool:
        if not self.locked:
            return True
        newest = self.newest_answer
        return newest is not None and newest >= self.required_index(starts)

    def take(self, starts: ChunkStarts) -> float:
        """z [m] for the next chunk (call only when :meth:`ready`)."""
        if not self.locked:
            if self._commands:
                self.z = self._commands[-1][1]
            return self.z
        need = self.required_index(starts)
        chosen = None
        while self._commands and self._commands[0][0] <= need:
            chosen = self._commands.popleft()
        if (
            chosen is None
        ):  # only newer answers (a controller that joined late): the oldest of them
            chosen = self._commands[0]
        else:
            self._commands.appendleft(
                chosen
            )  # may serve the next chunk too if nothing newer comes
        self.z = chosen[1]
        return self.z


class ConsumerWindow:
    """Acknowledgements of the consumers of the stream, by consumer name."""

    def __init__(self, window: int = 32):
        self.window = int(window)
        self.acks: dict[str, int] = {}

    def receive(self, name: str, next_index: int, stream_next_index: int) -> bool:
        """Record an acknowledgement; return True if ``name`` is a new consumer."""
        new = name not in self.acks
        if next_index == ACK_LEAVING:
            self.acks.pop(name, None)
            return False
        if next_index == ACK_READY:
            # subscribed, nothing received yet: chunks from now on are for it (the transient-local
            # history of the chunk topics also brings it the recent ones)
            if new:
                self.acks[name] = stream_next_index
        elif next_index >= 0:
            self.acks[name] = next_index if new else max(self.acks[name], next_index)
        return new

    def forget_absent(self, present: set[str]) -> list[str]:
        """Drop consumers whose acknowledgement publisher left the graph; return their names."""
        gone = [n for n in self.acks if n not in present]
        for n in gone:
            del self.acks[n]
        return gone

    def blocking(self, starts: ChunkStarts) -> list[str]:
        """Consumers more than ``window - 1`` chunks behind the next chunk."""
        need = starts.back(self.window)
        return [n for n, a in self.acks.items() if a < need]

    def ready(self, starts: ChunkStarts) -> bool:
        need = starts.back(self.window)
        return all(a >= need for a in self.acks.values())


class SlowdownReporter:
    """When, and in what words, to tell the user that the loop runs slower than asked (wall s).

    A slowdown is an episode in which the pacing gives up simulated time (it cannot keep up). The
    first report comes only after ``first_after`` wall seconds of one episode (a start-up compile
    or a short stall is not news), later ones at most every ``period`` seconds; each gives the
    factor achieved since the previous report, what limits it (the gate the loop spent most of that
    wall time waiting at, else the integration itself) and what the user can do. Nothing is ever
    lost by a slowdown: the loop waits, the session stays exact.
    """

    def __init__(self, first_after: float = 5.0, period: float = 60.0, gap: float = 2.0):
        self.first_after, self.period, self.gap = first_after, period, gap
        self._episode: float | None = None  # wall time the current episode started
        self._last_giveup = -float("inf")  # wall time simulated time was last given up
        self._given_up = 0.0
        self._mark: tuple[float, float, dict] | None = (
            None  # (wall, simulated, waits) the next report measures from
        )
        self._last_report = -float("inf")

    def update(
        self,
        now: float,
        sim_time: float,
        given_up: float,
        requested: float,
        waits: dict[str, float],
        reasons: dict[str, str],
    ) -> str | None:
        """Feed the pacing state: ``given_up`` simulated seconds given up so far, ``waits`` the
        wall seconds spent at each gate so far ('feedback', 'consumers') and ``reasons`` the last
        wait reason of each. Returns a warning text or None."""
        if given_up <= self._given_up:
            if self._episode is not None and now - self._last_giveup > self.gap:
                self._episode = None  # caught up again
            return None  # reported only while behind
        self._given_up = given_up
        if self._episode is None:
            self._episode = now
            if self._mark is None or now - self._last_report > self.period:
                self._mark = (now, sim_time, dict(waits))
        self._last_giveup = now
        if now - self._episode < self.first_after or now - self._last_report < self.period:
            return None
        wall = now - self._mark[0]
        achieved = (sim_time - self._mark[1]) / wall if wall > 0 else 0.0
        waited = {k: waits.get(k, 0.0) - self._mark[2].get(k, 0.0) for k in waits}
        kind = max(waited, key=waited.get, default=None)
        if kind is not None and waited[kind] < 0.2 * wall:
            kind = None
        self._mark = (now, sim_time, dict(waits))
        self._last_report = now
        suggest = float(f"{max(achieved * 0.9, 0.01):.1g}")
        return (
            f"running at {achieved:.2f}x real time instead of the requested {requested:g}x: "
            f"{slowdown_bottleneck(kind, reasons.get(kind, ''))} cannot keep up on this machine. "
            "Nothing is "
            "lost (the loop waits, every sample is computed and the session stays exact). To run "
            "steadily, "
            "lower the cantilever's real_time_factor, e.g. 'afm_ctl set cantilever "
            "real_time_factor "
            f"{suggest:g}' (0 = as fast as possible); next report in {self.period:g} s at the "
            "earliest"
        )


def slowdown_bottleneck(wait_kind: str | None, wait_reason: str) -> str:
    """Which part of the loop limits the speed, from the gate it waited at most (None: none)."""
    if wait_kind == "feedback":
        return f"the thread serving the lock-in, z controller and recorder ({wait_reason})"
    if wait_kind == "consumers":
        return f"a consumer of the stream ({wait_reason})"
    return "the integration (RK4 worker)"
