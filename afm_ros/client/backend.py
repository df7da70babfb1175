"""What a backend of :class:`afm_ros.client.Microscope` provides: the same verbs over ROS
(:class:`afm_ros.client.ros_backend.RosBackend`) and in-process
(:class:`afm_ros.client.local_backend.LocalBackend`). SI units; refusals raise the errors of
:mod:`afm_ros.client.errors`."""

from __future__ import annotations

from typing import Any, Callable, Protocol

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


class Backend(Protocol):
    def close(self) -> None: ...

    def recover(self, verb: str) -> None:
        """After Ctrl-C inside ``verb``: leave the instrument where the next verb works."""

    def wall_per_simulated_second(self) -> float:
        """Wall seconds per simulated second measured so far (nan before any)."""

    def set_values(self, node: str, values: dict) -> None: ...

    def get_values(self, node: str, names: list[str]) -> dict: ...

    def scan_settings(self) -> ScanSettings: ...

    def feedback(self) -> Feedback: ...

    def state(self) -> StageState: ...

    def advance(self, seconds: float) -> None: ...

    def wait_until(self, t: float) -> float:
        """Run to the first chunk boundary at or after the simulated time ``t`` [s]; that time."""

    def tune(self) -> TuneResult: ...

    def approach(self) -> ApproachResult: ...

    def withdraw(self) -> WithdrawResult: ...

    def scan(self, progress: Callable[[int, int], None] | None) -> Any:
        """One frame as an xarray Dataset (afm_ros.client.frames)."""

    def move_tip(self, x: float, y: float) -> None: ...

    def spectroscopy(self, values: dict) -> Any:
        """One curve as an xarray Dataset (afm_ros.client.frames)."""

    def flags(self) -> dict: ...

    def truth(self) -> Truth: ...

    def set_tick(self, tick: Callable[[], None] | None) -> None:
        """Call ``tick()`` between chunks inside every verb (see Microscope.set_tick)."""

    def signals(self) -> Signals: ...

    def frame_so_far(self) -> Any:
        """The running (or last) scan's frame on its whole raster, NaN where not yet scanned;
        None before any scan."""

    def move_motor(self, steps: int) -> None: ...

    def move_z(self, z: float) -> None: ...

    def oscilloscope(self, samples: int) -> Trace: ...
