"""What a Nanonis controller remembers between commands (the scan buffer, the autosave settings,
the spectroscopy's settings, the session folder) and the files it writes there: every finished
frame, and a stopped one marked so, as ``.sxm``; every Z spectroscopy as ``.dat``.

:class:`Session` owns the :class:`~afm_ros.client.nanonis.controller.Controller` (the instrument
thread) and answers requests through :func:`afm_ros.client.nanonis.commands.dispatch`.
"""

from __future__ import annotations

import threading
from datetime import datetime
from pathlib import Path
from typing import Callable

import numpy as np

from afm_ros.client.errors import Interrupted
from afm_ros.client.frames import warm_up
from afm_ros.client.microscope import Microscope
from afm_ros.client.nanonis.commands import dispatch as dispatch_command
from afm_ros.client.nanonis.controller import Controller, Job
from afm_ros.client.nanonis.signals import BY_CHANNEL, SIGNALS, Z_INDEX, image_channels
from afm_ros.core.nanonis_server import DEFAULT_PORT, MAX_CLIENTS, NanonisServer
from afm_ros.formats.folders import check_output_directory
from afm_ros.formats.nanonis_files import SxmChannel, SxmFrame, scan_order, write_sxm

VERSION = "afm_ros Nanonis emulation 1"
HOST_RELEASE = RT_RELEASE = 14718  # the protocol document the commands follow (April 2025)
DEFAULT_SERIES = "Scan"


class Session:
    """One server's state over ``afm``; files go to ``folder`` (created if missing, one level).
    ``mode`` 'am' (tapping) or 'fm'; ``idle``, ``pace``, ``real_time_factor``: the controller's."""

    def __init__(
        self,
        afm: Microscope,
        folder,
        mode: str = "am",
        idle: str = "run",
        pace: bool = False,
        real_time_factor: float = 1.0,
        log: Callable[[str, str], None] | None = None,
    ):
        if mode not in ("am", "fm"):
            raise ValueError(f"mode={mode!r}: 'am' (tapping) or 'fm'")
        self.folder = check_output_directory(folder, create=True, field="session folder")
        self.mode = mode
        self.log = log or (lambda level, text: None)
        self.controller = Controller(
            afm, idle=idle, pace=pace, real_time_factor=real_time_factor, log=self.log
        )
        available = [BY_CHANNEL[c].index for c in image_channels(mode)]
        self.buffer = [Z_INDEX] + [i for i in available if i != Z_INDEX]
        self.continuous = False
        self.autosave = "all"  # all, next, off
        self.series = DEFAULT_SERIES
        self.comment = ""
        self.files: list[str] = []  # every file written, in order
        self.last_sxm = ""
        self._counters = {"sxm": 0, "dat": 0}
        self._frames = threading.Condition()
        self.frames_ended = 0  # frames (whole or stopped) ended so far
        self.folme = {"speed": 1e-6, "custom": 0}  # [m/s]
        self.osci = {"channel": 8, "samples": 5000}
        # Z spectroscopy (ZSpectr.*): channels recorded, points per sweep, backward sweep,
        # autosave, the range [m] and the timing [s] that give the ramp's rate
        self.zspectr = {
            "channels": [6, 4] if mode == "fm" else [4, 5],
            "points": 256,
            "backward": True,
            "sweeps": 1,
            "autosave": True,
            "save_all": False,
            "base_name": "Z-Spectroscopy",
            "offset": 10e-9,
            "distance": 30e-9,
            "z_avg_time": 0.1,
            "initial_settling": 0.1,
            "max_slew_rate": 0.0,
            "settling": 0.0,
            "integration": 0.59e-3,
            "end_settling": 0.0,
            "z_control_time": 0.0,
        }

    # --- the instrument
    # -------------------------------------------------------------------------------
    def start(self) -> "Session":
        # what the first frame's end would load (scipy for the frame checks, xarray's array
        # modules: a second together) is loaded now, not while every connection waits for it
        import scipy.ndimage  # noqa: F401
        import scipy.optimize  # noqa: F401

        warm_up()
        self.controller.start()
        return self

    def close(self) -> None:
        self.controller.close()

    def call(self, fn, timeout: float | None = None):
        """``fn(afm)`` on the instrument thread (see Controller.call)."""
        return self.controller.call(fn) if timeout is None else self.controller.call(fn, timeout)

    def dispatch(self, name: str, body: bytes) -> bytes:
        return dispatch_command(self, name, body)

    # --- files
    # ---------------------------------------------------------------------------------------
    def next_path(self, base: str, suffix: str) -> Path:
        """``<folder>/<base><NNN><suffix>`` with the next free number (Nanonis' autosave
        names)."""
        kind = suffix.lstrip(".")
        while True:
            self._counters[kind] += 1
            path = self.folder / f"{base}{self._counters[kind]:03d}{suffix}"
            if not path.exists():
                return path

    def frame_file(self, ds, stopped: bool) -> str:
        """Write the frame ``ds`` (a Dataset on its whole raster) as .sxm with the buffer's
        channels; returns the path ('' when autosave is off)."""
        if self.autosave == "off":
            return ""
        if self.autosave == "next":
            self.autosave = "off"
        lines_done = int(ds.attrs.get("lines_done", ds.attrs.get("scan_lines", 0)))
        planned = int(ds.attrs["scan_lines"])
        channels = []
        for index in self.buffer:
            s = SIGNALS[index]
            if s.channel not in ds:
                continue
            data = ds[s.channel].values
            channels.append(SxmChannel(index, s.file_name, s.unit, data[0], data[1]))
        rate = float(ds.attrs["scan_line_rate"])
        header = {
            "afm_ros>lines_done": f"{lines_done} of {planned}",
            "afm_ros>stopped": "TRUE" if stopped else "FALSE",
            "afm_ros>start_time_s": f"{float(ds.attrs.get('start_time_s', 0.0)):.9g}",
        }
        path = self.next_path(self.series, ".sxm")
        frame = SxmFrame(
            pixels=int(ds.attrs["scan_pixels_per_line"]),
            lines=planned,
            size=(float(ds.attrs["scan_size_x"]), float(ds.attrs["scan_size_y"])),
            center=(float(ds.attrs["scan_center_x"]), float(ds.attrs["scan_center_y"])),
            angle=float(ds.attrs.get("scan_angle", 0.0)),
            direction=str(ds.attrs["scan_slow_scan_direction"]),
            line_time=0.5 / rate,
            channels=channels,
            acquisition_time=lines_done / rate,
            recorded=datetime.now(),
            comment=(
                f"afm_ros: stopped after {lines_done} of {planned} lines"
                if stopped
                else f"afm_ros: {self.comment}".rstrip(": ")
            ),
            header={"SCAN_FILE": str(path), **header},
        )
        write_sxm(path, frame)
        self.files.append(str(path))
        self.last_sxm = str(path)
        self.log("info", f"frame saved: {path}" + (" (stopped)" if stopped else ""))
        return str(path)

    # --- the scan
    # -------------------------------------------------------------------------------------
    def run_scan(self, afm: Microscope):
        """The scan job: frames until the scan is stopped (continuous) or one frame; each saved
        as it ends, a stopped one too (marked)."""
        ds = None
        while True:
            try:
                ds = afm.scan()
            except Interrupted:
                partial = afm.frame_so_far()
                if partial is not None and int(partial.attrs.get("lines_done", 0)) > 0:
                    self.frame_file(partial, stopped=True)
                self._frame_ended()
                raise
            self.frame_file(afm.frame_so_far() or ds, stopped=False)
            self._frame_ended()
            if not self.continuous:
                return ds

    def _frame_ended(self) -> None:
        with self._frames:
            self.frames_ended += 1
            self._frames.notify_all()

    def wait_frame(self, timeout: float | None) -> bool:
        """Until the frame being scanned ends (or the scan job ends); False on timeout. At once
        if no scan runs."""
        job = self.controller.running("scan")
        if job is None:
            return True
        with self._frames:
            seen = self.frames_ended
            return self._frames.wait_for(
                lambda: self.frames_ended > seen or job.done.is_set(), timeout
            )

    def grab(self, index: int, forward: bool) -> tuple[str, np.ndarray, str]:
        """(name, lines x pixels in scan order, slow direction) of buffer channel ``index`` of the
        frame being scanned or the last one."""
        if index not in self.buffer:
            raise ValueError(
                f"channel {index} is not in the scan buffer {self.buffer} (Scan.BufferSet)"
            )
        s = SIGNALS[index]
        ds = self.call(lambda afm: afm.frame_so_far())
        if ds is None:
            raise ValueError("no frame yet: start a scan first (Scan.Action)")
        if s.channel not in ds:
            raise ValueError(f"{s.name} is not a channel of this frame")
        direction = str(ds.attrs["scan_slow_scan_direction"])
        image = ds[s.channel].values[0 if forward else 1]
        return s.name, scan_order(image, direction, not forward), direction

    def job_error(self, job: Job) -> None:
        """Raise what ended ``job`` unless it ended well or was stopped on request."""
        if job.error is not None and not job.stopped:
            raise job.error


class Served:
    """A Session and the NanonisServer in front of it (:func:`serve`); :meth:`close` stops the
    action running (its results kept: a stopped frame is saved), then the server."""

    def __init__(self, session: Session, server):
        self.session, self.server = session, server

    @property
    def port(self) -> int:
        return self.server.port

    def close(self) -> None:
        try:
            self.session.close()
        finally:
            self.server.close()


def serve(
    afm: Microscope,
    folder,
    mode: str = "am",
    address: str = "127.0.0.1",
    port: int = DEFAULT_PORT,
    idle: str = "run",
    pace: bool = False,
    real_time_factor: float = 1.0,
    max_clients: int = MAX_CLIENTS,
    log: Callable[[str, str], None] | None = None,
) -> Served:
    """Serve ``afm`` over the Nanonis protocol on ``address``:``port`` (0: any free port), files
    in ``folder``; OSError naming the address if it cannot listen (nothing left running)."""
    session = Session(afm, folder, mode, idle, pace, real_time_factor, log).start()
    try:
        server = NanonisServer(
            session.dispatch, address, port, max_clients=max_clients, log=log
        ).start()
    except BaseException:
        session.close()
        raise
    return Served(session, server)
